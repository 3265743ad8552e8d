//! Accuracy survey of ToF depth in fog (reference Ch. 5) on simulated frames.
//!
//! For every fog preset and seed it simulates a Kinect v2-like frame (`murk::simulate::tof`),
//! runs [`murk::tof::estimate_tof_depth`] with the defaults (plus the frame's modulation
//! frequency, intrinsics and emitter position, as a caller with a calibrated camera gives them)
//! and scores the result over the ground-truth mask: the object pixels the emitter lights.
//! It prints two Markdown tables: one row per frame, then one row per preset, and a verdict
//! against the targets of [accuracy.md](../../../docs/accuracy.md): object recall ≥ 0.995 on every
//! frame, z error ≤ 30 mm (thick fog 40 mm) and ≤ raw/3 on ≥ 90 % of the frames, no frame worse
//! than raw.
//!
//! ```sh
//! cargo run --release -p murk --example tof_survey -- --layout obstacles --seeds 0-4 \
//!     --size reduced,half,full --presets medium,thick
//! cargo run --release -p murk --example tof_survey -- --layout separated --seeds 0-5
//! cargo run --release -p murk --example tof_survey -- --layout cluttered --seeds 0-5
//! cargo run --release -p murk --example tof_survey -- --layout cluttered --seeds 0-2 --size full
//! cargo run --release -p murk --example tof_survey -- --layout cluttered --seeds 1 --size full \
//!     --presets thick --fine-iterations 50
//! ```

mod common;

use std::time::Instant;

use anyhow::Context;
use clap::Parser;

use common::{mean, parse_seeds, range_from_path, Size, Table};
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig, TofSimFrame};
use murk::simulate::SceneLayout;
use murk::tof::{
    estimate_tof_depth, TofInput, TofOutput, TofParams, MASK_OBJECT, MASK_UNCERTAIN,
    SPEED_OF_LIGHT_M_PER_S,
};
use murk::Monitor;

/// Flags of the survey.
#[derive(Parser, Debug)]
#[command(about = "ToF depth in fog on simulated frames: range error, mask IoU and time")]
struct Args {
    /// Object placement: separated (2–4 objects apart), cluttered (a large near sphere
    /// occluding a panel, plus 1–2 objects) or obstacles (a near object, a panel seen nearly
    /// edge-on at its outline, a thin pole).
    #[arg(long, default_value = "separated")]
    layout: SceneLayout,
    /// Simulator seeds: `4`, `0-5` or a list such as `0-2,7`.
    #[arg(long, default_value = "0-5")]
    seeds: String,
    /// Image sizes, comma-separated: every seed and preset is run at each.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "reduced")]
    size: Vec<Size>,
    /// Fog presets, comma-separated: thin, medium, thick.
    #[arg(long, value_delimiter = ',', default_value = "thin,medium,thick")]
    presets: Vec<FogPreset>,
    /// Cap on the fine IRLS iterations (default: `TofParams`' 150; the reference's is 50).
    #[arg(long)]
    fine_iterations: Option<usize>,
    /// Multiplier of the sensor's noise (both its shot and its read terms' standard
    /// deviations; 1: the Kinect v2-like sensor of the docs).
    #[arg(long, default_value_t = 1.0)]
    noise_scale: f64,
}

