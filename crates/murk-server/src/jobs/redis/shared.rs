//! This replica's side of Redis: the key names, the connections, the scripts and the views its
//! callers hold, with the operations the worker and the event listener perform on them, each
//! written once: reading and taking over stream entries, and starting, renewing, finishing or
//! handing back a claimed job.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use futures::future::BoxFuture;
use redis::aio::{ConnectionManager, ConnectionManagerConfig};
use redis::Value;
use tokio::sync::Semaphore;

use super::record::{now_ms, Record};
use super::scripts::Scripts;
use super::stream::{parse_entry, read_reply, text, Claimed};
use super::{Rebuild, RedisConfig, MAX_RECORDS_PER_TENANT};
use crate::jobs::entry::RemoteJob;
use crate::jobs::error_codec::encode_error;
use crate::jobs::handle::{JobHandle, WeakJobHandle};
use crate::jobs::manager::{JobManager, JobsError};
use crate::jobs::state::{JobSnapshot, JobState, ResultBytes};
use murk::error::MurkError;

/// Consumer group of the work stream.
const GROUP: &str = "workers";

/// Key names.
pub(super) struct Keys {
    prefix: String,
}

impl Keys {
    pub(super) fn record(&self, tenant: &str, id: &str) -> String {
        format!("{}:job:{tenant}:{id}", self.prefix)
    }
    pub(super) fn tenant_jobs(&self, tenant: &str) -> String {
        format!("{}:jobs:{tenant}", self.prefix)
    }
    pub(super) fn queued(&self) -> String {
        format!("{}:queued", self.prefix)
    }
    pub(super) fn stream(&self) -> String {
        format!("{}:queue", self.prefix)
    }
    pub(super) fn generation(&self) -> String {
        format!("{}:gen", self.prefix)
    }
    pub(super) fn result(&self, id: &str) -> String {
        format!("{}:result:{id}", self.prefix)
    }
    pub(super) fn channel(&self) -> String {
        format!("{}:events", self.prefix)
    }
}

