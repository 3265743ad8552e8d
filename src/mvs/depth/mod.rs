//! Depth from a plane-sweep cost volume without training (issue 3, item 4): the classical
//! regulariser murk uses where the reference (Ch. 3.2.3) feeds its cost volume to a CNN.
//!
//! Pipeline ([`estimate_depth`] / [`depth_from_cost_volume`]):
//!
//! 0. optional Gaussian pre-smoothing of every view ([`presmooth`], σ = 0.8 px by default), the
//!    lens's radial fall-off divided out of every view ([`vignetting`], on by default), and each
//!    source's channels divided by their gains relative to the reference ([`exposure`], on by
//!    default);
//! 1. the ordinary (Eq. 3.1) or dehazing (Eq. 3.7) cost volume, `C(p, i)` in `[0, γ]`, `γ = 3`
//!    for RGB ([`crate::mvs::cost_volume`]), plus the optional census term
//!    ([`crate::mvs::cost_volume::census`]);
//! 2. contrast normalisation: each pixel's curve weighted by `clamp(c₀/c_p, 1, w_max)` from the
//!    reference's local contrast ([`contrast`]), then the box mean of each plane ([`window`]),
//!    written as `u16` levels of the largest weighted cost the strip can hold ([`quantise`]);
//! 3. semi-global aggregation with penalties `P1`, `P2` on plane-index jumps, `P2` optionally
//!    adapted to the reference image gradient ([`sgm`]), in `u16`: by default over the 5 paths
//!    of one top-to-bottom pass ([`sgm::ONE_PASS_DIRECTIONS`], OpenCV's `MODE_SGBM`), or over 8
//!    (or 4) paths in two passes;
//! 4. winner-take-all, parabola sub-plane refinement in inverse depth and a confidence from the
//!    aggregated curve ([`select`]);
//! 5. optional guided, confidence-weighted median of inverse depth ([`filter`]).
//!
//! Memory, 5 paths (the default): every path reaches a row from rows above it, so rows stream
//! from costs to selections a band at a time ([`one_pass_selections`]): a band's `f32` costs,
//! its `u16` levels, one row of sums and one row of path costs per direction, a few MiB per
//! stripe and nothing the size of the volume. Stripes of about 256 rows run in parallel, each
//! one's paths starting 24 rows above it. Within a band, a group of 8 planes at a time is
//! costed, windowed and written as levels ([`window::window_groups_to_levels`]), so the group's
//! rows (164 KB at 640 pixels, 4 own rows and the window's 4) stay in L2 between the three
//! steps, and each row's claims and selection follow its aggregation at once.
//!
//! Memory, 8 or 4 paths: the upward paths need the whole volume of levels and of sums.
//! [`estimate_depth`] builds each strip's `f32` costs (plane-major) a band of rows at a
//! time and windows each band into the strip's pixel-major `u16` levels at once, so no `f32`
//! volume of the whole strip exists; the sum over all paths is a second `u16` volume. The
//! levels' scale is therefore fixed before any cost is computed, from the largest cost the
//! volume can hold ([`quantise`]). At 256×192×256: two 25 MB volumes and a 24 MB band. Larger
//! volumes go in horizontal strips ([`SgmParams::volume_budget_mib`]). [`depth_from_costs`],
//! given a whole `f32` volume, windows it at once and aggregates into its memory.

pub mod consistency;
pub mod contrast;
pub mod exposure;
pub mod filter;
pub mod presmooth;
pub mod quantise;
pub mod select;
pub mod sgm;
pub mod vignetting;
pub mod window;

use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::cost_volume::census::{self, CensusImage, CensusRows, CensusScratch, CensusSource};
use crate::mvs::cost_volume::{
    penalty_for, validate_inputs, CostKind, CostRows, CostScratch, CostVolume, SweepImages, View,
};
use crate::mvs::plane_sweep::PlaneSet;

use crate::mvs::pose::Pose;
use consistency::{ClaimScratch, SourceClaims, SourceGeometry, SourceWinners, Verdict};
use quantise::Quantiser;

pub use select::{select_curve, Selection};
pub use sgm::Penalties;

/// Optional edge-aware post-filter of the inverse-depth map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PostFilter {
    /// No post-filter.
    None,
    /// Guided, confidence-weighted median of inverse depth ([`filter::weighted_median`]).
    WeightedMedian {
        /// Window radius, pixels (`1 ..= 16`).
        radius: usize,
        /// Colour scale σ of the guide weights, pixel-value units per channel (`> 0`).
        sigma: f32,
    },
}

/// Largest accepted [`SgmParams::volume_budget_mib`].
pub const MAX_VOLUME_BUDGET_MIB: usize = 1 << 16;

/// Largest accepted [`SgmParams::speckle_max_size_px`].
pub const MAX_SPECKLE_SIZE_PX: usize = 1 << 20;

