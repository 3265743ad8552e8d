//! Vignetting compensation: the radial fall-off of the lens, estimated from the matching cost
//! and divided out of every view before the cost volume.
//!
//! A lens records a scene point at image radius `r` darker than at the centre, the airlight
//! included: `I = V(r)·(J·t + A(1 − t))` (Eq. 3.3 with the lens's fall-off). A reference pixel
//! and its match lie at different radii (by their displacement), so even two cameras with the
//! same lens see the same point `V(r_r)/V(r_s)` apart, a few per cent toward the image's sides.
//! Like the exposure gains of [`super::exposure`], that is an offset in every voxel of the L1
//! residuals (Eq. 3.1, and the dehazing residual of Eq. 3.4–3.7 in observation space), and it
//! varies across the image, so one gain per source cannot absorb it: on the hazy Aloe pair with
//! both lenses 30 % darker at the corners, murk's C.P. on SGBM's pixels fell from 97.7 to 77.6 %.
//!
//! The model is one fall-off shared by every view, `V(r) = 1 + a·r²`, `r` the distance from
//! the image centre over the half-diagonal (so `1 + a` is the corners' gain): the views of one
//! moving camera, or a rig of cameras with the same lens. It is the first term of the usual
//! polynomial vignetting models (Kang & Weiss 2000; Goldman 2010). `a` is found as the gains
//! are, from the matching cost itself: on the sample pixels and planes of
//! [`super::exposure::Samples`], with both views divided by `V` and the source by its gains,
//! each sample's best capped residual over the planes, summed over the samples and sources, is
//! minimised over `a ∈ [−0.8, 0.4]` (a grid of 0.05, then Brent's method,
//! [`crate::minimise::grid_then_brent`]). A wrong `a` leaves an offset in the best match of
//! every sample whose match lies at another radius; the identification comes from those
//! displacements, so a fall-off is found only where the views' displacements are a sizable
//! part of the image (a stereo pair's disparity, a moving camera's parallax). A fall-off that
//! removes less than [`MIN_EXPLAINED`] of the matching cost is not applied: on noisy hazy views
//! the best-of-planes objective alone prefers darker corners.
//!
//! A source whose lens differs from the reference's gets its own fall-off relative to the
//! reference's on top (`1 + δ·r²` at its pixels, `estimate_relative_falloff`): the ratio of
//! the two lenses' fall-offs is a gain that varies over the image, seen without any
//! displacement, so it is estimated with the source's gains, before the shared fall-off.

pub use super::image_radius::radius2;
use rayon::prelude::*;

use crate::image::ImageF32;
use crate::minimise::{brent_minimise, grid_then_brent};

use super::exposure::Samples;

/// The range of `a` searched: corners from 0.2 to 1.4 times the centre's brightness.
pub const FALLOFF_RANGE: (f64, f64) = (-0.8, 0.4);

/// Spacing of the search's grid in `a`.
const GRID_STEP: f64 = 0.05;

/// The search's tolerance in `a`.
const TOLERANCE: f64 = 1e-3;

/// The searches' grid uses every this-many-th sample.
const SEARCH_STRIDE: usize = 4;

/// A fall-off with `|a|` below this is not applied ([`applied_falloff`]). On views without
/// vignetting the estimate lands near, not at, 0: on the simulator's hazy rooms (seeds 0–9)
/// within 0.04 with the dehazing cost, and up to 0.067 with the ordinary cost, whose residual
/// has no term for the haze's brightness differences between views and lets the fall-off absorb
/// part of them; hazy far surfaces notice photometric offsets of 0.1 %. A threshold of 0.08
/// would cover those; since [`MIN_EXPLAINED`] rejects fall-offs that remove little of the cost, 0.05
/// keeps the simulator's tables unchanged and lets a shared part of −0.074 through (the hazy
/// Aloe pair with the left lens at 10 % and the right at 30 %: C.P. on SGBM's pixels 94.9 →
/// 97.4 %).
pub const DEAD_BAND: f32 = 0.05;

