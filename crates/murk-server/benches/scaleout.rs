//! Scale-out costs, against a real `redis-server` started on a free loopback port:
//!
//! - `redis_overhead`: what the Redis backend adds per job over the embedded one, with one
//!   in-process server each: a cache-hit `SubmitJob` round trip, and a small ToF job computed
//!   from scratch through the unary `TofDepth` RPC (submit script, stream entry, a worker's
//!   claim, start/finish scripts, result stored in Redis, pub/sub back to the waiting call).
//! - `replica_throughput`: jobs per second with 1, 2 and 3 `murk serve --redis-url` processes
//!   sharing one queue, next to one embedded `murk serve`, with a batch of concurrent clients
//!   spread over the replicas.
//!
//! cargo bench -p murk-server --bench scaleout
//!
//! Without `redis-server` on the PATH the bench prints `SKIPPED` and measures nothing.

#[path = "../tests/service/common/mod.rs"]
mod common;

use std::process::{Child, Command};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use common::redis_server::RedisServer;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use murk_server::jobs::redis::RedisConfig;
use murk_server::jobs::JobsConfig;
use murk_server::server::{InProcessServer, ServerConfig};
use murk_server::service::proto::v1 as pb;
use pb::jobs_client::JobsClient;
use pb::reconstruction_client::ReconstructionClient;
use tonic::transport::{Channel, Endpoint};

/// The solver's default weight tolerance; each request nudges it by a negligible amount so
/// that every call is a distinct job (a distinct content hash), never a cache hit.
const TOLERANCE: f64 = 1e-3;

/// Numbers each request so that no two are the same job.
static NEXT: AtomicU64 = AtomicU64::new(1);

fn distinct(base: &pb::TofDepthRequest) -> pb::TofDepthRequest {
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    let mut r = base.clone();
    r.options = Some(pb::TofOptions {
        convergence_tolerance: Some(TOLERANCE * (1.0 + n as f64 * 1e-12)),
        ..Default::default()
    });
    r
}

fn channel(url: &str) -> Channel {
    Endpoint::from_shared(url.to_string())
        .expect("url")
        .connect_lazy()
}

fn in_process(rt: &tokio::runtime::Runtime, redis: Option<&RedisServer>) -> InProcessServer {
    rt.block_on(InProcessServer::start(ServerConfig {
        jobs: JobsConfig {
            workers: 2,
            queue_capacity: 64,
            ..JobsConfig::default()
        },
        redis: redis.map(|r| RedisConfig::new(r.url())),
        ..ServerConfig::default()
    }))
    .expect("server")
}

fn redis_overhead(c: &mut Criterion) {
    // `everysec` is what deploy/docker-compose.yml runs; `always` (an fsync per write, as the
    // tests use) bounds the cost of the strictest durability.
    let (Some(everysec), Some(always)) = (
        RedisServer::start_with_fsync("everysec"),
        RedisServer::start_with_fsync("always"),
    ) else {
        return;
    };
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let _enter = rt.enter();
    let small = common::tof_request(32, 24, 11);
    let hit = common::job(common::tof_request(64, 53, 12));
    let mut group = c.benchmark_group("redis_overhead");
    group.sample_size(30);
    for (backend, redis) in [
        ("embedded", None),
        ("redis_everysec", Some(&everysec)),
        ("redis_always", Some(&always)),
    ] {
        let server = in_process(&rt, redis);
        let ch = channel(&server.url());
        let jobs = JobsClient::new(ch.clone()).max_decoding_message_size(usize::MAX);
        let recon = ReconstructionClient::new(ch).max_decoding_message_size(usize::MAX);
        // Computed once, so that every measured call is a cache hit.
        rt.block_on(async {
            let mut j = jobs.clone();
            let first = j
                .submit_job(hit.clone())
                .await
                .expect("submit")
                .into_inner();
            let mut s = j
                .watch_job(pb::WatchJobRequest {
                    id: first.id,
                    omit_result: true,
                })
                .await
                .expect("watch")
                .into_inner();
            while s.message().await.expect("stream").is_some() {}
        });
        group.bench_function(format!("cache_hit_64x53/{backend}"), |b| {
            b.to_async(&rt).iter(|| {
                let mut j = jobs.clone();
                let req = hit.clone();
                async move {
                    let job = j.submit_job(req).await.expect("submit").into_inner();
                    assert!(job.cached, "a cache hit");
                    job
                }
            })
        });
        group.bench_function(format!("tof_job_32x24/{backend}"), |b| {
            b.to_async(&rt).iter(|| {
                let mut r = recon.clone();
                let req = distinct(&small);
                async move { r.tof_depth(req).await.expect("computed").into_inner() }
            })
        });
        rt.block_on(server.stop()).expect("stop");
    }
    group.finish();
}

/// A `murk serve` child process, killed on drop.
struct Serve(Child, String);

impl Serve {
    fn start(redis: Option<&RedisServer>, concurrent_jobs: usize) -> Self {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_murk"));
        cmd.args(["serve", "--addr", "127.0.0.1:0", "--workers", "2"])
            .args(["--queue-capacity", "256"])
            .args(["--concurrent-jobs", &concurrent_jobs.to_string()]);
        if let Some(r) = redis {
            cmd.args(["--redis-url", &r.url()]);
        }
        let (child, url) = common::spawn_serve(cmd);
        Self(child, url)
    }
}

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Jobs in one measured batch, sent at once by as many clients, spread round-robin.
const BATCH: usize = 16;

fn replica_throughput(c: &mut Criterion) {
    let Some(redis) = RedisServer::start_with_fsync("everysec") else {
        return;
    };
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let _enter = rt.enter();
    // ~90 ms of compute each on this machine: long against the per-job overhead, short enough
    // for many batches.
    let base = common::tof_request(128, 106, 13);
    let mut group = c.benchmark_group("replica_throughput");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(20))
        .throughput(Throughput::Elements(BATCH as u64));
    // (label, replicas, backend, jobs at once per replica): one embedded server computing two
    // jobs at once shows what two replicas on one 2-core machine gain without Redis.
    for (label, replicas, backend, concurrent) in [
        ("embedded_1", 1, None, 1),
        ("embedded_1_concurrent_2", 1, None, 2),
        ("redis_1", 1, Some(&redis), 1),
        ("redis_2", 2, Some(&redis), 1),
        ("redis_3", 3, Some(&redis), 1),
    ] {
        let servers: Vec<Serve> = (0..replicas)
            .map(|_| Serve::start(backend, concurrent))
            .collect();
        let clients: Vec<ReconstructionClient<Channel>> = servers
            .iter()
            .map(|s| ReconstructionClient::new(channel(&s.1)).max_decoding_message_size(usize::MAX))
            .collect();
        group.bench_function(label, |b| {
            b.to_async(&rt).iter_custom(|iters| {
                let clients = clients.clone();
                let base = base.clone();
                async move {
                    let mut total = Duration::ZERO;
                    for _ in 0..iters {
                        let reqs: Vec<_> = (0..BATCH).map(|_| distinct(&base)).collect();
                        let started = Instant::now();
                        let calls = reqs.into_iter().enumerate().map(|(i, req)| {
                            let mut cl = clients[i % clients.len()].clone();
                            tokio::spawn(async move { cl.tof_depth(req).await.map(|_| ()) })
                        });
                        for call in calls.collect::<Vec<_>>() {
                            call.await.expect("task").expect("computed");
                        }
                        total += started.elapsed();
                    }
                    total
                }
            })
        });
        drop(servers);
    }
    group.finish();
}

criterion_group!(benches, redis_overhead, replica_throughput);
criterion_main!(benches);
