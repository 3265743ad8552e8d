//! murk's service: the gRPC API over the [`murk`] library's methods, the job queue and its
//! backends (in process, or shared through Redis), the server with its auth, TLS, metrics and
//! drain, and the telemetry. The `murk` binary (CLI) is built on it.
//!
//! The algorithms know nothing of this crate; [`service`] converts protobuf ↔ domain types and
//! maps [`murk::MurkError`] to `tonic::Status` in one place.

// The docs are written for users and for developers (`cargo doc --document-private-items`):
// a public item may point at the private helper that does the work.
#![allow(rustdoc::private_intra_doc_links)]

pub mod allocator;
pub mod bag;
pub mod cgroup;
pub mod connections;
pub mod jobs;
pub mod server;
pub mod service;
pub mod telemetry;
