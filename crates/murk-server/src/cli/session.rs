//! Streams a sequence of frames through a sensor session (`murk tof --sequence`,
//! `murk stereo --sequence`): frames are read and sent by one task (at the sensor's rate with
//! `--rate-hz`), results are received and written by another, and the run ends with the frame
//! rate and the latency percentiles.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};
use tokio::sync::mpsc;

use murk_server::server::{InProcessServer, ServerConfig};
use murk_server::service::proto::v1 as pb;
use pb::session_event::Event;
use pb::sessions_client::SessionsClient;

use super::client::{bearer_token, channel};

/// The queue policy, as named on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum QueuePolicyArg {
    /// Every frame is computed; a full queue pushes back on the sender.
    Fifo,
    /// A full queue drops its oldest frame (reported): the latest frames are answered.
    Latest,
}

/// Options of a streamed sequence.
#[derive(Args, Debug, Clone)]
pub struct SequenceFlags {
    /// Stream every sub-folder of DIR (sorted by name; each one frame in the one-shot layout)
    /// through a sensor session instead of computing one frame. Writes OUT/<frame>/.
    #[arg(long)]
    pub sequence: Option<PathBuf>,
    /// Queue policy of the session.
    #[arg(long, value_enum, default_value_t = QueuePolicyArg::Fifo, requires = "sequence")]
    pub queue_policy: QueuePolicyArg,
    /// Frames that may wait while one is computed, 1..=64 (default 1 for latest, 4 for fifo).
    #[arg(long, requires = "sequence")]
    pub max_queued_frames: Option<u32>,
    /// Send frames at this rate, as the sensor would, instead of as fast as the session takes
    /// them.
    #[arg(long, requires = "sequence")]
    pub rate_hz: Option<f64>,
    /// Drop frames that waited longer than this, seconds.
    #[arg(long, requires = "sequence")]
    pub frame_deadline_secs: Option<f64>,
}

impl SequenceFlags {
    /// The session configuration's queue fields.
    pub fn apply(&self, config: &mut pb::SessionConfig) {
        config.queue_policy = match self.queue_policy {
            QueuePolicyArg::Fifo => pb::QueuePolicy::Fifo,
            QueuePolicyArg::Latest => pb::QueuePolicy::Latest,
        } as i32;
        config.max_queued_frames = self.max_queued_frames.unwrap_or(0);
        config.frame_deadline_seconds = self.frame_deadline_secs.unwrap_or(0.0);
    }

    /// Streams frame folders (`--sequence`) at `--rate-hz`, each result written by `write` into
    /// `out`, and prints the run's summary.
    pub fn stream_folders(
        &self,
        url: Option<&str>,
        config: pb::SessionConfig,
        frames: Vec<(String, PathBuf)>,
        load: LoadFrame,
        write: WriteResult,
        out: &std::path::Path,
    ) -> anyhow::Result<()> {
        let report = stream_sequence(
            url,
            config,
            folder_frames(frames, load),
            self.rate_hz,
            ResultSink { write, parallel: 2 },
        )?;
        println!("{}; outputs in {}", report.summary(), out.display());
        Ok(())
    }
}

/// The sub-folders of `dir`, sorted by name, as (name, path).
pub fn frame_dirs(dir: &std::path::Path) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let mut frames = Vec::new();
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let entry = entry?;
        if entry.file_type()?.is_dir() {
            frames.push((
                entry.file_name().to_string_lossy().into_owned(),
                entry.path(),
            ));
        }
    }
    frames.sort();
    if frames.is_empty() {
        bail!("{} has no frame folders", dir.display());
    }
    Ok(frames)
}

/// Loads one frame's images (blocking).
pub type LoadFrame =
    Arc<dyn Fn(&std::path::Path) -> anyhow::Result<pb::SessionFrame> + Send + Sync>;
/// The frames of a stream, read on a blocking thread one at a time. A frame without a
/// sequence number gets its position (from 1); one without a stamp gets the time it is sent.
pub type FrameSource = Box<dyn Iterator<Item = anyhow::Result<pb::SessionFrame>> + Send>;

/// The frames of folders (see [`frame_dirs`]), each loaded by `load` and named by its folder.
pub fn folder_frames(frames: Vec<(String, PathBuf)>, load: LoadFrame) -> FrameSource {
    Box::new(frames.into_iter().map(move |(name, dir)| {
        let mut frame = load(&dir).with_context(|| format!("reading frame {name}"))?;
        frame.frame_id = name;
        Ok(frame)
    }))
}
/// Writes one frame's result under its name (blocking).
pub type WriteResult = Arc<dyn Fn(&str, &pb::FrameResult) -> anyhow::Result<()> + Send + Sync>;

