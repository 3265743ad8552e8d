//! ToF in a stream: each frame starts from the previous frame's answer (the temporal prior of a
//! sensor session), and from scratch when that answer no longer fits.
//!
//! What is carried from frame to frame: the scatter estimate (the phasor's two parts), the
//! final IRLS weights and the fine scale σ₁ of the previous frame, 24 bytes a pixel (5.2 MB at
//! 512×424). The next frame skips Algorithm 2's coarse level, whose work is to find the objects
//! from "no object": its residuals against the previous scatter are weighted at the previous
//! σ₁, and the fine level runs from there to convergence ([`IrlsStart`]). What is dropped, and
//! when:
//! - a frame of another size, a failed frame, or the amplitude/phase channels
//!   (`ScatterChannels::AmplitudePhase`), which always start cold;
//! - a frame whose observation, where the previous frame saw only fog, departs from the previous
//!   scatter estimate by more than [`MAX_SCATTER_CHANGE`] (median relative difference): the fog
//!   changed suddenly, and from so far off the fine level can settle on a wrong answer, so the
//!   frame is computed from scratch ([`TofStart::Restarted`]);
//! - a frame whose object mask, computed from the start, differs from the start's in more than
//!   [`MAX_CHANGED_FRACTION`] of the pixels: the scene changed (a cut), and the frame is computed
//!   again from scratch ([`TofStart::Restarted`]).
//!
//! With a scatter grid ([`TofTracker::with_scatter_grid`]) the warm frames solve the scatter on
//! the frame's block means and decide everything else at full size
//! ([`estimate_tof_depth_on_grid`]); the carried start lives on the grid (6 bytes a pixel at
//! factor 2). Cold and restarted frames solve their coarse level on the grid too, judge it at
//! full size, and run the fine level at full size (`tof::grid_coarse`): the same answer in
//! about 0.6 of the time (docs/benchmarks.md). The checks for a fog change and a cut compare the
//! grid's block means and weights.

use rayon::prelude::*;

use super::grid::{solve_on_grid, GridFrame};
use super::grid_coarse::cold_frame_on_grid;
use super::irls::IrlsStart;
use super::params::{ScatterChannels, TofInput, TofOutput, TofParams};
use super::pipeline::estimate_tof_depth_from;
use crate::error::Result;
use crate::monitor::Monitor;

/// Largest fraction of pixels whose object/background class may change from the start to the
/// answer before the frame is computed again from scratch.
pub const MAX_CHANGED_FRACTION: f64 = 0.2;

/// Largest median relative difference, over the previous frame's fog-only pixels, between the
/// observed phasor and the previous scatter estimate before a frame starts from scratch. Sensor
/// noise gives about 2 % on the simulated camera and a fog drifting by 10 % over 10 s under 1 %
/// a frame at 10 fps; a fog that thickens by half between two frames gives tens of percent.
pub const MAX_SCATTER_CHANGE: f64 = 0.1;

/// How a frame was computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TofStart {
    /// From scratch: the first frame, or after a dropped start.
    Cold,
    /// From the previous frame's answer.
    Warm,
    /// From scratch although the previous frame's answer was at hand, because the fog changed
    /// suddenly or too much of the mask changed (a scene cut).
    Restarted,
}

/// A frame's estimate and how it was computed.
#[derive(Clone, Debug)]
pub struct TrackedTof {
    /// The estimate.
    pub output: TofOutput,
    /// How it started.
    pub start: TofStart,
}

/// Computes a stream's frames, each from the previous one's answer where that still fits.
#[derive(Debug)]
pub struct TofTracker {
    params: TofParams,
    /// Warm frames solve the scatter on blocks of this many pixels a side (1: the frame's).
    scatter_grid: usize,
    /// The previous frame's size, and its answer on the grid it was carried to.
    start: Option<((usize, usize), Carried)>,
}

/// A start and the grid factor it lives on.
#[derive(Debug)]
struct Carried {
    factor: usize,
    start: IrlsStart,
}

/// Largest scatter grid factor a tracker accepts: 4 keeps the true scatter within 0.1 mm of
/// the noise floor on the simulated obstacles (docs/benchmarks.md), and coarser blocks would
/// average objects a few pixels wide into the fog.
pub const MAX_SCATTER_GRID: usize = 4;

