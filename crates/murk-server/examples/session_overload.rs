//! One ToF sensor session overloaded for a minute: frames arrive at twice the rate the session
//! sustains, under the `latest` queue policy. What a robot that sends faster than murk computes
//! gets: the server's memory over the minute, the drops, and the latency of what is answered.
//!
//! 1. `--distinct` frames (6) of a simulated moving stream (512×424, medium fog, objects moving,
//!    fog drifting) are simulated once and sent in a cycle.
//! 2. **Calibration.** A `fifo` session is sent `--calibration-frames` (8) as fast as it takes
//!    them. The mean compute time of its frames after the first (which starts cold) gives the
//!    rate one session sustains: one frame per compute time.
//! 3. **Overload.** A `latest` session (a queue of one frame) is sent frames at `--load` (2)
//!    times that rate for `--seconds` (60). Every superseded frame must come back as a
//!    `FrameDropped` naming it. With `--sessions=N`, N such sessions run at once, each at that
//!    rate, and the answered frames per session show how evenly the replica shares its cores.
//!
//! The server is a separate `murk serve` process; its RSS is sampled every 100 ms and reported
//! as the largest value in each 5 s window. Latency is the client's, from sending a frame to
//! receiving its result.
//!
//! ```text
//! cargo build --release -p murk-server
//! cargo run --release -p murk-server --example session_overload
//! cargo run --release -p murk-server --example session_overload -- --seconds=20 --size=256x212
//! cargo run --release -p murk-server --example session_overload -- --sessions=2 --seconds=30
//! ```

use std::collections::HashMap;
use std::process::{Child, Command};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context};
use murk::monitor::Monitor;
use murk::simulate::tof::TofSimConfig;
use murk::simulate::tof_sequence::{simulate_tof_sequence_frame, TofMotion};
use murk_server::service::convert::simulated_tof_request;
use murk_server::service::proto::v1 as pb;
use pb::session_event::Event;
use pb::sessions_client::SessionsClient;
use tokio::sync::mpsc;
use tonic::transport::{Channel, Endpoint};

/// The test suite's helper that starts `murk serve` and reads its address from the log.
#[path = "../tests/service/common/serve.rs"]
mod serve_child;

#[path = "common/rss.rs"]
mod rss;
use rss::rss_bytes;

struct Args {
    murk: String,
    width: usize,
    height: usize,
    distinct: usize,
    calibration_frames: usize,
    load: f64,
    seconds: f64,
    sessions: usize,
}

fn args() -> anyhow::Result<Args> {
    let mut a = Args {
        murk: concat!(env!("CARGO_MANIFEST_DIR"), "/../../target/release/murk").to_string(),
        width: 512,
        height: 424,
        distinct: 6,
        calibration_frames: 8,
        load: 2.0,
        seconds: 60.0,
        sessions: 1,
    };
    for arg in std::env::args().skip(1) {
        let (key, value) = arg.split_once('=').unwrap_or((arg.as_str(), ""));
        match key {
            "--murk" => a.murk = value.to_string(),
            "--size" => {
                let (w, h) = value.split_once('x').context("--size=WxH")?;
                (a.width, a.height) = (w.parse()?, h.parse()?);
            }
            "--distinct" => a.distinct = value.parse().context("--distinct=N")?,
            "--calibration-frames" => {
                a.calibration_frames = value.parse().context("--calibration-frames=N")?
            }
            "--load" => a.load = value.parse().context("--load=X")?,
            "--seconds" => a.seconds = value.parse().context("--seconds=S")?,
            "--sessions" => a.sessions = value.parse().context("--sessions=N")?,
            other => bail!(
                "unknown argument {other} (--murk=PATH --size=WxH --distinct=N \
                 --calibration-frames=N --load=X --seconds=S --sessions=N)"
            ),
        }
    }
    ensure!(a.distinct > 0, "--distinct must be positive");
    ensure!(
        a.calibration_frames >= 2,
        "--calibration-frames must be at least 2"
    );
    ensure!(
        a.load > 0.0 && a.load <= 100.0,
        "--load must be in (0, 100]"
    );
    ensure!(
        (1..=16).contains(&a.sessions),
        "--sessions must be in 1..=16"
    );
    ensure!(
        a.seconds > 0.0 && a.seconds <= 3600.0,
        "--seconds must be in (0, 3600]"
    );
    Ok(a)
}

/// What one session did.
#[derive(Default)]
struct Run {
    sent: usize,
    answered: usize,
    failed: usize,
    /// Drops, and how many of them named a frame that was sent and not answered.
    dropped: usize,
    dropped_named: usize,
    /// Send → result, seconds.
    latencies: Vec<f64>,
    /// Server-side compute, seconds, in the order of the results.
    compute: Vec<f64>,
    seconds: f64,
}

