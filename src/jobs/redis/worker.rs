//! This replica's side of the work stream: claim entries while a compute slot is free, run them
//! on the local pool, keep their lease and progress current, store the result, acknowledge;
//! and take over the entries of replicas that stopped renewing their lease.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures::future::BoxFuture;
use redis::aio::ConnectionManager;
use redis::Value;
use tokio::sync::OwnedSemaphorePermit;

use super::record::now_ms;
use super::{conn_config, member, Shared, GROUP};
use crate::error::MurkError;
use crate::jobs::error_codec::encode_error;
use crate::jobs::state::{JobSnapshot, JobState};

/// How long one blocking read waits before the loop looks at its stop flag again.
const BLOCK: Duration = Duration::from_secs(1);

/// Least time between two progress writes of one job (stage changes always go through), and
/// the time a job runs before its first one: a job of a few milliseconds writes only its start
/// and its end, which with `appendfsync always` saves an fsync per stage.
const PROGRESS_EVERY: Duration = Duration::from_millis(200);

/// One stream entry: a job to compute.
#[derive(Debug)]
struct Claimed {
    entry: String,
    tenant: String,
    id: String,
    method: String,
    gen: String,
    request: Vec<u8>,
}

fn text(v: &Value) -> String {
    match v {
        Value::BulkString(b) => String::from_utf8_lossy(b).into_owned(),
        Value::SimpleString(s) => s.clone(),
        Value::Int(i) => i.to_string(),
        _ => String::new(),
    }
}

/// `[id, [k, v, …]]` → a claimed job; `None` for a deleted entry (nil fields).
fn parse_entry(v: &Value) -> Option<Claimed> {
    let Value::Array(parts) = v else { return None };
    let entry = text(parts.first()?);
    let Value::Array(kv) = parts.get(1)? else {
        return None;
    };
    let mut c = Claimed {
        entry,
        tenant: String::new(),
        id: String::new(),
        method: String::new(),
        gen: String::new(),
        request: Vec::new(),
    };
    for pair in kv.chunks(2) {
        let [k, v] = pair else { continue };
        match text(k).as_str() {
            "tenant" => c.tenant = text(v),
            "id" => c.id = text(v),
            "method" => c.method = text(v),
            "gen" => c.gen = text(v),
            "request" => {
                if let Value::BulkString(b) = v {
                    c.request = b.clone();
                }
            }
            _ => {}
        }
    }
    (!c.id.is_empty()).then_some(c)
}

/// Entries of an `XREADGROUP` reply: `[[stream, [entry, …]]]`.
fn read_reply(v: &Value) -> Vec<Claimed> {
    let Value::Array(streams) = v else {
        return Vec::new();
    };
    streams
        .iter()
        .filter_map(|s| match s {
            Value::Array(p) => p.get(1),
            _ => None,
        })
        .flat_map(|entries| match entries {
            Value::Array(e) => e.iter().filter_map(parse_entry).collect(),
            _ => Vec::new(),
        })
        .collect()
}

/// Creates the consumer group (and the stream) if missing. From id 0, so entries written
/// before the group existed are not skipped.
async fn ensure_group(shared: &Shared, conn: &mut ConnectionManager) -> redis::RedisResult<()> {
    let r: redis::RedisResult<Value> = redis::cmd("XGROUP")
        .arg("CREATE")
        .arg(shared.keys.stream())
        .arg(GROUP)
        .arg("0")
        .arg("MKSTREAM")
        .query_async(conn)
        .await;
    match r {
        Err(e) if e.code() == Some("BUSYGROUP") => Ok(()),
        other => other.map(|_| ()),
    }
}

