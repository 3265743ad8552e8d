//! How far the SfM points stand out of one plane: a flat point cloud facing the reference is
//! where SfM's poses are ambiguous, and with them the depth differences that carry β.
//!
//! When the points' depth varies little about their distance, perspective barely differs from
//! an affine camera, and two views cannot tell a rotation of the camera about an axis in the
//! image plane from a scaled relief (the bas-relief ambiguity of structure from motion,
//! Szeliski & Kang 1997): a reconstruction whose sources are turned by several degrees, whose
//! baselines point elsewhere and whose relief is flattened reprojects almost as well as the
//! truth. Only the points that stand out of the plane break the ambiguity. The reprojection
//! error and the bundle adjustment's covariance ([`crate::params::pose_error`]) are computed
//! at the solution SfM chose, so they cannot see a wrong one: on the COLMAP models of
//! `docs/scattering-params.md` the poses of such models were off by 5–15° with a 1-σ
//! rotation of 0.2–1.6° and a reprojection error of 0.6–1.05 px, like sound models. What they
//! share is the flattened relief: their points lie within 0.3–3.5 % of their depth of one
//! plane facing the reference, where the sound models facing a plane lie 5–10 % off it.
//!
//! [`Relief`] measures that: a least-squares plane through the points in the reference camera
//! (all of them, so the points on objects pull it as much as those on a wall), the median
//! distance of the points to it over their median depth, and the angle between its normal and
//! the optical axis. A plane seen obliquely (a floor, a wall along the path) is not
//! ambiguous in this way: the depth changes across it, which is perspective the affine camera
//! cannot mimic.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::camera::Intrinsics;
use crate::params::sparse::SparseDepth;

/// Fewest points for a relief: fewer cannot tell a plane from chance.
pub const MIN_RELIEF_POINTS: usize = 10;
/// Median distance of the points to their plane, over their median depth, below which a plane
/// facing the reference ([`MAX_FACING_TILT_DEG`]) makes the poses ambiguous. Chosen between the
/// COLMAP models of the survey in `docs/scattering-params.md` whose poses were off by 5° or more
/// (at most 0.035) and the sound ones facing a plane (0.05 and more); a chosen threshold, not a
/// fitted one.
pub const MIN_RELIEF: f64 = 0.04;
/// Largest angle between the plane's normal and the reference's optical axis, degrees, for the
/// plane to count as facing the reference.
pub const MAX_FACING_TILT_DEG: f64 = 45.0;

/// The SfM points' relief about their plane, in the reference camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Relief {
    /// Points behind the plane fit.
    pub points: usize,
    /// Median distance of the points to the least-squares plane through them, over their median
    /// z-depth (unitless; 0 = all on the plane).
    pub relief: f64,
    /// Angle between the plane's normal and the optical axis, degrees (0 = the plane faces the
    /// camera, 90 = seen edge-on).
    pub tilt_deg: f64,
}

impl Relief {
    /// The relief of the points of `sparse`, back-projected with the reference's `intrinsics`
    /// (at their sub-pixel positions). `None` with fewer than [`MIN_RELIEF_POINTS`] points.
    pub fn of(sparse: &SparseDepth, intrinsics: &Intrinsics) -> Option<Self> {
        let points: Vec<Vector3<f64>> = sparse
            .samples()
            .iter()
            .map(|s| {
                let ray = intrinsics.ray(f64::from(s.u), f64::from(s.v));
                ray * (f64::from(s.z) / ray.z)
            })
            .collect();
        Self::of_points(&points)
    }

    /// The relief of points given in the camera frame (z along the optical axis, > 0).
    /// `None` with fewer than [`MIN_RELIEF_POINTS`] points.
    pub fn of_points(points: &[Vector3<f64>]) -> Option<Self> {
        if points.len() < MIN_RELIEF_POINTS {
            return None;
        }
        let n = points.len() as f64;
        let centroid = points.iter().sum::<Vector3<f64>>() / n;
        let scatter = points.iter().fold(Matrix3::zeros(), |acc, p| {
            let d = p - centroid;
            acc + d * d.transpose()
        });
        // The plane's normal is the direction of least spread.
        let eig = SymmetricEigen::new(scatter);
        let normal = eig.eigenvectors.column(eig.eigenvalues.imin()).into_owned();
        let mut distance: Vec<f64> = points
            .iter()
            .map(|p| (p - centroid).dot(&normal).abs())
            .collect();
        let mut depth: Vec<f64> = points.iter().map(|p| p.z).collect();
        let median_depth = median(&mut depth);
        if median_depth <= 0.0 || !median_depth.is_finite() {
            return None;
        }
        Some(Self {
            points: points.len(),
            relief: median(&mut distance) / median_depth,
            tilt_deg: normal.z.abs().min(1.0).acos().to_degrees(),
        })
    }

    /// Whether the points lie so close to one plane facing the reference that SfM's poses are
    /// ambiguous (see the module docs).
    pub fn is_ambiguous(&self) -> bool {
        self.relief < MIN_RELIEF && self.tilt_deg <= MAX_FACING_TILT_DEG
    }

