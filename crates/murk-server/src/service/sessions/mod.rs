//! The `Sessions` service: a robot's sensor stream answered frame by frame
//! (`proto/murk/v1/sessions.proto`).
//!
//! - [`plan`]: the configuration, validated once, and one frame's computation;
//! - [`queue`]: the frame queue and its policy (LATEST drops the oldest, FIFO pushes back);
//! - [`run`]: the session's reader and worker;
//! - [`registry`]: sessions per replica and per tenant, bounded;
//! - [`metrics`]: frames in, out and dropped, latency, open sessions.
//!
//! A session keeps its configuration and nothing else between frames; its memory is bounded by
//! `max_queued_frames` frames plus the one being computed.

pub mod metrics;
pub mod plan;
pub mod queue;
pub mod registry;
mod run;

use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use futures::Stream;
use tokio::sync::{mpsc, watch};
use tonic::{Code, Request, Response, Status, Streaming};
use tonic_types::{ErrorDetails, StatusExt};

use crate::jobs::JobManager;
use crate::service::auth::Tenant;
use crate::service::convert::ImageLimits;
use crate::service::oversize::oversize_request;
use crate::service::proto::v1 as pb;
use crate::service::status::to_status;
use murk::error::MurkError;

pub use metrics::SessionMetrics;
pub use plan::{SessionMethod, SessionPlan, MAX_FRAME_ID_BYTES, MAX_QUEUED_FRAMES};
pub use registry::{Refusal, SessionLimits, SessionRegistry};

/// The `murk.v1.Sessions` service. Cheap to clone.
#[derive(Clone)]
pub struct SessionsApi {
    registry: SessionRegistry,
    limits: ImageLimits,
    jobs: JobManager,
    metrics: SessionMetrics,
    stop: watch::Receiver<bool>,
    next_id: Arc<AtomicU64>,
    /// One frame computes at a time on this replica, taken in the order the sessions asked
    /// (tokio's semaphore is first-come first-served): see [`run::FrameGate`].
    gate: run::FrameGate,
}

impl SessionsApi {
    /// Sessions on `jobs`' compute pool, bounded by `limits`, with frames under `images`;
    /// they end when `stop` turns true.
    pub fn new(
        limits: SessionLimits,
        images: ImageLimits,
        jobs: JobManager,
        metrics: SessionMetrics,
        stop: watch::Receiver<bool>,
    ) -> Self {
        Self {
            registry: SessionRegistry::new(limits),
            limits: images,
            jobs,
            metrics,
            stop,
            next_id: Arc::default(),
            gate: run::FrameGate::default(),
        }
    }
}

/// RESOURCE_EXHAUSTED with a retry hint for a refused session.
fn refusal_status(r: &Refusal) -> Status {
    let message = match r {
        Refusal::Replica(n) => format!(
            "this replica has its maximum of {n} sessions open; retry later or on another replica"
        ),
        Refusal::Tenant(n) => format!(
            "this tenant has its maximum of {n} sessions open on this replica; end one first"
        ),
    };
    Status::with_error_details(
        Code::ResourceExhausted,
        message,
        ErrorDetails::with_retry_info(Some(Duration::from_secs(1))),
    )
}

type EventStream = Pin<Box<dyn Stream<Item = Result<pb::SessionEvent, Status>> + Send>>;

#[tonic::async_trait]
impl pb::sessions_server::Sessions for SessionsApi {
    type StreamStream = EventStream;

    async fn stream(
        &self,
        request: Request<Streaming<pb::SessionRequest>>,
    ) -> Result<Response<Self::StreamStream>, Status> {
        let tenant = Tenant::of(&request);
        let slot = self
            .registry
            .open(&tenant)
            .map_err(|r| refusal_status(&r))?;
        let mut inbound = request.into_inner();
        // A few events of slack: results wait here while the client reads, then the worker
        // waits for the client (a slow reader slows its own session only).
        let (events, rx) = mpsc::channel(4);
        let api = self.clone();
        let id = format!(
            "s{}-{}",
            std::process::id(),
            self.next_id.fetch_add(1, Ordering::Relaxed)
        );
        tokio::spawn(async move {
            let _slot = slot;
            let timeout = api.registry.limits().config_timeout;
            let first = tokio::time::timeout(timeout, inbound.message()).await;
            let config = match first {
                Err(_) => {
                    let _ = events
                        .send(Err(Status::deadline_exceeded(format!(
                            "no session configuration within {timeout:?}"
                        ))))
                        .await;
                    return;
                }
                // A configuration over the request limit: the stream cannot go on after it.
                Ok(Err(status)) => {
                    if let Some(s) = oversize_request(&status) {
                        let _ = events.send(Err(s)).await;
                    }
                    return;
                }
                // The client went away before configuring.
                Ok(Ok(None)) => return,
                Ok(Ok(Some(pb::SessionRequest {
                    message: Some(pb::session_request::Message::Config(c)),
                }))) => c,
                Ok(Ok(Some(_))) => {
                    let e = MurkError::invalid(
                        "config",
                        "the first message of a session must configure it",
                    );
                    let _ = events.send(Err(to_status(&e))).await;
                    return;
                }
            };
            let plan = match SessionPlan::from_proto(&config, &api.limits) {
                Ok(p) => p,
                Err(e) => {
                    let _ = events.send(Err(to_status(&e.within("config")))).await;
                    return;
                }
            };
            let ctx = run::SessionContext {
                id,
                plan: Arc::new(plan),
                limits: api.limits,
                jobs: api.jobs.clone(),
                metrics: api.metrics.clone(),
                stop: api.stop.clone(),
                gate: api.gate.clone(),
            };
            run::run(ctx, inbound, events).await;
        });
        let stream = futures::stream::unfold(rx, |mut rx| async move {
            rx.recv().await.map(|event| (event, rx))
        });
        Ok(Response::new(Box::pin(stream)))
    }
}
