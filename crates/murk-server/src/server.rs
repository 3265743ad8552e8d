//! Assembling and running the gRPC server: Jobs + Reconstruction + grpc.health.v1 + reflection,
//! behind tower layers for request metrics, request ids and bearer-token authentication, over
//! plain TCP or TLS (optionally mutual), with a Prometheus endpoint, explicit limits and graceful
//! shutdown (health goes NOT_SERVING, stop accepting, drain for a grace period, abort the rest
//! with a retryable status).

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use crate::connections::ConnectionLimits;
use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::{oneshot, watch};
use tonic::codec::CompressionEncoding;
use tonic::transport::{Certificate, Identity, Server, ServerTlsConfig};

use std::sync::Arc;

use crate::jobs::redis::{RedisConfig, RedisJobs};
use crate::jobs::{JobBackend, JobManager, JobsConfig};
use crate::service::auth::{AuthLayer, TokenStore};
use crate::service::convert::{AirlightService, ImageLimits};
use crate::service::grpc_metrics::MetricsLayer;
use crate::service::oversize::oversize_layer;
use crate::service::proto::v1::jobs_server::JobsServer;
use crate::service::proto::v1::reconstruction_server::ReconstructionServer;
use crate::service::proto::v1::sessions_server::SessionsServer;
use crate::service::proto::FILE_DESCRIPTOR_SET;
use crate::service::request_id::RequestIdLayer;
use crate::service::watchers::WatchLimits;
use crate::service::{
    CacheScope, JobsApi, ReconstructionApi, RequestLimits, ServiceState,
    DEFAULT_MAX_UNARY_RESULT_BYTES,
};
use crate::service::{SessionLimits, SessionsApi};
use crate::telemetry::{serve_metrics, Telemetry};
use murk::params::airlight::AirlightEstimator;

/// Default request limit: a dozen 16-bit 1-megapixel images (≈ 24 MiB) plus headroom.
pub const DEFAULT_MAX_REQUEST_BYTES: usize = 32 << 20;

/// Everything that configures a server.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    /// Job system sizing.
    pub jobs: JobsConfig,
    /// Largest request message accepted, bytes, as it arrives (after decompression), unknown
    /// fields included; larger → RESOURCE_EXHAUSTED before anything is decoded.
    pub max_request_bytes: usize,
    /// Largest image accepted, pixels.
    pub max_image_pixels: u64,
    /// Largest forward-scatter kernel a photometric-stereo job may store, bytes (the method's
    /// memory peak: object pixels × r² × 4).
    pub max_ps_kernel_bytes: usize,
    /// How long shutdown waits for queued and running jobs before cancelling them.
    pub shutdown_grace: Duration,
    /// The airlight estimator of scattering-parameter requests that do not name one (loaded
    /// by the caller, so a bad weights file fails before the server starts).
    pub airlight: AirlightEstimator,
    /// Largest message a unary response may carry (see `ServiceState`).
    pub max_unary_result_bytes: usize,
    /// Bearer tokens and their tenants; `None` serves everyone as the default tenant.
    pub auth: Option<TokenStore>,
    /// Whose identical requests share results; `None`: per tenant with `auth`, else global
    /// ([`CacheScope::default_for`]).
    pub cache_scope: Option<CacheScope>,
    /// TLS (optionally mutual); `None` serves plain HTTP/2.
    pub tls: Option<TlsSettings>,
    /// Share jobs, queue and results with other replicas through Redis; `None` keeps them in
    /// this process (the embedded default).
    pub redis: Option<RedisConfig>,
    /// Sensor sessions per replica and per tenant.
    pub sessions: SessionLimits,
    /// Connections before any request: how many, how fast they must speak, keepalive.
    pub connections: ConnectionLimits,
    /// Watch streams per job and per tenant, and the result bytes they may hold.
    pub watchers: WatchLimits,
}

