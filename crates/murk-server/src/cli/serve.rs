//! `murk serve`.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use murk::params::airlight::AirlightEstimator;

use murk_server::connections::ConnectionLimits;
use murk_server::jobs::redis::RedisConfig;
use murk_server::jobs::JobsConfig;
use murk_server::server::{
    serve, shutdown_signal, ServerConfig, TlsSettings, DEFAULT_MAX_REQUEST_BYTES,
};
use murk_server::service::auth::TokenStore;
use murk_server::service::watchers::WatchLimits;
use murk_server::service::{CacheScope, SessionLimits, DEFAULT_MAX_UNARY_RESULT_BYTES};

/// Server configuration; each flag is also an environment variable.
#[derive(Args, Debug, Clone)]
pub struct ServeArgs {
    /// Address to listen on. A non-loopback address needs `--auth-tokens-file` or an explicit
    /// `--allow-unauthenticated`.
    #[arg(long, env = "MURK_ADDR", default_value = "127.0.0.1:50051")]
    pub addr: String,
    /// Bearer tokens: one `TENANT TOKEN` pair per line, `#` comments; re-read on SIGHUP.
    /// Clients send `authorization: Bearer TOKEN`; jobs belong to the token's tenant.
    #[arg(long, env = "MURK_AUTH_TOKENS_FILE")]
    pub auth_tokens_file: Option<PathBuf>,
    /// Serve a non-loopback address without authentication (anyone who can connect may submit,
    /// read and cancel jobs).
    #[arg(long, env = "MURK_ALLOW_UNAUTHENTICATED", value_parser = clap::builder::BoolishValueParser::new())]
    pub allow_unauthenticated: bool,
    /// TLS certificate chain (PEM); with `--tls-key` the server speaks TLS only.
    #[arg(long, env = "MURK_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM).
    #[arg(long, env = "MURK_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// CA certificate(s) (PEM) that client certificates must chain to: mutual TLS, connections
    /// without a valid client certificate are refused.
    #[arg(long, env = "MURK_TLS_CLIENT_CA", requires = "tls_cert")]
    pub tls_client_ca: Option<PathBuf>,
    /// Serve Prometheus metrics at http://HOST:PORT/metrics.
    #[arg(long, env = "MURK_METRICS_ADDR")]
    pub metrics_addr: Option<String>,
    /// Largest message a unary response may carry, bytes (default: gRPC clients' default 4 MiB
    /// receive limit). Larger results are fetched with `Jobs.GetJobResult` in 1 MiB chunks.
    #[arg(long, env = "MURK_MAX_UNARY_RESULT_BYTES", default_value_t = DEFAULT_MAX_UNARY_RESULT_BYTES)]
    pub max_unary_result_bytes: usize,
    /// Compute threads (0 = number of cores).
    #[arg(long, env = "MURK_WORKERS", default_value_t = 0)]
    pub workers: usize,
    /// Jobs computed at once (each uses all compute threads for its inner loops).
    #[arg(long, env = "MURK_CONCURRENT_JOBS", default_value_t = 1)]
    pub concurrent_jobs: usize,
    /// Jobs that may wait; one more gets RESOURCE_EXHAUSTED with a retry hint.
    #[arg(long, env = "MURK_QUEUE_CAPACITY", default_value_t = 64)]
    pub queue_capacity: usize,
    /// In-memory result cache, bytes.
    #[arg(long, env = "MURK_CACHE_BYTES", default_value_t = 512 << 20)]
    pub cache_bytes: u64,
    /// Whose identical requests share results: `tenant` (each tenant's own; the default with
    /// --auth-tokens-file) or `global` (shared between tenants, which lets a tenant learn that
    /// another ran the same input; the default without authentication).
    #[arg(long, env = "MURK_CACHE_SCOPE", value_enum)]
    pub cache_scope: Option<CacheScope>,
    /// Directory where results persist across restarts (optional).
    #[arg(long, env = "MURK_CACHE_DIR")]
    pub cache_dir: Option<PathBuf>,
    /// Largest total size of the result files in --cache-dir, bytes; least recently used go
    /// first.
    #[arg(long, env = "MURK_CACHE_DIR_BYTES", default_value_t = murk_server::jobs::DEFAULT_CACHE_DIR_BYTES)]
    pub cache_dir_bytes: u64,
    /// Largest request message, bytes, as it arrives (after decompression, every field
    /// counted); larger ones get RESOURCE_EXHAUSTED. The default fits a dozen 16-bit
    /// 1-megapixel images.
    #[arg(long, env = "MURK_MAX_REQUEST_BYTES", default_value_t = DEFAULT_MAX_REQUEST_BYTES)]
    pub max_request_bytes: usize,
    /// Largest image, pixels.
    #[arg(long, env = "MURK_MAX_IMAGE_PIXELS", default_value_t = 16 << 20)]
    pub max_image_pixels: u64,
    /// Largest forward-scatter kernel of a photometric-stereo job, bytes (object pixels ×
    /// stored entries per pixel × 4, the entries of the near block and the far cells' window:
    /// 1 121 at r = 81 with the default cells; the method's memory peak). Larger requests are
    /// refused before they are queued, RESOURCE_EXHAUSTED naming `support_r`. Default: half
    /// the container's memory limit (cgroup) per concurrent job, at most 4 GiB; 4 GiB without
    /// a limit.
    #[arg(long, env = "MURK_MAX_PS_KERNEL_BYTES")]
    pub max_ps_kernel_bytes: Option<usize>,
    /// Sensor sessions (the Sessions stream) open at once on this replica; more are refused
    /// with RESOURCE_EXHAUSTED. Each holds its frame queue and one frame in computation.
    #[arg(long, env = "MURK_MAX_SESSIONS", default_value_t = 32)]
    pub max_sessions: usize,
    /// Sensor sessions open at once for one tenant on this replica.
    #[arg(long, env = "MURK_MAX_SESSIONS_PER_TENANT", default_value_t = 8)]
    pub max_sessions_per_tenant: usize,
    /// Seconds a new session stream may take to send its configuration before it is ended
    /// (DEADLINE_EXCEEDED): an idle stream must not hold a session slot.
    #[arg(long, env = "MURK_SESSION_CONFIG_TIMEOUT_SECS", default_value_t = 10.0)]
    pub session_config_timeout_secs: f64,
    /// Connections open at once; one more is accepted and closed at once. Each holds a file
    /// descriptor: keep it below the process's limit (`ulimit -n`).
    #[arg(long, env = "MURK_MAX_CONNECTIONS", default_value_t = 1024)]
    pub max_connections: usize,
    /// Seconds a new connection may take to send its opening bytes (the HTTP/2 preface or a
    /// TLS hello) before it is closed: an idle socket must not hold a slot.
    #[arg(long, env = "MURK_HANDSHAKE_TIMEOUT_SECS", default_value_t = 10.0)]
    pub handshake_timeout_secs: f64,
    /// HTTP/2 streams one connection may have open at once (calls, watches, sessions).
    #[arg(long, env = "MURK_MAX_CONCURRENT_STREAMS", default_value_t = 256)]
    pub max_concurrent_streams: u32,
    /// Seconds between the server's HTTP/2 pings; a connection whose ping goes unanswered for
    /// --keepalive-timeout-secs is closed.
    #[arg(long, env = "MURK_KEEPALIVE_INTERVAL_SECS", default_value_t = 30.0)]
    pub keepalive_interval_secs: f64,
    /// Seconds a ping may go unanswered.
    #[arg(long, env = "MURK_KEEPALIVE_TIMEOUT_SECS", default_value_t = 20.0)]
    pub keepalive_timeout_secs: f64,
    /// WatchJob streams of one job at once; one more gets RESOURCE_EXHAUSTED.
    #[arg(long, env = "MURK_MAX_WATCHERS_PER_JOB", default_value_t = WatchLimits::default().max_per_job)]
    pub max_watchers_per_job: usize,
    /// WatchJob streams of one tenant at once, over all its jobs.
    #[arg(long, env = "MURK_MAX_WATCHERS_PER_TENANT", default_value_t = WatchLimits::default().max_per_tenant)]
    pub max_watchers_per_tenant: usize,
    /// Result bytes that WatchJob messages may hold at once, over all streams; beyond it a
    /// result goes out omitted (`result_omitted`) and the client fetches it with GetJobResult.
    #[arg(long, env = "MURK_WATCH_RESULT_BUDGET_BYTES", default_value_t = WatchLimits::default().result_budget_bytes)]
    pub watch_result_budget_bytes: u64,
    /// Seconds to drain jobs on SIGTERM/Ctrl-C before cancelling them.
    #[arg(long, env = "MURK_SHUTDOWN_GRACE_SECS", default_value_t = 10.0)]
    pub shutdown_grace_secs: f64,
    /// Smallest back-off suggested to clients when the queue is full, milliseconds (the hint is
    /// the estimated time until a queue slot frees when that is longer, +0–50 % jitter).
    #[arg(long, env = "MURK_RETRY_AFTER_MS", default_value_t = 500)]
    pub retry_after_ms: u64,
    /// Job records kept for Get/List (results stay in the cache regardless).
    #[arg(long, env = "MURK_MAX_JOB_RECORDS", default_value_t = 10_000)]
    pub max_job_records: usize,
    /// Airlight estimator for scattering-parameter requests that do not name one.
    #[arg(long, env = "MURK_AIRLIGHT_ESTIMATOR", value_enum, default_value_t = AirlightArg::Cnn)]
    pub airlight_estimator: AirlightArg,
    /// Weights of the airlight CNN (a burnpack file from `murk train airlight`); default: the
    /// weights built into murk. A missing or corrupt file stops the server from starting.
    #[arg(long, env = "MURK_AIRLIGHT_WEIGHTS")]
    pub airlight_weights: Option<std::path::PathBuf>,
    /// Share jobs, the queue and results with other replicas through Redis
    /// (`redis://[[USER]:PASSWORD@]HOST:PORT/DB`, or `rediss://` for TLS, verified against the
    /// system's trust store or --redis-ca-file). Without it murk keeps everything in this
    /// process and needs no external service.
    #[arg(long, env = "MURK_REDIS_URL")]
    pub redis_url: Option<String>,
    /// PEM CA certificate that signed Redis's TLS certificate (with a `rediss://` URL), instead
    /// of the system's trust store.
    #[arg(long, env = "MURK_REDIS_CA_FILE", requires = "redis_url")]
    pub redis_ca_file: Option<std::path::PathBuf>,
    /// PEM client certificate for a Redis that authenticates TLS clients (with
    /// --redis-client-key).
    #[arg(long, env = "MURK_REDIS_CLIENT_CERT", requires_all = ["redis_url", "redis_client_key"])]
    pub redis_client_cert: Option<std::path::PathBuf>,
    /// PEM key of --redis-client-cert.
    #[arg(long, env = "MURK_REDIS_CLIENT_KEY", requires = "redis_client_cert")]
    pub redis_client_key: Option<std::path::PathBuf>,
    /// Prefix of murk's Redis keys (several deployments may share one Redis).
    #[arg(long, env = "MURK_REDIS_PREFIX", default_value = "murk")]
    pub redis_prefix: String,
    /// Lease on a running job, seconds: a replica that stops renewing it for this long (it
    /// died or hung) loses its jobs to the other replicas.
    #[arg(long, env = "MURK_REDIS_LEASE_SECS", default_value_t = 10.0)]
    pub redis_lease_secs: f64,
    /// How long results stay in Redis, seconds (its maxmemory policy may evict them sooner;
    /// finished job records are kept as long).
    #[arg(long, env = "MURK_REDIS_RESULT_TTL_SECS", default_value_t = 7 * 24 * 3600)]
    pub redis_result_ttl_secs: u64,
    /// With unusable CNN weights, log a warning and use the dark-channel estimator instead of
    /// refusing to start.
    #[arg(long, env = "MURK_AIRLIGHT_FALLBACK", value_parser = clap::builder::BoolishValueParser::new())]
    pub airlight_fallback: bool,
}

