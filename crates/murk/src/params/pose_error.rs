//! What the SfM poses' uncertainty does to `A` and β.
//!
//! The joint fit ([`crate::params::joint_fit`]) takes the SfM model as exact. Its standard
//! errors cover the image noise, the sources' disagreement and the errors a point carries into
//! all its equations. An error in a pose is different: it shifts the depth difference
//! `z_s − z_r` of every point a source sees in the same way (a translation direction a few
//! degrees off tilts them all), so no resampling of points or sources can see it. On small
//! COLMAP models of hazy footage such errors moved `A` and β by several of the fit's standard
//! errors (docs/scattering-params.md).
//!
//! **The poses' covariance** is that of a bundle adjustment of the request's views, linearised
//! at the model:
//! - each 2-D observation gives the Jacobian of its reprojection with respect to the view's
//!   pose and to the world point. A pose moves by a rotation `ω` and a translation `τ` in its
//!   camera frame, `X_c' = X_c + ω × X_c + τ`;
//! - the points are eliminated (Schur complement), so a pose error that the points can absorb,
//!   such as the bas-relief ambiguity of short baselines, shows as the weak direction it is.
//!   Points seen by fewer than two of the views say nothing of the poses and are left out;
//! - the gauge: the reference's pose is fixed, and so is the scale (the step along the
//!   scene's scaling about the reference camera is projected out);
//! - the noise is the observations' reprojection error per degree of freedom,
//!   `σ² = Σ r² / (2·observations − 3·points − (6·sources − 1))`.
//!
//! **Propagation** by sigma points: along each eigen-direction `d_i` of the poses' covariance
//! (one standard deviation long) the poses move by `±d_i`, the points with them as the
//! adjustment would move them (first order, `δx = −H_xx⁻¹ H_xp δp`), the scene is rescaled
//! about the reference camera so that the points' mean log depth there is unchanged (β is per
//! unit of depth, and the scale is not an error), the points are sampled again, and the fit is
//! re-run from its solution. The variance of `A` or β is `Σ_i ((θ₊ᵢ − θ₋ᵢ)/2)²`.
//!
//! The error is a lower bound where the model has systematic errors (a wrong match that BA
//! kept, a bas-relief solution the observations fit well): the covariance is the spread that
//! the observations' own noise allows.

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, SMatrix, SymmetricEigen, Vector3};
use rayon::prelude::*;

use crate::camera::Intrinsics;
use crate::error::Result;
use crate::monitor::Monitor;
use crate::mvs::pose::Pose;
use crate::mvs::View;
use crate::params::joint_fit::JointFit;
use crate::params::point_ratio::blurred_ratio_samples;
use crate::params::sparse::SparseDepth;
pub use crate::params::tracks::{Observation, SfmTracks};

/// Pose parameters per source: rotation `ω` (3) then translation `τ` (3), camera frame.
const POSE_DOF: usize = 6;
/// A point whose 3 × 3 information is this ill-conditioned (smallest over largest eigenvalue)
/// is not located by its observations (seen from one centre): it is left out.
const MIN_POINT_CONDITION: f64 = 1e-9;
/// Most points behind the poses' covariance: those with the longest tracks. Each keeps a 3 × 3
/// inverse and a 3 × 6 coupling per source that sees it (about 0.5 KB for three sources), so
/// the cap bounds a job's memory (about 10 MB) on the largest requests. Leaving points out only
/// widens the covariance, and the points left out keep their place in the sigma points (their
/// samples move with the poses): both err on the side of a larger error. The survey's COLMAP
/// models have 100–1 200 points.
pub const MAX_COVARIANCE_POINTS: usize = 20_000;
/// The poses count as undetermined when the weakest direction's information is below this
/// fraction of the strongest's.
const MIN_POSE_CONDITION: f64 = 1e-12;

