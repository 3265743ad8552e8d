//! The options of depth from a cost volume ([`super::estimate_depth`]): SGM's penalties and paths,
//! and the passes around it (pre-smoothing, contrast normalisation, the consistency check, the
//! speckle filter, exposure and vignetting compensation, the census term, the memory budget).

use crate::error::{MurkError, Result};

use super::presmooth;
use super::sgm::Penalties;

/// Optional edge-aware post-filter of the inverse-depth map.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum PostFilter {
    /// No post-filter.
    #[default]
    None,
    /// Guided, confidence-weighted median of inverse depth ([`filter::weighted_median`](super::filter::weighted_median)).
    WeightedMedian {
        /// Window radius, pixels (`1 ..= 16`).
        radius: usize,
        /// Colour scale σ of the guide weights, pixel-value units per channel (`> 0`).
        sigma: f32,
    },
}

/// Largest accepted [`SgmParams::volume_budget_mib`].
pub const MAX_VOLUME_BUDGET_MIB: usize = 1 << 16;

/// Largest accepted [`RejectionParams::speckle_max_size_px`].
pub const MAX_SPECKLE_SIZE_PX: usize = 1 << 20;

/// Parameters of the training-free depth estimator, by concern: SGM itself, how the cost curves
/// are made, the photometric compensation of the views, the rejection of unreliable pixels, and
/// the post-filter.
///
/// Cost units: the L1 cost is summed over channels, so for RGB values in `[0, 1]` a voxel lies
/// in `[0, 3]` (and `γ = 3`, Eq. 3.7). The defaults are in those units: `P1 = 0.01` (a ±1
/// plane step costs about the residual of one noise standard deviation of a typical camera,
/// ~0.003 per channel, summed over RGB), `P2 = 0.1` (a larger jump costs about a thirtieth of
/// the cost range, so it needs a few pixels of consistent evidence along a path), adapted to
/// the image gradient with `τ = 0.05`, on a 5×5 cost window. Haze scales the photometric
/// contrast by `t` (0.1–0.4 in the reference's setting), so penalties sized for clear images
/// (`P1 = 0.05`, `P2 = 0.5`) drown far surfaces in smoothness: on the simulated hazy scenes
/// (seeds 0–4) the smaller penalties raise mean C.P. by 9 points with the ordinary volume and 14
/// with the dehazing one, at a cost of 0.6 points on the clear images (`examples/mvs_survey.rs
/// --p1 0.01,0.05 --p2 0.1,0.5`, with `--clear`). For one-channel images divide the penalties
/// by 3.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DepthParams {
    /// Semi-global aggregation: penalties, paths and the memory they may use.
    pub sgm: SgmParams,
    /// How each pixel's cost curve is made before aggregation.
    pub matching: MatchingParams,
    /// The views' photometric differences estimated and divided out before the sweep.
    pub photometric: PhotometricParams,
    /// The rejection of pixels whose depth the evidence does not support.
    pub rejection: RejectionParams,
    /// Optional post-filter (off by default).
    pub post_filter: PostFilter,
}

