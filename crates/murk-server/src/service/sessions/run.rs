//! One session's life once configured: a reader task moves frames from the stream into the
//! queue (reporting the frames the LATEST policy pushes out), and the session's own task
//! computes them one at a time, in order, on the job system's compute pool, where they share
//! the cores with one-shot jobs and the other sessions (one frame in flight per session, so
//! sessions get an even share).
//!
//! The session ends when the client half-closes the stream (after the queued frames), when it
//! cancels or disconnects (the frame being computed is cancelled), or when the server shuts
//! down (UNAVAILABLE: reconnect elsewhere).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use tokio::sync::{mpsc, watch};
use tonic::{Status, Streaming};

use super::metrics::SessionMetrics;
use super::plan::SessionPlan;
use super::queue::{FrameQueue, Queued};
use crate::jobs::JobManager;
use crate::service::convert::ImageLimits;
use crate::service::oversize::oversize_request;
use crate::service::proto::v1 as pb;
use crate::service::status::{job_error, to_status};
use murk::error::MurkError;
use murk::monitor::Monitor;

/// The events a session sends; an `Err` ends the stream.
pub(super) type Events = mpsc::Sender<Result<pb::SessionEvent, Status>>;

/// What a configured session runs with.
pub(super) struct SessionContext {
    /// Its id (logs, `SessionStarted`).
    pub id: String,
    /// The validated configuration.
    pub plan: Arc<SessionPlan>,
    /// Per-image limits for the frames.
    pub limits: ImageLimits,
    /// The compute pool's owner.
    pub jobs: JobManager,
    /// Frame and session metrics.
    pub metrics: SessionMetrics,
    /// Turns true when the server shuts down.
    pub stop: watch::Receiver<bool>,
    /// The replica's turn to compute a frame.
    pub gate: FrameGate,
}

/// Whose frame computes next on this replica. A frame uses every core of the compute pool, so
/// two frames computing at once only split the cores, and rayon's work stealing splits them
/// unevenly: of two sessions overloading one replica, one got 0.69 of the other's frames and a
/// p99 latency of 4.8 compute times. One frame at a time, in the order the sessions became
/// ready (tokio's semaphore queues its waiters first-come first-served), gives each of N busy
/// sessions every N-th turn and bounds a frame's wait by the other sessions' frames.
#[derive(Clone, Debug)]
pub(super) struct FrameGate(Arc<tokio::sync::Semaphore>);

impl Default for FrameGate {
    fn default() -> Self {
        Self(Arc::new(tokio::sync::Semaphore::new(1)))
    }
}

impl FrameGate {
    /// Waits for this session's turn; the turn ends when the permit is dropped.
    async fn turn(&self) -> tokio::sync::OwnedSemaphorePermit {
        // Never closed, so acquiring cannot fail.
        self.0
            .clone()
            .acquire_owned()
            .await
            .expect("the frame gate is never closed")
    }
}

/// Counts the session as open for its life.
struct OpenGauge(SessionMetrics, &'static str);

impl Drop for OpenGauge {
    fn drop(&mut self) {
        self.0.open(self.1, -1);
    }
}

fn event(e: pb::session_event::Event) -> pb::SessionEvent {
    pb::SessionEvent { event: Some(e) }
}

fn dropped(frame: &pb::SessionFrame, reason: pb::DropReason) -> pb::SessionEvent {
    event(pb::session_event::Event::Dropped(pb::FrameDropped {
        sequence: frame.sequence,
        frame_id: frame.frame_id.clone(),
        stamp: frame.stamp,
        reason: reason as i32,
    }))
}

/// Resolves once the server starts shutting down (or is gone).
async fn stopped(stop: &mut watch::Receiver<bool>) {
    // The borrowed value is dropped here: it must not live across the caller's awaits.
    let _ = stop.wait_for(|s| *s).await.map(|_| ());
}

/// The status that ends a session when the server shuts down.
fn shutting_down() -> Result<pb::SessionEvent, Status> {
    Err(Status::unavailable(
        "the server is shutting down; open a new session (it starts cold)",
    ))
}

/// `wait`'s output, unless the client goes away or the server stops first: then why the
/// session ends (a stopping server first tells the client).
async fn unless_ended<T>(
    wait: impl std::future::Future<Output = T>,
    events: &Events,
    stop: &mut watch::Receiver<bool>,
) -> Result<T, &'static str> {
    tokio::select! {
        t = wait => Ok(t),
        _ = events.closed() => Err("client gone"),
        _ = stopped(stop) => {
            let _ = events.send(shutting_down()).await;
            Err("server shutdown")
        }
    }
}

