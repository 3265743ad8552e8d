//! What callers hold: handles on one job (snapshots, change notifications, waiter registration)
//! and the guards that cancel a job when its last unary caller goes away.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use tokio::sync::watch;

use super::entry::{JobEntry, CANCEL_BY_CALLER};
use super::shared::{cancel_entry, Inner};
use super::state::JobSnapshot;

/// What `submit`/`find` returns.
pub struct Submitted {
    /// The job.
    pub handle: JobHandle,
    /// True when the job had already succeeded (now or in an earlier run): no recomputation.
    pub cached: bool,
}

/// A reference to one job: snapshots, change notifications, waiter registration.
#[derive(Clone)]
pub struct JobHandle {
    entry: Arc<JobEntry>,
    inner: Arc<Inner>,
}

impl JobHandle {
    pub(super) fn new(entry: Arc<JobEntry>, inner: Arc<Inner>) -> Self {
        Self { entry, inner }
    }

    /// The job id.
    pub fn id(&self) -> &str {
        &self.entry.id
    }
    /// Current snapshot.
    pub fn snapshot(&self) -> JobSnapshot {
        self.entry.snapshot()
    }
    /// A receiver that sees every state/progress change.
    pub fn subscribe(&self) -> watch::Receiver<JobSnapshot> {
        self.entry.tx.subscribe()
    }
    /// Replaces a view's snapshot (see [`JobManager::view`](super::JobManager::view)); a
    /// terminal snapshot is final.
    pub(crate) fn publish(&self, snap: JobSnapshot) {
        self.entry.tx.send_if_modified(|s| {
            if s.state.is_terminal() {
                return false;
            }
            *s = snap;
            true
        });
    }

    /// A handle that does not keep the job's record alive.
    pub(crate) fn downgrade(&self) -> WeakJobHandle {
        WeakJobHandle {
            entry: Arc::downgrade(&self.entry),
            inner: self.inner.clone(),
        }
    }

    /// Marks the job as owned by the Jobs API: it keeps running when unary waiters leave.
    pub fn detach(&self) {
        if !self.entry.detached.swap(true, Ordering::SeqCst) {
            if let Some(r) = &self.entry.remote {
                r.detached(&self.entry.tenant, &self.entry.id);
            }
        }
    }
    /// Registers a unary caller; when the last guard drops before the job is terminal and the
    /// job was never detached, the job is cancelled (the caller went away).
    pub fn attach(&self) -> WaiterGuard {
        let n = self.entry.waiters.fetch_add(1, Ordering::SeqCst) + 1;
        if let Some(r) = &self.entry.remote {
            let seq = self.entry.waiter_seq.fetch_add(1, Ordering::SeqCst) + 1;
            r.waiters_changed(&self.entry.tenant, &self.entry.id, n, seq);
        }
        WaiterGuard {
            handle: self.clone(),
        }
    }
}

/// A handle that does not keep its job's record alive (the Redis backend's table of views).
#[derive(Clone)]
pub(crate) struct WeakJobHandle {
    entry: std::sync::Weak<JobEntry>,
    inner: Arc<Inner>,
}

impl WeakJobHandle {
    /// The handle, if anyone still holds it.
    pub(crate) fn upgrade(&self) -> Option<JobHandle> {
        Some(JobHandle {
            entry: self.entry.upgrade()?,
            inner: self.inner.clone(),
        })
    }
}

/// Dropping the last one of these cancels an attached-only job. See [`JobHandle::attach`].
pub struct WaiterGuard {
    handle: JobHandle,
}

impl Drop for WaiterGuard {
    fn drop(&mut self) {
        let e = &self.handle.entry;
        if let Some(r) = &e.remote {
            let n = e.waiters.fetch_sub(1, Ordering::SeqCst) - 1;
            let seq = e.waiter_seq.fetch_add(1, Ordering::SeqCst) + 1;
            r.waiters_changed(&e.tenant, &e.id, n, seq);
            return;
        }
        if e.waiters.fetch_sub(1, Ordering::SeqCst) == 1
            && !e.detached.load(Ordering::SeqCst)
            && !e.state().is_terminal()
        {
            tracing::info!(id = %e.id, "last caller went away; cancelling job");
            cancel_entry(&self.handle.inner, e, CANCEL_BY_CALLER);
        }
    }
}
