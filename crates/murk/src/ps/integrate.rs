//! Perspective normal integration (reference Ch. 4.1.2, Eq. 4.8–4.27, with the normal-similarity
//! weights of §4.3.4, Eq. 4.60–4.62).
//!
//! Under perspective projection the depth map is recovered through its logarithm g = log Z
//! (Eq. 4.15): the normal fixes the direction of the surface tangent plane but not its distance,
//! so it determines ∂g/∂u and ∂g/∂v (Eq. 4.16) and g only up to an additive constant per
//! connected piece of the mask, i.e. Z only up to a scale per piece.
//!
//! # Log-depth gradients
//!
//! With ū = u − c_x, v̄ = v − c_y and `Intrinsics` `u = f_x·x/z + γ·y/z + c_x`,
//! `v = f_y·y/z + c_y`, the surface point seen at pixel (u, v) is P = Z·m with
//! m = (a, b, 1), b = v̄/f_y, a = (ū − γ·b)/f_x. Its tangents are
//! P_u = Z_u·m + Z·(1/f_x, 0, 0) and P_v = Z_v·m + Z·(−γ/(f_x f_y), 1/f_y, 0); the normal is
//! orthogonal to both, which gives
//!
//! g̃_u = Z_u/Z = −n_x / (f_x·d),  g̃_v = Z_v/Z = (γ·n_x/f_x − n_y) / (f_y·d),  d = n·m.
//!
//! Multiplying numerator and denominator by f_x f_y/n_z and writing r₁ = n_x/n_z, r₂ = n_y/n_z
//! (Eq. 4.20–4.21) turns these into exactly the printed Eq. 4.24–4.25; the intermediate
//! Eq. 4.13/4.14/4.22/4.23 as printed are not consistent with them (f_u vs f_x, missing skew
//! terms), which is why the tests check the result against finite differences of log Z of
//! analytic surfaces instead of against the print.
//!
//! # Integration
//!
//! [`integrate_normals`] minimises, over the mask, the discrete weighted form of Eq. 4.17
//!
//! E(g) = Σ_edges w_pq · (g_q − g_p − t_pq)²,
//!
//! where the sum runs over 4-neighbour pairs (p, q) both inside the mask, t_pq is the average of
//! the two pixels' g̃_u (horizontal edges) or g̃_v (vertical edges) and
//! w_pq = exp(−(1 − n_p·n_q)/s) is the normal-similarity weight of Eq. 4.61–4.62. Its normal
//! equations are, per pixel, Σ_q w_pq (g_q − g_p) = Σ_q w_pq (±t_pq): a weighted Laplacian equal to
//! a weighted divergence, i.e. the weighted Poisson equation that Eq. 4.18 discretised with the
//! one-sided weighted derivatives of Eq. 4.60 approximates. The correspondence is not literal:
//! Eq. 4.60 weights only the divergence of (g̃_u, g̃_v) and leaves the Laplacian unweighted and
//! uses normalised weights w₁/(w₁+w₂), whereas here the same weights enter both sides because
//! they come from one energy. That keeps the system symmetric positive semi-definite (so a sparse
//! Cholesky applies) and lets an edge across a crease (dissimilar normals) decouple both sides at
//! once; with all weights 1 it reduces to Eq. 4.18 with a central instead of the backward
//! difference of Eq. 4.26–4.27. Mask-internal edges only means the natural (Neumann) boundary
//! condition at the silhouette.

use faer::sparse::{SparseColMat, Triplet};
use faer::Side;

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::linalg::SparseLlt;

/// Smallest allowed cosine between a normal and the reversed viewing ray when forming the
/// log-depth gradients. At the silhouette n·m → 0 and Eq. 4.24–4.25 divide by zero; normals
/// that are more grazing than ≈ 89.4° (or face away from the camera) are treated as exactly that
/// grazing, which bounds |g̃| by ≈ 100/f per pixel instead of producing ±∞ or NaN.
const MIN_COS_VIEW: f64 = 0.01;

/// Floor of the edge weights. For s = 0.02 it only clamps edges whose normals differ by more
/// than ≈ 44°, i.e. creases; it keeps every 4-connected mask component one well-conditioned
/// system (an exp(−100) weight would make parts of a component numerically disconnected, their
/// relative offset undetermined and the Cholesky factor close to singular).
const MIN_EDGE_WEIGHT: f64 = 1e-6;

