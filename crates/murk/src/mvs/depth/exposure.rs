//! Exposure compensation: the gain of each source camera relative to the reference, per colour
//! channel, estimated from the matching cost itself.
//!
//! Two cameras rarely turn the same radiance into the same number: exposure time, analogue gain
//! and aperture differ. With a gain `g_s` the source records `I_s = g_s·(J·t_s + A(1 − t_s))`
//! (Eq. 3.3 scaled), while the dehazing residual of Eq. 3.5 (observation space,
//! `(I_r − A) − k(I_s − A)`, `k = t_r/t_s`) and the ordinary residual of Eq. 3.1 assume `g_s = 1`.
//! The mismatch is an offset proportional to the brightness, everywhere, which outweighs the
//! texture differences that haze has already scaled down by `t`: on the hazy Aloe pair a 5 %
//! gain on the right camera takes murk's C.P. from 95 % to 44 % (SGBM, whose census cost ignores
//! gains, loses 3 points).
//!
//! The estimate: on a grid of at most [`MAX_SAMPLES`] reference pixels, each pixel's best cost
//! over the planes, `min_i min(|(I_r,c − A) − k_i(I_s,c(π_i(p))/g − A)|, 1)` (the cost volume's
//! residual, one channel at a time, with the source's channel divided by `g`), summed over the
//! pixels, is minimised over `g`. A wrong gain leaves an offset in every pixel's best match,
//! textured or flat, so the sum has its minimum at the true gain; where the plane sweep has no
//! true plane (occlusions, outside the range) the pixel adds a constant-ish term. The search runs
//! over `ln g ∈ [ln ½, ln 2]` on a quarter of the samples, a grid of 0.1 steps then Brent's method
//! between the best point's neighbours ([`crate::minimise::grid_then_brent`]). Then, with each sample's best plane over all channels held
//! fixed, the objective separates by channel and an exact L1 step per channel (a weighted median)
//! refines each gain; the match is chosen again and the step repeated. Gains within
//! [`DEAD_BAND`] of 1 are not applied. The source is then divided by its gains before its cost
//! volume is built ([`compensate`]), which keeps every cost variant unchanged.

use rayon::prelude::*;

use crate::atmosphere::{inverse_transmission, transmission, MIN_TRANSMISSION};
use crate::cpu::compiled_for_avx2;
use crate::image::ImageF32;
use crate::minimise::grid_then_brent;
use crate::mvs::cost_volume::sample::bilinear_inside;
use crate::mvs::cost_volume::{CostKind, View};
use crate::mvs::plane_sweep::{PlaneSet, PlaneWarp};
use crate::mvs::pose::Pose;

use super::image_radius::radius2;

/// Most reference pixels the estimate samples (a regular grid).
pub const MAX_SAMPLES: usize = 2048;

/// Most planes the estimate sweeps (evenly strided over the plane set).
pub const MAX_PLANES: usize = 128;

/// Smallest and largest gain searched (the source's brightness relative to the reference).
pub const GAIN_RANGE: (f32, f32) = (0.5, 2.0);

/// Whether a gain stopped at an end of [`GAIN_RANGE`] (within 0.1 %): the camera may differ by
/// more than it says.
pub fn at_bound(gain: f32) -> bool {
    (gain / GAIN_RANGE.0 - 1.0).abs() < 1e-3 || (gain / GAIN_RANGE.1 - 1.0).abs() < 1e-3
}

/// One sample row's reference values, planes per sample, `k`, source values (interleaved by
/// channel) and the radii of the reference and source positions (the fields of [`Samples`],
/// before they are joined).
type RowSamples = (Vec<f32>, Vec<usize>, Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>);

/// One sample pixel's reference values minus the airlight and, per plane that sees it, `k` and
/// the source's values; the vignetting estimate ([`super::vignetting`]) shares them.
pub(super) struct Samples {
    channels: usize,
    /// `I_r − A` per sample and channel.
    reference: Vec<f32>,
    /// Start of each sample's planes in `k`, `source[c]` and `src_r2`; one extra end.
    start: Vec<usize>,
    /// `k = t_r/t_s` per visible (sample, plane) (1 for the ordinary volume).
    k: Vec<f32>,
    /// `I_s` per channel, then per visible (sample, plane): a sample's planes are contiguous
    /// in each channel, so the searches' loops over them run on vector registers
    /// ([`lowest_scaled`]).
    source: Vec<Vec<f32>>,
    /// `r²` of each sample in the reference ([`super::image_radius::radius2`]).
    ref_r2: Vec<f32>,
    /// `r²` of each visible (sample, plane)'s position in the source.
    src_r2: Vec<f32>,
    airlight: f32,
    penalty: f32,
}