    /// The sentence for the user, with the numbers.
    pub fn describe(&self) -> String {
        format!(
            "the {} SfM points seen by the reference lie within {:.1} % of their depth of one \
             plane facing it (median distance; tilted {:.0} degrees; ambiguous below {:.0} % \
             within {:.0} degrees): for such a point cloud, sources turned by several degrees \
             with a flattened relief reproject as well as the true poses (the bas-relief \
             ambiguity), so the poses, the depth differences and beta may be wrong with small \
             errors. Frames that see objects standing out of the plane, or that view the scene \
             from more directions, help",
            self.points,
            100.0 * self.relief,
            self.tilt_deg,
            100.0 * MIN_RELIEF,
            MAX_FACING_TILT_DEG
        )
    }
}

/// The median of `v` (the upper one for an even count); reorders `v`.
fn median(v: &mut [f64]) -> f64 {
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, f64::total_cmp);
    *m
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mvs::pose::Pose;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Points on the plane through `(0, 0, z0)` with the given normal, spread over the image of
    /// a 60°-wide camera, each moved off the plane by a uniform `±relief · z0`.
    fn plane(normal: Vector3<f64>, z0: f64, relief: f64, n: usize, seed: u64) -> Vec<Vector3<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let normal = normal.normalize();
        (0..n)
            .map(|_| {
                let ray = Vector3::new(
                    rng.random_range(-0.55..0.55),
                    rng.random_range(-0.4..0.4),
                    1.0,
                );
                // The ray meets the plane n·(p − z0·ẑ) = 0 at t = n.z·z0 / n·ray.
                let t = normal.z * z0 / normal.dot(&ray);
                ray * t + normal * (relief * z0 * rng.random_range(-1.0..1.0))
            })
            .collect()
    }

    #[test]
    fn a_flat_cloud_facing_the_camera_is_ambiguous() {
        let r = Relief::of_points(&plane(Vector3::new(0.1, 0.2, 1.0), 5.0, 0.01, 300, 1)).unwrap();
        assert!(r.relief < 0.006, "{r:?}");
        assert!((r.tilt_deg - 12.6).abs() < 1.5, "{r:?}");
        assert!(r.is_ambiguous());
        assert!(r.describe().contains("bas-relief"));
    }

    #[test]
    fn objects_standing_out_of_the_plane_break_the_ambiguity() {
        let r = Relief::of_points(&plane(Vector3::z(), 5.0, 0.2, 300, 2)).unwrap();
        assert!(r.relief > MIN_RELIEF, "{r:?}");
        assert!(!r.is_ambiguous());
    }

    #[test]
    fn a_flat_floor_seen_obliquely_is_not_ambiguous() {
        // A floor 1.5 units below the camera: its normal is nearly perpendicular to the axis.
        let floor = plane(Vector3::new(0.0, 1.0, 0.3), 5.0, 0.005, 300, 3);
        let r = Relief::of_points(&floor).unwrap();
        assert!(r.relief < MIN_RELIEF && r.tilt_deg > 60.0, "{r:?}");
        assert!(!r.is_ambiguous());
    }

    #[test]
    fn too_few_points_have_no_relief() {
        let few = plane(Vector3::z(), 5.0, 0.01, MIN_RELIEF_POINTS - 1, 4);
        assert!(Relief::of_points(&few).is_none());
    }

    #[test]
    fn the_sparse_map_gives_the_relief_of_its_points() {
        let k = Intrinsics::new(200.0, 200.0, 127.5, 95.5);
        let pts = plane(Vector3::new(0.0, 0.3, 1.0), 4.0, 0.01, 400, 5);
        let world: Vec<[f64; 3]> = pts.iter().map(|p| [p.x, p.y, p.z]).collect();
        let sparse = SparseDepth::from_points(&world, &k, &Pose::identity(), 256, 192).unwrap();
        let from_map = Relief::of(&sparse, &k).unwrap();
        let direct = Relief::of_points(&pts).unwrap();
        // The map keeps one point per pixel, so it may hold fewer.
        assert!(from_map.points <= direct.points && from_map.points > 300);
        assert!(
            (from_map.relief - direct.relief).abs() < 0.002,
            "{from_map:?} {direct:?}"
        );
        assert!((from_map.tilt_deg - direct.tilt_deg).abs() < 1.0);
    }

    proptest! {
        /// The relief is a shape's, not the unit's or the camera's turn about its axis: scaling
        /// the scene or rotating it about the optical axis leaves relief and tilt unchanged.
        #[test]
        fn relief_ignores_the_unit_and_the_roll(
            scale in 0.01f64..100.0,
            roll in -3.1f64..3.1,
            relief in 0.001f64..0.2,
            seed in 0u64..1000,
        ) {
            let pts = plane(Vector3::new(0.2, -0.1, 1.0), 5.0, relief, 200, seed);
            let (s, c) = roll.sin_cos();
            let moved: Vec<Vector3<f64>> = pts
                .iter()
                .map(|p| Vector3::new(c * p.x - s * p.y, s * p.x + c * p.y, p.z) * scale)
                .collect();
            let a = Relief::of_points(&pts).unwrap();
            let b = Relief::of_points(&moved).unwrap();
            prop_assert!((a.relief - b.relief).abs() < 1e-9 * (1.0 + a.relief));
            prop_assert!((a.tilt_deg - b.tilt_deg).abs() < 1e-6);
        }
    }
}