/// PEM material for TLS.
#[derive(Clone)]
pub struct TlsSettings {
    /// The server's certificate chain.
    pub cert_pem: Vec<u8>,
    /// The server's private key.
    pub key_pem: Vec<u8>,
    /// CA certificates that client certificates must chain to; `Some` requires a client
    /// certificate from every connection (mutual TLS).
    pub client_ca_pem: Option<Vec<u8>>,
}

impl std::fmt::Debug for TlsSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never print key material.
        f.debug_struct("TlsSettings")
            .field("mutual", &self.client_ca_pem.is_some())
            .finish()
    }
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            jobs: JobsConfig::default(),
            max_request_bytes: DEFAULT_MAX_REQUEST_BYTES,
            max_image_pixels: 16 << 20,
            max_ps_kernel_bytes: murk::ps::pipeline::DEFAULT_MAX_KERNEL_BYTES,
            shutdown_grace: Duration::from_secs(10),
            airlight: AirlightEstimator::from_config(None, true)
                .unwrap_or(AirlightEstimator::DarkChannel(Default::default())),
            max_unary_result_bytes: DEFAULT_MAX_UNARY_RESULT_BYTES,
            auth: None,
            cache_scope: None,
            tls: None,
            redis: None,
            sessions: SessionLimits::default(),
            connections: ConnectionLimits::default(),
            watchers: WatchLimits::default(),
        }
    }
}

/// Failures starting or running the server.
#[derive(Debug, Error)]
pub enum ServerError {
    /// Binding, thread or cache-directory setup failed.
    #[error("i/o: {0}")]
    Io(#[from] std::io::Error),
    /// The gRPC transport failed.
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// Reflection descriptors could not be loaded.
    #[error("reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The job backend could not be set up (e.g. a malformed Redis URL).
    #[error("job backend: {0}")]
    Backend(#[from] murk::error::MurkError),
}

/// Serves on `listener` (and Prometheus metrics on `metrics`, if given) until `shutdown`
/// resolves, then shuts down gracefully.
pub async fn serve(
    config: ServerConfig,
    listener: TcpListener,
    metrics: Option<TcpListener>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let manager = JobManager::new(config.jobs.clone())?;
    serve_with_manager(config, manager, listener, metrics, shutdown).await
}

async fn serve_with_manager(
    config: ServerConfig,
    manager: JobManager,
    listener: TcpListener,
    metrics: Option<TcpListener>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let limits = RequestLimits {
        images: ImageLimits {
            max_pixels: config.max_image_pixels,
            max_channels: 4,
        },
        max_ps_kernel_bytes: config.max_ps_kernel_bytes,
    };
    let airlight = AirlightService::new(config.airlight.clone());
    let backend: Arc<dyn JobBackend> = match &config.redis {
        None => Arc::new(manager.clone()),
        Some(redis) => {
            let airlight = airlight.clone();
            let rebuild: crate::jobs::redis::Rebuild =
                Arc::new(move |_, bytes| crate::service::rebuild_work(bytes, &limits, &airlight));
            Arc::new(RedisJobs::start(manager.clone(), redis.clone(), rebuild)?)
        }
    };
    let telemetry = Telemetry::new(backend.clone());
    // Tells the metrics endpoint to stop once the gRPC server has.
    let (stopped_tx, stopped_rx) = watch::channel(false);
    if let Some(l) = metrics {
        tracing::info!(addr = %l.local_addr()?, "metrics at /metrics");
        let mut rx = stopped_rx.clone();
        tokio::spawn(serve_metrics(l, telemetry.clone(), async move {
            let _ = rx.wait_for(|s| *s).await;
        }));
    }
    let cache_scope = config
        .cache_scope
        .unwrap_or_else(|| CacheScope::default_for(config.auth.is_some()));
    let state = ServiceState {
        jobs: backend.clone(),
        limits,
        airlight,
        max_unary_result_bytes: config.max_unary_result_bytes,
        cache_scope,
    };
    // Jobs accepted before a crash (or stopped by a shutdown) run again; decoding their images
    // is CPU work, so off the runtime's threads. (With Redis the shared queue keeps them.)
    let requeued = if config.redis.is_some() {
        0
    } else {
        let (m, limits, airlight) = (manager.clone(), state.limits, state.airlight.clone());
        tokio::task::spawn_blocking(move || {
            let requeued =
                m.recover(|_, bytes| crate::service::rebuild_work(bytes, &limits, &airlight));
            // Records of jobs that ended before the restart; after the re-queue, so a job
            // resubmitted since an old record of it wins.
            if let Err(e) = m.restore_records() {
                tracing::error!(error = %e, "could not read the job-record log; earlier jobs' records are not restored");
            }
            requeued
        })
        .await
        .unwrap_or(0)
    };
    if requeued > 0 {
        tracing::info!(requeued, "jobs from the journal re-queued");
    }
    // The one request limit, on the wire: every byte counts, unknown fields too.
    let transport_limit = config.max_request_bytes;
    // Responses are compressed only for clients that advertise the encoding.
    let jobs = JobsServer::new(JobsApi::new(state.clone(), config.watchers))
        .max_decoding_message_size(transport_limit)
        .max_encoding_message_size(usize::MAX)
        .accept_compressed(CompressionEncoding::Gzip)
        .accept_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Gzip);
    // Sessions end (UNAVAILABLE) when shutdown starts, so their streams do not hold it up.
    let (sessions_stop_tx, sessions_stop_rx) = watch::channel(false);
    let sessions = SessionsServer::new(SessionsApi::new(
        config.sessions,
        state.limits.images,
        manager.clone(),
        telemetry.sessions().clone(),
        sessions_stop_rx,
    ))
    .max_decoding_message_size(transport_limit)
    .max_encoding_message_size(usize::MAX)
    .accept_compressed(CompressionEncoding::Gzip)
    .accept_compressed(CompressionEncoding::Zstd)
    .send_compressed(CompressionEncoding::Zstd)
    .send_compressed(CompressionEncoding::Gzip);
    let recon = ReconstructionServer::new(ReconstructionApi::new(state))
        .max_decoding_message_size(transport_limit)
        .max_encoding_message_size(usize::MAX)
        .accept_compressed(CompressionEncoding::Gzip)
        .accept_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Gzip);