/// Streams `frames` (cycled, numbered from 1) through a session configured by `config`: `count`
/// frames, or as many as `period` allows in `duration`, and collects what comes back.
async fn session(
    channel: Channel,
    config: pb::SessionConfig,
    frames: Arc<Vec<pb::SessionFrame>>,
    count: Option<usize>,
    schedule: Option<(Duration, Duration)>,
) -> anyhow::Result<Run> {
    let mut client = SessionsClient::new(channel)
        .max_encoding_message_size(usize::MAX)
        .max_decoding_message_size(usize::MAX);
    let (tx, rx) = mpsc::channel::<pb::SessionRequest>(1);
    tx.send(pb::SessionRequest {
        message: Some(pb::session_request::Message::Config(config)),
    })
    .await?;
    let outbound =
        futures::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|m| (m, rx)) });
    let mut events = client.stream(outbound).await?.into_inner();
    match events.message().await? {
        Some(pb::SessionEvent {
            event: Some(Event::Started(_)),
        }) => {}
        other => bail!("the session did not start: {other:?}"),
    }
    let sent_at: Arc<Mutex<HashMap<u64, Instant>>> = Arc::default();
    let started = Instant::now();
    let sender = {
        let sent_at = sent_at.clone();
        tokio::spawn(async move {
            let mut ticks = schedule.map(|(period, _)| tokio::time::interval(period));
            let mut sent = 0usize;
            loop {
                if count.is_some_and(|c| sent >= c)
                    || schedule.is_some_and(|(_, d)| started.elapsed() >= d)
                {
                    break;
                }
                if let Some(t) = ticks.as_mut() {
                    t.tick().await;
                }
                let sequence = sent as u64 + 1;
                let frame = pb::SessionFrame {
                    sequence,
                    frame_id: format!("f{sequence}"),
                    ..frames[sent % frames.len()].clone()
                };
                sent_at
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .insert(sequence, Instant::now());
                let message = pb::session_request::Message::Frame(frame);
                if tx
                    .send(pb::SessionRequest {
                        message: Some(message),
                    })
                    .await
                    .is_err()
                {
                    break;
                }
                sent += 1;
            }
            sent
        })
    };
    let mut run = Run::default();
    while let Some(e) = events.message().await? {
        let now = Instant::now();
        let take = |sequence: u64| {
            sent_at
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .remove(&sequence)
        };
        match e.event {
            Some(Event::Result(r)) => {
                if let Some(t) = take(r.sequence) {
                    run.latencies.push((now - t).as_secs_f64());
                }
                if let Some(pb::frame_result::Outcome::Error(e)) = &r.outcome {
                    run.failed += 1;
                    eprintln!("frame {}: {} (field {})", r.frame_id, e.message, e.field);
                } else {
                    run.answered += 1;
                    run.compute.push(r.compute_seconds);
                }
            }
            Some(Event::Dropped(d)) => {
                run.dropped += 1;
                if take(d.sequence).is_some() && d.frame_id == format!("f{}", d.sequence) {
                    run.dropped_named += 1;
                }
            }
            other => bail!("unexpected event {other:?}"),
        }
    }
    run.sent = sender.await?;
    run.seconds = started.elapsed().as_secs_f64();
    Ok(run)
}

/// The sessions' runs as one: counts summed, samples pooled, the longest duration.
fn merged(runs: Vec<Run>) -> Run {
    runs.into_iter().fold(Run::default(), |mut all, r| {
        all.sent += r.sent;
        all.answered += r.answered;
        all.failed += r.failed;
        all.dropped += r.dropped;
        all.dropped_named += r.dropped_named;
        all.latencies.extend(r.latencies);
        all.compute.extend(r.compute);
        all.seconds = all.seconds.max(r.seconds);
        all
    })
}

fn percentile(values: &[f64], p: f64) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(((v.len() as f64 - 1.0) * p).round() as usize)
        .copied()
        .unwrap_or(f64::NAN)
}

fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len().max(1) as f64
}

