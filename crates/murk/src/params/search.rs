//! Algorithm 1 of the reference (§3.3.3–3.3.4): grid search for the airlight `A` and the
//! scattering coefficient `β` (per scene unit) that make the dense dehazing-cost-volume depth
//! `z_{A,β} = F(A, β)` agree with the sparse SfM depth (Eq. 3.8, residual ρ of Eq. 3.9).
//!
//! 1. `β₀ = argmin_β` over `beta_steps` values in `[β_min, β_max]` with `A = A₀` (Eq. 3.10),
//!    `A₀` from an airlight estimator — or, murk's default when the data pin them down, `A` and
//!    β fitted jointly to the SfM points' intensities with a gain per source
//!    ([`crate::params::joint_fit`], `A₀` as a prior), else β₀ from the points' transmission
//!    ratios at `A₀` ([`crate::params::point_ratio`]): the classical depth function barely
//!    depends on β (docs/scattering-params.md), the points do;
//! 2. `A*, β* = argmin` over a `grid_steps × grid_steps` grid uniform in
//!    `[A₀ − Δ_A, A₀ + Δ_A] × [β₀ − Δ_β, β₀ + Δ_β]` (clamped to `A ∈ (0, 1]`, `β ≥ 0`); the
//!    step-1 evaluation at `(A₀, β₀)` lies in that box and stays a candidate.
//!
//! **Units.** β is per scene unit, and a COLMAP model's unit is arbitrary, so no fixed β range
//! suits every model. Unless the caller gives one, `[β_min, β_max]` is the range that keeps the
//! median SfM point's transmission within [0.02, 0.98] ([`beta_range_from_points`]); the sweep
//! is then geometric. An estimate outside the range is clamped *and reported*
//! ([`ScatteringEstimate::beta_bound`]), and [`ScatteringEstimate::identifiability`] says whether
//! the data determine β at all (a rectified pair does not).
//!
//! The reference's settings are 10 steps, a 4×4 grid, `Δ_A = Δ_β = 0.05`, `δ = 5` px (26 depth
//! evaluations); all are parameters. Two deviations in murk's defaults, both measured
//! (docs/scattering-params.md): `Δ_A = 0` — with the classical depth function the residual
//! prefers larger `A` systematically (the argmin sat at `A₀ + Δ_A` on 9 of 10 scenes, turning the CNN's
//! MAE_A of 0.008 into 0.039), so `A* = A₀` and step 2 is a 1×4 refinement of β (14
//! evaluations); and a step-2 point replaces `(A₀, β₀)` only if its residual is lower by
//! `min_improvement_t` (3) standard errors of the paired per-point difference (0 = plain argmin). **Speed**: the depth function during the search runs on the images
//! box-downsampled by `search_downsample` (intrinsics and SfM pixels scaled to match, `δ`
//! divided) with `search_planes` planes: the residual is read at a few thousand SfM pixels, so the
//! full resolution buys little there; the caller computes the final depth `z* = F(A*, β*)` at full
//! resolution.
//!
//! **When the points and the estimator disagree on `A`.** The joint fit lets the points override
//! `A₀`, which is right when the estimator is off and wrong when the SfM model is: a model whose
//! translation directions are tens of degrees off still reprojects within a pixel, but it distorts
//! the points' depth differences, and the fit then moves `A` (by 0.10 and 0.24 on two of ten
//! COLMAP models of forward-moving scenes, docs/scattering-params.md). When `A*` and `A₀`
//! differ by more than [`AIRLIGHT_CONFLICT_SIGMAS`] of their combined uncertainty (the estimator's typical
//! error, `airlight_initial_error`, and the fit's standard error), the estimate is reported as
//! not identifiable ([`Identifiability::AirlightConflict`], [`AirlightConflict`]). Neither value is
//! substituted: which one is wrong cannot be told from these data (holding `A` at `A₀` and
//! letting Eq. 3.9 arbitrate fixed `A` on one such COLMAP model and made β worse on it, and
//! preferred the fit on the other).

use std::time::Instant;

use crate::atmosphere::AtmosphereParams;
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::{estimate_depth, CostKind, DehazingOptions, DepthParams, PlaneSet, View};
use crate::params::joint_fit::{
    fit_joint_samples, Identifiability, JointFit, JointPriors, MAX_RELATIVE_BETA_ERROR,
    MIN_EQUATIONS, MIN_POINTS,
};
use crate::params::point_ratio::{beta_from_ratio_samples, blurred_ratio_samples, PointRatioFit};
use crate::params::pose_error::{pose_error_of_fit, PoseError, SfmTracks};
use crate::params::relief::Relief;
use crate::params::residual::{paired_improvement_t, sparse_residuals};
use crate::params::sampling_share::{sampling_share, SamplingShare};
use crate::params::sparse::{SparseDepth, SparseSample};

/// Fewest SfM pixels in the reference view the search accepts: below this the residual of
/// Eq. 3.8 is decided by a handful of points (and their outliers).
pub const MIN_SPARSE_POINTS: usize = 10;
/// Most values along one axis of either search stage.
pub const MAX_GRID_STEPS: usize = 64;

/// Transmission range of the median SfM point that [`beta_range_from_points`] allows.
pub const POINT_TRANSMISSION_RANGE: [f64; 2] = [0.02, 0.98];
/// Default scale of the Cauchy prior on `A` around the estimator's `A₀` in the joint fit: about
/// the CNN's error in dense haze (MAE 0.009–0.017 at median transmission below 0.5,
/// docs/airlight.md), while the heavy tail lets the points override an `A₀` that is far off
/// (with `A₀` shifted by ±0.06, the held-out scenes of docs/scattering-params.md keep their
/// accuracy).
pub const AIRLIGHT_PRIOR_SIGMA: f32 = 0.015;
/// The joint fit's `A*` conflicts with the estimator's `A₀` when `|A* − A₀|` exceeds this many
/// `√(σ₀² + se(A*)²)`, `σ₀` being the estimator's typical error
/// ([`SearchParams::airlight_initial_error`]).
pub const AIRLIGHT_CONFLICT_SIGMAS: f64 = 3.0;
/// Typical error (≈ 1.25 × MAE) of the airlight CNN on held-out varied scenes (MAE 0.022,
/// docs/airlight.md): the default [`SearchParams::airlight_initial_error`].
pub const CNN_AIRLIGHT_ERROR: f32 = 0.03;
/// Typical error of the dark-channel airlight on the same held-out scenes (MAE 0.090).
pub const DARK_CHANNEL_AIRLIGHT_ERROR: f32 = 0.11;

