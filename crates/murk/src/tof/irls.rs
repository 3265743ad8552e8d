//! Algorithm 2: coarse-to-fine IRLS estimation of the scattering component and the outlier
//! (object) weights of one image (amplitude or phase).
//!
//! Coarse level (Eq. 5.16): one Tukey weight per patch from the patch's residual, then the fine
//! level (Eq. 5.11): one weight per pixel. Each level fixes its scale σ from the residuals of its
//! first iteration (§5.3.4); the fine level re-measures σ₁ once, from its first x-step solved
//! under pixel weights (see `run_irls`), and with a noise model measures it over the coarse
//! level's background, floored at the sensor noise (`fine_scale_with_noise_model`). Between
//! the levels a held-out check re-judges the coarse level's accepted blocks
//! ([`HELD_OUT_ROUNDS`]). Every iteration alternates the x-step and the a-step of Eq. 5.12, the
//! a-step fitting the quadratics with the IRLS weights (a deviation, see `x_and_a_step`).

use rayon::prelude::*;

use super::ambiguous::dilate;
pub use super::coarse_level::HELD_OUT_ROUNDS;
use super::coarse_level::{coarse_blocks, coarse_level, CoarseSolve};
use super::coherent::{coherent_contrast, coherent_residual};
use super::irls_settings::{weight_change, Convergence};
pub use super::irls_settings::{IrlsConfig, CONVERGED_RUNS};
use super::noise_model::NoiseModel;
pub use super::params::DEFAULT_WEIGHT_TOLERANCE;
use super::quadratic_prior::QuadraticPrior;
use super::tukey::{self, mad_sigma_in_place, median_in_place, scale_floor};
use super::wls::{XStepState, XStepSystem};
use crate::error::{MurkError, Result};
use crate::monitor::Monitor;

/// Result of one IRLS run.
#[derive(Clone, Debug, PartialEq)]
pub struct IrlsOutcome {
    /// Estimated scattering component x, one image per component of the input (one for an
    /// amplitude or phase image, two for a phasor's real and imaginary parts), in the input's
    /// units.
    pub scatter: Vec<Vec<f64>>,
    /// Final IRLS weights in [0, 1], shared by the components; small = outlier (object).
    pub weights: Vec<f64>,
    /// Coarse-level scale σ₂ (RMS residual units), if the coarse level ran.
    pub sigma_coarse: Option<f64>,
    /// Fine-level scale σ₁ per component as finally fixed (from the second fine iteration when
    /// it ran), if the fine level ran.
    pub sigma_fine: Option<f64>,
    /// Total conjugate-gradient iterations over all x-steps (0 for Cholesky).
    pub cg_iterations: usize,
    /// Coarse iterations actually run (≤ the cap; fewer when the level converged).
    pub coarse_iterations_run: usize,
    /// Fine iterations actually run.
    pub fine_iterations_run: usize,
    /// Coarse blocks the held-out check rejected after the coarse level (see
    /// [`HELD_OUT_ROUNDS`]).
    pub held_out_rejected: usize,
    /// Pixels the thin-structure check moved from the background to the objects (see
    /// [`THIN_ROUNDS`]).
    pub thin_accepted: usize,
    /// False when the fine level ran its cap of iterations without its weights settling (with
    /// the convergence test on and at least one fine iteration): the mask may still be moving.
    pub fine_converged: bool,
    /// The rim of the objects ([`HELD_OUT_RING`]): its pixels, and per component the scatter
    /// there when the rim is held out of the fit ([`hold_out_the_rim`]). `scatter` is the
    /// fit's own fixed point, from which a stream's next frame starts;
    /// [`IrlsOutcome::scatter_with_rim`] is the estimate to subtract.
    pub rim: Vec<usize>,
    /// See `rim`: one value per rim pixel and component.
    pub rim_scatter: Vec<Vec<f64>>,
}

impl IrlsOutcome {
    /// The scatter estimate with the rim's held-out values in place: what the pipeline
    /// subtracts from the observation.
    pub fn scatter_with_rim(&self) -> Vec<Vec<f64>> {
        let mut out = self.scatter.clone();
        for (xc, rc) in out.iter_mut().zip(&self.rim_scatter) {
            for (&i, &v) in self.rim.iter().zip(rc) {
                xc[i] = v;
            }
        }
        out
    }
}

/// Where an IRLS run starts when the previous frame of a stream is a good guess for this one:
/// its scatter estimate and its final weights. Fog changes slowly and objects move little
/// between frames, so the coarse level (whose job is to find the objects from "no object") is
/// skipped and the fine level starts from the previous frame's answer, converging in a few
/// iterations where a cold start needs tens.
#[derive(Clone, Debug, PartialEq)]
pub struct IrlsStart {
    /// The previous frame's scatter estimate, one image per component.
    pub scatter: Vec<Vec<f64>>,
    /// The previous frame's final weights.
    pub weights: Vec<f64>,
    /// The previous frame's fine scale σ₁, at which the new frame's residuals against the
    /// previous scatter are first weighted (without it the fine level starts from `weights`).
    pub sigma_fine: Option<f64>,
}