/// Semi-global aggregation ([`sgm`](super::sgm)): the penalties on plane-index jumps, the paths,
/// and the memory bound of the paths that need stored volumes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SgmParams {
    /// `P1`, cost units, finite and `≥ 0`.
    pub p1: f32,
    /// `P2`, cost units, finite and `≥ p1`.
    pub p2: f32,
    /// `τ` of the adaptive `P2` (see [`Penalties::p2_gradient_scale`]), pixel-value units;
    /// `0` = constant `P2`. Finite and `≥ 0`.
    pub p2_gradient_scale: f32,
    /// Number of path directions: 5 ([`sgm::ONE_PASS_DIRECTIONS`](super::sgm::ONE_PASS_DIRECTIONS): both horizontal ones and the
    /// three going down, one pass that keeps no volume), 8 (all, two passes over stored volumes
    /// bounded by [`SgmParams::volume_budget_mib`]) or 4 (horizontal + vertical, two passes).
    ///
    /// 5 is the default: on the hazy Aloe pair it is 0.05 points of C.P. below 8 paths (95.27
    /// against 95.32 %) at about three quarters of the time and 60 % of the peak memory, and on
    /// the simulator's hazy scenes its mean C.P. is as high (docs/accuracy.md).
    pub num_paths: usize,
    /// Memory bound with 8 or 4 paths, MiB (`1 ..= 65536`; the default 5 paths keep no volume and
    /// ignore it): when the `f32` cost volume of the whole reference is larger, depth is estimated
    /// in horizontal strips whose volume (own rows plus [`STRIP_OVERLAP_ROWS`](super::STRIP_OVERLAP_ROWS) above and below)
    /// fits it. A strip holds two `u16` volumes (the windowed levels and the aggregated costs,
    /// [`quantise`](super::quantise); together the size of the `f32` volume) and one band of `f32` costs, at most a
    /// quarter of this (the strip's costs are built and windowed band by band), so the peak is
    /// about 1.25 times this plus the images. Strips change SGM's vertical and diagonal paths only
    /// beyond the overlap: on the hazy Aloe pair (640×480, 173 planes) 0.06 % of the pixels moved,
    /// by at most 0.2 % of the inverse-depth range, at 48 MiB; on a simulated 160×120 scene cut
    /// into 15-row strips 98 % stayed within one plane step, with the same C.P. Default 96: three
    /// strips on that pair (the overlap adds 20 % to the rows processed, against 40 % in five
    /// strips at 64), a peak of about 205 MiB for the whole `murk mvs` process.
    pub volume_budget_mib: usize,
}

/// How each pixel's cost curve is made before aggregation: the views' pre-smoothing, the census
/// term, the contrast normalisation and the box window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MatchingParams {
    /// σ of the Gaussian applied to every view before the cost volume ([`presmooth`]), pixels,
    /// `0 ..= 4` (`0` = none). Used by [`estimate_depth`](super::estimate_depth), not by [`depth_from_cost_volume`](super::depth_from_cost_volume),
    /// which receives a finished volume.
    pub presmooth_sigma_px: f32,
    /// Weight `λ` of the census term added to every voxel
    /// ([`crate::mvs::cost_volume::census`]), cost units for a Hamming distance of all the
    /// code's bits (finite, `0 ..= 3`; `0` = off). Used by [`estimate_depth`](super::estimate_depth).
    pub census_weight: f32,
    /// Percentile (0–100) of the reference's local contrast that sets `c₀` of the contrast
    /// normalisation ([`contrast`](super::contrast)).
    pub contrast_percentile: f32,
    /// Largest contrast weight `w_max` (`1 ..= 64`; `1` = no contrast normalisation).
    pub contrast_max_weight: f32,
    /// Radius of the per-plane box mean applied before aggregation, pixels (`0` = none,
    /// at most 16).
    pub cost_window_radius: usize,
}

/// The views' photometric differences estimated from the matching cost and divided out before
/// the sweep. Both need the views: [`estimate_depth`](super::estimate_depth) applies them,
/// [`depth_from_cost_volume`](super::depth_from_cost_volume) cannot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhotometricParams {
    /// Estimate each source's exposure gain per channel relative to the reference and divide the
    /// source by it before the cost volume ([`exposure`](super::exposure)); the gains are reported in
    /// [`DepthResult::source_gains`](super::DepthResult::source_gains). Used by [`estimate_depth`](super::estimate_depth) (which has the views). Default
    /// on.
    pub exposure_compensation: bool,
    /// Estimate the lens's radial fall-off, one for every view, and divide it out of every view
    /// before the cost volume ([`vignetting`](super::vignetting)); the fall-off is reported in
    /// [`DepthResult::vignetting_falloff`](super::DepthResult::vignetting_falloff). Used by [`estimate_depth`](super::estimate_depth). Default on.
    pub vignetting_compensation: bool,
}