/// The server's default airlight estimator.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum AirlightArg {
    /// The CNN of the reference's Table 3.1.
    Cnn,
    /// The dark-channel prior's brightest-pixel rule.
    DarkChannel,
}

impl ServeArgs {
    /// The server configuration these flags describe.
    pub fn config(&self) -> anyhow::Result<ServerConfig> {
        anyhow::ensure!(
            self.shutdown_grace_secs.is_finite() && self.shutdown_grace_secs >= 0.0,
            "--shutdown-grace-secs must be a non-negative number"
        );
        anyhow::ensure!(self.queue_capacity > 0, "--queue-capacity must be positive");
        anyhow::ensure!(
            self.max_sessions > 0 && self.max_sessions_per_tenant > 0,
            "--max-sessions and --max-sessions-per-tenant must be positive (sessions cannot be \
             turned off; a client that never opens one costs nothing)"
        );
        anyhow::ensure!(
            self.session_config_timeout_secs.is_finite()
                && (0.1..=3600.0).contains(&self.session_config_timeout_secs),
            "--session-config-timeout-secs must be between 0.1 and 3600"
        );
        anyhow::ensure!(
            self.max_connections > 0 && self.max_concurrent_streams > 0,
            "--max-connections and --max-concurrent-streams must be positive"
        );
        for (flag, v) in [
            ("--handshake-timeout-secs", self.handshake_timeout_secs),
            ("--keepalive-interval-secs", self.keepalive_interval_secs),
            ("--keepalive-timeout-secs", self.keepalive_timeout_secs),
        ] {
            anyhow::ensure!(
                v.is_finite() && (0.1..=3600.0).contains(&v),
                "{flag} must be between 0.1 and 3600"
            );
        }
        anyhow::ensure!(
            self.max_watchers_per_job > 0 && self.max_watchers_per_tenant > 0,
            "--max-watchers-per-job and --max-watchers-per-tenant must be at least 1"
        );
        anyhow::ensure!(
            self.max_request_bytes >= 1024,
            "--max-request-bytes must be at least 1024"
        );
        anyhow::ensure!(
            self.max_unary_result_bytes >= 1024,
            "--max-unary-result-bytes must be at least 1024"
        );
        let auth = match &self.auth_tokens_file {
            Some(path) => {
                let store = TokenStore::from_file(path).map_err(|e| anyhow::anyhow!("{e}"))?;
                tracing::info!(tokens = store.len(), path = %path.display(), "bearer tokens loaded");
                Some(store)
            }
            None => None,
        };
        let tls = match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => Some(TlsSettings {
                cert_pem: read_pem(cert, "--tls-cert")?,
                key_pem: read_pem(key, "--tls-key")?,
                client_ca_pem: self
                    .tls_client_ca
                    .as_deref()
                    .map(|p| read_pem(p, "--tls-client-ca"))
                    .transpose()?,
            }),
            _ => None,
        };
        anyhow::ensure!(
            self.redis_lease_secs.is_finite() && self.redis_lease_secs >= 0.5,
            "--redis-lease-secs must be at least 0.5"
        );
        anyhow::ensure!(
            self.redis_result_ttl_secs >= 1,
            "--redis-result-ttl-secs must be at least 1"
        );
        let redis = match &self.redis_url {
            None => None,
            Some(url) => {
                let mut r = RedisConfig::new(url.clone());
                r.prefix = self.redis_prefix.clone();
                r.lease = Duration::from_secs_f64(self.redis_lease_secs);
                r.result_ttl = Duration::from_secs(self.redis_result_ttl_secs);
                r.record_ttl = r.result_ttl;
                r.tls.ca_pem = self
                    .redis_ca_file
                    .as_deref()
                    .map(|p| read_pem(p, "--redis-ca-file"))
                    .transpose()?;
                if let (Some(cert), Some(key)) = (&self.redis_client_cert, &self.redis_client_key) {
                    r.tls.client_cert_and_key_pem = Some((
                        read_pem(cert, "--redis-client-cert")?,
                        read_pem(key, "--redis-client-key")?,
                    ));
                }
                Some(r)
            }
        };
        Ok(ServerConfig {
            redis,
            jobs: JobsConfig {
                workers: self.workers,
                concurrent_jobs: self.concurrent_jobs.max(1),
                queue_capacity: self.queue_capacity,
                cache_bytes: self.cache_bytes,
                cache_dir: self.cache_dir.clone(),
                cache_dir_bytes: self.cache_dir_bytes,
                retry_after: Duration::from_millis(self.retry_after_ms),
                max_job_records: self.max_job_records.max(1),
            },
            max_unary_result_bytes: self.max_unary_result_bytes,
            auth,
            cache_scope: self.cache_scope,
            tls,
            max_request_bytes: self.max_request_bytes,
            max_image_pixels: self.max_image_pixels,
            max_ps_kernel_bytes: ps_kernel_bound(
                self.max_ps_kernel_bytes,
                murk_server::cgroup::memory_limit_bytes(),
                self.concurrent_jobs.max(1),
            ),
            shutdown_grace: Duration::from_secs_f64(self.shutdown_grace_secs),
            watchers: WatchLimits {
                max_per_job: self.max_watchers_per_job,
                max_per_tenant: self.max_watchers_per_tenant,
                result_budget_bytes: self.watch_result_budget_bytes,
            },
            connections: ConnectionLimits {
                max_connections: self.max_connections,
                handshake_timeout: Duration::from_secs_f64(self.handshake_timeout_secs),
                max_concurrent_streams: self.max_concurrent_streams,
                keepalive_interval: Duration::from_secs_f64(self.keepalive_interval_secs),
                keepalive_timeout: Duration::from_secs_f64(self.keepalive_timeout_secs),
            },
            sessions: SessionLimits {
                max_sessions: self.max_sessions,
                max_sessions_per_tenant: self.max_sessions_per_tenant,
                config_timeout: Duration::from_secs_f64(self.session_config_timeout_secs),
            },
            airlight: match self.airlight_estimator {
                AirlightArg::DarkChannel => AirlightEstimator::DarkChannel(Default::default()),
                AirlightArg::Cnn => AirlightEstimator::from_config(
                    self.airlight_weights.as_deref(),
                    self.airlight_fallback,
                )
                .map_err(|e| anyhow::anyhow!("loading the airlight CNN: {e}"))?,
            },
        })
    }
}