/// Settings of [`search_scattering`]. Lengths in scene units, `β` per scene unit.
#[derive(Clone, Debug, PartialEq)]
pub struct SearchParams {
    /// Lower end of the β range, `≥ 0`; `None` = from the SfM points
    /// ([`beta_range_from_points`]).
    pub beta_min: Option<f32>,
    /// Upper end of the β range, `> beta_min`; `None` = from the SfM points.
    pub beta_max: Option<f32>,
    /// Values of β in step 1, `1..=MAX_GRID_STEPS` (reference: 10).
    pub beta_steps: usize,
    /// Values per axis of the step-2 grid, `1..=MAX_GRID_STEPS` (reference: 4).
    pub grid_steps: usize,
    /// Half-width of the step-2 airlight range, `≥ 0` (reference: 0.05; murk's default 0: with
    /// the classical depth function the residual is biased towards larger `A` and the grid made
    /// the CNN's `A₀` worse, MAE 0.008 → 0.034, see docs/scattering-params.md). With 0 the grid
    /// has one airlight, `A₀`, and `grid_steps` values of β.
    pub delta_airlight: f32,
    /// Half-width of the step-2 β range, `≥ 0`, per scene unit (reference: 0.05); `None` = 10 %
    /// of β₀ (unit-free).
    pub delta_beta: Option<f32>,
    /// δ of Eq. 3.9, pixels at full resolution, `≤ 64` (reference: 5).
    pub delta_px: usize,
    /// Box-downsampling factor of the images during the search, `1..=8`.
    pub search_downsample: usize,
    /// Planes of the depth function during the search (the caller's plane range), `2..=1024`.
    pub search_planes: usize,
    /// Dehazing cost-volume options of the depth function.
    pub cost: DehazingOptions,
    /// Parameters of the depth function (the API's `sgm` options).
    pub depth: DepthParams,
    /// Step 2 replaces `(A₀, β₀)` only by a grid point whose residual is lower by at least this
    /// many standard errors (paired t over the SfM pixels, [`paired_improvement_t`]); 0 = the
    /// plain argmin of the published algorithm. Finite, `≥ 0`.
    pub min_improvement_t: f64,
    /// Step 1 takes β₀ from the SfM points' transmission ratios
    /// ([`crate::params::point_ratio`]) when that fit is reliable, clamped to
    /// `[beta_min, beta_max]`, and evaluates only `(A₀, β₀)`; otherwise (and with `false`, the
    /// published algorithm) it sweeps Eq. 3.10. With β₀ from the points step 2 keeps β and
    /// searches A only (nothing with `delta_airlight` 0).
    pub beta_from_points: bool,
    /// Step 1 takes `A` and β from the joint fit of the points' intensities
    /// ([`crate::params::joint_fit`]) when it converged with a finite standard error (β then
    /// counts as identifiable only when that error is below 15 % of β), and step 2 is skipped
    /// (the fit has placed `A` already). The fit always runs, for the identifiability verdict.
    pub joint_fit: bool,
    /// Scale of the joint fit's Cauchy prior on `A` around `A₀`, in (0, 1].
    pub airlight_prior_sigma: f32,
    /// Typical error of the estimator's `A₀`, in (0, 1]: a joint fit whose `A` lies more than
    /// [`AIRLIGHT_CONFLICT_SIGMAS`] of it (with the fit's own error) away is reported as an
    /// [`AirlightConflict`]. [`CNN_AIRLIGHT_ERROR`] by default.
    pub airlight_initial_error: f32,
}

impl Default for SearchParams {
    fn default() -> Self {
        Self {
            beta_min: None,
            beta_max: None,
            beta_steps: 10,
            grid_steps: 4,
            delta_airlight: 0.0,
            delta_beta: None,
            delta_px: 5,
            search_downsample: 2,
            search_planes: 64,
            cost: DehazingOptions::default(),
            depth: DepthParams::default(),
            min_improvement_t: 3.0,
            beta_from_points: true,
            joint_fit: true,
            airlight_prior_sigma: AIRLIGHT_PRIOR_SIGMA,
            airlight_initial_error: CNN_AIRLIGHT_ERROR,
        }
    }
}

/// Largest β end a search accepts, per scene unit: beyond it transmission vanishes within 1e-6
/// units, whatever the scene's scale, and the search's geometric grid loses f32 precision.
pub const MAX_BETA_PER_UNIT: f32 = 1e6;

impl SearchParams {
    /// Fails naming the first bad field.
    pub fn validate(&self) -> Result<()> {
        let bad = |f: &str, r: String| Err(MurkError::invalid(f, r));
        if let Some(lo) = self.beta_min {
            if !lo.is_finite() || lo < 0.0 {
                return bad("beta_min", format!("must be finite and >= 0, got {lo}"));
            }
        }
        if let Some(hi) = self.beta_max {
            if !hi.is_finite() || hi <= 0.0 {
                return bad("beta_max", format!("must be finite and > 0, got {hi}"));
            }
            if hi > MAX_BETA_PER_UNIT {
                return bad(
                    "beta_max",
                    format!(
                        "{hi} per scene unit is above {MAX_BETA_PER_UNIT:e}: the medium would be \
                         opaque within a millionth of a unit"
                    ),
                );
            }
            if let Some(lo) = self.beta_min.filter(|&lo| hi <= lo) {
                return bad(
                    "beta_max",
                    format!("must be > beta_min ({lo}), got {hi} (the β range is empty)"),
                );
            }
        }
        for (f, v) in [
            ("airlight_prior_sigma", self.airlight_prior_sigma),
            ("airlight_initial_error", self.airlight_initial_error),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 1.0) {
                return bad(f, format!("must be in (0, 1], got {v}"));
            }
        }
        for (f, v) in [
            ("beta_steps", self.beta_steps),
            ("grid_steps", self.grid_steps),
        ] {
            if !(1..=MAX_GRID_STEPS).contains(&v) {
                return bad(f, format!("must be in 1..={MAX_GRID_STEPS}, got {v}"));
            }
        }
        for (f, v) in [
            ("delta_airlight", self.delta_airlight),
            ("delta_beta", self.delta_beta.unwrap_or(0.0)),
        ] {
            if !v.is_finite() || !(0.0..=1.0).contains(&v) {
                return bad(f, format!("must be in [0, 1], got {v}"));
            }
        }
        if self.delta_px > 64 {
            return bad(
                "delta_px",
                format!("must be <= 64 pixels, got {}", self.delta_px),
            );
        }
        if !(1..=8).contains(&self.search_downsample) {
            return bad(
                "search_downsample",
                format!("must be in 1..=8, got {}", self.search_downsample),
            );
        }
        if !(2..=crate::mvs::MAX_PLANES).contains(&self.search_planes) {
            return bad(
                "search_planes",
                format!(
                    "must be in 2..={}, got {}",
                    crate::mvs::MAX_PLANES,
                    self.search_planes
                ),
            );
        }
        if !self.min_improvement_t.is_finite() || self.min_improvement_t < 0.0 {
            return bad(
                "min_improvement_t",
                format!("must be finite and >= 0, got {}", self.min_improvement_t),
            );
        }
        self.depth.validate().map_err(|e| e.within("sgm"))
    }

    /// Most depth evaluations of a search: `beta_steps + grid_steps²`, or
    /// `beta_steps + grid_steps` when `delta_airlight` is 0 (step 1 is one evaluation instead
    /// of `beta_steps` when β₀ comes from the points).
    pub fn evaluations(&self) -> usize {
        self.beta_steps + self.airlight_steps() * self.grid_steps
    }

    fn airlight_steps(&self) -> usize {
        if self.delta_airlight == 0.0 {
            1
        } else {
            self.grid_steps
        }
    }
}

/// Which step of Algorithm 1 an evaluation belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SearchStage {
    /// Step 1: β alone, `A = A₀` (Eq. 3.10).
    Beta,
    /// Step 2: the `A × β` grid around `(A₀, β₀)`.
    Joint,
}

/// One evaluation of the objective.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridEvaluation {
    /// The step it belongs to.
    pub stage: SearchStage,
    /// Airlight evaluated.
    pub airlight: f32,
    /// β evaluated, per scene unit.
    pub beta: f32,
    /// Mean Eq. 3.9 residual over the SfM pixels, scene units.
    pub residual: f64,
}

/// Where β* came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BetaSource {
    /// The joint fit of `A`, β and the source gains to the points' intensities.
    JointFit,
    /// The points' transmission ratios at `A₀`.
    PointRatio,
    /// The sweep of Eq. 3.10 (and step 2's grid) over the depth residual.
    Sweep,
}

/// The joint fit's `A` disagreed with the estimator's `A₀` by more than
/// [`AIRLIGHT_CONFLICT_SIGMAS`] (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AirlightConflict {
    /// `A` of the joint fit (the estimate's `A*`).
    pub fitted_airlight: f64,
    /// Its standard error.
    pub fitted_airlight_std_error: f64,
    /// The estimator's `A₀`.
    pub airlight_initial: f64,
    /// The estimator's typical error used in the test.
    pub airlight_initial_error: f64,
    /// `|A_fit − A₀| / √(σ₀² + se²)`.
    pub sigmas: f64,
}

impl AirlightConflict {
    /// The test of the module docs on a joint fit; `None` when the two agree.
    pub fn test(
        fit: &JointFit,
        airlight_initial: f64,
        airlight_initial_error: f64,
    ) -> Option<Self> {
        let spread = (airlight_initial_error.powi(2) + fit.airlight_std_error.powi(2)).sqrt();
        let sigmas = (fit.airlight - airlight_initial).abs() / spread;
        (sigmas > AIRLIGHT_CONFLICT_SIGMAS).then_some(Self {
            fitted_airlight: fit.airlight,
            fitted_airlight_std_error: fit.airlight_std_error,
            airlight_initial,
            airlight_initial_error,
            sigmas,
        })
    }

