//! Near-light photometric stereo with the source-surface forward-scatter term linearised by
//! `G(T, n·l) ≈ G(T, 1)·n·l` (Eq. 4.55–4.59).

use rayon::prelude::*;

use crate::ps::capture::PointLight;
use crate::ps::physics::{GTable, Medium};

/// Which image-formation model the shading rows use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShadingModel {
    /// Eq. 4.56: direct light attenuated by `e^{−T_sp}` plus the source-surface forward scatter
    /// `βσ/(2πT_sp)·G(T_sp, 1)`, both times `n·l`.
    ForwardScatter,
    /// The backscatter-only baseline [15]: direct light attenuated by `e^{−T_sp}`, no forward
    /// scatter at all.
    DirectOnly,
}

/// Row `i` of `D` (Eq. 4.59) for a surface point `x_mm`: `I0·(e^{−T}/d² + βσ/(2πT)·G(T,1))·l̂`,
/// with `l̂` the unit direction from the point to the light and `T = σ·d`.
pub fn shading_row(
    light: &PointLight,
    medium: &Medium,
    g: &GTable,
    model: ShadingModel,
    x_mm: [f64; 3],
) -> [f64; 3] {
    let d = [
        light.position_mm[0] - x_mm[0],
        light.position_mm[1] - x_mm[1],
        light.position_mm[2] - x_mm[2],
    ];
    let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
    let t = medium.sigma_per_mm * dist;
    let mut gain = (-t).exp() / (dist * dist);
    if model == ShadingModel::ForwardScatter && t > 0.0 {
        gain += medium.beta_per_mm * medium.sigma_per_mm / (2.0 * std::f64::consts::PI * t)
            * g.eval(t, 1.0);
    }
    let s = light.intensity * gain / dist;
    [d[0] * s, d[1] * s, d[2] * s]
}

/// Per-pixel result of the photometric-stereo solve.
#[derive(Clone, Debug)]
pub struct NormalEstimate {
    /// Unit normals towards the camera, row-major; `[0, 0, -1]` outside the mask.
    pub normals: Vec<[f32; 3]>,
    /// Albedo `ρ = ‖ñ‖` (Eq. 4.58); 0 outside the mask and where filled.
    pub albedo: Vec<f32>,
    /// Pixels solved from at least three lit observations (the rest were filled).
    pub solved: Vec<bool>,
}

/// Solves Eq. 4.57–4.58 at every masked pixel.
///
/// `reflected[i]` is the reflected component `L_s` of light `i` (full image, row-major) and
/// `points_mm` the current shape estimate. An observation counts as lit when it exceeds
/// `shadow_ratio` times the pixel's brightest observation (and 0): the reference keeps the
/// positive values, but forward scatter leaves attached-shadow pixels slightly positive while
/// Eq. 4.55 predicts a negative value there, so near-zero observations bias the solve. Pixels
/// with fewer than three lit observations or a singular system are marked unsolved and filled
/// from their neighbours (§4.3.4).
#[allow(clippy::too_many_arguments)]
pub fn solve_normals(
    reflected: &[Vec<f32>],
    lights: &[PointLight],
    medium: &Medium,
    g: &GTable,
    model: ShadingModel,
    points_mm: &[[f32; 3]],
    mask: &[bool],
    width: usize,
    shadow_ratio: f64,
    refine: bool,
) -> NormalEstimate {
    let n = mask.len();
    let mut normals = vec![[0.0f32, 0.0, -1.0]; n];
    let mut albedo = vec![0.0f32; n];
    let mut solved = vec![false; n];
    normals
        .par_iter_mut()
        .zip(albedo.par_iter_mut())
        .zip(solved.par_iter_mut())
        .enumerate()
        .for_each(|(p, ((normal, rho), ok))| {
            if !mask[p] {
                return;
            }
            let x = points_mm[p].map(f64::from);
            let max_obs = reflected
                .iter()
                .map(|img| f64::from(img[p]))
                .fold(0.0f64, f64::max);
            let thresh = (shadow_ratio * max_obs).max(0.0);
            // The lit observations (light index, value); m ≤ 64 (the capture's limit), on the
            // stack so nothing is allocated per pixel.
            let mut lit = [(0usize, 0.0f64); MAX_LIT];
            let mut count = 0;
            for (i, img) in reflected.iter().enumerate().take(MAX_LIT) {
                let obs = f64::from(img[p]);
                if obs.partial_cmp(&thresh) == Some(std::cmp::Ordering::Greater) {
                    lit[count] = (i, obs);
                    count += 1;
                }
            }
            let lit = &lit[..count];
            // Normal equations DᵀD ñ = Dᵀ L, accumulated in f64.
            let (ata, atb) = normal_equations(lights, medium, g, model, x, lit);
            if count < 3 {
                return;
            }
            let Some(sol) = solve3(ata, atb) else {
                return;
            };
            let len = (sol[0] * sol[0] + sol[1] * sol[1] + sol[2] * sol[2]).sqrt();
            if len.is_nan() || len <= 0.0 || !len.is_finite() {
                return;
            }
            let mut n = [sol[0] / len, sol[1] / len, sol[2] / len];
            let mut albedo = len;
            if refine && model == ShadingModel::ForwardScatter {
                if let Some((rn, ra)) = refine_exact_g(lights, medium, g, x, lit, n, albedo) {
                    n = rn;
                    albedo = ra;
                }
            }
            *normal = n.map(|v| v as f32);
            *rho = albedo as f32;
            *ok = true;
        });
    fill_unsolved(&mut normals, &solved, mask, width);
    NormalEstimate {
        normals,
        albedo,
        solved,
    }
}