impl Samples {
    /// The samples of `source` against `reference` (see the module docs).
    pub(super) fn collect(
        reference: &View<'_>,
        source: &View<'_>,
        planes: &PlaneSet,
        kind: CostKind,
    ) -> Self {
        let (w, h, c) = (
            reference.image.width(),
            reference.image.height(),
            reference.image.channels(),
        );
        debug_assert!(
            c <= MAX_CHANNELS,
            "views are validated to have 1 or 3 channels"
        );
        let (sw, sh) = (source.image.width(), source.image.height());
        let (airlight, beta) = match kind.dehazing() {
            Some((p, _)) => (p.airlight, p.beta),
            None => (0.0, 0.0),
        };
        let relative = Pose::relative(&reference.pose, &source.pose);
        let stride = planes.num_planes.div_ceil(MAX_PLANES).max(1);
        let warps: Vec<(PlaneWarp, f32)> = (0..planes.num_planes)
            .step_by(stride)
            .map(|i| {
                let z = planes.depth(i as f64);
                let warp = PlaneWarp::new(&reference.intrinsics, &source.intrinsics, &relative, z);
                (warp, transmission(beta, z as f32).max(MIN_TRANSMISSION))
            })
            .collect();
        let step = ((w * h) as f64 / MAX_SAMPLES as f64).sqrt().ceil().max(1.0) as usize;
        let mut s = Samples {
            channels: c,
            reference: Vec::new(),
            start: vec![0],
            k: Vec::new(),
            source: vec![Vec::new(); c],
            ref_r2: Vec::new(),
            src_r2: Vec::new(),
            airlight,
            penalty: c as f32,
        };
        let (rd, sd) = (reference.image.data(), source.image.data());
        // One sample row per rayon task: (reference values, planes per sample, k, source values).
        let rows: Vec<usize> = (step / 2..h).step_by(step).collect();
        let parts: Vec<RowSamples> = rows
            .par_iter()
            .map(|&y| {
                let (mut refs, mut counts, mut ks, mut src, mut rr2, mut sr2) = (
                    Vec::new(),
                    Vec::new(),
                    Vec::new(),
                    Vec::new(),
                    Vec::new(),
                    Vec::new(),
                );
                for x in (step / 2..w).step_by(step) {
                    let before = ks.len();
                    for (warp, t_r) in &warps {
                        let (u, v, zeta) = warp.map(x as f64, y as f64);
                        if zeta <= 0.0
                            || !(0.0..=(sw - 1) as f64).contains(&u)
                            || !(0.0..=(sh - 1) as f64).contains(&v)
                        {
                            continue;
                        }
                        ks.push(if beta > 0.0 {
                            t_r * inverse_transmission(transmission(beta, zeta as f32))
                        } else {
                            1.0
                        });
                        let (u, v) = (u as f32, v as f32);
                        sr2.push(radius2(u, v, sw, sh));
                        match c {
                            1 => src.extend(bilinear_inside::<1>(sd, sw, u, v, sh)),
                            _ => src.extend(bilinear_inside::<3>(sd, sw, u, v, sh)),
                        }
                    }
                    if ks.len() > before {
                        refs.extend(rd[(y * w + x) * c..][..c].iter().map(|v| v - airlight));
                        counts.push(ks.len() - before);
                        rr2.push(radius2(x as f32, y as f32, w, h));
                    }
                }
                (refs, counts, ks, src, rr2, sr2)
            })
            .collect();
        for (refs, counts, ks, src, rr2, sr2) in parts {
            s.ref_r2.extend(rr2);
            s.src_r2.extend(sr2);
            s.reference.extend(refs);
            for n in counts {
                let last = s.start.last().copied().unwrap_or(0);
                s.start.push(last + n);
            }
            s.k.extend(ks);
            for (ch, plane) in s.source.iter_mut().enumerate() {
                plane.extend(src.iter().skip(ch).step_by(c));
            }
        }
        s
    }

