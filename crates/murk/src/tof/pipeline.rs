//! The full ToF-in-fog pipeline (reference Ch. 5): validate, pre-filter, run Algorithm 2 on the
//! amplitude and phase images, intersect their object masks and subtract the scattering phasor
//! (Eq. 5.8–5.9) to obtain the direct component's range (Eq. 5.2).
//!
//! Limitation: phase is assumed not to wrap inside the image (every pixel within one ambiguity
//! interval c/(2f)); the quadratic/symmetry/smoothness priors treat phase as a smooth real field.

use std::f64::consts::{PI, TAU};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::ambiguous::uncertain_pixels;
use super::bilateral::bilateral_filter;
use super::irls::{run_irls_vector_from, thin_border_band, IrlsConfig, IrlsOutcome, IrlsStart};
use super::noise_model::NoiseModel;
use super::params::IrlsChannelParams;
use super::params::{
    PriorCoupling, ScatterChannels, TofInput, TofOutput, TofParams, MASK_BACKGROUND, MASK_OBJECT,
    MASK_UNCERTAIN, SPEED_OF_LIGHT_M_PER_S,
};
use super::quadratic_prior::{PatchGrid, QuadraticPrior};
use super::symmetry::RowMirror;
use super::wls::{XStepSolver, XStepSystem};
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;

/// Progress fractions of the pipeline's stages.
pub(super) const PREFILTER_END: f32 = 0.05;
const IRLS_END: f32 = 0.95;

/// Estimates the object mask and the fog-corrected range of a CW-ToF frame (Ch. 5, Algorithm 2,
/// Eq. 5.2, 5.8–5.16) with the default x-step solver.
///
/// Errors: the `InvalidArgument` of [`TofInput::validate`] / [`TofParams::validate`] unchanged,
/// `Cancelled` when `monitor` is cancelled (checked every IRLS iteration), `Numerical` if a solve
/// fails. Progress stages: `tof.prefilter`, `tof.{amplitude,phase}.{coarse,fine}`, `tof.compose`.
pub fn estimate_tof_depth(
    input: &TofInput,
    params: &TofParams,
    monitor: &Monitor,
) -> Result<TofOutput> {
    estimate_tof_depth_with_solver(input, params, XStepSolver::default(), monitor)
}

/// [`estimate_tof_depth`] with an explicit x-step solver (benchmarks, cross-checks).
pub fn estimate_tof_depth_with_solver(
    input: &TofInput,
    params: &TofParams,
    solver: XStepSolver,
    monitor: &Monitor,
) -> Result<TofOutput> {
    estimate(input, params, solver, None, monitor).map(|(out, _)| out)
}

/// [`estimate_tof_depth`] of a stream's next frame: from `start`, the previous frame's scatter
/// and weights, when given (the fine level only; see [`IrlsStart`]). Returns the estimate and
/// the start it leaves for the frame after, which exists for the default phasor channels only
/// (with `ScatterChannels::AmplitudePhase` every frame starts cold and the start is `None`).
/// [`TofTracker`](super::TofTracker) decides when a start is still good.
pub fn estimate_tof_depth_from(
    input: &TofInput,
    params: &TofParams,
    start: Option<&IrlsStart>,
    monitor: &Monitor,
) -> Result<(TofOutput, Option<IrlsStart>)> {
    estimate(input, params, XStepSolver::default(), start, monitor)
}

fn estimate(
    input: &TofInput,
    params: &TofParams,
    solver: XStepSolver,
    start: Option<&IrlsStart>,
    monitor: &Monitor,
) -> Result<(TofOutput, Option<IrlsStart>)> {
    input.validate()?;
    params.validate_for(input)?;
    monitor.checkpoint()?;
    let raw = RawPhasor::of(input);
    let (est, next) = separate(input, &raw, params, solver, start, monitor)?;
    let out = finish(input, params, &est, raw, monitor)?;
    Ok((out, next))
}

/// A frame's phasor as observed, before any filter: real and imaginary parts, row-major.
pub(super) struct RawPhasor {
    pub(super) re: Vec<f32>,
    pub(super) im: Vec<f32>,
}

impl RawPhasor {
    /// The phasor of `input`'s amplitude and phase.
    pub(super) fn of(input: &TofInput) -> Self {
        let (re, im) = input
            .amplitude
            .data()
            .par_iter()
            .zip(input.phase.data().par_iter())
            .map(|(&a, &p)| {
                let (s, c) = (p as f64).sin_cos();
                ((a as f64 * c) as f32, (a as f64 * s) as f32)
            })
            .unzip();
        Self { re, im }
    }
}

/// The two images of an observation (`w × h` each) through the pre-filter of `params`, or
/// copied without one, in `f64` as the IRLS takes them; the two side by side.
pub(super) fn prefiltered_pair(
    first: &[f32],
    second: &[f32],
    (w, h): (usize, usize),
    params: &TofParams,
) -> [Vec<f64>; 2] {
    let one = |img: &[f32]| -> Vec<f64> {
        let filtered = match &params.bilateral {
            Some(b) => {
                let mut out = vec![0.0; w * h];
                bilateral_filter(img, w, h, b, &mut out);
                out
            }
            None => img.to_vec(),
        };
        filtered.into_par_iter().map(f64::from).collect()
    };
    let (a, b) = rayon::join(|| one(first), || one(second));
    [a, b]
}

