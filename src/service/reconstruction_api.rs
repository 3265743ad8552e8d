//! `murk.v1.Reconstruction`: one unary RPC per method that submits a job and waits for it.
//!
//! The call shares the job system with `Jobs.SubmitJob` (same id, same cache, same dedupe). If
//! the client's deadline passes, or the client goes away, the handler future is dropped; its
//! waiter guard then cancels the job unless another caller (or a SubmitJob) still wants it.

use std::time::Duration;

use prost::Message;
use tonic::metadata::MetadataMap;
use tonic::{Request, Response, Status};

use super::proto::v1 as pb;
use super::status::to_status;
use super::submit::{submit, ServiceState};
use crate::jobs::JobState;

/// Implementation of the `Reconstruction` service.
pub struct ReconstructionApi {
    state: ServiceState,
}

impl ReconstructionApi {
    /// Wraps the shared state.
    pub fn new(state: ServiceState) -> Self {
        Self { state }
    }

    async fn run(
        &self,
        metadata: &MetadataMap,
        req: pb::JobRequest,
    ) -> Result<pb::job_result::Method, Status> {
        let deadline = grpc_timeout(metadata);
        let submitted = submit(&self.state, req, None).await?;
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
                pb::JobResult::decode(bytes.as_slice())
                    .map_err(|e| Status::internal(format!("stored result is corrupt: {e}")))?
                    .method
                    .ok_or_else(|| Status::internal("empty stored result"))
            }
            _ => Err(snap
                .error
                .as_ref()
                .map(to_status)
                .unwrap_or_else(|| Status::cancelled("job was cancelled"))),
        }
    }
}

#[tonic::async_trait]
impl pb::reconstruction_server::Reconstruction for ReconstructionApi {
    async fn tof_depth(
        &self,
        request: Request<pb::TofDepthRequest>,
    ) -> Result<Response<pb::TofDepthResult>, Status> {
        let (metadata, _, req) = request.into_parts();
        let job = pb::JobRequest {
            method: Some(pb::job_request::Method::TofDepth(req)),
        };
        match self.run(&metadata, job).await? {
            pb::job_result::Method::TofDepth(r) => Ok(Response::new(r)),
            _ => Err(Status::internal("stored result is of another method")),
        }
    }

    async fn mvs_depth(
        &self,
        request: Request<pb::MvsDepthRequest>,
    ) -> Result<Response<pb::MvsDepthResult>, Status> {
        let (metadata, _, req) = request.into_parts();
        let job = pb::JobRequest {
            method: Some(pb::job_request::Method::MvsDepth(req)),
        };
        match self.run(&metadata, job).await? {
            pb::job_result::Method::MvsDepth(r) => Ok(Response::new(r)),
            _ => Err(Status::internal("stored result is of another method")),
        }
    }

    async fn scattering_params(
        &self,
        request: Request<pb::ScatteringParamsRequest>,
    ) -> Result<Response<pb::ScatteringParamsResult>, Status> {
        let (metadata, _, req) = request.into_parts();
        let job = pb::JobRequest {
            method: Some(pb::job_request::Method::ScatteringParams(req)),
        };
        match self.run(&metadata, job).await? {
            pb::job_result::Method::ScatteringParams(r) => Ok(Response::new(r)),
            _ => Err(Status::internal("stored result is of another method")),
        }
    }

    async fn photometric_stereo(
        &self,
        request: Request<pb::PhotometricStereoRequest>,
    ) -> Result<Response<pb::PhotometricStereoResult>, Status> {
        let (metadata, _, req) = request.into_parts();
        let job = pb::JobRequest {
            method: Some(pb::job_request::Method::PhotometricStereo(req)),
        };
        match self.run(&metadata, job).await? {
            pb::job_result::Method::PhotometricStereo(r) => Ok(Response::new(r)),
            _ => Err(Status::internal("stored result is of another method")),
        }
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