/// One frame's scores, all over the ground-truth mask unless stated.
struct Scores {
    /// Mean |corrected range − true range|, metres.
    err_m: f64,
    /// Mean |raw range − true range|, metres (no fog correction).
    raw_m: f64,
    /// Mean error when the true scattering phasor is subtracted from the noisy observation:
    /// what is left is the sensor noise, the floor of any estimate of the scatter.
    floor_m: f64,
    /// Intersection over union of the estimated object mask and the ground-truth mask.
    iou: f64,
    /// Share of the ground-truth object pixels in the estimated mask.
    recall: f64,
    /// Share of the ground-truth object pixels the mask calls object or uncertain: the object
    /// pixels that did not vanish into the background.
    recall_uncertain: f64,
    /// Share of the pixels that see no object (the wall) that the mask calls uncertain.
    false_uncertain: f64,
    /// Mean |z-depth − true z-depth| over the ground-truth mask, metres: every true object
    /// pixel counts, whatever the mask says, so a lost part costs its full error.
    z_err_m: f64,
    /// The same for the raw (uncorrected) z-depth.
    z_raw_m: f64,
    /// Share of the ground-truth object pixels whose z-depth is off by more than 100 mm.
    off_100mm: f64,
    /// Shares of pixels whose error is within 1 and 3 of the reported `range_std_m`.
    within: [f64; 2],
    /// Wall-clock seconds of `estimate_tof_depth` (simulation excluded).
    seconds: f64,
    /// Whether the result carried warnings (an IRLS stopped at its iteration cap).
    warned: bool,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let seeds = parse_seeds(&args.seeds).map_err(anyhow::Error::msg)?;
    if !(args.noise_scale.is_finite() && args.noise_scale >= 0.0) {
        anyhow::bail!(
            "--noise-scale must be finite and at least 0, got {}",
            args.noise_scale
        );
    }
    let cap = args
        .fine_iterations
        .map(|n| format!(", fine-iteration cap {n}"))
        .unwrap_or_default();
    let sizes = args
        .size
        .iter()
        .map(|s| {
            let (w, h) = s.dims();
            format!("{w}×{h}")
        })
        .collect::<Vec<_>>()
        .join(", ");
    println!(
        "## ToF survey: {} layout, {sizes}, seeds {}{cap}\n",
        args.layout, args.seeds
    );
    let mut frames = Table::new(&[
        "size",
        "preset",
        "seed",
        "error (mm)",
        "raw (mm)",
        "raw / error",
        "floor (mm)",
        "z error (mm)",
        "z raw (mm)",
        "recall",
        "recall with uncertain",
        "background uncertain",
        "off > 100 mm",
        "IoU",
        "in 1σ",
        "in 3σ",
        "time (s)",
        "warning",
    ]);
    let mut per_preset = Vec::new();
    for &preset in &args.presets {
        let mut scores = Vec::new();
        for &size in &args.size {
            let (w, h) = size.dims();
            for &seed in &seeds {
                eprintln!("{preset} {w}×{h} seed {seed} ...");
                let frame = simulate(preset, seed, w, h, args.layout, args.noise_scale)
                    .with_context(|| format!("simulating {preset} seed {seed}"))?;
                let input = TofInput {
                    amplitude: frame.amplitude.clone(),
                    phase: frame.phase.clone(),
                    intrinsics: Some(frame.intrinsics),
                };
                let defaults = TofParams::default();
                let params = TofParams {
                    modulation_frequency_hz: frame.config.modulation_frequency_hz,
                    light_position_m: Some(frame.config.light_position_m()),
                    fine_iterations: args.fine_iterations.unwrap_or(defaults.fine_iterations),
                    ..defaults
                };
                let t = Instant::now();
                let out = estimate_tof_depth(&input, &params, &Monitor::noop())
                    .with_context(|| format!("estimating {preset} seed {seed}"))?;
                let s = score(&frame, &out, t.elapsed().as_secs_f64());
                frames.row(&[
                    format!("{w}×{h}"),
                    preset.to_string(),
                    seed.to_string(),
                    format!("{:.1}", s.err_m * 1e3),
                    format!("{:.1}", s.raw_m * 1e3),
                    format!("{:.0}", s.raw_m / s.err_m.max(1e-12)),
                    format!("{:.1}", s.floor_m * 1e3),
                    format!("{:.1}", s.z_err_m * 1e3),
                    format!("{:.1}", s.z_raw_m * 1e3),
                    format!("{:.4}", s.recall),
                    format!("{:.4}", s.recall_uncertain),
                    format!("{:.2} %", s.false_uncertain * 100.0),
                    format!("{:.2} %", s.off_100mm * 100.0),
                    format!("{:.3}", s.iou),
                    format!("{:.3}", s.within[0]),
                    format!("{:.3}", s.within[1]),
                    format!("{:.2}", s.seconds),
                    if s.warned { "yes" } else { "" }.to_string(),
                ]);
                scores.push(s);
            }
        }
        per_preset.push((preset, scores));
    }
    frames.print();

