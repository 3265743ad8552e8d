//! Multi-view stereo through haze with the dehazing cost volume (reference Ch. 3.2).
//!
//! Building blocks, one idea per module: world-to-camera poses and the reference→source
//! transform ([`pose`]), the plane sweep — planes uniform in inverse depth, the per-plane
//! homography π_{r→s} (Eq. 3.2) and the source-camera depth ζ (Eq. 3.6) — ([`plane_sweep`]), and
//! COLMAP sparse-model I/O ([`colmap`]), and the ordinary and dehazing cost volumes
//! (Eq. 3.1, 3.7; [`cost_volume`]), and training-free depth from a cost volume — semi-global
//! aggregation, winner-take-all, sub-plane refinement, confidence ([`depth`]). The scattering model itself lives in
//! [`crate::atmosphere`].
//!
//! Units: depths, translations and plane positions are in scene units (COLMAP's arbitrary SfM
//! scale for real data), so `β` is per scene unit.

pub mod colmap;
pub mod cost_volume;
pub mod depth;
pub mod plane_count;
pub mod plane_sweep;
pub mod pose;
pub mod rectified;
pub mod stereo_tracker;

#[cfg(test)]
mod tests;

pub use cost_volume::{
    build_cost_volume, estimate_noise_sigma, CostKind, CostVolume, DehazingOptions,
    DehazingResidual, RangePenalty, View,
};
pub use depth::{
    depth_from_cost_volume, depth_from_costs, estimate_depth, estimate_depth_from_prior,
    DepthParams, DepthPrior, DepthResult, MatchingParams, PhotometricParams, PhotometricPrior,
    PhotometricSearch, PlaneWindows, PostFilter, RejectionParams, SgmParams,
};
pub use plane_count::{planes_for_displacement, Camera, AUTO_PLANES_MAX, AUTO_PLANES_MIN};
pub use plane_sweep::{PlaneSet, PlaneWarp, MAX_PLANES};
pub use pose::Pose;
pub use rectified::{
    estimate_rectified, estimate_rectified_from_prior, RectifiedDepth, RectifiedOptions,
    RectifiedRig, StereoRange, DEFAULT_MAX_DISPARITY_PX,
};
pub use stereo_tracker::{Search, StereoTracker, TrackedDepth};
