//! `murk bag IN.mcap --out OUT.mcap`: a ROS 2 bag through a sensor session. Stereo pairs
//! (`--left`, `--right`) or ToF frames (`--amplitude`, `--phase`) are read with their
//! CameraInfo, streamed through one session, and the results written to a new MCAP file as ROS 2
//! messages under `--prefix`, each with its input's stamp and frame_id.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use anyhow::{bail, Context};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use murk::camera::Intrinsics;
use murk::tof::unmeasured_range_std_m;
use murk::ImageF32;
use murk_server::bag::frames::{BagFrame, BagFrames, FramePlan};
use murk_server::bag::images::{float_image, mono8_image, to_api_image, SampleMapping};
use murk_server::bag::msgs::{CameraInfo, DisparityImage, Header, MessageType, RegionOfInterest};
use murk_server::bag::pointcloud::rgb_cloud_from_api;
use murk_server::bag::reader::{BagMessage, BagReader};
use murk_server::bag::writer::{BagWriter, ChunkCompression};
use murk_server::service::convert::{image_from_proto, ImageLimits};
use murk_server::service::proto::v1 as pb;

use super::session::{stream_sequence, ResultSink, WriteResult};
use super::stereo::StereoMethodFlags;
use super::tof::parse_numbers;

/// Options of `murk bag`.
#[derive(Args, Debug)]
pub struct BagArgs {
    /// The input bag: MCAP with CDR-encoded ROS 2 messages (rosbag2's default). Only read.
    pub input: PathBuf,
    /// The output bag (created; written as OUT.partial and renamed when complete).
    #[arg(long)]
    pub out: PathBuf,
    /// Stereo: the rectified left image topic (sensor_msgs/Image or CompressedImage).
    #[arg(long, requires = "right", conflicts_with_all = ["amplitude", "phase"])]
    pub left: Option<String>,
    /// Stereo: the rectified right image topic.
    #[arg(long, requires = "left")]
    pub right: Option<String>,
    /// The left camera's CameraInfo topic (default: `camera_info` beside the image topic, or
    /// beside its base topic for a transport's `…/compressed`).
    #[arg(long, requires = "left")]
    pub left_info: Option<String>,
    /// The right camera's CameraInfo topic (default: as for the left one);
    /// its P gives the baseline (P[3] = Tx = −fx·B).
    #[arg(long, requires = "right")]
    pub right_info: Option<String>,
    /// ToF: the amplitude image topic (32FC1, or 16-bit with --amplitude-scale).
    #[arg(long, requires = "phase", required_unless_present = "left")]
    pub amplitude: Option<String>,
    /// ToF: the phase image topic, radians (32FC1, or 16-bit with --phase-scale).
    #[arg(long, requires = "amplitude")]
    pub phase: Option<String>,
    /// The ToF camera's CameraInfo topic (default: `camera_info` beside the amplitude topic, or
    /// beside its base topic for a transport's `…/compressed`).
    #[arg(long, requires = "amplitude")]
    pub camera_info: Option<String>,
    /// ToF: modulation frequency, Hz.
    #[arg(long, requires = "amplitude")]
    pub frequency_hz: Option<f64>,
    /// ToF: multiplier of the amplitude samples (16-bit samples are first mapped to [0, 1]).
    #[arg(long, default_value_t = 1.0)]
    pub amplitude_scale: f32,
    /// ToF: multiplier of the phase samples (e.g. 6.2831853 for 16-bit phases of 0..2π).
    #[arg(long, default_value_t = 1.0)]
    pub phase_scale: f32,
    /// ToF: the light source's position "x,y,z" in the camera frame, metres.
    #[arg(long, requires = "amplitude")]
    pub light_position_m: Option<String>,
    /// ToF: cap on the fine IRLS iterations.
    #[arg(long, requires = "amplitude")]
    pub fine_iterations: Option<u32>,
    /// ToF: frames computed from the previous frame's answer solve the scatter on blocks of this
    /// many pixels a side, 1..=4 (1: at full size; default 2); frames computed from scratch
    /// solve their coarse level there.
    #[arg(long, requires = "amplitude")]
    pub scatter_grid: Option<u32>,
    /// ToF: pixels whose range_std_m exceeds this are no measurement: NaN in the depth image and
    /// left out of the points (the request's max_point_range_std_m). Fog-only pixels, whose
    /// direct return is buried in the scatter, carry spreads of metres.
    #[arg(long, default_value_t = 0.1)]
    pub max_range_std_m: f64,
    /// Stereo: the search and the haze (β per metre: CameraInfo gives metres).
    #[command(flatten)]
    pub stereo: StereoMethodFlags,
    /// Topic prefix of the results.
    #[arg(long, default_value = "/murk")]
    pub prefix: String,
    /// Compression of the output's chunks: zstd (level 1), lz4 or none.
    #[arg(long, value_enum, default_value_t = CompressionArg::Zstd)]
    pub compression: CompressionArg,
    /// Copy the input topics murk reads into the output, so one file shows both.
    #[arg(long)]
    pub copy_inputs: bool,
    /// Leave the point clouds out: the session computes none and the output has no `points`
    /// topic (the depth image and the CameraInfo let a viewer make one). A 640×480 cloud is
    /// about 4.9 MB a frame, most of what the output's compression works on.
    #[arg(long)]
    pub no_points: bool,
    /// Largest difference of the two images' header stamps in a pair, milliseconds.
    #[arg(long, default_value_t = 1.0)]
    pub stamp_tolerance_ms: f64,
    /// Largest MCAP record (a chunk, compressed or not) read, MiB.
    #[arg(long, default_value_t = 1024)]
    pub max_record_mib: usize,
    /// Frames that may wait while one is computed, 1..=64.
    #[arg(long)]
    pub max_queued_frames: Option<u32>,
    /// Server URL; without it a server is started in this process.
    #[arg(long, env = "MURK_SERVER")]
    pub server: Option<String>,
}

