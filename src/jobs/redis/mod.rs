//! The shared job backend on Redis: any number of `murk serve --redis-url …` replicas share one
//! job registry, one bounded work queue and one result cache, so a job submitted to replica A
//! can be watched, fetched or cancelled through replica B, and a job whose replica died is
//! computed by another.
//!
//! Layout (all keys under a configurable prefix, `murk` by default):
//! - `{p}:job:{tenant}:{id}`: the job record, a hash (see [`scripts`] for its fields). Records of
//!   finished jobs expire after `record_ttl`.
//! - `{p}:jobs:{tenant}`: the tenant's job ids by creation time (ListJobs), capped per tenant.
//! - `{p}:queue`: the work queue, a Redis Stream read by the consumer group `workers`. An entry
//!   carries the canonical request, so any replica can rebuild the work. A replica reads only
//!   while it has a free compute slot; the entry stays pending (its lease) until the result is
//!   stored, and the replica renews that lease while it computes. Entries of a replica that
//!   stopped renewing are taken over with `XAUTOCLAIM` and recomputed: safe, because results
//!   are deterministic and ids are content hashes.
//! - `{p}:queued`: jobs accepted but not started, for the global queue bound.
//! - `{p}:result:{id}`: result bytes, shared across tenants like the local cache, with a TTL so
//!   that Redis's `maxmemory-policy volatile-lru` evicts results (and finished records) but
//!   never the queue. The local memory/disk cache reads through.
//! - `{p}:events`: pub/sub channel: `u\t{tenant}\t{id}` when a record changed, `c\t…` when a
//!   running job must stop; every replica listens, refreshes the views its callers watch, and
//!   stops the jobs it runs.
//!
//! Why Redis Streams directly rather than a job library (e.g. `apalis-redis`): murk needs
//! content-hash deduplication per tenant, cancellation of a *running* job from any replica,
//! progress visible from any replica, and a global queue bound answered at submit time; those
//! live in the job record next to the queue entry and must change atomically with it, which the
//! Lua scripts here do. A library's own job table would duplicate the record.

mod events;
mod record;
mod scripts;
mod worker;

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use async_trait::async_trait;
use redis::aio::{ConnectionManager, ConnectionManagerConfig};
use tokio::sync::Semaphore;

use self::record::{now_ms, Record};
use self::scripts::Scripts;
use super::backend::JobBackend;
use super::manager::{JobHandle, JobManager, JobsError, RemoteJob, Submitted, WeakJobHandle, Work};
use super::state::{JobSnapshot, JobState, ResultBytes};
use crate::error::MurkError;

/// Rebuilds a job's work from `(method, canonical request bytes)` on the replica that runs it.
pub type Rebuild = Arc<dyn Fn(&str, &[u8]) -> Result<Work, MurkError> + Send + Sync>;

/// Settings of the Redis backend.
#[derive(Clone)]
pub struct RedisConfig {
    /// `redis://[:password@]host:port/db` (or `rediss://` for TLS).
    pub url: String,
    /// Prefix of every key, so several deployments can share one Redis.
    pub prefix: String,
    /// A running job's lease: a replica silent for this long loses its jobs to the others.
    pub lease: Duration,
    /// How long finished job records are kept.
    pub record_ttl: Duration,
    /// How long results are kept (Redis's maxmemory policy may evict them earlier).
    pub result_ttl: Duration,
    /// Starts of one job (each ended by its replica dying) before it is failed as poison.
    pub max_attempts: u32,
}

impl RedisConfig {
    /// Defaults around `url`: prefix `murk`, 10 s lease, records and results kept 7 days,
    /// 3 attempts.
    pub fn new(url: impl Into<String>) -> Self {
        Self {
            url: url.into(),
            prefix: "murk".into(),
            lease: Duration::from_secs(10),
            record_ttl: Duration::from_secs(7 * 24 * 3600),
            result_ttl: Duration::from_secs(7 * 24 * 3600),
            max_attempts: 3,
        }
    }
}

