//! Algorithm 2: coarse-to-fine IRLS estimation of the scattering component and the outlier
//! (object) weights of one image (amplitude or phase).
//!
//! Coarse level (Eq. 5.16): one Tukey weight per patch from the patch's residual, then the fine
//! level (Eq. 5.11): one weight per pixel. Each level fixes its scale σ from the residuals of its
//! first iteration (§5.3.4); the fine level re-measures σ₁ once, from its first x-step solved
//! under pixel weights (see `run_irls`). Every iteration alternates the x-step and the a-step of
//! Eq. 5.12, the a-step fitting the quadratics with the IRLS weights (a deviation, see
//! `x_and_a_step`).

use rayon::prelude::*;

use super::params::IrlsChannelParams;
use super::quadratic_prior::QuadraticPrior;
use super::tukey::{self, mad_sigma_in_place, median_in_place, scale_floor};
use super::wls::{XStepSolver, XStepState, XStepSystem};
use crate::error::{MurkError, Result};
use crate::monitor::Monitor;

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
}

/// Consecutive converged iterations after which a level stops.
pub const CONVERGED_RUNS: usize = 2;

/// Default of [`IrlsConfig::weight_tolerance`].
pub const DEFAULT_WEIGHT_TOLERANCE: f64 = 1e-3;

/// Tracks the convergence test of one IRLS level.
#[derive(Default)]
struct Convergence {
    runs: usize,
    /// Largest weight change of the last iteration (1 before any).
    last_change: f64,
}

impl Convergence {
    fn new() -> Self {
        Self {
            runs: 0,
            last_change: 1.0,
        }
    }

