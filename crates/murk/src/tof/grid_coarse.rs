//! A stream's cold frame with Algorithm 2's coarse level solved on the grid and judged at the
//! frame's own size.
//!
//! From scratch, the coarse level and its held-out check ([`HELD_OUT_ROUNDS`]) take three
//! quarters of a 512×424 frame: about ten x-steps on every pixel. Their job is to find the
//! objects' blocks, and the scatter they solve is smooth, so [`cold_frame_on_grid`] solves it
//! on the frame's `factor × factor` block means (a quarter of the pixels at factor 2) and
//! interpolates it back ([`upsampled`]). What it judges stays at full size: every block's RMS
//! residual, the scale σ₂ and the held-out check's statistic are the frame's own pixels'
//! against the interpolated scatter, at their own noise. Judged on the block means instead,
//! whose noise is half a pixel's, the quadratic patches' misfit shows through and the held-out
//! check rejects the wall in thick fog (docs/accuracy.md, "A quieter sensor"). The fine level
//! then runs at full size from the coarse level's scatter and block weights, as it does from
//! scratch, and the frame leaves its answer on the grid for the stream's next frame.

use super::coarse_level::{coarse_blocks, coarse_level, CoarseSolve};
use super::grid::{block_means, coarse_input, grid_params, upsampled, GridFrame, Prepared};
#[cfg(doc)]
use super::irls::HELD_OUT_ROUNDS;
use super::irls::{
    observed_scale_floor, squared_residuals, x_and_a_step, IrlsStart, NoiseScale,
    HELD_OUT_TOL_SCALE,
};
use super::params::{ScatterChannels, TofInput, TofOutput, TofParams};
use super::pipeline::{
    finish, irls_config, prefiltered_pair, scatter_system, separate_observed, PREFILTER_END,
};
use super::quadratic_prior::{PatchGrid, QuadraticPrior};
use super::wls::{XStepSolver, XStepState, XStepSystem};
use crate::error::{MurkError, Result};
use crate::monitor::Monitor;

/// A stream's cold (or restarted) frame, `frame` holding its phasor and block means: the coarse
/// level on the grid, judged at full size, then the fine level and the rest at full size (see
/// the module docs). Returns the frame's estimate and the start on the grid it leaves for the
/// next frame.
///
/// Errors: those of [`TofParams::validate_for`]; `channels` with
/// [`ScatterChannels::AmplitudePhase`]; `coarse_iterations` when it is 0 (no coarse level to
/// solve on the grid); `Cancelled` from `monitor`.
pub(super) fn cold_frame_on_grid(
    input: &TofInput,
    frame: GridFrame,
    params: &TofParams,
    monitor: &Monitor,
) -> Result<(TofOutput, Option<IrlsStart>)> {
    params.validate_for(input)?;
    if params.channels != ScatterChannels::Phasor {
        return Err(MurkError::invalid(
            "channels",
            "a frame on the grid solves the phasor's scatter",
        ));
    }
    if params.coarse_iterations == 0 {
        return Err(MurkError::invalid(
            "coarse_iterations",
            "a cold frame on the grid solves its coarse level there: at least 1",
        ));
    }
    monitor.checkpoint()?;
    let (w, h) = input.amplitude.dims();
    let GridFrame { raw, factor, means } = frame;
    let (cw, ch) = (w / factor, h / factor);
    let (coarse, coarse_raw) = coarse_input(input, means, factor)?;
    let on_grid = grid_params(params, factor);
    on_grid.validate_for(&coarse)?;
    let (prepared, grid_observed) = rayon::join(
        || Prepared::of(input, &raw, params),
        || prefiltered_pair(&coarse_raw.re, &coarse_raw.im, (cw, ch), &on_grid),
    );
    drop(coarse_raw);
    let Prepared {
        noise,
        noise_scale,
        observed,
    } = prepared;
    let solver = XStepSolver::default();
    let cfg = irls_config(params, params.phasor, solver);
    let (sys, patches) = scatter_system(&coarse, &on_grid, params.phasor)?;
    let frame_observed = [&observed[0][..], &observed[1][..]];
    let mut solves = GridSolves::new(
        &sys,
        solver,
        patches,
        grid_observed,
        frame_observed,
        noise_scale,
        (w, h, factor),
        monitor,
    )?;
    let blocks = coarse_blocks(
        &PatchGrid::new(w, h, params.patches_x, params.patches_y),
        params.coarse_subdivision,
    );
    let floor = observed_scale_floor(&frame_observed);
    // The fine level's ticks start at the pre-filter's end again: the coarse level's stay there,
    // so the progress does not move backwards.
    let tick = |stage: &str| monitor.progress(stage, PREFILTER_END);
    let outcome = coarse_level(
        &mut solves,
        &blocks,
        &cfg,
        floor,
        "tof.phasor.coarse",
        monitor,
        &tick,
    )?;
    // No fine level has run, so there is no σ₁ to re-judge the weights at: the fine level starts
    // from the coarse level's block weights and measures σ₁ as it does from scratch.
    let start = IrlsStart {
        scatter: solves.upsampled(&solves.scatter.x)?,
        weights: outcome.weights,
        sigma_fine: None,
    };
    drop(solves);
    let (est, next) = separate_observed(
        input,
        params,
        solver,
        Some(&start),
        observed,
        noise,
        monitor,
    )?;
    let out = finish(input, params, &est, raw, monitor)?;
    let next = next.map(|n| n.box_downsampled(w, h, factor)).transpose()?;
    Ok((out, next))
}

