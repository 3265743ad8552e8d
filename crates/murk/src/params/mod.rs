//! Scattering-parameter estimation (reference Ch. 3.3): the airlight `A` of a hazy image
//! ([`airlight`]) and the scattering coefficient `β` of Eq. 3.3, for a reference view with
//! sources and a sparse SfM point cloud. [`search::search_scattering`] fits both to the SfM
//! points' intensities ([`joint_fit`]) and falls back to the points' transmission ratios
//! ([`point_ratio`]) and to Algorithm 1's search over the depth residual ([`residual`]) where
//! the points do not determine β. Method, accuracy and limits: `docs/scattering-params.md`.

pub mod airlight;
pub mod footprint;
pub mod joint_fit;
pub mod point_ratio;
pub mod pose_error;
pub mod relief;
pub mod residual;
pub mod sampling_share;
pub mod search;
pub mod sparse;
mod tracks;