/// Allowed deviation of |n| from 1 for normals inside the mask (they arrive as f32).
const UNIT_TOLERANCE: f64 = 1e-3;

/// Parameters of [`integrate_normals`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IntegrationParams {
    /// s of Eq. 4.61–4.62: edges between neighbours whose normals differ by 1 − n_p·n_q ≫ s are
    /// down-weighted as exp(−(1 − n_p·n_q)/s). The reference uses 0.02.
    pub smoothness_s: f64,
}

impl Default for IntegrationParams {
    fn default() -> Self {
        Self { smoothness_s: 0.02 }
    }
}

/// Per-pixel gradients (g̃_u, g̃_v) of g = log Z (Eq. 4.15–4.16, 4.24–4.25, skew included) from
/// unit normals pointing towards the camera, derived in the module documentation.
///
/// Pixels are row-major, `width` per row, centres at integer coordinates. The result is NaN-free:
/// non-finite or zero normals give (0, 0), and grazing or back-facing normals are clamped to a
/// cosine of 0.01 with the viewing ray (see the module constant `MIN_COS_VIEW`) so the
/// denominator n·m never vanishes.
///
/// # Panics
/// If `normals.len() != width * height`.
pub fn log_depth_gradients(
    intr: &Intrinsics,
    width: usize,
    height: usize,
    normals: &[[f32; 3]],
) -> (Vec<f64>, Vec<f64>) {
    assert_eq!(
        normals.len(),
        width * height,
        "normals must hold width*height entries"
    );
    let mut gu = vec![0.0; normals.len()];
    let mut gv = vec![0.0; normals.len()];
    for y in 0..height {
        let b = (y as f64 - intr.cy) / intr.fy;
        for x in 0..width {
            let i = y * width + x;
            let [nx, ny, nz] = normals[i].map(f64::from);
            let n_norm = (nx * nx + ny * ny + nz * nz).sqrt();
            if !n_norm.is_finite() || n_norm == 0.0 {
                continue;
            }
            let a = (x as f64 - intr.cx - intr.skew * b) / intr.fx;
            let m_norm = (a * a + b * b + 1.0).sqrt();
            let d = (nx * a + ny * b + nz).min(-MIN_COS_VIEW * n_norm * m_norm);
            gu[i] = -nx / (intr.fx * d);
            gv[i] = (intr.skew * nx / intr.fx - ny) / (intr.fy * d);
        }
    }
    (gu, gv)
}

/// 4-connected component label per pixel (`u32::MAX` outside the mask) and the component count.
fn components(width: usize, height: usize, mask: &[bool]) -> (Vec<u32>, usize) {
    let mut label = vec![u32::MAX; mask.len()];
    let mut count = 0usize;
    let mut stack = Vec::new();
    for start in 0..mask.len() {
        if !mask[start] || label[start] != u32::MAX {
            continue;
        }
        let c = count as u32;
        count += 1;
        label[start] = c;
        stack.push(start);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % width, i / width);
            let mut visit = |j: usize| {
                if mask[j] && label[j] == u32::MAX {
                    label[j] = c;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < width {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - width);
            }
            if y + 1 < height {
                visit(i + width);
            }
        }
    }
    (label, count)
}

fn dot3(a: [f32; 3], b: [f32; 3]) -> f64 {
    a.iter()
        .zip(&b)
        .map(|(&p, &q)| f64::from(p) * f64::from(q))
        .sum()
}