    /// Sample `j`'s planes as the lowest-cost loops read them.
    #[inline]
    fn planes_of(&self, j: usize) -> SamplePlanes<'_> {
        let (c, planes) = (self.channels, self.start[j]..self.start[j + 1]);
        let mut source: [&[f32]; MAX_CHANNELS] = [&[]; MAX_CHANNELS];
        for (s, plane) in source.iter_mut().zip(&self.source) {
            *s = &plane[planes.clone()];
        }
        SamplePlanes {
            reference: &self.reference[j * c..(j + 1) * c],
            k: &self.k[planes.clone()],
            src_r2: &self.src_r2[planes],
            source,
        }
    }

    /// Sample `j`'s best (over the planes) capped residual with channel `c` of the source divided
    /// by `gains[c]`, and that plane's index into `k` (`usize::MAX` when no plane is under the
    /// cap): the first plane of least cost. [`Samples::lowest`] is its cost alone, faster.
    pub(super) fn best(&self, j: usize, inv_gains: &[f32]) -> (f32, usize) {
        // The least cost on vector registers, then the first plane that has it: the same plane
        // as a scan that keeps the first strictly lower cost, since every cost is the same
        // expression in both loops (bit for bit).
        let lowest = self.lowest(j, inv_gains);
        if lowest >= self.penalty {
            return (self.penalty, usize::MAX);
        }
        let (c, a) = (self.channels, self.airlight);
        let r = &self.reference[j * c..(j + 1) * c];
        let first = (self.start[j]..self.start[j + 1]).find(|&i| {
            let mut cost = 0.0f32;
            for ((&rv, plane), &ig) in r.iter().zip(&self.source).zip(inv_gains) {
                cost += scaled_residual(rv, self.k[i], plane[i], ig, 1.0, a);
            }
            cost == lowest
        });
        debug_assert!(
            first.is_some(),
            "the least cost is one of the planes' costs"
        );
        (lowest, first.unwrap_or(usize::MAX))
    }

    /// The cost of [`Samples::best`] alone.
    #[inline]
    pub(super) fn lowest(&self, j: usize, inv_gains: &[f32]) -> f32 {
        // A factor of exactly 1/1 multiplies exactly: the same residuals, bit for bit.
        self.lowest_source_scaled(j, inv_gains, 1.0, 0.0)
    }

    /// Σ over every `stride`-th sample of the best (over the planes) capped residual of channel
    /// `ch` alone with the source's channel divided by `gain`: each channel's gain is searched on
    /// its own, as a grey image would be, and on few samples (the weighted-median steps after
    /// the search use every sample).
    fn objective(&self, ch: usize, gain: f32, stride: usize) -> f64 {
        let (c, a, inv_g) = (self.channels, self.airlight, 1.0 / gain);
        (0..self.len())
            .into_par_iter()
            .step_by(stride)
            .map(|j| {
                let planes = self.start[j]..self.start[j + 1];
                f64::from(lowest_in_channel(
                    self.reference[j * c + ch],
                    &self.k[planes.clone()],
                    &self.source[ch][planes],
                    inv_g,
                    a,
                ))
            })
            .sum()
    }

    /// The L1 refinement at a fixed match, channel by channel: with each sample's best plane at
    /// `gains` held fixed, `Σ_p |(I_r − A + kA) − k·I_s·h_c|` is minimised over `h_c = 1/g_c`
    /// exactly by the weighted median of the ratios `(I_r − A + kA)/(k·I_s)` with weights `k·I_s`
    /// (the objective separates by channel once the match is fixed). Samples whose best cost
    /// reaches the cap (no plane explains them) are left out. A channel with nothing left keeps
    /// its gain.
    fn refine(&self, gains: &[f32]) -> Vec<f32> {
        let (c, a) = (self.channels, self.airlight);
        let inv: Vec<f32> = gains.iter().map(|g| 1.0 / g).collect();
        let mut pairs: Vec<Vec<(f32, f32)>> = vec![Vec::new(); c];
        let matches: Vec<usize> = (0..self.len())
            .into_par_iter()
            .map(|j| self.best(j, &inv).1)
            .collect();
        for (j, &i) in matches.iter().enumerate() {
            if i == usize::MAX {
                continue;
            }
            let k = self.k[i];
            let r = &self.reference[j * c..(j + 1) * c];
            for ((&rv, plane), ch) in r.iter().zip(&self.source).zip(&mut pairs) {
                let m = k * plane[i];
                if m > 0.0 {
                    ch.push(((rv + k * a) / m, m));
                }
            }
        }
        pairs
            .iter_mut()
            .zip(gains)
            .map(|(ch, &g)| match weighted_median(ch) {
                Some(h) if h > 0.0 => 1.0 / h,
                _ => g,
            })
            .collect()
    }

    /// Sample `j`'s best (over the planes) capped residual with both views divided by the
    /// fall-off `1 + a·r²` ([`super::vignetting`]), the residual measured in the reference's
    /// recorded units (times its `1 + a·r²`): dividing both views by more than 1 would otherwise
    /// shrink every residual and favour brighter corners whatever the data. Equal to
    /// [`Samples::lowest`] for `a = 0`.
    #[inline]
    pub(super) fn lowest_vignetted(&self, j: usize, inv_gains: &[f32], a: f32) -> f32 {
        let falloff = Falloff {
            ref_factor: 1.0 + a * self.ref_r2[j],
            a,
        };
        lowest_vignetted(
            &self.planes_of(j),
            inv_gains,
            falloff,
            self.airlight,
            self.penalty,
        )
    }

    /// [`Samples::lowest`] with each source value also multiplied by `norm / (1 + δ·r²)` of its
    /// position in the source: a source fall-off relative to the reference's
    /// ([`super::vignetting::estimate_relative_falloff`]), normalised by `norm`. Equal to
    /// [`Samples::lowest`] for `norm = 1`, `δ = 0`.
    #[inline]
    pub(super) fn lowest_source_scaled(
        &self,
        j: usize,
        inv_gains: &[f32],
        norm: f32,
        delta: f32,
    ) -> f32 {
        lowest_scaled(
            &self.planes_of(j),
            inv_gains,
            Falloff {
                ref_factor: norm,
                a: delta,
            },
            self.airlight,
            self.penalty,
        )
    }

    /// Mean `r²` of the source positions of every visible (sample, plane); 0 when empty.
    pub(super) fn mean_source_r2(&self) -> f32 {
        if self.src_r2.is_empty() {
            return 0.0;
        }
        (self.src_r2.iter().map(|&v| f64::from(v)).sum::<f64>() / self.src_r2.len() as f64) as f32
    }

    /// A copy with every source value divided by `1 + a·r²` of its position in the source: the
    /// source's own fall-off, relative to the reference's, taken out (as [`super::vignetting::
    /// compensate`] of the source image would, up to the bilinear interpolation's order).
    pub(super) fn with_source_falloff(&self, a: f32) -> Samples {
        let c = self.channels;
        let factors: Vec<f32> = self.src_r2.iter().map(|&r2| 1.0 / (1.0 + a * r2)).collect();
        let mut source = self.source.clone();
        for plane in &mut source {
            for (v, &f) in plane.iter_mut().zip(&factors) {
                *v *= f;
            }
        }
        Samples {
            channels: c,
            reference: self.reference.clone(),
            start: self.start.clone(),
            k: self.k.clone(),
            source,
            ref_r2: self.ref_r2.clone(),
            src_r2: self.src_r2.clone(),
            airlight: self.airlight,
            penalty: self.penalty,
        }
    }

    /// Number of sample pixels that some plane projects into the source.
    pub(super) fn len(&self) -> usize {
        self.start.len() - 1
    }

    /// No sample pixel is seen by the source.
    pub(super) fn is_empty(&self) -> bool {
        self.start.len() < 2
    }
}