/// The photometric-stereo kernel bound: `explicit` when given; otherwise half the container's
/// memory limit shared by the jobs that may run at once, at most the library's default (the
/// kernel is the job's memory peak; the other half holds the server, the images and results).
fn ps_kernel_bound(explicit: Option<usize>, memory_limit: Option<u64>, jobs: usize) -> usize {
    let default = murk::ps::pipeline::DEFAULT_MAX_KERNEL_BYTES;
    let (bound, source) = match (explicit, memory_limit) {
        (Some(b), _) => (b, "--max-ps-kernel-bytes"),
        (None, Some(limit)) => (
            usize::try_from(limit / 2 / jobs.max(1) as u64).map_or(default, |b| b.min(default)),
            "half the cgroup memory limit per concurrent job",
        ),
        (None, None) => (default, "default (no cgroup memory limit)"),
    };
    tracing::info!(
        bytes = bound,
        memory_limit = memory_limit.unwrap_or(0),
        source,
        "photometric-stereo kernel bound"
    );
    bound
}

fn read_pem(path: &std::path::Path, flag: &str) -> anyhow::Result<Vec<u8>> {
    let bytes = std::fs::read(path).with_context(|| format!("{flag} {}", path.display()))?;
    anyhow::ensure!(
        bytes.windows(11).any(|w| w == b"-----BEGIN "),
        "{flag} {} is not a PEM file",
        path.display()
    );
    Ok(bytes)
}