    /// One sentence for a user: the two values and what to check.
    pub fn describe(&self) -> String {
        format!(
            "the SfM points' intensities give A = {:.3} ± {:.3}, but the image's airlight \
             estimate is A0 = {:.3} (typical error {:.3}; {:.1} sigma apart). A wrong SfM model \
             (translation directions that are off distort the points' depth differences) or an \
             airlight estimator outside its range causes this: A* is not reliable, and beta* may \
             not be either; check the model's poses",
            self.fitted_airlight,
            self.fitted_airlight_std_error,
            self.airlight_initial,
            self.airlight_initial_error,
            self.sigmas
        )
    }
}

/// Which end of the β range an estimate was clamped to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BetaBound {
    /// `beta_min`.
    Min,
    /// `beta_max`.
    Max,
}

/// What the SfM model gives [`search_scattering`]: the sparse map of Eq. 3.8 and, when known,
/// the points' tracks, whose observations add the poses' share to the standard errors
/// ([`crate::params::pose_error`]).
#[derive(Clone, Copy, Debug)]
pub struct SfmEvidence<'a> {
    /// `z_sfm` and `m` of Eq. 3.8 in the reference view.
    pub sparse: &'a SparseDepth,
    /// The points with their observations in the reference and the sources; `None` takes the
    /// poses as exact.
    pub tracks: Option<&'a SfmTracks>,
}

impl<'a> SfmEvidence<'a> {
    /// The sparse map alone: the poses taken as exact.
    pub fn map(sparse: &'a SparseDepth) -> Self {
        Self {
            sparse,
            tracks: None,
        }
    }
}

/// Result of [`search_scattering`].
#[derive(Clone, Debug, PartialEq)]
pub struct ScatteringEstimate {
    /// `A*`.
    pub airlight: f32,
    /// `β*`, per scene unit.
    pub beta: f32,
    /// `A₀`, the airlight estimator's value.
    pub airlight_initial: f32,
    /// `β₀` of step 1.
    pub beta_initial: f32,
    /// Standard error of `A*`: from the joint fit when `A*` came from it, `None` when `A*` is the
    /// estimator's value or a grid point (no error model).
    pub airlight_std_error: Option<f64>,
    /// Standard error of `β*` per scene unit, from the fit it came from; `None` after the sweep.
    pub beta_std_error: Option<f64>,
    /// Which estimate `β*` is.
    pub beta_source: BetaSource,
    /// Whether the SfM points determine β (and with the joint fit `A`), and if not why. After a
    /// sweep this is the joint fit's verdict: the depth residual alone does not pin β down
    /// (docs/scattering-params.md), so a swept β is reported as not identifiable.
    pub identifiability: Identifiability,
    /// The β range used, per scene unit.
    pub beta_range: [f32; 2],
    /// Whether an end of the range came from the points ([`beta_range_from_points`]).
    pub beta_range_from_points: bool,
    /// The bound `β*` sits on when the estimate fell outside the range (or, after a sweep, its
    /// minimum lay at an end): the true minimum may lie beyond it.
    pub beta_bound: Option<BetaBound>,
    /// The estimate before clamping to the range, per scene unit.
    pub beta_unclamped: f32,
    /// The joint fit (always run, used when `joint_fit` is set and it determines β). With the
    /// model's tracks its standard errors include the poses' share ([`Self::pose_error`]).
    pub joint: Option<JointFit>,
    /// The SfM poses' share of the joint fit's standard errors, when the search was given the
    /// model's tracks and the fit determined β with a finite error.
    pub pose_error: Option<PoseError>,
    /// The share of the joint fit's standard errors that comes from where SfM put its points
    /// ([`crate::params::sampling_share`]), when the fit determined β with a finite error.
    pub sampling: Option<SamplingShare>,
    /// How far the SfM points stand out of one plane in the reference (`None` with too few
    /// points). A flat cloud facing the reference ([`Relief::is_ambiguous`]) makes an
    /// identifiable fit [`Identifiability::WeakSfm`]: SfM's poses may be wrong there with small
    /// errors.
    pub relief: Option<Relief>,
    /// Set when the joint fit's `A*` conflicted with `A₀` (see the module docs); an estimate the
    /// fit called identifiable is then reported as [`Identifiability::AirlightConflict`] (one it
    /// did not keeps its own reason).
    pub airlight_conflict: Option<AirlightConflict>,
    /// The points' transmission-ratio fit when step 1 tried it (reliable or not); β₀ came from
    /// it when [`PointRatioFit::is_reliable`] and the joint fit was not used.
    pub point_ratio: Option<PointRatioFit>,
    /// Mean Eq. 3.9 residual at `(A*, β*)`, scene units.
    pub residual: f64,
    /// Every evaluation in order (step 1 then step 2), e.g. to plot the curve of Fig. 3.7c.
    pub grid: Vec<GridEvaluation>,
    /// SfM pixels used (at the search resolution).
    pub num_sparse_points: usize,
    /// Wall time of the search, seconds.
    pub seconds: f64,
}

impl ScatteringEstimate {
    /// Sentences for the user about the estimate, with the numbers behind them: the airlight
    /// conflict, and when the points do not determine β, why and what would help.
    pub fn warnings(&self) -> Vec<String> {
        let mut out: Vec<String> = self
            .airlight_conflict
            .iter()
            .map(AirlightConflict::describe)
            .collect();
        // The reasons are the joint fit's own verdict, given only when the estimate is not
        // identifiable (a swept β after a fit the caller turned off has no reason of the fit's).
        let Some(j) = self
            .joint
            .as_ref()
            .filter(|_| self.identifiability != Identifiability::Identifiable)
        else {
            return out;
        };
        match j.identifiability {
            Identifiability::TooFewPoints => out.push(format!(
                "the SfM model gives {} usable equations from {} points seen by the reference and \
                 its sources (at least {} and {} are needed): more frames of the scene, or a lower \
                 SIFT peak threshold, give SfM more points",
                j.equations, j.points, MIN_EQUATIONS, MIN_POINTS
            )),
            Identifiability::FlatResidual if j.beta_std_error.is_finite() && j.beta > 0.0 => out
                .push(format!(
                    "the SfM points fit beta = {:.4} with a standard error of {:.0} % (identifiable \
                     below {:.0} %) from {} points at an RMS depth difference of {:.3} between the \
                     views: frames that move towards or away from the scene, a longer baseline, or \
                     more points (a lower SIFT peak threshold) help",
                    j.beta,
                    100.0 * j.beta_std_error / j.beta,
                    100.0 * MAX_RELATIVE_BETA_ERROR,
                    j.points,
                    j.rms_depth_difference
                )),
            // The SfM input's part of the verdict (JointFit::add_sfm_share): a share that could
            // not be computed, and when the shares took β's error past the limit, the larger of
            // them. A flat cloud's part is said below, as for any verdict.
            Identifiability::WeakSfm => {
                let pose_b = self.pose_error.as_ref().and_then(|p| p.beta_std_error);
                let sampling_b = self.sampling.and_then(|s| s.share).map(|s| s[1]);
                let too_wide = !j.beta_is_determined();
                let larger = |own: Option<f64>, other: Option<f64>| {
                    too_wide && own.is_some_and(|b| b >= other.unwrap_or(0.0))
                };
                out.extend(
                    self.pose_error
                        .as_ref()
                        .filter(|p| p.undetermined.is_some() || larger(pose_b, sampling_b))
                        .map(|p| weak_sfm_warning(j, p)),
                );
                out.extend(
                    self.sampling
                        .filter(|s| s.share.is_none() || larger(sampling_b, pose_b))
                        .map(|s| s.describe(j)),
                );
            }
            Identifiability::NoDepthDifference => out.push(format!(
                "the views see the points at the same depths (RMS depth difference {:.2e}): \
                 a rectified pair or a purely sideways move cannot tell beta; frames that move \
                 towards or away from the scene can",
                j.rms_depth_difference
            )),
            Identifiability::AirlightAtBound => out.push(format!(
                "the points' intensities put A at the bound of its range ({:.3}): the best fit \
                 lies beyond it, so A* and beta* are not reliable and their standard errors do \
                 not hold; check that the images are linear light (--srgb for sRGB-encoded \
                 images) and that the haze is not clipped",
                j.airlight
            )),
            _ => {}
        }
        // A flat cloud makes an identifiable fit weak_sfm (JointFit::check_relief) and casts
        // the same doubt on any other verdict.
        out.extend(
            self.relief
                .filter(Relief::is_ambiguous)
                .map(|r| r.describe()),
        );
        out
    }
}

