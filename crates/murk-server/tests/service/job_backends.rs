//! One job-system suite, run against both backends behind `JobBackend`: the embedded
//! `JobManager` and `RedisJobs` on a real redis-server (skipped with a printed reason when
//! redis-server is absent). Jobs are tiny programs encoded in the request bytes, so the Redis
//! backend can rebuild them on whichever "replica" claims them.

use crate::common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use common::redis_server::RedisServer;
use murk::MurkError;
use murk_server::jobs::redis::{RedisConfig, RedisJobs};
use murk_server::jobs::{
    JobBackend, JobHandle, JobManager, JobSnapshot, JobState, JobsConfig, JobsError,
};
use murk_server::jobs::{Submitted, Work};

/// `ms=N;out=TEXT[;fail]`: spin N ms on checkpoints reporting progress, then return TEXT (or
/// fail).
fn program(ms: u64, out: &str, fail: bool) -> Vec<u8> {
    format!("ms={ms};out={out}{}", if fail { ";fail" } else { "" }).into_bytes()
}

fn build(bytes: &[u8]) -> Result<Work, MurkError> {
    let text = String::from_utf8(bytes.to_vec()).map_err(|_| MurkError::invalid("x", "utf8"))?;
    let mut ms = 0u64;
    let mut out = String::new();
    let mut fail = false;
    for part in text.split(';') {
        match part.split_once('=') {
            Some(("ms", v)) => ms = v.parse().map_err(|_| MurkError::invalid("ms", "number"))?,
            Some(("out", v)) => out = v.to_string(),
            None if part == "fail" => fail = true,
            _ => return Err(MurkError::invalid("program", part.to_string())),
        }
    }
    Ok(Box::new(move |m| {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_millis(ms) {
            m.checkpoint()?;
            m.progress("spin", t0.elapsed().as_secs_f32() * 1e3 / ms.max(1) as f32);
            std::thread::sleep(Duration::from_millis(2));
        }
        if fail {
            return Err(MurkError::Numerical("boom".into()));
        }
        Ok(out.into_bytes())
    }))
}

fn local(queue: usize) -> JobManager {
    JobManager::new(JobsConfig {
        workers: 1,
        concurrent_jobs: 1,
        queue_capacity: queue,
        ..JobsConfig::default()
    })
    .unwrap()
}

/// Content-hash-like id of a program (the suite's jobs are identified by their bytes).
fn id_of(bytes: &[u8]) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(bytes))
}

async fn submit(b: &dyn JobBackend, tenant: &str, bytes: Vec<u8>) -> Result<Submitted, JobsError> {
    let id = id_of(&bytes);
    if let Some(found) = b.find(tenant, &id, "prog").await? {
        return Ok(found);
    }
    if b.queue_full().await? {
        return Err(b.refusal());
    }
    let work = build(&bytes).unwrap();
    b.submit(tenant, &id, "prog", work, Some(bytes)).await
}

async fn wait(h: &JobHandle, pred: impl Fn(&JobSnapshot) -> bool) -> JobSnapshot {
    let mut rx = h.subscribe();
    let s = tokio::time::timeout(Duration::from_secs(30), rx.wait_for(|s| pred(s)))
        .await
        .expect("in time")
        .expect("sender alive");
    s.clone()
}

async fn terminal(h: &JobHandle) -> JobSnapshot {
    wait(h, |s| s.state.is_terminal()).await
}

/// Submits `n` long jobs and waits until each runs: every compute slot is then busy.
async fn occupy(b: &dyn JobBackend, n: usize, tag: &str) -> Vec<Submitted> {
    let mut held = Vec::new();
    for k in 0..n {
        let s = submit(b, "", program(60_000, &format!("{tag}{k}"), false))
            .await
            .unwrap();
        wait(&s.handle, |s| s.state == JobState::Running).await;
        held.push(s);
    }
    held
}

async fn release(b: &dyn JobBackend, held: &[Submitted]) {
    for h in held {
        b.cancel("", h.handle.id()).await.unwrap();
    }
    for h in held {
        assert!(terminal(&h.handle).await.state.is_terminal());
    }
}