/// Parameters of the training-free depth estimator.
///
/// Cost units: the L1 cost is summed over channels, so for RGB values in `[0, 1]` a voxel lies
/// in `[0, 3]` (and `γ = 3`, Eq. 3.7). The defaults are in those units: `P1 = 0.01` (a ±1
/// plane step costs about the residual of one noise standard deviation of a typical camera,
/// ~0.003 per channel, summed over RGB), `P2 = 0.1` (a larger jump costs about a thirtieth of
/// the cost range, so it needs a few pixels of consistent evidence along a path), adapted to
/// the image gradient with `τ = 0.05`, on a 5×5 cost window. Haze scales the photometric
/// contrast by `t` (0.1–0.4 in the reference's setting), so penalties sized for clear images
/// (`P1 = 0.05`, `P2 = 0.5`, measured earlier) drown far surfaces in smoothness: on the
/// simulated hazy scenes the smaller penalties raise C.P. by about 10 points for both cost
/// volumes at a cost of ≈ 2 points on clear images (`src/mvs/tests.rs`). For one-channel images
/// divide the penalties by 3.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SgmParams {
    /// `P1`, cost units, finite and `≥ 0`.
    pub p1: f32,
    /// `P2`, cost units, finite and `≥ p1`.
    pub p2: f32,
    /// `τ` of the adaptive `P2` (see [`Penalties::p2_gradient_scale`]), pixel-value units;
    /// `0` = constant `P2`. Finite and `≥ 0`.
    pub p2_gradient_scale: f32,
    /// Number of path directions: 5 ([`sgm::ONE_PASS_DIRECTIONS`]: both horizontal ones and the
    /// three going down, one pass that keeps no volume), 8 (all, two passes over stored volumes
    /// bounded by [`SgmParams::volume_budget_mib`]) or 4 (horizontal + vertical, two passes).
    ///
    /// 5 is the default: on the hazy Aloe pair it is 0.05 points of C.P. below 8 paths (95.27
    /// against 95.32 %) at about three quarters of the time and 60 % of the peak memory, and on
    /// the simulator's hazy scenes its mean C.P. is as high (docs/ACCURACY.md).
    pub num_paths: usize,
    /// Radius of the per-plane box mean applied before aggregation, pixels (`0` = none,
    /// at most 16).
    pub cost_window_radius: usize,
    /// Optional post-filter (off by default).
    pub post_filter: PostFilter,
    /// σ of the Gaussian applied to every view before the cost volume ([`presmooth`]), pixels,
    /// `0 ..= 4` (`0` = none). Used by [`estimate_depth`], not by [`depth_from_cost_volume`],
    /// which receives a finished volume.
    pub presmooth_sigma_px: f32,
    /// Percentile (0–100) of the reference's local contrast that sets `c₀` of the contrast
    /// normalisation ([`contrast`]).
    pub contrast_percentile: f32,
    /// Largest contrast weight `w_max` (`1 ..= 64`; `1` = no contrast normalisation).
    pub contrast_max_weight: f32,
    /// Source–reference consistency check ([`consistency`]): pixels whose winning plane
    /// disagrees with every source's own winner get confidence 0 and a filled depth. Needs the
    /// views, so [`estimate_depth`] runs it and [`depth_from_cost_volume`] does not.
    pub consistency_check: bool,
    /// Largest disagreement, in planes, that still counts as consistent (finite, `>= 0`; about
    /// pixels of displacement with the automatic plane count; SGBM's `disp12MaxDiff`).
    pub consistency_tolerance_planes: f32,
    /// Speckles smaller than this many pixels are rejected ([`consistency::reject_speckles`]);
    /// `None` = automatic, `W·H / 3000` (100 pixels at 640×480, SGBM's usual window); `Some(0)`
    /// = off.
    pub speckle_max_size_px: Option<usize>,
    /// Largest plane-index step inside one speckle region (finite, `>= 0`).
    pub speckle_range_planes: f32,
    /// Estimate each source's exposure gain per channel relative to the reference and divide the
    /// source by it before the cost volume ([`exposure`]); the gains are reported in
    /// [`DepthResult::source_gains`]. Used by [`estimate_depth`] (which has the views). Default
    /// on.
    pub exposure_compensation: bool,
    /// Weight `λ` of the census term added to every voxel
    /// ([`crate::mvs::cost_volume::census`]), cost units for a Hamming distance of all the
    /// code's bits (finite, `0 ..= 3`; `0` = off). Used by [`estimate_depth`].
    pub census_weight: f32,
    /// Estimate the lens's radial fall-off, one for every view, and divide it out of every view
    /// before the cost volume ([`vignetting`]); the fall-off is reported in
    /// [`DepthResult::vignetting_falloff`]. Used by [`estimate_depth`]. Default on.
    pub vignetting_compensation: bool,
    /// Memory bound with 8 or 4 paths, MiB (`1 ..= 65536`; the default 5 paths keep no volume and
    /// ignore it): when the `f32` cost volume of the whole reference is larger, depth is estimated
    /// in horizontal strips whose volume (own rows plus [`STRIP_OVERLAP_ROWS`] above and below)
    /// fits it. A strip holds two `u16` volumes (the windowed levels and the aggregated costs,
    /// [`quantise`]; together the size of the `f32` volume) and one band of `f32` costs, at most a
    /// quarter of this (the strip's costs are built and windowed band by band), so the peak is
    /// about 1.25 times this plus the images. Strips change SGM's vertical and diagonal paths only
    /// beyond the overlap: on the hazy Aloe pair (640×480, 173 planes) 0.06 % of the pixels moved,
    /// by at most 0.2 % of the inverse-depth range, at 48 MiB; on a simulated 160×120 scene cut
    /// into 15-row strips 98 % stayed within one plane step, with the same C.P. Default 96: three
    /// strips on that pair (the overlap adds 20 % to the rows processed, against 40 % in five
    /// strips at 64), a peak of about 205 MiB for the whole `murk mvs` process.
    pub volume_budget_mib: usize,
}

impl Default for SgmParams {
    fn default() -> Self {
        Self {
            p1: 0.01,
            p2: 0.1,
            p2_gradient_scale: 0.05,
            num_paths: 5,
            cost_window_radius: 2,
            post_filter: PostFilter::None,
            presmooth_sigma_px: 0.8,
            contrast_percentile: 95.0,
            contrast_max_weight: 4.0,
            consistency_check: true,
            consistency_tolerance_planes: 1.0,
            speckle_max_size_px: None,
            speckle_range_planes: 2.0,
            exposure_compensation: true,
            census_weight: 0.0,
            vignetting_compensation: true,
            volume_budget_mib: 96,
        }
    }
}

impl SgmParams {
    /// Fails naming the offending field (`p1`, `p2`, `p2_gradient_scale`, `num_paths`,
    /// `cost_window_radius`, `post_filter.radius`, `post_filter.sigma`, `presmooth_sigma_px`,
    /// `contrast_percentile`, `contrast_max_weight`).
    pub fn validate(&self) -> Result<()> {
        if !self.p1.is_finite() || self.p1 < 0.0 {
            return Err(MurkError::invalid(
                "p1",
                format!("P1 must be finite and >= 0 (cost units), got {}", self.p1),
            ));
        }
        if !self.p2.is_finite() || self.p2 < self.p1 {
            return Err(MurkError::invalid(
                "p2",
                format!(
                    "P2 must be finite and >= P1 = {} (cost units), got {}",
                    self.p1, self.p2
                ),
            ));
        }
        if !self.p2_gradient_scale.is_finite() || self.p2_gradient_scale < 0.0 {
            return Err(MurkError::invalid(
                "p2_gradient_scale",
                format!("must be finite and >= 0, got {}", self.p2_gradient_scale),
            ));
        }
        if ![4, 5, 8].contains(&self.num_paths) {
            return Err(MurkError::invalid(
                "num_paths",
                format!("must be 4, 5 or 8, got {}", self.num_paths),
            ));
        }
        if self.cost_window_radius > 16 {
            return Err(MurkError::invalid(
                "cost_window_radius",
                format!("must be at most 16 pixels, got {}", self.cost_window_radius),
            ));
        }
        if !self.presmooth_sigma_px.is_finite()
            || !(0.0..=presmooth::MAX_PRESMOOTH_SIGMA_PX).contains(&self.presmooth_sigma_px)
        {
            return Err(MurkError::invalid(
                "presmooth_sigma_px",
                format!(
                    "must be in 0..={} pixels, got {}",
                    presmooth::MAX_PRESMOOTH_SIGMA_PX,
                    self.presmooth_sigma_px
                ),
            ));
        }
        if !self.contrast_percentile.is_finite()
            || !(0.0..=100.0).contains(&self.contrast_percentile)
        {
            return Err(MurkError::invalid(
                "contrast_percentile",
                format!("must be in 0..=100, got {}", self.contrast_percentile),
            ));
        }
        if !self.contrast_max_weight.is_finite()
            || !(1.0..=64.0).contains(&self.contrast_max_weight)
        {
            return Err(MurkError::invalid(
                "contrast_max_weight",
                format!("must be in 1..=64, got {}", self.contrast_max_weight),
            ));
        }
        if !self.consistency_tolerance_planes.is_finite() || self.consistency_tolerance_planes < 0.0
        {
            return Err(MurkError::invalid(
                "consistency_tolerance_planes",
                format!(
                    "must be finite and >= 0 planes, got {}",
                    self.consistency_tolerance_planes
                ),
            ));
        }
        if !self.speckle_range_planes.is_finite() || self.speckle_range_planes < 0.0 {
            return Err(MurkError::invalid(
                "speckle_range_planes",
                format!(
                    "must be finite and >= 0 planes, got {}",
                    self.speckle_range_planes
                ),
            ));
        }
        if let Some(s) = self.speckle_max_size_px {
            if s > MAX_SPECKLE_SIZE_PX {
                return Err(MurkError::invalid(
                    "speckle_max_size_px",
                    format!("must be at most {MAX_SPECKLE_SIZE_PX} pixels, got {s}"),
                ));
            }
        }
        if !self.census_weight.is_finite() || !(0.0..=3.0).contains(&self.census_weight) {
            return Err(MurkError::invalid(
                "census_weight",
                format!("must be in 0..=3 (cost units), got {}", self.census_weight),
            ));
        }
        if !(1..=MAX_VOLUME_BUDGET_MIB).contains(&self.volume_budget_mib) {
            return Err(MurkError::invalid(
                "volume_budget_mib",
                format!(
                    "must be in 1..={MAX_VOLUME_BUDGET_MIB} MiB, got {}",
                    self.volume_budget_mib
                ),
            ));
        }
        if let PostFilter::WeightedMedian { radius, sigma } = self.post_filter {
            if !(1..=16).contains(&radius) {
                return Err(MurkError::invalid(
                    "post_filter.radius",
                    format!("must be in 1..=16 pixels, got {radius}"),
                ));
            }
            if !sigma.is_finite() || sigma <= 0.0 {
                return Err(MurkError::invalid(
                    "post_filter.sigma",
                    format!("must be finite and > 0, got {sigma}"),
                ));
            }
        }
        Ok(())
    }