/// The [`Identifiability::WeakSfm`] sentence: how uncertain the poses are, what that does to
/// β, and what would help.
fn weak_sfm_warning(j: &JointFit, p: &PoseError) -> String {
    let poses = format!(
        "{} observations of {} points in the views place the sources to within {:.2} degrees of \
         rotation and {:.1} degrees of baseline direction (1 sigma; reprojection error {:.2} px)",
        p.observations,
        p.points,
        p.max_rotation_std_deg,
        p.max_baseline_direction_std_deg,
        p.reprojection_rms_px
    );
    let effect = match (&p.undetermined, p.beta_std_error) {
        (Some(why), _) => format!("the poses' effect on beta is unknown: {why}"),
        (None, Some(b)) => format!(
            "with them beta = {:.4} has a standard error of {:.0} % (identifiable below {:.0} %; \
             {:.0} % from the poses alone)",
            j.beta,
            100.0 * j.beta_std_error / j.beta,
            100.0 * MAX_RELATIVE_BETA_ERROR,
            100.0 * b / j.beta
        ),
        (None, None) => String::new(),
    };
    format!(
        "the SfM poses are too uncertain for beta: {poses}; {effect}. More frames, a longer \
         baseline, or more points (a lower SIFT peak threshold) help"
    )
}

/// `n` values uniform in `[lo, hi]` (the midpoint when `n = 1`).
fn linspace(lo: f32, hi: f32, n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![0.5 * (lo + hi)];
    }
    (0..n)
        .map(|i| lo + (hi - lo) * i as f32 / (n - 1) as f32)
        .collect()
}

/// `n` values in geometric progression from `lo` to `hi` (both > 0).
fn geomspace(lo: f32, hi: f32, n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![(lo * hi).sqrt()];
    }
    let r = f64::from(hi / lo);
    (0..n)
        .map(|i| lo * r.powf(i as f64 / (n - 1) as f64) as f32)
        .collect()
}

/// The β range, per scene unit, within which the median SfM point's transmission lies in
/// [`POINT_TRANSMISSION_RANGE`]: `[−ln 0.98, −ln 0.02] / z_med`. It scales with the model's
/// unit, so a COLMAP model in any unit gets a sensible range (the reference's fixed [0.4, 0.8]
/// is for metric indoor scenes). `None` without points.
pub fn beta_range_from_points(sparse: &SparseDepth) -> Option<[f32; 2]> {
    let z = f64::from(sparse.depth_quantile(0.5)?);
    (z > 0.0).then(|| {
        let [t_lo, t_hi] = POINT_TRANSMISSION_RANGE;
        [(-t_hi.ln() / z) as f32, (-t_lo.ln() / z) as f32]
    })
}

/// Mean over `f×f` blocks (the image cropped to a multiple of `f`).
fn box_downsample(img: &ImageF32, f: usize) -> ImageF32 {
    let (w, h, c) = (img.width() / f, img.height() / f, img.channels());
    let mut out = vec![0.0f32; w * h * c];
    let norm = 1.0 / (f * f) as f32;
    for y in 0..h {
        for x in 0..w {
            for ch in 0..c {
                let mut s = 0.0;
                for dy in 0..f {
                    for dx in 0..f {
                        s += img.get(x * f + dx, y * f + dy, ch);
                    }
                }
                out[(y * w + x) * c + ch] = s * norm;
            }
        }
    }
    ImageF32::from_vec(w, h, c, out).expect("non-empty: checked by the caller")
}

/// The β range of a search: the caller's ends, the missing ones from the points. Errors name
/// `params.beta_min`/`params.beta_max` when a given end leaves the range empty.
fn resolve_beta_range(params: &SearchParams, sparse: &SparseDepth) -> Result<([f32; 2], bool)> {
    let derived = beta_range_from_points(sparse);
    let from_points = params.beta_min.is_none() || params.beta_max.is_none();
    let [d_lo, d_hi] = derived.unwrap_or([0.0, f32::INFINITY]);
    let lo = params.beta_min.unwrap_or(d_lo);
    let hi = params.beta_max.unwrap_or(d_hi);
    if !(hi > lo && hi.is_finite()) {
        let field = if params.beta_min.is_some() {
            "params.beta_min"
        } else {
            "params.beta_max"
        };
        return Err(MurkError::invalid(
            field,
            format!(
                "leaves an empty β range [{lo}, {hi}] per scene unit with the end taken from the \
                 SfM points ([{d_lo:.4}, {d_hi:.4}], median point transmission 0.98 to 0.02); \
                 give both ends"
            ),
        ));
    }
    Ok(([lo, hi], from_points))
}