impl IrlsStart {
    /// The start a finished run leaves for the next frame.
    pub fn from_outcome(outcome: &IrlsOutcome) -> Self {
        Self {
            scatter: outcome.scatter.clone(),
            weights: outcome.weights.clone(),
            sigma_fine: outcome.sigma_fine,
        }
    }
}

/// Rounds of the thin-structure check that follows the fine level. A pixel's Tukey weight
/// judges its residual alone, and an object part whose direct return is only a few noise σ
/// above the fog — a panel seen at a grazing angle, a pole or a strip beside a nearer occluder
/// in thick fog — is kept as background. The x-step's smoothness then bends the scatter towards
/// it, and its residual shrinks further (to about 2 σ on a simulated thick-fog frame whose lost
/// strip was 4.8 σ from the true scatter), so the pixel ends with the wall's depth.
///
/// The check looks at what one pixel cannot show: over a 3 × 3 window an object's residuals
/// share one direction, noise's do not ([`coherent_residual`]). Each round:
/// 1. background pixels whose window statistic exceeds [`THIN_CANDIDATE`] are candidates;
/// 2. the scatter is solved again with the candidates held out (weight 0), so that it no
///    longer follows them;
/// 3. a candidate whose statistic against the held-out scatter, taken as a contrast with the
///    background around it that is no candidate ([`coherent_contrast`]), exceeds
///    [`THIN_ACCEPT`] joins the objects (weight 0); the others keep their weights. The contrast
///    cancels where the scatter model itself misfits the background: without it, the
///    outermost rows, where the beam falls off steeply, turned object on a thick-fog frame.
///    A candidate with too little such background around it (a strip squeezed between
///    objects) is judged on the window statistic alone.
///
/// The held-out scatter becomes the estimate. The rounds stop early when one finds no candidate
/// or accepts none.
pub const THIN_ROUNDS: usize = 1;

/// Window statistic above which a background pixel is held out by the thin-structure check
/// ([`THIN_ROUNDS`]): 3, where about one noise pixel in 90 lands (χ² with two degrees of
/// freedom).
pub const THIN_CANDIDATE: f64 = 3.0;

/// Width of the image border, in pixels, that the thin-structure check ([`THIN_ROUNDS`]) leaves
/// alone: one 64th of the longer side (8 pixels at 512 × 424, 2 at 128 × 106). Where the
/// illuminator's beam falls off steeply at the image edge, the smoothness prior cannot bend
/// the scatter estimate down far enough, and the outermost rows keep a coherent misfit of 2–4
/// noise σ over that width on thick-fog frames, as a dim strip would: checked, whole border
/// rows turned object. The border keeps the per-pixel Tukey test.
pub fn thin_border_band(width: usize, height: usize) -> usize {
    width.max(height).div_ceil(64)
}

/// Width in pixels (Chebyshev distance) of the rim of background around the objects whose
/// scatter the fine level takes from an estimate in which the rim has no weight
/// ([`hold_out_the_rim`]): 3. The x-step's smoothness bends the scatter towards a dim object part
/// that passed as background — the first columns of a panel seen edge-on, a strip beside a
/// nearer occluder — so that its residual, and with it the direct component the pipeline
/// subtracts, shrinks into the fog. It is also the band in which the pipeline looks for
/// uncertain pixels ([`crate::tof::ambiguous`]), which are then judged against a scatter that
/// did not follow them.
pub const HELD_OUT_RING: usize = crate::tof::ambiguous::REACH;

/// The rim of the objects — the [`HELD_OUT_RING`] pixels of background around the pixels whose
/// weight is below `threshold`, in a `width`-wide image — and, per component, the scatter
/// there from the estimate `solve` gives when the rim has no weight, warm-started at `x`; and
/// the CG iterations spent (nothing without objects). The objects and the background beyond
/// keep the estimate they had: the rim's data is the nearest the estimate has to the scatter
/// under an object, and the thin-structure check's decisions were taken with it (solved
/// together with the check's candidates, the rim's extrapolated scatter let the check accept
/// false object pixels beside objects in thin fog).
///
/// Warm-started at the in-sample estimate, which differs from the held-out one only near the
/// rim, the solve takes 3–4 CG iterations on the survey's frames. It keeps the preconditioner
/// of the last x-step, set up for weights that differ only on the rim: CG converges to the
/// held-out system's solution all the same. With the old setup the rim costs a few percent of
/// a 512 × 424 frame (docs/benchmarks.md); a new setup measured more.
fn hold_out_the_rim(
    weights: &[f64],
    x: &[Vec<f64>],
    threshold: f64,
    width: usize,
    mut solve: impl FnMut(&[f64], &mut [Vec<f64>]) -> Result<usize>,
) -> Result<(Vec<usize>, Vec<Vec<f64>>, usize)> {
    let n = weights.len();
    let object: Vec<bool> = weights.iter().map(|&v| v < threshold).collect();
    if !object.contains(&true) {
        return Ok((Vec::new(), vec![Vec::new(); x.len()], 0));
    }
    let near = dilate(&object, width, HELD_OUT_RING);
    let rim: Vec<usize> = (0..n).filter(|&i| near[i] && !object[i]).collect();
    let mut held = weights.to_vec();
    for &i in &rim {
        held[i] = 0.0;
    }
    let mut held_x = x.to_vec();
    let its = solve(&held, &mut held_x)?;
    let values = held_x
        .iter()
        .map(|hc| rim.iter().map(|&i| hc[i]).collect())
        .collect();
    Ok((rim, values, its))
}

