use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Duration;

use super::*;
use murk::error::MurkError;

fn manager(queue: usize) -> JobManager {
    JobManager::new(JobsConfig {
        workers: 2,
        concurrent_jobs: 1,
        queue_capacity: queue,
        ..JobsConfig::default()
    })
    .unwrap()
}

/// Work that signals when it starts and spins on checkpoints until released or cancelled.
fn gated(started: mpsc::Sender<()>, release: Arc<std::sync::atomic::AtomicBool>) -> Work {
    Box::new(move |m| {
        let _ = started.send(());
        while !release.load(Ordering::SeqCst) {
            m.checkpoint()?;
            std::thread::yield_now();
        }
        Ok(vec![42])
    })
}

/// A small manager keeping results, journal and records in `dir`.
fn durable_config(dir: &std::path::Path) -> JobsConfig {
    JobsConfig {
        workers: 2,
        concurrent_jobs: 1,
        queue_capacity: 4,
        cache_dir: Some(dir.to_path_buf()),
        ..JobsConfig::default()
    }
}

async fn wait_terminal(h: &JobHandle) -> JobSnapshot {
    let mut rx = h.subscribe();
    let s = rx
        .wait_for(|s| s.state.is_terminal())
        .await
        .expect("job sender alive");
    s.clone()
}

#[tokio::test]
async fn identical_submissions_compute_once_and_hit_cache() {
    let m = manager(4);
    let runs = Arc::new(AtomicUsize::new(0));
    let mk = |runs: Arc<AtomicUsize>| -> Work {
        Box::new(move |_| {
            runs.fetch_add(1, Ordering::SeqCst);
            Ok(vec![1, 2, 3])
        })
    };
    let a = m.submit("", "aa", "t", mk(runs.clone())).unwrap();
    assert!(!a.cached);
    let b = m.submit("", "aa", "t", mk(runs.clone())).unwrap();
    let sa = wait_terminal(&a.handle).await;
    let sb = wait_terminal(&b.handle).await;
    assert_eq!(sa.state, JobState::Succeeded);
    assert_eq!(sb.result.as_deref(), Some(&vec![1u8, 2, 3]));
    let c = m.submit("", "aa", "t", mk(runs.clone())).unwrap();
    assert!(c.cached);
    assert_eq!(runs.load(Ordering::SeqCst), 1);
    assert_eq!(m.executed(), 1);
}

