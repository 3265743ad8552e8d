//! This replica's side of the work stream: claim entries while a compute slot is free, run them
//! on the local pool, keep their lease and progress current, store the result, acknowledge;
//! and take over the entries of replicas that stopped renewing their lease.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures::future::BoxFuture;
use tokio::sync::OwnedSemaphorePermit;

use super::shared::Shared;
use super::stream::Claimed;
use crate::jobs::handle::JobHandle;
use crate::jobs::state::{JobSnapshot, JobState};
use murk::error::MurkError;

/// How long one blocking read waits before the loop looks at its stop flag again.
const BLOCK: Duration = Duration::from_secs(1);

/// Least time between two progress writes of one job (stage changes always go through), and
/// the time a job runs before its first one: a job of a few milliseconds writes only its start
/// and its end, which with `appendfsync always` saves an fsync per stage.
const PROGRESS_EVERY: Duration = Duration::from_millis(200);

/// Claims work while this replica has a free slot: first entries whose lease expired (their
/// replica died or hung; checked every lease/3), then new entries. Each runs in its own task
/// holding the slot.
pub(super) async fn claim_loop(shared: Arc<Shared>) {
    // A blocking read holds its connection, so it gets its own.
    let mut conn = loop {
        match shared.blocking_conn(BLOCK) {
            Ok(c) => break c,
            Err(e) => {
                tracing::error!(error = %e, "redis: cannot create the claim connection");
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    };
    let mut group_ready = false;
    let reclaim_every = shared.renew_every();
    let mut next_reclaim = Instant::now();
    let mut cursor = "0-0".to_string();
    while !shared.is_stopping() {
        let Ok(permit) = shared.slots.clone().acquire_owned().await else {
            return;
        };
        if !group_ready {
            match shared.ensure_group(&mut conn).await {
                Ok(()) => group_ready = true,
                Err(_) => {
                    drop(permit);
                    tokio::time::sleep(Duration::from_millis(500)).await;
                    continue;
                }
            }
        }
        if Instant::now() >= next_reclaim {
            next_reclaim = Instant::now() + reclaim_every;
            if let Some(c) = shared.reclaim(&mut conn, &mut cursor).await {
                tracing::warn!(id = %c.id, entry = %c.entry, "lease expired on another replica; taking the job over");
                tokio::spawn(run(shared.clone(), c, permit));
                continue;
            }
        }
        let block = next_reclaim
            .saturating_duration_since(Instant::now())
            .clamp(Duration::from_millis(10), BLOCK);
        match shared.read_new(&mut conn, block).await {
            Ok(Some(c)) if !shared.is_stopping() => {
                tokio::spawn(run(shared.clone(), c, permit));
            }
            // Read while stopping: leave it pending; the lease hands it to another replica.
            Ok(_) => drop(permit),
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

/// Keeps the global queue depth gauge current.
pub(super) async fn depth_loop(shared: Arc<Shared>) {
    while !shared.is_stopping() {
        let answered = shared.global_queue_depth().await.is_ok();
        shared.answered.store(answered, Ordering::Relaxed);
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
    match s.start(&c).await.as_deref() {
        Ok("run") => {}
        Ok(other) => {
            // Stale, cancelled or failed as poison: the record is settled; drop the entry.
            tracing::debug!(id = %c.id, outcome = other, "claimed entry needs no computation");
            s.finish(&c, JobState::Cancelled, None).await;
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
        s.finish(&c, JobState::Succeeded, None).await;
        s.push_local(&c, snap);
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
            s.finish(&c, JobState::Failed, Some(e)).await;
            return;
        }
    };
    let handle = match s.local.run_claimed(&c.tenant, &c.id, &c.method, work) {
        Ok(h) => h,
        Err(_) => {
            s.requeue(&c).await;
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
                            s.store_result(&c.id, bytes).await;
                        }
                        s.finish(&c, JobState::Succeeded, None).await;
                    }
                    (JobState::Failed, Some(MurkError::ShuttingDown)) => s.requeue(&c).await,
                    (state, error) => s.finish(&c, state, error).await,
                }
            };
            tokio::pin!(record);
            // Callers here see the end once Redis has it too, so that a Get through any replica
            // right after a watch ended agrees with it, however long a loaded Redis takes to
            // store a large result. Only with Redis unreachable do they see it first (and the
            // record follows when Redis returns).
            let redis_away = async {
                while s.is_reachable() {
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            };
            tokio::select! {
                _ = &mut record => s.push_local(&c, snap),
                _ = redis_away => {
                    s.push_local(&c, snap);
                    record.await;
                }
            }
        }
    }
}

/// Follows the local job: progress to the record, lease renewals, cancel requests, until it
/// ends or the job is lost to another replica.
async fn supervise(s: &Arc<Shared>, c: &Claimed, handle: &JobHandle) -> Outcome {
    let mut rx = handle.subscribe();
    let mut beat = tokio::time::interval(s.renew_every());
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
                s.push_local(c, snap.clone());
                if writing.is_none()
                    && started.elapsed() >= PROGRESS_EVERY
                    && (snap.stage != last_stage || last_write.elapsed() >= PROGRESS_EVERY)
                {
                    last_stage = snap.stage.clone();
                    last_write = Instant::now();
                    writing = Some(s.progress(c, &snap));
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
                match s.heartbeat(c).await {
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