    /// The aggregation penalties.
    pub fn penalties(&self) -> Penalties {
        Penalties {
            p1: self.p1,
            p2: self.p2,
            p2_gradient_scale: self.p2_gradient_scale,
        }
    }
}

/// Depth of the reference view.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthResult {
    /// z-depth, scene units (one channel): `1 / inverse_depth`.
    pub z_depth: ImageF32,
    /// Inverse z-depth, per scene unit (one channel), within the plane set's range.
    pub inverse_depth: ImageF32,
    /// Confidence in `[0, 1]` (one channel), see [`select`].
    pub confidence: ImageF32,
    /// The gain each source's channels were divided by ([`exposure`]), source-major, one per
    /// image channel (`sources × channels` values): the estimated gain of that channel relative
    /// to the reference's, exactly 1 within [`exposure::DEAD_BAND`] of 1 or where compensation
    /// is off; empty from [`depth_from_cost_volume`].
    pub source_gains: Vec<f32>,
    /// The fall-off `a` of `V(r) = 1 + a·r²` divided out of every view ([`vignetting`]; the
    /// corners' brightness relative to the centre is `1 + a`); exactly 0 within
    /// [`vignetting::DEAD_BAND`] of 0, where compensation is off, or from
    /// [`depth_from_cost_volume`].
    pub vignetting_falloff: f32,
    /// Each source's fall-off relative to the reference's, estimated with its gains from the
    /// matching cost ([`vignetting`]): `δ` of `1 + δ·r²` at the source's own pixels, divided out
    /// of that source (after the shared [`DepthResult::vignetting_falloff`]); exactly 0 within
    /// [`vignetting::RELATIVE_DEAD_BAND`] of 0, or where exposure or vignetting compensation is
    /// off; empty from [`depth_from_cost_volume`].
    pub source_falloffs: Vec<f32>,
    /// What the caller should know about the estimate, one sentence each: a source gain or the
    /// fall-off that reached the end of its searched range (the camera may differ by more than
    /// the compensation removed). Empty when nothing needs saying.
    pub warnings: Vec<String>,
}

/// Cost volume (Eq. 3.1 or 3.7) plus [`depth_from_cost_volume`]. Errors are those of
/// [`build_cost_volume`] plus `sgm.…` for bad parameters; cancellation returns `Cancelled`.
pub fn estimate_depth(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &SgmParams,
    monitor: &Monitor,
) -> Result<DepthResult> {
    estimate_depth_in_bands(
        reference,
        sources,
        planes,
        kind,
        params,
        Layout::default(),
        monitor,
    )
}

/// How [`estimate_depth_in_bands`] lays out its work; the defaults are [`estimate_depth`]'s.
#[derive(Clone, Copy, Debug, Default)]
struct Layout {
    /// Own rows per band (default [`band_rows_of`] for strips, [`ONE_PASS_BAND_ROWS`] for the
    /// one pass); the depth does not depend on it (tested).
    band_rows: Option<usize>,
    /// Own rows per one-pass stripe (default [`ONE_PASS_STRIPE_ROWS`]).
    stripe_rows: Option<usize>,
    /// With 5 paths, aggregate strip volumes ([`strip_pass_selections`]) instead of streaming
    /// rows: the same depth where the one pass has one stripe and the volumes one strip (tested).
    volumes: bool,
}

