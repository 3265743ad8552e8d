//! The settings of one IRLS run of Algorithm 2 and the convergence test of its levels ("repeat
//! … until converged"), shared by the coarse level ([`super::coarse_level`]) and the fine level
//! ([`super::irls`]).

use rayon::prelude::*;

use super::params::IrlsChannelParams;
use super::wls::XStepSolver;

/// Settings of one IRLS run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IrlsConfig {
    /// γ′ and Tukey constants of this image.
    pub channel: IrlsChannelParams,
    /// Cap on coarse (patch-wise) iterations.
    pub coarse_iterations: usize,
    /// Cap on fine (pixel-wise) iterations.
    pub fine_iterations: usize,
    /// x-step solver.
    pub solver: XStepSolver,
    /// Convergence test of a level ("repeat … until converged", Algorithm 2): the level stops
    /// once, for [`CONVERGED_RUNS`] consecutive iterations, no weight moved by more than this
    /// and no pixel (patch) crossed `mask_threshold`. 0 disables it (always run the caps).
    pub weight_tolerance: f64,
    /// Weight below which a pixel counts as object (see `TofParams::mask_threshold`).
    pub mask_threshold: f64,
    /// Coarse-level blocks per quadratic patch along each axis (1 = the patches themselves).
    pub coarse_subdivision: usize,
    /// Quantile of the blocks' RMS residuals taken as the coarse scale σ₂ (0.5 = the median).
    pub coarse_quantile: f64,
}

/// Consecutive converged iterations after which a level stops.
pub const CONVERGED_RUNS: usize = 2;

/// Tracks the convergence test of one IRLS level.
#[derive(Default)]
pub(super) struct Convergence {
    runs: usize,
    /// Largest weight change of the last iteration (1 before any).
    last_change: f64,
}

impl Convergence {
    pub(super) fn new() -> Self {
        Self {
            runs: 0,
            last_change: 1.0,
        }
    }

    /// Records an iteration's largest weight change and whether the binarised mask changed;
    /// true when the level has converged.
    pub(super) fn update(&mut self, max_change: f64, mask_changed: bool, tol: f64) -> bool {
        self.last_change = max_change;
        if tol > 0.0 && max_change < tol && !mask_changed {
            self.runs += 1;
        } else {
            self.runs = 0;
        }
        self.runs >= CONVERGED_RUNS
    }

    /// CG tolerance multiplier for the next x-step: while the weights still move by Δ, the
    /// x-step only needs to be accurate to a fraction of the change the next reweighting will
    /// bring, so the tolerance is relaxed by up to 100× (Δ ≥ 1) and reaches the configured one
    /// (×1) once Δ ≤ 1 %.
    pub(super) fn tol_scale(&self) -> f64 {
        (100.0 * self.last_change).clamp(1.0, 100.0)
    }
}

/// Largest |a − b| and whether any pair lies on different sides of `threshold`.
pub(super) fn weight_change(old: &[f64], new: &[f64], threshold: f64) -> (f64, bool) {
    old.par_iter()
        .zip(new.par_iter())
        .map(|(&a, &b)| ((a - b).abs(), (a < threshold) != (b < threshold)))
        .reduce(|| (0.0, false), |x, y| (x.0.max(y.0), x.1 || y.1))
}
