//! Prometheus metrics of a server: one registry per server (so several in-process servers never
//! mix their numbers), the job system's event families, the RPC families, scrape-time gauges
//! read from the job manager, and a small HTTP/1.1 endpoint that serves them at `/metrics`.
//!
//! Names follow Triton's metric set in spirit: queue depth and running jobs as gauges, jobs by
//! method and terminal state, compute time and queue wait as histograms, cache hits and misses.

use std::convert::Infallible;
use std::future::Future;
use std::sync::Arc;

use bytes::Bytes;
use http_body_util::Full;
use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper_util::rt::TokioIo;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::Registry;
use tokio::net::TcpListener;

use crate::jobs::JobBackend;
use crate::service::grpc_metrics::GrpcMetrics;
use crate::service::sessions::SessionMetrics;

/// OpenMetrics text, which Prometheus scrapes natively.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// A server's metrics registry.
#[derive(Debug)]
pub struct Telemetry {
    registry: Registry,
    grpc: GrpcMetrics,
    sessions: SessionMetrics,
}

impl Telemetry {
    /// The registry for a server around `jobs`.
    pub fn new(jobs: Arc<dyn JobBackend>) -> Arc<Self> {
        let mut registry = Registry::with_prefix("murk");
        jobs.local().metrics().register(&mut registry);
        let grpc = GrpcMetrics::default();
        grpc.register(&mut registry);
        let sessions = SessionMetrics::default();
        sessions.register(&mut registry);
        registry.register_collector(Box::new(JobGauges { jobs }));
        Arc::new(Self {
            registry,
            grpc,
            sessions,
        })
    }

    /// The RPC families (for the request-metrics layer).
    pub fn grpc(&self) -> &GrpcMetrics {
        &self.grpc
    }

    /// The session families (for the `Sessions` service).
    pub fn sessions(&self) -> &SessionMetrics {
        &self.sessions
    }

    /// The current values in OpenMetrics text.
    pub fn encode(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut out, &self.registry);
        out
    }
}

/// Values read from the job manager at scrape time.
struct JobGauges {
    jobs: Arc<dyn JobBackend>,
}

impl std::fmt::Debug for JobGauges {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("JobGauges")
    }
}

impl Collector for JobGauges {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let local = self.jobs.local();
        let cache = local.cache_stats();
        let gauges = [
            (
                "queue_depth",
                "Jobs waiting in the queue (the shared queue of all replicas with Redis)",
                self.jobs.queue_depth() as i64,
            ),
            (
                "queue_capacity",
                "Jobs the queue may hold",
                local.config().queue_capacity as i64,
            ),
            (
                "jobs_running",
                "Jobs being computed by this replica",
                local.running() as i64,
            ),
            (
                "cache_bytes",
                "Bytes of results held in the in-memory cache",
                cache.memory_bytes as i64,
            ),
            (
                "cache_entries",
                "Results held in the in-memory cache",
                cache.memory_entries as i64,
            ),
            (
                "cache_disk_bytes",
                "Bytes of result files in the cache directory",
                cache.disk_bytes as i64,
            ),
        ];
        let redis = self.jobs.store_up().map(|up| {
            (
                "redis_up",
                "1 while this replica's periodic Redis query (every second) is answered, else 0",
                i64::from(up),
            )
        });
        for (name, help, value) in gauges.into_iter().chain(redis) {
            let g = ConstGauge::new(value);
            g.encode(encoder.encode_descriptor(name, help, None, g.metric_type())?)?;
        }
        Ok(())
    }
}

/// Serves `GET /metrics` on `listener` until `shutdown` resolves. Any other path is 404.
pub async fn serve_metrics(
    listener: TcpListener,
    telemetry: Arc<Telemetry>,
    shutdown: impl Future<Output = ()>,
) {
    tokio::pin!(shutdown);
    loop {
        let accepted = tokio::select! {
            _ = &mut shutdown => return,
            a = listener.accept() => a,
        };
        let (stream, _) = match accepted {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!(error = %e, "metrics endpoint: accept failed");
                continue;
            }
        };
        let telemetry = telemetry.clone();
        tokio::spawn(async move {
            let svc = service_fn(move |req: hyper::Request<hyper::body::Incoming>| {
                let telemetry = telemetry.clone();
                async move {
                    let response = if req.uri().path() == "/metrics" {
                        hyper::Response::builder()
                            .header(hyper::header::CONTENT_TYPE, CONTENT_TYPE)
                            .body(Full::new(Bytes::from(telemetry.encode())))
                    } else {
                        hyper::Response::builder()
                            .status(hyper::StatusCode::NOT_FOUND)
                            .body(Full::new(Bytes::from_static(b"metrics are at /metrics\n")))
                    };
                    Ok::<_, Infallible>(response.unwrap_or_default())
                }
            });
            if let Err(e) = http1::Builder::new()
                .serve_connection(TokioIo::new(stream), svc)
                .await
            {
                tracing::debug!(error = %e, "metrics connection ended");
            }
        });
    }
}