/// The least share of the matching cost (the objective at `a = 0`) that a shared fall-off must
/// remove to be reported and applied. On forward motion without vignetting the estimate is
/// biased: on the simulator's rooms with `forward_motion` 0.5 (seeds 0–4, 4 sources) it found
/// −0.054 to −0.093, and applying −0.086 to −0.093 cost 2.8–3.7 points of C.P.; those fall-offs
/// removed 0.2–0.9 % of the cost. A real fall-off removes several per cent: −0.15 on the same
/// scenes 2.8–5.3 % (lateral motion 3.4–6.4 %), 10 % vignetting on the hazy Aloe pair 11 %.
/// The bias comes from sensor noise on hazy images: on those scenes without noise the raw
/// search finds `|a|` ≤ 0.005, while 512 planes, or only the sources behind or only those
/// ahead, leave it as it is. It grows with the noise: at σ = 0.02–0.03 false fall-offs removed
/// up to 2 % and true ones as little as 1.5 %, so this separates them only for clean sensors
/// (σ ≈ 0.01; docs/stereo-mvs.md, "Limits").
pub const MIN_EXPLAINED: f64 = 0.015;

/// `a`, or exactly 0 within [`DEAD_BAND`] of 0.
pub fn applied_falloff(a: f32) -> f32 {
    zero_within(a, DEAD_BAND)
}

/// `v`, or exactly 0 when `|v|` is below `band`.
fn zero_within(v: f32, band: f32) -> f32 {
    if v.abs() < band {
        0.0
    } else {
        v
    }
}

/// Σ over every `stride`-th sample of each source of the best (over the planes) capped residual
/// with both views divided by `1 + a·r²` and the source's channels by its `gains`.
fn objective(samples: &[(&Samples, &[f32])], a: f32, stride: usize) -> f64 {
    samples
        .iter()
        .map(|(s, gains)| {
            let inv_g: Vec<f32> = gains.iter().map(|g| 1.0 / g).collect();
            (0..s.len())
                .into_par_iter()
                .step_by(stride)
                .map(|j| f64::from(s.lowest_vignetted(j, &inv_g, a)))
                .sum::<f64>()
        })
        .sum()
}

/// The fall-off `a` of `V(r) = 1 + a·r²` shared by the reference and sources whose
/// samples are given, each with the gains its channels are divided by (see the module docs).
/// 0 when there are no samples, or when the fall-off found removes less than [`MIN_EXPLAINED`]
/// of the matching cost.
pub(super) fn estimate_falloff(samples: &[(&Samples, &[f32])]) -> f32 {
    if samples.iter().all(|(s, _)| s.is_empty()) {
        return 0.0;
    }
    let (a, value, at_zero) = search_falloff(samples);
    // Model selection: a fall-off that barely lowers the matching cost is not one (see
    // [`MIN_EXPLAINED`]).
    if value > (1.0 - MIN_EXPLAINED) * at_zero {
        return 0.0;
    }
    a as f32
}

/// The search of [`estimate_falloff`] without its model selection: the fall-off that minimises
/// the objective, the objective there, and the objective at `a = 0`.
fn search_falloff(samples: &[(&Samples, &[f32])]) -> (f64, f64, f64) {
    let coarse = |a: f64| objective(samples, a as f32, SEARCH_STRIDE);
    let fine = |a: f64| objective(samples, a as f32, 1);
    let m = grid_then_brent(
        coarse,
        fine,
        FALLOFF_RANGE.0,
        FALLOFF_RANGE.1,
        GRID_STEP,
        TOLERANCE,
    );
    (m.x, m.value, fine(0.0))
}

/// The range searched for a source's fall-off relative to the reference's (see
/// [`crate::mvs::DepthResult::source_falloffs`]).
pub const RELATIVE_FALLOFF_RANGE: (f64, f64) = (-0.6, 0.6);

