//! ToF depth in fog on board, with no server: read one CW-ToF frame from EXR files, run the
//! method of the reference's Ch. 5 (Algorithm 2 with the scattering priors of Eq. 5.10–5.12),
//! write the corrected range, its z-depth and the object mask.
//!
//! ```sh
//! cargo run --release -- simulate tof --out /tmp/frame --width 128 --height 106 --seed 1
//! cargo run --release -p murk --example tof_embedded -- --frame /tmp/frame --out /tmp/tof-out
//! # or a capture of your own (phase in radians):
//! cargo run --release -p murk --example tof_embedded -- --amplitude a.exr --phase p.exr \
//!     --frequency-hz 16e6 --intrinsics 365,365,255.5,211.5 --out /tmp/tof-out
//! ```
//!
//! Only the `murk` library crate is linked: no gRPC, no async runtime.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Parser;
use murk::camera::Intrinsics;
use murk::io::{read_image, write_colormap_png, write_exr, DecodeLimits};
use murk::simulate::read_tof_capture;
use murk::tof::{estimate_tof_depth, TofInput, TofParams};
use murk::Monitor;

/// Corrects one foggy CW-ToF frame and writes range_m.exr, z_depth_m.exr, mask.exr and
/// range.png.
#[derive(Parser, Debug)]
struct Args {
    /// A frame folder: amplitude.exr, phase.exr (radians) and optionally meta.json (the layout
    /// `murk simulate tof` writes).
    #[arg(long, conflicts_with_all = ["amplitude", "phase"])]
    frame: Option<PathBuf>,
    /// Amplitude image (EXR, 16-bit PNG or float TIFF), one channel.
    #[arg(long, requires = "phase")]
    amplitude: Option<PathBuf>,
    /// Phase image in radians, same size as the amplitude.
    #[arg(long, requires = "amplitude")]
    phase: Option<PathBuf>,
    /// Modulation frequency, Hz (overrides meta.json).
    #[arg(long)]
    frequency_hz: Option<f64>,
    /// Intrinsics "fx,fy,cx,cy", pixels (overrides meta.json); enables the z-depth output.
    #[arg(long, value_parser = intrinsics)]
    intrinsics: Option<Intrinsics>,
    /// Output folder (created).
    #[arg(long)]
    out: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let (amplitude, phase, mut intrinsics, mut frequency_hz, light_position_m) =
        match (&args.frame, &args.amplitude, &args.phase) {
            (Some(dir), _, _) => {
                let c =
                    read_tof_capture(dir).with_context(|| format!("reading {}", dir.display()))?;
                (
                    c.amplitude,
                    c.phase,
                    c.intrinsics,
                    c.modulation_frequency_hz,
                    c.light_position_m,
                )
            }
            (None, Some(a), Some(p)) => {
                let limits = DecodeLimits::default();
                (
                    read_image(a, &limits)?.into_mono()?,
                    read_image(p, &limits)?.into_mono()?,
                    None,
                    None,
                    None,
                )
            }
            _ => bail!("give --frame DIR, or --amplitude and --phase"),
        };
    if let Some(f) = args.frequency_hz {
        frequency_hz = Some(f);
    }
    if args.intrinsics.is_some() {
        intrinsics = args.intrinsics;
    }
    let Some(modulation_frequency_hz) = frequency_hz else {
        bail!("the modulation frequency is unknown: give --frequency-hz or meta.json");
    };

    let input = TofInput {
        amplitude,
        phase,
        intrinsics,
    };
    let params = TofParams {
        modulation_frequency_hz,
        // The emitter's offset from the lens matters only where range becomes z-depth.
        light_position_m: light_position_m.filter(|_| intrinsics.is_some()),
        ..TofParams::default()
    };
    let (w, h) = input.amplitude.dims();
    let started = Instant::now();
    let out = estimate_tof_depth(&input, &params, &Monitor::noop())?;
    let seconds = started.elapsed().as_secs_f64();

    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    write_exr(&args.out.join("range_m.exr"), &out.range_m)?;
    write_exr(&args.out.join("mask.exr"), &out.mask)?;
    if let Some(z) = &out.z_depth_m {
        write_exr(&args.out.join("z_depth_m.exr"), z)?;
    }
    let (lo, hi) = object_range(&out.range_m, &out.mask);
    write_colormap_png(
        &args.out.join("range.png"),
        &out.range_m,
        lo,
        hi,
        Some(&out.mask),
    )?;

    let objects = out.mask.data().iter().filter(|&&m| m > 0.5).count();
    println!(
        "{w}×{h} frame in {seconds:.2} s: {objects} object pixels ({:.1} %), object range {lo:.3}–{hi:.3} m; wrote {}",
        100.0 * objects as f64 / (w * h) as f64,
        args.out.display()
    );
    for warning in &out.warnings {
        println!("warning: {warning}");
    }
    Ok(())
}

/// The range span of the object pixels (for the preview's colour scale); the whole image's when
/// the mask is empty.
fn object_range(range: &murk::ImageF32, mask: &murk::ImageF32) -> (f32, f32) {
    let mut values: Vec<f32> = range
        .data()
        .iter()
        .zip(mask.data())
        .filter(|&(r, &m)| m > 0.5 && r.is_finite())
        .map(|(&r, _)| r)
        .collect();
    if values.is_empty() {
        values = range
            .data()
            .iter()
            .copied()
            .filter(|r| r.is_finite())
            .collect();
    }
    let lo = values.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    if lo < hi {
        (lo, hi)
    } else {
        (lo, lo + 1.0)
    }
}

/// Parses "fx,fy,cx,cy" (pixels).
fn intrinsics(text: &str) -> Result<Intrinsics, String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>().map_err(|e| format!("`{v}`: {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [fx, fy, cx, cy] => Ok(Intrinsics::new(fx, fy, cx, cy)),
        _ => Err(format!("expected fx,fy,cx,cy, got {} numbers", v.len())),
    }
}