/// The suite. `replicas` are backends sharing one job system (one for the embedded backend),
/// with one compute slot each and a queue capacity of 2.
async fn suite(replicas: Vec<Arc<dyn JobBackend>>) {
    let slots = replicas.len();
    let a = replicas[0].as_ref();
    let b = replicas.last().unwrap().as_ref();

    // Identical submissions share one computation; afterwards a cache hit.
    let p = program(50, "one", false);
    let s1 = submit(a, "", p.clone()).await.unwrap();
    let s2 = submit(b, "", p.clone()).await.unwrap();
    let done = terminal(&s1.handle).await;
    assert_eq!(done.state, JobState::Succeeded);
    assert_eq!(done.result.as_deref(), Some(&b"one".to_vec()));
    assert_eq!(
        terminal(&s2.handle).await.result.as_deref(),
        Some(&b"one".to_vec())
    );
    let hit = submit(b, "", p.clone()).await.unwrap();
    assert!(hit.cached);

    // Progress reaches watchers before the end.
    let slow = submit(a, "", program(600, "slow", false)).await.unwrap();
    let seen = wait(&slow.handle, |s| {
        s.state == JobState::Running && s.progress > 0.0
    })
    .await;
    assert_eq!(seen.stage, "spin");
    assert_eq!(terminal(&slow.handle).await.state, JobState::Succeeded);

    // Failures are failed jobs with their error.
    let f = submit(a, "", program(1, "x", true)).await.unwrap();
    let snap = terminal(&f.handle).await;
    assert_eq!(snap.state, JobState::Failed);
    assert_eq!(snap.error, Some(MurkError::Numerical("boom".into())));

    // Cancel a running and a queued job; resubmitting a cancelled one starts afresh.
    let long = program(60_000, "long", false);
    let running = submit(a, "", long.clone()).await.unwrap();
    wait(&running.handle, |s| s.state == JobState::Running).await;
    let busy = occupy(a, slots - 1, "busy").await;
    let queued = submit(a, "", program(60_000, "q", false)).await.unwrap();
    let snap = b.cancel("", queued.handle.id()).await.unwrap().unwrap();
    assert_eq!(snap.state, JobState::Cancelled);
    release(b, &busy).await;
    let t0 = Instant::now();
    b.cancel("", running.handle.id()).await.unwrap().unwrap();
    assert_eq!(terminal(&running.handle).await.state, JobState::Cancelled);
    assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
    let again = submit(a, "", long.clone()).await.unwrap();
    assert!(!again.cached);
    let snap = wait(&again.handle, |s| s.state != JobState::Cancelled).await;
    assert!(
        !snap.state.is_terminal(),
        "a fresh job, not the cancelled one"
    );
    a.cancel("", again.handle.id()).await.unwrap();
    terminal(&again.handle).await;
    assert!(a.cancel("", "unknown").await.unwrap().is_none());

    // Tenants: records are private, results shared.
    let t = program(5, "tenant", false);
    let mine = submit(a, "alpha", t.clone()).await.unwrap();
    terminal(&mine.handle).await;
    let id = mine.handle.id().to_string();
    assert!(b.get("beta", &id).await.unwrap().is_none());
    assert!(b.cancel("beta", &id).await.unwrap().is_none());
    assert!(b.list("beta", 0, 10).await.unwrap().0.is_empty());
    assert_eq!(b.list("alpha", 0, 10).await.unwrap().0.len(), 1);
    let theirs = submit(b, "beta", t).await.unwrap();
    assert!(theirs.cached, "the result is shared");
    assert_eq!(b.list("beta", 0, 10).await.unwrap().0.len(), 1);

    // Listing is newest first and paged.
    for k in 0..5 {
        let s = submit(a, "pager", program(1, &format!("p{k}"), false))
            .await
            .unwrap();
        terminal(&s.handle).await;
    }
    let (page, next) = b.list("pager", 0, 2).await.unwrap();
    assert_eq!(page.len(), 2);
    assert_eq!(page[0].result, None, "listings carry no results");
    assert_eq!(next, Some(2));
    let (last, next) = b.list("pager", 4, 2).await.unwrap();
    assert_eq!((last.len(), next), (1, None));

    // The queue bound (capacity 2 here): every slot running, two waiting, the next refused.
    let mut held = occupy(a, slots, "h").await;
    for k in slots..slots + 2 {
        held.push(
            submit(a, "", program(60_000, &format!("h{k}"), false))
                .await
                .unwrap(),
        );
    }
    match submit(b, "", program(60_000, "refused", false)).await {
        Err(JobsError::QueueFull { retry_after, .. }) => assert!(retry_after > Duration::ZERO),
        other => panic!("expected a full queue, got {:?}", other.map(|s| s.cached)),
    }
    release(a, &held).await;
}

#[tokio::test]
async fn embedded_backend_passes_the_suite() {
    suite(vec![Arc::new(local(2))]).await;
}

#[tokio::test]
async fn redis_backend_passes_the_suite_across_two_replicas() {
    let Some(redis) = RedisServer::start() else {
        return;
    };
    let rebuild: murk_server::jobs::redis::Rebuild = Arc::new(|_, bytes| build(bytes));
    let replicas: Vec<Arc<dyn JobBackend>> = (0..2)
        .map(|_| {
            let mut cfg = RedisConfig::new(redis.url());
            cfg.lease = Duration::from_secs(2);
            Arc::new(RedisJobs::start(local(2), cfg, rebuild.clone()).unwrap()) as _
        })
        .collect();
    suite(replicas).await;
}