/// A relative fall-off with `|δ|` below this is not applied ([`applied_relative_falloff`]).
/// Unlike the shared fall-off it needs no displacement to be seen, so its estimate on views
/// from one lens stays close to 0: −0.0025 on the un-vignetted hazy Aloe pair, and none
/// applied in 60 runs of the simulator's scenes (lateral and forward motion, A off by ±0.06,
/// the ordinary volume). A 10 % difference at the corners cost 12 points of C.P. on SGBM's
/// pixels on that pair; the band is half of it.
pub const RELATIVE_DEAD_BAND: f32 = 0.05;

/// The bracket, as multiples of the normalised search's answer (plus 0.05 away from 0), in
/// which [`estimate_relative_falloff`] refits the gains for every `δ`.
const REFIT_BRACKET: (f64, f64) = (0.75, 1.5);

/// Half-width in `ln g` of the gain search for each `δ` of the refit (about 10 %).
const REFIT_GAIN_SPAN: f64 = 0.1;

/// The refit's tolerance in `δ`: 0.3 % of brightness at the corners.
const REFIT_TOLERANCE: f64 = 3e-3;

/// Rounds of the gains' L1 refinement for each `δ` the refit tries (all of them for its answer).
const REFIT_ROUNDS: usize = 2;

/// `δ`, or exactly 0 within [`RELATIVE_DEAD_BAND`] of 0.
pub fn applied_relative_falloff(delta: f32) -> f32 {
    zero_within(delta, RELATIVE_DEAD_BAND)
}

/// A source's own fall-off relative to the reference's, `δ` of `1 + δ·r²` at the source's
/// positions, and the source's gains with it taken out: cameras of a rig rarely share the
/// lens's fall-off exactly, and the shared model ([`estimate_falloff`]) cannot represent a
/// difference (on the hazy Aloe pair with only the right lens 20 % darker at the corners,
/// murk's C.P. on SGBM's pixels was 67.6 % against SGBM's 97.2 %).
///
/// Unlike the shared fall-off, a difference between the views is seen without any
/// displacement: a reference pixel and its match differ in brightness by `1 + δ·r_s²` whatever
/// their radii, as a gain that varies over the image. `δ` is found like a gain, from the matching
/// cost on the samples, in two steps:
/// 1. a search over [`RELATIVE_FALLOFF_RANGE`] (grid and Brent) with the gains held at `gains`
///    and the fall-off normalised to keep the samples' mean brightness, `(1 + δ·m)/(1 + δ·r²)`
///    with `m` the samples' mean `r²`, so that the gains found without it stay roughly valid;
/// 2. where that finds more than half the dead band, Brent's method near its answer on the
///    same objective with the gains searched again for every `δ` (on the samples with `1 + δ·r²`
///    divided out), since the normalised gains hold only to first order.
///
/// Returns `δ` and the gains at it (`gains` unchanged when step 2 did not run).
pub(super) fn estimate_relative_falloff(samples: &Samples, gains: &[f32]) -> (f32, Vec<f32>) {
    if samples.is_empty() {
        return (0.0, gains.to_vec());
    }
    let m = samples.mean_source_r2();
    let inv_g: Vec<f32> = gains.iter().map(|g| 1.0 / g).collect();
    let objective = |d: f64, stride: usize| -> f64 {
        let d = d as f32;
        let norm = 1.0 + d * m;
        (0..samples.len())
            .into_par_iter()
            .step_by(stride)
            .map(|j| f64::from(samples.lowest_source_scaled(j, &inv_g, norm, d)))
            .sum()
    };
    let found = grid_then_brent(
        |d| objective(d, SEARCH_STRIDE),
        |d| objective(d, 1),
        RELATIVE_FALLOFF_RANGE.0,
        RELATIVE_FALLOFF_RANGE.1,
        GRID_STEP,
        TOLERANCE,
    );
    // Views from one lens: the bias below only weakens a fall-off, so one this far inside the
    // dead band is not refitted (the simulator's views, the un-vignetted Aloe pair: |δ| < 0.005).
    if found.x.abs() < f64::from(RELATIVE_DEAD_BAND) / 2.0 {
        return (found.x as f32, gains.to_vec());
    }
    // The normalised fall-off keeps the gains only to first order, which biases the search
    // toward a weaker fall-off (−0.16 for a true −0.2 on the hazy Aloe pair); near its answer
    // the gains are refitted for every δ ([`super::exposure::refine_gains`]) and the same
    // objective minimised again.
    let refit = |d: f64, rounds: usize| -> (f64, Vec<f32>) {
        let d = d as f32;
        let relieved = samples.with_source_falloff(d);
        // The normalised fall-off's gains, rescaled, are within a few per cent; searching
        // near them (the refinement alone, started there, can stop at a self-consistent wrong
        // match: 0.98 for a true 1.0 on the Aloe pair above).
        let ranges: Vec<(f64, f64)> = gains
            .iter()
            .map(|&g| {
                let ln = f64::from(g / (1.0 + d * m)).ln();
                (ln - REFIT_GAIN_SPAN, ln + REFIT_GAIN_SPAN)
            })
            .collect();
        let gains =
            super::exposure::gains_searched(&relieved, &ranges, REFIT_GAIN_SPAN / 4.0, rounds);
        let inv_g: Vec<f32> = gains.iter().map(|g| 1.0 / g).collect();
        let total = (0..relieved.len())
            .into_par_iter()
            .map(|j| f64::from(relieved.lowest(j, &inv_g)))
            .sum();
        (total, gains)
    };
    // The bias only weakens: the bracket reaches further from 0 than toward it.
    let (near, far) = (
        found.x * REFIT_BRACKET.0,
        found.x * REFIT_BRACKET.1 + 0.05 * found.x.signum(),
    );
    let (lo, hi) = (
        near.min(far).max(RELATIVE_FALLOFF_RANGE.0),
        near.max(far).min(RELATIVE_FALLOFF_RANGE.1),
    );
    let (d, _) = brent_minimise(
        |d| refit(d, REFIT_ROUNDS).0,
        lo,
        hi,
        found.x,
        REFIT_TOLERANCE,
    );
    let (_, gains) = refit(d, super::exposure::REFINE_ROUNDS);
    let d = d as f32;
    (d, gains)
}

