//! The per-row arithmetic that the cost kernels ([`super::kernel`]) and their AVX2 copies
//! ([`super::simd`]) share: a plane's haze constants, the source coordinates of a row, the
//! sources' inverse transmissions along it, and the mean over the observing sources.

use super::DehazingResidual;
use crate::atmosphere::inverse_transmission;
use crate::mvs::plane_sweep::RowWarp;

/// Per-plane constants of the dehazing volume: the reference is dehazed with the plane's own
/// depth `z_i` (Eq. 3.5), so `J_r = I_r·inv_t + offset` with both constant over the plane.
#[derive(Clone, Copy)]
pub(super) struct Haze {
    pub airlight: f32,
    pub beta: f32,
    pub ref_inv_t: f32,
    pub ref_offset: f32,
    /// Reference transmission `t_r = e^{−β z_i}` (scales the residual out of dehazed space).
    pub ref_t: f32,
    /// Where the residual is measured.
    pub residual: DehazingResidual,
    /// Accepted range of a dehazed reference value, `[ref_lo, ref_hi]` (`[0, 1]` for Eq. 3.7).
    pub ref_lo: f32,
    pub ref_hi: f32,
    /// Margin of the source range check in observation units: a dehazed source value is
    /// accepted in `[−m/t_s, 1 + m/t_s]` (`m = 0` for Eq. 3.7, `∞` for no check).
    pub src_margin: f32,
    /// Soft range penalty: `Some(m)` adds each channel's excursion beyond `[−m/t, 1 + m/t]`
    /// (dehazed units) to the residual before scaling, the voxel capped at `γ`.
    pub soft_margin: Option<f32>,
}

impl Haze {
    /// The ordinary volume's constants: no airlight, no dehazing (`J = I`), the `[0, 1]` range.
    pub const CLEAR: Haze = Haze {
        airlight: 0.0,
        beta: 0.0,
        ref_inv_t: 1.0,
        ref_offset: 0.0,
        ref_t: 1.0,
        residual: DehazingResidual::Eq37,
        ref_lo: 0.0,
        ref_hi: 1.0,
        src_margin: 0.0,
        soft_margin: None,
    };
}

/// `out[x] = sum[x] / observed[x]`, or `penalty` where no source observed the voxel. Divides by
/// `max(n, 1)` and selects afterwards, so the loop has no branch and vectorises.
#[inline(always)]
pub(super) fn mean_or_penalty(out: &mut [f32], sum: &[f32], observed: &[u32], penalty: f32) {
    for ((o, &s), &n) in out.iter_mut().zip(sum).zip(observed) {
        let mean = s / (n as f32).max(1.0);
        *o = if n == 0 { penalty } else { mean };
    }
}

/// Source sample coordinates of one reference row for one plane: `us[x], vs[x]` is
/// `π_{r→s}(x, y; z_i)`, with `us[x] = NaN` marking an unobserved sample (the plane point behind
/// the source camera, where `ζ = w·depth ≤ 0`, or outside the pixel-centre hull). The
/// homogeneous coordinates are affine in `u` along the row and evaluated in `f32`
/// ([`crate::mvs::plane_sweep::RowWarpF32`]). Branch-free, so it vectorises.
#[inline(always)]
pub(super) fn source_coords(
    warp: &RowWarp,
    width: usize,
    height: usize,
    us: &mut [f32],
    vs: &mut [f32],
) {
    let warp = warp.to_f32();
    let (wmax, hmax) = ((width - 1) as f32, (height - 1) as f32);
    // Views without a rotation between them (a rectified pair) share one 1/w along the row.
    match warp.constant_reciprocal() {
        Some(r) => coords_along(us, vs, wmax, hmax, |x| warp.project_with(x, r)),
        None => coords_along(us, vs, wmax, hmax, |x| warp.project(x)),
    }
}

/// The loop of [`source_coords`] for one way of projecting a column.
#[inline(always)]
fn coords_along(
    us: &mut [f32],
    vs: &mut [f32],
    wmax: f32,
    hmax: f32,
    project: impl Fn(f32) -> (f32, f32, f32),
) {
    for (x, (us, vs)) in us.iter_mut().zip(vs.iter_mut()).enumerate() {
        let (a, b, hw) = project(x as f32);
        let inside = hw > 0.0 && a >= 0.0 && b >= 0.0 && a <= wmax && b <= hmax;
        *us = if inside { a } else { f32::NAN };
        *vs = b;
    }
}

