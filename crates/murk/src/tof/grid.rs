//! A stream's frames on a grid coarser than the frames.
//!
//! Fog's backscatter varies slowly across the image: the true scatter averaged over 2×2 blocks
//! and interpolated back costs at most 0.1 mm of range over the sensor-noise floor on every
//! simulated 512×424 frame, and the x-step's work follows the pixels (docs/benchmarks.md, "The
//! scatter on a coarser grid"). [`estimate_tof_depth_on_grid`] computes a stream's warm frame
//! that way: the fine level of Algorithm 2 runs on the frame's `factor × factor` block means
//! ([`block_means`]) from the previous frame's start carried to that grid
//! ([`IrlsStart::box_downsampled`]); the scatter is interpolated back to the frame, and the
//! mask, the ranges and their uncertainties are decided at the frame's own size. Only frames
//! from a start run their fine level on the grid: from scratch, a block mean's halved noise
//! lets the quadratic patches' misfit show, and judged on the grid the coarse level's held-out
//! check fails in thick fog (docs/accuracy.md, "A quieter sensor") and the fine level peels
//! the wall for tens of iterations. A cold frame solves its coarse level on the grid but judges
//! it at full size, and runs its fine level at full size (`tof::grid_coarse`,
//! [`TofTracker::with_scatter_grid`](super::TofTracker::with_scatter_grid)).

use rayon::prelude::*;

use super::ambiguous::uncertain_pixels;
use super::irls::thin_border_band;
use super::irls::{weights_against, IrlsStart, NoiseScale};
use super::noise_model::NoiseModel;
use super::params::{ScatterChannels, TofInput, TofOutput, TofParams};
use super::pipeline::{
    compose, prefiltered_pair, separate, wrap_phase, Direct, RawPhasor, ScatterEstimate,
};
use super::wls::XStepSolver;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;

/// A stream's warm frame with the scatter solved on the grid of `factor × factor` block means,
/// from `start`, the previous frame's answer on that grid; returns the frame's estimate at its
/// own size and the start (on the grid) it leaves for the next frame. See the module docs.
///
/// What differs from [`estimate_tof_depth_from`](super::estimate_tof_depth_from) at full size:
/// the scatter is bilinear between block centres, and each pixel's IRLS weight (hence the mask)
/// is the fine level's Tukey weight of its own residual against that scatter, at the scale σ₁
/// measured over the grid's background at the frame's noise. The thin-structure check
/// ([`THIN_ROUNDS`](super::irls::THIN_ROUNDS)) runs on the block means only.
///
/// Errors: those of [`TofInput::validate`] and [`TofParams::validate_for`]; `factor` when it is
/// 0 or does not divide both sides; `start` when its images are not the grid's; `channels`
/// with [`ScatterChannels::AmplitudePhase`], which has no start; `Cancelled` from `monitor`.
pub fn estimate_tof_depth_on_grid(
    input: &TofInput,
    params: &TofParams,
    start: &IrlsStart,
    factor: usize,
    monitor: &Monitor,
) -> Result<(TofOutput, Option<IrlsStart>)> {
    input.validate()?;
    let frame = GridFrame::of(input, factor)?;
    solve_on_grid(input, frame, params, start, None, monitor)
}

/// A frame's raw phasor and its block means, computed once for both the tracker's checks and
/// the solve.
pub(super) struct GridFrame {
    pub(super) raw: RawPhasor,
    pub(super) factor: usize,
    /// The block means' real and imaginary parts, row-major on the grid.
    pub(super) means: (Vec<f64>, Vec<f64>),
}

impl GridFrame {
    /// The raw phasor of `input` and its `factor × factor` block means. Errors name `factor`
    /// unless it divides both sides.
    pub(super) fn of(input: &TofInput, factor: usize) -> Result<Self> {
        let (w, h) = input.amplitude.dims();
        let raw = RawPhasor::of(input);
        let (re, im) = rayon::join(
            || block_means(&raw.re, w, h, factor),
            || block_means(&raw.im, w, h, factor),
        );
        Ok(Self {
            raw,
            factor,
            means: (re?, im?),
        })
    }
}

/// The full-size observation as the pipeline sees it (the raw phasor pre-filtered, in `f64`),
/// its noise model, and the pixels' noise levels relative to its median brightness: what a
/// frame on the grid is decided against at its own size.
pub(super) struct Prepared {
    pub(super) noise: Option<NoiseModel>,
    pub(super) noise_scale: Option<NoiseScale>,
    pub(super) observed: [Vec<f64>; 2],
}