/// Integrates unit normals (towards the camera) into g = log Z over `mask` by the weighted least
/// squares of the module documentation (Eq. 4.17–4.18 with the weights of Eq. 4.60–4.62),
/// solved with a sparse Cholesky.
///
/// Returns g per pixel: NaN outside the mask, and on each 4-connected component of the mask
/// shifted to mean 0 (the gauge the normals cannot fix). Errors name `normals` or `mask` for a
/// length other than `width * height`, `normals` for a non-finite or non-unit normal inside the
/// mask, `mask` for an empty mask, `smoothness_s` unless it is finite and > 0, and the
/// intrinsics field that [`Intrinsics::validate`] rejects.
pub fn integrate_normals(
    intr: &Intrinsics,
    width: usize,
    height: usize,
    normals: &[[f32; 3]],
    mask: &[bool],
    params: &IntegrationParams,
) -> Result<Vec<f64>> {
    intr.validate()?;
    let npix = width
        .checked_mul(height)
        .ok_or_else(|| MurkError::invalid("width", "width*height overflows"))?;
    if normals.len() != npix {
        return Err(MurkError::invalid(
            "normals",
            format!(
                "expected {npix} entries (width*height), got {}",
                normals.len()
            ),
        ));
    }
    if mask.len() != npix {
        return Err(MurkError::invalid(
            "mask",
            format!("expected {npix} entries (width*height), got {}", mask.len()),
        ));
    }
    let s = params.smoothness_s;
    if !s.is_finite() || s <= 0.0 {
        return Err(MurkError::invalid(
            "smoothness_s",
            format!("must be finite and > 0, got {s}"),
        ));
    }
    for (i, n) in normals.iter().enumerate().filter(|&(i, _)| mask[i]) {
        let len = dot3(*n, *n).sqrt();
        if !len.is_finite() || (len - 1.0).abs() > UNIT_TOLERANCE {
            return Err(MurkError::invalid(
                "normals",
                format!(
                    "normal at pixel ({}, {}) inside the mask must be finite and unit length, got {n:?}",
                    i % width,
                    i / width
                ),
            ));
        }
    }
    let mut index = vec![usize::MAX; npix];
    let mut pixels = Vec::new();
    for (i, _) in mask.iter().enumerate().filter(|&(_, &m)| m) {
        index[i] = pixels.len();
        pixels.push(i);
    }
    let nu = pixels.len();
    if nu == 0 {
        return Err(MurkError::invalid("mask", "selects no pixel"));
    }
    let (label, ncomp) = components(width, height, mask);
    let (gu, gv) = log_depth_gradients(intr, width, height, normals);

    // Normal equations Aᵀ W A g = Aᵀ W t of E(g); lower triangle only, one off-diagonal entry per
    // edge (each pair appears once), diagonal accumulated separately.
    let mut diag = vec![0.0; nu];
    let mut rhs = vec![0.0; nu];
    let mut triplets: Vec<Triplet<usize, usize, f64>> = Vec::with_capacity(3 * nu);
    let mut add_edge = |p: usize, q: usize, target: f64, diag: &mut [f64], rhs: &mut [f64]| {
        let cos = dot3(normals[p], normals[q]).min(1.0);
        let w = (-(1.0 - cos) / s).exp().max(MIN_EDGE_WEIGHT);
        let (ip, iq) = (index[p], index[q]);
        diag[ip] += w;
        diag[iq] += w;
        rhs[ip] -= w * target;
        rhs[iq] += w * target;
        triplets.push(Triplet::new(ip.max(iq), ip.min(iq), -w));
    };
    for &p in &pixels {
        let (x, y) = (p % width, p / width);
        if x + 1 < width && mask[p + 1] {
            add_edge(p, p + 1, 0.5 * (gu[p] + gu[p + 1]), &mut diag, &mut rhs);
        }
        if y + 1 < height && mask[p + width] {
            let q = p + width;
            add_edge(p, q, 0.5 * (gv[p] + gv[q]), &mut diag, &mut rhs);
        }
    }
    // Gauge: a unit spring pulling the first pixel of each component to 0. E is invariant to a
    // constant shift per component, so the minimiser of E + g_pin² is an exact minimiser of E
    // (with g_pin = 0) and the system becomes positive definite without biasing the shape.
    let mut pinned = vec![false; ncomp];
    for &p in &pixels {
        let c = label[p] as usize;
        if !pinned[c] {
            pinned[c] = true;
            diag[index[p]] += 1.0;
        }
    }
    triplets.extend(diag.iter().enumerate().map(|(i, &d)| Triplet::new(i, i, d)));

    let mat = SparseColMat::<usize, f64>::try_new_from_triplets(nu, nu, &triplets)
        .map_err(|e| MurkError::Numerical(format!("integration matrix assembly failed: {e:?}")))?;
    let mut llt = SparseLlt::analyse(mat.symbolic(), Side::Lower).map_err(|e| {
        MurkError::Numerical(format!("integration symbolic factorisation failed: {e:?}"))
    })?;
    llt.factorize(mat.as_ref(), Side::Lower)
        .map_err(|e| MurkError::Numerical(format!("integration Cholesky failed: {e:?}")))?;
    llt.solve_in_place(&mut rhs);
    if rhs.iter().any(|v| !v.is_finite()) {
        return Err(MurkError::Numerical(
            "integration produced a non-finite solution".into(),
        ));
    }

    let mut sum = vec![0.0; ncomp];
    let mut cnt = vec![0usize; ncomp];
    for (&p, &g) in pixels.iter().zip(&rhs) {
        sum[label[p] as usize] += g;
        cnt[label[p] as usize] += 1;
    }
    let mut out = vec![f64::NAN; npix];
    for (&p, &g) in pixels.iter().zip(&rhs) {
        let c = label[p] as usize;
        out[p] = g - sum[c] / cnt[c] as f64;
    }
    Ok(out)
}