/// `1/t_s = e^{βζ}` for every pixel of one reference row and plane, clamped like
/// [`inverse_transmission`]. `ζ` is affine in `u` along the row (`ζ = depth·w(u)`), so this is a
/// geometric sequence: one multiply per pixel instead of an `exp` (in `f64`, so the drift over a
/// row is ~1e-14 relative; `β = 0` gives exactly 1). Rows where `e^{βζ}` over- or underflows at
/// an end fall back to one `exp` per pixel.
#[inline(always)]
pub(super) fn inverse_transmission_row(warp: &RowWarp, beta: f32, out: &mut [f32]) {
    let (slope, offset, depth) = warp.coefficients();
    let b = f64::from(beta);
    let (z0, dz) = (offset[2] * depth, slope[2] * depth);
    let last = out.len().saturating_sub(1) as f64;
    let (start, end) = ((b * z0).exp(), (b * (z0 + dz * last)).exp());
    let max_inv_t = f64::from(inverse_transmission(0.0));
    if dz == 0.0 && start.is_normal() {
        // A row at one depth (a fronto-parallel plane seen by a camera that does not tilt
        // against it, e.g. either view of a rectified pair): the sequence below with step 1.
        out.fill(start.min(max_inv_t) as f32);
    } else if start.is_normal() && end.is_normal() {
        // Four interleaved geometric sequences (ratio step⁴) so the multiplies do not form one
        // latency-bound chain across the row.
        let step = (b * dz).exp();
        let step4 = step.powi(4);
        let mut lanes = [
            start,
            start * step,
            start * step * step,
            start * step.powi(3),
        ];
        let mut chunks = out.chunks_exact_mut(4);
        for o in &mut chunks {
            for (o, l) in o.iter_mut().zip(lanes.iter_mut()) {
                *o = l.min(max_inv_t) as f32;
                *l *= step4;
            }
        }
        for (o, l) in chunks.into_remainder().iter_mut().zip(lanes) {
            *o = l.min(max_inv_t) as f32;
        }
    } else {
        for (x, o) in out.iter_mut().enumerate() {
            *o = (b * (z0 + dz * x as f64)).exp().min(max_inv_t) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::mvs::plane_sweep::PlaneWarp;
    use crate::mvs::pose::Pose;

    /// The interleaved geometric sequence equals one `exp` per pixel (clamped), on rows whose
    /// length is not a multiple of the 4 lanes, of a source that tilts against the plane (depth
    /// varies along the row) and of one that does not (one depth per row: the constant fill).
    #[test]
    fn inverse_transmission_row_matches_exp() {
        let k = Intrinsics::new(30.0, 30.0, 20.0, 6.0);
        let (c, s) = (0.2f64.cos(), 0.2f64.sin());
        let tilted = Pose::from_rows(
            [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]],
            [-0.3, 0.05, 0.1],
        )
        .unwrap();
        let straight = Pose::translation_only([-0.3, 0.05, 0.1]).unwrap();
        let max_inv_t = inverse_transmission(0.0);
        for ((z, beta, width), rel) in [(1.0f64, 0.3f32, 37usize), (6.0, 0.8, 41), (2.0, 0.0, 3)]
            .into_iter()
            .flat_map(|case| [(case, &tilted), (case, &straight)])
        {
            let warp = PlaneWarp::new(&k, &k, rel, z).row(4.0);
            let mut fast = vec![0.0f32; width];
            inverse_transmission_row(&warp, beta, &mut fast);
            let (slope, offset, depth) = warp.coefficients();
            for (x, &f) in fast.iter().enumerate() {
                let zeta = (offset[2] + slope[2] * x as f64) * depth;
                let exact = ((f64::from(beta) * zeta).exp() as f32).min(max_inv_t);
                assert!((f - exact).abs() <= 1e-6 * exact, "x {x}: {f} vs {exact}");
            }
        }
    }
}
