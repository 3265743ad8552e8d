//! Latency under overload: N concurrent clients each send one ToF frame through the unary
//! `Reconstruction.TofDepth` RPC to a server with a queue of 8, and retry every
//! RESOURCE_EXHAUSTED after the `RetryInfo` delay the server suggests, as a well-behaved gRPC
//! client does. Reports p50/p95/p99/max of the time from a client's first attempt to its result,
//! and the number of refused attempts. Every frame is distinct (no cache hits).
//!
//! cargo bench --bench overload            (MURK_OVERLOAD_CLIENTS=16,64 MURK_OVERLOAD_SIZE=256x212)
//!
//! Bounded: at most one request per client and a 10-minute cap on the whole run.

use std::time::{Duration, Instant};

use murk::jobs::JobsConfig;
use murk::server::{InProcessServer, ServerConfig};
use murk::service::convert::tof_request_to_proto;
use murk::service::proto::v1 as pb;
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk::Monitor;
use tonic::transport::Endpoint;
use tonic::Code;
use tonic_types::StatusExt;

fn frame(width: usize, height: usize, seed: u64) -> pb::TofDepthRequest {
    let cfg = TofSimConfig {
        seed,
        ..TofSimConfig::with_size(width, height)
    };
    let f = simulate_tof(&cfg, &Monitor::noop()).expect("simulate");
    tof_request_to_proto(
        &f.amplitude,
        &f.phase,
        Some(&f.intrinsics),
        cfg.modulation_frequency_hz,
        Some(cfg.light_position_m()),
    )
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn main() {
    let clients: Vec<usize> = std::env::var("MURK_OVERLOAD_CLIENTS")
        .unwrap_or_else(|_| "16,64".into())
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    let (w, h) = std::env::var("MURK_OVERLOAD_SIZE")
        .ok()
        .and_then(|s| {
            let (a, b) = s.split_once('x')?;
            Some((a.parse().ok()?, b.parse().ok()?))
        })
        .unwrap_or((256usize, 212usize));
    // `cargo bench` passes `--bench`; nothing else to parse.
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let started = Instant::now();
    for (round, &n) in clients.iter().enumerate() {
        let requests: Vec<pb::TofDepthRequest> = (0..n)
            .map(|i| frame(w, h, 10_000 * (round as u64 + 1) + i as u64))
            .collect();
        let server = rt
            .block_on(InProcessServer::start(ServerConfig {
                jobs: JobsConfig {
                    workers: 0,
                    concurrent_jobs: 1,
                    queue_capacity: 8,
                    ..JobsConfig::default()
                },
                ..ServerConfig::default()
            }))
            .expect("server");
        let url = server.url();
        let results: Vec<(f64, usize)> = rt.block_on(async {
            let tasks: Vec<_> = requests
                .into_iter()
                .map(|req| {
                    let url = url.clone();
                    tokio::spawn(async move {
                        let channel = Endpoint::from_shared(url).expect("url").connect_lazy();
                        let mut client =
                            pb::reconstruction_client::ReconstructionClient::new(channel)
                                .max_decoding_message_size(usize::MAX)
                                .max_encoding_message_size(usize::MAX);
                        let t0 = Instant::now();
                        let mut refused = 0;
                        loop {
                            match client.tof_depth(req.clone()).await {
                                Ok(_) => return (t0.elapsed().as_secs_f64(), refused),
                                Err(s) if s.code() == Code::ResourceExhausted => {
                                    refused += 1;
                                    let delay = s
                                        .get_error_details()
                                        .retry_info()
                                        .and_then(|r| r.retry_delay)
                                        .unwrap_or(Duration::from_secs(1));
                                    tokio::time::sleep(delay).await;
                                }
                                Err(s) => panic!("unexpected {s:?}"),
                            }
                            assert!(
                                t0.elapsed() < Duration::from_secs(600),
                                "run exceeded its 10-minute bound"
                            );
                        }
                    })
                })
                .collect();
            let mut out = Vec::new();
            for t in tasks {
                out.push(t.await.expect("client task"));
            }
            out
        });
        rt.block_on(server.stop()).expect("stop");
        let mut lat: Vec<f64> = results.iter().map(|r| r.0).collect();
        lat.sort_by(f64::total_cmp);
        let refused: usize = results.iter().map(|r| r.1).sum();
        println!(
            "overload {n:>3} clients, {w}x{h} ToF, queue 8: p50 {:.2} s  p95 {:.2} s  p99 {:.2} s  max {:.2} s  (refused attempts {refused}, wall {:.1} s)",
            percentile(&lat, 0.5),
            percentile(&lat, 0.95),
            percentile(&lat, 0.99),
            lat.last().copied().unwrap_or(0.0),
            lat.last().copied().unwrap_or(0.0),
        );
    }
    println!("total {:.1} s", started.elapsed().as_secs_f64());
}