/// The scatter on the grid, one image per component, and the patch quadratics of its priors.
#[derive(Clone)]
struct GridScatter {
    x: Vec<Vec<f64>>,
    priors: Vec<QuadraticPrior>,
    prior_img: Vec<Vec<f64>>,
}

/// The coarse level's solves on the grid, judged at the frame's size ([`CoarseSolve`]).
struct GridSolves<'a> {
    sys: &'a XStepSystem,
    /// The level's solver state, and the held-out check's, each set up for its own weights.
    state: XStepState,
    check_state: XStepState,
    scatter: GridScatter,
    /// The block means as the pipeline sees them (pre-filtered), per component.
    observed: [Vec<f64>; 2],
    rhs: Vec<f64>,
    /// The frame's observation, per component, and its noise levels.
    frame_observed: [&'a [f64]; 2],
    noise: Option<NoiseScale>,
    /// The frame's width and height, and the grid's factor.
    dims: (usize, usize, usize),
    monitor: &'a Monitor,
}

impl<'a> GridSolves<'a> {
    /// Algorithm 2's initialisation on the grid: the priors fitted to the block means, and the
    /// scatter starting at them.
    #[allow(clippy::too_many_arguments)]
    fn new(
        sys: &'a XStepSystem,
        solver: XStepSolver,
        patches: PatchGrid,
        observed: [Vec<f64>; 2],
        frame_observed: [&'a [f64]; 2],
        noise: Option<NoiseScale>,
        dims: (usize, usize, usize),
        monitor: &'a Monitor,
    ) -> Result<Self> {
        let mut priors = vec![QuadraticPrior::new(patches)?; 2];
        let mut prior_img = vec![vec![0.0; sys.len()]; 2];
        for ((prior, img), o) in priors.iter_mut().zip(&mut prior_img).zip(&observed) {
            prior.fit(o);
            prior.evaluate(img);
        }
        Ok(Self {
            sys,
            state: XStepState::new(solver, sys)?,
            check_state: XStepState::new(solver, sys)?,
            scatter: GridScatter {
                x: observed.to_vec(),
                priors,
                prior_img,
            },
            observed,
            rhs: vec![0.0; sys.len()],
            frame_observed,
            noise,
            dims,
            monitor,
        })
    }

    /// Grid images (one per component) interpolated to the frame.
    fn upsampled(&self, x: &[Vec<f64>]) -> Result<Vec<Vec<f64>>> {
        let (w, h, factor) = self.dims;
        x.iter()
            .map(|c| upsampled(c, w / factor, h / factor, factor))
            .collect()
    }

    /// The x- and a-steps of every component on the grid under the frame's `weights` (their
    /// block means), in the level's solver state or (`check`) the held-out check's, applied to
    /// `other` or else to the level's own scatter.
    fn steps(
        &mut self,
        check: bool,
        weights: &[f64],
        tol_scale: f64,
        other: Option<&mut GridScatter>,
    ) -> Result<usize> {
        let (w, h, factor) = self.dims;
        let weights = block_means(weights, w, h, factor)?;
        let scatter = other.unwrap_or(&mut self.scatter);
        let state = if check {
            &mut self.check_state
        } else {
            &mut self.state
        };
        let mut its = 0;
        for c in 0..2 {
            its += x_and_a_step(
                self.sys,
                state,
                c > 0,
                &mut scatter.priors[c],
                &weights,
                &self.observed[c],
                &mut scatter.prior_img[c],
                &mut self.rhs,
                &mut scatter.x[c],
                tol_scale,
                self.monitor,
            )?;
        }
        Ok(its)
    }

    /// Squared residuals of the frame's pixels against `up`, a grid scatter interpolated to
    /// them, at the noise levels as they stand.
    fn frame_residuals2(&self, up: &[Vec<f64>], out: &mut [f64]) {
        let g = self.noise.as_ref().map(NoiseScale::levels);
        squared_residuals(up, &self.frame_observed, g, out);
    }

    /// The grid's scatter interpolated to the frame, with the noise levels following it.
    fn follow(&mut self) -> Result<Vec<Vec<f64>>> {
        let up = self.upsampled(&self.scatter.x)?;
        if let Some(ns) = self.noise.as_mut() {
            ns.update(&up);
        }
        Ok(up)
    }
}

impl CoarseSolve for GridSolves<'_> {
    fn solve(&mut self, weights: &[f64], tol_scale: f64) -> Result<usize> {
        self.steps(false, weights, tol_scale, None)
    }

