//! Peak memory of a `murk serve` process while many clients watch one finished job with a
//! 2.6 MB result (a 256×212 ToF frame with every output in F32).
//!
//! Two rounds against a fresh server:
//! - **readers:** `--watchers` streams (default 300, over 10 connections) ask for the result
//!   inline and read to the end;
//! - **stallers:** as many streams open and read nothing for 3 s, then cancel; three times.
//!
//! The server's RSS is sampled from `/proc` every 10 ms; the peak above its RSS at rest (after
//! the job) is what the watchers cost. Streams over `--max-watchers-per-job` are refused, and
//! results beyond the `--watch-result-budget-bytes` budget go out omitted (the client would
//! fetch them with GetJobResult); both are counted.
//!
//! ```text
//! cargo build --release -p murk-server
//! cargo run --release -p murk-server --example watch_memory
//! cargo run --release -p murk-server --example watch_memory -- --serve-arg=--max-watchers-per-job=300
//! ```

use std::process::{Child, Command};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use murk::monitor::Monitor;
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk_server::service::convert::simulated_tof_request;
use murk_server::service::proto::v1 as pb;
use pb::jobs_client::JobsClient;
use tonic::transport::{Channel, Endpoint};

/// The test suite's helper that starts `murk serve` and reads its address from the log.
#[path = "../tests/service/common/serve.rs"]
mod serve_child;

#[path = "common/rss.rs"]
mod rss;
use rss::rss_bytes;

struct Args {
    murk: String,
    watchers: usize,
    connections: usize,
    serve_args: Vec<String>,
}

fn args() -> anyhow::Result<Args> {
    let mut a = Args {
        murk: concat!(env!("CARGO_MANIFEST_DIR"), "/../../target/release/murk").to_string(),
        watchers: 300,
        connections: 10,
        serve_args: Vec::new(),
    };
    for arg in std::env::args().skip(1) {
        let (key, value) = arg.split_once('=').unwrap_or((arg.as_str(), ""));
        match key {
            "--murk" => a.murk = value.to_string(),
            "--watchers" => a.watchers = value.parse().context("--watchers=N")?,
            "--connections" => a.connections = value.parse().context("--connections=N")?,
            "--serve-arg" => a.serve_args.push(value.to_string()),
            other => bail!(
                "unknown argument {other} (--murk=PATH --watchers=N --connections=N \
                 --serve-arg=FLAG=VALUE)"
            ),
        }
    }
    anyhow::ensure!(
        a.watchers > 0 && a.connections > 0,
        "counts must be positive"
    );
    Ok(a)
}

/// Starts `murk serve` on a free loopback port; returns it and its URL.
fn serve(a: &Args) -> anyhow::Result<(Child, String)> {
    anyhow::ensure!(
        std::path::Path::new(&a.murk).exists(),
        "{} not found (cargo build --release -p murk-server first)",
        a.murk
    );
    let mut cmd = Command::new(&a.murk);
    cmd.args(["serve", "--addr", "127.0.0.1:0", "--workers", "2"])
        .args(&a.serve_args);
    Ok(serve_child::spawn_serve(cmd))
}

/// Samples the RSS of `pid` until `stop`, keeping the peak.
fn sampler(pid: u32, stop: Arc<AtomicBool>, peak: Arc<AtomicU64>) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        while !stop.load(Ordering::SeqCst) {
            peak.fetch_max(rss_bytes(pid), Ordering::SeqCst);
            std::thread::sleep(Duration::from_millis(10));
        }
    })
}

#[derive(Default, Debug)]
struct Tally {
    inline: usize,
    omitted: usize,
    refused: usize,
    other_errors: usize,
}

async fn readers(channels: &[Channel], id: &str, n: usize) -> Tally {
    let tasks: Vec<_> = (0..n)
        .map(|k| {
            let mut c = JobsClient::new(channels[k % channels.len()].clone())
                .max_decoding_message_size(usize::MAX);
            let id = id.to_string();
            tokio::spawn(async move {
                let stream = c
                    .watch_job(pb::WatchJobRequest {
                        id,
                        omit_result: false,
                    })
                    .await;
                let mut stream = match stream {
                    Ok(s) => s.into_inner(),
                    Err(e) if e.code() == tonic::Code::ResourceExhausted => return 2,
                    Err(_) => return 3,
                };
                let mut last = None;
                while let Ok(Some(j)) = stream.message().await {
                    last = Some(j);
                }
                match last {
                    Some(j) if j.result_omitted => 1,
                    Some(_) => 0,
                    None => 3,
                }
            })
        })
        .collect();
    let mut t = Tally::default();
    for task in tasks {
        match task.await.unwrap_or(3) {
            0 => t.inline += 1,
            1 => t.omitted += 1,
            2 => t.refused += 1,
            _ => t.other_errors += 1,
        }
    }
    t
}

