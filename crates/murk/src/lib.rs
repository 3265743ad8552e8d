//! murk: 3D shape and depth through fog, smoke and turbid water.
//!
//! The physics-based methods of Yuki Fujimura's dissertation *3D Reconstruction in Scattering
//! Media* (the reference; equation numbers in the docs are its), as a library with no server
//! dependencies, for programs that run them on board:
//!
//! | method | module | entry point | reference |
//! | --- | --- | --- | --- |
//! | ToF depth in fog | [`tof`] | [`tof::estimate_tof_depth`] | Ch. 5, Algorithm 2 |
//! | MVS / stereo in haze | [`mvs`] | [`mvs::estimate_depth`] | Ch. 3.2, Eq. 3.1–3.7 |
//! | scattering parameters A and β | [`params`] | [`params::search::search_scattering`] | Ch. 3.3, Algorithm 1 |
//! | photometric stereo in turbid water | [`ps`] | [`ps::photometric_stereo`] | Ch. 4 |
//!
//! Around them: the image-formation model ([`atmosphere`], Eq. 3.3), cameras ([`camera`]),
//! images ([`image`]) and their files (EXR, 16-bit PNG, float TIFF: [`io`]), the reference's
//! accuracy metrics ([`metrics`]), a physically based simulator per method ([`simulate`]), and
//! progress and cooperative cancellation ([`Monitor`]). Every function reports bad input as
//! [`MurkError::InvalidArgument`] naming the field.
//!
//! The gRPC service, job queue and CLI live in the `murk-server` crate. The examples
//! `tof_embedded` and `stereo_embedded` show the library used on its own.
//!
//! Features: `airlight-cnn` (default) adds the learned airlight estimator of the reference's
//! Table 3.1 on burn's CPU backend; without it the dark-channel estimator is the only one.
//!
//! Threads: murk parallelises over pixels and rows on rayon's global pool, and runs faer's
//! factorisations sequentially by argument (it never changes faer's process-wide setting).

// The docs are written for users and for developers (`cargo doc --document-private-items`):
// a public item may point at the private helper that does the work.
#![allow(rustdoc::private_intra_doc_links)]

pub mod atmosphere;
pub mod camera;
mod cpu;
pub mod error;
pub mod image;
pub mod io;
pub mod large_buffer;
mod linalg;
pub mod metrics;
pub mod minimise;
pub mod monitor;
pub mod mvs;
pub mod mvs_io;
pub mod params;
pub mod ps;
pub mod simulate;
pub mod tof;

pub use error::{MurkError, Result};
pub use image::ImageF32;
pub use monitor::Monitor;