/// Fewest pixels along the longer side of the grid a warm frame is solved on; smaller frames
/// run at their own size. On a simulated 64×52 stream the 32×26 grid marked 30 % more object
/// pixels than the frames at full size (its noise model is fitted to 800 block means, and each
/// quadratic patch of the prior spans 8×6 of them); the 64×53 grid of 128×106 frames agrees
/// with them to a pixel.
pub const MIN_GRID_SIDE: usize = 64;

impl TofTracker {
    /// A tracker for frames computed with `params`, every frame at its own size.
    pub fn new(params: TofParams) -> Self {
        Self {
            params,
            scatter_grid: 1,
            start: None,
        }
    }

    /// A tracker whose warm frames solve the scatter on `factor × factor` block means, and whose
    /// cold frames solve their coarse level there (see the module docs); frames whose sides
    /// `factor` does not divide, or whose grid would be shorter than [`MIN_GRID_SIDE`] on its
    /// longer side, run at their own size. Errors name
    /// `scatter_grid` outside 1..=[`MAX_SCATTER_GRID`].
    pub fn with_scatter_grid(params: TofParams, factor: usize) -> Result<Self> {
        if !(1..=MAX_SCATTER_GRID).contains(&factor) {
            return Err(crate::error::MurkError::invalid(
                "scatter_grid",
                format!("must be in 1..={MAX_SCATTER_GRID}, got {factor}"),
            ));
        }
        Ok(Self {
            scatter_grid: factor,
            ..Self::new(params)
        })
    }

    /// The grid factor of warm frames (1: none).
    pub fn scatter_grid(&self) -> usize {
        self.scatter_grid
    }

    /// The parameters every frame is computed with.
    pub fn params(&self) -> &TofParams {
        &self.params
    }

    /// Estimates `input`, from the previous frame's answer when there is one of this size; see
    /// the module docs. An error leaves the tracker as it was.
    pub fn estimate(&mut self, input: &TofInput, monitor: &Monitor) -> Result<TrackedTof> {
        let dims = input.amplitude.dims();
        let threshold = self.params.mask_threshold;
        let g = self.scatter_grid;
        let fits = dims.0.is_multiple_of(g)
            && dims.1.is_multiple_of(g)
            && dims.0.max(dims.1) / g >= MIN_GRID_SIDE;
        let factor = if fits { g } else { 1 };
        let start = self
            .start
            .as_ref()
            .filter(|(d, c)| *d == dims && c.factor == factor)
            .map(|(_, c)| &c.start);
        // On the grid: the frame's phasor and block means, for the check and the solve.
        let phasor = self.params.channels == ScatterChannels::Phasor;
        let mut grid = (factor >= 2 && phasor)
            .then(|| GridFrame::of(input, factor))
            .transpose()?;
        let kind = match start {
            None => TofStart::Cold,
            Some(start)
                if scatter_change(input, grid.as_ref(), start, threshold) > MAX_SCATTER_CHANGE =>
            {
                TofStart::Restarted
            }
            Some(start) => {
                let (output, next) = match grid.take() {
                    Some(frame) => {
                        input.validate()?;
                        solve_on_grid(input, frame, &self.params, start, None, monitor)?
                    }
                    None => estimate_tof_depth_from(input, &self.params, Some(start), monitor)?,
                };
                let changed = next
                    .as_ref()
                    .map_or(1.0, |n| changed_fraction(start, n, threshold));
                if changed <= MAX_CHANGED_FRACTION {
                    self.start = next.map(|start| (dims, Carried { factor, start }));
                    return Ok(TrackedTof {
                        output,
                        start: TofStart::Warm,
                    });
                }
                TofStart::Restarted
            }
        };
        // From scratch: the coarse level on the grid where the grid applies, else wholly at
        // full size (the amplitude/phase channels, or no coarse level).
        let on_grid = factor >= 2 && phasor && self.params.coarse_iterations > 0;
        let (output, next) = if on_grid {
            input.validate()?;
            let frame = match grid {
                Some(frame) => frame,
                // The frame went to the warm attempt, which a cut undid.
                None => GridFrame::of(input, factor)?,
            };
            cold_frame_on_grid(input, frame, &self.params, monitor)?
        } else {
            let (output, next) = estimate_tof_depth_from(input, &self.params, None, monitor)?;
            let next = next
                .map(|n| n.box_downsampled(dims.0, dims.1, factor))
                .transpose()?;
            (output, next)
        };
        self.start = next.map(|start| (dims, Carried { factor, start }));
        Ok(TrackedTof {
            output,
            start: kind,
        })
    }
}

