//! Whether `murk bag` keeps up with a stereo rig: writes a bag of a rectified rig moving through
//! a hazy room (`murk::simulate::StereoSequence`, forward at 0.5 units a second) recorded at
//! `--rate-hz`, `rgb8` images and both CameraInfo on every frame; runs `murk bag` over it with
//! the haze given, and prints the frames per second against the recording's rate.
//!
//! ```sh
//! cargo build --release -p murk-server
//! cargo run --release -p murk-server --example bag_throughput -- --frames 30
//! ```

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Parser;

use murk::monitor::Monitor;
use murk::simulate::mvs::MvsSimConfig;
use murk::simulate::{StereoMotion, StereoSequence};
use murk::ImageF32;
use murk_server::bag::msgs::{CameraInfo, Header, Image, MessageType, Time};
use murk_server::bag::writer::{BagWriter, ChunkCompression};

/// Throughput of `murk bag` on a simulated stereo recording.
#[derive(Parser, Debug)]
struct Args {
    /// Pair size, WxH.
    #[arg(long, default_value = "640x480")]
    size: String,
    /// Frames in the bag.
    #[arg(long, default_value_t = 30)]
    frames: usize,
    /// The rig's frame rate, Hz.
    #[arg(long, default_value_t = 10.0)]
    rate_hz: f64,
    /// Scene seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// The `murk` binary.
    #[arg(long, default_value = "target/release/murk")]
    murk: PathBuf,
    /// `--compression` of `murk bag`'s output: lz4, zstd or none.
    #[arg(long, default_value = "zstd")]
    compression: String,
    /// Pass `--no-points` to `murk bag`: no point clouds computed or written.
    #[arg(long)]
    no_points: bool,
    /// Working folder (the bags are written here).
    #[arg(long, default_value = "target/bag-throughput")]
    work: PathBuf,
}

/// 8-bit RGB of `img` (interleaved, as murk stores it).
fn rgb8(img: &ImageF32) -> Vec<u8> {
    img.data()
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let (w, h) = a
        .size
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<usize>().ok()?, h.parse::<usize>().ok()?)))
        .context("--size is WxH")?;
    let seq = StereoSequence::new(
        &MvsSimConfig {
            seed: a.seed,
            ..MvsSimConfig::with_size(w, h)
        },
        &StereoMotion {
            frame_rate_hz: a.rate_hz,
            ..StereoMotion::default()
        },
    )?;
    let k = seq.intrinsics();
    let baseline = seq.baseline();
    std::fs::create_dir_all(&a.work)?;
    let bag = a.work.join(format!("stereo_{w}x{h}.mcap"));
    let mut writer = BagWriter::create(&bag, ChunkCompression::Lz4)?;
    let t0: u64 = 1_700_000_000_000_000_000;
    // The depths the whole recording spans, for the search range.
    let (mut near, mut far) = (f32::INFINITY, 0.0f32);
    for f in 0..a.frames {
        let pair = seq.frame(f, &Monitor::noop())?;
        let mut z: Vec<f32> = pair
            .left_depth
            .data()
            .iter()
            .copied()
            .filter(|z| *z > 0.0)
            .collect();
        z.sort_by(f32::total_cmp);
        near = near.min(z[z.len() / 100]);
        far = far.max(z[z.len() * 99 / 100]);
        let t = t0 + (f as f64 * 1e9 / a.rate_hz) as u64;
        let header = |frame_id: &str| Header {
            stamp: Time {
                sec: (t / 1_000_000_000) as i32,
                nanosec: (t % 1_000_000_000) as u32,
            },
            frame_id: frame_id.into(),
        };
        for (side, view, tx) in [
            ("left", &pair.left, 0.0),
            ("right", &pair.right, -k.fx * baseline),
        ] {
            let info = CameraInfo {
                header: header(side),
                height: h as u32,
                width: w as u32,
                distortion_model: "plumb_bob".into(),
                d: vec![0.0; 5],
                k: [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
                r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                p: [
                    k.fx, 0.0, k.cx, tx, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
                ],
                ..CameraInfo::default()
            };
            writer.write(
                &format!("/stereo/{side}/camera_info"),
                MessageType::CameraInfo,
                t,
                &info,
            )?;
            let image = Image {
                header: header(side),
                height: h as u32,
                width: w as u32,
                encoding: "rgb8".into(),
                is_bigendian: 0,
                step: (w * 3) as u32,
                data: rgb8(view),
            };
            writer.write(
                &format!("/stereo/{side}/image_rect"),
                MessageType::Image,
                t,
                &image,
            )?;
        }
    }
    writer.finish()?;
    let recorded_s = a.frames as f64 / a.rate_hz;
    println!(
        "{w}×{h} rectified rig moving through haze (A {:.3}, β {:.4} per scene unit), {} frames \
         at {} Hz ({recorded_s:.1} s recorded), bag {:.1} MB; searched over depths {near:.2}..{far:.2}",
        seq.airlight,
        seq.beta,
        a.frames,
        a.rate_hz,
        std::fs::metadata(&bag)?.len() as f64 / 1e6
    );
    let out = a.work.join(format!("stereo_{w}x{h}_out.mcap"));
    let started = Instant::now();
    let run = Command::new(&a.murk)
        .arg("bag")
        .arg(&bag)
        .arg("--out")
        .arg(&out)
        .args(["--left", "/stereo/left/image_rect"])
        .args(["--right", "/stereo/right/image_rect"])
        .args(["--airlight", &seq.airlight.to_string()])
        .args(["--beta", &seq.beta.to_string()])
        .args(["--depth-range", &format!("{near},{far}")])
        .args(["--compression", &a.compression])
        .args(a.no_points.then_some("--no-points"))
        .output()
        .with_context(|| format!("running {}", a.murk.display()))?;
    let seconds = started.elapsed().as_secs_f64();
    if !run.status.success() {
        bail!("murk bag failed: {}", String::from_utf8_lossy(&run.stderr));
    }
    print!("{}", String::from_utf8_lossy(&run.stdout));
    let fps = a.frames as f64 / seconds;
    println!(
        "wall {seconds:.2} s for the whole command (server start included): {fps:.2} frames/s, \
         {:.2}× real time ({})",
        fps / a.rate_hz,
        if fps >= a.rate_hz {
            "keeps up"
        } else {
            "falls behind"
        }
    );
    Ok(())
}