/// `image` divided by `1 + a·r²` (a copy): the fall-off taken out.
pub fn compensate(image: &ImageF32, a: f32) -> ImageF32 {
    scaled_by(image, |r2| 1.0 / (1.0 + a * r2))
}

/// `image` multiplied by `1 + a·r²` (a copy): as a lens with fall-off `a` records it, the
/// inverse of [`compensate`] (for simulated captures and tests).
pub fn vignette(image: &ImageF32, a: f32) -> ImageF32 {
    scaled_by(image, |r2| 1.0 + a * r2)
}

/// `image` with every pixel's channels multiplied by `factor(r²)`.
fn scaled_by(image: &ImageF32, factor: impl Fn(f32) -> f32 + Sync) -> ImageF32 {
    let (w, h, c) = (image.width(), image.height(), image.channels());
    let mut out = image.clone();
    out.data_mut()
        .par_chunks_mut((w * c).max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(c).enumerate() {
                let f = factor(radius2(x as f32, y as f32, w, h));
                px.iter_mut().for_each(|v| *v *= f);
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compensation_divides_by_the_falloff() {
        let img = ImageF32::from_vec(3, 3, 1, vec![0.5; 9]).unwrap();
        let out = compensate(&img, -0.5);
        assert_eq!(out.data()[4], 0.5, "the centre keeps its value");
        assert_eq!(
            out.data()[0],
            1.0,
            "a corner at half the centre's gain is doubled"
        );
        let vignetted = vignette(&img, -0.5);
        assert_eq!(vignetted.data()[0], 0.25);
        let back = compensate(&vignetted, -0.5);
        for (b, v) in back.data().iter().zip(img.data()) {
            assert!((b - v).abs() < 1e-6);
        }
    }

    #[test]
    fn falloffs_in_the_dead_band_are_not_applied() {
        assert_eq!(applied_falloff(0.02), 0.0);
        assert_eq!(applied_falloff(-0.049), 0.0);
        assert_eq!(applied_falloff(-0.074), -0.074);
        assert_eq!(applied_falloff(-0.3), -0.3);
    }
}