/// `--compression`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum CompressionArg {
    /// zstd chunks, level 1.
    Zstd,
    /// LZ4 chunks.
    Lz4,
    /// Uncompressed chunks.
    None,
}

/// The method a bag is read for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Stereo,
    Tof,
}

/// Transport suffixes of image_transport's plugins (image_transport_plugins): the compressed
/// stream of `/cam/image_rect` is published on `/cam/image_rect/compressed`, and its CameraInfo
/// stays at `/cam/camera_info`. The rule goes by the name alone (the bag is read as a stream,
/// so the topic's type is not known yet): a raw image published under such a name needs its
/// CameraInfo named with the `--*-info` flags, as the error for a missing one says.
const TRANSPORT_SUFFIXES: [&str; 4] = ["compressed", "compressedDepth", "theora", "zstd"];

/// `camera_info` beside an image topic: `/cam/left/image_rect` → `/cam/left/camera_info`, and
/// beside the base topic of a transport's topic: `/cam/left/image_rect/compressed` →
/// `/cam/left/camera_info`.
fn sibling_info(topic: &str) -> String {
    let base = match topic.rsplit_once('/') {
        Some((base, last)) if TRANSPORT_SUFFIXES.contains(&last) && !base.is_empty() => base,
        _ => topic,
    };
    match base.rsplit_once('/') {
        Some((parent, _)) => format!("{parent}/camera_info"),
        None => "camera_info".to_string(),
    }
}

/// The CameraInfo topics of a plan, for messages.
fn infos_topic(kind: Kind, plan: &FramePlan) -> String {
    match kind {
        Kind::Stereo => format!("{} / {}", plan.infos[0], plan.infos[1]),
        Kind::Tof => plan.infos[0].clone(),
    }
}

/// What the writer needs of a frame besides its result.
struct FrameMeta {
    header: Header,
    log_time: u64,
    info: CameraInfo,
    inputs: Vec<BagMessage>,
}

type Metas = Arc<Mutex<HashMap<u64, FrameMeta>>>;

/// Counts of the run, shared by the reading and the writing side.
#[derive(Default)]
struct Tally {
    frames_read: usize,
    written: usize,
    skipped: Vec<String>,
}

