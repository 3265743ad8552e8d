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
mod shared;
mod stream;
mod worker;

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;

use self::record::{now_ms, Record};
use self::shared::{member, unavailable, Shared};
use super::backend::JobBackend;
use super::entry::Work;
use super::handle::{JobHandle, Submitted};
use super::manager::{JobManager, JobsError};
use super::state::{JobSnapshot, JobState};
use murk::error::MurkError;

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
    /// Certificates for a `rediss://` URL; without them the system's trust store verifies the
    /// server and no client certificate is sent.
    pub tls: RedisTls,
}

/// PEM certificates for TLS to Redis.
#[derive(Clone, Default)]
pub struct RedisTls {
    /// The CA that signed Redis's certificate, instead of the system's trust store.
    pub ca_pem: Option<Vec<u8>>,
    /// A client certificate and its key, for a Redis that authenticates clients
    /// (`tls-auth-clients yes`).
    pub client_cert_and_key_pem: Option<(Vec<u8>, Vec<u8>)>,
}

impl RedisTls {
    /// Whether anything is set (a plain `redis::Client::open` otherwise).
    pub fn is_set(&self) -> bool {
        self.ca_pem.is_some() || self.client_cert_and_key_pem.is_some()
    }
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
            tls: RedisTls::default(),
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
            .field("tls_ca", &self.tls.ca_pem.is_some())
            .field(
                "tls_client_cert",
                &self.tls.client_cert_and_key_pem.is_some(),
            )
            .finish_non_exhaustive()
    }
}

/// Most job ids kept per tenant for ListJobs.
const MAX_RECORDS_PER_TENANT: usize = 10_000;

/// The Redis job backend. See the module docs.
#[derive(Clone)]
pub struct RedisJobs {
    shared: Arc<Shared>,
}

impl RedisJobs {
    /// Connects (lazily: an unreachable Redis at start is retried in the background, and calls
    /// answer UNAVAILABLE meanwhile) and starts this replica's claim, reclaim and event tasks.
    /// Must be called inside a tokio runtime.
    pub fn start(local: JobManager, cfg: RedisConfig, rebuild: Rebuild) -> Result<Self, MurkError> {
        let shared = Arc::new(Shared::new(local, cfg, rebuild)?);
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

    fn store_up(&self) -> Option<bool> {
        Some(self.shared.answered.load(Ordering::Relaxed))
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
        let depth = s
            .reached(s.global_queue_depth().await)
            .map_err(unavailable)?;
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
        s.stop();
        s.local.shutdown(grace).await;
        // Jobs the local shutdown stopped are handed back to the queue by their runners; give
        // them a moment (bounded) to do it.
        let all = s.concurrent as u32;
        let _ = tokio::time::timeout(Duration::from_secs(2), s.slots.acquire_many(all)).await;
    }
}
