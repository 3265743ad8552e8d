//! gRPC service layer: protobuf ↔ domain conversion, error mapping, and the `Jobs` and
//! `Reconstruction` services. The algorithms never see any of this.

pub mod auth;
pub mod codec;
pub mod convert;
pub mod grpc_metrics;
mod jobs_api;
pub mod proto;
mod reconstruction_api;
pub mod request_id;
pub mod status;
mod submit;

pub use jobs_api::JobsApi;
pub use reconstruction_api::{grpc_timeout, ReconstructionApi, JOB_ID_HEADER};
pub use submit::{
    job_id, method_name, RequestLimits, ServiceState, ALGORITHM_VERSION,
    DEFAULT_MAX_UNARY_RESULT_BYTES,
};