/// Algorithm 2 on a validated frame whose raw phasor is `raw`: the scatter, the weights and the
/// object mask, and the start the frame leaves for the next (phasor channels only).
pub(super) fn separate(
    input: &TofInput,
    raw: &RawPhasor,
    params: &TofParams,
    solver: XStepSolver,
    start: Option<&IrlsStart>,
    monitor: &Monitor,
) -> Result<(ScatterEstimate, Option<IrlsStart>)> {
    let (w, h) = input.amplitude.dims();
    let (raw_re, raw_im) = (&raw.re, &raw.im);
    // The noise model (shot + read) scales the IRLS residuals of the phasor channels and gives
    // every pixel's range uncertainty.
    let noise = NoiseModel::fit(raw_re, raw_im, input.amplitude.data(), w);
    // The observation as the pipeline sees it: amplitude and phase, or the phasor's real and
    // imaginary parts, each pre-filtered.
    let (first, second): (&[f32], &[f32]) = match params.channels {
        ScatterChannels::AmplitudePhase => (input.amplitude.data(), input.phase.data()),
        ScatterChannels::Phasor => (raw_re, raw_im),
    };
    let observed = prefiltered_pair(first, second, (w, h), params);
    monitor.progress("tof.prefilter", PREFILTER_END);
    separate_observed(input, params, solver, start, observed, noise, monitor)
}

/// The settings of one IRLS run of `params` on an image of `channel`.
pub(super) fn irls_config(
    params: &TofParams,
    channel: IrlsChannelParams,
    solver: XStepSolver,
) -> IrlsConfig {
    IrlsConfig {
        channel,
        coarse_iterations: params.coarse_iterations,
        fine_iterations: params.fine_iterations,
        solver,
        weight_tolerance: params.convergence_tolerance,
        mask_threshold: params.mask_threshold as f64,
        coarse_subdivision: params.coarse_subdivision,
        coarse_quantile: params.coarse_quantile,
    }
}

/// The x-step system of a validated `input` under `params` for an image of `channel`, and the
/// patch grid of its quadratic priors.
pub(super) fn scatter_system(
    input: &TofInput,
    params: &TofParams,
    channel: IrlsChannelParams,
) -> Result<(XStepSystem, PatchGrid)> {
    let (w, h) = input.amplitude.dims();
    let row0 = params
        .symmetry_row
        .or(input.intrinsics.map(|k| k.cy))
        .unwrap_or((h as f64 - 1.0) * 0.5);
    let grid = PatchGrid::new(w, h, params.patches_x, params.patches_y);
    let sys = XStepSystem::new(w, h, channel.effective_gamma(w, h), RowMirror::new(h, row0));
    let sys = match params.prior_coupling {
        PriorCoupling::Joint => sys.with_joint_prior(grid.clone())?,
        PriorCoupling::Alternating => sys,
    };
    Ok((sys, grid))
}

/// [`separate`] from the observation as the pipeline sees it (`observed`: the pre-filtered
/// amplitude and phase, or the phasor's real and imaginary parts, in `f64`) and the frame's
/// noise model.
pub(super) fn separate_observed(
    input: &TofInput,
    params: &TofParams,
    solver: XStepSolver,
    start: Option<&IrlsStart>,
    observed: [Vec<f64>; 2],
    noise: Option<NoiseModel>,
    monitor: &Monitor,
) -> Result<(ScatterEstimate, Option<IrlsStart>)> {
    monitor.checkpoint()?;
    let runs = match params.channels {
        ScatterChannels::AmplitudePhase => 2,
        ScatterChannels::Phasor => 1,
    };
    let total = runs * (params.coarse_iterations + params.fine_iterations);
    let done = AtomicUsize::new(0);
    let tick = |stage: &str| {
        let d = done.fetch_add(1, Ordering::Relaxed) + 1;
        let f = PREFILTER_END + (IRLS_END - PREFILTER_END) * d as f32 / total.max(1) as f32;
        monitor.progress(stage, f);
    };
    let run = |imgs: &[&[f64]],
               noise: Option<NoiseModel>,
               channel,
               start: Option<&IrlsStart>,
               prefix: &str|
     -> Result<IrlsOutcome> {
        let cfg = irls_config(params, channel, solver);
        let (sys, grid) = scatter_system(input, params, channel)?;
        let mut priors = vec![QuadraticPrior::new(grid)?; imgs.len()];
        run_irls_vector_from(
            imgs,
            noise,
            &sys,
            &mut priors,
            &cfg,
            start,
            prefix,
            monitor,
            &tick,
        )
    };
    let [o1, o2] = observed;
    let t = params.mask_threshold as f64;
    let mut next = None;
    let est = match params.channels {
        ScatterChannels::AmplitudePhase => {
            let (ra, rp) = rayon::join(
                || run(&[&o1], None, params.amplitude, None, "tof.amplitude"),
                || run(&[&o2], None, params.phase, None, "tof.phase"),
            );
            let (ra, rp) = (ra?, rp?);
            let warnings = [("amplitude", &ra), ("phase", &rp)]
                .into_iter()
                .filter_map(|(name, r)| not_converged_warning(name, r))
                .collect();
            let mut ra_scatter = ra.scatter_with_rim();
            let mut rp_scatter = rp.scatter_with_rim();
            let (sa, sp) = (ra_scatter.swap_remove(0), rp_scatter.swap_remove(0));
            // Object = outlier in both images (§5.3.4).
            let object = ra
                .weights
                .iter()
                .zip(&rp.weights)
                .map(|(&a, &p)| a < t && p < t)
                .collect();
            // A scattering amplitude is a magnitude; a slightly negative estimate (possible in
            // the unconstrained least squares) would flip the subtracted phasor.
            let polar = |a: &[f64], p: &[f64], clamp: bool| -> (Vec<f64>, Vec<f64>) {
                a.par_iter()
                    .zip(p.par_iter())
                    .map(|(&a, &p)| {
                        let a = if clamp { a.max(0.0) } else { a };
                        let (s, c) = p.sin_cos();
                        (a * c, a * s)
                    })
                    .unzip()
            };
            let (scatter_re, scatter_im) = polar(&sa, &sp, true);
            let (observed_re, observed_im) = polar(&o1, &o2, false);
            ScatterEstimate {
                object,
                observed_re,
                observed_im,
                scatter_re,
                scatter_im,
                weight_amplitude: ra.weights,
                weight_phase: rp.weights,
                noise,
                warnings,
            }
        }
        ScatterChannels::Phasor => {
            let r = run(&[&o1, &o2], noise, params.phasor, start, "tof.phasor")?;
            next = Some(IrlsStart::from_outcome(&r));
            let warnings = not_converged_warning("phasor", &r).into_iter().collect();
            let mut sc = r.scatter_with_rim();
            let scatter_im = sc.pop().unwrap_or_default();
            let scatter_re = sc.pop().unwrap_or_default();
            ScatterEstimate {
                object: r.weights.iter().map(|&v| v < t).collect(),
                observed_re: o1,
                observed_im: o2,
                scatter_re,
                scatter_im,
                weight_amplitude: r.weights.clone(),
                weight_phase: r.weights,
                noise,
                warnings,
            }
        }
    };
    monitor.checkpoint()?;
    Ok((est, next))
}

