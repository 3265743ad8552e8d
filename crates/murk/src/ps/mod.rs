//! Photometric stereo in turbid media (reference Ch. 4): remove backscatter, remove the
//! shape-dependent surface-camera forward scatter with a sparse kernel plus a constant term,
//! recover normals by near-light photometric stereo with Sun et al.'s `G` table, integrate them
//! under perspective, and iterate.
//!
//! Entry point: [`photometric_stereo`]. One idea per module: the single-scattering tables and
//! the forward-scatter kernel ([`physics`]), backscatter subtraction ([`backscatter`]), the
//! capture and its validation ([`capture`]), block BiCGStab for Eq. 4.52 ([`bicgstab`]),
//! near-light photometric stereo ([`near_light`]), perspective normal integration
//! ([`integrate`]), the iteration of §4.3.4 ([`pipeline`]) and the choice of the kernel
//! support from the object's size ([`support`]).
//!
//! Conventions: camera frame as in [`crate::camera`] (+x right, +y down, +z forward), lengths
//! in millimetres, β and σ per millimetre, unit normals pointing towards the camera (n_z < 0).

pub mod backscatter;
pub mod bicgstab;
pub mod capture;
pub mod distance;
pub mod integrate;
pub mod mesh;
pub mod near_light;
pub mod physics;
pub mod pipeline;
pub mod support;

#[cfg(test)]
mod tests;

pub use capture::{PointLight, PsCapture};
pub use near_light::ShadingModel;
pub use pipeline::{
    photometric_stereo, validate_request, DistanceMode, PsIterationStats, PsMode, PsParams,
    PsResult,
};
pub use support::{choose_support, SupportChoice};