/// Runs Algorithm 1 (see the module docs) from the initial airlight `airlight_initial` over the
/// plane range of `planes` (its count is replaced by `params.search_planes`). Errors name
/// `params.…` fields, `airlight_initial`, `sparse_points` (fewer than [`MIN_SPARSE_POINTS`]
/// SfM pixels, or a map of another size than the reference), and those of the depth function;
/// cancellation returns `Cancelled`. Progress is reported after every evaluation.
pub fn search_scattering(
    reference: &View<'_>,
    sources: &[View<'_>],
    sfm: SfmEvidence<'_>,
    airlight_initial: f32,
    planes: &PlaneSet,
    params: &SearchParams,
    monitor: &Monitor,
) -> Result<ScatteringEstimate> {
    let start = Instant::now();
    let SfmEvidence { sparse, tracks } = sfm;
    params.validate().map_err(|e| e.within("params"))?;
    if !(airlight_initial.is_finite() && airlight_initial > 0.0 && airlight_initial <= 1.0) {
        return Err(MurkError::invalid(
            "airlight_initial",
            format!("must be in (0, 1], got {airlight_initial}"),
        ));
    }
    if (sparse.width(), sparse.height()) != reference.image.dims() {
        return Err(MurkError::invalid(
            "sparse_points",
            format!(
                "sparse depth is {}x{} but the reference image is {}x{}",
                sparse.width(),
                sparse.height(),
                reference.image.width(),
                reference.image.height()
            ),
        ));
    }
    let f = params.search_downsample;
    let (w, h) = reference.image.dims();
    if w / f < 8 || h / f < 8 {
        return Err(MurkError::invalid(
            "params.search_downsample",
            format!("{w}x{h} downsampled by {f} leaves fewer than 8x8 pixels"),
        ));
    }
    // Search-resolution views and sparse map.
    let scaled = |v: &View<'_>| (box_downsample(v.image, f), v.intrinsics.box_downsampled(f));
    let ref_small = scaled(reference);
    let src_small: Vec<(ImageF32, Intrinsics)> = sources.iter().map(scaled).collect();
    let sparse_small = sparse.downsampled(f);
    if sparse_small.len() < MIN_SPARSE_POINTS {
        return Err(MurkError::invalid(
            "sparse_points",
            format!(
                "{} SfM points are visible in the reference view ({} distinct pixels at the \
                 search resolution); at least {MIN_SPARSE_POINTS} are needed",
                sparse.len(),
                sparse_small.len()
            ),
        ));
    }
    if let Some(t) = tracks {
        t.validate(1 + sources.len())
            .map_err(|e| e.within("tracks"))?;
    }
    let ([beta_lo, beta_hi], beta_range_from_points) = resolve_beta_range(params, sparse)?;
    let reference_view = View {
        image: &ref_small.0,
        intrinsics: ref_small.1,
        pose: reference.pose,
    };
    let source_views: Vec<View<'_>> = src_small
        .iter()
        .zip(sources)
        .map(|((img, k), v)| View {
            image: img,
            intrinsics: *k,
            pose: v.pose,
        })
        .collect();
    let search_planes = PlaneSet::new(planes.near, planes.far, params.search_planes)
        .map_err(|e| e.within("planes"))?;
    let delta = (params.delta_px as f64 / f as f64).round() as usize;
    // Step 1 from the points, at full resolution (the equations need the images' own pixels).
    // The joint fit always runs: its verdict says whether the data determine β at all.
    // The blurred samples are taken once, for the joint fit and the point-ratio fallback.
    let samples = blurred_ratio_samples(reference, sources, sparse);
    let priors = JointPriors {
        airlight: f64::from(airlight_initial),
        airlight_sigma: f64::from(params.airlight_prior_sigma),
        gain_sigma: 0.2,
        beta_start: f64::from((beta_lo.max(1e-6) * beta_hi).sqrt()),
        falloff_sigma: crate::params::joint_fit::FALLOFF_PRIOR_SIGMA,
        relative_falloff_sigma: crate::params::joint_fit::RELATIVE_FALLOFF_PRIOR_SIGMA,
    };
    let mut joint = fit_joint_samples(&samples, sparse, &priors);
    // The SfM input's shares of the fit's errors, both computed from the fit as it came out and
    // added in quadrature (neither depends on the images' noise): where SfM put its points, and
    // where the model's tracks say how well SfM placed the poses, the poses.
    let takes_shares = joint.as_ref().is_some_and(JointFit::takes_sfm_shares);
    let sampling = match joint.as_ref() {
        Some(j) if takes_shares => {
            monitor.checkpoint()?;
            Some(sampling_share(reference, sources, sparse, j))
        }
        _ => None,
    };
    let pose_error = match (tracks, joint.as_ref()) {
        (Some(t), Some(j)) if takes_shares => {
            monitor.checkpoint()?;
            Some(pose_error_of_fit(reference, sources, t, j, monitor)?)
        }
        _ => None,
    };
    if let Some(j) = joint.as_mut() {
        if let Some(s) = &sampling {
            j.add_sfm_share(s.share);
        }
        if let Some(pe) = &pose_error {
            j.add_sfm_share(pe.share());
        }
    }
    // A flat point cloud facing the reference hides wrong poses behind small errors (see
    // crate::params::relief): the fit's own errors cannot cover them.
    let relief = Relief::of(sparse, &reference.intrinsics);
    if let Some(j) = joint.as_mut() {
        j.check_relief(relief.as_ref());
    }
    // The joint fit's estimate is used whenever it converged with a finite standard error,
    // also when that error is too large to call β identifiable: it is still the data's best
    // estimate (on 20 held-out lateral scenes the one flat case erred by 0.07 with it and by 0.22
    // with the sweep, whose depth residual barely depends on β). The verdict says how far to
    // trust it.
    let from_joint = joint
        .as_ref()
        .filter(|j| {
            params.joint_fit
                && j.beta > 0.0
                && j.beta_std_error.is_finite()
                && matches!(
                    j.identifiability,
                    Identifiability::Identifiable
                        | Identifiability::FlatResidual
                        | Identifiability::AirlightAtBound
                        | Identifiability::WeakSfm
                )
        })
        .map(|j| ((j.airlight as f32).clamp(1e-3, 1.0), j.beta as f32));
    // The ratio fit samples the same points: too few for the joint fit are too few for it.
    let enough_points = joint.as_ref().is_none_or(|j| j.points >= MIN_POINTS);
    let point_ratio = (from_joint.is_none() && params.beta_from_points && enough_points)
        .then(|| beta_from_ratio_samples(&samples, airlight_initial))
        .flatten();
    let from_ratio = point_ratio
        .filter(PointRatioFit::is_reliable)
        .map(|fit| (airlight_initial, fit.beta as f32));
    let (beta_source, airlight_step1, fitted_beta) = match (from_joint, from_ratio) {
        (Some((a, b)), _) => (BetaSource::JointFit, a, Some(b)),
        (None, Some((a, b))) => (BetaSource::PointRatio, a, Some(b)),
        (None, None) => (BetaSource::Sweep, airlight_initial, None),
    };
    let clamped = fitted_beta.map(|b| b.clamp(beta_lo, beta_hi));
    let step1: Vec<f32> = match clamped {
        Some(b) => vec![b],
        None if beta_range_from_points => geomspace(beta_lo.max(1e-6), beta_hi, params.beta_steps),
        None => linspace(beta_lo, beta_hi, params.beta_steps),
    };
    let step2 = match (beta_source, params.airlight_steps()) {
        (BetaSource::JointFit, _) | (BetaSource::PointRatio, 1) => 0,
        (BetaSource::PointRatio, a) => a,
        (BetaSource::Sweep, a) => a * params.grid_steps,
    };
    let total = (step1.len() + step2) as f32;
    let mut grid: Vec<GridEvaluation> = Vec::with_capacity(step1.len() + step2);
    let mut evaluate = |stage: SearchStage, airlight: f32, beta: f32| -> Result<(f64, Vec<f32>)> {
        monitor.checkpoint()?;
        let i = grid.len() as f32;
        let kind = CostKind::DehazingWith(AtmosphereParams { airlight, beta }, params.cost);
        let depth = estimate_depth(
            &reference_view,
            &source_views,
            &search_planes,
            kind,
            &params.depth,
            &monitor.sub(i / total, (i + 1.0) / total),
        )?;
        let per_point = sparse_residuals(&depth.z_depth, &sparse_small, delta)?;
        let residual =
            per_point.iter().map(|&x| f64::from(x)).sum::<f64>() / per_point.len() as f64;
        grid.push(GridEvaluation {
            stage,
            airlight,
            beta,
            residual,
        });
        monitor.progress("params.search", (i + 1.0) / total);
        Ok((residual, per_point))
    };
    // Step 1 (Eq. 3.10, or the points' estimate).
    let mut best = (f64::INFINITY, airlight_step1, beta_lo);
    let mut incumbent: Vec<f32> = Vec::new();
    for &beta in &step1 {
        let (r, per_point) = evaluate(SearchStage::Beta, airlight_step1, beta)?;
        if r < best.0 {
            best = (r, airlight_step1, beta);
            incumbent = per_point;
        }
    }
    let beta_initial = best.2;
    // A swept minimum at an end of the range may lie beyond it.
    let sweep_at_end = beta_source == BetaSource::Sweep
        && step1.len() > 1
        && (beta_initial == step1[0] || beta_initial == step1[step1.len() - 1]);
    // Step 2 (Eq. 3.8 over Ω_A × Ω_β).
    let a_values = linspace(
        airlight_initial - params.delta_airlight,
        airlight_initial + params.delta_airlight,
        params.airlight_steps(),
    );
    // With β₀ from the points step 2 refines A only: the depth residual's preference in β is
    // a bias of the classical depth function (it moved the points' β₀ by +0.05 on 8 of 10
    // scenes past a paired t of 3, MAE_β 0.032 → 0.154), not information.
    // After the joint fit, which placed A with the points, step 2 does not run.
    let delta_beta = params.delta_beta.unwrap_or(0.1 * beta_initial);
    let (a_values, b_values) = match beta_source {
        BetaSource::JointFit => (Vec::new(), Vec::new()),
        // (A₀, β₀) is step 1's evaluation already.
        BetaSource::PointRatio if a_values.len() == 1 => (Vec::new(), Vec::new()),
        BetaSource::PointRatio => (a_values, vec![beta_initial]),
        BetaSource::Sweep => (
            a_values,
            linspace(
                beta_initial - delta_beta,
                beta_initial + delta_beta,
                params.grid_steps,
            ),
        ),
    };
    for &a in &a_values {
        let a = a.clamp(1e-3, 1.0);
        for &b in &b_values {
            let b = b.max(0.0);
            let (r, per_point) = evaluate(SearchStage::Joint, a, b)?;
            // Only a significant improvement over (A₀, β₀) moves the estimate: the residual
            // barely depends on A (docs/scattering-params.md), and an argmin over noise would
            // drift.
            let significant = params.min_improvement_t == 0.0
                || paired_improvement_t(&incumbent, &per_point) >= params.min_improvement_t;
            if r < best.0 && significant {
                best = (r, a, b);
            }
        }
    }
    let beta_unclamped = fitted_beta.unwrap_or(best.2);
    let beta_bound = if beta_unclamped < beta_lo || (sweep_at_end && best.2 <= step1[0]) {
        Some(BetaBound::Min)
    } else if beta_unclamped > beta_hi || (sweep_at_end && best.2 >= step1[step1.len() - 1]) {
        Some(BetaBound::Max)
    } else {
        None
    };
    // Only an A* that came from the fit can conflict with A₀.
    let airlight_conflict = joint
        .as_ref()
        .filter(|_| beta_source == BetaSource::JointFit)
        .and_then(|j| {
            AirlightConflict::test(
                j,
                f64::from(airlight_initial),
                f64::from(params.airlight_initial_error),
            )
        });
    let identifiability = match beta_source {
        BetaSource::JointFit => match joint.as_ref().map(|j| j.identifiability) {
            Some(Identifiability::Identifiable) if airlight_conflict.is_some() => {
                Identifiability::AirlightConflict
            }
            Some(other) => other,
            None => Identifiability::FlatResidual,
        },
        BetaSource::PointRatio => Identifiability::Identifiable,
        BetaSource::Sweep => match joint.as_ref().map(|j| j.identifiability) {
            // The fit determined β but the caller turned it off: the sweep's β is still a guess.
            Some(Identifiability::Identifiable) | None => Identifiability::FlatResidual,
            Some(other) => other,
        },
    };
    let (airlight_std_error, beta_std_error) = match beta_source {
        BetaSource::JointFit => joint.as_ref().map_or((None, None), |j| {
            (Some(j.airlight_std_error), Some(j.beta_std_error))
        }),
        BetaSource::PointRatio => (None, point_ratio.map(|p| p.std_error)),
        BetaSource::Sweep => (None, None),
    };
    Ok(ScatteringEstimate {
        airlight: best.1,
        beta: best.2,
        airlight_initial,
        beta_initial,
        airlight_std_error,
        beta_std_error,
        beta_source,
        identifiability,
        beta_range: [beta_lo, beta_hi],
        beta_range_from_points,
        beta_bound,
        beta_unclamped,
        joint,
        pose_error,
        sampling,
        relief,
        airlight_conflict,
        point_ratio,
        residual: best.0,
        grid,
        num_sparse_points: sparse_small.len(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// A plane range that covers the scene seen by the SfM points: `[0.75·q₀₁, 1.5·q₉₉]` of their
/// z-depth (1st and 99th percentiles, so a few outliers do not stretch it; the margins cover
/// surfaces just outside the points' range, such as an untextured far wall). `None` without points.
pub fn plane_range_from_sparse(sparse: &SparseDepth) -> Option<(f64, f64)> {
    let lo = f64::from(sparse.depth_quantile(0.01)?);
    let hi = f64::from(sparse.depth_quantile(0.99)?);
    Some((0.75 * lo, 1.5 * hi.max(lo * 1.01)))
}

impl SparseDepth {
    /// The map of the `f×f` box-downsampled image: fine pixel `(x, y)` falls in coarse pixel
    /// `(x / f, y / f)` (pixels outside the cropped image are dropped), the nearest point kept.
    pub fn downsampled(&self, f: usize) -> SparseDepth {
        let f = f.max(1);
        let (w, h) = (self.width() / f, self.height() / f);
        let mut samples: Vec<SparseSample> = self
            .samples()
            .iter()
            .map(|s| SparseSample {
                x: s.x / f as u32,
                y: s.y / f as u32,
                // Pixel centres at integers in both grids.
                u: (s.u + 0.5) / f as f32 - 0.5,
                v: (s.v + 0.5) / f as f32 - 0.5,
                ..*s
            })
            .filter(|s| (s.x as usize) < w && (s.y as usize) < h)
            .collect();
        samples.sort_by(|a, b| (a.y, a.x, a.z).partial_cmp(&(b.y, b.x, b.z)).unwrap());
        samples.dedup_by(|later, first| later.x == first.x && later.y == first.y);
        SparseDepth::from_samples(w, h, samples)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::sparse::SEEN_BY_EVERY_SOURCE;
    use crate::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};
    use std::sync::atomic::AtomicBool;
    use std::sync::{Arc, Mutex};

    #[test]
    fn downsampled_intrinsics_match_the_box_downsampled_image() {
        let k = Intrinsics {
            fx: 100.0,
            fy: 90.0,
            cx: 31.5,
            cy: 23.5,
            skew: 0.5,
        };
        for f in [1usize, 2, 3] {
            let kc = k.box_downsampled(f);
            let p = [0.3, -0.2, 2.0];
            let (u, v) = k.project(p).unwrap();
            let (uc, vc) = kc.project(p).unwrap();
            // Fine pixels f·i … f·i+f−1 average into coarse pixel i, centred at f·i + (f−1)/2.
            assert!((uc * f as f64 + (f as f64 - 1.0) / 2.0 - u).abs() < 1e-9);
            assert!((vc * f as f64 + (f as f64 - 1.0) / 2.0 - v).abs() < 1e-9);
        }
        let img = ImageF32::from_fn(6, 4, |x, y| (x + 10 * y) as f32);
        let d = box_downsample(&img, 2);
        assert_eq!(d.dims(), (3, 2));
        assert_eq!(d.get(1, 1, 0), (22.0 + 23.0 + 32.0 + 33.0) / 4.0);
    }

    #[test]
    fn linspace_covers_the_range() {
        assert_eq!(linspace(0.4, 0.8, 1), vec![0.5 * (0.4f32 + 0.8)]);
        let v = linspace(0.4, 0.8, 5);
        assert_eq!(v.len(), 5);
        assert_eq!(v[0], 0.4);
        assert!((v[4] - 0.8).abs() < 1e-7);
    }

    fn small_scene() -> MvsScene {
        let cfg = MvsSimConfig {
            seed: 7,
            beta_range: Some([0.4, 0.8]),
            ..MvsSimConfig::with_size(64, 48)
        };
        simulate_mvs(&cfg, &Monitor::noop()).unwrap()
    }

    /// The walking scene of `walking_test_scene` with its β drawn from `beta_range`: the same
    /// images, the world scaled so that β is in other units (×10 bigger for a range ÷10).
    fn walking_scene_in(beta_range: [f32; 2], seed: u64) -> MvsScene {
        let cfg = MvsSimConfig {
            seed,
            beta_range: Some(beta_range),
            forward_motion: 0.5,
            ..MvsSimConfig::with_size(128, 96)
        };
        simulate_mvs(&cfg, &Monitor::noop()).unwrap()
    }

    fn run(scene: &MvsScene, a0: f32, params: &SearchParams) -> ScatteringEstimate {
        let (reference, sources) = scene.reference_and_sources();
        let sparse = scene.sparse_depth().unwrap();
        let (near, far) = plane_range_from_sparse(&sparse).unwrap();
        let planes = PlaneSet::new(near, far, 32).unwrap();
        search_scattering(
            &reference,
            &sources,
            SfmEvidence::map(&sparse),
            a0,
            &planes,
            params,
            &Monitor::noop(),
        )
        .unwrap()
    }

    fn fast() -> SearchParams {
        SearchParams {
            search_planes: 16,
            ..SearchParams::default()
        }
    }

    /// An `A₀` far outside the estimator's typical error, on sound data: the fit still finds
    /// `A` (the Cauchy prior lets the points decide), and the disagreement is reported as a
    /// conflict that makes the estimate not identifiable, with `A*` and β* left as fitted. An
    /// estimator known to be that inaccurate raises none.
    #[test]
    fn an_airlight_far_from_the_points_is_reported_as_a_conflict() {
        // A scene of `params_survey`'s held-out set (A 0.602, β 0.244), the CNN 0.2 off.
        let cfg = MvsSimConfig {
            seed: 504,
            airlight_range: [0.5, 1.0],
            median_transmission_range: [0.1, 0.4],
            ..MvsSimConfig::default()
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        let a0 = scene.airlight + 0.2;
        let est = run(&scene, a0, &fast());
        assert_eq!(est.beta_source, BetaSource::JointFit);
        let joint = est.joint.clone().unwrap();
        assert_eq!(est.identifiability, Identifiability::AirlightConflict);
        assert_eq!(joint.identifiability, Identifiability::Identifiable);
        assert!((est.airlight - scene.airlight).abs() < 0.03, "{est:?}");
        assert_eq!(
            f64::from(est.airlight),
            joint.airlight.clamp(1e-3, 1.0) as f32 as f64
        );
        let c = est.airlight_conflict.unwrap();
        assert_eq!(c.fitted_airlight, joint.airlight);
        assert_eq!(c.airlight_initial, f64::from(a0));
        assert_eq!(c.airlight_initial_error, f64::from(CNN_AIRLIGHT_ERROR));
        let spread = (c.airlight_initial_error.powi(2) + joint.airlight_std_error.powi(2)).sqrt();
        assert!((c.sigmas - (joint.airlight - f64::from(a0)).abs() / spread).abs() < 1e-12);
        assert!(c.sigmas > AIRLIGHT_CONFLICT_SIGMAS);
        let text = c.describe();
        assert!(
            text.contains(&format!("A = {:.3}", joint.airlight))
                && text.contains(&format!("A0 = {a0:.3}"))
                && text.contains("SfM model"),
            "{text}"
        );

        let lenient = SearchParams {
            airlight_initial_error: 0.2,
            ..fast()
        };
        let est = run(&scene, a0, &lenient);
        assert_eq!(est.identifiability, Identifiability::Identifiable);
        assert!(est.airlight_conflict.is_none());
    }

    /// murk's default on a simulated room at reduced size (walking trajectory): A and β from
    /// the joint fit, although A₀ is 0.06 off, with standard errors; one depth evaluation; the
    /// range from the points, not binding. Without the joint fit the points' ratios at the true
    /// A; without either the published sweep, reported as not identifiable.
    #[test]
    fn default_search_fits_a_and_beta_from_the_points() {
        let scene = crate::simulate::mvs::walking_test_scene(5);
        let est = run(&scene, scene.airlight - 0.06, &fast());
        assert_eq!(est.beta_source, BetaSource::JointFit);
        assert_eq!(est.identifiability, Identifiability::Identifiable);
        assert_eq!(est.grid.len(), 1);
        assert!((est.airlight - scene.airlight).abs() < 0.03, "{est:?}");
        assert!((est.beta - scene.beta).abs() < 0.05, "{est:?}");
        let (se_a, se_b) = (est.airlight_std_error.unwrap(), est.beta_std_error.unwrap());
        assert!(se_a > 0.0 && se_a < 0.05 && se_b > 0.0 && se_b < 0.15 * f64::from(est.beta));
        assert!(est.beta_range_from_points && est.beta_bound.is_none());
        assert!(est.beta_range[0] < est.beta && est.beta < est.beta_range[1]);
        // 0.06 is 2 of the CNN's typical errors: no conflict.
        assert!(est.airlight_conflict.is_none(), "{est:?}");
        // The simulator's room stands well out of any plane, so its poses are not ambiguous.
        let relief = est.relief.unwrap();
        assert!(!relief.is_ambiguous() && relief.points == scene.sparse_depth().unwrap().len());
        // Had the points been flat, the verdict and the warning say so, with the numbers.
        let mut flat = est.clone();
        flat.relief = Some(Relief {
            relief: 0.012,
            tilt_deg: 8.0,
            ..relief
        });
        flat.identifiability = Identifiability::WeakSfm;
        flat.joint.as_mut().unwrap().identifiability = Identifiability::WeakSfm;
        let warnings = flat.warnings();
        assert_eq!(warnings.len(), 1, "{warnings:?}");
        assert!(
            warnings[0].contains("within 1.2 % of their depth"),
            "{warnings:?}"
        );
        assert!(warnings[0].contains("bas-relief"), "{warnings:?}");
        // The sampling's share is in the errors. Had it taken β's error past the limit, the
        // verdict's warning names it with its numbers.
        let sampling = est.sampling.unwrap();
        let [_, share_b] = sampling.share.unwrap();
        assert_eq!(sampling.wide_blur_px, 2.0 * sampling.base_blur_px);
        assert!(
            se_b >= share_b && share_b < 0.05 * f64::from(est.beta),
            "{sampling:?}"
        );
        let mut sampled = est.clone();
        sampled.identifiability = Identifiability::WeakSfm;
        let j = sampled.joint.as_mut().unwrap();
        j.identifiability = Identifiability::WeakSfm;
        j.beta_std_error = 0.2 * j.beta;
        let warnings = sampled.warnings();
        assert_eq!(warnings.len(), 1, "{warnings:?}");
        assert!(
            warnings[0].contains("depend on how they are sampled")
                && warnings[0].contains("standard error is 20 %"),
            "{warnings:?}"
        );
        sampled.sampling = Some(SamplingShare {
            refit: None,
            share: None,
            ..sampling
        });
        let warnings = sampled.warnings();
        let failed = format!(
            "a refit on samples with a {:.1} px blur failed",
            sampling.wide_blur_px
        );
        assert!(warnings[0].contains(&failed), "{warnings:?}");

        let ratio = SearchParams {
            joint_fit: false,
            ..fast()
        };
        let est = run(&scene, scene.airlight, &ratio);
        assert_eq!(est.beta_source, BetaSource::PointRatio);
        assert!(est.point_ratio.unwrap().is_reliable());
        assert_eq!((est.grid.len(), est.airlight), (1, scene.airlight));
        assert!((est.beta - scene.beta).abs() < 0.05, "{est:?}");
        assert!(est.airlight_std_error.is_none() && est.beta_std_error.is_some());

        let published = SearchParams {
            joint_fit: false,
            beta_from_points: false,
            beta_min: Some(0.4),
            beta_max: Some(0.8),
            delta_beta: Some(0.05),
            ..fast()
        };
        let est = run(&scene, scene.airlight, &published);
        assert_eq!(est.beta_source, BetaSource::Sweep);
        assert!(est.point_ratio.is_none() && est.beta_std_error.is_none());
        assert_eq!(est.grid.len(), published.evaluations());
        assert_ne!(est.identifiability, Identifiability::Identifiable);
        assert!(!est.beta_range_from_points);
    }

    /// The same scene in units ten times smaller (β ten times larger... here: the world ten
    /// times bigger, β per unit ÷10): the default range follows the points and the estimate
    /// scales with the unit, where a fixed range (the reference's [0.4, 0.8]) would clamp it —
    /// and a clamp is reported, never silent.
    #[test]
    fn the_beta_range_follows_the_models_unit_and_a_clamp_is_reported() {
        let metric = walking_scene_in([0.4, 0.8], 6);
        let big = walking_scene_in([0.04, 0.08], 6);
        assert!((big.beta * 10.0 - metric.beta).abs() < 1e-4);
        let (m, b) = (
            run(&metric, metric.airlight, &fast()),
            run(&big, big.airlight, &fast()),
        );
        assert!(
            (m.beta_range[0] / b.beta_range[0] - 10.0).abs() < 0.1,
            "{m:?} {b:?}"
        );
        assert!((m.beta - metric.beta).abs() < 0.05, "{m:?}");
        assert!((b.beta * 10.0 - metric.beta).abs() < 0.05, "{b:?}");
        assert!(b.beta_bound.is_none() && b.identifiability == Identifiability::Identifiable);
        // The reference's fixed range on the bigger model: clamped at 0.4, and said so.
        let fixed = SearchParams {
            beta_min: Some(0.4),
            beta_max: Some(0.8),
            ..fast()
        };
        let c = run(&big, big.airlight, &fixed);
        assert_eq!((c.beta, c.beta_bound), (0.4, Some(BetaBound::Min)));
        assert!(
            (c.beta_unclamped * 10.0 - metric.beta).abs() < 0.05,
            "{c:?}"
        );
        assert!(!c.beta_range_from_points);
    }

    /// A rectified pair sees every point at the same depth in both views: β does not change
    /// the cost, the points say so, and the result is marked not identifiable.
    #[test]
    fn a_rectified_pair_is_reported_as_not_identifiable() {
        let cfg = MvsSimConfig {
            seed: 8,
            rectified_pair: true,
            num_views: 2,
            ..MvsSimConfig::with_size(128, 96)
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        let est = run(&scene, scene.airlight, &fast());
        assert_eq!(
            est.identifiability,
            Identifiability::NoDepthDifference,
            "{est:?}"
        );
        assert_eq!(est.beta_source, BetaSource::Sweep);
        assert!(est.beta_std_error.is_none());
        let joint = est.joint.unwrap();
        assert!(!joint.is_identifiable() && joint.rms_depth_difference < 1e-6);
    }

    #[test]
    fn beta_range_from_points_scales_with_depth() {
        let near = SparseDepth::from_samples(
            8,
            8,
            (0..5)
                .map(|i| SparseSample {
                    x: i,
                    y: 0,
                    u: i as f32,
                    v: 0.0,
                    z: 2.0,
                    seen_by: SEEN_BY_EVERY_SOURCE,
                })
                .collect(),
        );
        let far = SparseDepth::from_samples(
            8,
            8,
            (0..5)
                .map(|i| SparseSample {
                    x: i,
                    y: 0,
                    u: i as f32,
                    v: 0.0,
                    z: 20.0,
                    seen_by: SEEN_BY_EVERY_SOURCE,
                })
                .collect(),
        );
        let [lo, hi] = beta_range_from_points(&near).unwrap();
        // Median point transmission 0.98 … 0.02.
        assert!(((-lo * 2.0).exp() - 0.98).abs() < 1e-4 && ((-hi * 2.0).exp() - 0.02).abs() < 1e-4);
        let [lo10, hi10] = beta_range_from_points(&far).unwrap();
        assert!((lo / lo10 - 10.0).abs() < 1e-3 && (hi / hi10 - 10.0).abs() < 1e-3);
        let g = geomspace(0.1, 10.0, 3);
        assert!((g[1] - 1.0).abs() < 1e-6 && (g[2] - 10.0).abs() < 1e-5);
    }

    /// The search's bookkeeping: `beta_steps + grid_steps²` evaluations in order, the step-2
    /// grid centred on (A₀, β₀), the answer the smallest residual seen, progress monotone up to
    /// 1, cancellation honoured. (Whether the minimum is at the true β depends on the depth
    /// function; see docs/scattering-params.md.)
    #[test]
    fn search_bookkeeping_progress_and_cancel() {
        let scene = small_scene();
        let (reference, sources) = scene.reference_and_sources();
        let sparse = scene.sparse_depth().unwrap();
        let (near, far) = plane_range_from_sparse(&sparse).unwrap();
        let planes = PlaneSet::new(near, far, 32).unwrap();
        let params = SearchParams {
            beta_steps: 4,
            grid_steps: 2,
            delta_airlight: 0.05,
            search_planes: 16,
            // The published plain argmin, so the estimate must be the grid's minimum.
            min_improvement_t: 0.0,
            beta_from_points: false,
            joint_fit: false,
            beta_min: Some(0.4),
            beta_max: Some(0.8),
            delta_beta: Some(0.05),
            ..SearchParams::default()
        };
        assert_eq!(params.evaluations(), 8);
        assert_eq!(
            SearchParams {
                delta_airlight: 0.0,
                ..params.clone()
            }
            .evaluations(),
            6
        );
        let seen: Arc<Mutex<Vec<f32>>> = Arc::default();
        let sink = {
            let seen = seen.clone();
            Arc::new(move |stage: &str, f: f32| {
                if stage == "params.search" {
                    seen.lock().unwrap().push(f);
                }
            })
        };
        let monitor = Monitor::new(Arc::new(AtomicBool::new(false)), Some(sink));
        let est = search_scattering(
            &reference,
            &sources,
            SfmEvidence::map(&sparse),
            0.85,
            &planes,
            &params,
            &monitor,
        )
        .unwrap();
        assert_eq!(est.grid.len(), 4 + 4);
        assert!(est.grid[..4]
            .iter()
            .all(|g| g.stage == SearchStage::Beta && g.airlight == 0.85));
        let betas: Vec<f32> = est.grid[..4].iter().map(|g| g.beta).collect();
        assert_eq!(betas, linspace(0.4, 0.8, 4));
        let best_step1 = est.grid[..4]
            .iter()
            .min_by(|a, b| a.residual.total_cmp(&b.residual))
            .unwrap();
        assert_eq!(est.beta_initial, best_step1.beta);
        for g in &est.grid[4..] {
            assert_eq!(g.stage, SearchStage::Joint);
            assert!((g.airlight - 0.85).abs() <= 0.05 + 1e-6);
            assert!((g.beta - est.beta_initial).abs() <= 0.05 + 1e-6);
        }
        let best = est
            .grid
            .iter()
            .min_by(|a, b| a.residual.total_cmp(&b.residual))
            .unwrap();
        assert_eq!(
            (est.airlight, est.beta, est.residual),
            (best.airlight, best.beta, best.residual)
        );
        let p = seen.lock().unwrap().clone();
        assert_eq!(p.len(), 8);
        assert!(p.windows(2).all(|w| w[0] <= w[1]));
        assert_eq!(*p.last().unwrap(), 1.0);

        let cancelled = Monitor::new(Arc::new(AtomicBool::new(true)), None);
        assert_eq!(
            search_scattering(
                &reference,
                &sources,
                SfmEvidence::map(&sparse),
                0.85,
                &planes,
                &params,
                &cancelled
            )
            .unwrap_err(),
            MurkError::Cancelled
        );
        // Too few points, bad A₀, bad parameters: named.
        let search = |a0: f32, p: &SearchParams| {
            search_scattering(
                &reference,
                &sources,
                SfmEvidence::map(&sparse),
                a0,
                &planes,
                p,
                &monitor,
            )
        };
        let few = SparseDepth::from_samples(64, 48, sparse.samples()[..3].to_vec());
        let err = search_scattering(
            &reference,
            &sources,
            SfmEvidence::map(&few),
            0.85,
            &planes,
            &params,
            &monitor,
        );
        assert_eq!(err.unwrap_err().field(), Some("sparse_points"));
        let err = search(0.0, &params);
        assert_eq!(err.unwrap_err().field(), Some("airlight_initial"));
        let bad = SearchParams {
            beta_min: Some(0.5),
            beta_max: Some(0.4),
            ..params.clone()
        };
        let err = search(0.85, &bad);
        assert_eq!(err.unwrap_err().field(), Some("params.beta_max"));
        for v in [0.0, -0.1, 1.5, f32::NAN] {
            let bad = SearchParams {
                airlight_initial_error: v,
                ..params.clone()
            };
            let err = search(0.85, &bad);
            assert_eq!(
                err.unwrap_err().field(),
                Some("params.airlight_initial_error")
            );
        }
        // Tracks that name a view the search was not given: refused under `tracks`.
        let tracks = SfmTracks {
            points: vec![[0.0, 0.0, 5.0]],
            seen_by: Vec::new(),
            observations: vec![crate::params::pose_error::Observation {
                point: 0,
                view: 1 + sources.len() as u32,
                pixel: [1.0, 1.0],
            }],
        };
        let sfm = SfmEvidence {
            sparse: &sparse,
            tracks: Some(&tracks),
        };
        let err = search_scattering(&reference, &sources, sfm, 0.85, &planes, &params, &monitor);
        assert_eq!(
            err.unwrap_err().field(),
            Some("tracks.observations[0].view")
        );
    }
}