/// Runs `murk bag`.
pub fn run(a: BagArgs) -> anyhow::Result<()> {
    let kind = if a.left.is_some() {
        Kind::Stereo
    } else {
        Kind::Tof
    };
    if kind == Kind::Tof && (a.stereo.airlight.is_some() || a.stereo.depth_range.is_some()) {
        bail!("--airlight, --beta and --depth-range are stereo options (give --left and --right)");
    }
    if a.max_range_std_m.is_nan() || a.max_range_std_m <= 0.0 {
        bail!("--max-range-std-m must be > 0");
    }
    if !a.stamp_tolerance_ms.is_finite() || a.stamp_tolerance_ms < 0.0 {
        bail!("--stamp-tolerance-ms must be ≥ 0");
    }
    let plan = match kind {
        Kind::Stereo => {
            let (l, r) = (a.left.clone().unwrap(), a.right.clone().unwrap());
            FramePlan {
                infos: [
                    a.left_info.clone().unwrap_or_else(|| sibling_info(&l)),
                    a.right_info.clone().unwrap_or_else(|| sibling_info(&r)),
                ],
                images: [l, r],
                tolerance_ns: (a.stamp_tolerance_ms * 1e6) as u64,
                keep_inputs: a.copy_inputs,
            }
        }
        Kind::Tof => {
            let (amp, ph) = (a.amplitude.clone().unwrap(), a.phase.clone().unwrap());
            let info = a.camera_info.clone().unwrap_or_else(|| sibling_info(&amp));
            FramePlan {
                infos: [info.clone(), info],
                images: [amp, ph],
                tolerance_ns: (a.stamp_tolerance_ms * 1e6) as u64,
                keep_inputs: a.copy_inputs,
            }
        }
    };
    let reader = BagReader::open(&a.input, plan.topics(), a.max_record_mib << 20)?;
    let mut frames = BagFrames::new(reader, plan.clone());
    let first = match frames.next() {
        Some(f) => f?,
        None => {
            let skipped = frames.take_skipped();
            bail!(
                "{}: no frame on {} and {}{}",
                a.input.display(),
                plan.images[0],
                plan.images[1],
                skipped
                    .first()
                    .map(|s| format!(" ({} unpaired, e.g. {s})", skipped.len()))
                    .unwrap_or_default()
            );
        }
    };
    let (config, rig) = session_config(&a, kind, &first)?;
    let writer = BagWriter::create(
        &a.out,
        match a.compression {
            CompressionArg::Lz4 => ChunkCompression::Lz4,
            CompressionArg::Zstd => ChunkCompression::Zstd,
            CompressionArg::None => ChunkCompression::None,
        },
    )?;

    let progress = ProgressBar::new(frames.progress().1).with_style(
        ProgressStyle::with_template("{bar:40} {bytes}/{total_bytes} {msg}")
            .expect("a valid template"),
    );
    let metas: Metas = Arc::default();
    let tally: Arc<Mutex<Tally>> = Arc::default();
    let source = {
        let metas = metas.clone();
        let tally = tally.clone();
        let progress = progress.clone();
        let mapping = [
            SampleMapping {
                scale: if kind == Kind::Tof {
                    a.amplitude_scale
                } else {
                    1.0
                },
                srgb: a.stereo.srgb,
            },
            SampleMapping {
                scale: if kind == Kind::Tof {
                    a.phase_scale
                } else {
                    1.0
                },
                srgb: a.stereo.srgb,
            },
        ];
        let topics = plan.clone();
        let mut sequence = 0u64;
        let mut frames = frames;
        let mut pending = Some(first);
        Box::new(std::iter::from_fn(move || {
            let frame = match pending.take() {
                Some(f) => Ok(f),
                None => frames.next()?,
            };
            let mut t = tally.lock().unwrap_or_else(|p| p.into_inner());
            for s in frames.take_skipped() {
                progress.suspend(|| eprintln!("skipped: {s}"));
                t.skipped.push(s);
            }
            progress.set_position(frames.progress().0);
            let frame = match frame {
                Ok(f) => f,
                Err(e) => return Some(Err(anyhow::Error::new(e))),
            };
            t.frames_read += 1;
            drop(t);
            sequence += 1;
            Some(to_session_frame(
                frame, sequence, kind, &rig, &topics, mapping, &metas,
            ))
        })) as super::session::FrameSource
    };

    let writer = Arc::new(Mutex::new(Some(writer)));
    let write: WriteResult = {
        let writer = writer.clone();
        let metas = metas.clone();
        let tally = tally.clone();
        let progress = progress.clone();
        let outputs = OutputWriter {
            prefix: a.prefix.trim_end_matches('/').to_string(),
            kind,
            rig,
            max_range_std_m: a.max_range_std_m as f32,
        };
        Arc::new(move |_name: &str, r: &pb::FrameResult| {
            let meta = {
                let mut m = metas.lock().unwrap_or_else(|p| p.into_inner());
                // Frames answered with an error leave their entries behind: drop what precedes.
                m.retain(|s, _| *s >= r.sequence);
                m.remove(&r.sequence)
            }
            .with_context(|| format!("a result for frame {}, which was not sent", r.sequence))?;
            let mut guard = writer.lock().unwrap_or_else(|p| p.into_inner());
            let w = guard.as_mut().context("the output is closed")?;
            outputs.write(w, &meta, r)?;
            let mut t = tally.lock().unwrap_or_else(|p| p.into_inner());
            t.written += 1;
            progress.set_message(format!("{} frames", t.written));
            Ok(())
        })
    };
    let report = stream_sequence(
        a.server.as_deref(),
        config,
        source,
        None,
        ResultSink { write, parallel: 1 },
    );
    progress.finish_and_clear();
    let report = report?;
    let writer = writer
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .take()
        .context("the output was closed")?;
    let messages = writer.messages();
    writer.finish()?;
    let t = tally.lock().unwrap_or_else(|p| p.into_inner());
    println!(
        "{} frames read, {} processed, {} failed, {} messages skipped{}; {:.2} frames/s \
         ({:.1} s; compute {:.0} ms a frame); {messages} messages written to {}",
        t.frames_read,
        report.computed,
        report.failed,
        t.skipped.len(),
        if t.skipped.is_empty() {
            String::new()
        } else {
            " (unpaired)".to_string()
        },
        report.computed as f64 / report.seconds.max(1e-9),
        report.seconds,
        1e3 * report.compute.iter().sum::<f64>() / report.compute.len().max(1) as f64,
        a.out.display()
    );
    if report.failed > 0 {
        bail!("{} of {} frames failed", report.failed, t.frames_read);
    }
    Ok(())
}

