//! The job manager: the face of the job system. It accepts work into the bounded, fair queue
//! (`queue.rs`) unless an identical request (same tenant, same content-hash id) is live or its
//! result is cached (`registry.rs`, `cache.rs`), journals it for crashes, and hands out handles
//! (`handle.rs`); dispatcher threads (`dispatch.rs`) compute it on a rayon pool.
//!
//! Retry safety: a record whose cancellation was requested (or that ended cancelled, failed or
//! aborted) is never handed to a new submission; an identical request submitted then starts a
//! fresh computation under the same id.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

use super::cache::{CacheStats, ResultCache};
use super::config::JobsConfig;
use super::dispatch::dispatch_loop;
use super::entry::{JobEntry, RemoteJob, Work, CANCEL_BY_CALLER, CANCEL_BY_SHUTDOWN};
use super::handle::{JobHandle, Submitted};
use super::journal::{Journal, JournalEntry};
use super::metrics::JobMetrics;
use super::record_log::{LoggedRecord, RecordLog};
use super::registry::Registry;
use super::shared::{cancel_entry, compact_if_grown, lock, Inner};
use super::state::{JobSnapshot, JobState};
use murk::error::MurkError;

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

    /// Runs `f` on the compute pool (blocking the calling thread), where its parallel loops
    /// share the cores with the jobs: the sessions' frames run here.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.inner.pool.install(f)
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
        if let Some(e) = reg.hydrated(&key, &self.inner.cache) {
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
        let entry = JobEntry::new(tenant, JobSnapshot::from_cache(id, method, bytes), None);
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
        reg.insert(entry.clone(), self.inner.cfg.max_job_records);
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
        if let Some(e) = reg.hydrated(&(tenant.to_string(), id.to_string()), &self.inner.cache) {
            return Some(self.handle(e));
        }
        if !tenant.is_empty() {
            return None;
        }
        let bytes = self.inner.cache.get(id)?;
        let entry = JobEntry::new(tenant, JobSnapshot::from_cache(id, "", bytes), None);
        reg.insert(entry.clone(), self.inner.cfg.max_job_records);
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
        let entry = JobEntry::new(tenant, JobSnapshot::queued(id, method), Some(work));
        entry.journaled.store(journaled, Ordering::SeqCst);
        reg.insert(entry.clone(), self.inner.cfg.max_job_records);
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
                let entry = JobEntry::new(&r.tenant, snap, None);
                reg.insert(entry, self.inner.cfg.max_job_records);
                restored += 1;
            }
        }
        log.rewrite(&records)?;
        // Jobs `recover` found lost: durable in the log first, then their journal entries go.
        let lost: Vec<Arc<JobEntry>> = self
            .inner
            .registry()
            .jobs
            .values()
            .filter(|e| e.state().is_terminal() && e.journaled.load(Ordering::SeqCst))
            .cloned()
            .collect();
        for e in lost {
            let snap = e.snapshot();
            if let Some(r) = LoggedRecord::ended(&e.tenant, &snap, snap.state, snap.error.as_ref())
            {
                log.append(&r, true)?;
            }
            self.forget_journal(&e.tenant, &e.id);
            e.journaled.store(false, Ordering::SeqCst);
        }
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
    /// bytes)`. Jobs whose result is cached meanwhile are dropped from the journal. A job whose
    /// entry is damaged or cannot be rebuilt was accepted and is lost: it gets a FAILED record
    /// with a DATA_LOSS error that says to resubmit, which [`JobManager::restore_records`] makes
    /// durable before the entry is removed, so a client polling it learns what happened instead
    /// of NOT_FOUND. The queue bound does not apply: these jobs were accepted already.
    /// Returns the number re-queued.
    pub fn recover(&self, rebuild: impl Fn(&str, &[u8]) -> Result<Work, MurkError>) -> usize {
        let Some(journal) = &self.inner.journal else {
            return 0;
        };
        let loaded = journal.load();
        for d in &loaded.damaged {
            self.record_lost(
                &d.tenant,
                &d.id,
                "",
                "its journal entry was corrupted on disk",
            );
        }
        let mut requeued = 0;
        for e in loaded.entries {
            if self.inner.cache.get(&e.id).is_some() {
                journal.remove(&e.tenant, &e.id);
                continue;
            }
            let work = match rebuild(&e.method, &e.request) {
                Ok(w) => w,
                Err(err) => {
                    tracing::warn!(id = %e.id, error = %err, "journalled job cannot be rebuilt; recorded as lost");
                    self.record_lost(
                        &e.tenant,
                        &e.id,
                        &e.method,
                        &format!("its journal entry cannot be rebuilt ({err})"),
                    );
                    continue;
                }
            };
            let entry = JobEntry::new(&e.tenant, JobSnapshot::queued(&e.id, &e.method), Some(work));
            entry.journaled.store(true, Ordering::SeqCst);
            // Its submitter may be gone; nobody is waiting to cancel it.
            entry.detached.store(true, Ordering::SeqCst);
            let mut reg = self.inner.registry();
            if reg.jobs.contains_key(&entry.key()) {
                continue;
            }
            reg.insert(entry.clone(), self.inner.cfg.max_job_records);
            reg.queue.push(entry);
            requeued += 1;
        }
        if requeued > 0 {
            tracing::info!(requeued, "re-queued journalled jobs");
            self.inner.queue_cv.notify_all();
        }
        requeued
    }

    /// A FAILED record for an accepted job whose journal entry is unusable. It keeps the
    /// `journaled` flag: the entry is removed once the record is in the record log.
    fn record_lost(&self, tenant: &str, id: &str, method: &str, why: &str) {
        let mut snap = JobSnapshot::queued(id, method);
        snap.state = JobState::Failed;
        snap.stage = "failed".into();
        snap.end_time = Some(std::time::SystemTime::now());
        snap.error = Some(MurkError::DataLoss(why.to_string()));
        let entry = JobEntry::new(tenant, snap, None);
        entry.journaled.store(true, Ordering::SeqCst);
        let mut reg = self.inner.registry();
        if !reg.jobs.contains_key(&entry.key()) {
            reg.insert(entry, self.inner.cfg.max_job_records);
        }
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
        let mut entry = JobEntry::new(tenant, snap, None);
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
        let entry = JobEntry::new(tenant, JobSnapshot::queued(id, method), Some(work));
        entry.detached.store(true, Ordering::SeqCst);
        reg.insert(entry.clone(), self.inner.cfg.max_job_records);
        reg.queue.push(entry.clone());
        drop(reg);
        self.inner.queue_cv.notify_one();
        Ok(self.handle(entry))
    }

    fn is_idle(&self) -> bool {
        self.inner.registry().queue.is_empty() && self.inner.running.load(Ordering::SeqCst) == 0
    }

    fn handle(&self, entry: Arc<JobEntry>) -> JobHandle {
        JobHandle::new(entry, self.inner.clone())
    }
}