/// Member of the queued set and payload of events: `tenant\tid`.
pub(super) fn member(tenant: &str, id: &str) -> String {
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

/// This replica's state in the Redis backend, shared by the backend's calls, the worker and the
/// event listener.
pub(super) struct Shared {
    pub(super) cfg: RedisConfig,
    /// The embedded manager: it computes the jobs this replica claims and holds the views.
    pub(super) local: JobManager,
    pub(super) client: redis::Client,
    conn: ConnectionManager,
    pub(super) scripts: Scripts,
    pub(super) keys: Keys,
    /// This replica's consumer name.
    pub(super) replica: String,
    pub(super) rebuild: Rebuild,
    views: Mutex<HashMap<(String, String), Arc<ViewSlot>>>,
    /// Free compute slots: a replica claims work only while it holds one.
    pub(super) slots: Arc<Semaphore>,
    pub(super) concurrent: usize,
    stopping: AtomicBool,
    /// Last global queue depth read (for the metrics gauge).
    pub(super) queue_depth: AtomicU64,
    /// Whether the last Redis call succeeded (for logs that say so once, not per call).
    reachable: AtomicBool,
    /// Whether the last periodic queue-depth query succeeded (connected, authenticated and
    /// answered), for the `murk_redis_up` gauge.
    pub(super) answered: AtomicBool,
}

/// A Redis error as the job system's refusal: the call may succeed later.
pub(super) fn unavailable(e: redis::RedisError) -> JobsError {
    JobsError::Unavailable(e.to_string())
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

/// This machine's name, for the replica's consumer name.
fn hostname() -> String {
    std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "murk".into())
}

/// The Redis client for `cfg`'s URL, with its certificates when any are given.
fn client_of(cfg: &RedisConfig) -> Result<redis::Client, MurkError> {
    let client = if cfg.tls.is_set() {
        if !cfg.url.starts_with("rediss://") {
            return Err(MurkError::invalid(
                "redis_url",
                "TLS certificates are given but the URL is not rediss://",
            ));
        }
        redis::Client::build_with_tls(
            cfg.url.as_str(),
            redis::TlsCertificates {
                client_tls: cfg.tls.client_cert_and_key_pem.as_ref().map(|(cert, key)| {
                    redis::ClientTlsConfig {
                        client_cert: cert.clone(),
                        client_key: key.clone(),
                    }
                }),
                root_cert: cfg.tls.ca_pem.clone(),
            },
        )
    } else {
        redis::Client::open(cfg.url.as_str())
    };
    client.map_err(|e| MurkError::invalid("redis_url", e.to_string()))
}

impl Shared {
    /// Connects lazily (an unreachable Redis at start is retried in the background) under a
    /// fresh consumer name for this replica.
    pub(super) fn new(
        local: JobManager,
        cfg: RedisConfig,
        rebuild: Rebuild,
    ) -> Result<Self, MurkError> {
        let client = client_of(&cfg)?;
        let conn = ConnectionManager::new_lazy_with_config(client.clone(), conn_config(None))
            .map_err(|e| MurkError::invalid("redis_url", e.to_string()))?;
        let concurrent = local.config().concurrent_jobs.max(1);
        let replica = format!(
            "{}-{}-{:04x}",
            hostname(),
            std::process::id(),
            rand::random::<u16>()
        );
        Ok(Self {
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
            answered: AtomicBool::new(false),
        })
    }

    /// Winds the background tasks down: no new claims, no event reconnections, and writes that
    /// keep failing are given up (the lease hands their jobs to another replica).
    pub(super) fn stop(&self) {
        self.stopping.store(true, Ordering::SeqCst);
    }

    /// True once [`Shared::stop`] was called.
    pub(super) fn is_stopping(&self) -> bool {
        self.stopping.load(Ordering::SeqCst)
    }

    /// Whether the last Redis call reached Redis.
    pub(super) fn is_reachable(&self) -> bool {
        self.reachable.load(Ordering::SeqCst)
    }

    /// Jobs accepted but not started, across all replicas; remembered for the gauge.
    pub(super) async fn global_queue_depth(&self) -> redis::RedisResult<u64> {
        let depth = redis::cmd("ZCARD")
            .arg(self.keys.queued())
            .query_async::<u64>(&mut self.conn())
            .await?;
        self.queue_depth.store(depth, Ordering::Relaxed);
        Ok(depth)
    }

    /// The shared multiplexed connection (a clone is a handle on it).
    pub(super) fn conn(&self) -> ConnectionManager {
        self.conn.clone()
    }

    /// Notes Redis's reachability, logging changes once.
    pub(super) fn reached<T>(&self, r: redis::RedisResult<T>) -> redis::RedisResult<T> {
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

    /// `tenant`'s record of job `id`, if Redis holds one.
    pub(super) async fn record(&self, tenant: &str, id: &str) -> Result<Option<Record>, JobsError> {
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
    pub(super) async fn load_result(&self, id: &str) -> Result<Option<ResultBytes>, JobsError> {
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
    pub(super) fn view_of(
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

    /// True when a caller here holds a view of the job.
    pub(super) fn is_watched(&self, tenant: &str, id: &str) -> bool {
        self.slot(tenant, id).is_some()
    }

    /// The jobs whose views callers here still hold.
    pub(super) fn watched(&self) -> Vec<(String, String)> {
        self.views
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .filter(|(_, slot)| slot.handle.upgrade().is_some())
            .map(|(k, _)| k.clone())
            .collect()
    }

    /// Re-reads a watched job's record into its view.
    pub(super) async fn refresh(self: &Arc<Self>, tenant: &str, id: &str) {
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
    pub(super) async fn from_cache(
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

/// The work stream and a claimed job's record: what the worker does in Redis.
impl Shared {
    /// A connection of its own for blocking reads of up to `block` (a blocking read holds its
    /// connection).
    pub(super) fn blocking_conn(&self, block: Duration) -> redis::RedisResult<ConnectionManager> {
        ConnectionManager::new_lazy_with_config(self.client.clone(), conn_config(Some(block)))
    }

    /// How often a running job's lease is renewed, and expired leases of others looked for.
    pub(super) fn renew_every(&self) -> Duration {
        (self.cfg.lease / 3).max(Duration::from_millis(100))
    }

    /// Creates the consumer group (and the stream) if missing. From id 0, so entries written
    /// before the group existed are not skipped.
    pub(super) async fn ensure_group(
        &self,
        conn: &mut ConnectionManager,
    ) -> redis::RedisResult<()> {
        let r: redis::RedisResult<Value> = redis::cmd("XGROUP")
            .arg("CREATE")
            .arg(self.keys.stream())
            .arg(GROUP)
            .arg("0")
            .arg("MKSTREAM")
            .query_async(conn)
            .await;
        match r {
            Err(e) if e.code() == Some("BUSYGROUP") => Ok(()),
            Err(e) => self.reached(Err(e)),
            Ok(_) => Ok(()),
        }
    }

    /// The next new entry for this replica, waiting up to `block` for one (`XREADGROUP`).
    pub(super) async fn read_new(
        &self,
        conn: &mut ConnectionManager,
        block: Duration,
    ) -> redis::RedisResult<Option<Claimed>> {
        let reply: redis::RedisResult<Value> = redis::cmd("XREADGROUP")
            .arg("GROUP")
            .arg(GROUP)
            .arg(&self.replica)
            .arg("COUNT")
            .arg(1)
            .arg("BLOCK")
            .arg(block.as_millis() as u64)
            .arg("STREAMS")
            .arg(self.keys.stream())
            .arg(">")
            .query_async(conn)
            .await;
        self.reached(reply)
            .map(|v| read_reply(&v).into_iter().next())
    }

    /// One entry whose lease expired, taken over by this replica (`XAUTOCLAIM`, resuming the
    /// scan at `cursor`).
    pub(super) async fn reclaim(
        &self,
        conn: &mut ConnectionManager,
        cursor: &mut String,
    ) -> Option<Claimed> {
        let reply: redis::RedisResult<Value> = redis::cmd("XAUTOCLAIM")
            .arg(self.keys.stream())
            .arg(GROUP)
            .arg(&self.replica)
            .arg(self.cfg.lease.as_millis() as u64)
            .arg(cursor.as_str())
            .arg("COUNT")
            .arg(1)
            .query_async(conn)
            .await;
        let Ok(Value::Array(parts)) = reply else {
            return None;
        };
        *cursor = parts.first().map(text).unwrap_or_else(|| "0-0".into());
        match parts.get(1) {
            Some(Value::Array(e)) => e.iter().filter_map(parse_entry).next(),
            _ => None,
        }
    }

    /// Moves a claimed job's record to running: `run`, or why it needs no computation
    /// (`stale`, `cancelled`, or `failed` as poison; see the START script).
    pub(super) async fn start(&self, c: &Claimed) -> redis::RedisResult<String> {
        let started: redis::RedisResult<String> = self
            .scripts
            .start
            .key(self.keys.record(&c.tenant, &c.id))
            .key(self.keys.queued())
            .arg(&c.tenant)
            .arg(&c.id)
            .arg(&c.gen)
            .arg(&self.replica)
            .arg(now_ms())
            .arg(self.cfg.max_attempts)
            .arg(self.keys.channel())
            .arg(self.cfg.record_ttl.as_secs().max(1))
            .invoke_async(&mut self.conn())
            .await;
        self.reached(started)
    }

    /// Writes a running job's progress to its record: 1 when cancellation was requested, 0 to
    /// go on, -1 when the record is no longer this computation's. The write holds its own
    /// connection, so the caller may poll it beside other work.
    pub(super) fn progress(
        &self,
        c: &Claimed,
        snap: &JobSnapshot,
    ) -> BoxFuture<'_, redis::RedisResult<i64>> {
        let mut inv = self.scripts.progress.prepare_invoke();
        inv.key(self.keys.record(&c.tenant, &c.id))
            .arg(&c.gen)
            .arg(snap.progress)
            .arg(&snap.stage)
            .arg(self.keys.channel())
            .arg(member(&c.tenant, &c.id));
        let mut conn = self.conn();
        Box::pin(async move { inv.invoke_async(&mut conn).await })
    }

    /// Renews a running job's lease: 1 when cancellation was requested, 0 to go on, -1 when
    /// the lease or the record was lost.
    pub(super) async fn heartbeat(&self, c: &Claimed) -> redis::RedisResult<i64> {
        let r: redis::RedisResult<i64> = self
            .scripts
            .heartbeat
            .key(self.keys.stream())
            .key(self.keys.record(&c.tenant, &c.id))
            .arg(GROUP)
            .arg(&c.entry)
            .arg(&self.replica)
            .arg(&c.gen)
            .invoke_async(&mut self.conn())
            .await;
        self.reached(r)
    }

    /// Shows a claimed job's snapshot to this replica's callers at once, without the round
    /// trip through Redis (and while Redis is away).
    pub(super) fn push_local(&self, c: &Claimed, snap: JobSnapshot) {
        if let Some(slot) = self.slot(&c.tenant, &c.id) {
            if slot.gen == c.gen {
                if let Some(h) = slot.handle.upgrade() {
                    h.publish(snap);
                }
            }
        }
    }

    /// Retries a Redis write until it succeeds, or gives up once this replica is stopping (the
    /// entry then stays pending and its lease hands the job to another replica).
    async fn persist<T, F, Fut>(&self, what: &str, id: &str, mut op: F) -> Option<T>
    where
        F: FnMut() -> Fut,
        Fut: std::future::Future<Output = redis::RedisResult<T>>,
    {
        let mut delay = Duration::from_millis(100);
        let mut tries = 0;
        loop {
            match self.reached(op().await) {
                Ok(v) => return Some(v),
                Err(e) => {
                    tries += 1;
                    if self.is_stopping() && tries >= 3 {
                        tracing::error!(%id, error = %e, "giving up on {what}; another replica will redo the job");
                        return None;
                    }
                    if tries == 1 {
                        tracing::warn!(%id, error = %e, "{what} failed; retrying until redis answers");
                    }
                    tokio::time::sleep(delay).await;
                    delay = (delay * 2).min(Duration::from_secs(2));
                }
            }
        }
    }

    /// Stores job `id`'s result for every replica.
    pub(super) async fn store_result(&self, id: &str, bytes: &[u8]) {
        let key = self.keys.result(id);
        let ttl = self.cfg.result_ttl.as_secs().max(1);
        self.persist("storing the result", id, || {
            let mut conn = self.conn();
            let key = key.clone();
            async move {
                redis::cmd("SET")
                    .arg(key)
                    .arg(bytes)
                    .arg("EX")
                    .arg(ttl)
                    .query_async::<()>(&mut conn)
                    .await
            }
        })
        .await;
    }

    /// An invocation of a script that settles a claimed stream entry (FINISH, REQUEUE): KEYS
    /// record, stream, queued set; ARGV gen, entry, group, then the script's own arguments.
    fn settle_invocation<'a>(
        &self,
        script: &'a redis::Script,
        c: &Claimed,
    ) -> redis::ScriptInvocation<'a> {
        let mut inv = script.prepare_invoke();
        inv.key(self.keys.record(&c.tenant, &c.id))
            .key(self.keys.stream())
            .key(self.keys.queued())
            .arg(&c.gen)
            .arg(&c.entry)
            .arg(GROUP);
        inv
    }

    /// Acknowledges the entry and closes the record (if it is still this generation's).
    pub(super) async fn finish(&self, c: &Claimed, state: JobState, error: Option<MurkError>) {
        let (kind, a, b) = error
            .as_ref()
            .map_or(("", String::new(), String::new()), encode_error);
        let end = now_ms();
        self.persist("recording the job's end", &c.id, || {
            let mut conn = self.conn();
            let mut inv = self.settle_invocation(&self.scripts.finish, c);
            inv.arg(state.name())
                .arg(end)
                .arg(kind)
                .arg(&a)
                .arg(&b)
                .arg(self.cfg.record_ttl.as_secs().max(1))
                .arg(self.keys.channel())
                .arg(member(&c.tenant, &c.id));
            async move { inv.invoke_async::<i64>(&mut conn).await }
        })
        .await;
    }

    /// Hands a job this stopping replica did not finish back to the queue.
    pub(super) async fn requeue(&self, c: &Claimed) {
        let now = now_ms();
        let done = self
            .persist("handing the job back", &c.id, || {
                let mut conn = self.conn();
                let mut inv = self.settle_invocation(&self.scripts.requeue, c);
                inv.arg(now)
                    .arg(self.keys.channel())
                    .arg(member(&c.tenant, &c.id))
                    .arg(&c.tenant)
                    .arg(&c.id)
                    .arg(&c.method)
                    .arg(&c.request)
                    .arg(self.cfg.record_ttl.as_secs().max(1));
                async move { inv.invoke_async::<i64>(&mut conn).await }
            })
            .await;
        tracing::info!(id = %c.id, requeued = done == Some(1), "job handed back to the queue");
    }
}
