//! Depth from a plane-sweep cost volume without training (issue 3, item 4): the classical
//! regulariser murk uses where the reference (Ch. 3.2.3) feeds its cost volume to a CNN.
//!
//! Pipeline ([`estimate_depth`] / [`depth_from_cost_volume`]):
//!
//! 0. optional Gaussian pre-smoothing of every view ([`presmooth`], σ = 0.8 px by default);
//! 1. the ordinary (Eq. 3.1) or dehazing (Eq. 3.7) cost volume, `C(p, i)` in `[0, γ]`, `γ = 3`
//!    for RGB ([`crate::mvs::cost_volume`]);
//! 2. contrast normalisation: each pixel's curve weighted by `clamp(c₀/c_p, 1, w_max)` from the
//!    reference's local contrast ([`contrast`]), then the box mean of each plane ([`window`]);
//! 3. semi-global aggregation over 8 (or 4) paths with penalties `P1`, `P2` on plane-index
//!    jumps, `P2` optionally adapted to the reference image gradient ([`sgm`]);
//! 4. winner-take-all, parabola sub-plane refinement in inverse depth and a confidence from the
//!    aggregated curve ([`select`]);
//! 5. optional guided, confidence-weighted median of inverse depth ([`filter`]).
//!
//! Memory: the volume is transposed once to pixel-major order (`W·H·N` `f32`) and one
//! aggregated volume of the same size holds the sum over all paths: at 256×192×256 that is
//! 2 × 50 MB (plus the cost volume itself while it is transposed).

pub mod contrast;
pub mod filter;
pub mod presmooth;
pub mod select;
pub mod sgm;
pub mod window;

use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::cost_volume::{build_cost_volume, CostKind, CostVolume, View};
use crate::mvs::plane_sweep::PlaneSet;

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
    /// Number of path directions: 4 (horizontal + vertical) or 8 (plus diagonals).
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
}

impl Default for SgmParams {
    fn default() -> Self {
        Self {
            p1: 0.01,
            p2: 0.1,
            p2_gradient_scale: 0.05,
            num_paths: 8,
            cost_window_radius: 2,
            post_filter: PostFilter::None,
            presmooth_sigma_px: 0.8,
            contrast_percentile: 95.0,
            contrast_max_weight: 4.0,
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
        if self.num_paths != 4 && self.num_paths != 8 {
            return Err(MurkError::invalid(
                "num_paths",
                format!("must be 4 or 8, got {}", self.num_paths),
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
    let (reference, sources): (View<'_>, Vec<View<'_>>) = match &smoothed {
        Some((r, s)) => (
            View {
                image: r,
                ..*reference
            },
            sources
                .iter()
                .zip(s)
                .map(|(v, img)| View { image: img, ..*v })
                .collect(),
        ),
        None => (*reference, sources.to_vec()),
    };
    let volume = build_cost_volume(&reference, &sources, planes, kind, &monitor.sub(0.0, 0.5))?;
    depth_from_cost_volume(volume, reference.image, params, &monitor.sub(0.5, 1.0))
}

/// Depth, inverse depth and confidence from a cost volume (steps 2–5 of the module docs).
/// `guide` is the reference image (same size as the volume), used by the adaptive `P2` and the
/// post-filter. The volume is consumed so its memory can be released after the transpose.
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
/// `costs` for a wrong length or non-finite cost, `guide` for a guide of another size.
pub fn depth_from_costs(
    mut data: Vec<f32>,
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
    if data.iter().any(|c| !c.is_finite()) {
        return Err(MurkError::invalid("costs", "costs must be finite"));
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
    if params.contrast_max_weight > 1.0 {
        let c = contrast::local_contrast(
            guide.data(),
            w,
            h,
            guide.channels(),
            params.cost_window_radius.max(1),
        );
        let weights =
            contrast::contrast_weights(&c, params.contrast_percentile, params.contrast_max_weight);
        contrast::apply_weights(&mut data, &weights);
    }
    window::box_filter_planes(&mut data, w, h, params.cost_window_radius, monitor)?;
    monitor.checkpoint()?;
    let costs = sgm::to_pixel_major(&data, w * h, n);
    drop(data);
    let sum = sgm::aggregate(
        &costs,
        w,
        h,
        n,
        params.num_paths,
        &params.penalties(),
        Some(guide),
        &monitor.sub(0.1, 0.9),
    )?;
    drop(costs);
    monitor.checkpoint()?;
    let (mut inv, conf) = select::select_all(
        &sum,
        n,
        planes,
        select::CONFIDENCE_EPS_PER_PATH * params.num_paths as f32,
    );
    drop(sum);
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
    })
}

#[cfg(test)]
mod tests;