/// The rejection of pixels whose depth the evidence does not support: the source–reference
/// consistency check and the speckle filter. A rejected pixel gets confidence 0 and a filled
/// depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RejectionParams {
    /// Source–reference consistency check ([`consistency`](super::consistency)): pixels whose winning plane
    /// disagrees with every source's own winner get confidence 0 and a filled depth. Needs the
    /// views, so [`estimate_depth`](super::estimate_depth) runs it and [`depth_from_cost_volume`](super::depth_from_cost_volume) does not.
    pub consistency_check: bool,
    /// Largest disagreement, in planes, that still counts as consistent (finite, `>= 0`; about
    /// pixels of displacement with the automatic plane count; SGBM's `disp12MaxDiff`).
    pub consistency_tolerance_planes: f32,
    /// Speckles smaller than this many pixels are rejected ([`consistency::reject_speckles`](super::consistency::reject_speckles));
    /// `None` = automatic, `W·H / 3000` (100 pixels at 640×480, SGBM's usual window); `Some(0)`
    /// = off.
    pub speckle_max_size_px: Option<usize>,
    /// Largest plane-index step inside one speckle region (finite, `>= 0`).
    pub speckle_range_planes: f32,
}

impl Default for SgmParams {
    fn default() -> Self {
        Self {
            p1: 0.01,
            p2: 0.1,
            p2_gradient_scale: 0.05,
            num_paths: 5,
            volume_budget_mib: 96,
        }
    }
}

impl Default for MatchingParams {
    fn default() -> Self {
        Self {
            presmooth_sigma_px: 0.8,
            census_weight: 0.0,
            contrast_percentile: 95.0,
            contrast_max_weight: 4.0,
            cost_window_radius: 2,
        }
    }
}

impl Default for PhotometricParams {
    fn default() -> Self {
        Self {
            exposure_compensation: true,
            vignetting_compensation: true,
        }
    }
}

impl Default for RejectionParams {
    fn default() -> Self {
        Self {
            consistency_check: true,
            consistency_tolerance_planes: 1.0,
            speckle_max_size_px: None,
            speckle_range_planes: 2.0,
        }
    }
}

impl DepthParams {
    /// Fails naming the offending field. The names are those of the API's flat `SgmOptions`
    /// (`p1`, `p2`, `p2_gradient_scale`, `num_paths`, `volume_budget_mib`, `cost_window_radius`,
    /// `presmooth_sigma_px`, `census_weight`, `contrast_percentile`, `contrast_max_weight`,
    /// `consistency_tolerance_planes`, `speckle_max_size_px`, `speckle_range_planes`,
    /// `post_filter.radius`, `post_filter.sigma`), so a service can report them as they are.
    pub fn validate(&self) -> Result<()> {
        self.sgm.validate()?;
        self.matching.validate()?;
        self.rejection.validate()?;
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
}

impl SgmParams {
    /// Fails naming `p1`, `p2`, `p2_gradient_scale`, `num_paths` or `volume_budget_mib`.
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
        if !(1..=MAX_VOLUME_BUDGET_MIB).contains(&self.volume_budget_mib) {
            return Err(MurkError::invalid(
                "volume_budget_mib",
                format!(
                    "must be in 1..={MAX_VOLUME_BUDGET_MIB} MiB, got {}",
                    self.volume_budget_mib
                ),
            ));
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

impl MatchingParams {
    /// Fails naming `cost_window_radius`, `presmooth_sigma_px`, `census_weight`,
    /// `contrast_percentile` or `contrast_max_weight`.
    pub fn validate(&self) -> Result<()> {
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
        if !self.census_weight.is_finite() || !(0.0..=3.0).contains(&self.census_weight) {
            return Err(MurkError::invalid(
                "census_weight",
                format!("must be in 0..=3 (cost units), got {}", self.census_weight),
            ));
        }
        Ok(())
    }
}

impl RejectionParams {
    /// Fails naming `consistency_tolerance_planes`, `speckle_range_planes` or
    /// `speckle_max_size_px`.
    pub fn validate(&self) -> Result<()> {
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
        Ok(())
    }
}
