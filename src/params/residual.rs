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
    let sum: f64 = sparse
        .samples()
        .iter()
        .map(|s| f64::from(rho(d, w, h, s.x as usize, s.y as usize, s.z, delta_px)))
        .sum();
    Ok(sum / sparse.len() as f64)
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
