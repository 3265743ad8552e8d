//! The dispatcher threads: each takes the next job from the queue and computes it on the shared
//! rayon pool, publishing its progress and its end.
//!
//! Why dispatcher threads in front of rayon instead of `pool.spawn` per job: rayon's own queue
//! is unbounded and work-stealing may start a second job inside a first job's `join`, so a fixed
//! number of dispatchers (`concurrent_jobs`) each `install` one job at a time on the shared pool;
//! the algorithms' inner `par_iter`s use all the pool's threads.

use std::panic::AssertUnwindSafe;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use super::entry::JobEntry;
use super::shared::{finish_entry, lock, record_compute_time, Inner};
use super::state::JobState;
use murk::error::MurkError;
use murk::monitor::{Monitor, ProgressSink};

/// One dispatcher thread's life (`slot` names it in `in_progress`): takes the next job, computes
/// it, charges its compute time to its method; returns once shutdown stopped the registry and
/// the queue is empty.
pub(super) fn dispatch_loop(inner: Arc<Inner>, slot: usize) {
    loop {
        let entry = {
            let mut reg = inner.registry();
            loop {
                if let Some(e) = reg.queue.pop() {
                    // Counted under the lock so `is_idle` never sees an empty queue and zero
                    // running jobs while one is in hand.
                    inner.running.fetch_add(1, Ordering::SeqCst);
                    break e;
                }
                if reg.stopped {
                    return;
                }
                reg = inner.queue_cv.wait(reg).unwrap_or_else(|p| p.into_inner());
            }
        };
        let started = Instant::now();
        lock(&inner.in_progress).insert(slot, (entry.method.clone(), started));
        run_job(&inner, &entry);
        lock(&inner.in_progress).remove(&slot);
        inner
            .registry()
            .queue
            .charge(&entry.method, started.elapsed().as_secs_f64());
        inner.running.fetch_sub(1, Ordering::SeqCst);
        inner.idle.notify_waiters();
    }
}

/// Computes one job on the pool and publishes its progress and its end.
fn run_job(inner: &Inner, entry: &Arc<JobEntry>) {
    let work = entry.work.lock().unwrap_or_else(|p| p.into_inner()).take();
    let Some(work) = work else {
        finish_entry(
            inner,
            entry,
            JobState::Failed,
            None,
            Some(MurkError::Internal("job has no work attached".into())),
        );
        return;
    };
    if entry.cancelling() {
        let (state, error) = entry.stopped_outcome();
        finish_entry(inner, entry, state, None, Some(error));
        return;
    }
    let span = tracing::info_span!("job", id = %entry.id);
    let _enter = span.enter();
    let now = SystemTime::now();
    entry.tx.send_modify(|s| {
        s.state = JobState::Running;
        s.start_time = Some(now);
        s.stage = "starting".into();
        let waited = now.duration_since(s.create_time).unwrap_or_default();
        inner.metrics.waited(&entry.method, waited.as_secs_f64());
    });
    inner.executed.fetch_add(1, Ordering::SeqCst);
    let started = Instant::now();
    let progress_entry = entry.clone();
    let sink: ProgressSink = Arc::new(move |stage: &str, fraction: f32| {
        progress_entry.tx.send_if_modified(|s| {
            // Never backwards: parallel parts of a method report from several threads, whose
            // reports can arrive out of order.
            let fraction = fraction.max(s.progress);
            // Coalesce: watchers only care about visible changes.
            if s.state != JobState::Running
                || (s.stage == stage && (fraction - s.progress).abs() < 0.002)
            {
                return false;
            }
            s.progress = fraction;
            if s.stage != stage {
                s.stage = stage.to_string();
            }
            true
        });
    });
    let monitor = Monitor::new(entry.cancel.clone(), Some(sink));
    let outcome =
        std::panic::catch_unwind(AssertUnwindSafe(|| inner.pool.install(|| work(&monitor))));
    let seconds = started.elapsed().as_secs_f64();
    let elapsed_ms = seconds * 1e3;
    inner.metrics.ran(&entry.method, seconds);
    match outcome {
        Ok(Ok(bytes)) => {
            record_compute_time(inner, &entry.method, seconds);
            let bytes = Arc::new(bytes);
            // Only complete results are cached; a job stopped part-way never is.
            inner.cache.put(&entry.id, bytes.clone());
            finish_entry(inner, entry, JobState::Succeeded, Some(bytes), None);
            tracing::info!(elapsed_ms, "job succeeded");
        }
        Ok(Err(MurkError::Cancelled)) => {
            let (state, error) = entry.stopped_outcome();
            tracing::info!(elapsed_ms, reason = %error, "job stopped");
            finish_entry(inner, entry, state, None, Some(error));
        }
        Ok(Err(e)) => {
            tracing::warn!(elapsed_ms, error = %e, "job failed");
            finish_entry(inner, entry, JobState::Failed, None, Some(e));
        }
        Err(panic) => {
            let msg = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            tracing::error!(elapsed_ms, panic = %msg, "job panicked");
            finish_entry(
                inner,
                entry,
                JobState::Failed,
                None,
                Some(MurkError::Internal(format!("worker panicked: {msg}"))),
            );
        }
    }
}
