//! Latency under overload: N concurrent clients each send one ToF frame through the unary
//! `Reconstruction.TofDepth` RPC to a server with a queue of 8, and retry every
//! RESOURCE_EXHAUSTED after the `RetryInfo` delay the server suggests, as a well-behaved gRPC
//! client does. Reports p50/p95/p99/max of the time from a client's first attempt to its result,
//! and the number of refused attempts. Every frame is distinct (no cache hits).
//!
//! A second scenario mixes methods: 4 clients send 96×96 photometric-stereo captures (r = 61, about a second each)
//! just before 24 clients send 32×24 ToF frames (milliseconds each); it reports the ToF clients' latency, which a
//! single FIFO would make wait behind every queued PS job.
//!
//! cargo bench -p murk-server --bench overload            (MURK_OVERLOAD_CLIENTS=16,64 MURK_OVERLOAD_SIZE=256x212)
//!
//! Bounded: at most one request per client and a 10-minute cap on each request.

use std::time::{Duration, Instant};

use murk::ps::PsParams;
use murk::simulate::ps::{simulate_ps, PsSimConfig};
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk::Monitor;
use murk_server::jobs::JobsConfig;
use murk_server::server::{InProcessServer, ServerConfig};
use murk_server::service::convert::{ps_request_to_proto, simulated_tof_request};
use murk_server::service::proto::v1 as pb;
use tonic::transport::Endpoint;
use tonic::Code;
use tonic_types::StatusExt;

fn frame(width: usize, height: usize, seed: u64) -> pb::TofDepthRequest {
    let cfg = TofSimConfig {
        seed,
        ..TofSimConfig::with_size(width, height)
    };
    let f = simulate_tof(&cfg, &Monitor::noop()).expect("simulate");
    simulated_tof_request(&f, &cfg)
}

/// One unary call, retried after every RESOURCE_EXHAUSTED as RetryInfo says: (latency s, refusals).
async fn call_until_accepted(url: String, req: Req) -> (f64, usize) {
    let channel = Endpoint::from_shared(url).expect("url").connect_lazy();
    let mut client = pb::reconstruction_client::ReconstructionClient::new(channel)
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX);
    let t0 = Instant::now();
    let mut refused = 0;
    loop {
        let outcome = match req.clone() {
            Req::Tof(r) => client.tof_depth(*r).await.map(|_| ()),
            Req::Ps(r) => client.photometric_stereo(*r).await.map(|_| ()),
        };
        match outcome {
            Ok(()) => return (t0.elapsed().as_secs_f64(), refused),
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
            "a request exceeded its 10-minute bound"
        );
    }
}

#[derive(Clone)]
enum Req {
    Tof(Box<pb::TofDepthRequest>),
    Ps(Box<pb::PhotometricStereoRequest>),
}

fn ps_capture(seed: u64) -> pb::PhotometricStereoRequest {
    let sim = simulate_ps(
        &PsSimConfig {
            seed,
            ..PsSimConfig::with_size(96, 96)
        },
        &Monitor::noop(),
    )
    .expect("simulate ps");
    ps_request_to_proto(
        &sim.capture,
        &PsParams {
            initial_distance_mm: sim.initial_distance_mm,
            support_r: 61,
            far_cell: 1,
            ..PsParams::default()
        },
    )
}

fn server(rt: &tokio::runtime::Runtime) -> InProcessServer {
    rt.block_on(InProcessServer::start(ServerConfig {
        jobs: JobsConfig {
            workers: 0,
            concurrent_jobs: 1,
            queue_capacity: 8,
            ..JobsConfig::default()
        },
        ..ServerConfig::default()
    }))
    .expect("server")
}

fn report(label: &str, results: &[(f64, usize)], wall: f64) {
    let mut lat: Vec<f64> = results.iter().map(|r| r.0).collect();
    lat.sort_by(f64::total_cmp);
    let refused: usize = results.iter().map(|r| r.1).sum();
    println!(
        "{label}: p50 {:.2} s  p95 {:.2} s  p99 {:.2} s  max {:.2} s  (refused attempts {refused}, wall {wall:.1} s)",
        percentile(&lat, 0.5),
        percentile(&lat, 0.95),
        percentile(&lat, 0.99),
        lat.last().copied().unwrap_or(0.0),
    );
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
        let server = server(&rt);
        let url = server.url();
        let round_started = Instant::now();
        let results: Vec<(f64, usize)> = rt.block_on(async {
            let tasks: Vec<_> = requests
                .into_iter()
                .map(|r| tokio::spawn(call_until_accepted(url.clone(), Req::Tof(Box::new(r)))))
                .collect();
            let mut out = Vec::new();
            for t in tasks {
                out.push(t.await.expect("client task"));
            }
            out
        });
        let wall = round_started.elapsed().as_secs_f64();
        rt.block_on(server.stop()).expect("stop");
        report(
            &format!("overload {n:>3} clients, {w}x{h} ToF, queue 8"),
            &results,
            wall,
        );
    }

    // Mixed methods: long PS jobs queued first, then short ToF frames.
    let ps: Vec<pb::PhotometricStereoRequest> = (0..4).map(|i| ps_capture(100 + i)).collect();
    let tof: Vec<pb::TofDepthRequest> = (0..24).map(|i| frame(32, 24, 900 + i)).collect();
    let server = server(&rt);
    let url = server.url();
    let round_started = Instant::now();
    let (ps_results, tof_results) = rt.block_on(async {
        let ps_tasks: Vec<_> = ps
            .into_iter()
            .map(|r| tokio::spawn(call_until_accepted(url.clone(), Req::Ps(Box::new(r)))))
            .collect();
        // Let the PS requests reach the queue first.
        while server.manager().queued() + (server.manager().executed() as usize) < 4 {
            tokio::task::yield_now().await;
        }
        let tof_tasks: Vec<_> = tof
            .into_iter()
            .map(|r| tokio::spawn(call_until_accepted(url.clone(), Req::Tof(Box::new(r)))))
            .collect();
        let mut a = Vec::new();
        for t in ps_tasks {
            a.push(t.await.expect("ps client"));
        }
        let mut b = Vec::new();
        for t in tof_tasks {
            b.push(t.await.expect("tof client"));
        }
        (a, b)
    });
    let wall = round_started.elapsed().as_secs_f64();
    rt.block_on(server.stop()).expect("stop");
    report("mixed: 4 PS 96x96 (r=61, exact)", &ps_results, wall);
    report("mixed: 24 ToF 32x24 behind them", &tof_results, wall);
    println!("total {:.1} s", started.elapsed().as_secs_f64());
}