#[tokio::test]
async fn full_queue_is_refused_with_retry_hint() {
    let m = manager(1);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let first = m
        .submit("", "01", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap(); // first is running, queue empty
    m.submit("", "02", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    let err = m
        .submit("", "03", "t", gated(tx, release.clone()))
        .err()
        .unwrap();
    assert!(matches!(err, JobsError::QueueFull { capacity: 1, .. }));
    release.store(true, Ordering::SeqCst);
    assert_eq!(
        wait_terminal(&first.handle).await.state,
        JobState::Succeeded
    );
}

#[tokio::test]
async fn cancel_running_and_queued_jobs() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let running = m
        .submit("", "0a", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    let queued = m.submit("", "0b", "t", gated(tx, release.clone())).unwrap();
    let snap = m.cancel("", "0b").unwrap();
    assert_eq!(snap.state, JobState::Cancelled, "queued jobs end at once");
    m.cancel("", "0a").unwrap();
    assert_eq!(
        wait_terminal(&running.handle).await.state,
        JobState::Cancelled
    );
    assert_eq!(
        wait_terminal(&queued.handle).await.state,
        JobState::Cancelled
    );
    assert!(m.cancel("", "unknown").is_none());
    // A cancelled job runs again when resubmitted.
    let again = m.submit("", "0a", "t", Box::new(|_| Ok(vec![9]))).unwrap();
    assert_eq!(
        wait_terminal(&again.handle).await.state,
        JobState::Succeeded
    );
}

#[tokio::test]
async fn last_unary_waiter_leaving_cancels_but_detached_jobs_survive() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let s = m
        .submit("", "0c", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    let g1 = s.handle.attach();
    let g2 = s.handle.attach();
    drop(g1);
    assert_eq!(s.handle.snapshot().state, JobState::Running);
    drop(g2);
    assert_eq!(wait_terminal(&s.handle).await.state, JobState::Cancelled);

    let d = m.submit("", "0d", "t", gated(tx, release.clone())).unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    d.handle.detach();
    drop(d.handle.attach());
    release.store(true, Ordering::SeqCst);
    assert_eq!(wait_terminal(&d.handle).await.state, JobState::Succeeded);
}

#[tokio::test]
async fn failures_and_panics_become_failed_jobs() {
    let m = manager(4);
    let f = m
        .submit(
            "",
            "0e",
            "t",
            Box::new(|_| Err(MurkError::Numerical("diverged".into()))),
        )
        .unwrap();
    let s = wait_terminal(&f.handle).await;
    assert_eq!(s.state, JobState::Failed);
    assert!(matches!(s.error, Some(MurkError::Numerical(_))));
    let p = m
        .submit("", "0f", "t", Box::new(|_| panic!("boom")))
        .unwrap();
    let s = wait_terminal(&p.handle).await;
    assert_eq!(s.state, JobState::Failed);
    assert!(matches!(s.error, Some(MurkError::Internal(ref msg)) if msg.contains("boom")));
    // The dispatcher survived the panic.
    let ok = m.submit("", "10", "t", Box::new(|_| Ok(vec![]))).unwrap();
    assert_eq!(wait_terminal(&ok.handle).await.state, JobState::Succeeded);
}

#[tokio::test]
async fn shutdown_drains_then_cancels_and_refuses_new_work() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let s = m.submit("", "11", "t", gated(tx, release)).unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    m.shutdown(Duration::from_millis(50)).await;
    // Stopped by the server, not by anyone who wanted it stopped: a retryable abort.
    let snap = s.handle.snapshot();
    assert_eq!(snap.state, JobState::Failed);
    assert_eq!(snap.error, Some(MurkError::ShuttingDown));
    assert_eq!(
        m.submit("", "12", "t", Box::new(|_| Ok(vec![]))).err(),
        Some(JobsError::ShuttingDown)
    );
}

#[tokio::test]
async fn list_is_newest_first_and_paged() {
    let m = manager(16);
    for i in 0..5 {
        let h = m
            .submit("", &format!("{i:02x}"), "t", Box::new(|_| Ok(vec![])))
            .unwrap();
        wait_terminal(&h.handle).await;
    }
    let (page, next) = m.list("", 0, 2);
    assert_eq!(
        page.iter().map(|s| s.id.as_str()).collect::<Vec<_>>(),
        ["04", "03"]
    );
    assert_eq!(next, Some(2));
    let (page, next) = m.list("", 4, 2);
    assert_eq!(page.len(), 1);
    assert_eq!(next, None);
}

#[tokio::test]
async fn progress_reaches_watchers() {
    let m = manager(4);
    let h = m
        .submit(
            "",
            "13",
            "t",
            Box::new(|mon| {
                mon.progress("half", 0.5);
                Ok(vec![])
            }),
        )
        .unwrap();
    let s = wait_terminal(&h.handle).await;
    assert_eq!(s.progress, 1.0);
    assert!(s.start_time.is_some() && s.end_time.is_some());
}

/// Reports that arrive out of order (parallel parts of a method report from several threads)
/// never move a job's progress backwards.
#[tokio::test]
async fn progress_never_goes_backwards() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let go = release.clone();
    let h = m
        .submit(
            "",
            "14",
            "t",
            Box::new(move |mon| {
                mon.progress("parts", 0.6);
                mon.progress("parts", 0.3);
                let _ = tx.send(());
                while !go.load(Ordering::SeqCst) {
                    std::thread::yield_now();
                }
                Ok(vec![])
            }),
        )
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    let mid = h.handle.subscribe().borrow().progress;
    release.store(true, Ordering::SeqCst);
    assert_eq!(mid, 0.6);
    assert_eq!(wait_terminal(&h.handle).await.progress, 1.0);
}

/// Work that signals when it starts and ignores cancellation until released (a stage without
/// checkpoints), so a cancel stays pending.
fn deaf(started: mpsc::Sender<()>, release: Arc<std::sync::atomic::AtomicBool>) -> Work {
    Box::new(move |_| {
        let _ = started.send(());
        while !release.load(Ordering::SeqCst) {
            std::thread::yield_now();
        }
        Ok(vec![7])
    })
}

