//! How fine a grid the scattering component needs: the range error left when the scatter is
//! known, or estimated, only on a grid K times coarser than the frame and interpolated back.
//!
//! The x-step of the IRLS (Eq. 5.12) solves for the scatter at every pixel, and its cost grows
//! with the pixels. Fog's backscatter varies slowly across the image, so a coarser grid could
//! carry it. For every simulated frame (`murk::simulate::tof`) this prints, over the
//! ground-truth mask, the mean |range − true range| (mm) of:
//! - *floor*: the true scatter phasor subtracted from the noisy observation (the sensor noise
//!   alone);
//! - *true at 1/K*: the true scatter averaged over K×K blocks and interpolated back
//!   (bilinear), subtracted the same way: what a grid K times coarser costs at best;
//! - *murk*: `estimate_tof_depth` on the frame, its scatter subtracted the same way (no outline
//!   fill, so that every column is scored alike), and its time;
//! - *murk at 1/K*: `estimate_tof_depth` on the frame's K×K block means (the observed phasors
//!   averaged, the intrinsics scaled), its scatter interpolated back and subtracted from the
//!   full frame, and its time.
//!
//! ```sh
//! cargo run --release -p murk --example tof_scatter_resolution -- --layout obstacles \
//!     --seeds 0-4 --size full --presets medium,thick
//! ```

mod common;

use std::time::Instant;

use anyhow::Context;
use clap::Parser;

use common::{mean, parse_seeds, range_error, Phasor, Size, Table};
use murk::camera::Intrinsics;
use murk::image::ImageF32;
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig, TofSimFrame};
use murk::simulate::SceneLayout;
use murk::tof::{estimate_tof_depth, TofInput, TofParams};
use murk::Monitor;

/// Flags of the experiment.
#[derive(Parser, Debug)]
#[command(about = "ToF: the range error of a scatter known or estimated on a coarser grid")]
struct Args {
    /// Object placement: separated, cluttered or obstacles.
    #[arg(long, default_value = "obstacles")]
    layout: SceneLayout,
    /// Simulator seeds: `4`, `0-5` or a list such as `0-2,7`.
    #[arg(long, default_value = "0-2")]
    seeds: String,
    /// Image sizes, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "full")]
    size: Vec<Size>,
    /// Fog presets, comma-separated: thin, medium, thick.
    #[arg(long, value_delimiter = ',', default_value = "medium,thick")]
    presets: Vec<FogPreset>,
    /// Coarsening factors K, comma-separated; each must divide the image's sides.
    #[arg(long, value_delimiter = ',', default_value = "2,4")]
    factors: Vec<usize>,
}

/// The estimate's scatter phasor and its seconds.
fn estimate(
    amplitude: ImageF32,
    phase: ImageF32,
    intrinsics: Intrinsics,
    frame: &TofSimFrame,
) -> anyhow::Result<(Phasor, f64)> {
    let input = TofInput {
        amplitude,
        phase,
        intrinsics: Some(intrinsics),
    };
    let params = TofParams {
        modulation_frequency_hz: frame.config.modulation_frequency_hz,
        light_position_m: Some(frame.config.light_position_m()),
        ..TofParams::default()
    };
    let t = Instant::now();
    let out = estimate_tof_depth(&input, &params, &Monitor::noop())?;
    let seconds = t.elapsed().as_secs_f64();
    Ok((
        Phasor::from_polar(&out.scatter_amplitude, &out.scatter_phase),
        seconds,
    ))
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let seeds = parse_seeds(&args.seeds).map_err(|e| anyhow::anyhow!("--seeds: {e}"))?;
    if args.factors.iter().any(|&k| k < 2) {
        anyhow::bail!("--factors: each factor must be at least 2");
    }
    let mut header = vec![
        "size".to_string(),
        "preset".into(),
        "seed".into(),
        "floor (mm)".into(),
        "murk (mm)".into(),
        "murk (s)".into(),
    ];
    for k in &args.factors {
        header.push(format!("true at 1/{k} (mm)"));
        header.push(format!("murk at 1/{k} (mm)"));
        header.push(format!("murk at 1/{k} (s)"));
    }
    println!(
        "## The scatter on a coarser grid: {} layout, seeds {}\n",
        args.layout, args.seeds
    );
    let mut table = Table::new(&header);
    // Per factor: the coarse estimate's error minus the full estimate's, and the time ratio.
    let mut excess = vec![Vec::new(); args.factors.len()];
    let mut speedup = vec![Vec::new(); args.factors.len()];
    for &preset in &args.presets {
        for &size in &args.size {
            let (w, h) = size.dims();
            for &seed in &seeds {
                eprintln!("{preset} {w}×{h} seed {seed} ...");
                let cfg = TofSimConfig {
                    preset,
                    seed,
                    layout: args.layout,
                    ..TofSimConfig::with_size(w, h)
                };
                let frame = simulate_tof(&cfg, &Monitor::noop())
                    .with_context(|| format!("simulating {preset} seed {seed}"))?;
                let truth = Phasor::from_polar(&frame.scatter_amplitude, &frame.scatter_phase);
                let observed = Phasor::from_polar(&frame.amplitude, &frame.phase);
                let (full, full_s) = estimate(
                    frame.amplitude.clone(),
                    frame.phase.clone(),
                    frame.intrinsics,
                    &frame,
                )
                .with_context(|| format!("estimating {preset} seed {seed}"))?;
                let full_err = range_error(&frame, &observed, &full);
                let mut row = vec![
                    format!("{w}×{h}"),
                    preset.to_string(),
                    seed.to_string(),
                    format!("{:.1}", range_error(&frame, &observed, &truth) * 1e3),
                    format!("{:.1}", full_err * 1e3),
                    format!("{full_s:.2}"),
                ];
                for (j, &k) in args.factors.iter().enumerate() {
                    if w % k != 0 || h % k != 0 {
                        row.extend(["–".to_string(), "–".into(), "–".into()]);
                        continue;
                    }
                    let oracle = truth.block_means(k)?.upsampled(k)?;
                    let (amplitude, phase) = observed.block_means(k)?.to_polar();
                    let intrinsics = frame.intrinsics.box_downsampled(k);
                    let (coarse, coarse_s) = estimate(amplitude, phase, intrinsics, &frame)
                        .with_context(|| format!("estimating {preset} seed {seed} at 1/{k}"))?;
                    let coarse_err = range_error(&frame, &observed, &coarse.upsampled(k)?);
                    excess[j].push((coarse_err - full_err) * 1e3);
                    speedup[j].push(full_s / coarse_s);
                    row.extend([
                        format!("{:.1}", range_error(&frame, &observed, &oracle) * 1e3),
                        format!("{:.1}", coarse_err * 1e3),
                        format!("{coarse_s:.2}"),
                    ]);
                }
                table.row(&row);
            }
        }
    }
    table.print();
    println!();
    for (j, k) in args.factors.iter().enumerate() {
        if excess[j].is_empty() {
            continue;
        }
        let worst = excess[j].iter().copied().fold(f64::NEG_INFINITY, f64::max);
        println!(
            "- 1/{k}: the coarse estimate's error minus the full one's, mean {:+.1} mm \
             (worst {worst:+.1} mm); the full estimate's time over the coarse one's, mean {:.1}×",
            mean(&excess[j]),
            mean(&speedup[j])
        );
    }
    Ok(())
}