/// Runs a configured session to its end.
pub(super) async fn run(
    ctx: SessionContext,
    inbound: Streaming<pb::SessionRequest>,
    events: Events,
) {
    let method = ctx.plan.method.name();
    ctx.metrics.open(method, 1);
    let _open = OpenGauge(ctx.metrics.clone(), method);
    let started = pb::SessionStarted {
        session_id: ctx.id.clone(),
        queue_policy: ctx.plan.policy as i32,
        max_queued_frames: ctx.plan.capacity as u32,
    };
    if events
        .send(Ok(event(pb::session_event::Event::Started(started))))
        .await
        .is_err()
    {
        return;
    }
    tracing::info!(session = %ctx.id, method, width = ctx.plan.dims.0, height = ctx.plan.dims.1, "session started");
    let queue = Arc::new(FrameQueue::new(ctx.plan.capacity, ctx.plan.policy));
    let reader = tokio::spawn(read_frames(
        inbound,
        queue.clone(),
        events.clone(),
        ctx.metrics.clone(),
        method,
    ));
    let (computed, why) = compute_frames(&ctx, &queue, &events, method).await;
    reader.abort();
    tracing::info!(session = %ctx.id, method, computed, why, "session ended");
}

/// The worker: frames in order until the queue closes, the client goes away or the server
/// stops. Returns the number of frames computed and why it stopped.
async fn compute_frames(
    ctx: &SessionContext,
    queue: &FrameQueue,
    events: &Events,
    method: &'static str,
) -> (u64, &'static str) {
    let mut stop = ctx.stop.clone();
    let mut computed = 0;
    // Moved into each frame's computation and back.
    let mut state = match ctx.plan.initial_state() {
        Ok(s) => Some(s),
        Err(e) => {
            let _ = events.send(Err(to_status(&e.within("config")))).await;
            return (0, "bad configuration");
        }
    };
    loop {
        match unless_ended(queue.wait_ready(), events, &mut stop).await {
            Ok(true) => {}
            Ok(false) => return (computed, "stream closed by the client"),
            Err(why) => return (computed, why),
        }
        // Held until this frame's answer is computed; LATEST keeps replacing the waiting frame
        // meanwhile, so the frame popped below is the newest.
        let turn = match unless_ended(ctx.gate.turn(), events, &mut stop).await {
            Ok(t) => t,
            Err(why) => return (computed, why),
        };
        let Some(Queued { frame, arrived }) = queue.pop().await else {
            return (computed, "stream closed by the client");
        };
        let queue_seconds = arrived.elapsed();
        if ctx.plan.deadline.is_some_and(|d| queue_seconds > d) {
            ctx.metrics.frame(method, "deadline");
            if events
                .send(Ok(dropped(&frame, pb::DropReason::Deadline)))
                .await
                .is_err()
            {
                return (computed, "client gone");
            }
            continue;
        }
        let cancelled = Arc::new(AtomicBool::new(false));
        let monitor = Monitor::new(cancelled.clone(), None);
        let (plan, jobs, limits) = (ctx.plan.clone(), ctx.jobs.clone(), ctx.limits);
        let meta = (frame.sequence, frame.frame_id.clone(), frame.stamp);
        let begun = Instant::now();
        let mut frame_state = state.take();
        let work = tokio::task::spawn_blocking(move || {
            let out = jobs.install(|| match frame_state.as_mut() {
                Some(s) => plan.compute(&frame, &limits, &monitor, s),
                None => Err(MurkError::Internal("session state lost".into())),
            });
            (out, frame_state)
        });
        let outcome = tokio::select! {
            r = work => r,
            _ = events.closed() => {
                cancelled.store(true, Ordering::Relaxed);
                return (computed, "client gone");
            }
            _ = stopped(&mut stop) => {
                cancelled.store(true, Ordering::Relaxed);
                let _ = events.send(shutting_down()).await;
                return (computed, "server shutdown");
            }
        };
        let compute_seconds = begun.elapsed().as_secs_f64();
        // The next session's turn: sending the answer may wait on this client.
        drop(turn);
        let (outcome, warnings) = match outcome {
            Ok((Ok((o, warnings)), back)) => {
                state = back;
                ctx.metrics.frame(method, "computed");
                (o, warnings)
            }
            Ok((Err(e), back)) => {
                state = back;
                ctx.metrics.frame(method, "failed");
                if !matches!(e, MurkError::InvalidArgument { .. }) {
                    tracing::warn!(session = %ctx.id, sequence = meta.0, error = %e, "frame failed");
                }
                let error = job_error(&e.within("frame"));
                (pb::frame_result::Outcome::Error(error), Vec::new())
            }
            Err(join) => {
                // The state went down with the computation: the next frame starts cold.
                state = ctx.plan.initial_state().ok();
                ctx.metrics.frame(method, "failed");
                tracing::error!(session = %ctx.id, sequence = meta.0, error = %join, "frame computation panicked");
                let error = job_error(&MurkError::Internal(format!(
                    "the frame's computation failed: {join}"
                )));
                (pb::frame_result::Outcome::Error(error), Vec::new())
            }
        };
        computed += 1;
        ctx.metrics.latency(method, arrived.elapsed().as_secs_f64());
        let result = pb::FrameResult {
            sequence: meta.0,
            frame_id: meta.1,
            stamp: meta.2,
            queue_seconds: queue_seconds.as_secs_f64(),
            compute_seconds,
            outcome: Some(outcome),
            warnings,
        };
        if events
            .send(Ok(event(pb::session_event::Event::Result(result))))
            .await
            .is_err()
        {
            return (computed, "client gone");
        }
    }
}