    let (health_reporter, health) = tonic_health::server::health_reporter();
    health_reporter.set_serving::<JobsServer<JobsApi>>().await;
    health_reporter
        .set_serving::<ReconstructionServer<ReconstructionApi>>()
        .await;
    health_reporter
        .set_serving::<SessionsServer<SessionsApi>>()
        .await;
    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        // google.rpc.BadRequest / RetryInfo / PreconditionFailure, so grpcurl can decode the
        // error details murk sends.
        .register_encoded_file_descriptor_set(tonic_types::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_types::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    let addr = listener.local_addr()?;
    tracing::info!(
        %addr,
        workers = manager.worker_threads(),
        queue = config.jobs.queue_capacity,
        backend = backend.kind(),
        max_request_bytes = config.max_request_bytes,
        auth = config.auth.is_some(),
        ?cache_scope,
        tls = config.tls.is_some(),
        mutual_tls = config.tls.as_ref().is_some_and(|t| t.client_ca_pem.is_some()),
        "murk serving"
    );
    let grace = config.shutdown_grace;
    let drain = backend.clone();
    let stop = async move {
        shutdown.await;
        tracing::info!(?grace, "shutting down: draining jobs");
        // The overall status first: balancers probing "" stop sending work at once.
        health_reporter
            .set_service_status("", tonic_health::ServingStatus::NotServing)
            .await;
        health_reporter
            .set_not_serving::<JobsServer<JobsApi>>()
            .await;
        health_reporter
            .set_not_serving::<ReconstructionServer<ReconstructionApi>>()
            .await;
        health_reporter
            .set_not_serving::<SessionsServer<SessionsApi>>()
            .await;
        let _ = sessions_stop_tx.send(true);
        drain.shutdown(grace).await;
    };
    let mut builder = config.connections.apply(Server::builder());
    if let Some(tls) = &config.tls {
        let mut tls_config =
            ServerTlsConfig::new().identity(Identity::from_pem(&tls.cert_pem, &tls.key_pem));
        if let Some(ca) = &tls.client_ca_pem {
            tls_config = tls_config.client_ca_root(Certificate::from_pem(ca));
        }
        builder = builder.tls_config(tls_config)?;
    }
    // After the drain, open connections get a GOAWAY and a moment to finish; a peer that
    // neither reads nor closes must not hold the shutdown until keepalive gives up on it.
    let (drained_tx, drained_rx) = oneshot::channel::<()>();
    let stop = async move {
        stop.await;
        let _ = drained_tx.send(());
    };
    // Outermost first: every request is counted (refused ones too) and carries a request id.
    let serving = builder
        .layer(MetricsLayer::new(telemetry.grpc().clone()))
        .layer(RequestIdLayer)
        .layer(AuthLayer::new(
            config.auth.clone(),
            telemetry.grpc().clone(),
        ))
        .layer(oversize_layer())
        .add_service(health)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(jobs)
        .add_service(recon)
        .add_service(sessions)
        .serve_with_incoming_shutdown(config.connections.incoming(listener), stop);
    let served = tokio::select! {
        served = serving => served,
        () = async {
            if drained_rx.await.is_ok() {
                tokio::time::sleep(CONNECTION_CLOSE_GRACE).await;
            } else {
                std::future::pending::<()>().await;
            }
        } => {
            tracing::warn!(
                "connections still open {CONNECTION_CLOSE_GRACE:?} after the drain: closing them"
            );
            Ok(())
        }
    };
    let _ = stopped_tx.send(true);
    served?;
    tracing::info!("murk stopped");
    Ok(())
}

/// How long connections may take to close after the drain (GOAWAY sent, in-flight calls
/// answered) before the server stops regardless.
const CONNECTION_CLOSE_GRACE: Duration = Duration::from_secs(1);

/// A server running inside this process (tests, `murk demo`, benchmarks).
pub struct InProcessServer {
    addr: SocketAddr,
    metrics_addr: SocketAddr,
    manager: JobManager,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<Result<(), ServerError>>,
}

impl InProcessServer {
    /// Binds 127.0.0.1:0 (and another ephemeral port for metrics) and starts serving on the
    /// current tokio runtime.
    pub async fn start(config: ServerConfig) -> Result<Self, ServerError> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let metrics = TcpListener::bind("127.0.0.1:0").await?;
        let metrics_addr = metrics.local_addr()?;
        let manager = JobManager::new(config.jobs.clone())?;
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(serve_with_manager(
            config,
            manager.clone(),
            listener,
            Some(metrics),
            async move {
                let _ = rx.await;
            },
        ));
        Ok(Self {
            addr,
            metrics_addr,
            manager,
            stop: Some(tx),
            task,
        })
    }

    /// The bound address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// `http://127.0.0.1:PORT`, for clients.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Where Prometheus metrics are served (`/metrics`).
    pub fn metrics_addr(&self) -> SocketAddr {
        self.metrics_addr
    }

    /// Asks the server to shut down (health NOT_SERVING, drain, abort) without waiting.
    pub fn begin_shutdown(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
    }

    /// The job system (for counters in tests and the demo).
    pub fn manager(&self) -> &JobManager {
        &self.manager
    }

    /// Graceful shutdown; returns the server's result.
    pub async fn stop(mut self) -> Result<(), ServerError> {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        (&mut self.task)
            .await
            .map_err(|e| ServerError::Io(std::io::Error::other(e)))?
    }
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}
