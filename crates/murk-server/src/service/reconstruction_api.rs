//! `murk.v1.Reconstruction`: one unary RPC per method that submits a job and waits for it.
//!
//! The call shares the job system with `Jobs.SubmitJob` (same id, same cache, same dedupe). If
//! the client's deadline passes, or the client goes away, the handler future is dropped; its
//! waiter guard then cancels the job unless another caller (or a SubmitJob) still wants it.

use std::time::Duration;

use prost::Message;
use tonic::metadata::{MetadataMap, MetadataValue};
use tonic::{Code, Request, Response, Status};
use tonic_types::{ErrorDetails, StatusExt};

use super::auth::Tenant;
use super::proto::v1 as pb;
use super::status::ended_without_result;
use super::submit::{submit, ServiceState};
use crate::jobs::JobState;

/// Response header carrying the job id of a unary call (on success and on error), so a client
/// can fetch a too-large result with `Jobs.GetJobResult` or look the job up later.
pub const JOB_ID_HEADER: &str = "x-murk-job-id";

fn with_job_id<T>(id: &str, mut r: Result<Response<T>, Status>) -> Result<Response<T>, Status> {
    if let Ok(v) = MetadataValue::try_from(id) {
        match &mut r {
            Ok(resp) => {
                resp.metadata_mut().insert(JOB_ID_HEADER, v);
            }
            Err(status) => {
                status.metadata_mut().insert(JOB_ID_HEADER, v);
            }
        }
    }
    r
}

/// Implementation of the `Reconstruction` service.
pub struct ReconstructionApi {
    state: ServiceState,
}

impl ReconstructionApi {
    /// Wraps the shared state.
    pub fn new(state: ServiceState) -> Self {
        Self { state }
    }

    /// Submits `req` for the request's tenant, waits for it and returns the result, with the
    /// job id in the response (or error) metadata.
    async fn run<T>(
        &self,
        request: Request<T>,
        wrap: impl FnOnce(T) -> pb::job_request::Method,
        unwrap: impl FnOnce(pb::job_result::Method) -> Option<T::Result>,
    ) -> Result<Response<T::Result>, Status>
    where
        T: MethodRequest,
    {
        let tenant = Tenant::of(&request);
        let (metadata, _, req) = request.into_parts();
        let job = pb::JobRequest {
            method: Some(wrap(req)),
        };
        let submitted = submit(&self.state, &tenant, job, None).await?;
        let id = submitted.handle.id().to_string();
        let out = self
            .wait(&metadata, submitted)
            .await
            .and_then(|m| {
                unwrap(m).ok_or_else(|| Status::internal("stored result is of another method"))
            })
            .map(Response::new);
        with_job_id(&id, out)
    }

    async fn wait(
        &self,
        metadata: &MetadataMap,
        submitted: crate::jobs::Submitted,
    ) -> Result<pb::job_result::Method, Status> {
        let deadline = grpc_timeout(metadata);
        let _waiter = submitted.handle.attach();
        let mut rx = submitted.handle.subscribe();
        let wait = rx.wait_for(|s| s.state.is_terminal());
        let snap = match deadline {
            Some(d) => tokio::time::timeout(d, wait).await.map_err(|_| {
                Status::deadline_exceeded("deadline passed before the job finished")
            })?,
            None => wait.await,
        }
        .map_err(|_| Status::internal("job vanished"))?
        .clone();
        match snap.state {
            JobState::Succeeded => {
                let bytes = snap
                    .result
                    .ok_or_else(|| Status::internal("succeeded job without result"))?;
                // The method result is the JobResult's one field: its size is the payload's.
                let limit = self.state.max_unary_result_bytes;
                if bytes.len() > limit {
                    return Err(too_large(&snap.id, bytes.len(), limit));
                }
                pb::JobResult::decode(bytes.as_slice())
                    .map_err(|e| Status::internal(format!("stored result is corrupt: {e}")))?
                    .method
                    .ok_or_else(|| Status::internal("empty stored result"))
            }
            _ => Err(ended_without_result(&snap)),
        }
    }
}

/// A method's request message and its result message.
trait MethodRequest {
    type Result;
}

