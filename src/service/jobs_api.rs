//! `murk.v1.Jobs`: submit / get / watch / cancel / list.

use std::pin::Pin;

use futures::Stream;
use tonic::{Request, Response, Status};

use super::convert::job_to_proto;
use super::proto::v1 as pb;
use super::submit::{submit, ServiceState};
use crate::jobs::JobHandle;

/// Default and maximum `ListJobs` page sizes.
const DEFAULT_PAGE: usize = 50;
const MAX_PAGE: usize = 1000;

/// Implementation of the `Jobs` service.
pub struct JobsApi {
    state: ServiceState,
}

impl JobsApi {
    /// Wraps the shared state.
    pub fn new(state: ServiceState) -> Self {
        Self { state }
    }

    fn handle(&self, id: &str) -> Result<JobHandle, Status> {
        if id.is_empty() {
            return Err(super::status::to_status(&crate::MurkError::invalid(
                "id", "required",
            )));
        }
        self.state
            .manager
            .get(id)
            .ok_or_else(|| Status::not_found(format!("no job with id `{id}`")))
    }
}

type JobStream = Pin<Box<dyn Stream<Item = Result<pb::Job, Status>> + Send>>;

#[tonic::async_trait]
impl pb::jobs_server::Jobs for JobsApi {
    async fn submit_job(
        &self,
        request: Request<pb::SubmitJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let Some(req) = request.into_inner().request else {
            return Err(super::status::to_status(&crate::MurkError::invalid(
                "request", "required",
            )));
        };
        let submitted = submit(&self.state, req, Some("request")).await?;
        submitted.handle.detach();
        let mut job = job_to_proto(&submitted.handle.snapshot(), false)?;
        job.cached |= submitted.cached;
        Ok(Response::new(job))
    }

    async fn get_job(
        &self,
        request: Request<pb::GetJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let r = request.into_inner();
        let h = self.handle(&r.id)?;
        Ok(Response::new(job_to_proto(&h.snapshot(), r.omit_result)?))
    }

    type WatchJobStream = JobStream;

    async fn watch_job(
        &self,
        request: Request<pb::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let r = request.into_inner();
        let h = self.handle(&r.id)?;
        let rx = h.subscribe();
        let omit = r.omit_result;
        // Yield the current snapshot at once, then one per change, ending after a terminal one.
        let stream = futures::stream::unfold(Some((rx, true)), move |st| async move {
            let (mut rx, first) = st?;
            if !first && rx.changed().await.is_err() {
                return None;
            }
            let snap = rx.borrow_and_update().clone();
            let item = job_to_proto(&snap, omit);
            let next = (!snap.state.is_terminal()).then_some((rx, false));
            Some((item, next))
        });
        // Holding the handle keeps the job's record alive for the stream's lifetime.
        let keep = h.clone();
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
        let id = request.into_inner().id;
        self.handle(&id)?;
        let snap = self
            .state
            .manager
            .cancel(&id)
            .ok_or_else(|| Status::not_found(format!("no job with id `{id}`")))?;
        Ok(Response::new(job_to_proto(&snap, true)?))
    }

    async fn list_jobs(
        &self,
        request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let r = request.into_inner();
        let size = match r.page_size as usize {
            0 => DEFAULT_PAGE,
            n => n.min(MAX_PAGE),
        };
        let offset = if r.page_token.is_empty() {
            0
        } else {
            r.page_token.parse::<usize>().map_err(|_| {
                super::status::to_status(&crate::MurkError::invalid(
                    "page_token",
                    "not a token returned by ListJobs",
                ))
            })?
        };
        let (page, next) = self.state.manager.list(offset, size);
        let jobs = page
            .iter()
            .map(|s| job_to_proto(s, true))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Response::new(pb::ListJobsResponse {
            jobs,
            next_page_token: next.map(|n| n.to_string()).unwrap_or_default(),
        }))
    }
}