/// Median of |observed − scatter| / |scatter| over the pixels `start` took for fog alone (weight
/// at least `threshold`), with the observation as the raw phasor (its block means in `grid`,
/// when `start` lives on the grid); 0 when there are none.
fn scatter_change(
    input: &TofInput,
    grid: Option<&GridFrame>,
    start: &IrlsStart,
    threshold: f32,
) -> f64 {
    let t = f64::from(threshold);
    let [re, im] = match start.scatter.as_slice() {
        [re, im] => [re, im],
        _ => return 0.0,
    };
    // In parallel: this check runs before every warm frame, and at 512×424 it took 7 ms on one
    // core. The median of the same values does not depend on their order. One square root a
    // pixel instead of two `hypot`s: the phasors are far from overflow.
    let relative = |(or, oi): (f64, f64), w: f64, (sr, si): (f64, f64)| -> Option<f64> {
        let s2 = sr * sr + si * si;
        let (dr, di) = (or - sr, oi - si);
        (w >= t && s2 > 0.0).then(|| ((dr * dr + di * di) / s2).sqrt())
    };
    let scatter = re.par_iter().zip(im.par_iter()).map(|(&r, &i)| (r, i));
    let weights = start.weights.par_iter();
    let mut rel: Vec<f64> = match grid {
        Some(g) => g
            .means
            .0
            .par_iter()
            .zip(g.means.1.par_iter())
            .map(|(&r, &i)| (r, i))
            .zip(weights)
            .zip(scatter)
            .filter_map(|((o, &w), s)| relative(o, w, s))
            .collect(),
        None => input
            .amplitude
            .data()
            .par_iter()
            .zip(input.phase.data().par_iter())
            .map(|(&a, &p)| {
                let (sin, cos) = f64::from(p).sin_cos();
                (f64::from(a) * cos, f64::from(a) * sin)
            })
            .zip(weights)
            .zip(scatter)
            .filter_map(|((o, &w), s)| relative(o, w, s))
            .collect(),
    };
    super::tukey::median_in_place(&mut rel).unwrap_or(0.0)
}