    println!("\n### Per preset\n");
    let mut summary = Table::new(&[
        "preset",
        "β (/mm)",
        "frames",
        "mean error (mm)",
        "raw (mm)",
        "mean z error (mm)",
        "lowest recall",
        "IoU",
        "mean time (s)",
    ]);
    for (preset, scores) in &per_preset {
        let pick = |f: fn(&Scores) -> f64| scores.iter().map(f).collect::<Vec<_>>();
        let span = |v: &[f64], scale: f64, digits: usize| {
            let lo = v.iter().copied().fold(f64::INFINITY, f64::min) * scale;
            let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max) * scale;
            if format!("{lo:.digits$}") == format!("{hi:.digits$}") {
                format!("{lo:.digits$}")
            } else {
                format!("{lo:.digits$}–{hi:.digits$}")
            }
        };
        let lowest = pick(|s| s.recall).into_iter().fold(f64::INFINITY, f64::min);
        summary.row(&[
            preset.to_string(),
            format!("{:.0e}", preset.beta_per_mm()),
            scores.len().to_string(),
            format!("{:.1}", mean(&pick(|s| s.err_m)) * 1e3),
            span(&pick(|s| s.raw_m), 1e3, 0),
            format!("{:.1}", mean(&pick(|s| s.z_err_m)) * 1e3),
            format!("{lowest:.4}"),
            span(&pick(|s| s.iou), 1.0, 3),
            format!("{:.2}", mean(&pick(|s| s.seconds))),
        ]);
    }
    summary.print();

    // The targets: every frame keeps its objects, ≥ 90 % of the frames are within the error
    // bound and a third of raw, none is worse than raw.
    let all: Vec<(FogPreset, &Scores)> = per_preset
        .iter()
        .flat_map(|(p, v)| v.iter().map(move |s| (*p, s)))
        .collect();
    let n = all.len();
    let recalled = all.iter().filter(|(_, s)| s.recall >= 0.995).count();
    let kept = all
        .iter()
        .filter(|(_, s)| s.recall_uncertain >= 0.995)
        .count();
    let within = all
        .iter()
        .filter(|(p, s)| {
            let bound = if *p == FogPreset::Thick { 0.040 } else { 0.030 };
            s.z_err_m <= bound && s.z_err_m <= s.z_raw_m / 3.0
        })
        .count();
    let worse = all.iter().filter(|(_, s)| s.z_err_m > s.z_raw_m).count();
    println!("\n### Targets\n");
    println!("- object recall ≥ 0.995: {recalled} of {n} frames");
    println!("- object or uncertain ≥ 0.995 of the object pixels: {kept} of {n} frames");
    println!(
        "- z error ≤ 30 mm (thick 40 mm) and ≤ raw/3: {within} of {n} frames ({:.0} %)",
        100.0 * within as f64 / n.max(1) as f64
    );
    println!("- worse than raw: {worse} of {n} frames");
    Ok(())
}

fn simulate(
    preset: FogPreset,
    seed: u64,
    width: usize,
    height: usize,
    layout: SceneLayout,
    noise_scale: f64,
) -> murk::Result<TofSimFrame> {
    let base = TofSimConfig::with_size(width, height);
    let cfg = TofSimConfig {
        preset,
        seed,
        layout,
        noise_shot: base.noise_shot * noise_scale,
        noise_read: base.noise_read * noise_scale,
        ..base
    };
    simulate_tof(&cfg, &Monitor::noop())
}