/// Most channels a view has (RGB; grey has one).
const MAX_CHANNELS: usize = 3;

/// Planes the lowest-cost loops take at once: one AVX2 register of `f32`.
const LANES: usize = 8;

/// One sample's reference values (`I_r − A` per channel) and, per plane that sees it, `k`, the
/// source position's `r²` and the source's values per channel (unused channels empty).
struct SamplePlanes<'a> {
    reference: &'a [f32],
    k: &'a [f32],
    src_r2: &'a [f32],
    source: [&'a [f32]; MAX_CHANNELS],
}

/// A fall-off `1 + a·r²` in a lowest-cost loop: `ref_factor` is what the reference's side is
/// multiplied by (`1 + a·r_ref²`, or the relative search's normalisation).
#[derive(Clone, Copy)]
struct Falloff {
    ref_factor: f32,
    a: f32,
}

/// The smaller of `best` and every lane of `lanes` (a minimum, so the order does not matter).
#[inline(always)]
fn lowest_lane(lanes: [f32; LANES], mut best: f32) -> f32 {
    for v in lanes {
        if v < best {
            best = v;
        }
    }
    best
}

/// The residual `|r − k·(s·ig·f − A)|` of one channel at one plane (Eq. 3.5's observation-space
/// residual with the source's gain and relative fall-off divided out): the one expression the
/// searches' loops and [`Samples::best`]'s scan share, so that their costs agree to the bit.
#[inline(always)]
fn scaled_residual(r: f32, k: f32, s: f32, ig: f32, f: f32, airlight: f32) -> f32 {
    (r - k * (s * ig * f - airlight)).abs()
}

/// `min(1, min_i |r − k_i·(s_i·inv_g − a)|)` over a sample's planes, one channel: the loop of
/// [`Samples::objective`] ([`lowest_over_planes`] on that channel alone, capped at 1).
#[inline(always)]
fn lowest_in_channel_body(r: f32, k: &[f32], source: &[f32], inv_g: f32, a: f32) -> f32 {
    let p = SamplePlanes {
        reference: &[r],
        k,
        src_r2: k,
        source: [source, &[], &[]],
    };
    // A factor of exactly 1 multiplies exactly; `src_r2` is not read by it.
    lowest_over_planes(
        &p,
        &[inv_g],
        1.0,
        |_| 1.0,
        |rv, k, s, ig, f| scaled_residual(rv, k, s, ig, f, a),
    )
}