/// [`estimate_depth`] with its work laid out as `layout` says.
fn estimate_depth_in_bands(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &SgmParams,
    layout: Layout,
    monitor: &Monitor,
) -> Result<DepthResult> {
    params.validate().map_err(|e| e.within("sgm"))?;
    // Invalid images are left to `build_cost_volume` to report; smoothing keeps their sizes and
    // spreads NaN, so the field it names is unchanged.
    let sigma = params.presmooth_sigma_px;
    let smoothed: Option<(ImageF32, Vec<ImageF32>)> = (sigma > 0.0).then(|| {
        (
            presmooth::gaussian_presmooth(reference.image, sigma),
            sources
                .iter()
                .map(|s| presmooth::gaussian_presmooth(s.image, sigma))
                .collect(),
        )
    });
    let (reference, sources) = views_over(reference, sources, &smoothed);
    // Bad views fail before any strip's volume is built.
    validate_inputs(&reference, &sources, planes, kind)?;
    let channels = reference.image.channels();
    // Each source's samples are collected once for its gains and the fall-off estimate.
    let samples: Vec<exposure::Samples> =
        if params.exposure_compensation || params.vignetting_compensation {
            sources
                .iter()
                .map(|s| exposure::Samples::collect(&reference, s, planes, kind))
                .collect()
        } else {
            Vec::new()
        };
    let gains_of = |samples: &[exposure::Samples]| -> Vec<f32> {
        if params.exposure_compensation {
            samples
                .iter()
                .flat_map(exposure::gains_from_samples)
                .collect()
        } else {
            vec![1.0; sources.len() * channels]
        }
    };
    // Each source's own fall-off relative to the reference's (a lens that differs) comes
    // first: a gain that varies over the image, seen without any displacement, so it is
    // estimated with the gains and only where they are. Left in, it would be read as a shared
    // fall-off (only the right lens of the hazy Aloe pair 20 % darker at the corners: 0.10).
    let relative = |samples: &[exposure::Samples], mut gains: Vec<f32>| -> (Vec<f32>, Vec<f32>) {
        let mut deltas = vec![0.0f32; samples.len()];
        if !(params.vignetting_compensation && params.exposure_compensation) {
            return (deltas, gains);
        }
        for ((delta, gains), samples) in deltas
            .iter_mut()
            .zip(gains.chunks_exact_mut(channels))
            .zip(samples)
        {
            if gains.iter().any(|&g| exposure::at_bound(g)) {
                continue;
            }
            let (d, refined) = vignetting::estimate_relative_falloff(samples, gains);
            *delta = vignetting::applied_relative_falloff(d);
            if *delta != 0.0 {
                gains.copy_from_slice(&refined);
            }
        }
        (deltas, gains)
    };
    let (raw_falloffs, raw_gains) = relative(&samples, gains_of(&samples));
    // The lens's fall-off shared by every view, with each source's channels divided by the
    // gains and its relative fall-off found without it. A source whose gain stopped at the
    // search's bound is left out: the brightness its gain did not remove would be read as a
    // fall-off (a source 2.5× brighter drove it to the bound).
    let falloff = if params.vignetting_compensation {
        let relieved: Vec<Option<exposure::Samples>> = samples
            .iter()
            .zip(&raw_falloffs)
            .map(|(s, &d)| (d != 0.0).then(|| s.with_source_falloff(d)))
            .collect();
        let usable: Vec<(&exposure::Samples, &[f32])> = samples
            .iter()
            .zip(&relieved)
            .map(|(s, r)| r.as_ref().unwrap_or(s))
            .zip(raw_gains.chunks_exact(channels))
            .filter(|(_, g)| !g.iter().any(|&g| exposure::at_bound(g)))
            .collect();
        vignetting::applied_falloff(vignetting::estimate_falloff(&usable))
    } else {
        0.0
    };
    let devignetted: Option<(ImageF32, Vec<ImageF32>)> = (falloff != 0.0).then(|| {
        (
            vignetting::compensate(reference.image, falloff),
            sources
                .iter()
                .map(|s| vignetting::compensate(s.image, falloff))
                .collect(),
        )
    });
    let (reference, sources) = views_over(&reference, &sources, &devignetted);
    // The samples again once the shared fall-off is out of the views, and the gains and
    // relative fall-offs from them: it had biased them toward its mean.
    let (source_falloffs, source_gains) = if devignetted.is_some() {
        let samples: Vec<exposure::Samples> = sources
            .iter()
            .map(|s| exposure::Samples::collect(&reference, s, planes, kind))
            .collect();
        relative(&samples, gains_of(&samples))
    } else {
        (raw_falloffs, raw_gains)
    };
    let source_gains: Vec<f32> = source_gains
        .into_iter()
        .map(exposure::applied_gain)
        .collect();
    let compensated: Vec<Option<ImageF32>> = sources
        .iter()
        .zip(source_gains.chunks_exact(channels))
        .zip(&source_falloffs)
        .map(|((s, g), &delta)| {
            let devignetted = (delta != 0.0).then(|| vignetting::compensate(s.image, delta));
            let image = devignetted.as_ref().unwrap_or(s.image);
            if g.iter().any(|&g| g != 1.0) {
                Some(exposure::compensate(image, g))
            } else {
                devignetted
            }
        })
        .collect();
    let sources: Vec<View<'_>> = sources
        .iter()
        .zip(&compensated)
        .map(|(v, img)| match img {
            Some(image) => View { image, ..*v },
            None => *v,
        })
        .collect();
    let geometry: Vec<SourceGeometry> = if params.consistency_check {
        sources
            .iter()
            .map(|s| SourceGeometry {
                k_ref: reference.intrinsics,
                k_src: s.intrinsics,
                relative: Pose::relative(&reference.pose, &s.pose),
                width: s.image.width(),
                height: s.image.height(),
            })
            .collect()
    } else {
        Vec::new()
    };
    let guide = reference.image;
    let (w, h) = guide.dims();
    let weights = contrast_weights_of(guide, params);
    // Codes of the views as the photometric term sees them (smoothed, gains divided out).
    let census: Option<(CensusImage, Vec<CensusImage>)> = (params.census_weight > 0.0).then(|| {
        (
            census::census_transform(reference.image),
            sources
                .iter()
                .map(|s| census::census_transform(s.image))
                .collect(),
        )
    });
    let census_sources: Vec<CensusSource<'_>> = match &census {
        Some((_, codes)) => sources
            .iter()
            .zip(codes)
            .map(|(s, codes)| CensusSource {
                census: codes,
                intrinsics: s.intrinsics,
                relative: Pose::relative(&reference.pose, &s.pose),
            })
            .collect(),
        None => Vec::new(),
    };
    let claims: Vec<SourceClaims> = geometry
        .iter()
        .map(|g| SourceClaims::new(g, planes))
        .collect();
    let images = SweepImages::new(&reference, &sources, planes, kind)?;
    let source = LevelSource {
        reference: &reference,
        sources: &sources,
        planes,
        kind,
        images: &images,
        census: census
            .as_ref()
            .map(|(codes, _)| (codes, &census_sources[..])),
        weights: &weights,
        census_weight: params.census_weight,
        radius: params.cost_window_radius,
    };
    let selections = if params.num_paths == 5 && !layout.volumes {
        one_pass_selections(&source, guide, params, layout, &claims, monitor)?
    } else {
        let bands = layout.band_rows;
        strip_pass_selections(&source, guide, params, bands, &claims, monitor)?
    };
    let mut depth = finish_depth(selections, w, h, planes, guide, params, claims, monitor)?;
    depth.source_gains = source_gains;
    depth.vignetting_falloff = falloff;
    depth.warnings = bound_warnings(&depth.source_gains, channels, falloff, &source_falloffs);
    depth.source_falloffs = source_falloffs;
    Ok(depth)
}

/// What building rows of `u16` levels needs besides the rows (step 1–2 of the module docs):
/// the views as the cost sees them and their sweep copies, the census codes, and the contrast
/// weights of the whole reference.
struct LevelSource<'a> {
    reference: &'a View<'a>,
    sources: &'a [View<'a>],
    planes: &'a PlaneSet,
    kind: CostKind,
    images: &'a SweepImages,
    /// The reference's census codes and the sources' (with their geometry), when the census
    /// term is on.
    census: Option<(&'a CensusImage, &'a [CensusSource<'a>])>,
    /// Contrast weights, row-major over the whole reference (empty = all 1).
    weights: &'a [f32],
    census_weight: f32,
    /// Radius of the box window, pixels.
    radius: usize,
}

impl LevelSource<'_> {
    fn width(&self) -> usize {
        self.reference.image.width()
    }

    fn height(&self) -> usize {
        self.reference.image.height()
    }

    fn planes(&self) -> usize {
        self.planes.num_planes
    }

    /// The contrast weights of the image rows `rows` (empty when there are none).
    fn weights_of(&self, rows: &std::ops::Range<usize>) -> &[f32] {
        if self.weights.is_empty() {
            self.weights
        } else {
            let w = self.width();
            &self.weights[rows.start * w..rows.end * w]
        }
    }
}

