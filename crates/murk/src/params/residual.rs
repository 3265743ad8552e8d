//! The depth residual of Eq. 3.8–3.9 between a dense depth map and the sparse SfM depth.

use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::params::sparse::SparseDepth;

/// Eq. 3.9 at one sample: `min |z_sfm − z|` over the pixel and its four neighbours at distance
/// `δ` (left, right, up, down). Neighbours outside the image are skipped. The neighbours
/// absorb SfM points that land on the wrong side of a depth discontinuity (reference Fig. 3.6).
#[inline]
fn rho(depth: &[f32], w: usize, h: usize, x: usize, y: usize, z_sfm: f32, delta: usize) -> f32 {
    let at = |xx: usize, yy: usize| (z_sfm - depth[yy * w + xx]).abs();
    let mut r = at(x, y);
    if x >= delta {
        r = r.min(at(x - delta, y));
    }
    if x + delta < w {
        r = r.min(at(x + delta, y));
    }
    if y >= delta {
        r = r.min(at(x, y - delta));
    }
    if y + delta < h {
        r = r.min(at(x, y + delta));
    }
    r
}

/// The objective of Eq. 3.8 with `ρ` of Eq. 3.9, **divided by the number of SfM pixels** (the
/// mean residual, scene units; the argmin is the same as the reference's sum, and the value is
/// comparable across views). `depth` is a one-channel z-depth map of the sparse map's size.
pub fn sparse_residual(depth: &ImageF32, sparse: &SparseDepth, delta_px: usize) -> Result<f64> {
    let r = sparse_residuals(depth, sparse, delta_px)?;
    Ok(r.iter().map(|&x| f64::from(x)).sum::<f64>() / r.len() as f64)
}

/// Eq. 3.9's `ρ` at every SfM pixel, in the order of [`SparseDepth::samples`] (scene units).
/// Errors as [`sparse_residual`].
pub fn sparse_residuals(
    depth: &ImageF32,
    sparse: &SparseDepth,
    delta_px: usize,
) -> Result<Vec<f32>> {
    if depth.dims() != (sparse.width(), sparse.height()) || depth.channels() != 1 {
        return Err(MurkError::invalid(
            "depth",
            format!(
                "expected a {}x{} one-channel depth map, got {}x{}x{}",
                sparse.width(),
                sparse.height(),
                depth.width(),
                depth.height(),
                depth.channels()
            ),
        ));
    }
    if sparse.is_empty() {
        return Err(MurkError::invalid(
            "sparse_points",
            "no SfM point is visible in the reference view",
        ));
    }
    let (w, h) = depth.dims();
    let d = depth.data();
    Ok(sparse
        .samples()
        .iter()
        .map(|s| rho(d, w, h, s.x as usize, s.y as usize, s.z, delta_px))
        .collect())
}

/// Paired t statistic of `incumbent − candidate` over the same SfM pixels: how many standard
/// errors the candidate's mean residual lies below the incumbent's (positive = candidate
/// better). 0 when the difference has no spread (identical depths).
pub fn paired_improvement_t(incumbent: &[f32], candidate: &[f32]) -> f64 {
    let n = incumbent.len().min(candidate.len());
    if n < 2 {
        return 0.0;
    }
    let d = || {
        incumbent
            .iter()
            .zip(candidate)
            .map(|(&a, &b)| f64::from(a) - f64::from(b))
    };
    let mean = d().sum::<f64>() / n as f64;
    let var = d().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    if var <= 0.0 {
        return 0.0;
    }
    mean / (var / n as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::mvs::pose::Pose;

    #[test]
    fn residual_is_zero_at_truth_and_uses_the_neighbours() {
        let (w, h) = (32, 24);
        let k = Intrinsics::new(40.0, 40.0, 15.5, 11.5);
        // A step edge at x = 16: near (1) left, far (3) right.
        let depth = ImageF32::from_fn(w, h, |x, _| if x < 16 { 1.0 } else { 3.0 });
        let back = |x: f64, y: f64, z: f64| [(x - 15.5) * z / 40.0, (y - 11.5) * z / 40.0, z];
        let pts = [back(5.0, 5.0, 1.0), back(25.0, 5.0, 3.0)];
        let s = SparseDepth::from_points(&pts, &k, &Pose::identity(), w, h).unwrap();
        assert_eq!(sparse_residual(&depth, &s, 5).unwrap(), 0.0);
        // A far point mislocated just left of the edge: 2.0 away at its pixel, matched by the
        // neighbour δ = 5 to the right, not with δ = 0.
        let edge = [back(14.0, 10.0, 3.0)];
        let s = SparseDepth::from_points(&edge, &k, &Pose::identity(), w, h).unwrap();
        assert_eq!(sparse_residual(&depth, &s, 0).unwrap(), 2.0);
        assert_eq!(sparse_residual(&depth, &s, 5).unwrap(), 0.0);
        // Mean, not sum.
        let two = [back(5.0, 5.0, 2.0), back(6.0, 5.0, 1.0)];
        let s = SparseDepth::from_points(&two, &k, &Pose::identity(), w, h).unwrap();
        assert_eq!(sparse_residual(&depth, &s, 0).unwrap(), 0.5);
    }

    #[test]
    fn paired_t_is_signed_and_scale_free() {
        let a = [1.0f32, 2.0, 3.0, 4.0];
        let better = [0.5f32, 1.6, 2.4, 3.5];
        let t = paired_improvement_t(&a, &better);
        assert!(t > 5.0, "{t}");
        assert!((paired_improvement_t(&better, &a) + t).abs() < 1e-12);
        let scaled: Vec<f32> = a.iter().map(|x| x * 10.0).collect();
        let scaled_b: Vec<f32> = better.iter().map(|x| x * 10.0).collect();
        assert!((paired_improvement_t(&scaled, &scaled_b) - t).abs() < 1e-4 * t);
        assert_eq!(paired_improvement_t(&a, &a), 0.0);
    }

    #[test]
    fn rejects_empty_and_mismatched() {
        let k = Intrinsics::new(40.0, 40.0, 15.5, 11.5);
        let depth = ImageF32::filled(32, 24, 1, 1.0);
        let none = SparseDepth::from_points(&[], &k, &Pose::identity(), 32, 24).unwrap();
        assert_eq!(
            sparse_residual(&depth, &none, 5).unwrap_err().field(),
            Some("sparse_points")
        );
        let other = SparseDepth::from_points(&[], &k, &Pose::identity(), 16, 24).unwrap();
        assert_eq!(
            sparse_residual(&depth, &other, 5).unwrap_err().field(),
            Some("depth")
        );
    }
}