/// What a streamed sequence did.
#[derive(Debug, Default)]
pub struct SequenceReport {
    /// Frames sent.
    pub sent: usize,
    /// Frames computed.
    pub computed: usize,
    /// Frames answered with an error.
    pub failed: usize,
    /// Frames dropped by the queue policy or the deadline.
    pub dropped: usize,
    /// From the first frame sent to the last event, seconds.
    pub seconds: f64,
    /// Send → result, seconds, per answered frame.
    pub latencies: Vec<f64>,
    /// Server-side compute, seconds, per computed frame.
    pub compute: Vec<f64>,
    /// When each computed frame's result arrived, seconds after the first frame was sent.
    pub arrivals: Vec<f64>,
}

impl SequenceReport {
    /// Computed frames per second from the first result to the last: the rate a stream
    /// sustains once running, without the first frame, which a session computes from scratch.
    /// `None` with fewer than two results.
    pub fn sustained_rate(&self) -> Option<f64> {
        match self.arrivals.as_slice() {
            [first, .., last] if last > first => {
                Some((self.arrivals.len() - 1) as f64 / (last - first))
            }
            _ => None,
        }
    }

    /// One line: frames/s and the latency percentiles.
    pub fn summary(&self) -> String {
        let mut l = self.latencies.clone();
        l.sort_by(f64::total_cmp);
        let pct = |p: f64| {
            l.get(((l.len() as f64 - 1.0) * p).round() as usize)
                .map_or(f64::NAN, |v| v * 1e3)
        };
        let mean_compute = self.compute.iter().sum::<f64>() / self.compute.len().max(1) as f64;
        let sustained = self.sustained_rate().map_or_else(String::new, |r| {
            format!(" ({r:.2} from the first result on)")
        });
        format!(
            "{} frames sent, {} computed, {} failed, {} dropped in {:.2} s: {:.2} frames/s{}; \
             latency (send to result) p50 {:.0} ms, p90 {:.0} ms, p99 {:.0} ms; compute mean \
             {:.0} ms",
            self.sent,
            self.computed,
            self.failed,
            self.dropped,
            self.seconds,
            self.computed as f64 / self.seconds.max(1e-9),
            sustained,
            pct(0.5),
            pct(0.9),
            pct(0.99),
            mean_compute * 1e3,
        )
    }
}

/// How results are written: by up to `parallel` blocking tasks at once (1 keeps them in order).
#[derive(Clone)]
pub struct ResultSink {
    /// Writes one result.
    pub write: WriteResult,
    /// Results written at once.
    pub parallel: usize,
}

/// Streams `frames` through a session configured by `config`, on `url` or on a server started
/// in this process, sending at `rate_hz` when given.
pub fn stream_sequence(
    url: Option<&str>,
    config: pb::SessionConfig,
    frames: FrameSource,
    rate_hz: Option<f64>,
    sink: ResultSink,
) -> anyhow::Result<SequenceReport> {
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async {
        match url {
            Some(url) => run(url, config, frames, rate_hz, sink).await,
            None => {
                let server = InProcessServer::start(ServerConfig {
                    max_request_bytes: 1 << 30,
                    ..ServerConfig::default()
                })
                .await?;
                let out = run(&server.url(), config, frames, rate_hz, sink).await;
                server.stop().await?;
                out
            }
        }
    })
}

