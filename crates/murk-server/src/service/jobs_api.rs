//! `murk.v1.Jobs`: submit / get / watch / cancel / list, and the chunked result stream.
//!
//! Every call is scoped to the caller's tenant (see `auth`): other tenants' jobs are NOT_FOUND.

use std::pin::Pin;

use futures::Stream;
use sha2::{Digest, Sha256};
use tonic::{Code, Request, Response, Status};
use tonic_types::{ErrorDetails, StatusExt};

use super::auth::Tenant;
use super::convert::job_to_proto;
use super::proto::v1 as pb;
use super::status::{ended_without_result, submit_status, to_status};
use super::submit::{submit, ServiceState};
use super::watchers::{WatchLimits, WatchRefusal, Watchers};
use crate::jobs::{JobHandle, JobSnapshot, JobState};
use std::sync::{Arc, Mutex};
use tokio::sync::OwnedSemaphorePermit;

/// Default and maximum `ListJobs` page sizes.
const DEFAULT_PAGE: usize = 50;
const MAX_PAGE: usize = 1000;

/// Largest `GetJobResult` chunk: a quarter of gRPC's default 4 MiB receive limit.
pub const MAX_RESULT_CHUNK_BYTES: usize = 1 << 20;

/// Smallest `GetJobResult` chunk a client may ask for. Each chunk costs a message header, a
/// frame and a wake-up on both sides; at one byte per chunk a 650 KB result took 650,000
/// messages, 50 MB on the wire and seconds of server CPU.
pub const MIN_RESULT_CHUNK_BYTES: usize = 16 << 10;

/// Implementation of the `Jobs` service.
pub struct JobsApi {
    state: ServiceState,
    watchers: Watchers,
}

impl JobsApi {
    /// Wraps the shared state; watch streams are bounded by `watch`.
    pub fn new(state: ServiceState, watch: WatchLimits) -> Self {
        Self {
            state,
            watchers: Watchers::new(watch),
        }
    }

    async fn handle(&self, tenant: &str, id: &str) -> Result<JobHandle, Status> {
        check_job_id(id)?;
        self.state
            .jobs
            .get(tenant, id)
            .await
            .map_err(|e| submit_status(&e))?
            .ok_or_else(|| Status::not_found(format!("no job with id `{id}`")))
    }

    fn job(&self, snap: &JobSnapshot, omit: bool) -> Result<pb::Job, Status> {
        visible_job(snap, omit, self.state.max_unary_result_bytes)
    }
}

/// True for a job the server stopped because it is shutting down. Such a job is not over: the
/// journal (or the shared queue) runs it again after the restart. Its internal FAILED state
/// only ends this process's record, so the API never shows it as terminal.
fn interrupted(snap: &JobSnapshot) -> bool {
    snap.state == JobState::Failed && matches!(snap.error, Some(murk::MurkError::ShuttingDown))
}

/// The answer to a Get, Watch or Cancel of an interrupted job: retryable UNAVAILABLE with
/// RetryInfo, never a terminal `Job`, so a client told "terminal" never sees the state change
/// when the job resumes.
fn interrupted_status(id: &str) -> Status {
    Status::with_error_details(
        Code::Unavailable,
        format!(
            "server shutting down: job `{id}` was interrupted, not finished; watch it again \
             after the restart (with a journal or a shared queue it resumes), or resubmit it"
        ),
        ErrorDetails::with_retry_info(Some(std::time::Duration::from_secs(1))),
    )
}

/// RESOURCE_EXHAUSTED with a retry hint for a watch stream over a limit.
fn watch_refusal_status(r: &WatchRefusal) -> Status {
    let message = match r {
        WatchRefusal::Job(n) => format!(
            "this job has its maximum of {n} watch streams (--max-watchers-per-job); share one \
             stream, or poll it with GetJob"
        ),
        WatchRefusal::Tenant(n) => format!(
            "this tenant has its maximum of {n} watch streams on this replica \
             (--max-watchers-per-tenant); end some first"
        ),
    };
    Status::with_error_details(
        Code::ResourceExhausted,
        message,
        ErrorDetails::with_retry_info(Some(std::time::Duration::from_secs(1))),
    )
}

/// `job_to_proto`, except that an interrupted job is UNAVAILABLE.
fn visible_job(snap: &JobSnapshot, omit: bool, limit: usize) -> Result<pb::Job, Status> {
    if interrupted(snap) {
        return Err(interrupted_status(&snap.id));
    }
    job_to_proto(snap, omit, limit)
}

/// A job for `ListJobs`, which cannot answer one entry with a status: an interrupted job is
/// listed as queued, which it is for the restart that will run it.
fn listed_job(snap: &JobSnapshot, limit: usize) -> Result<pb::Job, Status> {
    if !interrupted(snap) {
        return job_to_proto(snap, true, limit);
    }
    let mut queued = snap.clone();
    queued.state = JobState::Queued;
    queued.error = None;
    queued.end_time = None;
    queued.stage = "interrupted by shutdown".into();
    job_to_proto(&queued, true, limit)
}