/// Fraction of pixels whose class (object: weight below `threshold`) differs between two runs.
fn changed_fraction(a: &IrlsStart, b: &IrlsStart, threshold: f32) -> f64 {
    let t = f64::from(threshold);
    let changed = a
        .weights
        .iter()
        .zip(&b.weights)
        .filter(|(x, y)| (**x < t) != (**y < t))
        .count();
    changed as f64 / a.weights.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulate::{simulate_tof_sequence_frame, TofMotion, TofSimConfig};
    use crate::tof::{estimate_tof_depth, estimate_tof_depth_from};
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    fn frame(cfg: &TofSimConfig, motion: &TofMotion, k: usize) -> TofInput {
        let f = simulate_tof_sequence_frame(cfg, motion, k, &Monitor::noop()).unwrap();
        TofInput {
            amplitude: f.amplitude,
            phase: f.phase,
            intrinsics: Some(f.intrinsics),
        }
    }

    /// Pixels whose mask differs between the tracked answer and a cold start's.
    fn differs_from_cold(tracked: &TrackedTof, input: &TofInput, params: &TofParams) -> usize {
        let cold = estimate_tof_depth(input, params, &Monitor::noop()).unwrap();
        tracked
            .output
            .mask
            .data()
            .iter()
            .zip(cold.mask.data())
            .filter(|(a, b)| a != b)
            .count()
    }

    #[test]
    fn a_stream_starts_cold_then_warm_and_restarts_after_a_cut() {
        let cfg = TofSimConfig {
            seed: 5,
            ..TofSimConfig::with_size(96, 80)
        };
        let motion = TofMotion {
            cut_every: Some(3),
            ..TofMotion::default()
        };
        cold_warm_warm_restarted(TofTracker::new(TofParams::default()), &cfg, &motion);
    }

    /// Streams four frames of `cfg` with a cut before the fourth through `tracker`: every
    /// answer the same as from scratch but for at most 2 % of the mask, and the starts cold,
    /// warm, warm, then not cold.
    fn cold_warm_warm_restarted(mut tracker: TofTracker, cfg: &TofSimConfig, motion: &TofMotion) {
        let mut starts = Vec::new();
        for k in 0..4 {
            let input = frame(cfg, motion, k);
            let tracked = tracker.estimate(&input, &Monitor::noop()).unwrap();
            assert_eq!(tracked.output.mask.dims(), input.amplitude.dims());
            // The same answer as from scratch, to within the IRLS's convergence.
            let diff = differs_from_cold(&tracked, &input, tracker.params());
            assert!(
                diff * 50 <= input.amplitude.pixel_count(),
                "frame {k}: {diff} px"
            );
            starts.push(tracked.start);
        }
        assert_eq!(starts[0], TofStart::Cold);
        assert_eq!(&starts[1..3], &[TofStart::Warm, TofStart::Warm]);
        assert!(starts[3] != TofStart::Cold, "{starts:?}");
    }

    /// Fog that thickens threefold from one frame to the next: the previous frame's scatter is
    /// far off, the tracker starts from scratch and ends where a cold start does.
    #[test]
    fn a_sudden_change_of_fog_still_gives_the_cold_answer() {
        let thin = TofSimConfig {
            seed: 7,
            beta_per_mm: Some(2e-4),
            ..TofSimConfig::with_size(96, 80)
        };
        let thick = TofSimConfig {
            beta_per_mm: Some(6e-4),
            ..thin.clone()
        };
        let still = TofMotion {
            max_speed_m_per_s: 0.0,
            fog_drift: 0.0,
            ..TofMotion::default()
        };
        let mut tracker = TofTracker::new(TofParams::default());
        let a = frame(&thin, &still, 0);
        let b = frame(&thick, &still, 1);
        tracker.estimate(&a, &Monitor::noop()).unwrap();
        let tracked = tracker.estimate(&b, &Monitor::noop()).unwrap();
        let diff = differs_from_cold(&tracked, &b, tracker.params());
        assert!(
            diff * 50 <= b.amplitude.pixel_count(),
            "{diff} px differ ({:?})",
            tracked.start
        );
        assert_eq!(tracked.start, TofStart::Restarted);
    }

    /// Fine-level iterations of one frame from `start`, counted by its progress ticks, and its
    /// mask.
    fn fine_iterations(
        input: &TofInput,
        params: &TofParams,
        start: &IrlsStart,
    ) -> (usize, Vec<f32>) {
        let ticks = Arc::new(AtomicUsize::new(0));
        let counter = ticks.clone();
        let monitor = Monitor::new(
            Arc::default(),
            Some(Arc::new(move |stage: &str, _| {
                if stage.ends_with(".fine") {
                    counter.fetch_add(1, Ordering::Relaxed);
                }
            })),
        );
        let (out, _) = estimate_tof_depth_from(input, params, Some(start), &monitor).unwrap();
        let n = ticks.load(Ordering::Relaxed);
        (n, out.mask.data().to_vec())
    }

    /// A warm frame first weights its residuals at the previous σ₁: it converges in fewer
    /// reweightings than from the previous frame's weights, to the same mask.
    #[test]
    fn weighting_at_the_previous_scale_first_saves_iterations() {
        let cfg = TofSimConfig {
            seed: 2,
            ..TofSimConfig::with_size(128, 106)
        };
        let motion = TofMotion::default();
        let params = TofParams {
            light_position_m: Some(cfg.light_position_m()),
            ..TofParams::default()
        };
        let first = frame(&cfg, &motion, 0);
        let (_, start) = estimate_tof_depth_from(&first, &params, None, &Monitor::noop()).unwrap();
        let start = start.unwrap();
        assert!(start.sigma_fine.is_some());
        let next = frame(&cfg, &motion, 1);
        let (weighted, mask) = fine_iterations(&next, &params, &start);
        let unweighted_start = IrlsStart {
            sigma_fine: None,
            ..start.clone()
        };
        let (unweighted, mask_unweighted) = fine_iterations(&next, &params, &unweighted_start);
        assert!(
            weighted < unweighted,
            "{weighted} vs {unweighted} fine iterations"
        );
        let differ = mask
            .iter()
            .zip(&mask_unweighted)
            .filter(|(a, b)| a != b)
            .count();
        assert!(differ <= mask.len() / 1000, "{differ} mask pixels differ");
    }

    /// On a 2×2 grid the stream goes cold, warm, warm, restarted as at full size, and every
    /// frame's mask is the cold frame's but for a few pixels on the objects' outlines.
    #[test]
    fn a_stream_on_the_grid_agrees_with_cold_frames() {
        let cfg = TofSimConfig {
            seed: 5,
            ..TofSimConfig::with_size(128, 106)
        };
        let motion = TofMotion {
            cut_every: Some(3),
            ..TofMotion::default()
        };
        let tracker = TofTracker::with_scatter_grid(TofParams::default(), 2).unwrap();
        assert_eq!(tracker.scatter_grid(), 2);
        cold_warm_warm_restarted(tracker, &cfg, &motion);
    }

    /// A grid that does not divide the frame's sides, or would be too small, leaves its frames
    /// at full size: the answers of a tracker without a grid, warm from the second frame on.
    #[test]
    fn a_grid_that_does_not_fit_the_frame_runs_at_full_size() {
        let motion = TofMotion::default();
        for (w, h) in [(63, 53), (64, 52)] {
            let cfg = TofSimConfig::with_size(w, h);
            let mut on_grid = TofTracker::with_scatter_grid(TofParams::default(), 2).unwrap();
            let mut full = TofTracker::new(TofParams::default());
            for k in 0..2 {
                let input = frame(&cfg, &motion, k);
                let a = on_grid.estimate(&input, &Monitor::noop()).unwrap();
                let b = full.estimate(&input, &Monitor::noop()).unwrap();
                assert_eq!(a.start, b.start);
                assert_eq!(a.output.range_m.data(), b.output.range_m.data(), "{w}x{h}");
                assert_eq!(a.output.mask.data(), b.output.mask.data(), "{w}x{h}");
            }
            assert_eq!(on_grid.start.as_ref().map(|(_, c)| c.factor), Some(1));
        }
    }

    /// Without a coarse level there is nothing to solve on the grid from scratch: the cold
    /// frame is the full-size frame's bit for bit, and the warm frames go on on the grid.
    #[test]
    fn without_a_coarse_level_a_cold_frame_runs_at_full_size() {
        let params = TofParams {
            coarse_iterations: 0,
            ..TofParams::default()
        };
        let cfg = TofSimConfig {
            seed: 2,
            ..TofSimConfig::with_size(128, 106)
        };
        let input = frame(&cfg, &TofMotion::default(), 0);
        let mut tracker = TofTracker::with_scatter_grid(params.clone(), 2).unwrap();
        let tracked = tracker.estimate(&input, &Monitor::noop()).unwrap();
        let (full, _) = estimate_tof_depth_from(&input, &params, None, &Monitor::noop()).unwrap();
        assert_eq!(tracked.start, TofStart::Cold);
        assert_eq!(tracked.output.mask.data(), full.mask.data());
        assert_eq!(tracked.output.range_m.data(), full.range_m.data());
        assert_eq!(tracker.start.as_ref().map(|(_, c)| c.factor), Some(2));
    }

    #[test]
    fn a_grid_outside_its_range_is_refused_naming_it() {
        for g in [0, MAX_SCATTER_GRID + 1] {
            let e = TofTracker::with_scatter_grid(TofParams::default(), g).unwrap_err();
            assert!(e.to_string().contains("scatter_grid"), "{e}");
        }
    }

    #[test]
    fn a_frame_of_another_size_starts_cold() {
        let motion = TofMotion::default();
        let mut tracker = TofTracker::new(TofParams::default());
        let a = frame(&TofSimConfig::with_size(64, 53), &motion, 0);
        let b = frame(&TofSimConfig::with_size(48, 40), &motion, 1);
        tracker.estimate(&a, &Monitor::noop()).unwrap();
        let t = tracker.estimate(&b, &Monitor::noop()).unwrap();
        assert_eq!(t.start, TofStart::Cold);
    }
}
