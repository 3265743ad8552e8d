//! The job manager: a bounded FIFO queue, dispatcher threads that run jobs on a rayon pool, and
//! the registry that deduplicates identical requests by their content-hash id.
//!
//! Why dispatcher threads in front of rayon instead of `pool.spawn` per job: rayon's own queue
//! is unbounded and work-stealing may start a second job inside a first job's `join`, so a fixed
//! number of dispatchers (`concurrent_jobs`) each `install` one job at a time on the shared pool;
//! the algorithms' inner `par_iter`s use all the pool's threads.

use std::collections::{HashMap, VecDeque};
use std::panic::AssertUnwindSafe;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime};

use tokio::sync::{watch, Notify};

use super::cache::{CacheStats, ResultCache};
use super::state::{JobSnapshot, JobState};
use crate::error::MurkError;
use crate::monitor::{Monitor, ProgressSink};

/// The computation of one job: returns the encoded result message.
pub type Work = Box<dyn FnOnce(&Monitor) -> Result<Vec<u8>, MurkError> + Send + 'static>;

/// Sizing of the job system. Every limit is explicit.
#[derive(Clone, Debug)]
pub struct JobsConfig {
    /// Threads of the rayon compute pool (0 = number of cores).
    pub workers: usize,
    /// Jobs computed at the same time, each using the whole pool for its inner loops.
    pub concurrent_jobs: usize,
    /// Jobs that may wait in the queue; one more is refused with a retry hint.
    pub queue_capacity: usize,
    /// In-memory result cache budget in bytes.
    pub cache_bytes: u64,
    /// Optional directory where results persist across restarts.
    pub cache_dir: Option<PathBuf>,
    /// Suggested client back-off when the queue is full.
    pub retry_after: Duration,
    /// Job records kept for Get/List; the oldest terminal ones are forgotten beyond this
    /// (their results stay in the cache).
    pub max_job_records: usize,
}

impl Default for JobsConfig {
    fn default() -> Self {
        Self {
            workers: 0,
            concurrent_jobs: 1,
            queue_capacity: 64,
            cache_bytes: 512 << 20,
            cache_dir: None,
            retry_after: Duration::from_secs(2),
            max_job_records: 10_000,
        }
    }
}

/// Why a submission was refused.
#[derive(Debug, Clone, PartialEq)]
pub enum SubmitError {
    /// The queue holds `capacity` jobs already; retry after `retry_after`.
    QueueFull {
        /// Queue capacity.
        capacity: usize,
        /// Suggested back-off.
        retry_after: Duration,
    },
    /// The server is shutting down and accepts no new work.
    ShuttingDown,
}

struct JobEntry {
    id: String,
    cancel: Arc<AtomicBool>,
    tx: watch::Sender<JobSnapshot>,
    /// Unary callers currently waiting on this job.
    waiters: AtomicUsize,
    /// Submitted through the Jobs API at least once: never auto-cancelled when waiters leave.
    detached: AtomicBool,
    work: Mutex<Option<Work>>,
}

impl JobEntry {
    fn snapshot(&self) -> JobSnapshot {
        self.tx.borrow().clone()
    }

    fn state(&self) -> JobState {
        self.tx.borrow().state
    }

    /// Moves to a terminal state once; later calls are ignored.
    fn finish(&self, state: JobState, result: Option<Arc<Vec<u8>>>, error: Option<MurkError>) {
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
        });
    }
}

#[derive(Default)]
struct Registry {
    jobs: HashMap<String, Arc<JobEntry>>,
    /// Ids in submission order (oldest first), for listing and record eviction.
    order: VecDeque<String>,
    queue: VecDeque<Arc<JobEntry>>,
    stopped: bool,
}

struct Inner {
    cfg: JobsConfig,
    pool: rayon::ThreadPool,
    cache: ResultCache,
    registry: Mutex<Registry>,
    queue_cv: Condvar,
    shutting_down: AtomicBool,
    executed: AtomicU64,
    running: AtomicUsize,
    idle: Notify,
}