/// A job id is the hex SHA-256 of its request: 64 lowercase hex digits. Anything else is
/// INVALID_ARGUMENT naming `id`, and the error quotes at most its length, never the id: an id of
/// megabytes must not come back whole.
fn check_job_id(id: &str) -> Result<(), Status> {
    let reason = if id.is_empty() {
        "required".to_string()
    } else if id.len() != 64 {
        format!(
            "a job id is 64 hex digits (the SHA-256 of its request), got {} bytes",
            id.len()
        )
    } else if !id
        .bytes()
        .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        "a job id is 64 lowercase hex digits (the SHA-256 of its request)".to_string()
    } else {
        return Ok(());
    };
    Err(to_status(&murk::MurkError::invalid("id", reason)))
}

type JobStream = Pin<Box<dyn Stream<Item = Result<pb::Job, Status>> + Send>>;
type ChunkStream = Pin<Box<dyn Stream<Item = Result<pb::ResultChunk, Status>> + Send>>;

#[tonic::async_trait]
impl pb::jobs_server::Jobs for JobsApi {
    async fn submit_job(
        &self,
        request: Request<pb::SubmitJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let tenant = Tenant::of(&request);
        let r = request.into_inner();
        let Some(req) = r.request else {
            return Err(to_status(&murk::MurkError::invalid("request", "required")));
        };
        let submitted = submit(&self.state, &tenant, req, Some("request")).await?;
        submitted.handle.detach();
        let mut job = self.job(&submitted.handle.snapshot(), r.omit_result)?;
        job.cached |= submitted.cached;
        Ok(Response::new(job))
    }

    async fn get_job(
        &self,
        request: Request<pb::GetJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let tenant = Tenant::of(&request);
        let r = request.into_inner();
        let h = self.handle(&tenant, &r.id).await?;
        Ok(Response::new(self.job(&h.snapshot(), r.omit_result)?))
    }

    type WatchJobStream = JobStream;

    async fn watch_job(
        &self,
        request: Request<pb::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let tenant = Tenant::of(&request);
        let r = request.into_inner();
        let h = self.handle(&tenant, &r.id).await?;
        let slot = self
            .watchers
            .open(&tenant, &r.id)
            .map_err(|refusal| watch_refusal_status(&refusal))?;
        let rx = h.subscribe();
        let omit = r.omit_result;
        let limit = self.state.max_unary_result_bytes;
        let watchers = self.watchers.clone();
        // The budget share of the result this stream sent: it lives as long as the stream
        // (until the message is sent and the stream dropped, or the client cancels).
        let held: Arc<Mutex<Option<OwnedSemaphorePermit>>> = Arc::default();
        let holder = held.clone();
        // Yield the current snapshot at once, then one per change, ending after a terminal one.
        let stream = futures::stream::unfold(Some((rx, true)), move |st| {
            let watchers = watchers.clone();
            let held = held.clone();
            async move {
                let (mut rx, first) = st?;
                if !first && rx.changed().await.is_err() {
                    return None;
                }
                let snap = rx.borrow_and_update().clone();
                // A result goes out inline only with a share of the budget; without one the
                // client fetches it with GetJobResult, as for a result over the unary limit
                // (which is left out anyway, so it takes no share).
                let share = match &snap.result {
                    Some(bytes) if !omit && bytes.len() <= limit => watchers.reserve(bytes.len()),
                    _ => None,
                };
                let inline = share.is_some();
                if inline {
                    *held.lock().unwrap_or_else(|p| p.into_inner()) = share;
                }
                // An interrupted job ends the stream with UNAVAILABLE, without a terminal message.
                let item = visible_job(&snap, omit || !inline, limit);
                let next = (!snap.state.is_terminal()).then_some((rx, false));
                Some((item, next))
            }
        });
        // Holding the handle keeps the job's record alive for the stream's lifetime; the slot
        // and the budget share go when the stream does.
        let keep = (h.clone(), slot, holder);
        let stream = futures::StreamExt::map(stream, move |item| {
            let _ = &keep;
            item
        });
        Ok(Response::new(Box::pin(stream)))
    }

    async fn cancel_job(
        &self,
        request: Request<pb::CancelJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let tenant = Tenant::of(&request);
        let id = request.into_inner().id;
        self.handle(&tenant, &id).await?;
        let snap = self
            .state
            .jobs
            .cancel(&tenant, &id)
            .await
            .map_err(|e| submit_status(&e))?
            .ok_or_else(|| Status::not_found(format!("no job with id `{id}`")))?;
        Ok(Response::new(self.job(&snap, true)?))
    }