/// Contrast statistic against the held-out scatter above which a candidate is object
/// ([`THIN_ROUNDS`]): 5, which pure noise exceeds at about 4 pixels in a million.
pub const THIN_ACCEPT: f64 = 5.0;

/// CG tolerance multiplier of the held-out check's x-steps: the loosest the levels use while
/// their weights still move. The check compares block RMS residuals at the noise's scale, and
/// the fine level's first x-step solves the kept estimate again anyway.
pub(super) const HELD_OUT_TOL_SCALE: f64 = 100.0;

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
    run_irls_vector(
        &[observed],
        None,
        sys,
        std::slice::from_mut(prior),
        cfg,
        stage_prefix,
        monitor,
        tick,
    )
}

/// Algorithm 2 on a vector-valued image whose components share the priors' weights, the noise
/// scale and the outlier weights: each component has its own scatter field and quadratics, and
/// a pixel's residual is the Euclidean norm over the components. With the real and imaginary
/// parts of the observed phasor, an object is a pixel whose phasor departs from the scatter
/// phasor in any direction, in amplitude or in phase; one component is [`run_irls`].
///
/// `observed` and `priors` have one entry per component, each the system's size.
/// `noise`, when given, is the frame's noise model (per component, against the norm over the
/// components): each pixel's residual is divided by the model's σ at the *scatter estimate's*
/// brightness, relative to σ at the observation's median brightness, before the patch RMS, the
/// MAD and the Tukey weights. The inlier hypothesis is "observation = scatter + noise", whose
/// noise follows the scatter's brightness; an object's own brightness must not excuse its
/// residual.
#[allow(clippy::too_many_arguments)]
pub fn run_irls_vector(
    observed: &[&[f64]],
    noise: Option<NoiseModel>,
    sys: &XStepSystem,
    priors: &mut [QuadraticPrior],
    cfg: &IrlsConfig,
    stage_prefix: &str,
    monitor: &Monitor,
    tick: &(dyn Fn(&str) + Sync),
) -> Result<IrlsOutcome> {
    run_irls_vector_from(
        observed,
        noise,
        sys,
        priors,
        cfg,
        None,
        stage_prefix,
        monitor,
        tick,
    )
}

