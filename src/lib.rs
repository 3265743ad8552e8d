//! murk: 3D shape and depth through fog, smoke and turbid water.
//!
//! The library holds the physics-based methods of the reference dissertation
//! (`../shared/reference/scattering-media-dissertation.md`) and knows nothing of gRPC; the
//! [`service`] module converts protobuf ↔ domain types and maps [`MurkError`] to `tonic::Status`.

pub mod atmosphere;
pub mod camera;
mod cpu;
pub mod error;
mod faer_threads;
pub mod image;
pub mod io;
pub mod jobs;
pub mod large_buffer;
pub mod metrics;
pub mod minimise;
pub mod monitor;
pub mod mvs;
pub mod mvs_io;
pub mod params;
pub mod ps;
pub mod server;
pub mod service;
pub mod simulate;
pub mod telemetry;
pub mod tof;

pub use error::{MurkError, Result};
pub use image::ImageF32;
pub use monitor::Monitor;