impl std::fmt::Debug for RedisConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // The URL may carry a password.
        let url = match self.url.split_once('@') {
            Some((scheme_auth, host)) => {
                let scheme = scheme_auth.split("://").next().unwrap_or("redis");
                format!("{scheme}://***@{host}")
            }
            None => self.url.clone(),
        };
        f.debug_struct("RedisConfig")
            .field("url", &url)
            .field("prefix", &self.prefix)
            .field("lease", &self.lease)
            .finish_non_exhaustive()
    }
}

/// Consumer group of the work stream.
const GROUP: &str = "workers";

/// Most job ids kept per tenant for ListJobs.
const MAX_RECORDS_PER_TENANT: usize = 10_000;

/// Key names.
struct Keys {
    prefix: String,
}

impl Keys {
    fn record(&self, tenant: &str, id: &str) -> String {
        format!("{}:job:{tenant}:{id}", self.prefix)
    }
    fn tenant_jobs(&self, tenant: &str) -> String {
        format!("{}:jobs:{tenant}", self.prefix)
    }
    fn queued(&self) -> String {
        format!("{}:queued", self.prefix)
    }
    fn stream(&self) -> String {
        format!("{}:queue", self.prefix)
    }
    fn generation(&self) -> String {
        format!("{}:gen", self.prefix)
    }
    fn result(&self, id: &str) -> String {
        format!("{}:result:{id}", self.prefix)
    }
    fn channel(&self) -> String {
        format!("{}:events", self.prefix)
    }
}

/// Member of the queued set and payload of events: `tenant\tid`.
fn member(tenant: &str, id: &str) -> String {
    format!("{tenant}\t{id}")
}

/// A view this replica hands to callers, kept current from the event channel.
struct ViewSlot {
    handle: WeakJobHandle,
    /// The record generation the view shows; a resubmitted record gets a new view.
    gen: String,
    /// Highest record version applied, so refreshes arriving out of order never go back.
    version: AtomicU64,
}

impl ViewSlot {
    fn apply(&self, version: u64, snap: JobSnapshot) {
        if self.version.fetch_max(version, Ordering::SeqCst) < version {
            if let Some(h) = self.handle.upgrade() {
                h.publish(snap);
            }
        }
    }
}

struct Shared {
    cfg: RedisConfig,
    local: JobManager,
    client: redis::Client,
    conn: ConnectionManager,
    scripts: Scripts,
    keys: Keys,
    /// This replica's consumer name.
    replica: String,
    rebuild: Rebuild,
    views: Mutex<HashMap<(String, String), Arc<ViewSlot>>>,
    /// Free compute slots: a replica claims work only while it holds one.
    slots: Arc<Semaphore>,
    concurrent: usize,
    stopping: AtomicBool,
    /// Last global queue depth read (for the metrics gauge).
    queue_depth: AtomicU64,
    /// Whether the last Redis call succeeded (for logs that say so once, not per call).
    reachable: AtomicBool,
}

/// The Redis job backend. See the module docs.
#[derive(Clone)]
pub struct RedisJobs {
    shared: Arc<Shared>,
}

fn unavailable(e: redis::RedisError) -> JobsError {
    JobsError::Unavailable(e.to_string())
}

