//! gRPC service layer: protobuf ↔ domain conversion, error mapping, and the `Jobs` and
//! `Reconstruction` services. The algorithms never see any of this.

pub mod convert;
mod jobs_api;
pub mod proto;
mod reconstruction_api;
pub mod status;
mod submit;

pub use jobs_api::JobsApi;
pub use reconstruction_api::{grpc_timeout, ReconstructionApi};
pub use submit::{job_id, method_name, RequestLimits, ServiceState, ALGORITHM_VERSION};