impl Prepared {
    /// Prepared from the frame's raw phasor.
    pub(super) fn of(input: &TofInput, raw: &RawPhasor, params: &TofParams) -> Self {
        let (w, h) = input.amplitude.dims();
        let (noise, observed) = rayon::join(
            || NoiseModel::fit(&raw.re, &raw.im, input.amplitude.data(), w),
            || prefiltered_pair(&raw.re, &raw.im, (w, h), params),
        );
        let noise_scale =
            noise.map(|m| NoiseScale::of_observation(m, &[&observed[0], &observed[1]]));
        Self {
            noise,
            noise_scale,
            observed,
        }
    }
}

/// [`estimate_tof_depth_on_grid`] of a validated `input` whose phasor `frame` holds; `prepared`
/// is its full-size observation when the caller has it (else it is prepared beside the solve).
pub(super) fn solve_on_grid(
    input: &TofInput,
    frame: GridFrame,
    params: &TofParams,
    start: &IrlsStart,
    prepared: Option<Prepared>,
    monitor: &Monitor,
) -> Result<(TofOutput, Option<IrlsStart>)> {
    params.validate_for(input)?;
    let (w, h) = input.amplitude.dims();
    let factor = frame.factor;
    if params.channels != ScatterChannels::Phasor {
        return Err(MurkError::invalid(
            "channels",
            "a frame on the grid starts from the previous frame's phasor scatter",
        ));
    }
    let (cw, ch) = (w / factor, h / factor);
    if start.weights.len() != cw * ch || start.scatter.iter().any(|c| c.len() != cw * ch) {
        return Err(MurkError::invalid(
            "start",
            format!(
                "its images are not the {cw}×{ch} grid of the frame's {factor}×{factor} blocks"
            ),
        ));
    }
    monitor.checkpoint()?;
    let GridFrame { raw, means, .. } = frame;
    let (coarse, coarse_raw) = coarse_input(input, means, factor)?;
    let coarse_params = grid_params(params, factor);
    coarse_params.validate_for(&coarse)?;
    let solve = || {
        separate(
            &coarse,
            &coarse_raw,
            &coarse_params,
            XStepSolver::default(),
            Some(start),
            monitor,
        )
    };
    let (solved, prepared) = match prepared {
        Some(prepared) => (solve(), prepared),
        // The full-size observation, pre-filtered as a cold frame's is, and its noise model do
        // not depend on the solve: they are prepared beside it, on the cores its many short
        // parallel loops on the small grid leave idle.
        None => rayon::join(solve, || Prepared::of(input, &raw, params)),
    };
    let Prepared {
        noise,
        noise_scale,
        observed: [observed_re, observed_im],
    } = prepared;
    let (grid_est, next) = solved?;
    drop(coarse_raw);
    monitor.checkpoint()?;

    // Back at the frame's size: the scatter between block centres.
    let scatter = vec![
        upsampled(&grid_est.scatter_re, cw, ch, factor)?,
        upsampled(&grid_est.scatter_im, cw, ch, factor)?,
    ];
    let background: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|i| !grid_est.object[(i / w / factor) * cw + (i % w) / factor])
        .collect();
    let t = f64::from(params.mask_threshold);
    // Each pixel's weight, the mask and the uncertain pixels beside it (whose medians and
    // windows leave a core idle at times), beside the direct component, which needs neither.
    let (decided, direct) = rayon::join(
        || -> Result<_> {
            let weights = weights_against(
                &[&observed_re, &observed_im],
                &scatter,
                noise_scale,
                &background,
                params.phasor.c_fine,
            )?;
            let object: Vec<bool> = weights.par_iter().map(|&v| v < t).collect();
            let uncertain = uncertain_pixels(
                &raw.re,
                &raw.im,
                &scatter[0],
                &scatter[1],
                &object,
                noise.as_ref(),
                w,
                thin_border_band(w, h),
            );
            Ok((weights, object, uncertain))
        },
        || {
            Direct::of(
                input,
                params,
                [&observed_re, &observed_im],
                [&scatter[0], &scatter[1]],
                noise,
            )
        },
    );
    let (weights, object, uncertain) = decided?;
    drop(raw);
    let [scatter_re, scatter_im]: [Vec<f64>; 2] = scatter
        .try_into()
        .map_err(|_| MurkError::Numerical("two scatter components".into()))?;
    let est = ScatterEstimate {
        object,
        observed_re,
        observed_im,
        scatter_re,
        scatter_im,
        weight_amplitude: weights.clone(),
        weight_phase: weights,
        noise,
        warnings: grid_est.warnings,
    };
    let out = compose(input, params, &est, &uncertain, direct)?;
    monitor.progress("tof.compose", 1.0);
    Ok((out, next))
}