/// The frame's outputs from the separated scatter: the pixels beside the objects judged, then
/// the direct component and its ranges (see [`compose`]).
pub(super) fn finish(
    input: &TofInput,
    params: &TofParams,
    est: &ScatterEstimate,
    raw: RawPhasor,
    monitor: &Monitor,
) -> Result<TofOutput> {
    let (w, h) = input.amplitude.dims();
    // The raw phasor, not the filtered one, judges the pixels beside the objects: see
    // `tof::ambiguous`. The direct component does not depend on them, and is computed beside.
    let (uncertain, direct) = rayon::join(
        || {
            uncertain_pixels(
                &raw.re,
                &raw.im,
                &est.scatter_re,
                &est.scatter_im,
                &est.object,
                est.noise.as_ref(),
                w,
                thin_border_band(w, h),
            )
        },
        || {
            Direct::of(
                input,
                params,
                [&est.observed_re, &est.observed_im],
                [&est.scatter_re, &est.scatter_im],
                est.noise,
            )
        },
    );
    drop(raw);
    let out = compose(input, params, est, &uncertain, direct)?;
    monitor.progress("tof.compose", 1.0);
    Ok(out)
}

/// What the IRLS produced, as phasors: the pre-filtered observation and the scattering
/// component per pixel, the object mask and the channels' weights.
pub(super) struct ScatterEstimate {
    pub(super) object: Vec<bool>,
    pub(super) observed_re: Vec<f64>,
    pub(super) observed_im: Vec<f64>,
    pub(super) scatter_re: Vec<f64>,
    pub(super) scatter_im: Vec<f64>,
    pub(super) weight_amplitude: Vec<f64>,
    pub(super) weight_phase: Vec<f64>,
    /// The frame's noise model (`None` for frames too small to fit one).
    pub(super) noise: Option<NoiseModel>,
    /// What the caller should know about the estimate (see [`TofOutput::warnings`]).
    pub(super) warnings: Vec<String>,
}

/// A sentence when the IRLS of `channel` stopped at its cap of fine iterations with the weights
/// still moving: the mask and the scatter under it may be incomplete, and more iterations may
/// change them (on cluttered thick seed 1 at 512×424 the level converges only after about 105
/// iterations, 40 mm → 25 mm; docs/accuracy.md).
fn not_converged_warning(channel: &str, r: &IrlsOutcome) -> Option<String> {
    (!r.fine_converged).then(|| {
        format!(
            "{channel} IRLS: the fine level stopped at its cap of {} iterations before its \
             weights settled; the object mask and the scatter under it may be incomplete \
             (raise fine_iterations)",
            r.fine_iterations_run
        )
    })
}

/// The `range_std_m` of a pixel without a measurement: the cap of the reported standard
/// deviation, a quarter of the ambiguity interval (σ_φ = π/2 through Eq. 5.2), which a pixel
/// reaches where its direct return is no stronger than the noise, so that its corrected range
/// is a guess.
pub fn unmeasured_range_std_m(modulation_frequency_hz: f64) -> f32 {
    range_m(0.5 * PI, modulation_frequency_hz) as f32
}

/// Range along the ray (metres) of a phase (radians): Eq. 5.2, c·φ/(4πf).
#[inline]
fn range_m(phase_rad: f64, frequency_hz: f64) -> f64 {
    SPEED_OF_LIGHT_M_PER_S * phase_rad / (2.0 * TAU * frequency_hz)
}

/// A pixel whose `range_std_m` is at least this fraction of the cap (σ_φ ≥ π/4: its direct
/// return within about 1.4 noise σ of nothing) has a weak measurement ([`fill_outline_pixels`]).
const WEAK_FRACTION_OF_CAP: f32 = 0.5;

/// A weak measurement farther than this many of its own standard deviations from its measured
/// neighbours' median range takes that median ([`fill_outline_pixels`]).
const FILL_CONSISTENCY_SIGMAS: f32 = 2.0;

