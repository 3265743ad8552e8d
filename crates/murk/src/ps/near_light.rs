//! Near-light photometric stereo with the source-surface forward-scatter term linearised by
//! `G(T, n·l) ≈ G(T, 1)·n·l` (Eq. 4.55–4.59).

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::ps::capture::PointLight;
use crate::ps::physics::{GTable, Medium};

/// Which image-formation model the shading rows use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShadingModel {
    /// Eq. 4.56: direct light attenuated by `e^{−T_sp}` plus the source-surface forward scatter
    /// `βσ/(2πT_sp)·G(T_sp, 1)`, both times `n·l`.
    ForwardScatter,
    /// The backscatter-only baseline \[15\]: direct light attenuated by `e^{−T_sp}`, no forward
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
    x_mm: &Vector3<f64>,
) -> Vector3<f64> {
    let d = Vector3::from(light.position_mm) - x_mm;
    let dist = d.norm().max(1e-9);
    let t = medium.sigma_per_mm * dist;
    let mut gain = (-t).exp() / (dist * dist);
    if model == ShadingModel::ForwardScatter && t > 0.0 {
        gain += medium.beta_per_mm * medium.sigma_per_mm / (2.0 * std::f64::consts::PI * t)
            * g.eval(t, 1.0);
    }
    d * (light.intensity * gain / dist)
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
            let x = Vector3::from(points_mm[p].map(f64::from));
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
            let (ata, atb) = normal_equations(lights, medium, g, model, &x, lit);
            if count < 3 {
                return;
            }
            let Some(sol) = solve3(&ata, &atb) else {
                return;
            };
            let len = sol.norm();
            if len.is_nan() || len <= 0.0 || !len.is_finite() {
                return;
            }
            let mut n = sol / len;
            let mut albedo = len;
            if refine && model == ShadingModel::ForwardScatter {
                if let Some((rn, ra)) = refine_exact_g(lights, medium, g, &x, lit, n, albedo) {
                    n = rn;
                    albedo = ra;
                }
            }
            *normal = [n.x as f32, n.y as f32, n.z as f32];
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
    x_mm: &Vector3<f64>,
    lit: &[(usize, f64)],
) -> (Matrix3<f64>, Vector3<f64>) {
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for &(i, obs) in lit {
        let row = shading_row(&lights[i], medium, g, model, x_mm);
        ata += row * row.transpose();
        atb += row * obs;
    }
    (ata, atb)
}

/// The exact reflected component of Eq. 4.54 for albedo 1 and unit normal `n` at `x_mm` under
/// `light`: `I0·(e^{−T}/d²·max(n·l, 0) + β/(2π d)·G(T, n·l))`.
pub(crate) fn exact_shading(
    light: &PointLight,
    medium: &Medium,
    g: &GTable,
    x_mm: &Vector3<f64>,
    n: &Vector3<f64>,
) -> f64 {
    let dv = Vector3::from(light.position_mm) - x_mm;
    let d = dv.norm().max(1e-9);
    let c = n.dot(&dv) / d;
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
    x: &Vector3<f64>,
    lit: &[(usize, f64)],
    mut n: Vector3<f64>,
    mut rho: f64,
) -> Option<(Vector3<f64>, f64)> {
    const STEPS: usize = 6;
    let beta = medium.beta_per_mm;
    let sigma = medium.sigma_per_mm;
    for _ in 0..STEPS {
        // Tangent basis of n.
        let a = if n.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let e1 = n.cross(&a).normalize();
        let e2 = n.cross(&e1);
        let mut jtj = Matrix3::zeros();
        let mut jtr = Vector3::zeros();
        for &(i, obs) in lit {
            let light = &lights[i];
            let dv = Vector3::from(light.position_mm) - x;
            let d = dv.norm().max(1e-9);
            let l = dv / d;
            let c = n.dot(&l);
            let t = sigma * d;
            let direct = light.intensity * (-t).exp() / (d * d);
            let fwd = beta * light.intensity / (2.0 * std::f64::consts::PI * d);
            let (gc, dg) = g.eval_with_slope(t, c);
            let shade = direct * c.max(0.0) + fwd * gc;
            let dshade = direct * if c > 0.0 { 1.0 } else { 0.0 } + fwd * dg;
            let r = obs - rho * shade;
            let jl = rho * dshade;
            let j = Vector3::new(jl * l.dot(&e1), jl * l.dot(&e2), shade);
            jtj += j * j.transpose();
            jtr += j * r;
        }
        let step = solve3(&jtj, &jtr)?;
        if !step.iter().all(|v| v.is_finite()) {
            return None;
        }
        // Keep each step small against the linearisation's range.
        let (da, db) = (step[0].clamp(-0.2, 0.2), step[1].clamp(-0.2, 0.2));
        n = (n + e1 * da + e2 * db).normalize();
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

/// Solves a symmetric 3×3 system by Cramer's rule; `None` when it is (nearly) singular
/// relative to its scale. (Cramer's rule rather than a factorisation: the determinant it needs
/// anyway is the singularity test.)
pub(crate) fn solve3(a: &Matrix3<f64>, b: &Vector3<f64>) -> Option<Vector3<f64>> {
    let d = a.determinant();
    let scale = a.diagonal().amax();
    if !d.is_finite() || d.abs() <= 1e-12 * scale * scale * scale {
        return None;
    }
    Some(Vector3::from_fn(|c, _| {
        let mut m = *a;
        m.set_column(c, b);
        m.determinant() / d
    }))
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
        let a = Matrix3::new(4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0);
        let x = Vector3::new(0.3, -1.2, 2.0);
        let b = a * x;
        let got = solve3(&a, &b).unwrap();
        assert!((got - x).amax() < 1e-12);
        let singular = Matrix3::new(1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(solve3(&singular, &b).is_none());
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