/// Most lit observations one pixel keeps (the capture allows at most 64 lights).
pub(crate) const MAX_LIT: usize = 64;

/// DᵀD and DᵀL of Eq. 4.57 over the lit observations `lit` (light index, value) at `x_mm`.
pub(crate) fn normal_equations(
    lights: &[PointLight],
    medium: &Medium,
    g: &GTable,
    model: ShadingModel,
    x_mm: [f64; 3],
    lit: &[(usize, f64)],
) -> ([[f64; 3]; 3], [f64; 3]) {
    let mut ata = [[0.0f64; 3]; 3];
    let mut atb = [0.0f64; 3];
    for &(i, obs) in lit {
        let row = shading_row(&lights[i], medium, g, model, x_mm);
        for r in 0..3 {
            for c in 0..3 {
                ata[r][c] += row[r] * row[c];
            }
            atb[r] += row[r] * obs;
        }
    }
    (ata, atb)
}

/// The exact reflected component of Eq. 4.54 for albedo 1 and unit normal `n` at `x_mm` under
/// `light`: `I0·(e^{−T}/d²·max(n·l, 0) + β/(2π d)·G(T, n·l))`.
pub(crate) fn exact_shading(
    light: &PointLight,
    medium: &Medium,
    g: &GTable,
    x_mm: [f64; 3],
    n: [f64; 3],
) -> f64 {
    let dv = [
        light.position_mm[0] - x_mm[0],
        light.position_mm[1] - x_mm[1],
        light.position_mm[2] - x_mm[2],
    ];
    let d = (dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2])
        .sqrt()
        .max(1e-9);
    let c = (n[0] * dv[0] + n[1] * dv[1] + n[2] * dv[2]) / d;
    let t = medium.sigma_per_mm * d;
    let direct = light.intensity * (-t).exp() / (d * d);
    let fwd = medium.beta_per_mm * light.intensity / (2.0 * std::f64::consts::PI * d);
    direct * c.max(0.0) + fwd * g.eval(t, c)
}

/// Gauss–Newton on the exact reflected component of Eq. 4.54 (no linearisation of `G`):
/// `L_i = ρ·I0_i·(e^{−T_i}/d_i²·max(n·l_i, 0) + β/(2π d_i)·G(T_i, n·l_i))` over the lit
/// observations, for the unit normal (two tangent-plane parameters) and ρ, started from the
/// Eq. 4.57 solution. Eq. 4.55's `G(T, c) ≈ G(T, 1)·c` drops the part of the forward scatter that
/// reaches the surface whatever its orientation (`G(T, 0)` is about a quarter of `G(T, 1)` at
/// T = 1), which biases normals by several degrees when forward scatter is comparable to the
/// direct light (β·d_sp ≈ 1); the exact model removes that bias. Returns `None` (keep the
/// linear solution) if a step fails.
pub(crate) fn refine_exact_g(
    lights: &[PointLight],
    medium: &Medium,
    g: &GTable,
    x: [f64; 3],
    lit: &[(usize, f64)],
    mut n: [f64; 3],
    mut rho: f64,
) -> Option<([f64; 3], f64)> {
    const STEPS: usize = 6;
    let beta = medium.beta_per_mm;
    let sigma = medium.sigma_per_mm;
    for _ in 0..STEPS {
        // Tangent basis of n.
        let a = if n[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let e1 = normalize(cross(n, a));
        let e2 = cross(n, e1);
        let mut jtj = [[0.0f64; 3]; 3];
        let mut jtr = [0.0f64; 3];
        for &(i, obs) in lit {
            let light = &lights[i];
            let dv = [
                light.position_mm[0] - x[0],
                light.position_mm[1] - x[1],
                light.position_mm[2] - x[2],
            ];
            let d = (dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2])
                .sqrt()
                .max(1e-9);
            let l = [dv[0] / d, dv[1] / d, dv[2] / d];
            let c = n[0] * l[0] + n[1] * l[1] + n[2] * l[2];
            let t = sigma * d;
            let direct = light.intensity * (-t).exp() / (d * d);
            let fwd = beta * light.intensity / (2.0 * std::f64::consts::PI * d);
            let (gc, dg) = g.eval_with_slope(t, c);
            let shade = direct * c.max(0.0) + fwd * gc;
            let dshade = direct * if c > 0.0 { 1.0 } else { 0.0 } + fwd * dg;
            let r = obs - rho * shade;
            let jl = rho * dshade;
            let j = [
                jl * (l[0] * e1[0] + l[1] * e1[1] + l[2] * e1[2]),
                jl * (l[0] * e2[0] + l[1] * e2[1] + l[2] * e2[2]),
                shade,
            ];
            for r_ in 0..3 {
                for c_ in 0..3 {
                    jtj[r_][c_] += j[r_] * j[c_];
                }
                jtr[r_] += j[r_] * r;
            }
        }
        let step = solve3(jtj, jtr)?;
        if !step.iter().all(|v| v.is_finite()) {
            return None;
        }
        // Keep each step small against the linearisation's range.
        let (da, db) = (step[0].clamp(-0.2, 0.2), step[1].clamp(-0.2, 0.2));
        n = normalize([
            n[0] + da * e1[0] + db * e2[0],
            n[1] + da * e1[1] + db * e2[1],
            n[2] + da * e1[2] + db * e2[2],
        ]);
        rho += step[2];
        if rho.is_nan() || rho <= 0.0 {
            return None;
        }
        if da.abs() + db.abs() < 1e-7 {
            break;
        }
    }
    Some((n, rho))
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(v: [f64; 3]) -> [f64; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / l, v[1] / l, v[2] / l]
}