/// `range` with the weak pixels beside measured object pixels given the median range of those
/// pixels (within [`REACH`](crate::tof::ambiguous::REACH); measured: object pixels with a
/// `range_std` below [`WEAK_FRACTION_OF_CAP`] of `cap`): every unmeasured pixel (its
/// `range_std` at `cap`: a direct return no stronger than the noise, whose phase is a guess),
/// and every weak one whose range lies more than [`FILL_CONSISTENCY_SIGMAS`] of its own
/// `range_std` from that median. Their `range_std_m` stays as it was.
///
/// Such pixels lie on the objects' outlines: a dim edge, a strip beside a nearer occluder. The
/// phase of a noise-sized direct component is uniform over the ambiguity interval, so the guess
/// was metres off (8.3 m for a true 1.05 m on a cluttered survey frame, where that one pixel
/// added 3 mm to the frame's mean error). The surface beside it is the likelier answer, and a
/// robot that reads the depth without the mask or the uncertainty then sees the obstacle's
/// extent rather than a point far behind it.
fn fill_outline_pixels(
    range: &[f32],
    range_std: &[f32],
    object: &[bool],
    w: usize,
    cap: f32,
) -> Vec<f32> {
    let h = range.len() / w.max(1);
    let r = crate::tof::ambiguous::REACH;
    let weak = WEAK_FRACTION_OF_CAP * cap;
    let measured: Vec<bool> = (object, range_std)
        .into_par_iter()
        .map(|(&o, &s)| o && s < weak)
        .collect();
    // Most unmeasured pixels are fog far from any object: only those near one scan a window.
    let near = crate::tof::ambiguous::dilate(&measured, w, r);
    let mut out = range.to_vec();
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let mut around = Vec::new();
        for (x, v) in row.iter_mut().enumerate() {
            let i = y * w + x;
            if range_std[i] < weak || !near[i] {
                continue;
            }
            around.clear();
            for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                let cols = yy * w + x.saturating_sub(r)..yy * w + (x + r + 1).min(w);
                around.extend(cols.filter(|&j| measured[j]).map(|j| range[j]));
            }
            if around.is_empty() {
                continue;
            }
            let mid = around.len() / 2;
            let median = *around.select_nth_unstable_by(mid, f32::total_cmp).1;
            // A weak measurement within its own errors of the surroundings stands: it may see
            // a farther surface beside a nearer one. Beyond them, or without a measurement at
            // all, the surroundings are the better answer.
            if range_std[i] >= cap || (*v - median).abs() > FILL_CONSISTENCY_SIGMAS * range_std[i] {
                *v = median;
            }
        }
    });
    out
}

/// Range along the unit ray `d` (metres) of a surface whose optical path light → surface →
/// camera is `path_m`, for a light at `light` (camera frame, metres). From
/// `path = s + |s·d − L|`: `s = (path² − |L|²) / (2·(path − d·L))`. Falls back to `path/2` where
/// the path is shorter than the baseline (noise), which no real surface can produce.
#[inline]
fn range_from_path(path_m: f64, d: [f64; 3], light: [f64; 3]) -> f64 {
    let l2 = light[0] * light[0] + light[1] * light[1] + light[2] * light[2];
    let dl = d[0] * light[0] + d[1] * light[1] + d[2] * light[2];
    if path_m * path_m <= l2 || path_m <= dl {
        return 0.5 * path_m;
    }
    (path_m * path_m - l2) / (2.0 * (path_m - dl))
}

/// |re + i·im|. Amplitudes are at most 1e15 ([`crate::tof::AMPLITUDE_RANGE`]), so the squares
/// cannot overflow and the plain root serves where `hypot` would take several times as long.
#[inline]
fn magnitude(re: f64, im: f64) -> f64 {
    (re * re + im * im).sqrt()
}

/// Wraps radians into [0, 2π) (`rem_euclid` can round up to exactly 2π for tiny negatives).
#[inline]
pub(super) fn wrap_phase(p: f64) -> f64 {
    let r = p.rem_euclid(TAU);
    if r >= TAU {
        0.0
    } else {
        r
    }
}

fn image(w: usize, h: usize, data: Vec<f32>) -> Result<ImageF32> {
    ImageF32::from_vec(w, h, 1, data).map_err(|e| MurkError::Numerical(e.to_string()))
}

/// A frame's per-pixel results that the mask does not change: the direct component (Eq.
/// 5.8–5.9) and its range (Eq. 5.2) with its standard deviation, the scatter in polar form and
/// the raw phase's range, all before the outline fill and the light's offset.
pub(super) struct Direct {
    alpha_d: Vec<f32>,
    phi_d: Vec<f32>,
    range: Vec<f32>,
    scatter_a: Vec<f32>,
    scatter_p: Vec<f32>,
    range_std: Vec<f32>,
    raw_range: Vec<f32>,
}

