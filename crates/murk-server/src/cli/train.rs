//! `murk train ...`: trains the learned estimators. `murk train airlight` fits the airlight CNN
//! of reference Table 3.1 (§3.3.1) on simulated hazy rooms and prints its held-out error next to
//! the dark-channel rule's.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use murk::params::airlight::train::{
    eval_seeds, evaluate, simulate_samples, train, training_seeds, EvalRow, TrainConfig, TrainEvent,
};
use murk::params::airlight::AirlightCnn;
use murk::Monitor;

/// What to train.
#[derive(Subcommand, Debug)]
pub enum TrainCommand {
    /// The airlight CNN (reference Table 3.1): writes a burnpack weights file.
    Airlight(TrainAirlightArgs),
}

/// Options of `murk train airlight`; the defaults are the run that made the committed weights.
#[derive(Args, Debug)]
pub struct TrainAirlightArgs {
    /// Output weights file (burnpack, full precision), e.g. models/airlight_cnn.bpk.
    #[arg(long, required_unless_present = "evaluate")]
    pub out: Option<PathBuf>,
    /// Train nothing: score these weights (a burnpack file, or `embedded` for the weights built
    /// into murk) on the held-out scenes of the other settings.
    #[arg(long, conflicts_with = "out")]
    pub evaluate: Option<String>,
    /// Seed of the training scenes, initialisation and batch sampling (< 2^30).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Optimiser steps.
    #[arg(long, default_value_t = 3000)]
    pub steps: usize,
    /// Images per batch.
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    /// Peak Adam learning rate.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// Scenes in the training pool (two views each).
    #[arg(long, default_value_t = 4000)]
    pub pool_scenes: usize,
    /// Held-out scenes (one image each, seeds disjoint from training); 0 skips the evaluation.
    #[arg(long, default_value_t = 400)]
    pub eval_scenes: usize,
    /// Lowest median transmission of the simulated haze.
    #[arg(long, default_value_t = 0.1)]
    pub t_min: f64,
    /// Highest median transmission of the simulated haze.
    #[arg(long, default_value_t = 0.7)]
    pub t_max: f64,
    /// Lowest airlight A of the simulated haze.
    #[arg(long, default_value_t = 0.4)]
    pub a_min: f32,
    /// Highest airlight A of the simulated haze.
    #[arg(long, default_value_t = 1.0)]
    pub a_max: f32,
    /// Every scene is the simulator's default room, instead of scenes that vary in brightness,
    /// furniture, field of view, trajectory and noise (the narrower training set: weights
    /// trained on it read dim real haze badly).
    #[arg(long)]
    pub uniform_rooms: bool,
    /// Draw each image's darkening gain independently of its A, instead of drawing the target A
    /// uniformly first (which spreads the training targets evenly over `--a-min`..`--a-max`).
    #[arg(long)]
    pub independent_gain: bool,
}

/// Runs a train subcommand.
pub fn run(cmd: TrainCommand) -> anyhow::Result<()> {
    match cmd {
        TrainCommand::Airlight(a) => train_airlight(&a),
    }
}