/// Claims work while this replica has a free slot: first entries whose lease expired (their
/// replica died or hung; checked every lease/3), then new entries. Each runs in its own task
/// holding the slot.
pub(super) async fn claim_loop(shared: Arc<Shared>) {
    // A blocking read holds its connection, so it gets its own.
    let mut conn = loop {
        match ConnectionManager::new_lazy_with_config(
            shared.client.clone(),
            conn_config(Some(BLOCK)),
        ) {
            Ok(c) => break c,
            Err(e) => {
                tracing::error!(error = %e, "redis: cannot create the claim connection");
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    };
    let mut group_ready = false;
    let reclaim_every = (shared.cfg.lease / 3).max(Duration::from_millis(100));
    let mut next_reclaim = Instant::now();
    let mut cursor = "0-0".to_string();
    while !shared.stopping.load(Ordering::SeqCst) {
        let Ok(permit) = shared.slots.clone().acquire_owned().await else {
            return;
        };
        if !group_ready {
            match ensure_group(&shared, &mut conn).await {
                Ok(()) => group_ready = true,
                Err(e) => {
                    let _ = shared.reached::<()>(Err(e));
                    drop(permit);
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    continue;
                }
            }
        }
        if Instant::now() >= next_reclaim {
            next_reclaim = Instant::now() + reclaim_every;
            if let Some(c) = reclaim(&shared, &mut conn, &mut cursor).await {
                tracing::warn!(id = %c.id, entry = %c.entry, "lease expired on another replica; taking the job over");
                tokio::spawn(run(shared.clone(), c, permit));
                continue;
            }
        }
        let block = next_reclaim
            .saturating_duration_since(Instant::now())
            .clamp(Duration::from_millis(10), BLOCK);
        let reply: redis::RedisResult<Value> = redis::cmd("XREADGROUP")
            .arg("GROUP")
            .arg(GROUP)
            .arg(&shared.replica)
            .arg("COUNT")
            .arg(1)
            .arg("BLOCK")
            .arg(block.as_millis() as u64)
            .arg("STREAMS")
            .arg(shared.keys.stream())
            .arg(">")
            .query_async(&mut conn)
            .await;
        match shared.reached(reply) {
            Ok(v) => match read_reply(&v).into_iter().next() {
                Some(c) if !shared.stopping.load(Ordering::SeqCst) => {
                    tokio::spawn(run(shared.clone(), c, permit));
                }
                // Read while stopping: leave it pending; the lease hands it to another replica.
                _ => drop(permit),
            },
            Err(e) => {
                if e.code() == Some("NOGROUP") {
                    group_ready = false;
                }
                drop(permit);
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
        }
    }
}

/// One entry whose lease expired, taken over by this replica (`XAUTOCLAIM`, resuming the scan
/// at `cursor`).
async fn reclaim(
    shared: &Shared,
    conn: &mut ConnectionManager,
    cursor: &mut String,
) -> Option<Claimed> {
    let reply: redis::RedisResult<Value> = redis::cmd("XAUTOCLAIM")
        .arg(shared.keys.stream())
        .arg(GROUP)
        .arg(&shared.replica)
        .arg(shared.cfg.lease.as_millis() as u64)
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

/// Keeps the global queue depth gauge current.
pub(super) async fn depth_loop(shared: Arc<Shared>) {
    while !shared.stopping.load(Ordering::SeqCst) {
        if let Ok(depth) = redis::cmd("ZCARD")
            .arg(shared.keys.queued())
            .query_async::<u64>(&mut shared.conn())
            .await
        {
            shared.queue_depth.store(depth, Ordering::Relaxed);
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

/// How a claimed job ended on this replica.
enum Outcome {
    Done(JobSnapshot),
    /// Another replica holds the lease now, or the record moved on: leave everything to it.
    Lost,
}

/// Runs one claimed job to its end and records that end in Redis.
async fn run(shared: Arc<Shared>, c: Claimed, _permit: OwnedSemaphorePermit) {
    let s = &shared;
    let started: redis::RedisResult<String> = s
        .scripts
        .start
        .key(s.keys.record(&c.tenant, &c.id))
        .key(s.keys.queued())
        .arg(&c.tenant)
        .arg(&c.id)
        .arg(&c.gen)
        .arg(&s.replica)
        .arg(now_ms())
        .arg(s.cfg.max_attempts)
        .arg(s.keys.channel())
        .arg(s.cfg.record_ttl.as_secs().max(1))
        .invoke_async(&mut s.conn())
        .await;
    match s.reached(started).as_deref() {
        Ok("run") => {}
        Ok(other) => {
            // Stale, cancelled or failed as poison: the record is settled; drop the entry.
            tracing::debug!(id = %c.id, outcome = other, "claimed entry needs no computation");
            finish(s, &c, JobState::Cancelled, None).await;
            return;
        }
        Err(e) => {
            // The entry stays pending; the lease brings it back.
            tracing::warn!(id = %c.id, error = %e, "could not start a claimed job");
            return;
        }
    }
    // Computed already (the replica before stored the result but died before acknowledging).
    if let Ok(Some(bytes)) = s.load_result(&c.id).await {
        let mut snap = JobSnapshot::from_cache(&c.id, &c.method, bytes);
        snap.cached = false;
        finish(s, &c, JobState::Succeeded, None).await;
        push_local(s, &c, snap);
        return;
    }
    let rebuild = s.rebuild.clone();
    // The request stays with the claim, to hand the job back on shutdown.
    let (method, request) = (c.method.clone(), c.request.clone());
    let work = tokio::task::spawn_blocking(move || rebuild(&method, &request))
        .await
        .unwrap_or_else(|e| Err(MurkError::Internal(format!("decoder task failed: {e}"))));
    let work = match work {
        Ok(w) => w,
        Err(e) => {
            finish(s, &c, JobState::Failed, Some(e)).await;
            return;
        }
    };
    let handle = match s.local.run_claimed(&c.tenant, &c.id, &c.method, work) {
        Ok(h) => h,
        Err(_) => {
            requeue(s, &c).await;
            return;
        }
    };
    match supervise(s, &c, &handle).await {
        Outcome::Lost => {
            s.local.cancel(&c.tenant, &c.id);
        }
        Outcome::Done(snap) => {
            let (state, error, result) = (snap.state, snap.error.clone(), snap.result.clone());
            let record = async {
                match (state, error) {
                    (JobState::Succeeded, _) => {
                        if let Some(bytes) = &result {
                            store_result(s, &c.id, bytes).await;
                        }
                        finish(s, &c, JobState::Succeeded, None).await;
                    }
                    (JobState::Failed, Some(MurkError::ShuttingDown)) => requeue(s, &c).await,
                    (state, error) => finish(s, &c, state, error).await,
                }
            };
            tokio::pin!(record);
            // Callers here see the end once Redis has it too, so that a Get through any replica
            // right after a watch ended agrees with it, however long a loaded Redis takes to
            // store a large result. Only with Redis unreachable do they see it first (and the
            // record follows when Redis returns).
            let redis_away = async {
                while s.reachable.load(Ordering::SeqCst) {
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            };
            tokio::select! {
                _ = &mut record => push_local(s, &c, snap),
                _ = redis_away => {
                    push_local(s, &c, snap);
                    record.await;
                }
            }
        }
    }
}

/// Follows the local job: progress to the record, lease renewals, cancel requests, until it
/// ends or the job is lost to another replica.
async fn supervise(s: &Arc<Shared>, c: &Claimed, handle: &crate::jobs::JobHandle) -> Outcome {
    let mut rx = handle.subscribe();
    let mut beat = tokio::time::interval((s.cfg.lease / 3).max(Duration::from_millis(100)));
    beat.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let started = Instant::now();
    let mut last_write = started - PROGRESS_EVERY;
    let mut last_stage = String::new();
    // At most one progress write in flight, outside the loop's way: a slow Redis delays the
    // job's progress in the record, never the detection of its end or its heartbeats.
    let mut writing: Option<BoxFuture<'_, redis::RedisResult<i64>>> = None;
    loop {
        tokio::select! {
            changed = rx.changed() => {
                let snap = rx.borrow_and_update().clone();
                if changed.is_err() || snap.state.is_terminal() {
                    return Outcome::Done(snap);
                }
                push_local(s, c, snap.clone());
                if writing.is_none()
                    && started.elapsed() >= PROGRESS_EVERY
                    && (snap.stage != last_stage || last_write.elapsed() >= PROGRESS_EVERY)
                {
                    last_stage = snap.stage.clone();
                    last_write = Instant::now();
                    let mut inv = s.scripts.progress.prepare_invoke();
                    inv.key(s.keys.record(&c.tenant, &c.id))
                        .arg(&c.gen)
                        .arg(snap.progress)
                        .arg(&snap.stage)
                        .arg(s.keys.channel())
                        .arg(member(&c.tenant, &c.id));
                    let mut conn = s.conn();
                    writing = Some(Box::pin(async move { inv.invoke_async(&mut conn).await }));
                }
            }
            r = async { writing.as_mut().expect("guarded").await }, if writing.is_some() => {
                writing = None;
                match r {
                    Ok(1) => { s.local.cancel(&c.tenant, &c.id); }
                    Ok(-1) => return Outcome::Lost,
                    // Redis away: the job goes on; progress catches up later.
                    _ => {}
                }
            }
            _ = beat.tick() => {
                let r: redis::RedisResult<i64> = s
                    .scripts
                    .heartbeat
                    .key(s.keys.stream())
                    .key(s.keys.record(&c.tenant, &c.id))
                    .arg(GROUP)
                    .arg(&c.entry)
                    .arg(&s.replica)
                    .arg(&c.gen)
                    .invoke_async(&mut s.conn())
                    .await;
                match s.reached(r) {
                    Ok(1) => { s.local.cancel(&c.tenant, &c.id); }
                    Ok(-1) => {
                        tracing::warn!(id = %c.id, "lease lost to another replica; stopping the local computation");
                        return Outcome::Lost;
                    }
                    _ => {}
                }
            }
        }
    }
}

/// Shows a snapshot to this replica's callers at once, without the round trip through Redis
/// (and while Redis is away).
fn push_local(s: &Shared, c: &Claimed, snap: JobSnapshot) {
    if let Some(slot) = s.slot(&c.tenant, &c.id) {
        if slot.gen == c.gen {
            if let Some(h) = slot.handle.upgrade() {
                h.publish(snap);
            }
        }
    }
}

/// Retries a Redis write until it succeeds, or gives up once this replica is stopping (the
/// entry then stays pending and its lease hands the job to another replica).
async fn persist<T, F, Fut>(s: &Shared, what: &str, id: &str, mut op: F) -> Option<T>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = redis::RedisResult<T>>,
{
    let mut delay = Duration::from_millis(100);
    let mut tries = 0;
    loop {
        match s.reached(op().await) {
            Ok(v) => return Some(v),
            Err(e) => {
                tries += 1;
                if s.stopping.load(Ordering::SeqCst) && tries >= 3 {
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

async fn store_result(s: &Shared, id: &str, bytes: &[u8]) {
    let key = s.keys.result(id);
    let ttl = s.cfg.result_ttl.as_secs().max(1);
    persist(s, "storing the result", id, || {
        let mut conn = s.conn();
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
    s: &Shared,
    script: &'a redis::Script,
    c: &Claimed,
) -> redis::ScriptInvocation<'a> {
    let mut inv = script.prepare_invoke();
    inv.key(s.keys.record(&c.tenant, &c.id))
        .key(s.keys.stream())
        .key(s.keys.queued())
        .arg(&c.gen)
        .arg(&c.entry)
        .arg(GROUP);
    inv
}

/// Acknowledges the entry and closes the record (if it is still this generation's).
async fn finish(s: &Shared, c: &Claimed, state: JobState, error: Option<MurkError>) {
    let (kind, a, b) = error
        .as_ref()
        .map_or(("", String::new(), String::new()), encode_error);
    let end = now_ms();
    persist(s, "recording the job's end", &c.id, || {
        let mut conn = s.conn();
        let mut inv = settle_invocation(s, &s.scripts.finish, c);
        inv.arg(state.name())
            .arg(end)
            .arg(kind)
            .arg(&a)
            .arg(&b)
            .arg(s.cfg.record_ttl.as_secs().max(1))
            .arg(s.keys.channel())
            .arg(member(&c.tenant, &c.id));
        async move { inv.invoke_async::<i64>(&mut conn).await }
    })
    .await;
}

/// Hands a job this stopping replica did not finish back to the queue.
async fn requeue(s: &Shared, c: &Claimed) {
    let now = now_ms();
    let done = persist(s, "handing the job back", &c.id, || {
        let mut conn = s.conn();
        let mut inv = settle_invocation(s, &s.scripts.requeue, c);
        inv.arg(now)
            .arg(s.keys.channel())
            .arg(member(&c.tenant, &c.id))
            .arg(&c.tenant)
            .arg(&c.id)
            .arg(&c.method)
            .arg(&c.request)
            .arg(s.cfg.record_ttl.as_secs().max(1));
        async move { inv.invoke_async::<i64>(&mut conn).await }
    })
    .await;
    tracing::info!(id = %c.id, requeued = done == Some(1), "job handed back to the queue");
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bulk(s: &str) -> Value {
        Value::BulkString(s.as_bytes().to_vec())
    }

    #[test]
    fn xreadgroup_replies_parse_into_jobs() {
        let entry = Value::Array(vec![
            bulk("1-0"),
            Value::Array(vec![
                bulk("tenant"),
                bulk("acme"),
                bulk("id"),
                bulk("ab12"),
                bulk("method"),
                bulk("tof_depth"),
                bulk("gen"),
                bulk("7"),
                bulk("request"),
                Value::BulkString(vec![0, 159, 1]),
            ]),
        ]);
        let reply = Value::Array(vec![Value::Array(vec![
            bulk("murk:queue"),
            Value::Array(vec![entry, Value::Array(vec![bulk("2-0"), Value::Nil])]),
        ])]);
        let jobs = read_reply(&reply);
        assert_eq!(jobs.len(), 1, "the deleted entry is skipped");
        let j = &jobs[0];
        assert_eq!(
            (
                j.entry.as_str(),
                j.tenant.as_str(),
                j.id.as_str(),
                j.gen.as_str()
            ),
            ("1-0", "acme", "ab12", "7")
        );
        assert_eq!(j.request, vec![0, 159, 1]);
        assert!(read_reply(&Value::Nil).is_empty());
    }
}