impl Direct {
    /// The observed phasor less the scatter, pixel by pixel; `noise` gives the ranges'
    /// standard deviations.
    pub(super) fn of(
        input: &TofInput,
        params: &TofParams,
        observed: [&[f64]; 2],
        scatter: [&[f64]; 2],
        noise: Option<NoiseModel>,
    ) -> Self {
        let n = input.amplitude.pixel_count();
        let f = params.modulation_frequency_hz;
        let [observed_re, observed_im] = observed;
        let [scatter_re, scatter_im] = scatter;
        let mut alpha_d = vec![0.0f32; n];
        let mut phi_d = vec![0.0f32; n];
        let mut range = vec![0.0f32; n];
        let mut scatter_a = vec![0.0f32; n];
        let mut scatter_p = vec![0.0f32; n];
        let mut range_std = vec![0.0f32; n];
        let raw_range: Vec<f32> = input
            .phase
            .data()
            .par_iter()
            .map(|&p| range_m(wrap_phase(p as f64), f) as f32)
            .collect();
        (
            alpha_d.par_iter_mut(),
            phi_d.par_iter_mut(),
            range.par_iter_mut(),
            scatter_a.par_iter_mut(),
            scatter_p.par_iter_mut(),
            range_std.par_iter_mut(),
        )
            .into_par_iter()
            .enumerate()
            .for_each(|(i, (ad, pd, rg, sa, sp, sd))| {
                let (s_re, s_im) = (scatter_re[i], scatter_im[i]);
                let re = observed_re[i] - s_re;
                let im = observed_im[i] - s_im;
                let p = wrap_phase(im.atan2(re));
                let a_d = magnitude(re, im);
                *ad = a_d as f32;
                *pd = p as f32;
                *rg = range_m(p, f) as f32;
                let a_s = magnitude(s_re, s_im);
                *sa = a_s as f32;
                *sp = wrap_phase(s_im.atan2(s_re)) as f32;
                // Without a noise model (tiny frames) the spread of the scatter's own brightness
                // stands in: no uncertainty is never reported.
                let a_o = magnitude(observed_re[i], observed_im[i]);
                let (var_o, var_s) = match noise {
                    Some(nm) => (nm.sigma(a_o).powi(2), nm.sigma(a_s).powi(2)),
                    None => (0.0, (1e-3 * a_s).powi(2)),
                };
                let sigma_phi = ((var_o + var_s).sqrt() / a_d.max(1e-300)).min(0.5 * PI);
                *sd = range_m(sigma_phi, f) as f32;
            });
        Self {
            alpha_d,
            phi_d,
            range,
            scatter_a,
            scatter_p,
            range_std,
            raw_range,
        }
    }
}