    /// Records an iteration's largest weight change and whether the binarised mask changed;
    /// true when the level has converged.
    fn update(&mut self, max_change: f64, mask_changed: bool, tol: f64) -> bool {
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
    fn tol_scale(&self) -> f64 {
        (100.0 * self.last_change).clamp(1.0, 100.0)
    }
}

/// Largest |a − b| and whether any pair lies on different sides of `threshold`.
fn weight_change(old: &[f64], new: &[f64], threshold: f64) -> (f64, bool) {
    old.par_iter()
        .zip(new.par_iter())
        .map(|(&a, &b)| ((a - b).abs(), (a < threshold) != (b < threshold)))
        .reduce(|| (0.0, false), |x, y| (x.0.max(y.0), x.1 || y.1))
}

/// Result of one IRLS run.
#[derive(Clone, Debug, PartialEq)]
pub struct IrlsOutcome {
    /// Estimated scattering component x (same units as the input image).
    pub scatter: Vec<f64>,
    /// Final IRLS weights in [0, 1]; small = outlier (object).
    pub weights: Vec<f64>,
    /// Coarse-level scale σ₂ (RMS residual units), if the coarse level ran.
    pub sigma_coarse: Option<f64>,
    /// Fine-level scale σ₁ as finally fixed (from the second fine iteration when it ran), if the
    /// fine level ran.
    pub sigma_fine: Option<f64>,
    /// Total conjugate-gradient iterations over all x-steps (0 for Cholesky).
    pub cg_iterations: usize,
    /// Coarse iterations actually run (≤ the cap; fewer when the level converged).
    pub coarse_iterations_run: usize,
    /// Fine iterations actually run.
    pub fine_iterations_run: usize,
}

/// Runs Algorithm 2 on `observed` (row-major, the system's size).
///
/// `tick(stage)` is called after every iteration with `"{stage_prefix}.coarse"` or
/// `"{stage_prefix}.fine"`; cancellation is checked every iteration (and inside CG).
///
/// With zero iterations at both levels the result is the initial state of Algorithm 2: the
/// patch-wise quadratic fits of the observation as scatter and all weights 1 (no object).
pub fn run_irls(
    observed: &[f64],
    sys: &XStepSystem,
    prior: &mut QuadraticPrior,
    cfg: &IrlsConfig,
    stage_prefix: &str,
    monitor: &Monitor,
    tick: &(dyn Fn(&str) + Sync),
) -> Result<IrlsOutcome> {
    let n = sys.len();
    let w = sys.width();
    if observed.len() != n || prior.grid().width() != w || prior.grid().height() != sys.height() {
        return Err(MurkError::Numerical(
            "IRLS buffers do not match the image size".into(),
        ));
    }
    let magnitude = observed
        .par_iter()
        .map(|v| v.abs())
        .reduce(|| 0.0, f64::max);
    let floor = scale_floor(magnitude);
    let stage_coarse = format!("{stage_prefix}.coarse");
    let stage_fine = format!("{stage_prefix}.fine");

    let mut weights = vec![1.0; n];
    let mut prior_img = vec![0.0; n];
    let mut rhs = vec![0.0; n];
    let mut scratch = vec![0.0; n];
    // Algorithm 2's initialisation: a_k fitted to the observation; x warm-starts at x̃, which is
    // the W = I solution up to the (small) smoothing and prior terms.
    prior.fit(observed);
    prior.evaluate(&mut prior_img);
    let mut x = observed.to_vec();
    let mut state = XStepState::new(cfg.solver, sys)?;
    let mut cg_iterations = 0;

    let pxn = prior.grid().patches_x();
    let k = prior.grid().count();
    let mut row_sums = vec![0.0; sys.height() * pxn];
    let mut patch_rms = vec![0.0; k];
    let mut patch_weight = vec![1.0; k];
    let mut sigma_coarse = None;
    let mut prev_patch_weight = vec![1.0; k];
    let mut conv = Convergence::new();
    let mut coarse_run = 0;
    let mut fine_run = 0;
    for it in 0..cfg.coarse_iterations {
        monitor.checkpoint()?;
        cg_iterations += x_and_a_step(
            sys,
            &mut state,
            prior,
            &weights,
            observed,
            &mut prior_img,
            &mut rhs,
            &mut x,
            conv.tol_scale(),
            monitor,
        )?;
        coarse_run += 1;
        patch_rms_residuals(prior, &x, observed, &mut row_sums, &mut patch_rms);
        if it == 0 {
            // The patch residual is an RMS, i.e. already a per-pixel deviation about the ideal
            // zero residual, so its median over patches is the robust scale (a "median absolute
            // deviation" about zero): background patches sit near r = 1 and an object patch at
            // r ≫ 1, independent of patch size (the last patches are larger). (A pixel-level
            // MAD instead was tried: it ignores the quadratic misfit of background patches and
            // flagged whole background patches as outliers on several simulated frames.)
            scratch[..k].copy_from_slice(&patch_rms);
            let med = median_in_place(&mut scratch[..k]).ok_or_else(|| {
                MurkError::Numerical("non-finite residual at the coarse level".into())
            })?;
            sigma_coarse = Some(med.max(floor));
        }
        let s2 = sigma_coarse.unwrap_or(floor);
        for (pw, &rms) in patch_weight.iter_mut().zip(&patch_rms) {
            *pw = tukey::weight(rms / s2, cfg.channel.c_coarse);
        }
        spread_patch_weights(prior, &patch_weight, &mut weights);
        tick(&stage_coarse);
        let (dw, flipped) = weight_change(&prev_patch_weight, &patch_weight, cfg.mask_threshold);
        prev_patch_weight.copy_from_slice(&patch_weight);
        if it > 0 && conv.update(dw, flipped, cfg.weight_tolerance) {
            break;
        }
    }

    let mut sigma_fine = None;
    let c_fine = cfg.channel.c_fine;
    let mut prev_weights = vec![0.0; n];
    let mut conv = Convergence::new();
    for it in 0..cfg.fine_iterations {
        monitor.checkpoint()?;
        cg_iterations += x_and_a_step(
            sys,
            &mut state,
            prior,
            &weights,
            observed,
            &mut prior_img,
            &mut rhs,
            &mut x,
            conv.tol_scale(),
            monitor,
        )?;
        fine_run += 1;
        prev_weights.copy_from_slice(&weights);
        // σ₁ is measured twice and then fixed (§5.3.4 fixes it from the level's first
        // residuals). The first fine x-step still runs under the coarse patch weights: in every
        // rejected patch the background residuals are the priors' misfit, not noise, and
        // inflate σ₁ (3.5× the noise on a simulated medium-fog frame), which then keeps dim
        // object pixels as inliers. That first estimate only seeds the first pixel weights;
        // the residuals of the first x-step solved under pixel weights give the noise scale.
        if it <= 1 {
            scratch
                .par_iter_mut()
                .zip(x.par_iter().zip(observed.par_iter()))
                .for_each(|(s, (xi, oi))| *s = xi - oi);
            let s = mad_sigma_in_place(&mut scratch).ok_or_else(|| {
                MurkError::Numerical("non-finite residual at the fine level".into())
            })?;
            sigma_fine = Some(s.max(floor));
        }
        let inv_s1 = 1.0 / sigma_fine.unwrap_or(floor);
        weights
            .par_iter_mut()
            .zip(x.par_iter().zip(observed.par_iter()))
            .for_each(|(wi, (xi, oi))| {
                let r = (oi - xi) * inv_s1;
                *wi = tukey::weight(r, c_fine)
            });
        tick(&stage_fine);
        // The first fine iteration replaces patch weights by pixel weights: not a convergence
        // step.
        let (dw, flipped) = weight_change(&prev_weights, &weights, cfg.mask_threshold);
        if it > 0 && conv.update(dw, flipped, cfg.weight_tolerance) {
            break;
        }
    }

    if cfg.coarse_iterations + cfg.fine_iterations == 0 {
        x.copy_from_slice(&prior_img);
    }
    Ok(IrlsOutcome {
        scatter: x,
        weights,
        sigma_coarse,
        sigma_fine,
        cg_iterations,
        coarse_iterations_run: coarse_run,
        fine_iterations_run: fine_run,
    })
}

/// One alternation of Eq. 5.12: x given a_k (and W), then a_k given x. Returns CG iterations.
///
/// Deviation from Eq. 5.12: the a-step fits each patch's quadratic to x with the current IRLS
/// weights ([`QuadraticPrior::fit_weighted`]) instead of uniformly. Where W ≈ 0 (objects) x has
/// no data term: it is only what the priors made of it, so a uniform fit lets the priors confirm
/// themselves there. The previous state persists (the alternation is a slow diffusion in those
/// pixels) — in particular Algorithm 2's initial fit to the observation, bright objects
/// included — and a quadratic partially fitted to the object region (the failure of the
/// reference's Fig. 5.14/5.16) lifts x over the whole patch until the background pixels beside
/// the object turn outliers too. Weighted, a_k follows the data-constrained pixels and the
/// object region receives the background's quadratic. At the coarse level all pixels of a patch
/// share one weight, so the fit is the uniform one there (see `fit_weighted`).
#[allow(clippy::too_many_arguments)]
fn x_and_a_step(
    sys: &XStepSystem,
    state: &mut XStepState,
    prior: &mut QuadraticPrior,
    weights: &[f64],
    observed: &[f64],
    prior_img: &mut [f64],
    rhs: &mut [f64],
    x: &mut [f64],
    tol_scale: f64,
    monitor: &Monitor,
) -> Result<usize> {
    sys.rhs(weights, observed, prior_img, rhs);
    let stats = state.solve_inexact(sys, weights, rhs, x, tol_scale, monitor)?;
    if sys.is_joint() {
        // x already minimises over a: its uniform fits are the a-step's answer.
        prior.fit(x);
    } else {
        prior.fit_weighted(x, weights);
    }
    prior.evaluate(prior_img);
    Ok(stats.iterations)
}

/// RMS of x − x̃ over every patch (Eq. 5.16's ‖x_k − x̃_k‖ divided by √N_k).
fn patch_rms_residuals(
    prior: &QuadraticPrior,
    x: &[f64],
    observed: &[f64],
    row_sums: &mut [f64],
    out: &mut [f64],
) {
    let grid = prior.grid();
    let w = grid.width();
    let pxn = grid.patches_x();
    let cols = grid.col_ranges();
    row_sums
        .par_chunks_mut(pxn)
        .zip(x.par_chunks(w).zip(observed.par_chunks(w)))
        .for_each(|(sums, (xr, or))| {
            for (s, &(x0, x1)) in sums.iter_mut().zip(cols) {
                *s = xr[x0..x1]
                    .iter()
                    .zip(&or[x0..x1])
                    .map(|(a, b)| (a - b) * (a - b))
                    .sum();
            }
        });
    for (py, &(y0, y1)) in grid.row_ranges().iter().enumerate() {
        for (px, &(x0, x1)) in cols.iter().enumerate() {
            let ss: f64 = (y0..y1).map(|y| row_sums[y * pxn + px]).sum();
            out[py * pxn + px] = (ss / ((y1 - y0) * (x1 - x0)) as f64).sqrt();
        }
    }
}

/// Every pixel of a patch shares the patch's coarse weight (Eq. 5.16).
fn spread_patch_weights(prior: &QuadraticPrior, patch_weight: &[f64], weights: &mut [f64]) {
    let grid = prior.grid();
    let pxn = grid.patches_x();
    let cols = grid.col_ranges();
    weights
        .par_chunks_mut(grid.width())
        .enumerate()
        .for_each(|(y, row)| {
            let py = grid.patch_row_of(y);
            for (px, &(x0, x1)) in cols.iter().enumerate() {
                row[x0..x1].fill(patch_weight[py * pxn + px]);
            }
        });
}