impl Inner {
    fn registry(&self) -> MutexGuard<'_, Registry> {
        // A panic while holding the lock cannot leave the registry inconsistent in a way that
        // matters more than refusing all further work would, so poisoning is ignored.
        self.registry.lock().unwrap_or_else(|p| p.into_inner())
    }
}

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
    /// Marks the job as owned by the Jobs API: it keeps running when unary waiters leave.
    pub fn detach(&self) {
        self.entry.detached.store(true, Ordering::SeqCst);
    }
    /// Registers a unary caller; when the last guard drops before the job is terminal and the
    /// job was never detached, the job is cancelled (the caller went away).
    pub fn attach(&self) -> WaiterGuard {
        self.entry.waiters.fetch_add(1, Ordering::SeqCst);
        WaiterGuard {
            handle: self.clone(),
        }
    }
}

/// Dropping the last one of these cancels an attached-only job. See [`JobHandle::attach`].
pub struct WaiterGuard {
    handle: JobHandle,
}

impl Drop for WaiterGuard {
    fn drop(&mut self) {
        let e = &self.handle.entry;
        if e.waiters.fetch_sub(1, Ordering::SeqCst) == 1
            && !e.detached.load(Ordering::SeqCst)
            && !e.state().is_terminal()
        {
            tracing::info!(id = %e.id, "last caller went away; cancelling job");
            cancel_entry(&self.handle.inner, e);
        }
    }
}

/// The job system. Cheap to clone.
#[derive(Clone)]
pub struct JobManager {
    inner: Arc<Inner>,
}

impl JobManager {
    /// Builds the pool, the cache and the dispatcher threads.
    pub fn new(cfg: JobsConfig) -> std::io::Result<Self> {
        let workers = if cfg.workers == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            cfg.workers
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(workers)
            .thread_name(|i| format!("murk-worker-{i}"))
            .build()
            .map_err(std::io::Error::other)?;
        let cache = ResultCache::new(cfg.cache_bytes, cfg.cache_dir.clone())?;
        let concurrent = cfg.concurrent_jobs.max(1);
        let inner = Arc::new(Inner {
            cfg,
            pool,
            cache,
            registry: Mutex::new(Registry::default()),
            queue_cv: Condvar::new(),
            shutting_down: AtomicBool::new(false),
            executed: AtomicU64::new(0),
            running: AtomicUsize::new(0),
            idle: Notify::new(),
        });
        for i in 0..concurrent {
            let inner = inner.clone();
            std::thread::Builder::new()
                .name(format!("murk-dispatch-{i}"))
                .spawn(move || dispatch_loop(inner))?;
        }
        Ok(Self { inner })
    }

    /// The configuration in force.
    pub fn config(&self) -> &JobsConfig {
        &self.inner.cfg
    }

    /// Threads in the compute pool.
    pub fn worker_threads(&self) -> usize {
        self.inner.pool.current_num_threads()
    }

    /// Number of computations started since creation (cache hits do not count).
    pub fn executed(&self) -> u64 {
        self.inner.executed.load(Ordering::SeqCst)
    }

    /// Jobs waiting in the queue.
    pub fn queued(&self) -> usize {
        self.inner.registry().queue.len()
    }

    /// Cache counters.
    pub fn cache_stats(&self) -> CacheStats {
        self.inner.cache.stats()
    }

    /// The job with this id if it is live or succeeded, or a cached result. Failed and cancelled
    /// jobs are not returned, so resubmitting them runs them again.
    pub fn find(&self, id: &str, method: &str) -> Option<Submitted> {
        let mut reg = self.inner.registry();
        self.find_locked(&mut reg, id, method)
    }

    fn find_locked(&self, reg: &mut Registry, id: &str, method: &str) -> Option<Submitted> {
        if let Some(e) = reg.jobs.get(id) {
            let st = e.state();
            if matches!(
                st,
                JobState::Queued | JobState::Running | JobState::Succeeded
            ) {
                return Some(Submitted {
                    handle: self.handle(e.clone()),
                    cached: st == JobState::Succeeded,
                });
            }
        }
        let bytes = self.inner.cache.get(id)?;
        let entry = self.new_entry(JobSnapshot::from_cache(id, method, bytes), None);
        self.insert_locked(reg, entry.clone());
        Some(Submitted {
            handle: self.handle(entry),
            cached: true,
        })
    }