/// The linearised bundle adjustment of [`pose_covariance`]: the poses' covariance as sigma
/// directions, and how the points follow the poses.
#[derive(Clone, Debug)]
pub struct PoseCovariance {
    /// Observations used (in front of their camera, of points seen by two or more views).
    pub observations: usize,
    /// Points seen by two or more of the views.
    pub points: usize,
    /// Reprojection error per degree of freedom, pixels: the `σ` of the module docs.
    pub reprojection_rms_px: f64,
    /// Per source, the 1-σ rotation (root of the variances' sum), degrees.
    pub rotation_std_deg: Vec<f64>,
    /// Per source, the 1-σ angle by which the direction from the reference camera to the
    /// source's can turn, degrees.
    pub baseline_direction_std_deg: Vec<f64>,
    /// Why the observations do not determine the poses, when they do not.
    pub undetermined: Option<String>,
    directions: Vec<DVector<f64>>,
    point_blocks: Vec<PointBlock>,
    /// The points' mean log depth in the reference at the model: what a moved scene is
    /// rescaled back to.
    mean_log_depth: Option<f64>,
}

/// How one point follows the poses: `δx = −H_xx⁻¹ Σ_s B_s δp_s`.
#[derive(Clone, Debug)]
struct PointBlock {
    point: usize,
    hxx_inv: Matrix3<f64>,
    /// Per source that sees it, `B_s = J_xᵀ J_p` summed over its observations there.
    coupling: Vec<(usize, SMatrix<f64, 3, 6>)>,
}

/// The intrinsics and pose of `reference` and then of each source: the camera list of
/// [`pose_covariance`].
pub fn cameras(reference: &View<'_>, sources: &[View<'_>]) -> Vec<(Intrinsics, Pose)> {
    std::iter::once(reference)
        .chain(sources)
        .map(|v| (v.intrinsics, v.pose))
        .collect()
}

