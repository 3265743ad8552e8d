//! The state a job manager shares with its handles and its dispatcher threads, and how a job
//! ends: its journal file, its line in the record log, its terminal snapshot and its metrics.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::time::Instant;

use tokio::sync::Notify;

use super::cache::ResultCache;
use super::config::JobsConfig;
use super::entry::JobEntry;
use super::journal::Journal;
use super::metrics::JobMetrics;
use super::record_log::{LoggedRecord, RecordLog};
use super::registry::Registry;
use super::state::JobState;
use murk::error::MurkError;

/// Everything behind a [`JobManager`](super::JobManager) and its clones, handles and
/// dispatchers.
pub(super) struct Inner {
    pub(super) cfg: JobsConfig,
    pub(super) pool: rayon::ThreadPool,
    pub(super) cache: ResultCache,
    pub(super) registry: Mutex<Registry>,
    pub(super) queue_cv: Condvar,
    pub(super) shutting_down: AtomicBool,
    pub(super) executed: AtomicU64,
    pub(super) running: AtomicUsize,
    pub(super) idle: Notify,
    pub(super) metrics: JobMetrics,
    /// Exponential moving average of compute time per method, seconds.
    pub(super) mean_secs: Mutex<HashMap<String, f64>>,
    /// Method and start of every job being computed, by dispatcher.
    pub(super) in_progress: Mutex<HashMap<usize, (String, Instant)>>,
    /// Accepted jobs on disk (with a cache directory).
    pub(super) journal: Option<Journal>,
    /// Finished records across restarts (`--cache-dir/records.log`), once
    /// [`JobManager::restore_records`](super::JobManager::restore_records) opened it (the
    /// embedded default; not in Redis mode).
    pub(super) record_log: OnceLock<RecordLog>,
}

impl Inner {
    pub(super) fn registry(&self) -> MutexGuard<'_, Registry> {
        // A panic while holding the lock cannot leave the registry inconsistent in a way that
        // matters more than refusing all further work would, so poisoning is ignored.
        self.registry.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Raises `entry`'s cancel flag (remembering the first `reason`); a queued job ends at once, a
/// running one at its next checkpoint.
pub(super) fn cancel_entry(inner: &Inner, entry: &Arc<JobEntry>, reason: u8) {
    if !entry.cancel.swap(true, Ordering::SeqCst) {
        entry.cancel_reason.store(reason, Ordering::SeqCst);
    }
    let was_queued = inner.registry().queue.remove(entry);
    if was_queued {
        let (state, error) = entry.stopped_outcome();
        finish_entry(inner, entry, state, None, Some(error));
        inner.idle.notify_waiters();
    }
}

/// Moves `entry` to a terminal state and counts it.
pub(super) fn finish_entry(
    inner: &Inner,
    entry: &JobEntry,
    state: JobState,
    result: Option<Arc<Vec<u8>>>,
    error: Option<MurkError>,
) {
    if entry.state().is_terminal() {
        return;
    }
    let aborted = matches!(error, Some(MurkError::ShuttingDown));
    // Before the terminal state is published, so whoever sees it finds the journal settled.
    // A job the shutdown stopped keeps its journal file, so a restart finishes it.
    if !aborted && entry.journaled.load(Ordering::SeqCst) {
        if let Some(j) = &inner.journal {
            // A resubmission may own the same file by now (same tenant and id).
            let superseded = inner
                .registry()
                .jobs
                .get(&entry.key())
                .is_some_and(|e| !std::ptr::eq(Arc::as_ptr(e), entry));
            if !superseded {
                j.remove(&entry.tenant, &entry.id);
            }
        }
    }
    if !aborted && entry.remote.is_none() {
        log_end(inner, entry, state, error.as_ref());
    }
    if entry.finish(state, result, error.clone()) {
        let label = match (state, &error) {
            (JobState::Failed, Some(MurkError::ShuttingDown)) => "aborted",
            (JobState::Succeeded, _) => "succeeded",
            (JobState::Failed, _) => "failed",
            _ => "cancelled",
        };
        inner.metrics.finished(&entry.method, label);
    }
}

/// Appends a job's end to the record log (fsynced, before the end is published).
fn log_end(inner: &Inner, entry: &JobEntry, state: JobState, error: Option<&MurkError>) {
    let Some(log) = inner.record_log.get() else {
        return;
    };
    let Some(r) = LoggedRecord::ended(&entry.tenant, &entry.snapshot(), state, error) else {
        return;
    };
    let appended_at = match log.append(&r, true) {
        Ok(n) => n,
        Err(e) => {
            tracing::warn!(id = %entry.id, error = %e, "could not log the job record");
            return;
        }
    };
    if log.appended() > compaction_bound(inner) {
        compact_if_grown(inner, log, &inner.registry());
    }
    // A compaction between the append and now gathered the registry before this job's end
    // was published there, so without this its line would be lost.
    if log.rewrites() != appended_at {
        if let Err(e) = log.append(&r, true) {
            tracing::warn!(id = %entry.id, error = %e, "could not log the job record");
        }
    }
}

/// Lines the record log may hold before it is compacted.
fn compaction_bound(inner: &Inner) -> usize {
    2 * inner.cfg.max_job_records + 1024
}

/// Rewrites the record log from the registry once it has grown well past the records kept.
/// Called with the registry locked (lock order: registry, then log); a job's end logged
/// concurrently, before its state reached the registry, is appended again by its writer.
pub(super) fn compact_if_grown(inner: &Inner, log: &RecordLog, reg: &Registry) {
    if log.appended() > compaction_bound(inner) {
        let kept: Vec<LoggedRecord> = reg
            .order
            .iter()
            .filter_map(|k| reg.jobs.get(k))
            .filter(|e| e.remote.is_none())
            .filter_map(|e| {
                let s = e.snapshot();
                LoggedRecord::ended(&e.tenant, &s, s.state, s.error.as_ref())
            })
            .collect();
        if let Err(e) = log.rewrite(&kept) {
            tracing::warn!(error = %e, "could not compact the job-record log");
        }
    }
}

/// Folds one compute time into the method's moving average behind the retry hint.
pub(super) fn record_compute_time(inner: &Inner, method: &str, seconds: f64) {
    lock(&inner.mean_secs)
        .entry(method.to_string())
        .and_modify(|m| *m = 0.8 * *m + 0.2 * seconds)
        .or_insert(seconds);
}

/// Locks a mutex whose data stays consistent even if a holder panicked (plain maps of numbers).
pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}
