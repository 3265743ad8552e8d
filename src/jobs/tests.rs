use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Duration;

use super::*;
use crate::error::MurkError;

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
    let a = m.submit("aa", "t", mk(runs.clone())).unwrap();
    assert!(!a.cached);
    let b = m.submit("aa", "t", mk(runs.clone())).unwrap();
    let sa = wait_terminal(&a.handle).await;
    let sb = wait_terminal(&b.handle).await;
    assert_eq!(sa.state, JobState::Succeeded);
    assert_eq!(sb.result.as_deref(), Some(&vec![1u8, 2, 3]));
    let c = m.submit("aa", "t", mk(runs.clone())).unwrap();
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
        .submit("01", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap(); // first is running, queue empty
    m.submit("02", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    let err = m
        .submit("03", "t", gated(tx, release.clone()))
        .err()
        .unwrap();
    assert!(matches!(err, SubmitError::QueueFull { capacity: 1, .. }));
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
        .submit("0a", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    let queued = m.submit("0b", "t", gated(tx, release.clone())).unwrap();
    let snap = m.cancel("0b").unwrap();
    assert_eq!(snap.state, JobState::Cancelled, "queued jobs end at once");
    m.cancel("0a").unwrap();
    assert_eq!(
        wait_terminal(&running.handle).await.state,
        JobState::Cancelled
    );
    assert_eq!(
        wait_terminal(&queued.handle).await.state,
        JobState::Cancelled
    );
    assert!(m.cancel("unknown").is_none());
    // A cancelled job runs again when resubmitted.
    let again = m.submit("0a", "t", Box::new(|_| Ok(vec![9]))).unwrap();
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
        .submit("0c", "t", gated(tx.clone(), release.clone()))
        .unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    let g1 = s.handle.attach();
    let g2 = s.handle.attach();
    drop(g1);
    assert_eq!(s.handle.snapshot().state, JobState::Running);
    drop(g2);
    assert_eq!(wait_terminal(&s.handle).await.state, JobState::Cancelled);

    let d = m.submit("0d", "t", gated(tx, release.clone())).unwrap();
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
            "0e",
            "t",
            Box::new(|_| Err(MurkError::Numerical("diverged".into()))),
        )
        .unwrap();
    let s = wait_terminal(&f.handle).await;
    assert_eq!(s.state, JobState::Failed);
    assert!(matches!(s.error, Some(MurkError::Numerical(_))));
    let p = m.submit("0f", "t", Box::new(|_| panic!("boom"))).unwrap();
    let s = wait_terminal(&p.handle).await;
    assert_eq!(s.state, JobState::Failed);
    assert!(matches!(s.error, Some(MurkError::Internal(ref msg)) if msg.contains("boom")));
    // The dispatcher survived the panic.
    let ok = m.submit("10", "t", Box::new(|_| Ok(vec![]))).unwrap();
    assert_eq!(wait_terminal(&ok.handle).await.state, JobState::Succeeded);
}

#[tokio::test]
async fn shutdown_drains_then_cancels_and_refuses_new_work() {
    let m = manager(4);
    let release = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let s = m.submit("11", "t", gated(tx, release)).unwrap();
    rx.recv_timeout(Duration::from_secs(10)).unwrap();
    m.shutdown(Duration::from_millis(50)).await;
    assert_eq!(s.handle.snapshot().state, JobState::Cancelled);
    assert_eq!(
        m.submit("12", "t", Box::new(|_| Ok(vec![]))).err(),
        Some(SubmitError::ShuttingDown)
    );
}

#[tokio::test]
async fn list_is_newest_first_and_paged() {
    let m = manager(16);
    for i in 0..5 {
        let h = m
            .submit(&format!("{i:02x}"), "t", Box::new(|_| Ok(vec![])))
            .unwrap();
        wait_terminal(&h.handle).await;
    }
    let (page, next) = m.list(0, 2);
    assert_eq!(
        page.iter().map(|s| s.id.as_str()).collect::<Vec<_>>(),
        ["04", "03"]
    );
    assert_eq!(next, Some(2));
    let (page, next) = m.list(4, 2);
    assert_eq!(page.len(), 1);
    assert_eq!(next, None);
}

#[tokio::test]
async fn progress_reaches_watchers() {
    let m = manager(4);
    let h = m
        .submit(
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