/// The mean log z-depth of the points in front of `camera`; `None` when none is.
fn mean_log_depth(camera: &Pose, points: impl Iterator<Item = Vector3<f64>>) -> Option<f64> {
    let (sum, n) = points
        .map(|p| (camera.rotation() * p + camera.translation()).z)
        .filter(|z| *z > 0.0)
        .fold((0.0, 0usize), |(s, n), z| (s + z.ln(), n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// `[v]×`, the cross-product matrix.
fn cross_matrix(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Reprojection of camera-frame point `xc` and its 2 × 3 Jacobian; `None` behind the camera.
fn project(k: &Intrinsics, xc: &Vector3<f64>) -> Option<([f64; 2], SMatrix<f64, 2, 3>)> {
    if xc.z <= 0.0 {
        return None;
    }
    let (x, y, iz) = (xc.x / xc.z, xc.y / xc.z, 1.0 / xc.z);
    let uv = [k.fx * x + k.skew * y + k.cx, k.fy * y + k.cy];
    let jac = SMatrix::<f64, 2, 3>::new(
        k.fx * iz,
        k.skew * iz,
        -(k.fx * x + k.skew * y) * iz,
        0.0,
        k.fy * iz,
        -k.fy * y * iz,
    );
    Some((uv, jac))
}

/// The linearised bundle adjustment of the module docs for `views` (the reference first, then
/// the sources: intrinsics and world-to-camera pose) and `tracks` (validated by the caller).
pub fn pose_covariance(views: &[(Intrinsics, Pose)], tracks: &SfmTracks) -> PoseCovariance {
    let n_src = views.len().saturating_sub(1);
    let n = POSE_DOF * n_src;
    let mut by_point: Vec<Vec<usize>> = vec![Vec::new(); tracks.points.len()];
    for (i, o) in tracks.observations.iter().enumerate() {
        by_point[o.point as usize].push(i);
    }
    // The points with the longest tracks, at most `MAX_COVARIANCE_POINTS` of them (ties by
    // index, so the choice is deterministic).
    let mut chosen: Vec<usize> = (0..by_point.len())
        .filter(|&p| by_point[p].len() >= 2)
        .collect();
    if chosen.len() > MAX_COVARIANCE_POINTS {
        chosen.sort_by_key(|&p| (std::cmp::Reverse(by_point[p].len()), p));
        chosen.truncate(MAX_COVARIANCE_POINTS);
        chosen.sort_unstable();
    }
    let mut schur = DMatrix::<f64>::zeros(n, n);
    let mut blocks = Vec::new();
    let (mut ssr, mut used) = (0.0, 0usize);
    for &p in &chosen {
        let obs = &by_point[p];
        let x = Vector3::from(tracks.points[p]);
        let mut hxx = Matrix3::<f64>::zeros();
        let mut coupling: Vec<(usize, SMatrix<f64, 3, 6>)> = Vec::new();
        let mut hpp: Vec<(usize, SMatrix<f64, 6, 6>)> = Vec::new();
        let mut views_seen = 0u64;
        let (mut point_ssr, mut point_obs) = (0.0, 0usize);
        for &oi in obs {
            let o = tracks.observations[oi];
            let (k, pose) = &views[o.view as usize];
            let xc = pose.rotation() * x + pose.translation();
            let Some((uv, a)) = project(k, &xc) else {
                continue;
            };
            point_ssr += (o.pixel[0] - uv[0]).powi(2) + (o.pixel[1] - uv[1]).powi(2);
            point_obs += 1;
            views_seen |= 1 << (o.view.min(63));
            let jx = a * pose.rotation();
            hxx += jx.transpose() * jx;
            if o.view == 0 {
                continue;
            }
            let mut jp = SMatrix::<f64, 2, 6>::zeros();
            jp.fixed_view_mut::<2, 3>(0, 0)
                .copy_from(&(a * -cross_matrix(&xc)));
            jp.fixed_view_mut::<2, 3>(0, 3).copy_from(&a);
            let s = o.view as usize - 1;
            let b = jx.transpose() * jp;
            let h = jp.transpose() * jp;
            match coupling.iter_mut().find(|(t, _)| *t == s) {
                Some((_, c)) => *c += b,
                None => coupling.push((s, b)),
            }
            match hpp.iter_mut().find(|(t, _)| *t == s) {
                Some((_, c)) => *c += h,
                None => hpp.push((s, h)),
            }
        }
        if views_seen.count_ones() < 2 || coupling.is_empty() {
            continue;
        }
        let eig = hxx.symmetric_eigenvalues();
        let (lo, hi) = (eig.min(), eig.max());
        if !(hi > 0.0 && lo > MIN_POINT_CONDITION * hi) {
            continue;
        }
        let Some(hxx_inv) = hxx.try_inverse() else {
            continue;
        };
        ssr += point_ssr;
        used += point_obs;
        for (s, h) in &hpp {
            let mut view = schur.view_mut((POSE_DOF * s, POSE_DOF * s), (POSE_DOF, POSE_DOF));
            view += h;
        }
        for (s, bs) in &coupling {
            let left = bs.transpose() * hxx_inv;
            for (t, bt) in &coupling {
                let mut view = schur.view_mut((POSE_DOF * s, POSE_DOF * t), (POSE_DOF, POSE_DOF));
                view -= left * bt;
            }
        }
        blocks.push(PointBlock {
            point: p,
            hxx_inv,
            coupling,
        });
    }
    let dof = (2 * used) as f64 - (3 * blocks.len()) as f64 - (n as f64 - 1.0);
    let sigma = (ssr / dof.max(1.0)).sqrt();
    let mut out = PoseCovariance {
        observations: used,
        points: blocks.len(),
        reprojection_rms_px: sigma,
        rotation_std_deg: vec![f64::INFINITY; n_src],
        baseline_direction_std_deg: vec![f64::INFINITY; n_src],
        undetermined: None,
        directions: Vec::new(),
        point_blocks: blocks,
        mean_log_depth: views.first().and_then(|(_, reference)| {
            mean_log_depth(reference, tracks.points.iter().map(|p| Vector3::from(*p)))
        }),
    };
    if n_src == 0 {
        out.undetermined = Some("no source views".into());
        return out;
    }
    // The scale mode: the scene scaled about the reference camera's centre moves source `s`'s
    // translation by `t_s + R_s C_ref` and leaves every reprojection as it is.
    let c_ref = *views[0].1.inverse().translation();
    let mut scale = DVector::<f64>::zeros(n);
    for (s, (_, pose)) in views[1..].iter().enumerate() {
        let d = pose.translation() + pose.rotation() * c_ref;
        scale.rows_mut(POSE_DOF * s + 3, 3).copy_from(&d);
    }
    let norm = scale.norm();
    if !(norm > 0.0 && norm.is_finite()) {
        out.undetermined = Some("every source sits at the reference camera's centre".into());
        return out;
    }
    scale /= norm;
    // An orthonormal basis of the scale mode's complement: the Householder reflection that maps
    // the mode onto a coordinate axis, without that axis's column.
    let k = scale.iamax();
    let mut v = scale.clone();
    v[k] = scale[k] + if scale[k] >= 0.0 { 1.0 } else { -1.0 };
    let house = DMatrix::<f64>::identity(n, n) - (&v * v.transpose()) * (2.0 / v.norm_squared());
    let q = house.remove_column(k);
    let reduced = q.transpose() * &schur * &q;
    let eig = SymmetricEigen::new(reduced);
    let hi = eig.eigenvalues.max();
    let lo = eig.eigenvalues.min();
    if !(hi > 0.0 && lo > MIN_POSE_CONDITION * hi) {
        out.undetermined = Some(format!(
            "the {} observations of {} points seen twice or more leave a pose direction \
             unconstrained",
            out.observations, out.points
        ));
        return out;
    }
    let mut cov = DMatrix::<f64>::zeros(n, n);
    for (i, &lambda) in eig.eigenvalues.iter().enumerate() {
        let d = &q * eig.eigenvectors.column(i) * (sigma / lambda.sqrt());
        cov += &d * d.transpose();
        out.directions.push(d);
    }
    for (s, (_, pose)) in views[1..].iter().enumerate() {
        let o = POSE_DOF * s;
        let rot_var: f64 = (0..3).map(|i| cov[(o + i, o + i)]).sum();
        out.rotation_std_deg[s] = rot_var.max(0.0).sqrt().to_degrees();
        // δC = −Rᵀ τ (to first order; the rotation's part vanishes with C = −Rᵀ t).
        let rt = pose.rotation().transpose();
        let tau = cov.view((o + 3, o + 3), (3, 3)).into_owned();
        let cov_c = rt * tau * rt.transpose();
        let baseline = pose.inverse().translation() - c_ref;
        let len = baseline.norm();
        out.baseline_direction_std_deg[s] = if len > 0.0 {
            let b = baseline / len;
            let perp = Matrix3::identity() - b * b.transpose();
            ((perp * cov_c * perp).trace().max(0.0).sqrt() / len).to_degrees()
        } else {
            f64::INFINITY
        };
    }
    out
}

impl PoseCovariance {
    /// Whether the observations determine the poses.
    pub fn is_determined(&self) -> bool {
        self.undetermined.is_none()
    }

    /// The sources' poses moved by `d` (6 entries per source: `ω` then `τ`) and every point
    /// with them, rescaled about the reference camera so that the points' mean log depth there
    /// stays as it was.
    fn moved(
        &self,
        reference: &Pose,
        sources: &[View<'_>],
        tracks: &SfmTracks,
        d: &DVector<f64>,
    ) -> Option<(Vec<Pose>, Vec<[f64; 3]>)> {
        let mut points: Vec<Vector3<f64>> =
            tracks.points.iter().map(|p| Vector3::from(*p)).collect();
        for b in &self.point_blocks {
            let mut rhs = Vector3::zeros();
            for (s, c) in &b.coupling {
                rhs += c * d.fixed_rows::<6>(POSE_DOF * s);
            }
            points[b.point] -= b.hxx_inv * rhs;
        }
        let c_ref = *reference.inverse().translation();
        let scale =
            (self.mean_log_depth? - mean_log_depth(reference, points.iter().copied())?).exp();
        let points = points
            .iter()
            .map(|p| (c_ref + (p - c_ref) * scale).into())
            .collect();
        let mut poses = Vec::with_capacity(sources.len());
        for (s, v) in sources.iter().enumerate() {
            let step = d.fixed_rows::<6>(POSE_DOF * s);
            let turn = Rotation3::new(Vector3::new(step[0], step[1], step[2])).into_inner();
            let rotation = turn * v.pose.rotation();
            let translation = turn * v.pose.translation() + Vector3::new(step[3], step[4], step[5]);
            let centre = -(rotation.transpose() * translation);
            let centre = c_ref + (centre - c_ref) * scale;
            poses.push(Pose::new(rotation, -(rotation * centre)).ok()?);
        }
        Some((poses, points))
    }

    /// The sources moved by `d` ([`Self::moved`]) as views, and the sparse map of the moved
    /// points in the reference.
    fn moved_views<'a>(
        &self,
        reference: &View<'a>,
        sources: &[View<'a>],
        tracks: &SfmTracks,
        d: &DVector<f64>,
    ) -> Option<(Vec<View<'a>>, SparseDepth)> {
        let (poses, points) = self.moved(&reference.pose, sources, tracks, d)?;
        let moved = sources
            .iter()
            .zip(&poses)
            .map(|(v, p)| View {
                image: v.image,
                intrinsics: v.intrinsics,
                pose: *p,
            })
            .collect();
        let (w, h) = reference.image.dims();
        let sparse = SparseDepth::from_tracked_points(
            &points,
            &tracks.seen_by,
            &reference.intrinsics,
            &reference.pose,
            w,
            h,
        )
        .ok()?;
        Some((moved, sparse))
    }

    /// The spread of `(A, β)` that the poses' uncertainty causes: `refit` is run on the views
    /// and sparse map of every sigma point (views moved as [`PoseCovariance`]'s docs say) and
    /// returns its `[A, β]`. `None` when the poses are undetermined or a refit fails.
    pub fn propagate<F>(
        &self,
        reference: &View<'_>,
        sources: &[View<'_>],
        tracks: &SfmTracks,
        refit: F,
    ) -> Option<[f64; 2]>
    where
        F: Fn(&View<'_>, &[View<'_>], &SparseDepth) -> Option<[f64; 2]> + Sync,
    {
        if !self.is_determined() {
            return None;
        }
        let ends = |i: usize, sign: f64| -> Option<[f64; 2]> {
            let (moved, sparse) =
                self.moved_views(reference, sources, tracks, &(&self.directions[i] * sign))?;
            refit(reference, &moved, &sparse)
        };
        // `collect` keeps the directions' order, so the sum is the same for any thread count.
        let halves: Option<Vec<[f64; 2]>> = (0..self.directions.len())
            .into_par_iter()
            .map(|i| {
                let (plus, minus) = (ends(i, 1.0)?, ends(i, -1.0)?);
                Some([(plus[0] - minus[0]) / 2.0, (plus[1] - minus[1]) / 2.0])
            })
            .collect();
        let halves = halves?;
        let var = |k: usize| halves.iter().map(|h| h[k] * h[k]).sum::<f64>();
        Some([var(0).sqrt(), var(1).sqrt()])
    }
}

/// What the SfM poses' uncertainty adds to a joint fit's standard errors, with the numbers
/// behind it.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseError {
    /// The poses' share of `A`'s standard error; `None` when it could not be computed
    /// ([`PoseError::undetermined`] says why).
    pub airlight_std_error: Option<f64>,
    /// The poses' share of β's standard error, per scene unit; `None` as for `A`.
    pub beta_std_error: Option<f64>,
    /// Observations used ([`PoseCovariance::observations`]).
    pub observations: usize,
    /// Points seen by two or more of the views.
    pub points: usize,
    /// Reprojection error per degree of freedom, pixels.
    pub reprojection_rms_px: f64,
    /// The largest 1-σ rotation of a source, degrees.
    pub max_rotation_std_deg: f64,
    /// The largest 1-σ turn of a source's direction from the reference camera, degrees.
    pub max_baseline_direction_std_deg: f64,
    /// Why the poses' share could not be computed, when it could not.
    pub undetermined: Option<String>,
}

impl PoseError {
    /// The share `[A, β]`, when it could be computed.
    pub fn share(&self) -> Option<[f64; 2]> {
        Some([self.airlight_std_error?, self.beta_std_error?])
    }
}

/// The poses' share of `fit`'s standard errors for `reference` and `sources` (whose poses and
/// intrinsics the model gave) and the model's `tracks`: [`pose_covariance`], then
/// [`PoseCovariance::propagate`] with [`JointFit::refit`] on [`blurred_ratio_samples`].
///
/// The refits stop early when `monitor` is cancelled, and the call then returns `Cancelled`.
pub fn pose_error_of_fit(
    reference: &View<'_>,
    sources: &[View<'_>],
    tracks: &SfmTracks,
    fit: &JointFit,
    monitor: &Monitor,
) -> Result<PoseError> {
    let cov = pose_covariance(&cameras(reference, sources), tracks);
    // A cancelled job stops at the next refit: each sees `None` and the spread is dropped.
    let spread = cov.propagate(reference, sources, tracks, |r, s, sparse| {
        if monitor.is_cancelled() {
            return None;
        }
        fit.refit(&blurred_ratio_samples(r, s, sparse))
    });
    monitor.checkpoint()?;
    let largest = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    let undetermined = match (&cov.undetermined, spread) {
        (Some(why), _) => Some(why.clone()),
        (None, None) => Some(
            "a fit with the poses moved by one standard deviation failed (too few points stay \
             in view, or it did not converge)"
                .to_string(),
        ),
        (None, Some(_)) => None,
    };
    Ok(PoseError {
        airlight_std_error: spread.map(|s| s[0]),
        beta_std_error: spread.map(|s| s[1]),
        observations: cov.observations,
        points: cov.points,
        reprojection_rms_px: cov.reprojection_rms_px,
        max_rotation_std_deg: largest(&cov.rotation_std_deg),
        max_baseline_direction_std_deg: largest(&cov.baseline_direction_std_deg),
        undetermined,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::MurkError;
    use crate::params::joint_fit::{fit_joint_samples, JointPriors, FALLOFF_PRIOR_SIGMA};
    use crate::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Three cameras 0.3 apart looking at points 4–6 units away; each observation is the exact
    /// projection plus Gaussian noise of `noise_px`.
    fn synthetic(noise_px: f64, scale: f64, seed: u64) -> (Vec<(Intrinsics, Pose)>, SfmTracks) {
        synthetic_points(200, noise_px, scale, seed)
    }

    fn synthetic_points(
        points: u32,
        noise_px: f64,
        scale: f64,
        seed: u64,
    ) -> (Vec<(Intrinsics, Pose)>, SfmTracks) {
        let k = Intrinsics::new(300.0, 300.0, 160.0, 120.0);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let views: Vec<(Intrinsics, Pose)> =
            [[0.0, 0.0, 0.0], [-0.3, 0.02, 0.05], [0.3, -0.01, -0.1]]
                .iter()
                .map(|t| (k, Pose::translation_only(t.map(|c| c * scale)).unwrap()))
                .collect();
        let mut tracks = SfmTracks::default();
        let gauss = |rng: &mut ChaCha8Rng| {
            let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        for i in 0..points {
            let z = rng.random_range(4.0..6.0);
            let p = [
                rng.random_range(-2.0..2.0) * z / 4.0,
                rng.random_range(-1.5..1.5) * z / 4.0,
                z,
            ]
            .map(|c| c * scale);
            let first = tracks.observations.len();
            for (v, (k, pose)) in views.iter().enumerate() {
                let (u, w) = k.project(pose.transform(p)).unwrap();
                tracks.observations.push(Observation {
                    point: i,
                    view: v as u32,
                    pixel: [
                        u + noise_px * gauss(&mut rng),
                        w + noise_px * gauss(&mut rng),
                    ],
                });
            }
            // The point where its noisy observations put it, as SfM's adjustment would.
            tracks
                .points
                .push(triangulate(&views, &tracks.observations[first..], p));
        }
        (views, tracks)
    }

    /// Gauss–Newton on the point's reprojection errors, poses fixed, from `start`.
    fn triangulate(views: &[(Intrinsics, Pose)], obs: &[Observation], start: [f64; 3]) -> [f64; 3] {
        let mut x = Vector3::from(start);
        for _ in 0..10 {
            let (mut h, mut g) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros());
            for o in obs {
                let (k, pose) = &views[o.view as usize];
                let (uv, a) = project(k, &(pose.rotation() * x + pose.translation())).unwrap();
                let j = a * pose.rotation();
                let r = nalgebra::Vector2::new(o.pixel[0] - uv[0], o.pixel[1] - uv[1]);
                h += j.transpose() * j;
                g += j.transpose() * r;
            }
            x += h.try_inverse().unwrap() * g;
        }
        x.into()
    }

    #[test]
    fn the_noise_per_degree_of_freedom_is_the_observations_noise() {
        for noise in [0.3, 1.0] {
            let (views, tracks) = synthetic(noise, 1.0, 3);
            let cov = pose_covariance(&views, &tracks);
            assert!(cov.is_determined(), "{:?}", cov.undetermined);
            assert_eq!((cov.observations, cov.points), (600, 200));
            let ratio = cov.reprojection_rms_px / noise;
            assert!((0.85..1.15).contains(&ratio), "{noise}: {ratio}");
        }
    }

    /// The angles scale with the noise and do not depend on the scene's unit (the gauge fixes
    /// the scale); a source farther from the reference has a better-known direction.
    #[test]
    fn pose_uncertainty_scales_with_the_noise_and_not_with_the_unit() {
        let (views, tracks) = synthetic(0.5, 1.0, 4);
        let base = pose_covariance(&views, &tracks);
        let (views2, tracks2) = synthetic(1.0, 1.0, 4);
        let noisier = pose_covariance(&views2, &tracks2);
        let (views3, tracks3) = synthetic(0.5, 7.0, 4);
        let scaled = pose_covariance(&views3, &tracks3);
        for s in 0..2 {
            let d = base.baseline_direction_std_deg[s];
            assert!(d > 0.0 && d < 5.0, "{d}");
            let twice = noisier.baseline_direction_std_deg[s] / d;
            assert!((1.7..2.3).contains(&twice), "{twice}");
            assert!((scaled.baseline_direction_std_deg[s] / d - 1.0).abs() < 1e-6);
            assert!((scaled.rotation_std_deg[s] / base.rotation_std_deg[s] - 1.0).abs() < 1e-6);
        }
    }

    /// Past the cap the points with the longest tracks are used, the first by index among
    /// equals.
    #[test]
    fn the_longest_tracks_are_used_up_to_the_cap() {
        let extra = 100;
        let (views, mut tracks) =
            synthetic_points(MAX_COVARIANCE_POINTS as u32 + extra, 0.5, 1.0, 8);
        // The first 150 points lose their third view.
        tracks
            .observations
            .retain(|o| !(o.point < 150 && o.view == 2));
        let cov = pose_covariance(&views, &tracks);
        assert!(cov.is_determined());
        assert_eq!(cov.points, MAX_COVARIANCE_POINTS);
        let two_view = 150 - extra as usize;
        assert_eq!(
            cov.observations,
            3 * (MAX_COVARIANCE_POINTS - two_view) + 2 * two_view
        );
        // Left out: the two-view points past the first `two_view` of them.
        assert!(cov
            .point_blocks
            .iter()
            .all(|b| !(two_view..150).contains(&b.point)));
    }

    #[test]
    fn points_seen_once_say_nothing_and_no_overlap_is_undetermined() {
        let (views, mut tracks) = synthetic(0.5, 1.0, 5);
        // Source 2 sees no point: its pose is free.
        tracks.observations.retain(|o| o.view != 2);
        let cov = pose_covariance(&views, &tracks);
        assert!(!cov.is_determined());
        assert!(cov.undetermined.unwrap().contains("unconstrained"));
        // Only the reference sees anything: no point is seen twice.
        tracks.observations.retain(|o| o.view == 0);
        let cov = pose_covariance(&views, &tracks);
        assert_eq!(cov.points, 0);
        assert!(!cov.is_determined());
    }

    #[test]
    fn bad_tracks_are_refused_naming_the_field() {
        let (_, tracks) = synthetic(0.5, 1.0, 6);
        let field = |t: &SfmTracks| match t.validate(3) {
            Err(MurkError::InvalidArgument { field, .. }) => field,
            other => panic!("{other:?}"),
        };
        let mut t = tracks.clone();
        t.observations[5].view = 3;
        assert_eq!(field(&t), "observations[5].view");
        let mut t = tracks.clone();
        t.observations[7].point = 200;
        assert_eq!(field(&t), "observations[7].point");
        let mut t = tracks.clone();
        t.observations[9].pixel[1] = f64::NAN;
        assert_eq!(field(&t), "observations[9].pixel");
        let mut t = tracks.clone();
        t.points[3][0] = f64::INFINITY;
        assert_eq!(field(&t), "points[3]");
        let mut t = tracks;
        t.seen_by = vec![1; 2];
        assert_eq!(field(&t), "seen_by");
    }

    fn walking_scene(seed: u64) -> MvsScene {
        let cfg = MvsSimConfig {
            seed,
            forward_motion: 0.5,
            airlight_range: [0.5, 1.0],
            median_transmission_range: [0.1, 0.4],
            ..MvsSimConfig::with_size(128, 96)
        };
        simulate_mvs(&cfg, &Monitor::noop()).unwrap()
    }

    fn priors(scene: &MvsScene) -> JointPriors {
        JointPriors {
            airlight: f64::from(scene.airlight),
            airlight_sigma: 0.05,
            gain_sigma: 0.2,
            beta_start: f64::from(scene.beta),
            falloff_sigma: FALLOFF_PRIOR_SIGMA,
            relative_falloff_sigma: 0.0,
        }
    }

    /// On the simulator's model the observations are the true points' projections and the
    /// points carry a little noise: the poses are well known and their share is small. A
    /// cancelled job gets no share but `Cancelled`.
    #[test]
    fn sound_poses_add_little() {
        let scene = walking_scene(11);
        let (reference, sources) = scene.reference_and_sources();
        let tracks = scene.sfm_tracks(sources.len()).unwrap();
        let sparse = scene.sparse_depth().unwrap();
        let fit = fit_joint_samples(
            &blurred_ratio_samples(&reference, &sources, &sparse),
            &sparse,
            &priors(&scene),
        )
        .unwrap();
        let pe = pose_error_of_fit(&reference, &sources, &tracks, &fit, &Monitor::noop()).unwrap();
        assert!(pe.undetermined.is_none(), "{pe:?}");
        let b = pe.beta_std_error.unwrap();
        assert!(
            b < 0.5 * fit.beta_std_error,
            "{b} against {}",
            fit.beta_std_error
        );
        assert!(pe.max_baseline_direction_std_deg < 2.0, "{pe:?}");
        // A cancelled job stops the refits and says so.
        let cancelled = Monitor::new(std::sync::Arc::new(true.into()), None);
        assert_eq!(
            pose_error_of_fit(&reference, &sources, &tracks, &fit, &cancelled),
            Err(MurkError::Cancelled)
        );
    }

    /// Models as SfM would return them from observations with 3 px of noise: poses drawn
    /// from the covariance those observations give, the points moved with them. β of each is
    /// compared with the truth: within two of the fit's own standard errors on too few of
    /// them, within two of the errors with the poses' share on nearly all.
    #[test]
    fn models_with_perturbed_poses_are_covered_once_the_poses_share_is_added() {
        let scene = walking_scene(11);
        let (reference, sources) = scene.reference_and_sources();
        let mut tracks = scene.sfm_tracks(sources.len()).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut gauss = || {
            let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        for o in &mut tracks.observations {
            o.pixel[0] += 3.0 * gauss();
            o.pixel[1] += 3.0 * gauss();
        }
        let cov = pose_covariance(&cameras(&reference, &sources), &tracks);
        assert!(
            cov.is_determined() && cov.reprojection_rms_px > 2.5,
            "{cov:?}"
        );
        let truth = f64::from(scene.beta);
        let (mut own, mut with_poses) = (0, 0);
        let draws = 16;
        for _ in 0..draws {
            let mut d = DVector::<f64>::zeros(cov.directions[0].len());
            for dir in &cov.directions {
                d += dir * gauss();
            }
            let (moved, sparse) = cov.moved_views(&reference, &sources, &tracks, &d).unwrap();
            let fit = fit_joint_samples(
                &blurred_ratio_samples(&reference, &moved, &sparse),
                &sparse,
                &priors(&scene),
            )
            .unwrap();
            let pe =
                pose_error_of_fit(&reference, &moved, &tracks, &fit, &Monitor::noop()).unwrap();
            let miss = (fit.beta - truth).abs();
            own += usize::from(miss <= 2.0 * fit.beta_std_error);
            let total = fit.beta_std_error.hypot(pe.beta_std_error.unwrap());
            with_poses += usize::from(miss <= 2.0 * total);
        }
        assert!(with_poses >= draws - 1, "{with_poses} of {draws} covered");
        assert!(
            own + 4 <= with_poses,
            "own errors cover {own}, with the poses {with_poses}"
        );
    }
}