/// Solves a symmetric 3×3 system by Cramer's rule; `None` when it is (nearly) singular
/// relative to its scale.
pub(crate) fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&a);
    let scale = a[0][0].abs().max(a[1][1].abs()).max(a[2][2].abs());
    if !d.is_finite() || d.abs() <= 1e-12 * scale * scale * scale {
        return None;
    }
    let mut x = [0.0; 3];
    for (c, xc) in x.iter_mut().enumerate() {
        let mut m = a;
        for r in 0..3 {
            m[r][c] = b[r];
        }
        *xc = det(&m) / d;
    }
    Some(x)
}

/// Fills unsolved masked pixels with the normalised mean of their solved (or already filled)
/// 8-neighbours, sweeping outwards until every masked pixel has a normal. A masked component
/// with no solved pixel at all keeps the camera-facing default.
pub fn fill_unsolved(normals: &mut [[f32; 3]], solved: &[bool], mask: &[bool], width: usize) {
    let n = mask.len();
    let height = n / width.max(1);
    let mut known: Vec<bool> = (0..n).map(|p| !mask[p] || solved[p]).collect();
    let mut frontier: Vec<usize> = (0..n).filter(|&p| !known[p]).collect();
    while !frontier.is_empty() {
        let mut fills = Vec::new();
        for &p in &frontier {
            let (x, y) = ((p % width) as isize, (p / width) as isize);
            let mut acc = [0.0f32; 3];
            let mut cnt = 0;
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (nx, ny) = (x + dx, y + dy);
                    if (dx, dy) == (0, 0)
                        || nx < 0
                        || ny < 0
                        || nx >= width as isize
                        || ny >= height as isize
                    {
                        continue;
                    }
                    let q = ny as usize * width + nx as usize;
                    if mask[q] && known[q] {
                        for k in 0..3 {
                            acc[k] += normals[q][k];
                        }
                        cnt += 1;
                    }
                }
            }
            if cnt > 0 {
                let len = (acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2]).sqrt();
                if len > 0.0 {
                    fills.push((p, [acc[0] / len, acc[1] / len, acc[2] / len]));
                }
            }
        }
        if fills.is_empty() {
            break;
        }
        for (p, v) in fills {
            normals[p] = v;
            known[p] = true;
        }
        frontier.retain(|&p| !known[p]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve3_matches_known_solution_and_rejects_singular() {
        let a = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let x = [0.3, -1.2, 2.0];
        let b = [0, 1, 2].map(|r| (0..3).map(|c| a[r][c] * x[c]).sum::<f64>());
        let got = solve3(a, b).unwrap();
        for k in 0..3 {
            assert!((got[k] - x[k]).abs() < 1e-12);
        }
        assert!(solve3([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]], b).is_none());
    }

    #[test]
    fn fill_spreads_from_solved_neighbours() {
        let w = 4;
        let mask = vec![true; 8];
        let mut solved = vec![false; 8];
        solved[0] = true;
        let mut normals = vec![[0.0f32, 0.0, -1.0]; 8];
        normals[0] = [0.6, 0.0, -0.8];
        fill_unsolved(&mut normals, &solved, &mask, w);
        for n in &normals {
            assert!((n[0] - 0.6).abs() < 1e-6 && (n[2] + 0.8).abs() < 1e-6);
        }
    }
}