/// [`run_irls_vector`] from `start`, when given: the previous frame's scatter and weights
/// ([`IrlsStart`]) instead of Algorithm 2's initialisation, with no coarse level and no
/// held-out check. The weights are first re-judged from this frame's residuals against the
/// previous scatter at the previous σ₁ (when the start has one); the fine level then measures
/// its scale σ₁ afresh and iterates to convergence.
#[allow(clippy::too_many_arguments)]
pub fn run_irls_vector_from(
    observed: &[&[f64]],
    noise: Option<NoiseModel>,
    sys: &XStepSystem,
    priors: &mut [QuadraticPrior],
    cfg: &IrlsConfig,
    start: Option<&IrlsStart>,
    stage_prefix: &str,
    monitor: &Monitor,
    tick: &(dyn Fn(&str) + Sync),
) -> Result<IrlsOutcome> {
    let n = sys.len();
    let w = sys.width();
    let m = observed.len();
    if m == 0
        || priors.len() != m
        || observed.iter().any(|o| o.len() != n)
        || priors
            .iter()
            .any(|p| p.grid().width() != w || p.grid().height() != sys.height())
        || start.is_some_and(|s| {
            s.weights.len() != n || s.scatter.len() != m || s.scatter.iter().any(|x| x.len() != n)
        })
    {
        return Err(MurkError::Numerical(
            "IRLS buffers do not match the image size".into(),
        ));
    }
    let floor = observed_scale_floor(observed);
    let stage_coarse = format!("{stage_prefix}.coarse");
    let stage_fine = format!("{stage_prefix}.fine");

    let mut noise_scale = noise.map(|model| NoiseScale::new(model, observed, floor));
    let mut weights = start.map_or_else(|| vec![1.0; n], |s| s.weights.clone());
    let mut prior_img = vec![vec![0.0; n]; m];
    let mut rhs = vec![0.0; n];
    let mut scratch = vec![0.0; n * m];
    let mut res2 = vec![0.0; n];
    // Algorithm 2's initialisation: a_k fitted to the observation; x warm-starts at x̃, which is
    // the W = I solution up to the (small) smoothing and prior terms.
    for (c, prior) in priors.iter_mut().enumerate() {
        prior.fit(observed[c]);
        prior.evaluate(&mut prior_img[c]);
    }
    let mut x: Vec<Vec<f64>> = match start {
        Some(s) => s.scatter.clone(),
        None => observed.iter().map(|o| o.to_vec()).collect(),
    };
    // From the previous frame's answer the objects are already found: no coarse level.
    let coarse_iterations = if start.is_some() {
        0
    } else {
        cfg.coarse_iterations
    };
    let mut state = XStepState::new(cfg.solver, sys)?;
    let mut cg_iterations = 0;

    let mut coarse_run = 0;
    let mut fine_run = 0;
    let mut sigma_coarse = None;
    let mut held_out_rejected = 0;
    if coarse_iterations > 0 {
        // Blocks of the coarse level's weights (Eq. 5.16); see `coarse_blocks`.
        let blocks = coarse_blocks(priors[0].grid(), cfg.coarse_subdivision);
        let mut own = OwnSize {
            sys,
            state: &mut state,
            check_state: XStepState::new(cfg.solver, sys)?,
            priors,
            prior_img: &mut prior_img,
            x: &mut x,
            noise_scale: &mut noise_scale,
            observed,
            rhs: &mut rhs,
            monitor,
        };
        let coarse = coarse_level(&mut own, &blocks, cfg, floor, &stage_coarse, monitor, tick)?;
        weights = coarse.weights;
        sigma_coarse = coarse.sigma;
        coarse_run = coarse.iterations_run;
        held_out_rejected = coarse.held_out_rejected;
        cg_iterations += coarse.cg_iterations;
    }

    let mut x_and_a_steps = |weights: &[f64],
                             x: &mut [Vec<f64>],
                             prior_img: &mut [Vec<f64>],
                             priors: &mut [QuadraticPrior],
                             tol_scale: f64|
     -> Result<usize> {
        x_and_a_steps(
            sys, &mut state, priors, weights, observed, prior_img, &mut rhs, x, tol_scale, monitor,
        )
    };
    let mut sigma_fine = None;
    let c_fine = cfg.channel.c_fine;
    // The coarse level's background, where σ₁ is measured when a noise model is known.
    let coarse_inlier: Vec<bool> = weights.iter().map(|&w| w >= 0.5).collect();
    let mut prev_weights = vec![0.0; n];
    let mut conv = Convergence::new();
    let mut fine_converged = cfg.fine_iterations == 0 || cfg.weight_tolerance <= 0.0;
    // From the previous frame's answer, the weights are first re-judged against this frame's
    // observation at the previous frame's scale: the previous weights left the new frame's
    // noise and moved edges out of the first x-step, which then followed them (about three
    // times the CG iterations and twice the reweightings to converge, to the same answer).
    if let Some(s1) = start.and_then(|s| s.sigma_fine) {
        if let Some(ns) = noise_scale.as_mut() {
            ns.update(&x);
        }
        let g = noise_scale.as_ref().map(|ns| &ns.g[..]);
        pixel_weights(&x, observed, g, s1, c_fine, &mut res2, &mut weights);
    }
    for it in 0..cfg.fine_iterations {
        monitor.checkpoint()?;
        let tol_scale = conv.tol_scale();
        let its = x_and_a_steps(&weights, &mut x, &mut prior_img, priors, tol_scale)?;
        cg_iterations += its;
        fine_run += 1;
        prev_weights.copy_from_slice(&weights);
        // σ₁ is measured twice and then fixed (§5.3.4 fixes it from the level's first
        // residuals). From scratch, the first fine x-step still runs under the coarse patch
        // weights: in every rejected patch the background residuals are the priors' misfit,
        // not noise, and inflate σ₁ (3.5× the noise on a simulated medium-fog frame), which
        // then keeps dim object pixels as inliers. That first estimate only seeds the first
        // pixel weights; the residuals of the first x-step solved under pixel weights give the
        // noise scale.
        // With several components the residuals of all of them are pooled: one σ per component.
        if let Some(ns) = noise_scale.as_mut() {
            ns.update(&x);
        }
        let g = noise_scale.as_ref().map(|ns| &ns.g[..]);
        if it <= 1 {
            for c in 0..m {
                scratch[c * n..(c + 1) * n]
                    .par_iter_mut()
                    .zip(x[c].par_iter().zip(observed[c].par_iter()))
                    .enumerate()
                    .for_each(|(i, (s, (xi, oi)))| *s = (xi - oi) / g.map_or(1.0, |g| g[i]));
            }
            let s = match &noise_scale {
                Some(ns) => fine_scale_with_noise_model(&mut scratch, &coarse_inlier, ns),
                None => mad_sigma_in_place(&mut scratch),
            }
            .ok_or_else(|| MurkError::Numerical("non-finite residual at the fine level".into()))?;
            sigma_fine = Some(s.max(floor));
        }
        let s1 = sigma_fine.unwrap_or(floor);
        pixel_weights(&x, observed, g, s1, c_fine, &mut res2, &mut weights);
        tick(&stage_fine);

        // The first fine iteration replaces patch weights by pixel weights: not a convergence
        // step.
        let (dw, flipped) = weight_change(&prev_weights, &weights, cfg.mask_threshold);
        if it > 0 && conv.update(dw, flipped, cfg.weight_tolerance) {
            fine_converged = true;
            break;
        }
        // A fixed point: the x-step found x already solved at the final tolerance, so the
        // weights came out bit for bit as they went in (σ₁ is fixed from the third iteration
        // on). Every further iteration would repeat this one exactly, so it stands for the
        // remaining confirmations of `CONVERGED_RUNS`.
        let repeats = its == 0 && tol_scale <= 1.0 && dw == 0.0 && !flipped;
        if it > 1 && cfg.weight_tolerance > 0.0 && repeats {
            fine_converged = true;
            break;
        }
    }

    let mut thin_accepted = 0;
    let (mut rim, mut rim_scatter) = (Vec::new(), vec![Vec::new(); m]);
    if fine_run > 0 {
        let s1 = sigma_fine.unwrap_or(floor);
        let mut residuals = vec![vec![0.0; n]; m];
        for _ in 0..THIN_ROUNDS {
            monitor.checkpoint()?;
            let g = noise_scale.as_ref().map(|ns| &ns.g[..]);
            signed_residuals(&x, observed, g, &mut residuals);
            let background: Vec<bool> = weights.iter().map(|&v| v >= cfg.mask_threshold).collect();
            let t = coherent_residual(&residuals, &background, w, s1);
            let h = sys.height();
            let band = thin_border_band(w, h);
            let candidate: Vec<bool> = (0..n)
                .map(|i| {
                    let (px, py) = (i % w, i / w);
                    let inside = px >= band && py >= band && px + band < w && py + band < h;
                    inside && background[i] && t[i] > THIN_CANDIDATE
                })
                .collect();
            if !candidate.contains(&true) {
                break;
            }
            let held: Vec<f64> = (0..n)
                .map(|i| if candidate[i] { 0.0 } else { weights[i] })
                .collect();
            let mut held_x = x.clone();
            let (mut held_priors, mut held_img) = (priors.to_vec(), prior_img.clone());
            cg_iterations += x_and_a_steps(
                &held,
                &mut held_x,
                &mut held_img,
                &mut held_priors,
                HELD_OUT_TOL_SCALE,
            )?;
            signed_residuals(&held_x, observed, g, &mut residuals);
            let candidates: Vec<usize> = (0..n).filter(|&i| candidate[i]).collect();
            let contrast =
                coherent_contrast(&residuals, &background, &candidate, w, s1, &candidates);
            let accepted: Vec<usize> = candidates
                .iter()
                .zip(&contrast)
                .filter(|&(_, &t)| t > THIN_ACCEPT)
                .map(|(&i, _)| i)
                .collect();
            if accepted.is_empty() {
                break;
            }
            thin_accepted += accepted.len();
            for i in accepted {
                weights[i] = 0.0;
            }
            // The held-out scatter is the estimate under the new weights but for the rejected
            // candidates, about one pixel in a hundred scattered over the background, whose
            // data the smooth estimate hardly needs: no further solve.
            x = held_x;
            prior_img = held_img;
            priors.clone_from_slice(&held_priors);
            if let Some(ns) = noise_scale.as_mut() {
                ns.update(&x);
            }
        }
        // Only the rim's x is wanted: no a-step, and the last x-step's preconditioner setup.
        let (r, values, its) = hold_out_the_rim(&weights, &x, cfg.mask_threshold, w, |held, x| {
            let mut its = 0;
            for (c, xc) in x.iter_mut().enumerate() {
                its += x_step(
                    sys,
                    &mut state,
                    true,
                    held,
                    observed[c],
                    &prior_img[c],
                    &mut rhs,
                    xc,
                    HELD_OUT_TOL_SCALE,
                    monitor,
                )?;
            }
            Ok(its)
        })?;
        (rim, rim_scatter) = (r, values);
        cg_iterations += its;
    }

    if cfg.coarse_iterations + cfg.fine_iterations == 0 {
        for (xc, pc) in x.iter_mut().zip(&prior_img) {
            xc.copy_from_slice(pc);
        }
    }
    Ok(IrlsOutcome {
        scatter: x,
        weights,
        sigma_coarse,
        sigma_fine,
        cg_iterations,
        coarse_iterations_run: coarse_run,
        fine_iterations_run: fine_run,
        held_out_rejected,
        thin_accepted,
        fine_converged,
        rim,
        rim_scatter,
    })
}