compiled_for_avx2! {
    /// [`lowest_in_channel_body`].
    fn lowest_in_channel(r: f32, k: &[f32], source: &[f32], inv_g: f32, a: f32) -> f32
        => lowest_in_channel_body;
}

/// The least (capped at `penalty`) over a sample's planes of `Σ_c term(r_c, k, s_c, ig_c, f)`,
/// `f = factor(r_s²)` per plane: the loop both fall-off searches share. Eight planes at a time;
/// every lane's cost is the scalar expression's, operation for operation, and the last
/// `n mod 8` planes take the same expression one by one.
#[inline(always)]
fn lowest_over_planes(
    p: &SamplePlanes<'_>,
    inv_gains: &[f32],
    penalty: f32,
    factor: impl Fn(f32) -> f32,
    term: impl Fn(f32, f32, f32, f32, f32) -> f32,
) -> f32 {
    let n = p.k.len();
    let whole = n - n % LANES;
    let mut lanes = [penalty; LANES];
    for i in (0..whole).step_by(LANES) {
        let k = &p.k[i..i + LANES];
        let f: [f32; LANES] = std::array::from_fn(|l| factor(p.src_r2[i + l]));
        let mut cost = [0.0f32; LANES];
        for ((&rv, src), &ig) in p.reference.iter().zip(&p.source).zip(inv_gains) {
            let s = &src[i..i + LANES];
            for l in 0..LANES {
                cost[l] += term(rv, k[l], s[l], ig, f[l]);
            }
        }
        for l in 0..LANES {
            if cost[l] < lanes[l] {
                lanes[l] = cost[l];
            }
        }
    }
    let mut best = lowest_lane(lanes, penalty);
    for i in whole..n {
        let f = factor(p.src_r2[i]);
        let mut cost = 0.0f32;
        for ((&rv, src), &ig) in p.reference.iter().zip(&p.source).zip(inv_gains) {
            cost += term(rv, p.k[i], src[i], ig, f);
        }
        if cost < best {
            best = cost;
        }
    }
    best
}

/// The least (capped at `penalty`) of `Σ_c |r_c − k·(s_c·ig_c·f − A)|` over a sample's planes,
/// `f = falloff.ref_factor / (1 + falloff.a·r_s²)`: [`Samples::best`]'s cost with the source's
/// fall-off relative to the reference's divided out.
#[inline(always)]
fn lowest_scaled_body(
    p: &SamplePlanes<'_>,
    inv_gains: &[f32],
    falloff: Falloff,
    airlight: f32,
    penalty: f32,
) -> f32 {
    lowest_over_planes(
        p,
        inv_gains,
        penalty,
        |r2| falloff.ref_factor / (1.0 + falloff.a * r2),
        |rv, k, s, ig, f| scaled_residual(rv, k, s, ig, f, airlight),
    )
}

compiled_for_avx2! {
    /// [`lowest_scaled_body`].
    fn lowest_scaled(
        p: &SamplePlanes<'_>,
        inv_gains: &[f32],
        falloff: Falloff,
        airlight: f32,
        penalty: f32,
    ) -> f32 => lowest_scaled_body;
}

/// The least (capped at `penalty`) of `Σ_c |r_c + A − v_r·(A + k·(s_c·ig_c/v_s − A))|` over a
/// sample's planes, `v_r = falloff.ref_factor` and `v_s = 1 + falloff.a·r_s²`: both views
/// divided by the shared fall-off, the residual in the reference's recorded units
/// ([`Samples::lowest_vignetted`]).
#[inline(always)]
fn lowest_vignetted_body(
    p: &SamplePlanes<'_>,
    inv_gains: &[f32],
    falloff: Falloff,
    airlight: f32,
    penalty: f32,
) -> f32 {
    let vr = falloff.ref_factor;
    lowest_over_planes(
        p,
        inv_gains,
        penalty,
        |r2| 1.0 / (1.0 + falloff.a * r2),
        |rv, k, s, ig, inv_v| {
            (rv + airlight - vr * (airlight + k * (s * ig * inv_v - airlight))).abs()
        },
    )
}

compiled_for_avx2! {
    /// [`lowest_vignetted_body`].
    fn lowest_vignetted(
        p: &SamplePlanes<'_>,
        inv_gains: &[f32],
        falloff: Falloff,
        airlight: f32,
        penalty: f32,
    ) -> f32 => lowest_vignetted_body;
}