#[tokio::test]
async fn resubmitting_during_a_pending_cancel_starts_a_fresh_job() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let first = m
        .submit("", "21", "t", deaf(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    m.cancel("", "21").unwrap();
    assert_eq!(
        first.handle.snapshot().state,
        JobState::Running,
        "cancel pending"
    );
    let runs = Arc::new(AtomicUsize::new(0));
    let r = runs.clone();
    let retry = m
        .submit(
            "",
            "21",
            "t",
            Box::new(move |_| {
                r.fetch_add(1, Ordering::SeqCst);
                Ok(vec![8])
            }),
        )
        .unwrap();
    assert!(!retry.cached);
    assert_eq!(retry.handle.snapshot().state, JobState::Queued);
    release.store(true, Ordering::SeqCst);
    wait_terminal(&first.handle).await;
    let s = wait_terminal(&retry.handle).await;
    assert_eq!(s.state, JobState::Succeeded);
    assert_eq!(runs.load(Ordering::SeqCst), 1, "the retry computed");
    // The record the tenant sees now is the retry's.
    assert_eq!(
        m.get("", "21").unwrap().snapshot().result.as_deref(),
        Some(&vec![8u8])
    );
}

#[tokio::test]
async fn resubmitting_after_a_cancel_never_inherits_it() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let s = m
        .submit("", "22", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    drop(s.handle.attach()); // the unary caller's deadline passed: the job is cancelled
    assert_eq!(wait_terminal(&s.handle).await.state, JobState::Cancelled);
    let again = m.submit("", "22", "t", gated(tx, release.clone())).unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    release.store(true, Ordering::SeqCst);
    assert_eq!(
        wait_terminal(&again.handle).await.state,
        JobState::Succeeded
    );
}

#[tokio::test]
async fn job_records_belong_to_their_tenant_but_results_are_shared() {
    let m = manager(4);
    let a = m
        .submit("alpha", "31", "t", Box::new(|_| Ok(vec![5])))
        .unwrap();
    assert_eq!(wait_terminal(&a.handle).await.state, JobState::Succeeded);
    assert_eq!(m.list("alpha", 0, 10).0.len(), 1);
    assert!(
        m.list("beta", 0, 10).0.is_empty(),
        "beta lists only its own"
    );
    assert!(
        m.cancel("beta", "31").is_none(),
        "beta cannot cancel alpha's job"
    );
    // beta submitting the same work gets the computed result in a record of its own.
    let b = m
        .submit("beta", "31", "t", Box::new(|_| panic!("recomputed")))
        .unwrap();
    assert!(b.cached);
    assert_eq!(b.handle.snapshot().result.as_deref(), Some(&vec![5u8]));
    assert_eq!(m.list("beta", 0, 10).0.len(), 1);
    assert_eq!(m.executed(), 1);
}

#[tokio::test]
async fn another_tenants_live_job_is_invisible() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let a = m
        .submit("alpha", "32", "t", gated(tx, release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    assert!(m.get("beta", "32").is_none());
    assert!(m.cancel("beta", "32").is_none());
    assert_eq!(a.handle.snapshot().state, JobState::Running);
    release.store(true, Ordering::SeqCst);
    assert_eq!(wait_terminal(&a.handle).await.state, JobState::Succeeded);
}

#[tokio::test]
async fn the_least_served_method_goes_first() {
    let m = manager(16);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    // The blocker computes for at least 50 ms, so "long" is charged far more than the
    // microseconds a short job takes.
    let inner_release = release.clone();
    let blocker = m
        .submit(
            "",
            "40",
            "long",
            Box::new(move |mon| {
                let _ = tx.send(());
                std::thread::sleep(Duration::from_millis(50));
                while !inner_release.load(Ordering::SeqCst) {
                    mon.checkpoint()?;
                    std::thread::yield_now();
                }
                Ok(vec![])
            }),
        )
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    let order = Arc::new(std::sync::Mutex::new(Vec::new()));
    let record = |name: &'static str| -> Work {
        let order = order.clone();
        Box::new(move |_| {
            order.lock().unwrap().push(name);
            Ok(vec![])
        })
    };
    let mut handles = Vec::new();
    for (id, method, name) in [
        ("41", "long", "long1"),
        ("42", "long", "long2"),
        ("43", "long", "long3"),
        ("44", "short", "short1"),
        ("45", "short", "short2"),
    ] {
        handles.push(m.submit("", id, method, record(name)).unwrap().handle);
    }
    release.store(true, Ordering::SeqCst);
    wait_terminal(&blocker.handle).await;
    for h in &handles {
        wait_terminal(h).await;
    }
    // "long" was charged the blocker's compute time: both short jobs run before the queued
    // long ones, whatever the order of submission.
    assert_eq!(
        *order.lock().unwrap(),
        ["short1", "short2", "long1", "long2", "long3"]
    );
}

#[tokio::test]
async fn retry_hint_is_the_time_until_a_slot_frees_with_jitter() {
    let m = JobManager::new(JobsConfig {
        workers: 1,
        concurrent_jobs: 1,
        queue_capacity: 2,
        retry_after: Duration::from_millis(100),
        ..JobsConfig::default()
    })
    .unwrap();
    // One finished job of method "t" taking ~400 ms teaches the manager its compute time.
    let h = m
        .submit(
            "",
            "50",
            "t",
            Box::new(|_| {
                std::thread::sleep(Duration::from_millis(400));
                Ok(vec![])
            }),
        )
        .unwrap();
    wait_terminal(&h.handle).await;
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let running = m
        .submit("", "51", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    for id in ["52", "53"] {
        m.submit("", id, "t", gated(tx.clone(), release.clone()))
            .unwrap();
    }
    assert!(m.queue_full());
    let mut hints = Vec::new();
    for _ in 0..20 {
        match m.submit("", "54", "t", Box::new(|_| Ok(vec![]))) {
            Err(JobsError::QueueFull { retry_after, .. }) => hints.push(retry_after),
            other => panic!("expected a full queue, got {:?}", other.err()),
        }
    }
    // The running "t" job should end ~400 ms after it started: the hint is that remainder
    // (+0-50 %), above the 100 ms floor, and not the 2 × 400 ms of draining the whole queue.
    for h in &hints {
        assert!(
            (0.15..=0.61).contains(&h.as_secs_f64()),
            "hint {h:?} is not the ~0.4 s remainder + 0-50 %"
        );
    }
    assert!(hints.iter().any(|h| *h != hints[0]), "hints are jittered");
    release.store(true, Ordering::SeqCst);
    wait_terminal(&running.handle).await;
}

#[tokio::test]
async fn jobs_stopped_by_shutdown_run_again_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = durable_config(dir.path());
    let m = JobManager::new(cfg.clone()).unwrap();
    assert!(m.journaling());
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let s = m
        .submit_durable(
            "t1",
            "61",
            "t",
            gated(tx, release),
            Some(b"request-61".to_vec()),
        )
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    m.shutdown(Duration::from_millis(20)).await;
    assert_eq!(s.handle.snapshot().error, Some(MurkError::ShuttingDown));

    let again = JobManager::new(cfg).unwrap();
    let requeued = again.recover(|method, bytes| {
        assert_eq!((method, bytes), ("t", &b"request-61"[..]));
        Ok(Box::new(|_| Ok(vec![6, 1])))
    });
    assert_eq!(requeued, 1);
    let h = again.get("t1", "61").expect("the tenant's record is back");
    let snap = wait_terminal(&h).await;
    assert_eq!(snap.result.as_deref(), Some(&vec![6u8, 1]));
    assert_eq!(
        std::fs::read_dir(dir.path().join("journal"))
            .unwrap()
            .count(),
        0,
        "finished jobs leave the journal"
    );
    assert_eq!(again.recover(|_, _| panic!("nothing left")), 0);
}

#[tokio::test]
async fn finished_records_of_every_tenant_come_back_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = durable_config(dir.path());
    let m = JobManager::new(cfg.clone()).unwrap();
    assert_eq!(m.restore_records().unwrap(), 0);
    let ok = m
        .submit("alpha", "a1", "t", Box::new(|_| Ok(vec![1, 2, 3])))
        .unwrap();
    wait_terminal(&ok.handle).await;
    let bad = m
        .submit(
            "alpha",
            "a2",
            "t",
            Box::new(|_| Err(MurkError::invalid("phase", "must be finite"))),
        )
        .unwrap();
    wait_terminal(&bad.handle).await;
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let stopped = m.submit("beta", "b1", "t", gated(tx, release)).unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    m.cancel("beta", "b1").unwrap();
    wait_terminal(&stopped.handle).await;
    // Beta's cache hit on alpha's result is beta's own record.
    assert!(m.find("beta", "a1", "t").unwrap().cached);
    m.shutdown(Duration::from_millis(20)).await;
    drop(m);

    let again = JobManager::new(cfg).unwrap();
    assert_eq!(again.recover(|_, _| panic!("nothing was unfinished")), 0);
    assert_eq!(again.restore_records().unwrap(), 4);
    let snap = |t: &str, id: &str| again.get(t, id).expect("record is back").snapshot();
    let s = snap("alpha", "a1");
    assert_eq!(s.state, JobState::Succeeded);
    assert_eq!(
        s.result.as_deref(),
        Some(&vec![1u8, 2, 3]),
        "result from the cache"
    );
    assert!(s.start_time.is_some() && s.end_time.is_some());
    let s = snap("alpha", "a2");
    assert_eq!(s.state, JobState::Failed);
    assert!(
        matches!(s.error, Some(MurkError::InvalidArgument { ref field, .. }) if field == "phase")
    );
    assert_eq!(snap("beta", "b1").state, JobState::Cancelled);
    let hit = snap("beta", "a1");
    assert!(hit.cached && hit.result.is_some());
    assert!(
        again.get("beta", "a2").is_none(),
        "records stay with their tenant"
    );
    let (alpha, _) = again.list("alpha", 0, 10);
    let ids: Vec<&str> = alpha.iter().map(|s| s.id.as_str()).collect();
    assert_eq!(ids, ["a2", "a1"], "newest first, as before the restart");
    // Resubmitting the failed job runs it again; the succeeded one is a hit on its record.
    assert!(again.find("alpha", "a2", "t").is_none());
    assert!(again.find("alpha", "a1", "t").unwrap().cached);
}