/// The fine level's pixel weights (Eq. 5.11) of an observation against a scatter estimate found
/// elsewhere (on a coarser grid, see `tof::grid`), as the level's last reweighting would give
/// them: each pixel's residual relative to its noise level, at the scale σ₁ measured over
/// `background` as the level measures it ([`fine_scale_with_noise_model`], or the residuals'
/// MAD without a noise model). `observed` and `scatter` hold one image per component.
///
/// `noise` is the frame's noise model relative to its σ at the observation's median brightness
/// ([`NoiseScale::of_observation`]), which does not depend on the scatter and can be prepared
/// beforehand.
pub(super) fn weights_against(
    observed: &[&[f64]],
    scatter: &[Vec<f64>],
    noise: Option<NoiseScale>,
    background: &[bool],
    c_fine: f64,
) -> Result<Vec<f64>> {
    let n = background.len();
    let m = observed.len();
    if m == 0
        || scatter.len() != m
        || observed.iter().any(|o| o.len() != n)
        || scatter.iter().any(|x| x.len() != n)
    {
        return Err(MurkError::Numerical(
            "weights: buffers do not match the image size".into(),
        ));
    }
    // The noise scale was prepared on the same observation, with its floor.
    let floor = noise
        .as_ref()
        .map_or_else(|| observed_scale_floor(observed), |ns| ns.floor);
    if noise.as_ref().is_some_and(|ns| ns.g.len() != n) {
        return Err(MurkError::Numerical(
            "weights: the noise scale does not match the image size".into(),
        ));
    }
    let noise_scale = noise.map(|mut ns| {
        ns.update(scatter);
        ns
    });
    let g = noise_scale.as_ref().map(|ns| &ns.g[..]);
    let mut res = vec![0.0; n * m];
    for c in 0..m {
        res[c * n..(c + 1) * n]
            .par_iter_mut()
            .zip(scatter[c].par_iter().zip(observed[c].par_iter()))
            .enumerate()
            .for_each(|(i, (r, (xi, oi)))| *r = (xi - oi) / g.map_or(1.0, |g| g[i]));
    }
    let sigma = match &noise_scale {
        Some(ns) => fine_scale_with_noise_model(&mut res, background, ns),
        None => mad_sigma_in_place(&mut res),
    }
    .ok_or_else(|| MurkError::Numerical("non-finite residual against the scatter".into()))?
    .max(floor);
    let mut weights = vec![0.0; n];
    pixel_weights(
        scatter,
        observed,
        g,
        sigma,
        c_fine,
        &mut res[..n],
        &mut weights,
    );
    Ok(weights)
}