/// The weighted median of `(value, weight)` pairs (sorted in place), `None` when empty.
fn weighted_median(pairs: &mut [(f32, f32)]) -> Option<f32> {
    pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
    let half = 0.5 * pairs.iter().map(|p| f64::from(p.1)).sum::<f64>();
    let mut acc = 0.0f64;
    for &(v, w) in pairs.iter() {
        acc += f64::from(w);
        if acc >= half {
            return Some(v);
        }
    }
    pairs.last().map(|p| p.0)
}

/// The gain of each channel of `source` relative to the same channel of `reference` (see the
/// module docs), one per image channel: exposure moves them together, white balance apart. All
/// 1 when no sample pixel is seen by the source, or when the views do not both have 1 or 3
/// channels.
pub fn estimate_gains(
    reference: &View<'_>,
    source: &View<'_>,
    planes: &PlaneSet,
    kind: CostKind,
) -> Vec<f32> {
    let c = reference.image.channels();
    if !matches!(c, 1 | 3) || source.image.channels() != c {
        // The cost volume rejects such views with a named field; nothing to estimate here.
        return vec![1.0; c];
    }
    gains_from_samples(&Samples::collect(reference, source, planes, kind))
}

/// [`estimate_gains`] on samples already collected ([`Samples::collect`]), so that the
/// fall-off estimate ([`super::vignetting`]) can use the same ones.
pub(super) fn gains_from_samples(samples: &Samples) -> Vec<f32> {
    let range = (f64::from(GAIN_RANGE.0.ln()), f64::from(GAIN_RANGE.1.ln()));
    gains_searched(
        samples,
        &vec![range; samples.channels],
        GRID_STEP,
        REFINE_ROUNDS,
    )
}

/// [`gains_from_samples`] with the search of channel `c` over `ln g ∈ ln_ranges[c]` (inside
/// [`GAIN_RANGE`]) on a grid of `grid_step`: a search near gains already known to within a
/// few per cent ([`super::vignetting::estimate_relative_falloff`]).
pub(super) fn gains_searched(
    samples: &Samples,
    ln_ranges: &[(f64, f64)],
    grid_step: f64,
    rounds: usize,
) -> Vec<f32> {
    let channels = samples.channels;
    if samples.is_empty() {
        return vec![1.0; channels];
    }
    let (lo, hi) = (f64::from(GAIN_RANGE.0.ln()), f64::from(GAIN_RANGE.1.ln()));
    let gains: Vec<f32> = (0..channels)
        .map(|ch| {
            let f = |ln_g: f64| samples.objective(ch, ln_g.exp() as f32, SEARCH_STRIDE);
            let (a, b) = ln_ranges[ch];
            let m = grid_then_brent(f, f, a.max(lo), b.min(hi), grid_step, LOG_TOLERANCE);
            m.x.exp() as f32
        })
        .collect();
    // The searches end at a resolution of ~0.03 %, and hazy far surfaces notice less: their
    // texture contrast is scaled by t. The exact L1 step at a fixed match, now matched on all
    // channels, takes each channel to the data's own precision.
    refine_gains(samples, gains, rounds)
}

/// `gains` refined by up to `rounds` exact L1 steps at a fixed match ([`Samples::refine`]),
/// the match re-chosen after each step; each gain stays in [`GAIN_RANGE`].
pub(super) fn refine_gains(samples: &Samples, mut gains: Vec<f32>, rounds: usize) -> Vec<f32> {
    if samples.is_empty() {
        return gains;
    }
    for _ in 0..rounds {
        let next: Vec<f32> = samples
            .refine(&gains)
            .into_iter()
            .map(|g| g.clamp(GAIN_RANGE.0, GAIN_RANGE.1))
            .collect();
        let done = next
            .iter()
            .zip(&gains)
            .all(|(n, g)| (n / g - 1.0).abs() < 1e-5);
        gains = next;
        if done {
            break;
        }
    }
    gains
}

/// Gains within this relative distance of 1 are not applied ([`applied_gain`]).
///
/// Why: on the simulator's scenes, where every camera has gain 1, the estimate lands 0.01–0.14 %
/// off (the L1 optimum of the data, not the search's resolution), and hazy far surfaces are so
/// sensitive to a photometric offset that applying those gains lowered the mean C.P. of seeds
/// 0–4 from 82.3 to 80.9 %. Half a percent is 3.5× the largest such error; a real gain
/// difference of that size costs about as much as it would to apply a biased estimate of it.
pub const DEAD_BAND: f32 = 0.005;