    /// Any known job (including failed/cancelled ones), or a cached result.
    pub fn get(&self, id: &str) -> Option<JobHandle> {
        let mut reg = self.inner.registry();
        if let Some(e) = reg.jobs.get(id) {
            return Some(self.handle(e.clone()));
        }
        let bytes = self.inner.cache.get(id)?;
        let entry = self.new_entry(JobSnapshot::from_cache(id, "", bytes), None);
        self.insert_locked(&mut reg, entry.clone());
        Some(self.handle(entry))
    }

    /// Queues `work` under `id` unless an identical job is live/succeeded/cached (then that one is
    /// returned and `work` is dropped unrun).
    pub fn submit(&self, id: &str, method: &str, work: Work) -> Result<Submitted, SubmitError> {
        if self.inner.shutting_down.load(Ordering::SeqCst) {
            return Err(SubmitError::ShuttingDown);
        }
        let mut reg = self.inner.registry();
        if let Some(found) = self.find_locked(&mut reg, id, method) {
            return Ok(found);
        }
        if reg.queue.len() >= self.inner.cfg.queue_capacity {
            return Err(SubmitError::QueueFull {
                capacity: self.inner.cfg.queue_capacity,
                retry_after: self.inner.cfg.retry_after,
            });
        }
        let entry = self.new_entry(JobSnapshot::queued(id, method), Some(work));
        self.insert_locked(&mut reg, entry.clone());
        reg.queue.push_back(entry.clone());
        drop(reg);
        self.inner.queue_cv.notify_one();
        tracing::info!(%id, %method, "job queued");
        Ok(Submitted {
            handle: self.handle(entry),
            cached: false,
        })
    }

    /// Requests cancellation. Queued jobs end at once; running ones at their next checkpoint.
    /// `None` for unknown ids.
    pub fn cancel(&self, id: &str) -> Option<JobSnapshot> {
        let entry = self.inner.registry().jobs.get(id).cloned()?;
        cancel_entry(&self.inner, &entry);
        Some(entry.snapshot())
    }

    /// Snapshots of known jobs, newest first: `(page, next_offset)`.
    pub fn list(&self, offset: usize, page_size: usize) -> (Vec<JobSnapshot>, Option<usize>) {
        let reg = self.inner.registry();
        let total = reg.order.len();
        let page: Vec<JobSnapshot> = reg
            .order
            .iter()
            .rev()
            .skip(offset)
            .take(page_size)
            .filter_map(|id| reg.jobs.get(id).map(|e| e.snapshot()))
            .collect();
        let next = offset + page_size;
        (page, (next < total).then_some(next))
    }

