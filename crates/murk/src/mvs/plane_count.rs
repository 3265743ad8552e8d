//! How many planes a sweep needs: about one per pixel of the largest displacement a reference
//! pixel undergoes in any source between the nearest and the farthest plane.
//!
//! Planes are uniform in inverse depth, so for a translating camera the displacement between
//! neighbouring planes is the same for every plane; fewer planes than pixels of displacement
//! skip depths the images can resolve, many more only cost time and memory (the sub-plane
//! refinement interpolates between planes). A fixed count (the reference's 256) is too many for
//! a short baseline and too few for a long one.

use crate::camera::Intrinsics;
use crate::mvs::pose::Pose;
use crate::mvs::PlaneWarp;

/// Fewest planes chosen: the aggregation and the sub-plane refinement need a few on each side
/// of a minimum.
pub const AUTO_PLANES_MIN: usize = 16;
/// Most planes chosen (the reference's fixed count): beyond it memory grows with little gain.
pub const AUTO_PLANES_MAX: usize = 256;
/// Reference pixels sampled per axis to find the largest displacement.
const GRID: usize = 9;

/// One camera: intrinsics, world-to-camera pose and image size (pixels).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Pinhole intrinsics, pixels.
    pub intrinsics: Intrinsics,
    /// World-to-camera pose.
    pub pose: Pose,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
}

/// Largest displacement (pixels), over a grid of reference pixels and every source, between
/// the reference pixel's projections at z-depths `near` and `far` (scene units). Projections
/// behind a source are skipped; 0 when none is usable.
pub fn max_displacement_px(reference: &Camera, sources: &[Camera], near: f64, far: f64) -> f64 {
    let mut best = 0.0f64;
    for s in sources {
        let relative = Pose::relative(&reference.pose, &s.pose);
        let w_near = PlaneWarp::new(&reference.intrinsics, &s.intrinsics, &relative, near);
        let w_far = PlaneWarp::new(&reference.intrinsics, &s.intrinsics, &relative, far);
        for i in 0..GRID {
            for j in 0..GRID {
                let u = (reference.width.saturating_sub(1)) as f64 * i as f64 / (GRID - 1) as f64;
                let v = (reference.height.saturating_sub(1)) as f64 * j as f64 / (GRID - 1) as f64;
                let (un, vn, zn) = w_near.map(u, v);
                let (uf, vf, zf) = w_far.map(u, v);
                if zn > 0.0 && zf > 0.0 {
                    let d = (un - uf).hypot(vn - vf);
                    if d.is_finite() {
                        best = best.max(d);
                    }
                }
            }
        }
    }
    best
}

/// About one plane per pixel of [`max_displacement_px`], within
/// [`AUTO_PLANES_MIN`]`..=`[`AUTO_PLANES_MAX`] and at most `max_planes` (a memory limit).
pub fn planes_for_displacement(
    reference: &Camera,
    sources: &[Camera],
    near: f64,
    far: f64,
    max_planes: usize,
) -> usize {
    let d = max_displacement_px(reference, sources, near, far);
    let n = d.ceil() as usize + 1;
    n.clamp(AUTO_PLANES_MIN, AUTO_PLANES_MAX)
        .min(max_planes.max(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(tx: f64) -> Camera {
        Camera {
            intrinsics: Intrinsics::new(200.0, 200.0, 127.5, 95.5),
            pose: Pose::translation_only([tx, 0.0, 0.0]).unwrap(),
            width: 256,
            height: 192,
        }
    }

    #[test]
    fn one_plane_per_pixel_of_disparity() {
        // Rectified pair: disparity f·b/z, from 200·0.1/1 = 20 px at z = 1 to 2 px at z = 10.
        let (r, s) = (camera(0.0), camera(-0.1));
        let d = max_displacement_px(&r, &[s], 1.0, 10.0);
        assert!((d - 18.0).abs() < 1e-6, "{d}");
        // 19 planes (one per pixel of the 18 px sweep), at least the minimum.
        assert_eq!(planes_for_displacement(&r, &[s], 1.0, 10.0, 1024), 19);
        assert_eq!(
            planes_for_displacement(&r, &[s], 5.0, 10.0, 1024),
            AUTO_PLANES_MIN
        );
        // A long baseline: capped; and the memory limit wins over the cap.
        let far_src = camera(-2.0);
        assert_eq!(
            planes_for_displacement(&r, &[far_src], 1.0, 10.0, 1024),
            AUTO_PLANES_MAX
        );
        assert_eq!(planes_for_displacement(&r, &[far_src], 1.0, 10.0, 100), 100);
        // The largest displacement over the sources decides.
        assert_eq!(
            planes_for_displacement(&r, &[s, camera(-0.2)], 1.0, 10.0, 1024),
            37
        );
    }
}