/// Refuses to expose an unauthenticated server beyond this machine unless asked to.
fn check_exposure(addr: &std::net::SocketAddr, args: &ServeArgs) -> anyhow::Result<()> {
    if !addr.ip().is_loopback() && args.auth_tokens_file.is_none() && !args.allow_unauthenticated {
        anyhow::bail!(
            "refusing to serve {addr} without authentication: give --auth-tokens-file \
             (MURK_AUTH_TOKENS_FILE), bind a loopback address, or pass \
             --allow-unauthenticated to let anyone who can connect use and cancel every job"
        );
    }
    if !addr.ip().is_loopback() && args.tls_cert.is_none() && args.auth_tokens_file.is_some() {
        tracing::warn!(%addr, "bearer tokens travel in clear text without --tls-cert");
    }
    Ok(())
}

/// Runs the server until SIGTERM or Ctrl-C; SIGHUP re-reads the token file.
pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let config = args.config()?;
    check_descriptor_limit(args.max_connections);
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(&args.addr)
            .await
            .with_context(|| format!("binding {}", args.addr))?;
        check_exposure(&listener.local_addr()?, &args)?;
        let metrics = match &args.metrics_addr {
            Some(a) => Some(
                tokio::net::TcpListener::bind(a)
                    .await
                    .with_context(|| format!("binding --metrics-addr {a}"))?,
            ),
            None => None,
        };
        if let Some(store) = config.auth.clone() {
            reload_tokens_on_sighup(store);
        }
        serve(config, listener, metrics, shutdown_signal()).await?;
        Ok(())
    })
}