    /// Stops accepting work, lets queued and running jobs finish for up to `grace`, then cancels
    /// the rest and stops the dispatchers.
    pub async fn shutdown(&self, grace: Duration) {
        self.inner.shutting_down.store(true, Ordering::SeqCst);
        let deadline = Instant::now() + grace;
        loop {
            // Register interest before checking, so a job finishing in between is not missed.
            let notified = self.inner.idle.notified();
            if self.is_idle() {
                break;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() || tokio::time::timeout(left, notified).await.is_err() {
                break;
            }
        }
        let live: Vec<Arc<JobEntry>> = {
            let mut reg = self.inner.registry();
            reg.stopped = true;
            reg.jobs.values().cloned().collect()
        };
        for e in live {
            if !e.state().is_terminal() {
                cancel_entry(&self.inner, &e);
            }
        }
        self.inner.queue_cv.notify_all();
        // Running jobs stop at their next checkpoint; wait briefly so their state is final.
        let deadline = Instant::now() + Duration::from_secs(5);
        while self.inner.running.load(Ordering::SeqCst) > 0 {
            let notified = self.inner.idle.notified();
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() || tokio::time::timeout(left, notified).await.is_err() {
                break;
            }
        }
    }

    fn is_idle(&self) -> bool {
        self.inner.registry().queue.is_empty() && self.inner.running.load(Ordering::SeqCst) == 0
    }

    fn handle(&self, entry: Arc<JobEntry>) -> JobHandle {
        JobHandle {
            entry,
            inner: self.inner.clone(),
        }
    }

    fn new_entry(&self, snap: JobSnapshot, work: Option<Work>) -> Arc<JobEntry> {
        let (tx, _) = watch::channel(snap.clone());
        Arc::new(JobEntry {
            id: snap.id,
            cancel: Arc::new(AtomicBool::new(false)),
            tx,
            waiters: AtomicUsize::new(0),
            detached: AtomicBool::new(false),
            work: Mutex::new(work),
        })
    }

    fn insert_locked(&self, reg: &mut Registry, entry: Arc<JobEntry>) {
        let id = entry.id.clone();
        if reg.jobs.insert(id.clone(), entry).is_some() {
            reg.order.retain(|x| x != &id);
        }
        reg.order.push_back(id);
        // Forget the oldest terminal records beyond the limit; live jobs are never forgotten.
        let mut i = 0;
        while reg.jobs.len() > self.inner.cfg.max_job_records && i < reg.order.len() {
            let terminal = reg
                .jobs
                .get(&reg.order[i])
                .is_none_or(|e| e.state().is_terminal());
            if terminal {
                if let Some(old) = reg.order.remove(i) {
                    reg.jobs.remove(&old);
                }
            } else {
                i += 1;
            }
        }
    }
}

fn cancel_entry(inner: &Inner, entry: &Arc<JobEntry>) {
    entry.cancel.store(true, Ordering::SeqCst);
    let was_queued = {
        let mut reg = inner.registry();
        let before = reg.queue.len();
        reg.queue.retain(|e| !Arc::ptr_eq(e, entry));
        reg.queue.len() != before
    };
    if was_queued {
        entry.finish(JobState::Cancelled, None, Some(MurkError::Cancelled));
        inner.idle.notify_waiters();
    }
}

fn dispatch_loop(inner: Arc<Inner>) {
    loop {
        let entry = {
            let mut reg = inner.registry();
            loop {
                if let Some(e) = reg.queue.pop_front() {
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
        run_job(&inner, &entry);
        inner.running.fetch_sub(1, Ordering::SeqCst);
        inner.idle.notify_waiters();
    }
}

fn run_job(inner: &Inner, entry: &Arc<JobEntry>) {
    let work = entry.work.lock().unwrap_or_else(|p| p.into_inner()).take();
    let Some(work) = work else {
        entry.finish(
            JobState::Failed,
            None,
            Some(MurkError::Internal("job has no work attached".into())),
        );
        return;
    };
    if entry.cancel.load(Ordering::SeqCst) {
        entry.finish(JobState::Cancelled, None, Some(MurkError::Cancelled));
        return;
    }
    let span = tracing::info_span!("job", id = %entry.id);
    let _enter = span.enter();
    entry.tx.send_modify(|s| {
        s.state = JobState::Running;
        s.start_time = Some(SystemTime::now());
        s.stage = "starting".into();
    });
    inner.executed.fetch_add(1, Ordering::SeqCst);
    let started = Instant::now();
    let progress_entry = entry.clone();
    let sink: ProgressSink = Arc::new(move |stage: &str, fraction: f32| {
        progress_entry.tx.send_if_modified(|s| {
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
    let elapsed_ms = started.elapsed().as_secs_f64() * 1e3;
    match outcome {
        Ok(Ok(bytes)) => {
            let bytes = Arc::new(bytes);
            inner.cache.put(&entry.id, bytes.clone());
            entry.finish(JobState::Succeeded, Some(bytes), None);
            tracing::info!(elapsed_ms, "job succeeded");
        }
        Ok(Err(MurkError::Cancelled)) => {
            entry.finish(JobState::Cancelled, None, Some(MurkError::Cancelled));
            tracing::info!(elapsed_ms, "job cancelled");
        }
        Ok(Err(e)) => {
            tracing::warn!(elapsed_ms, error = %e, "job failed");
            entry.finish(JobState::Failed, None, Some(e));
        }
        Err(panic) => {
            let msg = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            tracing::error!(elapsed_ms, panic = %msg, "job panicked");
            entry.finish(
                JobState::Failed,
                None,
                Some(MurkError::Internal(format!("worker panicked: {msg}"))),
            );
        }
    }
}