/// Depth Z = c·exp(g) in millimetres on the mask (NaN elsewhere), with the single scale c chosen
/// so that the mean of Z over the mask equals `mean_depth_mm`.
///
/// The scale is one for the whole mask, not one per 4-connected component: without the image
/// width the components cannot be told apart here. Since [`integrate_normals`] centres g on each
/// component, every component then has the same geometric-mean depth; callers that know the
/// components' depths separately rescale them themselves. Masked pixels with a non-finite g are
/// NaN in the output and ignored in the mean; if no masked pixel has a finite g, all are NaN.
///
/// # Panics
/// If `g.len() != mask.len()`.
pub fn depth_from_log(g: &[f64], mask: &[bool], mean_depth_mm: f64) -> Vec<f32> {
    assert_eq!(g.len(), mask.len(), "g and mask must have the same length");
    let (sum, cnt) = g
        .iter()
        .zip(mask)
        .filter(|&(v, &m)| m && v.is_finite())
        .fold((0.0, 0usize), |(s, c), (v, _)| (s + v.exp(), c + 1));
    let scale = if cnt > 0 {
        mean_depth_mm * cnt as f64 / sum
    } else {
        f64::NAN
    };
    g.iter()
        .zip(mask)
        .map(|(&v, &m)| {
            if m && v.is_finite() {
                (scale * v.exp()) as f32
            } else {
                f32::NAN
            }
        })
        .collect()
}