/// The outputs: the mask, the ranges of `direct` with the outline filled and the light's
/// offset solved for, z-depth.
pub(super) fn compose(
    input: &TofInput,
    params: &TofParams,
    est: &ScatterEstimate,
    uncertain: &[bool],
    direct: Direct,
) -> Result<TofOutput> {
    let (w, h) = input.amplitude.dims();
    let n = w * h;
    let f = params.modulation_frequency_hz;
    let mask: Vec<f32> = (0..n)
        .into_par_iter()
        .map(|i| {
            if est.object[i] {
                MASK_OBJECT
            } else if uncertain[i] {
                MASK_UNCERTAIN
            } else {
                MASK_BACKGROUND
            }
        })
        .collect();
    let Direct {
        alpha_d,
        phi_d,
        range,
        scatter_a,
        scatter_p,
        range_std,
        raw_range,
    } = direct;
    let mut range = fill_outline_pixels(
        &range,
        &range_std,
        &est.object,
        w,
        unmeasured_range_std_m(f),
    );
    let mut raw_range = raw_range;
    // With intrinsics: the ranges for a light off the lens (Eq. 5.2 gives half the optical
    // path; with the light off the lens the range is not), and z = range · (the unit ray's z
    // component), from one ray per pixel.
    let (z_depth, raw_z_depth) = match input.intrinsics {
        Some(k) => {
            let (mut z, mut raw_z) = (vec![0.0f32; n], vec![0.0f32; n]);
            (
                range.par_chunks_mut(w),
                raw_range.par_chunks_mut(w),
                z.par_chunks_mut(w),
                raw_z.par_chunks_mut(w),
            )
                .into_par_iter()
                .enumerate()
                .for_each(|(y, (r, raw_r, z, raw_z))| {
                    for x in 0..w {
                        let d = k.ray(x as f64, y as f64);
                        if let Some(light) = params.light_position_m {
                            for v in [&mut r[x], &mut raw_r[x]] {
                                *v = range_from_path(2.0 * *v as f64, d.into(), light) as f32;
                            }
                        }
                        z[x] = (r[x] as f64 * d[2]) as f32;
                        raw_z[x] = (raw_r[x] as f64 * d[2]) as f32;
                    }
                });
            (Some(z), Some(raw_z))
        }
        None => (None, None),
    };
    let to_f32 = |v: &[f64]| v.par_iter().map(|&x| x as f32).collect::<Vec<f32>>();
    Ok(TofOutput {
        range_m: image(w, h, range)?,
        range_std_m: image(w, h, range_std)?,
        z_depth_m: z_depth.map(|z| image(w, h, z)).transpose()?,
        raw_range_m: image(w, h, raw_range)?,
        raw_z_depth_m: raw_z_depth.map(|z| image(w, h, z)).transpose()?,
        mask: image(w, h, mask)?,
        scatter_amplitude: image(w, h, scatter_a)?,
        scatter_phase: image(w, h, scatter_p)?,
        weight_amplitude: image(w, h, to_f32(&est.weight_amplitude))?,
        weight_phase: image(w, h, to_f32(&est.weight_phase))?,
        corrected_amplitude: image(w, h, alpha_d)?,
        corrected_phase: image(w, h, phi_d)?,
        warnings: est.warnings.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::tof::params::{IrlsChannelParams, REFERENCE_SIZE_PX};

    /// A 12 × 9 frame whose columns 0..5 are a measured object (`range_std` 0.01 m) at the
    /// range `range_of(column)`, everything else unmeasured (at `cap`) with a guessed 7.5 m:
    /// `(range, range_std, object)`.
    fn object_in_columns(
        cap: f32,
        range_of: impl Fn(usize) -> f32,
    ) -> (Vec<f32>, Vec<f32>, Vec<bool>) {
        let (w, h) = (12, 9);
        let mut range = vec![7.5f32; w * h];
        let mut std = vec![cap; w * h];
        let mut object = vec![false; w * h];
        for y in 0..h {
            for x in 0..5 {
                let i = y * w + x;
                object[i] = true;
                range[i] = range_of(x);
                std[i] = 0.01;
            }
        }
        (range, std, object)
    }

    #[test]
    fn an_unmeasured_pixel_beside_an_object_takes_the_objects_range() {
        let (w, h) = (12, 9);
        let cap = 2.0f32;
        // The object at 1.0–1.4 m, measured but for (4, 4).
        let (range, mut std, object) = object_in_columns(cap, |x| 1.0 + 0.1 * x as f32);
        let hole = 4 * w + 4;
        std[hole] = cap;
        let out = fill_outline_pixels(&range, &std, &object, w, cap);
        // The hole and the background pixels within 3 columns take the median of the measured
        // object pixels in their 7 × 7 window: the hole's holds columns 1–4 (7 pixels each of
        // columns 1–3, 6 of column 4), (5, 4)'s columns 2–4, (7, 4)'s column 4 alone.
        let column = |x: usize| range[x];
        assert_eq!(out[hole], column(2));
        assert_eq!(out[4 * w + 5], column(3));
        assert_eq!(out[4 * w + 7], column(4));
        // Beyond reach, and wherever the pixel is measured, nothing changes.
        assert_eq!(out[4 * w + 8], 7.5);
        for i in (0..w * h).filter(|&i| std[i] < cap) {
            assert_eq!(out[i], range[i]);
        }
    }

    /// A weak measurement (σ_φ ≥ π/4) beside an object takes the object's range only when it
    /// lies beyond two of its own standard deviations from it: a guess 7 m behind the object
    /// goes (a cluttered survey frame's worst pixel), a farther surface 0.7 m behind it, seen
    /// weakly beside the nearer one, stays.
    #[test]
    fn a_weak_pixel_keeps_its_range_only_within_its_errors_of_its_neighbours() {
        let w = 12;
        let cap = 2.0f32;
        let (mut range, mut std, object) = object_in_columns(cap, |_| 1.1);
        let (guess, farther, measured) = (2 * w + 4, 6 * w + 4, 4 * w + 3);
        (range[guess], std[guess]) = (8.4, 1.6);
        (range[farther], std[farther]) = (1.8, 1.6);
        (range[measured], std[measured]) = (1.4, 0.9);
        let out = fill_outline_pixels(&range, &std, &object, w, cap);
        assert_eq!(out[guess], 1.1);
        assert_eq!(out[farther], 1.8);
        // Below half the cap a pixel is measured, and is never filled.
        assert_eq!(out[measured], 1.4);
    }

    #[test]
    fn range_from_path_inverts_the_offset_light_geometry() {
        let light = [0.06, 0.01, 0.0];
        for (d, s) in [
            ([0.0f64, 0.0, 1.0], 1.5),
            ([0.5f64, -0.2, 0.84], 0.8),
            ([-0.55, 0.3, 0.78], 2.7),
        ] {
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let d = [d[0] / n, d[1] / n, d[2] / n];
            let p = [d[0] * s, d[1] * s, d[2] * s];
            let rl = ((p[0] - light[0]).powi(2) + (p[1] - light[1]).powi(2) + p[2].powi(2)).sqrt();
            let got = range_from_path(s + rl, d, light);
            assert!((got - s).abs() < 1e-12, "{got} vs {s}");
        }
        assert_eq!(range_from_path(0.01, [0.0, 0.0, 1.0], light), 0.005);
    }
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;

    const W: usize = 64;
    const H: usize = 48;

    fn gauss(rng: &mut ChaCha8Rng) -> f64 {
        let u1: f64 = 1.0 - rng.random::<f64>();
        let u2: f64 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (TAU * u2).cos()
    }

    /// Smooth scatter symmetric about row (H−1)/2 (camera and light on a horizontal line), plus
    /// an optional bright disc (the object) and Gaussian noise. Returns input, true scatter
    /// amplitude and the disc mask.
    fn scene(blob: bool, seed: u64) -> (TofInput, Vec<f32>, Vec<bool>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (cy, cx) = ((H as f64 - 1.0) / 2.0, 40.0);
        let mut amp = vec![0.0f32; W * H];
        let mut ph = vec![0.0f32; W * H];
        let mut sa = vec![0.0f32; W * H];
        let mut m = vec![false; W * H];
        for y in 0..H {
            for x in 0..W {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                // Gentle enough that γ′₃'s boundary bias (≈ γ′₃·gradient at the Neumann border) stays
                // within Tukey's c·σ: steeper scatter makes border pixels outliers.
                let s_a = 100.0 - 0.003 * dx * dx - 0.006 * dy * dy;
                let s_p = 0.2 + 0.00002 * dx * dx + 0.00004 * dy * dy;
                let i = y * W + x;
                sa[i] = s_a as f32;
                let (bx, by) = (x as f64 - 22.0, y as f64 - 18.0);
                let inside = blob && bx * bx + by * by <= 64.0;
                m[i] = inside;
                let (mut re, mut im) = (s_a * s_p.cos(), s_a * s_p.sin());
                if inside {
                    // Object 1.5 m away at 16 MHz: phase ≈ 1.0 rad.
                    re += 150.0 * 1.0f64.cos();
                    im += 150.0 * 1.0f64.sin();
                }
                re += 0.5 * gauss(&mut rng);
                im += 0.5 * gauss(&mut rng);
                amp[i] = re.hypot(im) as f32;
                ph[i] = wrap_phase(im.atan2(re)) as f32;
            }
        }
        let input = TofInput {
            amplitude: ImageF32::from_vec(W, H, 1, amp).unwrap(),
            phase: ImageF32::from_vec(W, H, 1, ph).unwrap(),
            intrinsics: None,
        };
        (input, sa, m)
    }

    fn fast_params() -> TofParams {
        // The synthetic scene's structures are sized in pixels as on a 512-wide frame (an
        // 8-pixel-radius blob); keep the smoothing per pixel of the reference resolution by
        // undoing the (64/512)² size scaling of γ′₃ (see `IrlsChannelParams::gamma`).
        let s = (REFERENCE_SIZE_PX / W as f64).powi(2);
        let mut amplitude = IrlsChannelParams::AMPLITUDE;
        let mut phase = IrlsChannelParams::PHASE;
        let mut phasor = IrlsChannelParams::PHASOR;
        amplitude.gamma[2] *= s;
        phase.gamma[2] *= s;
        phasor.gamma[2] *= s;
        TofParams {
            coarse_iterations: 5,
            fine_iterations: 20,
            amplitude,
            phase,
            phasor,
            ..TofParams::default()
        }
    }

    /// An object whose direct return leaves the amplitude unchanged (observed = scatter·e^{jθ}):
    /// invisible to the amplitude channel, so the reference's "outlier in both" mask misses it,
    /// while the phasor's complex residual flags it and the corrected phase is the object's.
    #[test]
    fn object_invisible_in_amplitude_is_masked_by_the_phasor_residual() {
        let (mut input, _, _) = scene(false, 13);
        let theta = 0.6f64;
        let mut phase = input.phase.data().to_vec();
        for (i, p) in phase.iter_mut().enumerate() {
            if blob_at(i) {
                *p = wrap_phase(*p as f64 + theta) as f32;
            }
        }
        input.phase = ImageF32::from_vec(W, H, 1, phase).unwrap();
        let iou = |out: &TofOutput| {
            let (mut inter, mut uni) = (0, 0);
            for i in 0..W * H {
                let m = out.mask.data()[i] > 0.5;
                let b = blob_at(i);
                inter += (m && b) as usize;
                uni += (m || b) as usize;
            }
            inter as f64 / uni.max(1) as f64
        };
        let phasor = estimate_tof_depth(&input, &fast_params(), &Monitor::noop()).unwrap();
        assert!(iou(&phasor) > 0.8, "phasor IoU {}", iou(&phasor));
        let reference = TofParams {
            channels: ScatterChannels::AmplitudePhase,
            ..fast_params()
        };
        let ap = estimate_tof_depth(&input, &reference, &Monitor::noop()).unwrap();
        assert!(iou(&ap) < 0.2, "amplitude/phase IoU {}", iou(&ap));
    }

    fn blob_at(i: usize) -> bool {
        let (x, y) = ((i % W) as f64, (i / W) as f64);
        (x - 22.0).powi(2) + (y - 18.0).powi(2) <= 64.0
    }

    #[test]
    fn background_only_has_unit_weights_and_no_mask() {
        let (input, _, _) = scene(false, 7);
        let out = estimate_tof_depth(&input, &fast_params(), &Monitor::noop()).unwrap();
        let n = (W * H) as f64;
        let mean_w: f64 = out
            .weight_amplitude
            .data()
            .iter()
            .map(|&v| v as f64)
            .sum::<f64>()
            / n;
        assert!(mean_w > 0.85, "mean amplitude weight {mean_w}");
        let masked: f32 = out.mask.data().iter().sum();
        assert!(
            masked <= 0.005 * n as f32,
            "{masked} background pixels masked"
        );
        assert!(out.range_m.data().iter().all(|v| v.is_finite()));
        // Fog alone returns no direct signal: where the scatter estimate leaves less than the
        // noise, a pixel reports the cap (a third of them here); none reports more.
        let cap = unmeasured_range_std_m(16e6);
        let std = out.range_std_m.data();
        assert!(std.iter().all(|&s| s <= cap));
        let unmeasured = std.iter().filter(|&&s| s == cap).count();
        assert!(
            unmeasured as f64 > 0.25 * n,
            "{unmeasured} of {n} pixels without a measurement"
        );
    }

    #[test]
    fn bright_blob_is_masked_and_scatter_recovered_under_it() {
        let (input, true_sa, blob) = scene(true, 11);
        let out = estimate_tof_depth(&input, &fast_params(), &Monitor::noop()).unwrap();
        let (mut inter, mut uni, mut err, mut nb) = (0, 0, 0.0, 0);
        for i in 0..W * H {
            let m = out.mask.data()[i] > 0.5;
            inter += (m && blob[i]) as usize;
            uni += (m || blob[i]) as usize;
            if blob[i] {
                err += (out.scatter_amplitude.data()[i] - true_sa[i]).abs() as f64;
                // Direct phase is the object's 1.0 rad once the scatter is removed.
                let pd = out.corrected_phase.data()[i] as f64;
                assert!((pd - 1.0).abs() < 0.05, "direct phase {pd}");
                nb += 1;
            }
        }
        let iou = inter as f64 / uni as f64;
        assert!(iou > 0.85, "IoU {iou}");
        let rel = err / nb as f64 / 100.0;
        assert!(rel < 0.02, "relative scatter error under the blob {rel}");
        let expect_m = SPEED_OF_LIGHT_M_PER_S * 1.0 / (2.0 * TAU * 16e6);
        let i = 18 * W + 22;
        assert!((out.range_m.data()[i] as f64 - expect_m).abs() < 0.05);
        assert!((out.raw_range_m.data()[i] as f64 - expect_m).abs() > 0.01);
        assert!(out.warnings.is_empty(), "{:?}", out.warnings);
    }

    /// A fine level cut off by its cap says so; one that converges, or runs with the
    /// convergence test off (the caller asked for exactly that many), does not.
    #[test]
    fn a_fine_level_stopped_at_its_cap_is_reported() {
        let (input, _, _) = scene(true, 11);
        let capped = TofParams {
            fine_iterations: 2,
            ..fast_params()
        };
        let out = estimate_tof_depth(&input, &capped, &Monitor::noop()).unwrap();
        assert_eq!(out.warnings.len(), 1, "{:?}", out.warnings);
        let w = &out.warnings[0];
        assert!(
            w.starts_with("phasor IRLS: the fine level stopped at its cap of 2"),
            "{w}"
        );
        assert!(
            w.contains("raise fine_iterations") && !w.contains("  "),
            "{w}"
        );

        let both = TofParams {
            channels: ScatterChannels::AmplitudePhase,
            ..capped.clone()
        };
        let out = estimate_tof_depth(&input, &both, &Monitor::noop()).unwrap();
        assert_eq!(out.warnings.len(), 2, "{:?}", out.warnings);
        assert!(
            out.warnings[1].starts_with("phase IRLS"),
            "{:?}",
            out.warnings
        );

        let untested = TofParams {
            convergence_tolerance: 0.0,
            ..capped
        };
        let out = estimate_tof_depth(&input, &untested, &Monitor::noop()).unwrap();
        assert!(out.warnings.is_empty(), "{:?}", out.warnings);
    }

    #[test]
    fn zero_iterations_and_constant_image_are_finite() {
        let (input, _, _) = scene(true, 3);
        let p = TofParams {
            coarse_iterations: 0,
            fine_iterations: 0,
            ..TofParams::default()
        };
        let out = estimate_tof_depth(&input, &p, &Monitor::noop()).unwrap();
        assert!(out.mask.data().iter().all(|&v| v == 0.0));
        assert!(out.weight_phase.data().iter().all(|&v| v == 1.0));
        assert!(out.range_m.data().iter().all(|v| v.is_finite()));

        let c = TofInput {
            amplitude: ImageF32::filled(W, H, 1, 5.0),
            phase: ImageF32::filled(W, H, 1, 0.3),
            intrinsics: Some(Intrinsics::new(50.0, 50.0, 31.5, 23.5)),
        };
        let out = estimate_tof_depth(&c, &fast_params(), &Monitor::noop()).unwrap();
        for img in [&out.range_m, &out.weight_amplitude, &out.scatter_phase] {
            assert!(img.data().iter().all(|v| v.is_finite()));
        }
        assert!(out.z_depth_m.unwrap().data().iter().all(|v| v.is_finite()));
        // The raw z-depth is the raw range times the ray's z component: below the range off
        // the optical axis, equal on it.
        let raw_z = out.raw_z_depth_m.unwrap();
        let k = c.intrinsics.unwrap();
        for (i, (&z, &r)) in raw_z.data().iter().zip(out.raw_range_m.data()).enumerate() {
            let ray = k.ray((i % W) as f64, (i / W) as f64);
            assert!((f64::from(z) - f64::from(r) * ray[2]).abs() < 1e-5 * f64::from(r));
        }
        assert!(out.mask.data().iter().all(|&v| v == 0.0));
    }

    #[test]
    fn cancellation_stops_the_job() {
        let (input, _, _) = scene(true, 5);
        let m = Monitor::noop();
        m.cancel();
        assert_eq!(
            estimate_tof_depth(&input, &fast_params(), &m).unwrap_err(),
            MurkError::Cancelled
        );
        // Cancel from the progress sink after the first IRLS iteration.
        let flag = Arc::new(AtomicBool::new(false));
        let f2 = flag.clone();
        let m = Monitor::new(
            flag,
            Some(Arc::new(move |stage: &str, _| {
                if stage.ends_with(".coarse") {
                    f2.store(true, Ordering::Relaxed);
                }
            })),
        );
        assert_eq!(
            estimate_tof_depth(&input, &fast_params(), &m).unwrap_err(),
            MurkError::Cancelled
        );
    }

    use crate::error::field_of as field;

    #[test]
    fn validation_errors_name_fields() {
        let (input, _, _) = scene(false, 1);
        let m = Monitor::noop();
        let mut bad = input.clone();
        bad.phase = ImageF32::filled(W - 1, H, 1, 0.1);
        assert_eq!(
            field(estimate_tof_depth(&bad, &fast_params(), &m).unwrap_err()),
            "phase"
        );
        let mut bad = input.clone();
        bad.amplitude.set(3, 4, 0, f32::NAN);
        assert_eq!(
            field(estimate_tof_depth(&bad, &fast_params(), &m).unwrap_err()),
            "amplitude"
        );
        for f in [0.0, -1.0, f64::NAN] {
            let p = TofParams {
                modulation_frequency_hz: f,
                ..fast_params()
            };
            assert_eq!(
                field(estimate_tof_depth(&input, &p, &m).unwrap_err()),
                "modulation_frequency_hz"
            );
        }
    }
}
