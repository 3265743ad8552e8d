//! One job's record: the channel its snapshots go out on, its cancel flag, its waiters and the
//! work it has not started yet. The registry holds these; handles, the queue and the dispatchers
//! share them.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use tokio::sync::watch;

use super::state::{JobSnapshot, JobState};
use murk::error::MurkError;
use murk::monitor::Monitor;

/// The computation of one job: returns the encoded result message.
pub type Work = Box<dyn FnOnce(&Monitor) -> Result<Vec<u8>, MurkError> + Send + 'static>;

/// The other side of a job view whose job lives in a shared store (see `jobs::redis`): what a
/// local handle's waiter and detach changes mean there.
pub(crate) trait RemoteJob: Send + Sync {
    /// The local count of unary waiters changed to `waiters`; `seq` orders the changes, so the
    /// store keeps the latest whatever order the updates arrive in. A count of 0 on a job no
    /// one detached cancels it.
    fn waiters_changed(&self, tenant: &str, id: &str, waiters: usize, seq: u64);
    /// The job was submitted through the Jobs API: it must never be cancelled for lack of
    /// waiters.
    fn detached(&self, tenant: &str, id: &str);
}

/// Registry key: the owning tenant and the job id.
pub(super) type JobKey = (String, String);

/// Why a job's cancel flag was raised.
pub(super) const CANCEL_BY_CALLER: u8 = 0;
pub(super) const CANCEL_BY_SHUTDOWN: u8 = 1;

/// One job's record (or a view of a job that lives in a shared store).
pub(super) struct JobEntry {
    pub(super) id: String,
    pub(super) tenant: String,
    pub(super) method: String,
    pub(super) cancel: Arc<AtomicBool>,
    /// `CANCEL_BY_*`: what raised `cancel`, so shutdown ends jobs as retryable aborts rather
    /// than as user cancels.
    pub(super) cancel_reason: std::sync::atomic::AtomicU8,
    pub(super) tx: watch::Sender<JobSnapshot>,
    /// Unary callers currently waiting on this job.
    pub(super) waiters: AtomicUsize,
    /// Submitted through the Jobs API at least once: never auto-cancelled when waiters leave.
    pub(super) detached: AtomicBool,
    /// Has a journal file to remove when it ends.
    pub(super) journaled: AtomicBool,
    pub(super) work: Mutex<Option<Work>>,
    /// Set for a view of a job in a shared store: waiter and detach changes go there.
    pub(super) remote: Option<Arc<dyn RemoteJob>>,
    /// Orders the waiter-count updates sent to `remote`.
    pub(super) waiter_seq: AtomicU64,
}

impl JobEntry {
    /// A record showing `snap`, owned by `tenant`, that will compute `work` when dispatched.
    pub(super) fn new(tenant: &str, snap: JobSnapshot, work: Option<Work>) -> Arc<Self> {
        let (tx, _) = watch::channel(snap.clone());
        Arc::new(JobEntry {
            id: snap.id,
            tenant: tenant.to_string(),
            method: snap.method,
            cancel: Arc::new(AtomicBool::new(false)),
            cancel_reason: std::sync::atomic::AtomicU8::new(CANCEL_BY_CALLER),
            tx,
            waiters: AtomicUsize::new(0),
            detached: AtomicBool::new(false),
            journaled: AtomicBool::new(false),
            work: Mutex::new(work),
            remote: None,
            waiter_seq: AtomicU64::new(0),
        })
    }

    pub(super) fn snapshot(&self) -> JobSnapshot {
        self.tx.borrow().clone()
    }

    pub(super) fn state(&self) -> JobState {
        self.tx.borrow().state
    }

    pub(super) fn key(&self) -> JobKey {
        (self.tenant.clone(), self.id.clone())
    }

    /// True once cancellation was requested; such a record is never reused by a new submission.
    pub(super) fn cancelling(&self) -> bool {
        self.cancel.load(Ordering::SeqCst)
    }

    /// The terminal state and error of a job stopped through its cancel flag: a user cancel, or
    /// a retryable abort when the server stopped it on shutdown.
    pub(super) fn stopped_outcome(&self) -> (JobState, MurkError) {
        if self.cancel_reason.load(Ordering::SeqCst) == CANCEL_BY_SHUTDOWN {
            (JobState::Failed, MurkError::ShuttingDown)
        } else {
            (JobState::Cancelled, MurkError::Cancelled)
        }
    }

    /// Moves to a terminal state once; later calls are ignored. True if this call did it.
    pub(super) fn finish(
        &self,
        state: JobState,
        result: Option<Arc<Vec<u8>>>,
        error: Option<MurkError>,
    ) -> bool {
        self.tx.send_if_modified(|s| {
            if s.state.is_terminal() {
                return false;
            }
            s.state = state;
            s.end_time = Some(SystemTime::now());
            if state == JobState::Succeeded {
                s.progress = 1.0;
                s.stage = "done".into();
            } else {
                s.stage = format!("{state:?}").to_lowercase();
            }
            s.result = result;
            s.error = error;
            true
        })
    }
}
