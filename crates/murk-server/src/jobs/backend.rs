//! Where job records, the queue and results live, behind one trait the service talks to:
//! [`JobManager`] keeps them in this process (the embedded default, no external services);
//! [`super::redis::RedisJobs`] keeps them in Redis so any number of replicas share them.
//!
//! Both run the computations on the local [`JobManager`]'s pool; only the bookkeeping differs.

use std::time::Duration;

use async_trait::async_trait;

use super::entry::Work;
use super::handle::{JobHandle, Submitted};
use super::manager::{JobManager, JobsError};
use super::state::JobSnapshot;

/// The job system as the service sees it. Every call is scoped to a tenant (`""` without
/// authentication): another tenant's job is indistinguishable from an unknown id.
#[async_trait]
pub trait JobBackend: Send + Sync + 'static {
    /// `"embedded"` or `"redis"`, for logs.
    fn kind(&self) -> &'static str;

    /// The local executor (pool, metrics, local cache).
    fn local(&self) -> &JobManager;

    /// True when [`JobBackend::submit`] needs the canonical request bytes (to journal them, or
    /// to hand the job to whichever replica runs it).
    fn wants_request(&self) -> bool;

    /// Jobs waiting to start (across all replicas for a shared backend; for the metrics gauge).
    fn queue_depth(&self) -> usize;

    /// For a backend on an external store: whether its last periodic check reached it and was
    /// answered (the `murk_redis_up` gauge); `None` for the in-process backend.
    fn store_up(&self) -> Option<bool> {
        None
    }

    /// `tenant`'s live or succeeded job with this id, or a cached result recorded as a
    /// succeeded job; `None` when the request must be (re)computed.
    async fn find(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
    ) -> Result<Option<Submitted>, JobsError>;

    /// `tenant`'s job with this id in any state.
    async fn get(&self, tenant: &str, id: &str) -> Result<Option<JobHandle>, JobsError>;

    /// True when the (global) queue has no free slot: a cheap check before decoding a request.
    async fn queue_full(&self) -> Result<bool, JobsError>;

    /// The refusal for a full queue, with a retry hint.
    fn refusal(&self) -> JobsError;

    /// Queues `work` under `(tenant, id)` unless an identical job is live or succeeded (that one
    /// is returned). `request` is the canonical request when [`JobBackend::wants_request`].
    async fn submit(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
        work: Work,
        request: Option<Vec<u8>>,
    ) -> Result<Submitted, JobsError>;

    /// Requests cancellation; `None` for unknown ids (and other tenants' jobs).
    async fn cancel(&self, tenant: &str, id: &str) -> Result<Option<JobSnapshot>, JobsError>;

    /// `tenant`'s jobs, newest first: `(page, next_offset)`. Snapshots carry no results.
    async fn list(
        &self,
        tenant: &str,
        offset: usize,
        page_size: usize,
    ) -> Result<(Vec<JobSnapshot>, Option<usize>), JobsError>;

    /// Stops taking work, drains for up to `grace`, then stops what still runs (a shared
    /// backend hands such jobs back to the queue for another replica).
    async fn shutdown(&self, grace: Duration);
}

#[async_trait]
impl JobBackend for JobManager {
    fn kind(&self) -> &'static str {
        "embedded"
    }

    fn local(&self) -> &JobManager {
        self
    }

    fn wants_request(&self) -> bool {
        self.journaling()
    }

    fn queue_depth(&self) -> usize {
        self.queued()
    }

    async fn find(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
    ) -> Result<Option<Submitted>, JobsError> {
        Ok(JobManager::find(self, tenant, id, method))
    }

    async fn get(&self, tenant: &str, id: &str) -> Result<Option<JobHandle>, JobsError> {
        Ok(JobManager::get(self, tenant, id))
    }

    async fn queue_full(&self) -> Result<bool, JobsError> {
        Ok(JobManager::queue_full(self))
    }

    fn refusal(&self) -> JobsError {
        JobManager::refusal(self)
    }

    async fn submit(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
        work: Work,
        request: Option<Vec<u8>>,
    ) -> Result<Submitted, JobsError> {
        self.submit_durable(tenant, id, method, work, request)
    }

    async fn cancel(&self, tenant: &str, id: &str) -> Result<Option<JobSnapshot>, JobsError> {
        Ok(JobManager::cancel(self, tenant, id))
    }

    async fn list(
        &self,
        tenant: &str,
        offset: usize,
        page_size: usize,
    ) -> Result<(Vec<JobSnapshot>, Option<usize>), JobsError> {
        let (mut page, next) = JobManager::list(self, tenant, offset, page_size);
        for s in &mut page {
            s.result = None;
        }
        Ok((page, next))
    }

    async fn shutdown(&self, grace: Duration) {
        JobManager::shutdown(self, grace).await
    }
}