/// The camera model a bag's results are written with.
#[derive(Clone, Copy, Debug)]
struct Rig {
    /// The (left) camera's intrinsics, pixels.
    k: Intrinsics,
    /// Stereo: baseline, metres.
    baseline_m: f64,
    /// ToF: modulation frequency, Hz.
    frequency_hz: f64,
    width: usize,
    height: usize,
}

/// The session's configuration, from the first frame's CameraInfo and the flags.
fn session_config(
    a: &BagArgs,
    kind: Kind,
    first: &BagFrame,
) -> anyhow::Result<(pb::SessionConfig, Rig)> {
    let info = &first.infos[0];
    let (width, height) = (info.width as usize, info.height as usize);
    let (k, baseline_m) = camera_of(kind, &first.infos, &first.header.stamp.display())?;
    let intrinsics = pb::CameraIntrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        skew: 0.0,
    };
    let mut config = pb::SessionConfig {
        width: width as u32,
        height: height as u32,
        queue_policy: pb::QueuePolicy::Fifo as i32,
        max_queued_frames: a.max_queued_frames.unwrap_or(0),
        ..Default::default()
    };
    let frequency_hz = match kind {
        Kind::Stereo => {
            let right_cx = first.infos[1].p[2];
            let mut request = a.stereo.request(
                intrinsics,
                baseline_m,
                (right_cx != k.cx).then_some(right_cx),
            )?;
            request.outputs = Some(pb::OutputOptions {
                fields: ["z_depth", "disparity", "confidence"]
                    .map(String::from)
                    .to_vec(),
                encoding: pb::ImageEncoding::F32 as i32,
            });
            request.return_points = !a.no_points;
            config.method = Some(pb::session_config::Method::Stereo(request));
            0.0
        }
        Kind::Tof => {
            let f = a
                .frequency_hz
                .context("ToF needs the modulation frequency: pass --frequency-hz")?;
            let light = a
                .light_position_m
                .as_deref()
                .map(|s| parse_numbers::<3>(s, "--light-position-m", "x,y,z"))
                .transpose()?;
            config.method = Some(pb::session_config::Method::Tof(pb::TofDepthRequest {
                modulation_frequency_hz: f,
                intrinsics: Some(intrinsics),
                light_position_m: light.map(|[x, y, z]| pb::Vector3 { x, y, z }),
                options: Some(pb::TofOptions {
                    fine_iterations: a.fine_iterations,
                    ..Default::default()
                }),
                return_points: !a.no_points,
                max_point_range_std_m: a.max_range_std_m as f32,
                outputs: Some(pb::OutputOptions {
                    fields: ["z_depth_m", "mask", "range_std_m"]
                        .map(String::from)
                        .to_vec(),
                    encoding: pb::ImageEncoding::F32 as i32,
                }),
                ..Default::default()
            }));
            config.tof_scatter_grid = a.scatter_grid.unwrap_or(0);
            f
        }
    };
    Ok((
        config,
        Rig {
            k,
            baseline_m,
            frequency_hz,
            width,
            height,
        },
    ))
}

