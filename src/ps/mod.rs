//! Photometric stereo in turbid media (reference Ch. 4): remove backscatter, remove the
//! shape-dependent surface-camera forward scatter with a sparse kernel plus a constant term,
//! recover normals by near-light photometric stereo with Sun et al.'s `G` table, integrate them
//! under perspective, and iterate.
//!
//! Conventions: camera frame as in [`crate::camera`] (+x right, +y down, +z forward), lengths
//! in millimetres, β and σ per millimetre, unit normals pointing towards the camera (n_z < 0).

pub mod bicgstab;
pub mod integrate;
pub mod physics;
