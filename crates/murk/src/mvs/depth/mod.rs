//! Depth from a plane-sweep cost volume without training: the classical
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
//! With a prior ([`estimate_depth_from_prior`]), groups of rows may search only a run of the
//! planes each ([`windows`]), with the 5 paths of the one pass.
//!
//! Memory, 5 paths (the default): every path reaches a row from rows above it, so rows stream
//! from costs to selections a band at a time ([`one_pass_selections`](bands::one_pass_selections)): a band's `f32` costs,
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
pub mod photometric;
pub mod presmooth;
pub mod quantise;
pub mod select;
pub mod sgm;
pub mod vignetting;
pub mod window;
pub mod windows;

mod bands;
mod depth_params;
mod image_radius;
mod shift_claims;

use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::cost_volume::{CostKind, CostVolume, View};
use crate::mvs::plane_sweep::PlaneSet;

use bands::{contrast_weights_of, estimate_depth_in_bands, strip_selections, Layout, Strip};
use consistency::{SourceClaims, SourceWinners, Verdict};
use quantise::Quantiser;

pub use bands::STRIP_OVERLAP_ROWS;
pub use depth_params::{
    DepthParams, MatchingParams, PhotometricParams, PostFilter, RejectionParams, SgmParams,
    MAX_SPECKLE_SIZE_PX, MAX_VOLUME_BUDGET_MIB,
};
pub use photometric::{PhotometricPrior, PhotometricSearch};
pub use select::{select_curve, Selection};
pub use sgm::Penalties;
pub use windows::PlaneWindows;

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
    /// The gains as estimated, before [`exposure::DEAD_BAND`] (the layout of
    /// [`DepthResult::source_gains`]); what the next pair of a stream starts from
    /// ([`DepthResult::photometric_prior`]).
    pub estimated_gains: Vec<f32>,
    /// Whether the photometric corrections were searched or carried from a prior
    /// ([`photometric`]).
    pub photometric_search: PhotometricSearch,
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

impl DepthResult {
    /// This result's photometric corrections, for the next pair of the same rig
    /// ([`estimate_depth_from_prior`]).
    pub fn photometric_prior(&self) -> PhotometricPrior {
        PhotometricPrior {
            estimated_gains: self.estimated_gains.clone(),
            vignetting_falloff: self.vignetting_falloff,
            source_falloffs: self.source_falloffs.clone(),
        }
    }
}

/// Cost volume (Eq. 3.1 or 3.7) plus [`depth_from_cost_volume`]. Errors are those of
/// [`build_cost_volume`](crate::mvs::cost_volume::build_cost_volume) plus `sgm.…` for bad parameters; cancellation returns `Cancelled`.
pub fn estimate_depth(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &DepthParams,
    monitor: &Monitor,
) -> Result<DepthResult> {
    estimate_depth_from_prior(
        reference,
        sources,
        planes,
        kind,
        params,
        &DepthPrior::default(),
        monitor,
    )
}

/// What a previous result of the same cameras tells [`estimate_depth_from_prior`]; the default
/// (nothing) estimates as [`estimate_depth`] does.
#[derive(Clone, Copy, Debug, Default)]
pub struct DepthPrior<'a> {
    /// The photometric corrections start from these (a previous result's
    /// [`DepthResult::photometric_prior`]): its fall-offs are kept and its gains confirmed on
    /// these views, or everything is searched again where a gain moved ([`photometric`]). A
    /// prior of other sources or channels is searched again.
    pub photometric: Option<&'a PhotometricPrior>,
    /// Each group of rows searches only its window of the planes ([`windows`]). Used with the
    /// default 5 paths ([`SgmParams::num_paths`]); with 8 or 4 paths every row searches every
    /// plane.
    pub windows: Option<&'a windows::PlaneWindows>,
}

/// [`estimate_depth`] for the next views of the same cameras, with what a previous result says
/// ([`DepthPrior`]). Errors as [`estimate_depth`], and `windows` for windows outside `planes`.
pub fn estimate_depth_from_prior(
    reference: &View<'_>,
    sources: &[View<'_>],
    planes: &PlaneSet,
    kind: CostKind,
    params: &DepthParams,
    prior: &DepthPrior<'_>,
    monitor: &Monitor,
) -> Result<DepthResult> {
    estimate_depth_in_bands(
        reference,
        sources,
        planes,
        kind,
        params,
        prior,
        Layout::default(),
        monitor,
    )
}

/// Step 5 and the rejections: the consistency verdicts from the sources' `claims` (none when
/// empty), speckles, confidence 0 and the fill for rejected pixels, the optional post-filter.
#[allow(clippy::too_many_arguments)]
pub(super) fn finish_depth(
    selections: Vec<Selection>,
    w: usize,
    h: usize,
    planes: &PlaneSet,
    guide: &ImageF32,
    params: &DepthParams,
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
        verdict = consistency::check(
            &winner,
            w,
            &sources,
            params.rejection.consistency_tolerance_planes,
        );
    }
    let index: Vec<f32> = selections.iter().map(|s| s.index).collect();
    consistency::reject_speckles(
        &index,
        &mut verdict,
        w,
        h,
        params.rejection.speckle_max_size_px.unwrap_or(w * h / 3000),
        params.rejection.speckle_range_planes,
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
        estimated_gains: Vec::new(),
        photometric_search: PhotometricSearch::Searched,
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
    params: &DepthParams,
    monitor: &Monitor,
) -> Result<DepthResult> {
    let (w, h) = (volume.width(), volume.height());
    let planes = *volume.planes();
    depth_from_costs(volume.into_vec(), w, h, &planes, guide, params, monitor)
}

/// [`depth_from_cost_volume`] on raw costs: `data` is a `[plane][y][x]` `f32` volume of
/// `planes.num_planes` planes of `w×h` pixels (cost units as in [`DepthParams`]). Fails naming
/// `costs` for a wrong length or a negative or non-finite cost (SGM aggregates unsigned integer
/// levels of the costs, [`quantise`]), `guide` for a guide of another size.
pub fn depth_from_costs(
    data: Vec<f32>,
    w: usize,
    h: usize,
    planes: &PlaneSet,
    guide: &ImageF32,
    params: &DepthParams,
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
        params.sgm.p2.max(params.sgm.p1),
        params.sgm.num_paths,
    );
    let mut levels = crate::large_buffer::zeroed::<u16>(data.len());
    let mut data = data;
    window::window_to_levels(
        &mut data,
        &weights,
        w,
        h,
        n,
        params.matching.cost_window_radius,
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