#[cfg(unix)]
fn reload_tokens_on_sighup(store: TokenStore) {
    use tokio::signal::unix::{signal, SignalKind};
    let Ok(mut hup) = signal(SignalKind::hangup()) else {
        tracing::warn!("cannot listen for SIGHUP; token file changes need a restart");
        return;
    };
    tokio::spawn(async move {
        while hup.recv().await.is_some() {
            match store.reload() {
                Ok(n) => tracing::info!(tokens = n, "SIGHUP: bearer tokens reloaded"),
                Err(e) => {
                    tracing::error!(error = %e, "SIGHUP: token file unusable; keeping the tokens in force")
                }
            }
        }
    });
}

#[cfg(not(unix))]
fn reload_tokens_on_sighup(_store: TokenStore) {}

/// Descriptors beyond the connections: the listeners, the cache and journal files, Redis,
/// the runtime's own.
const DESCRIPTOR_MARGIN: u64 = 64;

/// Warns when the process's open-file limit cannot hold `max_connections` (Linux: read from
/// /proc/self/limits; elsewhere nothing is said). At the limit, new connections fail to be
/// accepted until one closes.
fn check_descriptor_limit(max_connections: usize) {
    let Ok(limits) = std::fs::read_to_string("/proc/self/limits") else {
        return;
    };
    let soft = limits
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(3))
        .and_then(|v| v.parse::<u64>().ok());
    let need = max_connections as u64 + DESCRIPTOR_MARGIN;
    match soft {
        Some(soft) if soft < need => tracing::warn!(
            limit = soft,
            max_connections,
            "the open-file limit ({soft}) is below --max-connections + {DESCRIPTOR_MARGIN} \
             ({need}): raise it (ulimit -n {need}) or lower --max-connections"
        ),
        Some(soft) => tracing::info!(limit = soft, max_connections, "open-file limit"),
        None => {}
    }
}

#[cfg(test)]
mod kernel_bound_tests {
    use super::ps_kernel_bound;
    use murk::ps::pipeline::DEFAULT_MAX_KERNEL_BYTES;

    #[test]
    fn an_explicit_bound_wins_and_the_default_follows_the_container() {
        assert_eq!(ps_kernel_bound(Some(123), Some(1 << 30), 1), 123);
        // A 3 GiB pod running one job at a time: 1.5 GiB for the kernel.
        assert_eq!(ps_kernel_bound(None, Some(3 << 30), 1), 3 << 29);
        // Two concurrent jobs share it.
        assert_eq!(ps_kernel_bound(None, Some(3 << 30), 2), 3 << 28);
        // Never above the library's default, nor without a limit.
        assert_eq!(
            ps_kernel_bound(None, Some(64 << 30), 1),
            DEFAULT_MAX_KERNEL_BYTES
        );
        assert_eq!(ps_kernel_bound(None, None, 1), DEFAULT_MAX_KERNEL_BYTES);
    }
}