impl RedisJobs {
    /// Connects (lazily: an unreachable Redis at start is retried in the background, and calls
    /// answer UNAVAILABLE meanwhile) and starts this replica's claim, reclaim and event tasks.
    /// Must be called inside a tokio runtime.
    pub fn start(local: JobManager, cfg: RedisConfig, rebuild: Rebuild) -> Result<Self, MurkError> {
        let client = redis::Client::open(cfg.url.as_str())
            .map_err(|e| MurkError::invalid("redis_url", e.to_string()))?;
        let conn = ConnectionManager::new_lazy_with_config(client.clone(), conn_config(None))
            .map_err(|e| MurkError::invalid("redis_url", e.to_string()))?;
        let concurrent = local.config().concurrent_jobs.max(1);
        let replica = format!(
            "{}-{}-{:04x}",
            hostname(),
            std::process::id(),
            rand::random::<u16>()
        );
        let shared = Arc::new(Shared {
            keys: Keys {
                prefix: cfg.prefix.clone(),
            },
            cfg,
            local,
            client,
            conn,
            scripts: Scripts::new(),
            replica,
            rebuild,
            views: Mutex::new(HashMap::new()),
            slots: Arc::new(Semaphore::new(concurrent)),
            concurrent,
            stopping: AtomicBool::new(false),
            queue_depth: AtomicU64::new(0),
            reachable: AtomicBool::new(true),
        });
        tracing::info!(replica = %shared.replica, prefix = %shared.cfg.prefix, "redis job backend");
        tokio::spawn(worker::claim_loop(shared.clone()));
        tokio::spawn(worker::depth_loop(shared.clone()));
        tokio::spawn(events::listen(shared.clone()));
        Ok(Self { shared })
    }

    /// This replica's consumer name in the work stream.
    pub fn replica(&self) -> &str {
        &self.shared.replica
    }
}

/// Connection settings: quick failure while Redis is away (calls answer UNAVAILABLE instead of
/// hanging), automatic reconnection. `block` is the longest blocking command's wait.
fn conn_config(block: Option<Duration>) -> ConnectionManagerConfig {
    ConnectionManagerConfig::new()
        .set_connection_timeout(Some(Duration::from_secs(2)))
        .set_response_timeout(Some(Duration::from_secs(5) + block.unwrap_or_default()))
        .set_number_of_retries(2)
        .set_max_delay(Duration::from_secs(2))
}

fn hostname() -> String {
    std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "murk".into())
}

impl Shared {
    fn conn(&self) -> ConnectionManager {
        self.conn.clone()
    }

    /// Notes Redis's reachability, logging changes once.
    fn reached<T>(&self, r: redis::RedisResult<T>) -> redis::RedisResult<T> {
        let ok = r.is_ok() || r.as_ref().is_err_and(|e| !e.is_io_error());
        let was = self.reachable.swap(ok, Ordering::SeqCst);
        match (&r, was, ok) {
            (Err(e), true, false) => {
                tracing::error!(error = %e, "redis unreachable: new work is refused until it returns")
            }
            (_, false, true) => tracing::info!("redis reachable again"),
            _ => {}
        }
        r
    }

    async fn record(&self, tenant: &str, id: &str) -> Result<Option<Record>, JobsError> {
        let fields: HashMap<String, String> = self
            .reached(
                redis::cmd("HGETALL")
                    .arg(self.keys.record(tenant, id))
                    .query_async(&mut self.conn())
                    .await,
            )
            .map_err(unavailable)?;
        Ok(Record::from_fields(fields))
    }

    /// The result of job `id`: the local cache, else Redis (then kept locally too).
    async fn load_result(&self, id: &str) -> Result<Option<ResultBytes>, JobsError> {
        if let Some(b) = self.local.cache().get(id) {
            return Ok(Some(b));
        }
        let bytes: Option<Vec<u8>> = self
            .reached(
                redis::cmd("GET")
                    .arg(self.keys.result(id))
                    .query_async(&mut self.conn())
                    .await,
            )
            .map_err(unavailable)?;
        Ok(bytes.map(|b| {
            let b = Arc::new(b);
            self.local.cache().put(id, b.clone());
            b
        }))
    }

