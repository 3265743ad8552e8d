//! The job manager: a bounded queue (one FIFO per method, served by least compute time received
//! so short jobs do not starve behind long ones), dispatcher threads that run jobs on a rayon pool, and the
//! registry that deduplicates identical requests by their content-hash id.
//!
//! Job records belong to a tenant (the authenticated caller; `""` when authentication is off):
//! the registry is keyed by `(tenant, id)`, so another tenant's Get/Watch/Cancel never reaches a
//! record it does not own. Results are shared across tenants through the cache, which is keyed
//! by the content hash alone: identical work computes once, but records are never shared.
//!
//! Retry safety: a record whose cancellation was requested (or that ended cancelled, failed or
//! aborted) is never handed to a new submission; an identical request submitted then starts a
//! fresh computation under the same id.
//!
//! Why dispatcher threads in front of rayon instead of `pool.spawn` per job: rayon's own queue
//! is unbounded and work-stealing may start a second job inside a first job's `join`, so a fixed
//! number of dispatchers (`concurrent_jobs`) each `install` one job at a time on the shared pool;
//! the algorithms' inner `par_iter`s use all the pool's threads.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::panic::AssertUnwindSafe;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant, SystemTime};

use tokio::sync::{watch, Notify};

use super::cache::{CacheStats, ResultCache};
use super::journal::{Journal, JournalEntry};
use super::metrics::JobMetrics;
use super::record_log::{LoggedRecord, RecordLog};
use super::state::{JobSnapshot, JobState};
use crate::error::MurkError;
use crate::monitor::{Monitor, ProgressSink};

/// The computation of one job: returns the encoded result message.
pub type Work = Box<dyn FnOnce(&Monitor) -> Result<Vec<u8>, MurkError> + Send + 'static>;

/// Default bound of the cache directory: 8 GiB.
pub const DEFAULT_CACHE_DIR_BYTES: u64 = 8 << 30;

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
    /// Optional directory where results persist across restarts. It also holds the journal of
    /// accepted jobs (`journal/`), so queued and running jobs survive a crash.
    pub cache_dir: Option<PathBuf>,
    /// Largest total size of the entry files in `cache_dir`; least recently used go first.
    pub cache_dir_bytes: u64,
    /// Smallest client back-off suggested when the queue is full; the hint is the estimated
    /// time until a slot frees when that is longer, +0–50 % jitter.
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
            cache_dir_bytes: DEFAULT_CACHE_DIR_BYTES,
            retry_after: Duration::from_millis(500),
            max_job_records: 10_000,
        }
    }
}

/// Why the job system refused a call (a submission, or with a shared backend any call).
#[derive(Debug, Clone, PartialEq)]
pub enum JobsError {
    /// The queue holds `capacity` jobs already; retry after `retry_after`.
    QueueFull {
        /// Queue capacity.
        capacity: usize,
        /// Suggested back-off.
        retry_after: Duration,
    },
    /// The server is shutting down and accepts no new work.
    ShuttingDown,
    /// The shared job store (Redis) cannot be reached; the call may succeed later.
    Unavailable(String),
}

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
type JobKey = (String, String);

/// Why a job's cancel flag was raised.
const CANCEL_BY_CALLER: u8 = 0;
const CANCEL_BY_SHUTDOWN: u8 = 1;

struct JobEntry {
    id: String,
    tenant: String,
    method: String,
    cancel: Arc<AtomicBool>,
    /// `CANCEL_BY_*`: what raised `cancel`, so shutdown ends jobs as retryable aborts rather
    /// than as user cancels.
    cancel_reason: std::sync::atomic::AtomicU8,
    tx: watch::Sender<JobSnapshot>,
    /// Unary callers currently waiting on this job.
    waiters: AtomicUsize,
    /// Submitted through the Jobs API at least once: never auto-cancelled when waiters leave.
    detached: AtomicBool,
    /// Has a journal file to remove when it ends.
    journaled: AtomicBool,
    work: Mutex<Option<Work>>,
    /// Set for a view of a job in a shared store: waiter and detach changes go there.
    remote: Option<Arc<dyn RemoteJob>>,
    /// Orders the waiter-count updates sent to `remote`.
    waiter_seq: AtomicU64,
}