/// The reader: frames into the queue until the client half-closes, fails or goes away.
async fn read_frames(
    mut inbound: Streaming<pb::SessionRequest>,
    queue: Arc<FrameQueue>,
    events: Events,
    metrics: SessionMetrics,
    method: &'static str,
) {
    use pb::session_request::Message;
    loop {
        let message = tokio::select! {
            m = inbound.message() => m,
            _ = events.closed() => break,
        };
        let refused = match message {
            Ok(Some(pb::SessionRequest {
                message: Some(Message::Frame(frame)),
            })) => {
                metrics.frame(method, "received");
                let arrived = Instant::now();
                if let Some(old) = queue.push(Queued { frame, arrived }).await {
                    metrics.frame(method, "superseded");
                    if events
                        .send(Ok(dropped(&old.frame, pb::DropReason::Superseded)))
                        .await
                        .is_err()
                    {
                        break;
                    }
                }
                continue;
            }
            Ok(Some(pb::SessionRequest {
                message: Some(Message::Config(_)),
            })) => MurkError::invalid(
                "config",
                "a session's configuration cannot change; end this session and open a new one",
            ),
            Ok(Some(pb::SessionRequest { message: None })) => {
                MurkError::invalid("message", "empty: set config or frame")
            }
            // Half-closed: the queued frames are still computed.
            Ok(None) => break,
            // A frame over the request limit ends the session (the transport cannot find the
            // next message after it): RESOURCE_EXHAUSTED, as for any oversize request. Frames
            // queued before it are dropped with the stream.
            Err(status) => {
                if let Some(s) = oversize_request(&status) {
                    let _ = events.send(Err(s)).await;
                }
                // Otherwise the client cancelled, or its stream broke.
                break;
            }
        };
        let e = event(pb::session_event::Event::Refused(job_error(&refused)));
        if events.send(Ok(e)).await.is_err() {
            break;
        }
    }
    queue.close();
}

#[cfg(test)]
mod gate_tests {
    use super::FrameGate;
    use std::sync::{Arc, Mutex};

    #[tokio::test]
    async fn turns_go_one_at_a_time_in_the_order_they_were_asked_for() {
        let gate = FrameGate::default();
        let first = gate.turn().await;
        let order = Arc::new(Mutex::new(Vec::new()));
        let mut waiters = Vec::new();
        for k in 0..3 {
            let (gate, order) = (gate.clone(), order.clone());
            waiters.push(tokio::spawn(async move {
                let _turn = gate.turn().await;
                order.lock().unwrap().push(k);
            }));
            // On the test's single-threaded runtime this runs the waiter until it queues.
            tokio::task::yield_now().await;
        }
        assert!(
            order.lock().unwrap().is_empty(),
            "nobody passes a held turn"
        );
        drop(first);
        for w in waiters {
            w.await.unwrap();
        }
        assert_eq!(*order.lock().unwrap(), vec![0, 1, 2]);
    }
}