/// One band's costs (`[plane][row][x]`, each plane's rows `stride` values apart) and which image
/// rows it holds, reused band after band: a band's first rows are usually the previous band's
/// last ones (the rows both bands' windows read), whose weighted horizontal means are moved to
/// the front of each plane instead of computed again.
struct Band {
    costs: Vec<f32>,
    /// Values from one plane's rows to the next plane's: the most rows a band holds.
    stride: usize,
    /// The image rows of the last band.
    kept: Option<std::ops::Range<usize>>,
}

impl Band {
    /// A band of up to `rows` rows of `w`-pixel, `n`-plane costs.
    fn new(rows: usize, w: usize, n: usize) -> Self {
        Self {
            costs: crate::large_buffer::zeroed::<f32>(rows * w * n),
            stride: rows * w,
            kept: None,
        }
    }

    /// The levels of image rows `own` into `out` (`[row][x][plane]`, `own.len() · w · n`
    /// values), scaled by `quant`: their costs and those of the rows their windows read are
    /// built (or their means moved from the last band), the census term added, and the window
    /// run, clipped at the rows `clip` (a strip's rows, or the whole image's), a group of planes
    /// at a time while its rows are in L2 ([`window::window_groups_to_levels`]). The band must
    /// hold `own.len() + 2r` rows.
    fn levels(
        &mut self,
        src: &LevelSource<'_>,
        clip: std::ops::Range<usize>,
        own: std::ops::Range<usize>,
        quant: &Quantiser,
        out: &mut [u16],
        monitor: &Monitor,
    ) -> Result<()> {
        let (w, n, r) = (src.width(), src.planes(), src.radius);
        let read = own.start.saturating_sub(r).max(clip.start)..(own.end + r).min(clip.end);
        let (held, stride) = (read.len(), self.stride);
        assert!(
            held * w <= stride,
            "the band holds the rows its windows read"
        );
        // A row's horizontal means do not depend on the band or the strip, so any row of the
        // last band is moved; with the census term, which adds to whole bands' costs, they are
        // computed again.
        let (have, shift) = match &self.kept {
            Some(prev)
                if src.census.is_none() && prev.start <= read.start && read.start < prev.end =>
            {
                (prev.end.min(read.end) - read.start, read.start - prev.start)
            }
            _ => (0, 0),
        };
        // The kept means are invalid from here until every group has been rebuilt.
        self.kept = None;
        let costs = (have < held)
            .then(|| {
                CostRows::new(
                    src.reference,
                    src.sources,
                    src.planes,
                    src.kind,
                    read.start + have..read.end,
                    src.images,
                )
            })
            .transpose()?;
        let census = src.census.map(|(codes, sources)| CensusRows {
            reference: codes,
            k_ref: &src.reference.intrinsics,
            sources,
            planes: src.planes,
            rows: read.clone(),
            weight: src.census_weight,
            pixel_weights: src.weights_of(&read),
        });
        let groups = n.div_ceil(window::LEVEL_GROUP);
        let done = AtomicUsize::new(0);
        window::window_groups_to_levels(
            &mut self.costs[..n * stride],
            stride,
            window::GroupRows {
                data_rows: read.start - clip.start..read.end - clip.start,
                filtered: have,
                out_rows: own.start - clip.start..own.end - clip.start,
            },
            src.weights_of(&clip),
            (w, clip.len(), n, r),
            quant,
            out,
            || (CostScratch::default(), CensusScratch::default()),
            |(cost_scratch, census_scratch), g0, group| {
                for (j, plane) in group.chunks_exact_mut(stride).enumerate() {
                    if have > 0 && shift > 0 {
                        plane.copy_within(shift * w..(shift + have) * w, 0);
                    }
                    if let Some(costs) = &costs {
                        costs.fill_plane(g0 + j, &mut plane[have * w..held * w], cost_scratch);
                    }
                    if let Some(census) = &census {
                        census.add_to_plane(g0 + j, &mut plane[..held * w], census_scratch);
                    }
                }
                let k = done.fetch_add(1, Ordering::Relaxed) + 1;
                monitor.progress("mvs.cost_volume", k as f32 / groups as f32);
                Ok(())
            },
            monitor,
        )?;
        self.kept = Some(read);
        Ok(())
    }
}

/// Steps 1–4 of the module docs with 8 or 4 paths: strip by strip ([`strips_of`]), each strip's
/// levels built band by band ([`band_rows_of`] own rows, or `band_rows`), then SGM over the
/// strip's levels into its sums and the selections of its own rows ([`strip_selections`]).
fn strip_pass_selections(
    src: &LevelSource<'_>,
    guide: &ImageF32,
    params: &SgmParams,
    band_rows: Option<usize>,
    claims: &[SourceClaims],
    monitor: &Monitor,
) -> Result<Vec<Selection>> {
    let (w, h, n) = (src.width(), src.height(), src.planes());
    let r = src.radius;
    let strips = strips_of(w, h, n, params.volume_budget_mib);
    let band_rows = band_rows
        .unwrap_or_else(|| band_rows_of(w, n, r, params.volume_budget_mib))
        .max(1);
    let mut selections = Vec::with_capacity(w * h);
    let k = strips.len() as f32;
    // The levels and the aggregated costs of the tallest strip, and one band's `f32` costs,
    // reused from strip to strip and band to band.
    let tallest = strips.iter().map(|s| s.rows.len()).max().unwrap_or(0) * w * n;
    let mut levels = crate::large_buffer::zeroed::<u16>(tallest);
    let mut sum = crate::large_buffer::zeroed::<u16>(tallest);
    let mut band = Band::new((band_rows + 2 * r).min(h), w, n);
    let row_len = w * n;
    for (j, strip) in strips.iter().enumerate() {
        let rows = strip.rows.len();
        let quant = Quantiser::new(
            cost_bound(
                src.reference.image.channels(),
                src.weights_of(&strip.rows),
                params.census_weight,
            ),
            params.p2.max(params.p1),
            params.num_paths,
        );
        let m = monitor.sub(j as f32 / k, (j as f32 + 0.5) / k);
        // Bands of equal height, so that the last one is not a sliver that one worker windows.
        let bands = rows.div_ceil(band_rows);
        let band_rows = rows.div_ceil(bands);
        for b in 0..bands {
            let m = m.sub(b as f32 / bands as f32, (b + 1) as f32 / bands as f32);
            // Strip-relative own rows of the band.
            let own = b * band_rows..((b + 1) * band_rows).min(rows);
            band.levels(
                src,
                strip.rows.clone(),
                strip.rows.start + own.start..strip.rows.start + own.end,
                &quant,
                &mut levels[own.start * row_len..own.end * row_len],
                &m,
            )?;
        }
        let m = monitor.sub((j as f32 + 0.5) / k, (j as f32 + 1.0) / k);
        selections.extend(strip_selections(
            &levels[..rows * row_len],
            &mut sum[..rows * row_len],
            &quant,
            strip,
            w,
            src.planes,
            guide,
            params,
            claims,
            &m,
        )?);
    }
    Ok(selections)
}