impl MethodRequest for pb::TofDepthRequest {
    type Result = pb::TofDepthResult;
}
impl MethodRequest for pb::MvsDepthRequest {
    type Result = pb::MvsDepthResult;
}
impl MethodRequest for pb::ScatteringParamsRequest {
    type Result = pb::ScatteringParamsResult;
}
impl MethodRequest for pb::PhotometricStereoRequest {
    type Result = pb::PhotometricStereoResult;
}
impl MethodRequest for pb::RectifiedStereoRequest {
    type Result = pb::RectifiedStereoResult;
}

/// FAILED_PRECONDITION for a result the unary RPC may not send, naming the RPC that can.
fn too_large(id: &str, size: usize, limit: usize) -> Status {
    let message = format!(
        "result is {size} bytes, over this RPC's limit of {limit} bytes (gRPC clients refuse \
         larger messages by default); fetch it in chunks with murk.v1.Jobs/GetJobResult for job \
         id `{id}` (also in the `{JOB_ID_HEADER}` response header)"
    );
    Status::with_error_details(
        Code::FailedPrecondition,
        message.clone(),
        ErrorDetails::with_precondition_failure_violation(
            "RESULT_TOO_LARGE",
            "murk.v1.Jobs/GetJobResult",
            message,
        ),
    )
}

#[tonic::async_trait]
impl pb::reconstruction_server::Reconstruction for ReconstructionApi {
    async fn tof_depth(
        &self,
        request: Request<pb::TofDepthRequest>,
    ) -> Result<Response<pb::TofDepthResult>, Status> {
        use pb::job_result::Method as R;
        self.run(request, pb::job_request::Method::TofDepth, |m| match m {
            R::TofDepth(r) => Some(r),
            _ => None,
        })
        .await
    }

    async fn rectified_stereo(
        &self,
        request: Request<pb::RectifiedStereoRequest>,
    ) -> Result<Response<pb::RectifiedStereoResult>, Status> {
        use pb::job_result::Method as R;
        self.run(
            request,
            pb::job_request::Method::RectifiedStereo,
            |m| match m {
                R::RectifiedStereo(r) => Some(r),
                _ => None,
            },
        )
        .await
    }

    async fn mvs_depth(
        &self,
        request: Request<pb::MvsDepthRequest>,
    ) -> Result<Response<pb::MvsDepthResult>, Status> {
        use pb::job_result::Method as R;
        self.run(request, pb::job_request::Method::MvsDepth, |m| match m {
            R::MvsDepth(r) => Some(r),
            _ => None,
        })
        .await
    }

    async fn scattering_params(
        &self,
        request: Request<pb::ScatteringParamsRequest>,
    ) -> Result<Response<pb::ScatteringParamsResult>, Status> {
        use pb::job_result::Method as R;
        self.run(
            request,
            pb::job_request::Method::ScatteringParams,
            |m| match m {
                R::ScatteringParams(r) => Some(r),
                _ => None,
            },
        )
        .await
    }

    async fn photometric_stereo(
        &self,
        request: Request<pb::PhotometricStereoRequest>,
    ) -> Result<Response<pb::PhotometricStereoResult>, Status> {
        use pb::job_result::Method as R;
        self.run(
            request,
            pb::job_request::Method::PhotometricStereo,
            |m| match m {
                R::PhotometricStereo(r) => Some(r),
                _ => None,
            },
        )
        .await
    }
}

/// The client's deadline from the `grpc-timeout` header (gRPC over HTTP/2 spec: 1–8 digits and a
/// unit H, M, S, m, u, n).
pub fn grpc_timeout(md: &MetadataMap) -> Option<Duration> {
    let v = md.get("grpc-timeout")?.to_str().ok()?;
    if v.len() < 2 || v.len() > 9 {
        return None;
    }
    let (digits, unit) = v.split_at(v.len() - 1);
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.saturating_mul(3600)),
        "M" => Duration::from_secs(n.saturating_mul(60)),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_grpc_timeout_units() {
        let mut md = MetadataMap::new();
        for (v, d) in [
            ("100m", Duration::from_millis(100)),
            ("2S", Duration::from_secs(2)),
            ("1H", Duration::from_secs(3600)),
            ("5u", Duration::from_micros(5)),
        ] {
            md.insert("grpc-timeout", v.parse().unwrap());
            assert_eq!(grpc_timeout(&md), Some(d));
        }
        md.insert("grpc-timeout", "12x".parse().unwrap());
        assert_eq!(grpc_timeout(&md), None);
    }
}