    fn residuals2(&mut self, out: &mut [f64]) -> Result<()> {
        let up = self.follow()?;
        self.frame_residuals2(&up, out);
        Ok(())
    }

    fn held_out_residuals2(&mut self, held: &[f64], out: &mut [f64]) -> Result<usize> {
        let mut other = self.scatter.clone();
        let its = self.steps(true, held, HELD_OUT_TOL_SCALE, Some(&mut other))?;
        self.frame_residuals2(&self.upsampled(&other.x)?, out);
        Ok(its)
    }

    fn resolve(&mut self, weights: &[f64]) -> Result<usize> {
        let its = self.steps(true, weights, HELD_OUT_TOL_SCALE, None)?;
        self.follow()?;
        Ok(its)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::tof::FogPreset;
    use crate::tof::estimate_tof_depth_from;
    use crate::tof::grid::tests::{assert_agrees, sim_input};

    /// In medium and thick fog, a cold frame with its coarse level on the grid gives the frame
    /// from scratch's mask and ranges, and leaves a start on the grid.
    #[test]
    fn a_cold_frame_on_the_grid_matches_the_frame_from_scratch() {
        let params = TofParams::default();
        for (seed, preset) in [(3, FogPreset::Medium), (1, FogPreset::Thick)] {
            let input = sim_input(seed, preset, 0);
            let (scratch, _) =
                estimate_tof_depth_from(&input, &params, None, &Monitor::noop()).unwrap();
            let frame = GridFrame::of(&input, 2).unwrap();
            let (grid, next) =
                cold_frame_on_grid(&input, frame, &params, &Monitor::noop()).unwrap();
            assert_eq!(next.unwrap().weights.len(), 64 * 53);
            assert_agrees(&scratch, &grid, &format!("{preset:?}"));
        }
    }

    /// Cancelled from the progress sink during the coarse level on the grid, the frame stops.
    #[test]
    fn a_cancel_during_the_coarse_level_stops_the_frame() {
        use std::sync::atomic::{AtomicBool, Ordering};
        use std::sync::Arc;
        let input = sim_input(3, FogPreset::Medium, 0);
        let flag = Arc::new(AtomicBool::new(false));
        let (f2, seen) = (flag.clone(), Arc::new(AtomicBool::new(false)));
        let s2 = seen.clone();
        let monitor = Monitor::new(
            flag,
            Some(Arc::new(move |stage: &str, _| {
                if stage.ends_with(".coarse") {
                    s2.store(true, Ordering::Relaxed);
                    f2.store(true, Ordering::Relaxed);
                }
            })),
        );
        let frame = GridFrame::of(&input, 2).unwrap();
        let e = cold_frame_on_grid(&input, frame, &TofParams::default(), &monitor).unwrap_err();
        assert_eq!(e, MurkError::Cancelled);
        assert!(seen.load(Ordering::Relaxed));
    }

    #[test]
    fn channels_and_a_missing_coarse_level_are_refused_naming_the_field() {
        let input = sim_input(1, FogPreset::Medium, 0);
        let run = |p: TofParams| {
            let frame = GridFrame::of(&input, 2).unwrap();
            cold_frame_on_grid(&input, frame, &p, &Monitor::noop())
                .unwrap_err()
                .to_string()
        };
        let e = run(TofParams {
            channels: ScatterChannels::AmplitudePhase,
            ..TofParams::default()
        });
        assert!(e.contains("channels"), "{e}");
        let e = run(TofParams {
            coarse_iterations: 0,
            ..TofParams::default()
        });
        assert!(e.contains("coarse_iterations"), "{e}");
    }
}