/// Own rows of a one-pass stripe ([`one_pass_selections`]), about: tall enough that the paths'
/// warm-up rows above each stripe ([`STRIP_OVERLAP_ROWS`]) are a small share, and fixed, so the
/// depth does not depend on the number of cores.
const ONE_PASS_STRIPE_ROWS: usize = 256;

/// The one pass's stripes of an `h`-row image, about `stripe_rows` own rows each: `core` the rows
/// a stripe decides (a partition of the image, in order), `rows` those it aggregates, its core
/// and the [`STRIP_OVERLAP_ROWS`] above it where its paths start. Every stripe aggregates about
/// the same number of rows (the first, with no rows above it, decides more), so stripes running
/// side by side finish together.
fn one_pass_stripes(h: usize, stripe_rows: usize) -> Vec<Strip> {
    let count = h.div_ceil(stripe_rows.max(1)).max(1);
    let ov = STRIP_OVERLAP_ROWS;
    let each = (h + (count - 1) * ov).div_ceil(count);
    let mut out = Vec::with_capacity(count);
    let mut start = 0;
    while start < h {
        let own = if start == 0 {
            each
        } else {
            each.saturating_sub(ov)
        }
        .max(1);
        let core = start..(start + own).min(h);
        out.push(Strip {
            rows: core.start.saturating_sub(ov)..core.end,
            core: core.clone(),
        });
        start = core.end;
    }
    out
}

/// Own rows of a one-pass band. A band's levels (221 KB per row at 640 pixels and 173 planes)
/// are written by the window and read back by SGM, so they should stay in L2 with SGM's own
/// rows: 4 rows were faster than 16 on hazy Aloe (docs/BENCHMARKS.md), and fault in a quarter
/// of the pages.
const ONE_PASS_BAND_ROWS: usize = 4;

/// Steps 1–4 of the module docs with the 5 one-pass paths ([`sgm::ONE_PASS_DIRECTIONS`]): rows
/// stream from costs to selections, a band at a time, and no volume of the strip or image is
/// kept. The image is split into stripes of about [`ONE_PASS_STRIPE_ROWS`] own rows run in
/// parallel, each stripe's paths starting [`STRIP_OVERLAP_ROWS`] rows above its own rows (the
/// window is clipped at the image's rows, not the stripe's). One quantiser serves the whole
/// image.
fn one_pass_selections(
    src: &LevelSource<'_>,
    guide: &ImageF32,
    params: &SgmParams,
    layout: Layout,
    claims: &[SourceClaims],
    monitor: &Monitor,
) -> Result<Vec<Selection>> {
    let (w, h, n) = (src.width(), src.height(), src.planes());
    let r = src.radius;
    let row_len = w * n;
    let quant = Quantiser::new(
        cost_bound(
            src.reference.image.channels(),
            src.weights,
            params.census_weight,
        ),
        params.p2.max(params.p1),
        params.num_paths,
    );
    let pen = quant.penalties(&params.penalties());
    let isa = crate::cpu::Isa::detect();
    let stripes = one_pass_stripes(h, layout.stripe_rows.unwrap_or(ONE_PASS_STRIPE_ROWS));
    let total = stripes.iter().map(|s| s.rows.len()).sum::<usize>().max(1);
    let done = AtomicUsize::new(0);
    let silent = monitor.silent();
    let mut selections = vec![Selection::NONE; w * h];
    // Each stripe's own rows' selections, split off in order.
    let mut parts = Vec::with_capacity(stripes.len());
    let mut rest = &mut selections[..];
    for stripe in &stripes {
        let (part, tail) = rest.split_at_mut(stripe.core.len() * w);
        parts.push((stripe, part));
        rest = tail;
    }
    parts
        .into_par_iter()
        .try_for_each(|(stripe, selected)| -> Result<()> {
            let Strip { rows, core } = stripe.clone();
            let band_rows = (layout.band_rows)
                .unwrap_or(ONE_PASS_BAND_ROWS)
                .clamp(1, rows.len());
            let mut band = Band::new((band_rows + 2 * r).min(h), w, n);
            let mut levels = crate::large_buffer::zeroed::<u16>(band_rows * row_len);
            // One row of sums: each row's claims and selection follow its aggregation at once,
            // while its sums are in L2.
            let mut srow = vec![0u16; row_len];
            let mut claim_scratch = ClaimScratch::default();
            let mut pass = sgm::OnePass::new(w, n, isa);
            let mut y0 = rows.start;
            while y0 < rows.end {
                silent.checkpoint()?;
                let y1 = (y0 + band_rows).min(rows.end);
                let levels = &mut levels[..(y1 - y0) * row_len];
                band.levels(src, 0..h, y0..y1, &quant, levels, &silent)?;
                for (y, crow) in (y0..y1).zip(levels.chunks_exact(row_len)) {
                    pass.row(crow, &mut srow, y, &pen, Some(sgm::Guide::new(guide)));
                    if core.contains(&y) {
                        let k = y - core.start;
                        claim_and_select_row(
                            &srow,
                            y,
                            n,
                            &quant,
                            params,
                            claims,
                            &mut selected[k * w..(k + 1) * w],
                            &mut claim_scratch,
                        );
                    }
                }
                // The job's progress sink never moves backwards, so stripes may report in any
                // order.
                let done = done.fetch_add(y1 - y0, Ordering::Relaxed) + (y1 - y0);
                monitor.progress("mvs.depth", 0.95 * done as f32 / total as f32);
                y0 = y1;
            }
            Ok(())
        })?;
    Ok(selections)
}

/// A sentence for each source gain and each fall-off that ended at a bound of its search
/// ([`exposure::GAIN_RANGE`], [`vignetting::FALLOFF_RANGE`],
/// [`vignetting::RELATIVE_FALLOFF_RANGE`]): the value was applied, but the camera may differ by
/// more. `gains` are source-major, `channels` per source.
fn bound_warnings(
    gains: &[f32],
    channels: usize,
    falloff: f32,
    source_falloffs: &[f32],
) -> Vec<String> {
    let (lo, hi) = exposure::GAIN_RANGE;
    let mut out: Vec<String> = gains
        .chunks_exact(channels.max(1))
        .enumerate()
        .flat_map(|(s, g)| {
            g.iter()
                .enumerate()
                .filter(|&(_, &g)| exposure::at_bound(g))
                .map(move |(c, &g)| {
                    format!(
                        "source {s} channel {c}: exposure gain {g:.3} is at the end of the searched \
                         range {lo}..{hi}; the camera may differ by more, and the compensation is \
                         then incomplete"
                    )
                })
        })
        .collect();
    let (flo, fhi) = vignetting::FALLOFF_RANGE;
    if falloff != 0.0
        && ((f64::from(falloff) - flo).abs() < 1e-3 || (f64::from(falloff) - fhi).abs() < 1e-3)
    {
        out.push(format!(
            "lens fall-off {falloff:.3} is at the end of the searched range {flo}..{fhi}; the \
             lens may vignette more, and the compensation is then incomplete"
        ));
    }
    let (rlo, rhi) = vignetting::RELATIVE_FALLOFF_RANGE;
    for (s, &d) in source_falloffs.iter().enumerate() {
        if (f64::from(d) - rlo).abs() < 1e-3 || (f64::from(d) - rhi).abs() < 1e-3 {
            out.push(format!(
                "source {s}: its lens fall-off relative to the reference's, {d:.3}, is at the end \
                 of the searched range {rlo}..{rhi}; the lenses may differ by more, and the \
                 compensation is then incomplete"
            ));
        }
    }
    out
}