impl JobEntry {
    fn snapshot(&self) -> JobSnapshot {
        self.tx.borrow().clone()
    }

    fn state(&self) -> JobState {
        self.tx.borrow().state
    }

    fn key(&self) -> JobKey {
        (self.tenant.clone(), self.id.clone())
    }

    /// True once cancellation was requested; such a record is never reused by a new submission.
    fn cancelling(&self) -> bool {
        self.cancel.load(Ordering::SeqCst)
    }

    /// The terminal state and error of a job stopped through its cancel flag: a user cancel, or
    /// a retryable abort when the server stopped it on shutdown.
    fn stopped_outcome(&self) -> (JobState, MurkError) {
        if self.cancel_reason.load(Ordering::SeqCst) == CANCEL_BY_SHUTDOWN {
            (JobState::Failed, MurkError::ShuttingDown)
        } else {
            (JobState::Cancelled, MurkError::Cancelled)
        }
    }

    /// Moves to a terminal state once; later calls are ignored. True if this call did it.
    fn finish(
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

/// Waiting jobs: one FIFO per method. The next job comes from the waiting method that has
/// received the least compute time (fair queuing by time, not by job count): a method of
/// millisecond jobs is not held to one job per multi-second job of another. A method that comes
/// back after its queue ran empty starts level with the least-served active method, so idle time
/// earns no credit.
#[derive(Default)]
struct FairQueue {
    by_method: BTreeMap<String, VecDeque<Arc<JobEntry>>>,
    /// Compute seconds charged to each method.
    served: HashMap<String, f64>,
    len: usize,
}

impl FairQueue {
    fn push(&mut self, e: Arc<JobEntry>) {
        let q = self.by_method.entry(e.method.clone()).or_default();
        if q.is_empty() {
            let level = self
                .by_method
                .iter()
                .filter(|(m, q)| !q.is_empty() && **m != e.method)
                .filter_map(|(m, _)| self.served.get(m))
                .copied()
                .fold(f64::INFINITY, f64::min);
            let own = self.served.entry(e.method.clone()).or_insert(0.0);
            if level.is_finite() && *own < level {
                *own = level;
            }
        }
        self.by_method
            .get_mut(&e.method)
            .expect("inserted above")
            .push_back(e);
        self.len += 1;
    }

    fn pop(&mut self) -> Option<Arc<JobEntry>> {
        let served = &self.served;
        let method = self
            .by_method
            .iter()
            .filter(|(_, q)| !q.is_empty())
            .map(|(m, _)| (m, served.get(m).copied().unwrap_or(0.0)))
            .min_by(|a, b| a.1.total_cmp(&b.1))?
            .0
            .clone();
        let e = self.by_method.get_mut(&method)?.pop_front()?;
        self.len -= 1;
        Some(e)
    }

    /// Charges `seconds` of compute to `method`.
    fn charge(&mut self, method: &str, seconds: f64) {
        *self.served.entry(method.to_string()).or_insert(0.0) += seconds;
    }

    fn remove(&mut self, entry: &Arc<JobEntry>) -> bool {
        let Some(q) = self.by_method.get_mut(&entry.method) else {
            return false;
        };
        let before = q.len();
        q.retain(|e| !Arc::ptr_eq(e, entry));
        let removed = before - q.len();
        self.len -= removed;
        removed > 0
    }

    fn len(&self) -> usize {
        self.len
    }

    fn is_empty(&self) -> bool {
        self.len == 0
    }
}

#[derive(Default)]
struct Registry {
    jobs: HashMap<JobKey, Arc<JobEntry>>,
    /// Keys in submission order (oldest first), for listing and record eviction.
    order: VecDeque<JobKey>,
    queue: FairQueue,
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
    metrics: JobMetrics,
    /// Exponential moving average of compute time per method, seconds.
    mean_secs: Mutex<HashMap<String, f64>>,
    /// Method and start of every job being computed, by dispatcher.
    in_progress: Mutex<HashMap<usize, (String, Instant)>>,
    /// Accepted jobs on disk (with a cache directory).
    journal: Option<Journal>,
    /// Finished records across restarts (`--cache-dir/records.log`), once
    /// [`JobManager::restore_records`] opened it (the embedded default; not in Redis mode).
    record_log: OnceLock<RecordLog>,
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
    /// Replaces a view's snapshot (see [`JobManager::view`]); a terminal snapshot is final.
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
        let cache = ResultCache::with_disk_bound(
            cfg.cache_bytes,
            cfg.cache_dir.clone(),
            cfg.cache_dir_bytes,
        )?;
        let journal = match &cfg.cache_dir {
            Some(d) => Some(Journal::open(&d.join("journal"))?),
            None => None,
        };
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
            metrics: JobMetrics::default(),
            mean_secs: Mutex::new(HashMap::new()),
            in_progress: Mutex::new(HashMap::new()),
            journal,
            record_log: OnceLock::new(),
        });
        for i in 0..concurrent {
            let inner = inner.clone();
            std::thread::Builder::new()
                .name(format!("murk-dispatch-{i}"))
                .spawn(move || dispatch_loop(inner, i))?;
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

    /// Jobs computing now.
    pub fn running(&self) -> usize {
        self.inner.running.load(Ordering::SeqCst)
    }

    /// The event metrics (register them with a Prometheus registry to export them).
    pub fn metrics(&self) -> &JobMetrics {
        &self.inner.metrics
    }

    /// `tenant`'s job with this id if it is live (and not being cancelled) or succeeded, or a
    /// cached result. Failed, cancelled and cancelling jobs are not returned, so resubmitting
    /// them runs them again.
    pub fn find(&self, tenant: &str, id: &str, method: &str) -> Option<Submitted> {
        let mut reg = self.inner.registry();
        self.find_locked(&mut reg, tenant, id, method)
    }

    fn find_locked(
        &self,
        reg: &mut Registry,
        tenant: &str,
        id: &str,
        method: &str,
    ) -> Option<Submitted> {
        let key = (tenant.to_string(), id.to_string());
        if let Some(e) = self.hydrated(reg, &key) {
            let st = e.state();
            let reusable = match st {
                JobState::Succeeded => true,
                JobState::Queued | JobState::Running => !e.cancelling(),
                JobState::Failed | JobState::Cancelled => false,
            };
            if reusable {
                if st == JobState::Succeeded {
                    self.inner.metrics.cache_hits.inc();
                }
                return Some(Submitted {
                    handle: self.handle(e.clone()),
                    cached: st == JobState::Succeeded,
                });
            }
        }
        let bytes = self.inner.cache.get(id)?;
        self.inner.metrics.cache_hits.inc();
        let entry = self.new_entry(tenant, JobSnapshot::from_cache(id, method, bytes), None);
        // An authenticated tenant's record of a cache hit is its own: keep it across restarts
        // (the default tenant's comes back from the cache anyway). Not fsynced: a killed
        // process keeps it, and this is the hot path of repeated requests.
        if !tenant.is_empty() {
            if let Some(log) = self.inner.record_log.get() {
                let snap = entry.snapshot();
                if let Some(r) = LoggedRecord::ended(tenant, &snap, snap.state, None) {
                    if let Err(e) = log.append(&r, false) {
                        tracing::warn!(%id, error = %e, "could not log the job record");
                    }
                }
                compact_if_grown(&self.inner, log, reg);
            }
        }
        self.insert_locked(reg, entry.clone());
        Some(Submitted {
            handle: self.handle(entry),
            cached: true,
        })
    }

    /// `tenant`'s job with this id (in any state). Another tenant's job is `None`, exactly like
    /// an unknown id: knowing an id (from a log line, say) gives no access. Without
    /// authentication (the default tenant `""`) a result in the cache without a record (e.g.
    /// after a restart) is returned as a succeeded job; an authenticated tenant reaches such a
    /// result by resubmitting its request, which is a cache hit.
    pub fn get(&self, tenant: &str, id: &str) -> Option<JobHandle> {
        let mut reg = self.inner.registry();
        if let Some(e) = self.hydrated(&mut reg, &(tenant.to_string(), id.to_string())) {
            return Some(self.handle(e));
        }
        if !tenant.is_empty() {
            return None;
        }
        let bytes = self.inner.cache.get(id)?;
        let entry = self.new_entry(tenant, JobSnapshot::from_cache(id, "", bytes), None);
        self.insert_locked(&mut reg, entry.clone());
        Some(self.handle(entry))
    }

    /// Queues `work` under `(tenant, id)` unless that tenant's identical job is live/succeeded or
    /// the result is cached (then that one is returned and `work` is dropped unrun).
    pub fn submit(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
        work: Work,
    ) -> Result<Submitted, JobsError> {
        self.submit_durable(tenant, id, method, work, None)
    }

    /// True when accepted jobs are journalled (a cache directory is configured): callers then
    /// pass the request's bytes to [`JobManager::submit_durable`].
    pub fn journaling(&self) -> bool {
        self.inner.journal.is_some()
    }

    /// [`JobManager::submit`] that, with a journal, writes `request` (the bytes
    /// [`JobManager::recover`]'s rebuild function understands) to disk before the job is
    /// accepted, so it survives a crash.
    pub fn submit_durable(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
        work: Work,
        request: Option<Vec<u8>>,
    ) -> Result<Submitted, JobsError> {
        if self.inner.shutting_down.load(Ordering::SeqCst) {
            return Err(JobsError::ShuttingDown);
        }
        {
            let mut reg = self.inner.registry();
            if let Some(found) = self.find_locked(&mut reg, tenant, id, method) {
                return Ok(found);
            }
            if reg.queue.len() >= self.inner.cfg.queue_capacity {
                drop(reg);
                return Err(self.refusal());
            }
        }
        // The fsync happens outside the registry lock; the checks are repeated after it.
        let record = match (&self.inner.journal, request) {
            (Some(j), Some(request)) => {
                let entry = JournalEntry {
                    tenant: tenant.to_string(),
                    id: id.to_string(),
                    method: method.to_string(),
                    request,
                };
                match j.record(&entry) {
                    Ok(()) => Some(entry),
                    Err(e) => {
                        // Not durable, but still correct: serve it, and say so.
                        tracing::error!(%id, error = %e, "could not journal the job; it will not survive a crash");
                        None
                    }
                }
            }
            _ => None,
        };
        let journaled = record.is_some();
        let mut reg = self.inner.registry();
        if let Some(found) = self.find_locked(&mut reg, tenant, id, method) {
            // A twin got in first: its record (same tenant and id) owns the journal file when it
            // is live; a finished result needs none.
            if journaled && found.cached {
                self.forget_journal(tenant, id);
            }
            return Ok(found);
        }
        if reg.queue.len() >= self.inner.cfg.queue_capacity {
            drop(reg);
            if journaled {
                self.forget_journal(tenant, id);
            }
            return Err(self.refusal());
        }
        let entry = self.new_entry(tenant, JobSnapshot::queued(id, method), Some(work));
        entry.journaled.store(journaled, Ordering::SeqCst);
        self.insert_locked(&mut reg, entry.clone());
        reg.queue.push(entry.clone());
        self.inner.metrics.cache_misses.inc();
        drop(reg);
        // A cancelled twin (same tenant and id) that ended between the journal write and the
        // insert may have removed the file; from the insert on it no longer can.
        if let (Some(j), Some(e)) = (&self.inner.journal, &record) {
            if !j.contains(tenant, id) {
                if let Err(err) = j.record(e) {
                    tracing::error!(%id, error = %err, "could not journal the job; it will not survive a crash");
                }
            }
        }
        self.inner.queue_cv.notify_one();
        tracing::info!(%id, %method, %tenant, journaled, "job queued");
        Ok(Submitted {
            handle: self.handle(entry),
            cached: false,
        })
    }

    /// The registry's entry for `key`, with the result of a succeeded record restored from the
    /// record log loaded from the cache; such a record whose result the cache no longer holds
    /// is forgotten (`None`: a resubmission recomputes it).
    fn hydrated(&self, reg: &mut Registry, key: &JobKey) -> Option<Arc<JobEntry>> {
        let e = reg.jobs.get(key)?.clone();
        let needs_result = {
            let s = e.tx.borrow();
            s.state == JobState::Succeeded && s.result.is_none()
        };
        if !needs_result {
            return Some(e);
        }
        match self.inner.cache.get(&e.id) {
            Some(bytes) => {
                e.tx.send_modify(|s| s.result = Some(bytes));
                Some(e)
            }
            None => {
                reg.jobs.remove(key);
                reg.order.retain(|k| k != key);
                None
            }
        }
    }

    /// Brings back the records of jobs that ended before the last stop or crash, from
    /// `--cache-dir/records.log` (at most `max_job_records`, the newest), and from now on logs
    /// every job's end there. Call once at start, after [`JobManager::recover`] (a re-queued job
    /// takes precedence over an old record of the same id). Returns the number restored; 0
    /// without a cache directory.
    pub fn restore_records(&self) -> std::io::Result<usize> {
        let Some(dir) = &self.inner.cfg.cache_dir else {
            return Ok(0);
        };
        let log = RecordLog::open(&dir.join("records.log"))?;
        let mut records = log.load()?;
        let keep = self.inner.cfg.max_job_records;
        if records.len() > keep {
            records.drain(..records.len() - keep);
        }
        let mut restored = 0;
        {
            let mut reg = self.inner.registry();
            for r in &records {
                let Some(snap) = r.snapshot() else { continue };
                let key = (r.tenant.clone(), r.id.clone());
                if reg.jobs.contains_key(&key) {
                    continue;
                }
                let entry = self.new_entry(&r.tenant, snap, None);
                self.insert_locked(&mut reg, entry);
                restored += 1;
            }
        }
        log.rewrite(&records)?;
        let _ = self.inner.record_log.set(log);
        if restored > 0 {
            tracing::info!(restored, "restored finished job records");
        }
        Ok(restored)
    }

    fn forget_journal(&self, tenant: &str, id: &str) {
        if let Some(j) = &self.inner.journal {
            j.remove(tenant, id);
        }
    }

    /// Re-queues the jobs the journal holds (accepted before a crash or a shutdown, not
    /// finished), rebuilding each job's work from its request bytes with `rebuild(method,
    /// bytes)`. Jobs whose result is cached meanwhile, or that cannot be rebuilt, are dropped
    /// from the journal. The queue bound does not apply: these jobs were accepted already.
    /// Returns the number re-queued.
    pub fn recover(&self, rebuild: impl Fn(&str, &[u8]) -> Result<Work, MurkError>) -> usize {
        let Some(journal) = &self.inner.journal else {
            return 0;
        };
        let mut requeued = 0;
        for e in journal.load() {
            if self.inner.cache.get(&e.id).is_some() {
                journal.remove(&e.tenant, &e.id);
                continue;
            }
            let work = match rebuild(&e.method, &e.request) {
                Ok(w) => w,
                Err(err) => {
                    tracing::warn!(id = %e.id, error = %err, "journalled job cannot be rebuilt; dropped");
                    journal.remove(&e.tenant, &e.id);
                    continue;
                }
            };
            let entry =
                self.new_entry(&e.tenant, JobSnapshot::queued(&e.id, &e.method), Some(work));
            entry.journaled.store(true, Ordering::SeqCst);
            // Its submitter may be gone; nobody is waiting to cancel it.
            entry.detached.store(true, Ordering::SeqCst);
            let mut reg = self.inner.registry();
            if reg.jobs.contains_key(&entry.key()) {
                continue;
            }
            self.insert_locked(&mut reg, entry.clone());
            reg.queue.push(entry);
            requeued += 1;
        }
        if requeued > 0 {
            tracing::info!(requeued, "re-queued journalled jobs");
            self.inner.queue_cv.notify_all();
        }
        requeued
    }

    /// The back-off to suggest when the queue is full: the estimated time until a slot frees,
    /// i.e. until the first running job ends (its method's mean compute time minus the time it
    /// has run), at least the configured minimum and at most 5 minutes, spread over +0–50 % so
    /// refused clients do not come back in one herd. Waiting for the whole queue to drain
    /// instead would keep clients of short jobs away long after the long ones are done.
    fn retry_hint(&self) -> Duration {
        let now = Instant::now();
        let next_free = {
            let means = lock(&self.inner.mean_secs);
            lock(&self.inner.in_progress)
                .values()
                .map(|(method, started)| {
                    let mean = means.get(method).copied().unwrap_or(0.0);
                    (mean - now.duration_since(*started).as_secs_f64()).max(0.0)
                })
                .fold(f64::INFINITY, f64::min)
        };
        let floor = self.inner.cfg.retry_after.as_secs_f64();
        let estimate = if next_free.is_finite() {
            next_free
        } else {
            0.0
        };
        let base = estimate.clamp(floor, floor.max(300.0));
        let jitter = 1.0 + 0.5 * rand::random::<f64>();
        Duration::from_secs_f64(base * jitter)
    }

    /// The refusal a submission gets while the queue is full, with the current retry hint.
    pub fn refusal(&self) -> JobsError {
        JobsError::QueueFull {
            capacity: self.inner.cfg.queue_capacity,
            retry_after: self.retry_hint(),
        }
    }

    /// True when the queue has no free slot (a cheap pre-check before decoding a request).
    pub fn queue_full(&self) -> bool {
        self.inner.registry().queue.len() >= self.inner.cfg.queue_capacity
    }

    /// Requests cancellation of `tenant`'s job. Queued jobs end at once; running ones at their
    /// next checkpoint. `None` for unknown ids (and other tenants' jobs).
    pub fn cancel(&self, tenant: &str, id: &str) -> Option<JobSnapshot> {
        let entry = self
            .inner
            .registry()
            .jobs
            .get(&(tenant.to_string(), id.to_string()))
            .cloned()?;
        cancel_entry(&self.inner, &entry, CANCEL_BY_CALLER);
        Some(entry.snapshot())
    }

    /// Snapshots of `tenant`'s known jobs, newest first: `(page, next_offset)`.
    pub fn list(
        &self,
        tenant: &str,
        offset: usize,
        page_size: usize,
    ) -> (Vec<JobSnapshot>, Option<usize>) {
        let reg = self.inner.registry();
        let mut own = reg.order.iter().rev().filter(|(t, _)| t == tenant);
        let page: Vec<JobSnapshot> = own
            .by_ref()
            .skip(offset)
            .take(page_size)
            .filter_map(|k| reg.jobs.get(k).map(|e| e.snapshot()))
            .collect();
        let more = own.next().is_some();
        (page, more.then_some(offset + page_size))
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
                cancel_entry(&self.inner, &e, CANCEL_BY_SHUTDOWN);
            }
        }
        self.inner.queue_cv.notify_all();
        // Running jobs stop at their next checkpoint (every stage checks within 250 ms); wait
        // briefly so their state is final, but never so long that the process overstays its
        // grace period by more than a second.
        let deadline = Instant::now() + Duration::from_millis(750);
        while self.inner.running.load(Ordering::SeqCst) > 0 {
            let notified = self.inner.idle.notified();
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() || tokio::time::timeout(left, notified).await.is_err() {
                break;
            }
        }
    }

    /// The result cache (memory, and disk with a cache directory).
    pub(crate) fn cache(&self) -> &ResultCache {
        &self.inner.cache
    }

    /// True once shutdown began.
    pub(crate) fn shutting_down(&self) -> bool {
        self.inner.shutting_down.load(Ordering::SeqCst)
    }

    /// A handle on a job that lives elsewhere (a shared store): not in the local registry, its
    /// snapshots come from [`JobHandle::publish`], and waiter/detach changes go to `remote`.
    pub(crate) fn view(
        &self,
        tenant: &str,
        snap: JobSnapshot,
        remote: Arc<dyn RemoteJob>,
    ) -> JobHandle {
        let mut entry = self.new_entry(tenant, snap, None);
        Arc::get_mut(&mut entry)
            .expect("entry not shared yet")
            .remote = Some(remote);
        self.handle(entry)
    }

    /// Runs `work` here for a job claimed from a shared queue: it bypasses the local queue
    /// bound (the claimer takes work only when a dispatcher is free) and is never cancelled for
    /// lack of local waiters. A live local record of the same job is returned as is.
    pub(crate) fn run_claimed(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
        work: Work,
    ) -> Result<JobHandle, JobsError> {
        if self.shutting_down() {
            return Err(JobsError::ShuttingDown);
        }
        let mut reg = self.inner.registry();
        if let Some(e) = reg.jobs.get(&(tenant.to_string(), id.to_string())) {
            if !e.state().is_terminal() && !e.cancelling() {
                return Ok(self.handle(e.clone()));
            }
        }
        let entry = self.new_entry(tenant, JobSnapshot::queued(id, method), Some(work));
        entry.detached.store(true, Ordering::SeqCst);
        self.insert_locked(&mut reg, entry.clone());
        reg.queue.push(entry.clone());
        drop(reg);
        self.inner.queue_cv.notify_one();
        Ok(self.handle(entry))
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

    fn new_entry(&self, tenant: &str, snap: JobSnapshot, work: Option<Work>) -> Arc<JobEntry> {
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

    fn insert_locked(&self, reg: &mut Registry, entry: Arc<JobEntry>) {
        let key = entry.key();
        if reg.jobs.insert(key.clone(), entry).is_some() {
            reg.order.retain(|x| x != &key);
        }
        reg.order.push_back(key);
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

fn cancel_entry(inner: &Inner, entry: &Arc<JobEntry>, reason: u8) {
    if !entry.cancel.swap(true, Ordering::SeqCst) {
        entry.cancel_reason.store(reason, Ordering::SeqCst);
    }
    let was_queued = inner.registry().queue.remove(entry);
    if was_queued {
        let (state, error) = entry.stopped_outcome();
        finish(inner, entry, state, None, Some(error));
        inner.idle.notify_waiters();
    }
}

/// Moves `entry` to a terminal state and counts it.
fn finish(
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
fn compact_if_grown(inner: &Inner, log: &RecordLog, reg: &Registry) {
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
fn record_compute_time(inner: &Inner, method: &str, seconds: f64) {
    lock(&inner.mean_secs)
        .entry(method.to_string())
        .and_modify(|m| *m = 0.8 * *m + 0.2 * seconds)
        .or_insert(seconds);
}

/// Locks a mutex whose data stays consistent even if a holder panicked (plain maps of numbers).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

fn dispatch_loop(inner: Arc<Inner>, slot: usize) {
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

fn run_job(inner: &Inner, entry: &Arc<JobEntry>) {
    let work = entry.work.lock().unwrap_or_else(|p| p.into_inner()).take();
    let Some(work) = work else {
        finish(
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
        finish(inner, entry, state, None, Some(error));
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
            finish(inner, entry, JobState::Succeeded, Some(bytes), None);
            tracing::info!(elapsed_ms, "job succeeded");
        }
        Ok(Err(MurkError::Cancelled)) => {
            let (state, error) = entry.stopped_outcome();
            tracing::info!(elapsed_ms, reason = %error, "job stopped");
            finish(inner, entry, state, None, Some(error));
        }
        Ok(Err(e)) => {
            tracing::warn!(elapsed_ms, error = %e, "job failed");
            finish(inner, entry, JobState::Failed, None, Some(e));
        }
        Err(panic) => {
            let msg = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            tracing::error!(elapsed_ms, panic = %msg, "job panicked");
            finish(
                inner,
                entry,
                JobState::Failed,
                None,
                Some(MurkError::Internal(format!("worker panicked: {msg}"))),
            );
        }
    }
}
