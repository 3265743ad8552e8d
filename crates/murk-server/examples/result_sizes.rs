//! What a result costs on the wire: the encoded size of ToF and rectified-stereo results for
//! each choice of images (every image, or a session's default set) and encoding (F32, F16,
//! PNG), the time to encode them, and what transport compression (gzip, zstd, as tonic applies
//! them when the client accepts them) takes off. Simulated frames, several seeds.
//!
//! ```sh
//! cargo run --release -p murk-server --example result_sizes -- --seeds 0-4
//! ```

use std::io::Write;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use prost::Message;

use murk::atmosphere::AtmosphereParams;
use murk::monitor::Monitor;
use murk::mvs::RectifiedRig;
use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk::tof::estimate_tof_depth;
use murk_server::service::convert::{
    simulated_tof_request, stereo_from_proto, stereo_outputs_from_proto, stereo_request_to_proto,
    stereo_to_proto, tof_from_proto, tof_outputs_from_proto, tof_to_proto, Delivery, ImageLimits,
};
use murk_server::service::proto::v1 as pb;

/// Result sizes per image set and encoding.
#[derive(Parser, Debug)]
struct Args {
    /// Scene seeds, e.g. "0-4" or "1,3".
    #[arg(long, default_value = "0-4")]
    seeds: String,
    /// ToF frame size, WxH (the simulator keeps the field of view).
    #[arg(long, default_value = "512x424")]
    tof_size: String,
    /// Stereo pair size, WxH.
    #[arg(long, default_value = "640x480")]
    stereo_size: String,
}

fn parse_size(s: &str) -> anyhow::Result<(usize, usize)> {
    let (w, h) = s.split_once('x').context("a size is WxH")?;
    Ok((w.parse()?, h.parse()?))
}

fn parse_seeds(s: &str) -> anyhow::Result<Vec<u64>> {
    let mut seeds = Vec::new();
    for part in s.split(',') {
        match part.split_once('-') {
            Some((a, b)) => seeds.extend(a.parse::<u64>()?..=b.parse::<u64>()?),
            None => seeds.push(part.parse()?),
        }
    }
    Ok(seeds)
}

/// One variant over the seeds: the message's bytes, gzip and zstd of it, and the encode time.
#[derive(Default)]
struct Tally {
    bytes: Vec<f64>,
    gzip: Vec<f64>,
    zstd: Vec<f64>,
    ms: Vec<f64>,
}

impl Tally {
    fn add(&mut self, message: &[u8], seconds: f64) -> anyhow::Result<()> {
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        gz.write_all(message)?;
        self.gzip.push(gz.finish()?.len() as f64);
        // Level 3 is zstd's default.
        self.zstd
            .push(zstd::bulk::compress(message, 3)?.len() as f64);
        self.bytes.push(message.len() as f64);
        self.ms.push(1e3 * seconds);
        Ok(())
    }

    fn row(&self, name: &str) {
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let max = self.bytes.iter().copied().fold(0.0, f64::max);
        println!(
            "| {name} | {:.3} | {:.3} | {:.3} | {:.3} | {:.1} |",
            mean(&self.bytes) / 1e6,
            max / 1e6,
            mean(&self.gzip) / 1e6,
            mean(&self.zstd) / 1e6,
            mean(&self.ms)
        );
    }
}

/// The variants, each image set (one-shot default: every image; session default: the compact
/// set) in each encoding, as (delivery, encoding).
fn variants() -> Vec<(Delivery, pb::ImageEncoding)> {
    let encodings = [
        pb::ImageEncoding::F32,
        pb::ImageEncoding::F16,
        pb::ImageEncoding::Png,
    ];
    [Delivery::OneShot, Delivery::Session]
        .into_iter()
        .flat_map(|d| encodings.map(|e| (d, e)))
        .collect()
}