    /// The view of `record` for `tenant` (one per job and generation on this replica).
    fn view_of(
        self: &Arc<Self>,
        tenant: &str,
        record: &Record,
        result: Option<ResultBytes>,
    ) -> Option<JobHandle> {
        let snap = record.snapshot(result)?;
        let key = (tenant.to_string(), snap.id.clone());
        let mut views = self.views.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(slot) = views.get(&key) {
            if slot.gen == record.gen() {
                if let Some(h) = slot.handle.upgrade() {
                    slot.apply(record.version(), snap);
                    return Some(h);
                }
            }
        }
        let link = Arc::new(ViewLink {
            shared: Arc::downgrade(self),
            field: format!("w:{}:{:016x}", self.replica, rand::random::<u64>()),
        });
        let h = self.local.view(tenant, snap, link);
        if views.len() >= 4096 {
            views.retain(|_, s| s.handle.upgrade().is_some());
        }
        views.insert(
            key,
            Arc::new(ViewSlot {
                handle: h.downgrade(),
                gen: record.gen().to_string(),
                version: AtomicU64::new(record.version()),
            }),
        );
        Some(h)
    }

    /// The view slot of a job, if a caller here holds one.
    fn slot(&self, tenant: &str, id: &str) -> Option<Arc<ViewSlot>> {
        self.views
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(&(tenant.to_string(), id.to_string()))
            .cloned()
    }

    /// Re-reads a watched job's record into its view.
    async fn refresh(self: &Arc<Self>, tenant: &str, id: &str) {
        let Some(slot) = self.slot(tenant, id) else {
            return;
        };
        let Ok(Some(rec)) = self.record(tenant, id).await else {
            return;
        };
        if rec.gen() != slot.gen {
            return;
        }
        let result = if rec.state() == Some(JobState::Succeeded) {
            self.load_result(id).await.ok().flatten()
        } else {
            None
        };
        if let Some(snap) = rec.snapshot(result) {
            slot.apply(rec.version(), snap);
        }
    }

    /// The cached result of `id` recorded as `tenant`'s succeeded job.
    async fn from_cache(
        self: &Arc<Self>,
        tenant: &str,
        id: &str,
        method: &str,
    ) -> Result<Option<JobHandle>, JobsError> {
        if self.load_result(id).await?.is_none() {
            return Ok(None);
        }
        let written: i64 = self
            .reached(
                self.scripts
                    .cached
                    .key(self.keys.record(tenant, id))
                    .key(self.keys.tenant_jobs(tenant))
                    .arg(tenant)
                    .arg(id)
                    .arg(method)
                    .arg(now_ms())
                    .arg(self.cfg.record_ttl.as_secs().max(1))
                    .arg(MAX_RECORDS_PER_TENANT)
                    .arg(self.keys.channel())
                    .invoke_async(&mut self.conn())
                    .await,
            )
            .map_err(unavailable)?;
        tracing::debug!(%id, written, "cache hit recorded");
        // Written now, or a twin's live/succeeded record won the race: either way, read it.
        let Some(rec) = self.record(tenant, id).await? else {
            return Ok(None);
        };
        let result = self.load_result(id).await?;
        Ok(self.view_of(tenant, &rec, result))
    }
}

/// What a view's waiter and detach changes do in Redis (see [`RemoteJob`]).
struct ViewLink {
    shared: Weak<Shared>,
    /// This view's waiter field in the record.
    field: String,
}

impl RemoteJob for ViewLink {
    fn waiters_changed(&self, tenant: &str, id: &str, waiters: usize, seq: u64) {
        let (Some(shared), Ok(rt)) = (self.shared.upgrade(), tokio::runtime::Handle::try_current())
        else {
            return;
        };
        let (tenant, id, field) = (tenant.to_string(), id.to_string(), self.field.clone());
        rt.spawn(async move {
            let r: redis::RedisResult<i64> = shared
                .scripts
                .waiters
                .key(shared.keys.record(&tenant, &id))
                .key(shared.keys.queued())
                .arg(field)
                .arg(seq)
                .arg(waiters)
                .arg(now_ms())
                .arg(shared.cfg.record_ttl.as_secs().max(1))
                .arg(shared.keys.channel())
                .arg(member(&tenant, &id))
                .invoke_async(&mut shared.conn())
                .await;
            match r {
                Ok(1) => tracing::info!(%id, "last caller went away; job cancelled"),
                Ok(_) => {}
                Err(e) => tracing::warn!(%id, error = %e, "could not record the job's waiters"),
            }
        });
    }