async fn stallers(channels: &[Channel], id: &str, n: usize, stall: Duration) -> Tally {
    let mut streams = Vec::new();
    let mut t = Tally::default();
    for k in 0..n {
        let mut c = JobsClient::new(channels[k % channels.len()].clone())
            .max_decoding_message_size(usize::MAX);
        match c
            .watch_job(pb::WatchJobRequest {
                id: id.to_string(),
                omit_result: false,
            })
            .await
        {
            Ok(s) => streams.push(s.into_inner()),
            Err(e) if e.code() == tonic::Code::ResourceExhausted => t.refused += 1,
            Err(_) => t.other_errors += 1,
        }
    }
    tokio::time::sleep(stall).await;
    drop(streams);
    t
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let a = args()?;
    let (mut child, url) = serve(&a)?;
    let pid = child.id();
    let result = run(&a, &url, pid).await;
    let _ = child.kill();
    let _ = child.wait();
    result
}

async fn run(a: &Args, url: &str, pid: u32) -> anyhow::Result<()> {
    let channels: Vec<Channel> = (0..a.connections)
        .map(|_| Endpoint::from_shared(url.to_string()).map(|e| e.connect_lazy()))
        .collect::<Result<_, _>>()?;
    let cfg = TofSimConfig {
        seed: 1,
        ..TofSimConfig::with_size(256, 212)
    };
    let frame = simulate_tof(&cfg, &Monitor::noop())?;
    let mut req = simulated_tof_request(&frame, &cfg);
    req.outputs = Some(pb::OutputOptions {
        fields: murk_server::service::convert::TOF_OUTPUTS
            .iter()
            .map(|f| f.name.to_string())
            .collect(),
        encoding: pb::ImageEncoding::F32 as i32,
    });
    let mut c = JobsClient::new(channels[0].clone()).max_decoding_message_size(usize::MAX);
    let id = c
        .submit_job(pb::SubmitJobRequest {
            request: Some(pb::JobRequest {
                method: Some(pb::job_request::Method::TofDepth(req)),
            }),
            omit_result: true,
        })
        .await?
        .into_inner()
        .id;
    let mut watch = c
        .watch_job(pb::WatchJobRequest {
            id: id.clone(),
            omit_result: true,
        })
        .await?
        .into_inner();
    let mut size = 0;
    while let Some(j) = watch.message().await? {
        size = j.result_size_bytes;
    }
    drop(watch);
    anyhow::ensure!(size > 0, "the job did not succeed");
    let rest = rss_bytes(pid);
    println!(
        "server pid {pid}: result {:.2} MB, RSS at rest {:.0} MB; {} watchers over {} connections; server flags: {:?}",
        size as f64 / 1e6,
        rest as f64 / 1e6,
        a.watchers,
        a.connections,
        a.serve_args
    );

    let mib = |b: u64| b.saturating_sub(rest) as f64 / (1u64 << 20) as f64;
    let (stop, peak) = (
        Arc::new(AtomicBool::new(false)),
        Arc::new(AtomicU64::new(0)),
    );
    let s = sampler(pid, stop.clone(), peak.clone());
    let started = Instant::now();
    let t = readers(&channels, &id, a.watchers).await;
    stop.store(true, Ordering::SeqCst);
    s.join().ok();
    println!(
        "readers:  peak {:.0} MiB above rest in {:.1} s; {} inline, {} omitted (budget), {} refused (per-job cap), {} other errors",
        mib(peak.load(Ordering::SeqCst)),
        started.elapsed().as_secs_f64(),
        t.inline,
        t.omitted,
        t.refused,
        t.other_errors
    );

    let (stop, peak) = (
        Arc::new(AtomicBool::new(false)),
        Arc::new(AtomicU64::new(0)),
    );
    let s = sampler(pid, stop.clone(), peak.clone());
    let mut total = Tally::default();
    for _ in 0..3 {
        let t = stallers(&channels, &id, a.watchers, Duration::from_secs(3)).await;
        total.refused += t.refused;
        total.other_errors += t.other_errors;
    }
    stop.store(true, Ordering::SeqCst);
    s.join().ok();
    println!(
        "stallers: peak {:.0} MiB above rest over 3 rounds of {} streams unread for 3 s; {} refused, {} other errors; RSS after {:.0} MB",
        mib(peak.load(Ordering::SeqCst)),
        a.watchers,
        total.refused,
        total.other_errors,
        rss_bytes(pid) as f64 / 1e6
    );
    Ok(())
}