/// σ₁ of the fine level when the frame's noise model is known: the MAD of the residuals (`res`,
/// `m` components of n pixels, already divided by the relative noise level) over the pixels the
/// coarse level kept as background (`background`), but never below the sensor noise itself.
///
/// Both alternatives are biased. Over all pixels the objects inflate the MAD: with a quarter
/// of the frame object the median residual sits at the inliers' 67 % quantile, σ₁ comes out
/// 1.4× the noise, and a band of a large near object 17 σ off the true scatter passed as
/// background on a thick-fog frame (docs/accuracy.md). Over the background alone the MAD
/// *under*-states the noise: the x-step is a smoother that follows the observation in part,
/// so its residuals are smaller than the noise (0.77× on a medium-fog frame), and pure-noise
/// pixels at 3.3 σ were flagged. The noise model gives the noise directly; the background's
/// MAD still raises σ₁ where the priors' misfit exceeds it. `None` on non-finite residuals.
fn fine_scale_with_noise_model(
    res: &mut [f64],
    background: &[bool],
    ns: &NoiseScale,
) -> Option<f64> {
    let n = background.len();
    let kept = background.iter().filter(|&&b| b).count();
    // Too little background to measure (a frame nearly filled by objects): all pixels.
    let mad = if kept * 10 >= n {
        let mut sel: Vec<f64> = (0..res.len())
            .filter(|&j| background[j % n])
            .map(|j| res[j])
            .collect();
        mad_sigma_in_place(&mut sel)
    } else {
        mad_sigma_in_place(res)
    }?;
    Some(mad.max(1.0 / ns.inv_ref))
}

