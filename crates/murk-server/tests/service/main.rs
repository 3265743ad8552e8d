//! The service end to end: the real server started in process on an ephemeral port (or the
//! `murk` binary, or replicas behind Redis and nginx), driven over gRPC as clients would.
//! One test binary, so the suite links the service once.

mod api;
mod bad_input;
mod cli;
mod common;
mod connections;
mod fuzz_requests;
mod job_backends;
mod mvs_api;
mod mvs_bad_input;
mod numeric_extremes;
mod params_api;
mod proto_lint;
mod ps_api;
mod redis_scaleout;
mod service_ops;
mod sessions_api;
mod stereo_api;