async fn run(
    url: &str,
    config: pb::SessionConfig,
    frames: FrameSource,
    rate_hz: Option<f64>,
    sink: ResultSink,
) -> anyhow::Result<SequenceReport> {
    let channel = channel(url).await?;
    let mut client = SessionsClient::with_interceptor(channel, bearer_token()?)
        .max_encoding_message_size(usize::MAX)
        .max_decoding_message_size(usize::MAX);
    let (tx, rx) = mpsc::channel::<pb::SessionRequest>(2);
    tx.send(pb::SessionRequest {
        message: Some(pb::session_request::Message::Config(config)),
    })
    .await?;
    let outbound =
        futures::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|m| (m, rx)) });
    let mut events = client
        .stream(outbound)
        .await
        .map_err(|s| anyhow::anyhow!("opening the session: {:?}: {}", s.code(), s.message()))?
        .into_inner();
    match events.message().await {
        Ok(Some(pb::SessionEvent {
            event: Some(Event::Started(s)),
        })) => tracing::info!(session = %s.session_id, "session started"),
        Ok(other) => bail!("the session did not start: {other:?}"),
        Err(s) => bail!("the session was refused: {:?}: {}", s.code(), s.message()),
    }

    let sent_at: Arc<Mutex<HashMap<u64, Instant>>> = Arc::default();
    let started = Instant::now();
    let sender = {
        let sent_at = sent_at.clone();
        let period = rate_hz
            .filter(|r| *r > 0.0)
            .map(|r| Duration::from_secs_f64(1.0 / r));
        tokio::spawn(async move {
            let mut ticks = period.map(tokio::time::interval);
            let mut frames = frames;
            let mut sent = 0usize;
            loop {
                let (rest, next) = tokio::task::spawn_blocking(move || {
                    let next = frames.next();
                    (frames, next)
                })
                .await?;
                frames = rest;
                let Some(frame) = next else { break };
                let mut frame = frame?;
                if let Some(t) = ticks.as_mut() {
                    t.tick().await;
                }
                sent += 1;
                if frame.sequence == 0 {
                    frame.sequence = sent as u64;
                }
                if frame.stamp.is_none() {
                    frame.stamp = Some(prost_types::Timestamp::from(SystemTime::now()));
                }
                sent_at
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .insert(frame.sequence, Instant::now());
                if tx
                    .send(pb::SessionRequest {
                        message: Some(pb::session_request::Message::Frame(frame)),
                    })
                    .await
                    .is_err()
                {
                    break;
                }
            }
            // Dropping `tx` half-closes the stream: the session answers what it holds, then ends.
            anyhow::Ok(sent)
        })
    };

    let mut report = SequenceReport::default();
    // Results are written off the receiving task.
    let mut writes = tokio::task::JoinSet::new();
    loop {
        let event = match events.message().await {
            Ok(Some(e)) => e.event,
            Ok(None) => break,
            Err(s) => bail!("the session ended: {:?}: {}", s.code(), s.message()),
        };
        match event {
            Some(Event::Result(r)) => {
                let arrived = Instant::now();
                if let Some(t) = sent_at
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .remove(&r.sequence)
                {
                    report.latencies.push((arrived - t).as_secs_f64());
                }
                if let Some(pb::frame_result::Outcome::Error(e)) = &r.outcome {
                    report.failed += 1;
                    eprintln!("frame {}: {} (field {})", r.frame_id, e.message, e.field);
                    continue;
                }
                report.computed += 1;
                report.compute.push(r.compute_seconds);
                report.arrivals.push((arrived - started).as_secs_f64());
                while writes.len() >= sink.parallel.max(1) {
                    if let Some(done) = writes.join_next().await {
                        done??;
                    }
                }
                let write = sink.write.clone();
                writes.spawn_blocking(move || write(&r.frame_id, &r));
            }
            Some(Event::Dropped(d)) => {
                report.dropped += 1;
                sent_at
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .remove(&d.sequence);
                let why = match pb::DropReason::try_from(d.reason) {
                    Ok(pb::DropReason::Deadline) => "waited past its deadline",
                    _ => "superseded by a newer frame",
                };
                eprintln!("frame {} dropped: {why}", d.frame_id);
            }
            Some(Event::Refused(e)) => eprintln!("refused: {}", e.message),
            Some(Event::Started(_)) | None => {}
        }
    }
    report.seconds = started.elapsed().as_secs_f64();
    report.sent = sender.await??;
    while let Some(done) = writes.join_next().await {
        done??;
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sustained_rate_leaves_out_the_wait_for_the_first_result() {
        let report = SequenceReport {
            computed: 4,
            seconds: 1.6,
            arrivals: vec![1.0, 1.2, 1.4, 1.6],
            ..SequenceReport::default()
        };
        let rate = report.sustained_rate().unwrap();
        assert!((rate - 5.0).abs() < 1e-9, "{rate}");
        assert!(report
            .summary()
            .contains("2.50 frames/s (5.00 from the first result on)"));
        let one = SequenceReport {
            arrivals: vec![1.0],
            ..SequenceReport::default()
        };
        assert_eq!(one.sustained_rate(), None);
    }
}