/// Relative noise level of every pixel under the inlier hypothesis (see [`run_irls_vector`]).
pub(super) struct NoiseScale {
    model: NoiseModel,
    /// 1 / σ at the observation's median brightness.
    inv_ref: f64,
    /// σ(|x|)/σ_ref per pixel, never below 1e-3.
    g: Vec<f64>,
    /// The observation's scale floor ([`scale_floor`]) the reference was bounded by.
    floor: f64,
}

/// The smallest robust scale of an observation (`observed`, one image per component): see
/// [`scale_floor`].
pub(super) fn observed_scale_floor(observed: &[&[f64]]) -> f64 {
    let magnitude = observed
        .iter()
        .map(|o| o.par_iter().map(|v| v.abs()).reduce(|| 0.0, f64::max))
        .fold(0.0, f64::max);
    scale_floor(magnitude)
}

impl NoiseScale {
    /// The noise levels of `model` relative to its σ at the observation's median brightness
    /// (never below `floor`), with every pixel's level at 1 until [`NoiseScale::update`].
    fn new(model: NoiseModel, observed: &[&[f64]], floor: f64) -> Self {
        let n = observed.first().map_or(0, |o| o.len());
        let mut norms: Vec<f64> = (0..n)
            .into_par_iter()
            .map(|i| observed.iter().map(|o| o[i] * o[i]).sum::<f64>().sqrt())
            .collect();
        let med = median_in_place(&mut norms).unwrap_or(0.0);
        NoiseScale {
            model,
            inv_ref: 1.0 / model.sigma(med).max(floor),
            g: vec![1.0; n],
            floor,
        }
    }

    /// [`NoiseScale::new`] at the observation's own scale floor.
    pub(super) fn of_observation(model: NoiseModel, observed: &[&[f64]]) -> Self {
        Self::new(model, observed, observed_scale_floor(observed))
    }

    /// Every pixel's noise level relative to the reference, as last updated.
    pub(super) fn levels(&self) -> &[f64] {
        &self.g
    }

    /// The levels at the brightness of the scatter estimate `x` (one image per component).
    pub(super) fn update(&mut self, x: &[Vec<f64>]) {
        let (model, inv_ref) = (self.model, self.inv_ref);
        self.g.par_iter_mut().enumerate().for_each(|(i, g)| {
            let norm = x.iter().map(|c| c[i] * c[i]).sum::<f64>().sqrt();
            *g = (model.sigma(norm) * inv_ref).max(1e-3);
        });
    }
}

/// `out[c][i] = (x̃_c − x_c)ᵢ / gᵢ`: each component's residual relative to the pixel's noise
/// level `g` (1 without one).
fn signed_residuals(
    x: &[Vec<f64>],
    observed: &[&[f64]],
    noise_scale: Option<&[f64]>,
    out: &mut [Vec<f64>],
) {
    for ((oc, xc), rc) in observed.iter().zip(x).zip(out.iter_mut()) {
        rc.par_iter_mut().enumerate().for_each(|(i, r)| {
            *r = (oc[i] - xc[i]) / noise_scale.map_or(1.0, |g| g[i]);
        });
    }
}

/// `out[i] = Σ_c (x_c − x̃_c)ᵢ² / gᵢ²`: each pixel's squared residual norm over the components,
/// relative to its noise level `g` (1 without one).
pub(super) fn squared_residuals(
    x: &[Vec<f64>],
    observed: &[&[f64]],
    noise_scale: Option<&[f64]>,
    out: &mut [f64],
) {
    out.par_iter_mut().enumerate().for_each(|(i, o)| {
        let ss: f64 = x
            .iter()
            .zip(observed)
            .map(|(xc, oc)| (xc[i] - oc[i]) * (xc[i] - oc[i]))
            .sum();
        *o = match noise_scale {
            Some(g) => ss / (g[i] * g[i]),
            None => ss,
        };
    });
}