fn variant_name(delivery: Delivery, encoding: pb::ImageEncoding) -> String {
    let set = match delivery {
        Delivery::OneShot => "every image",
        Delivery::Session => "default set",
    };
    let default = match (delivery, encoding) {
        (Delivery::OneShot, pb::ImageEncoding::F32) => " (one-shot default)",
        (Delivery::Session, pb::ImageEncoding::Png) => " (session default)",
        _ => "",
    };
    format!(
        "{set}, {}{default}",
        encoding.as_str_name().trim_start_matches("IMAGE_ENCODING_")
    )
}

fn options(encoding: pb::ImageEncoding) -> pb::OutputOptions {
    pb::OutputOptions {
        fields: Vec::new(),
        encoding: encoding as i32,
    }
}

fn table(what: &str, tallies: &[Tally]) {
    println!("\n{what}\n");
    println!("| result | MB (mean) | MB (max) | gzip MB | zstd MB | encode ms |");
    println!("| --- | --- | --- | --- | --- | --- |");
    for ((delivery, encoding), t) in variants().into_iter().zip(tallies) {
        t.row(&variant_name(delivery, encoding));
    }
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let seeds = parse_seeds(&a.seeds)?;
    let monitor = Monitor::noop();
    let limits = ImageLimits::default();

    let (w, h) = parse_size(&a.tof_size)?;
    let mut tallies: Vec<Tally> = variants().iter().map(|_| Tally::default()).collect();
    for &seed in &seeds {
        let cfg = TofSimConfig {
            seed,
            ..TofSimConfig::with_size(w, h)
        };
        let frame = simulate_tof(&cfg, &monitor)?;
        let mut req = simulated_tof_request(&frame, &cfg);
        let (input, params, _, _) = tof_from_proto(&req, &limits)?;
        let out = estimate_tof_depth(&input, &params, &monitor)?;
        for ((delivery, encoding), tally) in variants().into_iter().zip(&mut tallies) {
            req.outputs = Some(options(encoding));
            let outputs = tof_outputs_from_proto(&req, delivery)?;
            let started = Instant::now();
            let message = tof_to_proto(&out, &params, &outputs, None)?.encode_to_vec();
            tally.add(&message, started.elapsed().as_secs_f64())?;
        }
    }
    table(
        &format!(
            "ToF {w}x{h}, medium fog, seeds {} (default set: z_depth_m, mask, range_std_m)",
            a.seeds
        ),
        &tallies,
    );

    let (w, h) = parse_size(&a.stereo_size)?;
    let mut tallies: Vec<Tally> = variants().iter().map(|_| Tally::default()).collect();
    for &seed in &seeds {
        let scene = simulate_mvs(
            &MvsSimConfig {
                seed,
                rectified_pair: true,
                num_views: 2,
                ..MvsSimConfig::with_size(w, h)
            },
            &monitor,
        )?;
        let rig = RectifiedRig::new(
            scene.views[0].intrinsics,
            -scene.views[1].pose.translation()[0],
        );
        let req = stereo_request_to_proto(
            &scene.views[0].hazy,
            &scene.views[1].hazy,
            &rig,
            None,
            Some(AtmosphereParams {
                airlight: scene.airlight,
                beta: scene.beta,
            }),
        );
        let mut input = stereo_from_proto(&req, &limits)?;
        let (out, points) = input.estimate(&monitor)?;
        for ((delivery, encoding), tally) in variants().into_iter().zip(&mut tallies) {
            input.outputs = stereo_outputs_from_proto(Some(&options(encoding)), delivery)?;
            let started = Instant::now();
            let message = stereo_to_proto(&input, &out, &points, 0.0)?.encode_to_vec();
            tally.add(&message, started.elapsed().as_secs_f64())?;
        }
    }
    table(
        &format!(
            "Rectified stereo {w}x{h}, simulated haze, seeds {} (default set: z_depth, confidence)",
            a.seeds
        ),
        &tallies,
    );
    Ok(())
}