/// The camera a frame's CameraInfo describes: the (left) intrinsics, and for stereo the
/// baseline in metres.
fn camera_of(kind: Kind, infos: &[CameraInfo; 2], at: &str) -> anyhow::Result<(Intrinsics, f64)> {
    match kind {
        Kind::Stereo => {
            // Rectified images: the projection matrices, not K, describe them.
            let (p, q) = (&infos[0].p, &infos[1].p);
            let k = Intrinsics::new(p[0], p[5], p[2], p[6]);
            k.validate()
                .with_context(|| format!("the left camera's CameraInfo at {at}: its P"))?;
            if q[0] <= 0.0 || !q[3].is_finite() || q[3] >= 0.0 {
                bail!(
                    "the right camera's CameraInfo at {at}: P[3] = Tx = {} with fx {}; a \
                     rectified right camera has Tx = −fx·B < 0",
                    q[3],
                    q[0]
                );
            }
            Ok((k, -q[3] / q[0]))
        }
        Kind::Tof => {
            let k = &infos[0].k;
            let k = Intrinsics::new(k[0], k[4], k[2], k[5]);
            k.validate()
                .with_context(|| format!("the CameraInfo at {at}: its K"))?;
            Ok((k, 0.0))
        }
    }
}

/// A bag frame as a session frame; what the writer needs is kept in `metas`.
fn to_session_frame(
    frame: BagFrame,
    sequence: u64,
    kind: Kind,
    rig: &Rig,
    topics: &FramePlan,
    mapping: [SampleMapping; 2],
    metas: &Metas,
) -> anyhow::Result<pb::SessionFrame> {
    let at = frame.header.stamp.display();
    // A session keeps one rig: a frame whose calibration differs would be measured with the
    // wrong one.
    let (k, baseline_m) = camera_of(kind, &frame.infos, &at)?;
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0);
    if !(close(k.fx, rig.k.fx)
        && close(k.fy, rig.k.fy)
        && close(k.cx, rig.k.cx)
        && close(k.cy, rig.k.cy)
        && close(baseline_m, rig.baseline_m))
    {
        bail!(
            "{} at {at}: the calibration changed within the bag (fx, fy, cx, cy, baseline {:?} \
             where the first frame had {:?}); murk runs a bag with one rig: split it where the \
             calibration changes",
            infos_topic(kind, topics),
            (k.fx, k.fy, k.cx, k.cy, baseline_m),
            (rig.k.fx, rig.k.fy, rig.k.cx, rig.k.cy, rig.baseline_m)
        );
    }
    let mut images = Vec::with_capacity(2);
    for (i, (img, info)) in frame.images.iter().zip(&frame.infos).enumerate() {
        let topic = &topics.images[i];
        let api =
            to_api_image(img, mapping[i]).map_err(|e| anyhow::anyhow!("{topic} at {at}: {e}"))?;
        if api.dims != (info.width as usize, info.height as usize) {
            bail!(
                "{topic} at {at}: {}×{} pixels, its CameraInfo says {}×{}",
                api.dims.0,
                api.dims.1,
                info.width,
                info.height
            );
        }
        if api.dims != (rig.width, rig.height) {
            bail!(
                "{topic} at {at}: {}×{} pixels, the bag's first frame {}×{}",
                api.dims.0,
                api.dims.1,
                rig.width,
                rig.height
            );
        }
        images.push(api.image);
    }
    let [first, second]: [pb::Image; 2] = images.try_into().expect("two images");
    let stamp = prost_types::Timestamp {
        seconds: i64::from(frame.header.stamp.sec),
        nanos: frame.header.stamp.nanosec as i32,
    };
    let mut out = pb::SessionFrame {
        sequence,
        frame_id: at,
        stamp: Some(stamp),
        ..Default::default()
    };
    match kind {
        Kind::Stereo => {
            out.left = Some(first);
            out.right = Some(second);
        }
        Kind::Tof => {
            out.amplitude = Some(first);
            out.phase = Some(second);
        }
    }
    let [info, _] = frame.infos;
    metas.lock().unwrap_or_else(|p| p.into_inner()).insert(
        sequence,
        FrameMeta {
            header: frame.header,
            log_time: frame.log_time,
            info,
            inputs: frame.inputs,
        },
    );
    Ok(out)
}

/// Writes one frame's results as ROS 2 messages.
struct OutputWriter {
    prefix: String,
    kind: Kind,
    rig: Rig,
    max_range_std_m: f32,
}

