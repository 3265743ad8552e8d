//! gRPC service layer: protobuf ↔ domain conversion, error mapping, and the `Jobs`,
//! `Reconstruction` and `Sessions` services. The algorithms never see any of this.

pub mod auth;
pub mod codec;
pub mod convert;
pub mod grpc_metrics;
mod jobs_api;
pub mod oversize;
pub mod proto;
mod reconstruction_api;
pub mod request_id;
pub mod sessions;
pub mod status;
mod submit;
pub mod watchers;

pub use jobs_api::JobsApi;
pub use reconstruction_api::{grpc_timeout, ReconstructionApi, JOB_ID_HEADER};
pub use sessions::{SessionLimits, SessionsApi};
pub use submit::{
    job_id, method_name, rebuild_work, CacheScope, RequestLimits, ServiceState, ALGORITHM_VERSION,
    DEFAULT_MAX_UNARY_RESULT_BYTES,
};

/// The boxed response future of murk's tower layers.
pub(crate) type BoxFuture<T, E> =
    std::pin::Pin<Box<dyn std::future::Future<Output = Result<T, E>> + Send>>;

/// The service that was polled ready, for the call at hand, leaving a fresh clone in its place
/// (tower's rule: the readied instance must serve the request).
pub(crate) fn take_ready<S: Clone>(slot: &mut S) -> S {
    let fresh = slot.clone();
    std::mem::replace(slot, fresh)
}