/// Unit normals (towards the camera, n_z < 0 for visible surfaces) of the depth map `depth_mm`
/// on `mask`, NaN outside it.
///
/// Each masked pixel is back-projected to P = Z·m (see the module documentation); the tangents
/// along u and v are central differences of P where both neighbours are masked with finite
/// depth, one-sided differences where only one is (mask borders), and the normal is their cross
/// product. A pixel lacking any valid neighbour along u or along v has no tangent plane; it gets
/// the normal facing the camera along its own viewing ray (−ray), the least committal guess and
/// the one [`log_depth_gradients`] maps to zero gradient.
///
/// # Panics
/// If `depth_mm` or `mask` does not hold `width * height` entries.
pub fn normals_from_depth(
    intr: &Intrinsics,
    width: usize,
    height: usize,
    depth_mm: &[f32],
    mask: &[bool],
) -> Vec<[f32; 3]> {
    let npix = width * height;
    assert_eq!(
        depth_mm.len(),
        npix,
        "depth_mm must hold width*height entries"
    );
    assert_eq!(mask.len(), npix, "mask must hold width*height entries");
    let valid = |i: usize| mask[i] && depth_mm[i].is_finite() && depth_mm[i] > 0.0;
    let point = |i: usize| -> [f64; 3] {
        let (x, y) = ((i % width) as f64, (i / width) as f64);
        let b = (y - intr.cy) / intr.fy;
        let a = (x - intr.cx - intr.skew * b) / intr.fx;
        let z = f64::from(depth_mm[i]);
        [a * z, b * z, z]
    };
    // Tangent from the valid neighbours `lo` (before) and `hi` (after) of pixel i.
    let tangent = |i: usize, lo: Option<usize>, hi: Option<usize>| -> Option<[f64; 3]> {
        let lo = lo.filter(|&j| valid(j));
        let hi = hi.filter(|&j| valid(j));
        let (a, b) = match (lo, hi) {
            (Some(l), Some(h)) => (point(l), point(h)),
            (Some(l), None) => (point(l), point(i)),
            (None, Some(h)) => (point(i), point(h)),
            (None, None) => return None,
        };
        Some([b[0] - a[0], b[1] - a[1], b[2] - a[2]])
    };
    let mut out = vec![[f32::NAN; 3]; npix];
    for (i, o) in out.iter_mut().enumerate() {
        if !valid(i) {
            continue;
        }
        let (x, y) = (i % width, i / width);
        let tu = tangent(i, (x > 0).then(|| i - 1), (x + 1 < width).then(|| i + 1));
        let tv = tangent(
            i,
            (y > 0).then(|| i - width),
            (y + 1 < height).then(|| i + width),
        );
        let n = match (tu, tv) {
            (Some(a), Some(b)) => {
                // (+x right, +y down, +z forward): P_u × P_v points away from the camera.
                let c = [
                    a[2] * b[1] - a[1] * b[2],
                    a[0] * b[2] - a[2] * b[0],
                    a[1] * b[0] - a[0] * b[1],
                ];
                let len = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
                (len > 0.0 && len.is_finite()).then(|| c.map(|v| v / len))
            }
            _ => None,
        };
        let n = n.unwrap_or_else(|| {
            let r = intr.ray(x as f64, y as f64);
            [-r[0], -r[1], -r[2]]
        });
        *o = n.map(|v| v as f32);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Surface given as a graph z = h(x, y) in the camera frame, with its gradient.
    trait Surface {
        /// (h, h_x, h_y) at (x, y).
        fn h(&self, x: f64, y: f64) -> (f64, f64, f64);

        /// Depth along the ray m = (a, b, 1): solves z = h(z·a, z·b) by Newton from 300 mm.
        fn depth(&self, a: f64, b: f64) -> f64 {
            let mut z = 300.0;
            for _ in 0..50 {
                let (h, hx, hy) = self.h(z * a, z * b);
                let step = (z - h) / (1.0 - hx * a - hy * b);
                z -= step;
                if step.abs() < 1e-13 * z {
                    break;
                }
            }
            z
        }

        /// Unit normal towards the camera: ∝ (h_x, h_y, −1).
        fn normal(&self, a: f64, b: f64) -> [f64; 3] {
            let z = self.depth(a, b);
            let (_, hx, hy) = self.h(z * a, z * b);
            let l = (hx * hx + hy * hy + 1.0).sqrt();
            [hx / l, hy / l, -1.0 / l]
        }
    }

    struct Plane;
    impl Surface for Plane {
        fn h(&self, x: f64, y: f64) -> (f64, f64, f64) {
            (280.0 + 0.4 * x - 0.25 * y, 0.4, -0.25)
        }
    }

    /// Smooth, asymmetric bump on a slanted background.
    struct Bump;
    impl Surface for Bump {
        fn h(&self, x: f64, y: f64) -> (f64, f64, f64) {
            let (sx, sy) = (30.0, 20.0);
            let (dx, dy) = (x - 8.0, y + 5.0);
            let e = (-(dx * dx / (2.0 * sx * sx) + dy * dy / (2.0 * sy * sy))).exp();
            let h = 300.0 - 25.0 * e + 0.15 * x + 0.001 * x * y - 0.0005 * y * y;
            let hx = 25.0 * e * dx / (sx * sx) + 0.15 + 0.001 * y;
            let hy = 25.0 * e * dy / (sy * sy) + 0.001 * x - 0.001 * y;
            (h, hx, hy)
        }
    }

    /// Visible half of a sphere (closed form instead of Newton).
    struct Sphere {
        c: [f64; 3],
        r: f64,
    }
    impl Sphere {
        /// Depth along m = (a, b, 1), or None when the ray misses.
        fn hit(&self, a: f64, b: f64) -> Option<f64> {
            let m = [a, b, 1.0];
            let mm = a * a + b * b + 1.0;
            let mc: f64 = m.iter().zip(&self.c).map(|(p, q)| p * q).sum();
            let cc: f64 = self.c.iter().map(|v| v * v).sum();
            let disc = mc * mc - mm * (cc - self.r * self.r);
            (disc >= 0.0).then(|| (mc - disc.sqrt()) / mm)
        }
    }
    impl Surface for Sphere {
        fn h(&self, _: f64, _: f64) -> (f64, f64, f64) {
            unreachable!("sphere overrides depth and normal")
        }
        fn depth(&self, a: f64, b: f64) -> f64 {
            self.hit(a, b).unwrap_or(f64::NAN)
        }
        fn normal(&self, a: f64, b: f64) -> [f64; 3] {
            let z = self.depth(a, b);
            let p = [a * z, b * z, z];
            [0, 1, 2].map(|k| (p[k] - self.c[k]) / self.r)
        }
    }

    fn ab(k: &Intrinsics, u: f64, v: f64) -> (f64, f64) {
        let b = (v - k.cy) / k.fy;
        ((u - k.cx - k.skew * b) / k.fx, b)
    }

    fn sample<S: Surface>(s: &S, k: &Intrinsics, w: usize, h: usize) -> (Vec<f64>, Vec<[f32; 3]>) {
        let mut z = Vec::with_capacity(w * h);
        let mut n = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (a, b) = ab(k, x as f64, y as f64);
                z.push(s.depth(a, b));
                n.push(s.normal(a, b).map(|v| v as f32));
            }
        }
        (z, n)
    }

    fn cameras() -> [Intrinsics; 2] {
        [
            Intrinsics::new(300.0, 310.0, 58.3, 70.9),
            Intrinsics {
                fx: 290.0,
                fy: 305.0,
                cx: 70.2,
                cy: 55.6,
                skew: 12.0,
            },
        ]
    }

    fn check_gradients<S: Surface>(s: &S, k: &Intrinsics, mask: impl Fn(f64) -> bool) {
        let (w, h) = (128, 128);
        let (_, n) = sample(s, k, w, h);
        let (gu, gv) = log_depth_gradients(k, w, h, &n);
        let logz = |u: f64, v: f64| {
            let (a, b) = ab(k, u, v);
            s.depth(a, b).ln()
        };
        let eps = 1e-3;
        let mut checked = 0;
        for y in (2..h - 2).step_by(3) {
            for x in (2..w - 2).step_by(3) {
                let (u, v) = (x as f64, y as f64);
                if !mask(logz(u, v)) {
                    continue;
                }
                let fu = (logz(u + eps, v) - logz(u - eps, v)) / (2.0 * eps);
                let fv = (logz(u, v + eps) - logz(u, v - eps)) / (2.0 * eps);
                let i = y * w + x;
                // f32 normals limit the agreement to ≈ 1e-7 relative.
                let tol = 1e-5 * (fu.abs() + fv.abs()) + 1e-9;
                assert!(
                    (gu[i] - fu).abs() < tol && (gv[i] - fv).abs() < tol,
                    "({x},{y}) skew {}: g̃ ({}, {}) vs finite diff ({fu}, {fv})",
                    k.skew,
                    gu[i],
                    gv[i]
                );
                checked += 1;
            }
        }
        assert!(checked > 100, "only {checked} pixels checked");
    }

    #[test]
    fn gradients_match_finite_differences_of_log_depth() {
        for k in cameras() {
            check_gradients(&Plane, &k, |_| true);
            check_gradients(&Bump, &k, |_| true);
            let sphere = Sphere {
                c: [5.0, -3.0, 300.0],
                r: 40.0,
            };
            // Away from the silhouette, where the gradient diverges.
            check_gradients(&sphere, &k, |lz| lz.is_finite() && lz < (292.0f64).ln());
        }
    }

    #[test]
    fn gradients_are_finite_for_grazing_back_facing_and_bad_normals() {
        let k = cameras()[1];
        let normals = [
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            [f32::NAN, 0.0, -1.0],
            [0.0, 0.0, 0.0],
        ];
        let (gu, gv) = log_depth_gradients(&k, 2, 2, &normals);
        assert!(gu.iter().chain(&gv).all(|v| v.is_finite()));
        assert_eq!((gu[2], gv[2], gu[3], gv[3]), (0.0, 0.0, 0.0, 0.0));
    }

    /// Max relative depth error after the least-squares scale alignment of `rec` to `truth`.
    fn aligned_error(rec: &[f32], truth: &[f64], mask: &[bool]) -> f64 {
        let (mut num, mut den) = (0.0, 0.0);
        for i in (0..mask.len()).filter(|&i| mask[i]) {
            let r = f64::from(rec[i]);
            num += r * truth[i];
            den += r * r;
        }
        let s = num / den;
        (0..mask.len())
            .filter(|&i| mask[i])
            .map(|i| (s * f64::from(rec[i]) - truth[i]).abs() / truth[i])
            .fold(0.0, f64::max)
    }

    /// Pixels whose sphere normal is within acos(min_cos) of the reversed viewing ray.
    fn cap_mask(s: &Sphere, k: &Intrinsics, w: usize, h: usize, min_cos: f64) -> Vec<bool> {
        (0..w * h)
            .map(|i| {
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                let (a, b) = ab(k, u, v);
                if s.hit(a, b).is_none() {
                    return false;
                }
                let n = s.normal(a, b);
                let r = k.ray(u, v);
                -(n[0] * r[0] + n[1] * r[1] + n[2] * r[2]) >= min_cos
            })
            .collect()
    }

    #[test]
    fn sphere_cap_is_recovered_up_to_scale() {
        let (w, h) = (128, 128);
        let k = Intrinsics::new(300.0, 300.0, 63.5, 63.5);
        let s = Sphere {
            c: [0.0, 0.0, 300.0],
            r: 40.0,
        };
        let mask = cap_mask(&s, &k, w, h, 0.3);
        let (z, n) = sample(&s, &k, w, h);
        let g = integrate_normals(&k, w, h, &n, &mask, &IntegrationParams::default()).unwrap();
        let rec = depth_from_log(&g, &mask, 280.0);
        let e = aligned_error(&rec, &z, &mask);
        eprintln!(
            "sphere cap: {} px, max rel error {e:.2e}",
            mask.iter().filter(|&&m| m).count()
        );
        assert!(e < 0.01, "max relative error {e}");
    }

    #[test]
    fn asymmetric_surface_is_recovered_up_to_scale() {
        let (w, h) = (128, 128);
        for k in cameras() {
            let (z, n) = sample(&Bump, &k, w, h);
            let mask = vec![true; w * h];
            let g = integrate_normals(&k, w, h, &n, &mask, &IntegrationParams::default()).unwrap();
            let rec = depth_from_log(&g, &mask, 300.0);
            let e = aligned_error(&rec, &z, &mask);
            eprintln!("bump, skew {}: max rel error {e:.2e}", k.skew);
            assert!(e < 0.01, "skew {}: max relative error {e}", k.skew);
        }
    }

    #[test]
    fn two_components_are_gauge_fixed_separately() {
        let (w, h) = (96, 64);
        let k = Intrinsics::new(250.0, 250.0, 50.0, 30.0);
        let left = Sphere {
            c: [-45.0, 0.0, 300.0],
            r: 30.0,
        };
        let right = Sphere {
            c: [45.0, 5.0, 250.0],
            r: 25.0,
        };
        let (zl, nl) = sample(&left, &k, w, h);
        let (zr, nr) = sample(&right, &k, w, h);
        let ml = cap_mask(&left, &k, w, h, 0.3);
        let mr = cap_mask(&right, &k, w, h, 0.3);
        assert!(ml.iter().zip(&mr).all(|(a, b)| !(a & b)));
        let mask: Vec<bool> = ml.iter().zip(&mr).map(|(a, b)| a | b).collect();
        let n: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                if mr[i] {
                    nr[i]
                } else if ml[i] {
                    nl[i]
                } else {
                    [f32::NAN; 3]
                }
            })
            .collect();
        let g = integrate_normals(&k, w, h, &n, &mask, &IntegrationParams::default()).unwrap();
        assert!(g.iter().zip(&mask).all(|(v, &m)| v.is_finite() == m));
        for (m, z) in [(&ml, &zl), (&mr, &zr)] {
            let cnt = m.iter().filter(|&&v| v).count();
            assert!(cnt > 100);
            let mean: f64 = (0..w * h).filter(|&i| m[i]).map(|i| g[i]).sum::<f64>() / cnt as f64;
            assert!(mean.abs() < 1e-12, "component mean {mean}");
            let e = aligned_error(&depth_from_log(&g, m, 1.0), z, m);
            assert!(e < 0.01, "component error {e}");
        }
    }

    #[test]
    fn depth_from_log_hits_the_mean_depth() {
        let g = [0.1, -0.2, f64::NAN, 0.3];
        let mask = [true, true, false, true];
        let z = depth_from_log(&g, &mask, 500.0);
        let mean = (z[0] + z[1] + z[3]) / 3.0;
        assert!((mean - 500.0).abs() < 1e-3);
        assert!(z[2].is_nan());
        assert!(((z[3] / z[1]) as f64 - 0.5f64.exp()).abs() < 1e-5);
    }

    #[test]
    fn normals_from_sphere_depth_match_analytic_normals() {
        let (w, h) = (128, 128);
        let k = cameras()[1];
        let s = Sphere {
            c: [5.0, -3.0, 300.0],
            r: 40.0,
        };
        let (z, n_true) = sample(&s, &k, w, h);
        let mask: Vec<bool> = z.iter().map(|v| v.is_finite()).collect();
        let depth: Vec<f32> = z.iter().map(|&v| v as f32).collect();
        let n = normals_from_depth(&k, w, h, &depth, &mask);
        let inner = cap_mask(&s, &k, w, h, 0.3);
        let (mut sum, mut cnt, mut worst) = (0.0, 0, 0.0f64);
        for i in 0..w * h {
            if !mask[i] {
                assert!(n[i][0].is_nan());
                continue;
            }
            let len = dot3(n[i], n[i]).sqrt();
            assert!((len - 1.0).abs() < 1e-5 && n[i][2] < 0.0);
            if inner[i] {
                let ang = dot3(n[i], n_true[i]).clamp(-1.0, 1.0).acos().to_degrees();
                sum += ang;
                cnt += 1;
                worst = worst.max(ang);
            }
        }
        let mean = sum / cnt as f64;
        eprintln!("normals_from_depth: mean {mean:.3}°, max {worst:.3}° over {cnt} px");
        assert!(mean < 1.0, "mean angular error {mean}°");
    }

    #[test]
    fn isolated_pixel_faces_the_camera() {
        let k = cameras()[1];
        let mut mask = vec![false; 9];
        mask[4] = true;
        let n = normals_from_depth(&k, 3, 3, &[300.0; 9], &mask);
        let r = k.ray(1.0, 1.0);
        for c in 0..3 {
            assert!((f64::from(n[4][c]) + r[c]).abs() < 1e-6);
        }
    }

    #[test]
    fn bad_inputs_name_their_field() {
        let k = cameras()[0];
        let p = IntegrationParams::default();
        let n = vec![[0.0f32, 0.0, -1.0]; 6];
        let m = vec![true; 6];
        let field = |r: Result<Vec<f64>>| r.unwrap_err().field().unwrap().to_string();
        assert_eq!(
            field(integrate_normals(&k, 3, 2, &n[..5], &m, &p)),
            "normals"
        );
        assert_eq!(field(integrate_normals(&k, 3, 2, &n, &m[..5], &p)), "mask");
        let mut bad = n.clone();
        bad[2] = [0.0, 0.0, -2.0];
        assert_eq!(field(integrate_normals(&k, 3, 2, &bad, &m, &p)), "normals");
        bad[2] = [f32::NAN, 0.0, -1.0];
        assert_eq!(field(integrate_normals(&k, 3, 2, &bad, &m, &p)), "normals");
        // Bad normals outside the mask are fine.
        let mut m2 = m.clone();
        m2[2] = false;
        assert!(integrate_normals(&k, 3, 2, &bad, &m2, &p).is_ok());
        assert_eq!(
            field(integrate_normals(&k, 3, 2, &n, &[false; 6], &p)),
            "mask"
        );
        for s in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let ps = IntegrationParams { smoothness_s: s };
            assert_eq!(
                field(integrate_normals(&k, 3, 2, &n, &m, &ps)),
                "smoothness_s"
            );
        }
        let kb = Intrinsics::new(0.0, 1.0, 0.0, 0.0);
        assert_eq!(field(integrate_normals(&kb, 3, 2, &n, &m, &p)), "fx");
    }
}
