//! Assembling and running the gRPC server: Jobs + Reconstruction + grpc.health.v1 + reflection,
//! with explicit limits and graceful shutdown (stop accepting, drain for a grace period, cancel
//! the rest).

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use thiserror::Error;
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tonic::transport::server::TcpIncoming;
use tonic::transport::Server;

use crate::jobs::{JobManager, JobsConfig};
use crate::params::airlight::AirlightEstimator;
use crate::service::convert::{AirlightService, ImageLimits};
use crate::service::proto::v1::jobs_server::JobsServer;
use crate::service::proto::v1::reconstruction_server::ReconstructionServer;
use crate::service::proto::FILE_DESCRIPTOR_SET;
use crate::service::{JobsApi, ReconstructionApi, RequestLimits, ServiceState};

/// Default request limit: a dozen 16-bit 1-megapixel images (≈ 24 MiB) plus headroom.
pub const DEFAULT_MAX_REQUEST_BYTES: usize = 32 << 20;

/// Everything that configures a server.
#[derive(Clone, Debug)]
pub struct ServerConfig {
    /// Job system sizing.
    pub jobs: JobsConfig,
    /// Largest request accepted, bytes; larger → INVALID_ARGUMENT naming the largest field
    /// (above twice this the transport refuses it with OUT_OF_RANGE before decoding).
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
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            jobs: JobsConfig::default(),
            max_request_bytes: DEFAULT_MAX_REQUEST_BYTES,
            max_image_pixels: 16 << 20,
            max_ps_kernel_bytes: crate::ps::pipeline::DEFAULT_MAX_KERNEL_BYTES,
            shutdown_grace: Duration::from_secs(10),
            airlight: AirlightEstimator::from_config(None, true)
                .unwrap_or(AirlightEstimator::DarkChannel(Default::default())),
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
}

/// Serves on `listener` until `shutdown` resolves, then shuts down gracefully.
pub async fn serve(
    config: ServerConfig,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let manager = JobManager::new(config.jobs.clone())?;
    serve_with_manager(config, manager, listener, shutdown).await
}

async fn serve_with_manager(
    config: ServerConfig,
    manager: JobManager,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let state = ServiceState {
        manager: manager.clone(),
        limits: RequestLimits {
            max_request_bytes: config.max_request_bytes,
            images: ImageLimits {
                max_pixels: config.max_image_pixels,
                max_channels: 4,
            },
            max_ps_kernel_bytes: config.max_ps_kernel_bytes,
        },
        airlight: AirlightService::new(config.airlight.clone()),
    };
    // The transport's hard ceiling; between 1× and 2× the handlers answer INVALID_ARGUMENT with
    // the field named, which is more useful to a client than a bare OUT_OF_RANGE.
    let transport_limit = config.max_request_bytes.saturating_mul(2);
    let jobs = JobsServer::new(JobsApi::new(state.clone()))
        .max_decoding_message_size(transport_limit)
        .max_encoding_message_size(usize::MAX);
    let recon = ReconstructionServer::new(ReconstructionApi::new(state))
        .max_decoding_message_size(transport_limit)
        .max_encoding_message_size(usize::MAX);

    let (health_reporter, health) = tonic_health::server::health_reporter();
    health_reporter.set_serving::<JobsServer<JobsApi>>().await;
    health_reporter
        .set_serving::<ReconstructionServer<ReconstructionApi>>()
        .await;
    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    let addr = listener.local_addr()?;
    tracing::info!(
        %addr,
        workers = manager.worker_threads(),
        queue = config.jobs.queue_capacity,
        max_request_bytes = config.max_request_bytes,
        "murk serving"
    );
    let grace = config.shutdown_grace;
    let drain_manager = manager.clone();
    let stop = async move {
        shutdown.await;
        tracing::info!(?grace, "shutting down: draining jobs");
        health_reporter
            .set_not_serving::<JobsServer<JobsApi>>()
            .await;
        health_reporter
            .set_not_serving::<ReconstructionServer<ReconstructionApi>>()
            .await;
        drain_manager.shutdown(grace).await;
    };
    Server::builder()
        .add_service(health)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(jobs)
        .add_service(recon)
        .serve_with_incoming_shutdown(
            // Without TCP_NODELAY small responses wait on delayed ACKs (~15 ms per call).
            TcpIncoming::from(listener)
                .with_nodelay(Some(true))
                .with_keepalive(Some(Duration::from_secs(60))),
            stop,
        )
        .await?;
    tracing::info!("murk stopped");
    Ok(())
}

/// A server running inside this process (tests, `murk demo`, benchmarks).
pub struct InProcessServer {
    addr: SocketAddr,
    manager: JobManager,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<Result<(), ServerError>>,
}

impl InProcessServer {
    /// Binds 127.0.0.1:0 and starts serving on the current tokio runtime.
    pub async fn start(config: ServerConfig) -> Result<Self, ServerError> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let manager = JobManager::new(config.jobs.clone())?;
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(serve_with_manager(
            config,
            manager.clone(),
            listener,
            async move {
                let _ = rx.await;
            },
        ));
        Ok(Self {
            addr,
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