    async fn list_jobs(
        &self,
        request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let tenant = Tenant::of(&request);
        let r = request.into_inner();
        let size = match r.page_size as usize {
            0 => DEFAULT_PAGE,
            n => n.min(MAX_PAGE),
        };
        let offset = if r.page_token.is_empty() {
            0
        } else {
            r.page_token.parse::<usize>().map_err(|_| {
                to_status(&murk::MurkError::invalid(
                    "page_token",
                    "not a token returned by ListJobs",
                ))
            })?
        };
        let (page, next) = self
            .state
            .jobs
            .list(&tenant, offset, size)
            .await
            .map_err(|e| submit_status(&e))?;
        let jobs = page
            .iter()
            .map(|s| listed_job(s, self.state.max_unary_result_bytes))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Response::new(pb::ListJobsResponse {
            jobs,
            next_page_token: next.map(|n| n.to_string()).unwrap_or_default(),
        }))
    }

    type GetJobResultStream = ChunkStream;

    async fn get_job_result(
        &self,
        request: Request<pb::GetJobResultRequest>,
    ) -> Result<Response<Self::GetJobResultStream>, Status> {
        let tenant = Tenant::of(&request);
        let r = request.into_inner();
        let chunk = match r.chunk_bytes as usize {
            0 => MAX_RESULT_CHUNK_BYTES,
            n if n < MIN_RESULT_CHUNK_BYTES => {
                return Err(to_status(&murk::MurkError::invalid(
                    "chunk_bytes",
                    format!(
                        "{n} is below the smallest chunk, {MIN_RESULT_CHUNK_BYTES} bytes \
                         (0 asks for the largest, {MAX_RESULT_CHUNK_BYTES})"
                    ),
                )))
            }
            n => n.min(MAX_RESULT_CHUNK_BYTES),
        };
        let snap = self.handle(&tenant, &r.id).await?.snapshot();
        if interrupted(&snap) {
            return Err(interrupted_status(&r.id));
        }
        let bytes = match snap.state {
            JobState::Succeeded => snap
                .result
                .ok_or_else(|| Status::internal("succeeded job without result"))?,
            JobState::Failed | JobState::Cancelled => return Err(ended_without_result(&snap)),
            JobState::Queued | JobState::Running => {
                return Err(Status::failed_precondition(format!(
                    "job `{}` is not finished (watch it with WatchJob first)",
                    r.id
                )))
            }
        };
        let total = bytes.len();
        let sha256 = hex::encode(Sha256::digest(bytes.as_slice()));
        // An empty result still yields one (empty) chunk, so the client sees the total and hash.
        let starts: Vec<usize> = if total == 0 {
            vec![0]
        } else {
            (0..total).step_by(chunk).collect()
        };
        let stream = futures::stream::iter(starts.into_iter().map(move |start| {
            let end = (start + chunk).min(total);
            Ok(pb::ResultChunk {
                offset: start as u64,
                data: bytes[start..end].to_vec(),
                total_bytes: total as u64,
                sha256: sha256.clone(),
            })
        }));
        Ok(Response::new(Box::pin(stream)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ended(state: JobState, error: Option<murk::MurkError>) -> JobSnapshot {
        let mut s = JobSnapshot::queued(&"a".repeat(64), "tof_depth");
        s.state = state;
        s.error = error;
        s.end_time = Some(std::time::SystemTime::now());
        s
    }

    #[test]
    fn an_interrupted_job_is_unavailable_to_get_and_listed_as_queued() {
        let snap = ended(JobState::Failed, Some(murk::MurkError::ShuttingDown));
        let err = visible_job(&snap, true, usize::MAX).unwrap_err();
        assert_eq!(err.code(), Code::Unavailable);
        assert!(err.get_details_retry_info().is_some());
        let listed = listed_job(&snap, usize::MAX).unwrap();
        assert_eq!(listed.state, pb::JobState::Queued as i32);
        assert!(listed.outcome.is_none() && listed.end_time.is_none());
        // A job that really failed or was cancelled stays terminal everywhere.
        for snap in [
            ended(
                JobState::Failed,
                Some(murk::MurkError::Numerical("x".into())),
            ),
            ended(JobState::Cancelled, Some(murk::MurkError::Cancelled)),
        ] {
            let got = visible_job(&snap, true, usize::MAX).unwrap();
            assert_eq!(got, listed_job(&snap, usize::MAX).unwrap());
            assert_ne!(got.state, pb::JobState::Queued as i32);
        }
    }

    #[test]
    fn job_ids_must_be_64_lowercase_hex_digits() {
        assert!(check_job_id(&"0f".repeat(32)).is_ok());
        for bad in [
            "",
            "abc",
            &"0F".repeat(32),
            &"g".repeat(64),
            &"a".repeat(15_000),
        ] {
            let err = check_job_id(bad).unwrap_err();
            assert_eq!(err.code(), Code::InvalidArgument);
            assert!(err.message().len() < 200, "{}", err.message());
        }
    }
}