impl OutputWriter {
    fn write(
        &self,
        w: &mut BagWriter,
        meta: &FrameMeta,
        r: &pb::FrameResult,
    ) -> anyhow::Result<()> {
        for m in &meta.inputs {
            w.copy(m)?;
        }
        let limits = ImageLimits {
            max_pixels: u64::MAX,
            max_channels: 4,
        };
        let decode = |name: &str, img: &Option<pb::Image>| -> anyhow::Result<ImageF32> {
            let img = img
                .as_ref()
                .with_context(|| format!("the result has no {name}"))?;
            image_from_proto(img, &limits).with_context(|| format!("decoding {name}"))
        };
        let topic = |name: &str| format!("{}/{name}", self.prefix);
        let (h, t) = (&meta.header, meta.log_time);
        let mut info = meta.info.clone();
        info.header = h.clone();
        let points = match (&r.outcome, self.kind) {
            (Some(pb::frame_result::Outcome::Stereo(s)), Kind::Stereo) => {
                let z = decode("z_depth", &s.z_depth)?;
                let disparity = decode("disparity", &s.disparity)?;
                let confidence = decode("confidence", &s.confidence)?;
                // Pixels the consistency checks rejected (confidence 0) hold a filled-in depth:
                // no measurement, NaN as REP 118 has it.
                let rejected = |i: usize| confidence.data()[i] <= 0.0;
                w.write(
                    &topic("depth"),
                    MessageType::Image,
                    t,
                    &float_image(h, &z, rejected),
                )?;
                w.write(
                    &topic("confidence"),
                    MessageType::Image,
                    t,
                    &float_image(h, &confidence, |_| false),
                )?;
                let planes = s.num_planes.max(2) as f32;
                w.write(
                    &topic("disparity"),
                    MessageType::DisparityImage,
                    t,
                    &DisparityImage {
                        header: h.clone(),
                        image: float_image(h, &disparity, rejected),
                        f: self.rig.k.fx as f32,
                        t: self.rig.baseline_m as f32,
                        valid_window: RegionOfInterest {
                            width: self.rig.width as u32,
                            height: self.rig.height as u32,
                            ..RegionOfInterest::default()
                        },
                        min_disparity: s.min_disparity_px,
                        max_disparity: s.max_disparity_px,
                        delta_d: (s.max_disparity_px - s.min_disparity_px) / (planes - 1.0),
                    },
                )?;
                s.points.as_ref()
            }
            (Some(pb::frame_result::Outcome::Tof(o)), Kind::Tof) => {
                let z = decode("z_depth_m", &o.z_depth_m)?;
                let mask = decode("mask", &o.mask)?;
                let std = decode("range_std_m", &o.range_std_m)?;
                // The cap marks a pixel with no direct return at all; the limit, one too
                // uncertain to publish.
                let cap = unmeasured_range_std_m(self.rig.frequency_hz).min(self.max_range_std_m);
                let unmeasured = |i: usize| std.data()[i].is_nan() || std.data()[i] >= cap;
                w.write(
                    &topic("depth"),
                    MessageType::Image,
                    t,
                    &float_image(h, &z, unmeasured),
                )?;
                w.write(
                    &topic("mask"),
                    MessageType::Image,
                    t,
                    &mono8_image(h, &mask),
                )?;
                w.write(
                    &topic("range_std"),
                    MessageType::Image,
                    t,
                    &float_image(h, &std, |_| false),
                )?;
                // The server's points (murk::tof::measured_points) keep the same pixels.
                o.points.as_ref()
            }
            _ => bail!("frame {}: a result of another method", r.frame_id),
        };
        // None with --no-points.
        if let Some(cloud) = points {
            w.write(
                &topic("points"),
                MessageType::PointCloud2,
                t,
                &rgb_cloud_from_api(h, cloud)?,
            )?;
        }
        w.write(&topic("camera_info"), MessageType::CameraInfo, t, &info)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_info_defaults_to_the_image_topics_sibling() {
        assert_eq!(
            sibling_info("/stereo/left/image_rect"),
            "/stereo/left/camera_info"
        );
        assert_eq!(sibling_info("image"), "camera_info");
        assert_eq!(
            sibling_info("/stereo/left/image_rect/compressed"),
            "/stereo/left/camera_info"
        );
        assert_eq!(
            sibling_info("/tof/depth/compressedDepth"),
            "/tof/camera_info"
        );
        // a topic merely named like a transport
        assert_eq!(sibling_info("/compressed"), "/camera_info");
    }
}