fn score(frame: &TofSimFrame, out: &TofOutput, seconds: f64) -> Scores {
    let (w, _) = frame.amplitude.dims();
    let gt = frame.gt_mask.data();
    let truth = frame.gt_range_m.data();
    let light = frame.config.light_position_m();
    // Optical path per radian of phase: the phase is 2πf·path/c.
    let path_per_rad = SPEED_OF_LIGHT_M_PER_S
        / (2.0 * std::f64::consts::PI * frame.config.modulation_frequency_hz);
    let (mut err, mut raw, mut floor, mut n) = (0.0, 0.0, 0.0, 0usize);
    let (mut z_err, mut z_raw, mut recalled, mut off) = (0.0, 0.0, 0usize, 0usize);
    let truth_z = frame.gt_z_depth_m.data();
    let z = out.z_depth_m.as_ref().expect("the survey gives intrinsics");
    let z_raw_img = out
        .raw_z_depth_m
        .as_ref()
        .expect("the survey gives intrinsics");
    let mut within = [0usize; 2];
    let (mut inter, mut union) = (0usize, 0usize);
    let (mut kept, mut uncertain, mut background) = (0usize, 0usize, 0usize);
    for (i, &g) in gt.iter().enumerate() {
        let g = g > 0.5;
        let mv = out.mask.data()[i];
        let m = mv == MASK_OBJECT;
        let u = mv == MASK_UNCERTAIN;
        inter += (g && m) as usize;
        union += (g || m) as usize;
        if !g {
            // Object pixels too dim to measure even in clear air are not counted as background.
            if frame.gt_object_mask.data()[i] < 0.5 {
                background += 1;
                uncertain += u as usize;
            }
            continue;
        }
        recalled += m as usize;
        kept += (m || u) as usize;
        let ez = (f64::from(z.data()[i]) - f64::from(truth_z[i])).abs();
        z_err += ez;
        off += (ez > 0.1) as usize;
        z_raw += (f64::from(z_raw_img.data()[i]) - f64::from(truth_z[i])).abs();
        let r = f64::from(truth[i]);
        let e = (f64::from(out.range_m.data()[i]) - r).abs();
        err += e;
        raw += (f64::from(out.raw_range_m.data()[i]) - r).abs();
        let sd = f64::from(out.range_std_m.data()[i]);
        within[0] += (e <= sd) as usize;
        within[1] += (e <= 3.0 * sd) as usize;
        // The noisy observation less the true, noise-free scatter phasor.
        let polar = |a: f32, p: f32| {
            let (s, c) = f64::from(p).sin_cos();
            (f64::from(a) * c, f64::from(a) * s)
        };
        let (o_re, o_im) = polar(frame.amplitude.data()[i], frame.phase.data()[i]);
        let (s_re, s_im) = polar(
            frame.scatter_amplitude.data()[i],
            frame.scatter_phase.data()[i],
        );
        let phase = (o_im - s_im)
            .atan2(o_re - s_re)
            .rem_euclid(std::f64::consts::TAU);
        let d = frame.intrinsics.ray((i % w) as f64, (i / w) as f64);
        floor += (range_from_path(phase * path_per_rad, d.into(), light) - r).abs();
        n += 1;
    }
    let nn = n.max(1) as f64;
    Scores {
        err_m: err / nn,
        raw_m: raw / nn,
        floor_m: floor / nn,
        iou: if union == 0 {
            1.0
        } else {
            inter as f64 / union as f64
        },
        recall: recalled as f64 / nn,
        recall_uncertain: kept as f64 / nn,
        false_uncertain: uncertain as f64 / background.max(1) as f64,
        z_err_m: z_err / nn,
        z_raw_m: z_raw / nn,
        off_100mm: off as f64 / nn,
        within: within.map(|k| k as f64 / nn),
        seconds,
        warned: !out.warnings.is_empty(),
    }
}