/// The gain to divide the source by: `gain`, or exactly 1 within [`DEAD_BAND`] of 1.
pub fn applied_gain(gain: f32) -> f32 {
    if (gain - 1.0).abs() < DEAD_BAND {
        1.0
    } else {
        gain
    }
}

/// Spacing of the search's grid in `ln g` (about 10 %).
const GRID_STEP: f64 = 0.1;

/// The search's tolerance in `ln g` (0.025 %); the weighted-median steps refine further.
const LOG_TOLERANCE: f64 = 2.5e-4;

/// The searches use every this-many-th sample (a quarter): they only need to land near the
/// optimum, which the refinement on every sample then finds.
const SEARCH_STRIDE: usize = 4;

/// Rounds of [`Samples::refine`] after the search.
pub(super) const REFINE_ROUNDS: usize = 6;

/// `image` with each channel divided by its gain in `gains` (a copy; one gain per channel), so
/// that a source recorded with those gains matches the reference's exposure and white balance.
pub fn compensate(image: &ImageF32, gains: &[f32]) -> ImageF32 {
    let inv: Vec<f32> = gains.iter().map(|g| 1.0 / g).collect();
    let mut out = image.clone();
    for px in out.data_mut().chunks_exact_mut(inv.len().max(1)) {
        for (v, k) in px.iter_mut().zip(&inv) {
            *v *= k;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::atmosphere::AtmosphereParams;
    use crate::monitor::Monitor;
    use crate::mvs::cost_volume::DehazingOptions;
    use crate::simulate::mvs::{simulate_mvs, MvsSimConfig};

    /// A hazy rectified pair of the simulator whose source's channels are recorded with `gain`
    /// times `tint`, and the gains the estimate finds with the true A and β, and with the
    /// ordinary volume.
    fn found(gain: f32, tint: [f32; 3], seed: u64) -> (Vec<f32>, Vec<f32>) {
        let cfg = MvsSimConfig {
            seed,
            num_views: 2,
            rectified_pair: true,
            ..MvsSimConfig::with_size(160, 120)
        };
        let scene = simulate_mvs(&cfg, &Monitor::noop()).unwrap();
        let views = scene.hazy_views();
        let reference = views[scene.reference];
        let source = views[1 - scene.reference];
        let mut brighter = source.image.clone();
        for px in brighter.data_mut().chunks_exact_mut(3) {
            for (v, t) in px.iter_mut().zip(tint) {
                *v *= gain * t;
            }
        }
        let source = View {
            image: &brighter,
            ..source
        };
        let planes = PlaneSet::new(1.5, 15.0, 64).unwrap();
        let haze = CostKind::DehazingWith(
            AtmosphereParams {
                airlight: scene.airlight,
                beta: scene.beta,
            },
            DehazingOptions::default(),
        );
        (
            estimate_gains(&reference, &source, &planes, haze),
            estimate_gains(&reference, &source, &planes, CostKind::Ordinary),
        )
    }

    #[test]
    fn recovers_source_gains_within_half_a_percent() {
        let neutral = [1.0f32; 3];
        let warmer = [1.04, 1.0, 1.0 / 1.04];
        for (gain, tint, seed) in [
            (1.0f32, neutral, 1u64),
            (1.08, neutral, 2),
            (0.9, neutral, 3),
            (1.25, neutral, 4),
            (1.0, warmer, 5),
            (0.95, warmer, 6),
        ] {
            let (dehazing, ordinary) = found(gain, tint, seed);
            for g in [&dehazing, &ordinary] {
                for (c, (&gc, t)) in g.iter().zip(tint).enumerate() {
                    assert!(
                        (gc / (gain * t) - 1.0).abs() < 0.005,
                        "seed {seed}: channel {c} gain {} estimated as {gc} \
                         (dehazing {dehazing:?}, ordinary {ordinary:?})",
                        gain * t
                    );
                }
            }
        }
    }

    /// Samples with random values: sample `j` has `j % 21` planes (none, fewer than a vector,
    /// several vectors and a remainder), and every third plane repeats the one before it, so
    /// that equal least costs occur and the first must win.
    fn random_samples(channels: usize, seed: u64) -> Samples {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut s = Samples {
            channels,
            reference: Vec::new(),
            start: vec![0],
            k: Vec::new(),
            source: vec![Vec::new(); channels],
            ref_r2: Vec::new(),
            src_r2: Vec::new(),
            airlight: 0.8,
            penalty: channels as f32,
        };
        for j in 0..60 {
            s.reference
                .extend((0..channels).map(|_| rng.random_range(-0.8f32..0.2)));
            s.ref_r2.push(rng.random_range(0.0f32..1.0));
            for i in 0..j % 21 {
                if i % 3 == 2 {
                    let last = s.k.len() - 1;
                    s.k.push(s.k[last]);
                    s.src_r2.push(s.src_r2[last]);
                    for plane in &mut s.source {
                        plane.push(plane[last]);
                    }
                    continue;
                }
                s.k.push(rng.random_range(0.5f32..3.0));
                s.src_r2.push(rng.random_range(0.0f32..1.0));
                for plane in &mut s.source {
                    plane.push(rng.random_range(0.0f32..1.0));
                }
            }
            s.start.push(s.k.len());
        }
        s
    }

    /// The searches' loops before they ran on vector registers: every plane's cost in turn,
    /// the first strictly lower kept. `factor` multiplies the source value; `vignetted` is
    /// `Some(a)` for [`Samples::lowest_vignetted`]'s residual.
    fn scanned(
        s: &Samples,
        j: usize,
        inv_gains: &[f32],
        factor: impl Fn(f32) -> f32,
        vignetted: Option<f32>,
    ) -> (f32, usize) {
        let (c, air) = (s.channels, s.airlight);
        let r = &s.reference[j * c..(j + 1) * c];
        let mut best = (s.penalty, usize::MAX);
        for i in s.start[j]..s.start[j + 1] {
            let k = s.k[i];
            let cost: f32 = (0..c)
                .map(|ch| {
                    let (rv, sv, ig) = (r[ch], s.source[ch][i], inv_gains[ch]);
                    match vignetted {
                        None => (rv - k * (sv * ig * factor(s.src_r2[i]) - air)).abs(),
                        Some(a) => {
                            let vr = 1.0 + a * s.ref_r2[j];
                            let inv_vs = 1.0 / (1.0 + a * s.src_r2[i]);
                            (rv + air - vr * (air + k * (sv * ig * inv_vs - air))).abs()
                        }
                    }
                })
                .sum();
            if cost < best.0 {
                best = (cost, i);
            }
        }
        best
    }

    /// The vector loops give the scanned loops' least costs and first planes bit for bit, with
    /// AVX2 and without, for grey and RGB samples.
    #[test]
    fn lowest_costs_match_the_scanned_planes() {
        for (channels, seed) in [(1usize, 3u64), (3, 4)] {
            let s = random_samples(channels, seed);
            let inv_gains: Vec<f32> = [0.9f32, 1.07, 1.21][..channels].to_vec();
            for scalar in [false, true] {
                crate::cpu::force_scalar(scalar);
                for j in 0..s.len() {
                    let plain = scanned(&s, j, &inv_gains, |_| 1.0, None);
                    assert_eq!(s.best(j, &inv_gains), plain, "sample {j}");
                    assert_eq!(s.lowest(j, &inv_gains).to_bits(), plain.0.to_bits());
                    for (norm, d) in [(1.1f32, 0.25f32), (0.93, -0.2)] {
                        let want = scanned(&s, j, &inv_gains, |r2| norm / (1.0 + d * r2), None);
                        let got = s.lowest_source_scaled(j, &inv_gains, norm, d);
                        assert_eq!(got.to_bits(), want.0.to_bits(), "sample {j}");
                    }
                    for a in [-0.3f32, 0.0, 0.15] {
                        let want = scanned(&s, j, &inv_gains, |_| 1.0, Some(a));
                        let got = s.lowest_vignetted(j, &inv_gains, a);
                        assert_eq!(got.to_bits(), want.0.to_bits(), "sample {j}, a {a}");
                    }
                    for (ch, &inv_g) in inv_gains.iter().enumerate() {
                        let planes = s.start[j]..s.start[j + 1];
                        let r = s.reference[j * channels + ch];
                        let want = planes.clone().fold(1.0f32, |best, i| {
                            best.min((r - s.k[i] * (s.source[ch][i] * inv_g - s.airlight)).abs())
                        });
                        let got = lowest_in_channel(
                            r,
                            &s.k[planes.clone()],
                            &s.source[ch][planes],
                            inv_g,
                            s.airlight,
                        );
                        assert_eq!(got.to_bits(), want.to_bits(), "sample {j}, channel {ch}");
                    }
                }
            }
            crate::cpu::force_scalar(false);
        }
    }

    #[test]
    fn compensation_divides_each_channel_by_its_gain() {
        let img = ImageF32::from_vec(2, 1, 1, vec![0.5, 1.0]).unwrap();
        assert_eq!(compensate(&img, &[2.0]).data(), &[0.25, 0.5]);
        let rgb = ImageF32::from_vec(1, 1, 3, vec![0.5, 0.5, 0.5]).unwrap();
        assert_eq!(compensate(&rgb, &[2.0, 1.0, 0.5]).data(), &[0.25, 0.5, 1.0]);
    }
}