    fn detached(&self, tenant: &str, id: &str) {
        let (Some(shared), Ok(rt)) = (self.shared.upgrade(), tokio::runtime::Handle::try_current())
        else {
            return;
        };
        let key = shared.keys.record(tenant, id);
        rt.spawn(async move {
            let r: redis::RedisResult<i64> = shared
                .scripts
                .detach
                .key(key)
                .invoke_async(&mut shared.conn())
                .await;
            if let Err(e) = r {
                tracing::warn!(error = %e, "could not mark the job detached");
            }
        });
    }
}

#[async_trait]
impl JobBackend for RedisJobs {
    fn kind(&self) -> &'static str {
        "redis"
    }

    fn local(&self) -> &JobManager {
        &self.shared.local
    }

    fn wants_request(&self) -> bool {
        true
    }

    fn queue_depth(&self) -> usize {
        self.shared.queue_depth.load(Ordering::Relaxed) as usize
    }

    async fn find(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
    ) -> Result<Option<Submitted>, JobsError> {
        let s = &self.shared;
        if let Some(rec) = s.record(tenant, id).await?.filter(Record::reusable) {
            let succeeded = rec.state() == Some(JobState::Succeeded);
            let result = if succeeded {
                s.load_result(id).await?
            } else {
                None
            };
            // A succeeded record whose result Redis evicted is recomputed.
            if !succeeded || result.is_some() {
                if succeeded {
                    s.local.metrics().cache_hits.inc();
                }
                return Ok(s.view_of(tenant, &rec, result).map(|handle| Submitted {
                    handle,
                    cached: succeeded,
                }));
            }
        }
        let hit = s.from_cache(tenant, id, method).await?;
        if hit.is_some() {
            s.local.metrics().cache_hits.inc();
        }
        Ok(hit.map(|handle| Submitted {
            handle,
            cached: true,
        }))
    }

    async fn get(&self, tenant: &str, id: &str) -> Result<Option<JobHandle>, JobsError> {
        let s = &self.shared;
        if let Some(rec) = s.record(tenant, id).await? {
            let result = if rec.state() == Some(JobState::Succeeded) {
                s.load_result(id).await?
            } else {
                None
            };
            return Ok(s.view_of(tenant, &rec, result));
        }
        // As the embedded backend: without authentication a cached result is a job.
        if tenant.is_empty() {
            return s.from_cache(tenant, id, "").await;
        }
        Ok(None)
    }

    async fn queue_full(&self) -> Result<bool, JobsError> {
        let s = &self.shared;
        let depth: u64 = s
            .reached(
                redis::cmd("ZCARD")
                    .arg(s.keys.queued())
                    .query_async(&mut s.conn())
                    .await,
            )
            .map_err(unavailable)?;
        s.queue_depth.store(depth, Ordering::Relaxed);
        Ok(depth >= s.local.config().queue_capacity as u64)
    }

    fn refusal(&self) -> JobsError {
        self.shared.local.refusal()
    }

    async fn submit(
        &self,
        tenant: &str,
        id: &str,
        method: &str,
        work: Work,
        request: Option<Vec<u8>>,
    ) -> Result<Submitted, JobsError> {
        let s = &self.shared;
        if s.local.shutting_down() {
            return Err(JobsError::ShuttingDown);
        }
        // The replica that claims the job rebuilds it from the request; building it here
        // validated the request.
        drop(work);
        let request = request.ok_or_else(|| {
            JobsError::Unavailable("the redis backend needs the request bytes".into())
        })?;
        let out: Vec<redis::Value> = s
            .reached(
                s.scripts
                    .submit
                    .key(s.keys.record(tenant, id))
                    .key(s.keys.queued())
                    .key(s.keys.tenant_jobs(tenant))
                    .key(s.keys.stream())
                    .key(s.keys.generation())
                    .arg(tenant)
                    .arg(id)
                    .arg(method)
                    .arg(now_ms())
                    .arg(s.local.config().queue_capacity)
                    .arg(request)
                    .arg(MAX_RECORDS_PER_TENANT)
                    .arg(s.keys.channel())
                    // `find` saw no usable record: a succeeded one has lost its result.
                    .arg("1")
                    .invoke_async(&mut s.conn())
                    .await,
            )
            .map_err(unavailable)?;
        let status = out
            .first()
            .and_then(|v| redis::from_redis_value_ref::<String>(v).ok())
            .unwrap_or_default();
        match status.as_str() {
            "full" => return Err(self.refusal()),
            "queued" => {
                s.local.metrics().cache_misses.inc();
                tracing::info!(%id, %method, %tenant, "job queued in redis");
            }
            _ => {}
        }
        let rec = s
            .record(tenant, id)
            .await?
            .ok_or_else(|| JobsError::Unavailable("job record vanished".into()))?;
        let succeeded = rec.state() == Some(JobState::Succeeded);
        let result = if succeeded {
            s.load_result(id).await?
        } else {
            None
        };
        let handle = s
            .view_of(tenant, &rec, result)
            .ok_or_else(|| JobsError::Unavailable("job record unreadable".into()))?;
        Ok(Submitted {
            handle,
            cached: succeeded,
        })
    }

    async fn cancel(&self, tenant: &str, id: &str) -> Result<Option<JobSnapshot>, JobsError> {
        let s = &self.shared;
        let outcome: String = s
            .reached(
                s.scripts
                    .cancel
                    .key(s.keys.record(tenant, id))
                    .key(s.keys.queued())
                    .arg(now_ms())
                    .arg(s.cfg.record_ttl.as_secs().max(1))
                    .arg(s.keys.channel())
                    .arg(member(tenant, id))
                    .invoke_async(&mut s.conn())
                    .await,
            )
            .map_err(unavailable)?;
        if outcome == "missing" {
            return Ok(None);
        }
        if outcome == "signalled" {
            // Running here: stop it now rather than when the event comes back.
            s.local.cancel(tenant, id);
        }
        s.refresh(tenant, id).await;
        Ok(s.record(tenant, id).await?.and_then(|r| r.snapshot(None)))
    }

    async fn list(
        &self,
        tenant: &str,
        offset: usize,
        page_size: usize,
    ) -> Result<(Vec<JobSnapshot>, Option<usize>), JobsError> {
        let s = &self.shared;
        let ids: Vec<String> = s
            .reached(
                redis::cmd("ZREVRANGE")
                    .arg(s.keys.tenant_jobs(tenant))
                    .arg(offset)
                    .arg(offset + page_size)
                    .query_async(&mut s.conn())
                    .await,
            )
            .map_err(unavailable)?;
        let more = ids.len() > page_size;
        let mut pipe = redis::pipe();
        for id in ids.iter().take(page_size) {
            pipe.cmd("HGETALL").arg(s.keys.record(tenant, id));
        }
        let records: Vec<HashMap<String, String>> = if ids.is_empty() {
            Vec::new()
        } else {
            s.reached(pipe.query_async(&mut s.conn()).await)
                .map_err(unavailable)?
        };
        // Expired records leave a gap in the page rather than shifting later pages.
        let page = records
            .into_iter()
            .filter_map(Record::from_fields)
            .filter_map(|r| r.snapshot(None))
            .collect();
        Ok((page, more.then_some(offset + page_size)))
    }

    async fn shutdown(&self, grace: Duration) {
        let s = &self.shared;
        s.stopping.store(true, Ordering::SeqCst);
        s.local.shutdown(grace).await;
        // Jobs the local shutdown stopped are handed back to the queue by their runners; give
        // them a moment (bounded) to do it.
        let all = s.concurrent as u32;
        let _ = tokio::time::timeout(Duration::from_secs(2), s.slots.acquire_many(all)).await;
    }
}