/// Samples the RSS of `pid` every 100 ms until `stop`: (seconds since the start, bytes).
fn sampler(pid: u32, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<Vec<(f64, u64)>> {
    std::thread::spawn(move || {
        let started = Instant::now();
        let mut samples = Vec::new();
        while !stop.load(Ordering::SeqCst) {
            samples.push((started.elapsed().as_secs_f64(), rss_bytes(pid)));
            std::thread::sleep(Duration::from_millis(100));
        }
        samples
    })
}

fn serve(a: &Args) -> anyhow::Result<(Child, String)> {
    ensure!(
        std::path::Path::new(&a.murk).exists(),
        "{} not found (cargo build --release -p murk-server first)",
        a.murk
    );
    let mut cmd = Command::new(&a.murk);
    cmd.args(["serve", "--addr", "127.0.0.1:0"]);
    Ok(serve_child::spawn_serve(cmd))
}

/// The session configuration (a one-shot request with its images taken out, default outputs:
/// the compact set) and the distinct frames.
fn simulated(a: &Args) -> anyhow::Result<(pb::SessionConfig, Vec<pb::SessionFrame>)> {
    let cfg = TofSimConfig {
        seed: 1,
        ..TofSimConfig::with_size(a.width, a.height)
    };
    let motion = TofMotion::default();
    let mut config = None;
    let mut frames = Vec::new();
    for k in 0..a.distinct {
        let f = simulate_tof_sequence_frame(&cfg, &motion, k, &Monitor::noop())?;
        let mut req = simulated_tof_request(&f, &cfg);
        frames.push(pb::SessionFrame {
            amplitude: req.amplitude.take(),
            phase: req.phase.take(),
            ..Default::default()
        });
        config.get_or_insert(pb::SessionConfig {
            width: a.width as u32,
            height: a.height as u32,
            method: Some(pb::session_config::Method::Tof(req)),
            ..Default::default()
        });
    }
    Ok((config.expect("at least one frame"), frames))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let a = args()?;
    println!(
        "simulating {} distinct {}x{} frames",
        a.distinct, a.width, a.height
    );
    let (config, frames) = simulated(&a)?;
    let frames = Arc::new(frames);
    let (mut child, url) = serve(&a)?;
    let result = run(&a, &url, child.id(), config, frames).await;
    let _ = child.kill();
    let _ = child.wait();
    result
}

async fn run(
    a: &Args,
    url: &str,
    pid: u32,
    config: pb::SessionConfig,
    frames: Arc<Vec<pb::SessionFrame>>,
) -> anyhow::Result<()> {
    let channel = Endpoint::from_shared(url.to_string())?.connect().await?;
    let fifo = pb::SessionConfig {
        queue_policy: pb::QueuePolicy::Fifo as i32,
        ..config.clone()
    };
    let cal = session(
        channel.clone(),
        fifo,
        frames.clone(),
        Some(a.calibration_frames),
        None,
    )
    .await?;
    ensure!(
        cal.failed == 0 && cal.answered == a.calibration_frames,
        "the calibration frames were not all answered"
    );
    // The first frame starts cold; the overload's frames start from the previous answer.
    let compute = mean(&cal.compute[1..]);
    let sustainable = 1.0 / compute;
    let rate = a.load * sustainable;
    println!(
        "calibration (fifo, {} frames): compute {:.0} ms a frame after the first, so one session \
         sustains {sustainable:.2} frames/s; server RSS {:.0} MB",
        a.calibration_frames,
        compute * 1e3,
        rss_bytes(pid) as f64 / 1e6
    );

    let latest = pb::SessionConfig {
        queue_policy: pb::QueuePolicy::Latest as i32,
        max_queued_frames: 1,
        ..config
    };
    let stop = Arc::new(AtomicBool::new(false));
    let samples = sampler(pid, stop.clone());
    let schedule = Some((
        Duration::from_secs_f64(1.0 / rate),
        Duration::from_secs_f64(a.seconds),
    ));
    let runs = futures::future::join_all((0..a.sessions).map(|_| {
        session(
            channel.clone(),
            latest.clone(),
            frames.clone(),
            None,
            schedule,
        )
    }))
    .await;
    stop.store(true, Ordering::SeqCst);
    let samples = samples.join().expect("sampler");
    let runs = runs.into_iter().collect::<anyhow::Result<Vec<Run>>>()?;
    let answered: Vec<usize> = runs.iter().map(|r| r.answered).collect();
    let load = merged(runs);
    println!(
        "overload (latest, queue 1) of {} session(s), each at {rate:.2} frames/s ({}x one \
         session's rate) for {:.1} s: {} sent, {} answered, {} failed, {} dropped ({} reported \
         with the frame's id)",
        a.sessions,
        a.load,
        load.seconds,
        load.sent,
        load.answered,
        load.failed,
        load.dropped,
        load.dropped_named
    );
    if a.sessions > 1 {
        let (lo, hi) = (
            answered.iter().min().copied().unwrap_or(0),
            answered.iter().max().copied().unwrap_or(0),
        );
        println!(
            "answered per session: {answered:?}; fewest / most {:.2}",
            lo as f64 / hi.max(1) as f64
        );
    }
    let compute = mean(&load.compute);
    let p99 = percentile(&load.latencies, 0.99);
    println!(
        "latency send to result: p50 {:.0} ms, p90 {:.0} ms, p99 {:.0} ms; compute mean {:.0} ms; \
         p99 / compute {:.2}",
        percentile(&load.latencies, 0.5) * 1e3,
        percentile(&load.latencies, 0.9) * 1e3,
        p99 * 1e3,
        compute * 1e3,
        p99 / compute
    );
    let window = 5.0;
    let windows = (load.seconds / window).ceil() as usize;
    let peaks: Vec<u64> = (0..windows)
        .map(|w| {
            samples
                .iter()
                .filter(|(t, _)| (*t / window) as usize == w)
                .map(|s| s.1)
                .max()
                .unwrap_or(0)
        })
        .collect();
    let mb = |b: u64| b as f64 / 1e6;
    println!(
        "server RSS, largest in each {window:.0} s window (MB): {}",
        peaks
            .iter()
            .map(|p| format!("{:.0}", mb(*p)))
            .collect::<Vec<_>>()
            .join(" ")
    );
    if let (Some(second), Some(last)) = (peaks.get(1), peaks.last()) {
        println!(
            "RSS change from the second window to the last: {:+.1} MB",
            mb(*last) - mb(*second)
        );
    }
    ensure!(
        load.dropped == load.dropped_named,
        "a dropped frame was reported without its id"
    );
    Ok(())
}