/// `params` for the grid of `factor × factor` blocks: the symmetry row in grid rows.
pub(super) fn grid_params(params: &TofParams, factor: usize) -> TofParams {
    TofParams {
        symmetry_row: params
            .symmetry_row
            .map(|r| (r - (factor as f64 - 1.0) / 2.0) / factor as f64),
        ..params.clone()
    }
}

/// The frame's block means (`means`: real and imaginary parts) as a frame of its own, with the
/// intrinsics of the coarser pixels, and as its raw phasor (the means themselves, which the
/// polar images would only give back through a round of trigonometry).
pub(super) fn coarse_input(
    input: &TofInput,
    means: (Vec<f64>, Vec<f64>),
    factor: usize,
) -> Result<(TofInput, RawPhasor)> {
    let (w, h) = input.amplitude.dims();
    let (re, im) = means;
    let (amplitude, phase): (Vec<f32>, Vec<f32>) = re
        .par_iter()
        .zip(im.par_iter())
        .map(|(&r, &i)| ((r * r + i * i).sqrt() as f32, wrap_phase(i.atan2(r)) as f32))
        .unzip();
    let image = |data| {
        ImageF32::from_vec(w / factor, h / factor, 1, data)
            .map_err(|e| MurkError::Numerical(e.to_string()))
    };
    let to_f32 = |v: Vec<f64>| -> Vec<f32> { v.into_par_iter().map(|x| x as f32).collect() };
    let input = TofInput {
        amplitude: image(amplitude)?,
        phase: image(phase)?,
        intrinsics: input.intrinsics.map(|k| k.box_downsampled(factor)),
    };
    Ok((
        input,
        RawPhasor {
            re: to_f32(re),
            im: to_f32(im),
        },
    ))
}

/// Bilinear interpolation of a `cw × ch` grid of `factor × factor` block means back to the
/// frame's `cw·factor × ch·factor` pixels: a pixel's centre lies at `(x − (factor − 1)/2) /
/// factor` in grid pixels, and beyond the outermost block centres the edge values hold. Errors
/// name `factor` when it is 0 and `values` when there are not `cw × ch` of them (at least one).
pub fn upsampled(values: &[f64], cw: usize, ch: usize, factor: usize) -> Result<Vec<f64>> {
    if factor == 0 {
        return Err(MurkError::invalid("factor", "must be at least 1"));
    }
    if cw == 0 || ch == 0 || values.len() != cw * ch {
        return Err(MurkError::invalid(
            "values",
            format!("{} values for a {cw}×{ch} grid", values.len()),
        ));
    }
    let (w, h) = (cw * factor, ch * factor);
    let off = (factor as f64 - 1.0) / 2.0;
    let axis = |x: usize, n: usize| {
        let u = ((x as f64 - off) / factor as f64).clamp(0.0, n.saturating_sub(1) as f64);
        let u0 = (u.floor() as usize).min(n.saturating_sub(2));
        (u0, (u0 + 1).min(n - 1), u - u0 as f64)
    };
    let cols: Vec<(usize, usize, f64)> = (0..w).map(|x| axis(x, cw)).collect();
    let mut out = vec![0.0; w * h];
    out.par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            let (y0, y1, ty) = axis(y, ch);
            let (top, bottom) = (
                &values[y0 * cw..(y0 + 1) * cw],
                &values[y1 * cw..(y1 + 1) * cw],
            );
            for (o, &(x0, x1, tx)) in row.iter_mut().zip(&cols) {
                let t = top[x0] * (1.0 - tx) + top[x1] * tx;
                let b = bottom[x0] * (1.0 - tx) + bottom[x1] * tx;
                *o = t * (1.0 - ty) + b * ty;
            }
        });
    Ok(out)
}

impl IrlsStart {
    /// This start (of `width × height` frames) on the grid of `factor × factor` block means:
    /// each scatter component and the weights averaged over the blocks, and σ₁ divided by
    /// `factor`, as the noise of a mean of `factor²` pixels is. Errors name `factor` when it is
    /// 0 or does not divide both sides, and `start` when the images are not `width × height`.
    pub fn box_downsampled(&self, width: usize, height: usize, factor: usize) -> Result<Self> {
        let n = width * height;
        if self.weights.len() != n || self.scatter.iter().any(|c| c.len() != n) {
            return Err(MurkError::invalid(
                "start",
                format!("its images are not the frame's {width}×{height}"),
            ));
        }
        let means = |values: &[f64]| block_means(values, width, height, factor);
        Ok(Self {
            scatter: self
                .scatter
                .iter()
                .map(|c| means(c))
                .collect::<Result<_>>()?,
            weights: means(&self.weights)?,
            sigma_fine: self.sigma_fine.map(|s| s / factor as f64),
        })
    }
}