/// The views with their images replaced by `images` (the reference's, then the sources' in
/// order), or as they are when `None`: intrinsics and poses stay.
fn views_over<'a>(
    reference: &View<'a>,
    sources: &[View<'a>],
    images: &'a Option<(ImageF32, Vec<ImageF32>)>,
) -> (View<'a>, Vec<View<'a>>) {
    match images {
        Some((r, s)) => (
            View {
                image: r,
                ..*reference
            },
            sources
                .iter()
                .zip(s)
                .map(|(v, image)| View { image, ..*v })
                .collect(),
        ),
        None => (*reference, sources.to_vec()),
    }
}

/// Rows added above and below a strip's own rows so that the box window, the contrast measure
/// and SGM's vertical and diagonal paths reach the strip's rows with context: the strip's paths
/// start this many rows early.
pub const STRIP_OVERLAP_ROWS: usize = 24;

/// One horizontal strip of the reference: the rows its volume covers and the rows it decides.
#[derive(Clone, Debug, PartialEq)]
struct Strip {
    /// Rows of the strip's volume (own rows plus the overlap).
    rows: std::ops::Range<usize>,
    /// Rows whose depth this strip decides (a partition of the image over all strips).
    core: std::ops::Range<usize>,
}

/// The strips for a `w×h` reference and `n` planes: one strip (the whole image, no overlap) when
/// the `f32` volume fits `budget_mib` MiB, else strips of equal own height (the last may be
/// shorter) whose volume with the overlap fits it; when the budget holds fewer than 16 own rows
/// plus the overlap, strips of about 16 own rows exceed it.
fn strips_of(w: usize, h: usize, n: usize, budget_mib: usize) -> Vec<Strip> {
    let row_bytes = (w * n * std::mem::size_of::<f32>()).max(1);
    let strip_budget = budget_mib << 20;
    if h * row_bytes <= strip_budget {
        return vec![Strip {
            rows: 0..h,
            core: 0..h,
        }];
    }
    let own = (strip_budget / row_bytes)
        .saturating_sub(2 * STRIP_OVERLAP_ROWS)
        .max(16);
    let count = h.div_ceil(own);
    let own = h.div_ceil(count);
    (0..count)
        .map(|k| {
            let core = k * own..((k + 1) * own).min(h);
            Strip {
                rows: core.start.saturating_sub(STRIP_OVERLAP_ROWS)
                    ..(core.end + STRIP_OVERLAP_ROWS).min(h),
                core,
            }
        })
        .collect()
}

/// Per-pixel contrast weights of the whole reference (row-major), empty when off. The
/// percentile `c₀` is a property of the whole image, so strips share one set of weights.
fn contrast_weights_of(guide: &ImageF32, params: &SgmParams) -> Vec<f32> {
    if params.contrast_max_weight <= 1.0 {
        return Vec::new();
    }
    let c = contrast::local_contrast(
        guide.data(),
        guide.width(),
        guide.height(),
        guide.channels(),
        params.cost_window_radius.max(1),
    );
    contrast::contrast_weights(&c, params.contrast_percentile, params.contrast_max_weight)
}

/// The largest weighted cost a strip's windowed means can reach, known before any cost is
/// computed, so that a strip is quantised band by band as its costs are built: every voxel of
/// the volume is at most `γ` ([`penalty_for`]`(channels)`: the dehazing volume caps its voxels there, the ordinary one reaches it only for images outside `[0, 1]`, which
/// then take the top level, a truncated cost), times the strip's largest contrast weight, plus
/// the census term, which arrives unweighted and is at most `census_weight`. On the hazy Aloe
/// pair every strip's largest weighted cost was exactly this (the out-of-view penalty at the
/// largest weight), so its levels are those of the exact maximum.
fn cost_bound(channels: usize, strip_weights: &[f32], census_weight: f32) -> f32 {
    let w_max = strip_weights.iter().copied().fold(1.0f32, f32::max);
    penalty_for(channels) * w_max + census_weight
}

/// Own rows per band of a strip whose costs are built and windowed together (see
/// [`estimate_depth`]): the band's `f32` costs, with the `r` rows above and below that its
/// windows read, take at most a quarter of the volume budget and at most 32 MiB, so they are
/// still in cache when the window reads them; at least 8 rows, so the rows recomputed for the
/// windows stay a small share.
fn band_rows_of(w: usize, n: usize, r: usize, budget_mib: usize) -> usize {
    let row_bytes = (w * n * std::mem::size_of::<f32>()).max(1);
    let bytes = ((budget_mib << 20) / 4).min(32 << 20);
    (bytes / row_bytes).saturating_sub(2 * r).max(8)
}

/// Steps 3–4 of the module docs on one strip's `u16` levels (pixel-major `[row][x][plane]`,
/// the strip's rows, scaled by `quant`): SGM into `sum` (same length, contents overwritten),
/// then the selections of the strip's own rows, whose aggregated costs also go to the sources'
/// `claims`.
#[allow(clippy::too_many_arguments)]
fn strip_selections(
    levels: &[u16],
    sum: &mut [u16],
    quant: &Quantiser,
    strip: &Strip,
    w: usize,
    planes: &PlaneSet,
    guide: &ImageF32,
    params: &SgmParams,
    claims: &[SourceClaims],
    monitor: &Monitor,
) -> Result<Vec<Selection>> {
    let n = planes.num_planes;
    let rows = strip.rows.len();
    let row_len = w * n;
    monitor.checkpoint()?;
    sgm::aggregate_into(
        levels,
        sum,
        w,
        rows,
        n,
        params.num_paths,
        &quant.penalties(&params.penalties()),
        Some(sgm::Guide::rows(guide, strip.rows.clone())),
        &monitor.sub(0.1, 0.9),
    )?;
    monitor.checkpoint()?;
    let own = (strip.core.start - strip.rows.start) * row_len
        ..(strip.core.end - strip.rows.start) * row_len;
    let mut selections = vec![select::Selection::NONE; strip.core.len() * w];
    claim_and_select(
        &sum[own],
        strip.core.start,
        w,
        n,
        quant,
        params,
        claims,
        &mut selections,
    );
    Ok(selections)
}

/// The claims and the selections of consecutive `w`-pixel rows from `first_row` on, whose
/// aggregated costs are `sums` (`[row][x][plane]`, `n` planes, levels of `quant`), into `selected` (`w`
/// per row): each row's claims and selection in one pass while it is in cache (the sums are
/// read once instead of once per source and again for the selection), rows in parallel.
#[allow(clippy::too_many_arguments)]
fn claim_and_select(
    sums: &[u16],
    first_row: usize,
    w: usize,
    n: usize,
    quant: &Quantiser,
    params: &SgmParams,
    claims: &[SourceClaims],
    selected: &mut [Selection],
) {
    if w * n == 0 {
        return;
    }
    sums.par_chunks(w * n)
        .zip(selected.par_chunks_mut(w))
        .enumerate()
        .for_each_init(ClaimScratch::default, |scratch, (k, (row, sel))| {
            claim_and_select_row(row, first_row + k, n, quant, params, claims, sel, scratch);
        });
}