fn bar(len: u64, prefix: &str) -> ProgressBar {
    let b = ProgressBar::new(len);
    b.set_style(
        ProgressStyle::with_template(
            "{prefix:>12} [{bar:40}] {pos}/{len} {elapsed_precise} (eta {eta}) {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    b.set_prefix(prefix.to_string());
    b
}

fn train_airlight(a: &TrainAirlightArgs) -> anyhow::Result<()> {
    let cfg = TrainConfig {
        seed: a.seed,
        steps: a.steps,
        batch: a.batch,
        learning_rate: a.lr,
        pool_scenes: a.pool_scenes,
        transmission_range: [a.t_min, a.t_max],
        airlight_range: [a.a_min, a.a_max],
        varied_scenes: !a.uniform_rooms,
        uniform_targets: !a.independent_gain,
        ..TrainConfig::default()
    };
    cfg.validate().context("invalid training settings")?;
    let start = Instant::now();
    if let Some(weights) = &a.evaluate {
        let cnn = if weights == "embedded" {
            AirlightCnn::embedded()?
        } else {
            let bytes = std::fs::read(weights).with_context(|| format!("reading {weights}"))?;
            AirlightCnn::from_bytes(&bytes)?
        };
        return held_out(&cfg, &cnn, a.eval_scenes, start);
    }
    let out = a.out.as_ref().context("--out is required when training")?;

    let b = bar(cfg.pool_scenes as u64, "simulating");
    let pool = simulate_samples(&cfg, &training_seeds(&cfg), true, &|| b.inc(1))
        .context("simulating the training pool")?;
    b.finish();
    let sim_s = start.elapsed().as_secs_f64();
    println!(
        "training pool: {} images from {} scenes in {sim_s:.0} s ({:.0} ms/scene)",
        pool.len(),
        cfg.pool_scenes,
        1e3 * sim_s / cfg.pool_scenes as f64
    );

    let t_train = Instant::now();
    let b = bar(cfg.steps as u64, "training");
    // Running loss: exponential moving average over ~50 steps, what the bar shows.
    let mut ema: Option<f32> = None;
    let cnn = train(&cfg, &pool, &Monitor::noop(), &mut |ev| match ev {
        TrainEvent::Step { step, loss, lr } => {
            let e = ema.map_or(loss, |e| 0.98 * e + 0.02 * loss);
            ema = Some(e);
            b.set_position(step as u64);
            b.set_message(format!("L1 {e:.4} (batch {loss:.4}) lr {lr:.1e}"));
        }
    })
    .context("training the airlight CNN")?;
    b.finish();
    let train_s = t_train.elapsed().as_secs_f64();
    println!(
        "trained {} steps × {} images in {train_s:.0} s ({:.2} s/step), final running L1 {:.4}",
        cfg.steps,
        cfg.batch,
        train_s / cfg.steps as f64,
        ema.unwrap_or(f32::NAN)
    );

    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let bytes = cnn.save_bytes()?;
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    println!(
        "wrote {} ({} parameters, {:.1} MB)",
        out.display(),
        cnn.num_params(),
        bytes.len() as f64 / 1e6
    );
    held_out(&cfg, &cnn, a.eval_scenes, start)
}

/// Scores `cnn` on `scenes` held-out scenes of `cfg` (none: nothing) and prints the table.
fn held_out(
    cfg: &TrainConfig,
    cnn: &AirlightCnn,
    scenes: usize,
    start: Instant,
) -> anyhow::Result<()> {
    if scenes > 0 {
        let b = bar(scenes as u64, "held-out");
        let held_out = simulate_samples(cfg, &eval_seeds(scenes), false, &|| b.inc(1))
            .context("simulating the held-out scenes")?;
        b.finish();
        let rows = evaluate(
            cnn,
            &held_out,
            &[[0.1, 0.3], [0.3, 0.5], [0.5, 0.7]],
            &[[0.4, 0.55], [0.55, 0.7], [0.7, 0.85], [0.85, 1.0]],
        )?;
        print_eval(cfg, &rows);
    }
    println!(
        "total wall time {:.1} min",
        start.elapsed().as_secs_f64() / 60.0
    );
    Ok(())
}

fn print_eval(cfg: &TrainConfig, rows: &[EvalRow]) {
    println!(
        "held-out airlight error |Â − A| (A ~ U[{}, {}], {}), CNN vs dark channel:",
        cfg.airlight_range[0],
        cfg.airlight_range[1],
        if cfg.varied_scenes {
            "varied scenes"
        } else {
            "default rooms"
        }
    );
    println!(
        "{:>14} {:>14} {:>6} {:>9} {:>9} {:>9} {:>9} {:>9} {:>9}",
        "median t", "A", "n", "MAE cnn", "MAE dc", "max cnn", "max dc", "bias cnn", "bias dc"
    );
    for r in rows {
        println!(
            "{:>14} {:>14} {:>6} {:>9.4} {:>9.4} {:>9.4} {:>9.4} {:>+9.4} {:>+9.4}",
            format!("[{:.2}, {:.2})", r.transmission[0], r.transmission[1]),
            format!("[{:.2}, {:.2})", r.airlight[0], r.airlight[1]),
            r.count,
            r.mae_cnn,
            r.mae_dark_channel,
            r.max_cnn,
            r.max_dark_channel,
            r.bias_cnn,
            r.bias_dark_channel
        );
    }
}