/// `values` (`width × height`, row-major) averaged over `factor × factor` blocks, row-major on
/// the coarse grid. Errors name `factor` when it is 0 or does not divide both sides, and
/// `values` when there are not `width × height` of them.
pub fn block_means<T: Copy + Into<f64>>(
    values: &[T],
    width: usize,
    height: usize,
    factor: usize,
) -> Result<Vec<f64>> {
    if factor == 0 || !width.is_multiple_of(factor) || !height.is_multiple_of(factor) {
        return Err(MurkError::invalid(
            "factor",
            format!("{factor} must be at least 1 and divide the frame's {width}×{height}"),
        ));
    }
    if values.len() != width * height {
        return Err(MurkError::invalid(
            "values",
            format!("{} values for a {width}×{height} grid", values.len()),
        ));
    }
    let cw = width / factor;
    let mut out = vec![0.0; cw * (height / factor)];
    for (y, row) in values.chunks_exact(width).enumerate() {
        let coarse = &mut out[(y / factor) * cw..(y / factor + 1) * cw];
        for (x, &v) in row.iter().enumerate() {
            coarse[x / factor] += v.into();
        }
    }
    let inv = 1.0 / (factor * factor) as f64;
    out.iter_mut().for_each(|v| *v *= inv);
    Ok(out)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::simulate::tof::FogPreset::Medium;
    use crate::tof::MASK_OBJECT;

    fn start(width: usize, height: usize) -> IrlsStart {
        let ramp = |k: f64| {
            (0..width * height)
                .map(|i| k * i as f64)
                .collect::<Vec<_>>()
        };
        IrlsStart {
            scatter: vec![ramp(1.0), ramp(-2.0)],
            weights: (0..width * height).map(|i| (i % 2) as f64).collect(),
            sigma_fine: Some(3.0),
        }
    }

    /// Bilinear interpolation reproduces a plane between the block centres, and holds the
    /// edge values beyond them.
    #[test]
    fn upsampling_block_means_of_a_plane_gives_the_plane_back() {
        let (w, h, k) = (12, 8, 2);
        let plane: Vec<f64> = (0..w * h)
            .map(|i| 0.5 * (i % w) as f64 - 1.5 * (i / w) as f64 + 3.0)
            .collect();
        let up = upsampled(&block_means(&plane, w, h, k).unwrap(), w / k, h / k, k).unwrap();
        for y in 0..h {
            for x in 0..w {
                // Beyond the outermost block centres (half a block) the edge values hold.
                let cx = (x as f64).clamp(0.5, w as f64 - 1.5);
                let cy = (y as f64).clamp(0.5, h as f64 - 1.5);
                let want = 0.5 * cx - 1.5 * cy + 3.0;
                assert!((up[y * w + x] - want).abs() < 1e-12, "({x}, {y})");
            }
        }
    }

    /// Frame `k` of a simulated 128×106 stream (`TofMotion::default()`) of scene `seed` in
    /// `preset` fog.
    pub(in crate::tof) fn sim_input(
        seed: u64,
        preset: crate::simulate::tof::FogPreset,
        k: usize,
    ) -> TofInput {
        use crate::simulate::{simulate_tof_sequence_frame, TofMotion, TofSimConfig};
        let cfg = TofSimConfig {
            seed,
            preset,
            ..TofSimConfig::with_size(128, 106)
        };
        let f =
            simulate_tof_sequence_frame(&cfg, &TofMotion::default(), k, &Monitor::noop()).unwrap();
        TofInput {
            amplitude: f.amplitude,
            phase: f.phase,
            intrinsics: Some(f.intrinsics),
        }
    }

    /// A warm frame on the grid: full-size outputs whose mask and ranges agree with the same
    /// frame computed warm at full size.
    #[test]
    fn a_frame_on_the_grid_matches_the_full_size_frame() {
        let params = TofParams::default();
        let first = sim_input(3, Medium, 0);
        let (_, start) =
            crate::tof::estimate_tof_depth_from(&first, &params, None, &Monitor::noop()).unwrap();
        let start = start.unwrap();
        let next = sim_input(3, Medium, 1);
        let (full, _) =
            crate::tof::estimate_tof_depth_from(&next, &params, Some(&start), &Monitor::noop())
                .unwrap();
        let coarse = start.box_downsampled(128, 106, 2).unwrap();
        let (grid, grid_next) =
            estimate_tof_depth_on_grid(&next, &params, &coarse, 2, &Monitor::noop()).unwrap();
        assert_eq!(grid_next.unwrap().weights.len(), 64 * 53);
        assert_eq!(grid.range_m.dims(), (128, 106));
        assert_agrees(&full, &grid, "warm");
    }

    /// `b` agrees with `a`, a frame with more than 500 object pixels: their masks differ on at
    /// most 1 % of `a`'s object pixels, and the median range difference over the object pixels
    /// both share is under 5 mm. `what` names the case in a failure.
    pub(in crate::tof) fn assert_agrees(a: &TofOutput, b: &TofOutput, what: &str) {
        let (mut differ, mut objects, mut range_diff) = (0, 0, Vec::new());
        let (ma, mb) = (a.mask.data(), b.mask.data());
        for i in 0..ma.len() {
            differ += usize::from((ma[i] == MASK_OBJECT) != (mb[i] == MASK_OBJECT));
            if ma[i] == MASK_OBJECT && mb[i] == MASK_OBJECT {
                objects += 1;
                range_diff.push((a.range_m.data()[i] - b.range_m.data()[i]).abs());
            }
        }
        assert!(objects > 500, "{what}: {objects} object pixels");
        assert!(
            differ * 100 <= objects,
            "{what}: {differ} of {objects} object pixels differ"
        );
        range_diff.sort_by(f32::total_cmp);
        let median = range_diff[range_diff.len() / 2];
        assert!(median < 5e-3, "{what}: median range difference {median} m");
    }

    #[test]
    fn bad_grids_starts_and_channels_are_refused_naming_the_field() {
        let input = sim_input(1, Medium, 0);
        let params = TofParams::default();
        let start = IrlsStart {
            scatter: vec![vec![0.0; 64 * 53]; 2],
            weights: vec![1.0; 64 * 53],
            sigma_fine: None,
        };
        let run = |p: &TofParams, s: &IrlsStart, k| {
            estimate_tof_depth_on_grid(&input, p, s, k, &Monitor::noop())
                .unwrap_err()
                .to_string()
        };
        // 4 does not divide the 106 rows.
        for k in [0, 3, 4] {
            assert!(run(&params, &start, k).contains("factor"));
        }
        let small = IrlsStart {
            weights: vec![1.0; 10],
            ..start.clone()
        };
        assert!(run(&params, &small, 2).contains("start"));
        let amplitude_phase = TofParams {
            channels: ScatterChannels::AmplitudePhase,
            ..params.clone()
        };
        assert!(run(&amplitude_phase, &start, 2).contains("channels"));
    }

    #[test]
    fn blocks_average_their_pixels_and_the_noise_scale_shrinks() {
        let s = start(4, 2).box_downsampled(4, 2, 2).unwrap();
        // Blocks {0, 1, 4, 5} and {2, 3, 6, 7}.
        assert_eq!(s.scatter[0], vec![2.5, 4.5]);
        assert_eq!(s.scatter[1], vec![-5.0, -9.0]);
        assert_eq!(s.weights, vec![0.5, 0.5]);
        assert_eq!(s.sigma_fine, Some(1.5));
    }

    #[test]
    fn factor_one_keeps_the_start() {
        let s = start(6, 3);
        assert_eq!(s.box_downsampled(6, 3, 1).unwrap(), s);
    }

    #[test]
    fn bad_factors_and_sizes_are_refused_naming_the_field() {
        let s = start(6, 4);
        for factor in [0, 4, 5] {
            let e = s.box_downsampled(6, 4, factor).unwrap_err().to_string();
            assert!(e.contains("factor"), "{e}");
        }
        let e = s.box_downsampled(8, 4, 2).unwrap_err().to_string();
        assert!(e.contains("start"), "{e}");
        let e = block_means(&[1.0; 5], 2, 2, 1).unwrap_err().to_string();
        assert!(e.contains("values"), "{e}");
        for (values, cw, ch, k, field) in [
            (&[1.0; 4][..], 2, 2, 0, "factor"),
            (&[1.0; 5][..], 2, 2, 2, "values"),
            (&[][..], 0, 3, 2, "values"),
        ] {
            let e = upsampled(values, cw, ch, k).unwrap_err().to_string();
            assert!(e.contains(field), "{e}");
        }
    }
}