/// [`claim_and_select`] of the one row `y` whose sums are `row`.
#[allow(clippy::too_many_arguments)]
fn claim_and_select_row(
    row: &[u16],
    y: usize,
    n: usize,
    quant: &Quantiser,
    params: &SgmParams,
    claims: &[SourceClaims],
    selected: &mut [Selection],
    scratch: &mut ClaimScratch,
) {
    let eps = quant.scaled(select::CONFIDENCE_EPS_PER_PATH * params.num_paths as f32);
    for c in claims {
        c.add_row(y, row, n, quant.unit(), scratch);
    }
    select::select_into(row, n, eps, selected);
}

/// Step 5 and the rejections: the consistency verdicts from the sources' `claims` (none when
/// empty), speckles, confidence 0 and the fill for rejected pixels, the optional post-filter.
#[allow(clippy::too_many_arguments)]
fn finish_depth(
    selections: Vec<Selection>,
    w: usize,
    h: usize,
    planes: &PlaneSet,
    guide: &ImageF32,
    params: &SgmParams,
    claims: Vec<SourceClaims>,
    monitor: &Monitor,
) -> Result<DepthResult> {
    let n = planes.num_planes;
    let mut verdict = vec![Verdict::Consistent; w * h];
    if !claims.is_empty() {
        monitor.checkpoint()?;
        let winner: Vec<u32> = selections
            .iter()
            .map(|s| (s.index.round().max(0.0) as u32).min(n as u32 - 1))
            .collect();
        let sources: Vec<SourceWinners> = claims.into_iter().map(SourceClaims::winners).collect();
        verdict = consistency::check(&winner, w, &sources, params.consistency_tolerance_planes);
    }
    let index: Vec<f32> = selections.iter().map(|s| s.index).collect();
    consistency::reject_speckles(
        &index,
        &mut verdict,
        w,
        h,
        params.speckle_max_size_px.unwrap_or(w * h / 3000),
        params.speckle_range_planes,
    );
    let mut inv: Vec<f32> = index
        .iter()
        .map(|&i| planes.inverse_depth(f64::from(i)) as f32)
        .collect();
    let conf: Vec<f32> = selections
        .iter()
        .zip(&verdict)
        .map(|(s, v)| {
            if *v == Verdict::Consistent {
                s.confidence
            } else {
                0.0
            }
        })
        .collect();
    consistency::fill_rejected(&mut inv, &verdict, w, h);
    if let PostFilter::WeightedMedian { radius, sigma } = params.post_filter {
        monitor.checkpoint()?;
        inv = filter::weighted_median(
            &inv,
            &conf,
            guide.data(),
            guide.channels(),
            w,
            h,
            radius,
            sigma,
        );
    }
    let z: Vec<f32> = inv.iter().map(|&v| 1.0 / v).collect();
    monitor.progress("mvs.depth", 1.0);
    Ok(DepthResult {
        z_depth: ImageF32::from_vec(w, h, 1, z)?,
        inverse_depth: ImageF32::from_vec(w, h, 1, inv)?,
        confidence: ImageF32::from_vec(w, h, 1, conf)?,
        source_gains: Vec::new(),
        vignetting_falloff: 0.0,
        source_falloffs: Vec::new(),
        warnings: Vec::new(),
    })
}

/// Depth, inverse depth and confidence from a cost volume (steps 2–5 of the module docs).
/// `guide` is the reference image (same size as the volume), used by the adaptive `P2` and the
/// post-filter. The volume is consumed so its memory can be released after the transpose.
/// Without the views there is no consistency check (speckles are still rejected).
pub fn depth_from_cost_volume(
    volume: CostVolume,
    guide: &ImageF32,
    params: &SgmParams,
    monitor: &Monitor,
) -> Result<DepthResult> {
    let (w, h) = (volume.width(), volume.height());
    let planes = *volume.planes();
    depth_from_costs(volume.into_vec(), w, h, &planes, guide, params, monitor)
}

/// [`depth_from_cost_volume`] on raw costs: `data` is a `[plane][y][x]` `f32` volume of
/// `planes.num_planes` planes of `w×h` pixels (cost units as in [`SgmParams`]). Fails naming
/// `costs` for a wrong length or a negative or non-finite cost (SGM aggregates unsigned integer
/// levels of the costs, [`quantise`]), `guide` for a guide of another size.
pub fn depth_from_costs(
    data: Vec<f32>,
    w: usize,
    h: usize,
    planes: &PlaneSet,
    guide: &ImageF32,
    params: &SgmParams,
    monitor: &Monitor,
) -> Result<DepthResult> {
    params.validate().map_err(|e| e.within("sgm"))?;
    planes.validate().map_err(|e| e.within("planes"))?;
    let n = planes.num_planes;
    if w == 0 || h == 0 || data.len() != w * h * n {
        return Err(MurkError::invalid(
            "costs",
            format!(
                "expected {w}x{h}x{n} = {} costs, got {}",
                w * h * n,
                data.len()
            ),
        ));
    }
    if let Some(c) = data.iter().find(|c| !(c.is_finite() && **c >= 0.0)) {
        return Err(MurkError::invalid(
            "costs",
            format!("costs must be finite and >= 0 (cost units), got {c}"),
        ));
    }
    if guide.dims() != (w, h) {
        return Err(MurkError::invalid(
            "guide",
            format!(
                "guide image is {}x{} but the cost volume is {w}x{h}",
                guide.width(),
                guide.height()
            ),
        ));
    }
    guide.ensure_finite().map_err(|e| e.within("guide"))?;
    let weights = contrast_weights_of(guide, params);
    let whole = Strip {
        rows: 0..h,
        core: 0..h,
    };
    // Given costs have no known bound: the exact largest weighted cost sets the levels.
    let quant = Quantiser::new(
        window::largest_weighted(&data, &weights, w, h, n),
        params.p2.max(params.p1),
        params.num_paths,
    );
    let mut levels = crate::large_buffer::zeroed::<u16>(data.len());
    let mut data = data;
    window::window_to_levels(
        &mut data,
        &weights,
        w,
        h,
        n,
        params.cost_window_radius,
        &quant,
        &mut levels,
        monitor,
    )?;
    // The plane-major volume is spent once windowed: its memory holds `S`.
    let len = data.len();
    let sum = &mut bytemuck::cast_slice_mut::<f32, u16>(&mut data[..])[..len];
    let selections = strip_selections(
        &levels,
        sum,
        &quant,
        &whole,
        w,
        planes,
        guide,
        params,
        &[],
        monitor,
    )?;
    finish_depth(selections, w, h, planes, guide, params, Vec::new(), monitor)
}

#[cfg(test)]
mod tests;