/// The fine level's Tukey weight of every pixel (Eq. 5.11) from its residual norm at the scale
/// `sigma` (`res2` receives the squared residuals, see [`squared_residuals`]).
fn pixel_weights(
    x: &[Vec<f64>],
    observed: &[&[f64]],
    noise_scale: Option<&[f64]>,
    sigma: f64,
    c: f64,
    res2: &mut [f64],
    weights: &mut [f64],
) {
    squared_residuals(x, observed, noise_scale, res2);
    let inv_sigma = 1.0 / sigma;
    weights
        .par_iter_mut()
        .zip(res2.par_iter())
        .for_each(|(wi, r2)| *wi = tukey::weight(r2.sqrt() * inv_sigma, c));
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
pub(super) fn x_and_a_step(
    sys: &XStepSystem,
    state: &mut XStepState,
    same_weights: bool,
    prior: &mut QuadraticPrior,
    weights: &[f64],
    observed: &[f64],
    prior_img: &mut [f64],
    rhs: &mut [f64],
    x: &mut [f64],
    tol_scale: f64,
    monitor: &Monitor,
) -> Result<usize> {
    let iterations = x_step(
        sys,
        state,
        same_weights,
        weights,
        observed,
        prior_img,
        rhs,
        x,
        tol_scale,
        monitor,
    )?;
    if sys.is_joint() {
        // x already minimises over a: its uniform fits are the a-step's answer.
        prior.fit(x);
    } else {
        prior.fit_weighted(x, weights);
    }
    prior.evaluate(prior_img);
    Ok(iterations)
}

/// [`x_and_a_step`] for every component under the same `weights`: the components share the
/// weights, so one solver state serves them all and sets its preconditioner up once.
#[allow(clippy::too_many_arguments)]
fn x_and_a_steps(
    sys: &XStepSystem,
    state: &mut XStepState,
    priors: &mut [QuadraticPrior],
    weights: &[f64],
    observed: &[&[f64]],
    prior_img: &mut [Vec<f64>],
    rhs: &mut [f64],
    x: &mut [Vec<f64>],
    tol_scale: f64,
    monitor: &Monitor,
) -> Result<usize> {
    let mut its = 0;
    for c in 0..observed.len() {
        its += x_and_a_step(
            sys,
            state,
            c > 0,
            &mut priors[c],
            weights,
            observed[c],
            &mut prior_img[c],
            rhs,
            &mut x[c],
            tol_scale,
            monitor,
        )?;
    }
    Ok(its)
}

/// The coarse level's solves on the system's own pixels, which it also judges.
struct OwnSize<'a> {
    sys: &'a XStepSystem,
    /// The level's solver state, which the fine level goes on with.
    state: &'a mut XStepState,
    /// The held-out check's, set up for its own weights.
    check_state: XStepState,
    priors: &'a mut [QuadraticPrior],
    prior_img: &'a mut [Vec<f64>],
    x: &'a mut [Vec<f64>],
    noise_scale: &'a mut Option<NoiseScale>,
    observed: &'a [&'a [f64]],
    rhs: &'a mut [f64],
    monitor: &'a Monitor,
}

impl OwnSize<'_> {
    /// The x- and a-steps of every component under `weights`, in the level's solver state or
    /// (`check`) the held-out check's.
    fn steps(&mut self, check: bool, weights: &[f64], tol_scale: f64) -> Result<usize> {
        let state = if check {
            &mut self.check_state
        } else {
            &mut *self.state
        };
        x_and_a_steps(
            self.sys,
            state,
            self.priors,
            weights,
            self.observed,
            self.prior_img,
            self.rhs,
            self.x,
            tol_scale,
            self.monitor,
        )
    }

    /// The noise levels following the scatter.
    fn follow(&mut self) {
        if let Some(ns) = self.noise_scale.as_mut() {
            ns.update(self.x);
        }
    }
}

impl CoarseSolve for OwnSize<'_> {
    fn solve(&mut self, weights: &[f64], tol_scale: f64) -> Result<usize> {
        self.steps(false, weights, tol_scale)
    }

    fn residuals2(&mut self, out: &mut [f64]) -> Result<()> {
        self.follow();
        let g = self.noise_scale.as_ref().map(|ns| &ns.g[..]);
        squared_residuals(self.x, self.observed, g, out);
        Ok(())
    }

    fn held_out_residuals2(&mut self, held: &[f64], out: &mut [f64]) -> Result<usize> {
        let mut xs = self.x.to_vec();
        let (mut priors, mut img) = (self.priors.to_vec(), self.prior_img.to_vec());
        let its = x_and_a_steps(
            self.sys,
            &mut self.check_state,
            &mut priors,
            held,
            self.observed,
            &mut img,
            self.rhs,
            &mut xs,
            HELD_OUT_TOL_SCALE,
            self.monitor,
        )?;
        let g = self.noise_scale.as_ref().map(|ns| &ns.g[..]);
        squared_residuals(&xs, self.observed, g, out);
        Ok(its)
    }

    fn resolve(&mut self, weights: &[f64]) -> Result<usize> {
        let its = self.steps(true, weights, HELD_OUT_TOL_SCALE)?;
        self.follow();
        Ok(its)
    }
}

/// The x-step alone: `x` solved for `weights` from the patch quadratics' current image
/// `prior_img` (which the joint form does not read), without the a-step that follows it in
/// [`x_and_a_step`]. Returns the CG iterations.
#[allow(clippy::too_many_arguments)]
fn x_step(
    sys: &XStepSystem,
    state: &mut XStepState,
    same_weights: bool,
    weights: &[f64],
    observed: &[f64],
    prior_img: &[f64],
    rhs: &mut [f64],
    x: &mut [f64],
    tol_scale: f64,
    monitor: &Monitor,
) -> Result<usize> {
    sys.rhs(weights, observed, prior_img, rhs);
    let stats = state.solve_reusing(sys, weights, rhs, x, tol_scale, same_weights, monitor)?;
    Ok(stats.iterations)
}
