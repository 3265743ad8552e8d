//! `murk simulate ...`.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Subcommand};

use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::write_tof_frame;
use murk::Monitor;

/// What to simulate.
#[derive(Subcommand, Debug)]
pub enum SimulateCommand {
    /// A foggy CW-ToF frame with ground truth (amplitude, phase, GT range, mask, scatter).
    Tof(SimTofArgs),
}

/// Options of `murk simulate tof`.
#[derive(Args, Debug)]
pub struct SimTofArgs {
    /// Output folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Fog density: thin, medium or thick.
    #[arg(long, default_value = "medium")]
    pub preset: String,
    /// Seed of the scene layout and noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width (the field of view is kept).
    #[arg(long, default_value_t = 512)]
    pub width: usize,
    /// Image height.
    #[arg(long, default_value_t = 424)]
    pub height: usize,
    /// Overrides the preset's extinction coefficient, per millimetre.
    #[arg(long)]
    pub beta_per_mm: Option<f64>,
}

/// Runs a simulate subcommand.
pub fn run(cmd: SimulateCommand) -> anyhow::Result<()> {
    match cmd {
        SimulateCommand::Tof(a) => {
            let preset: FogPreset = a.preset.parse()?;
            let cfg = TofSimConfig {
                preset,
                seed: a.seed,
                beta_per_mm: a.beta_per_mm,
                ..TofSimConfig::with_size(a.width, a.height)
            };
            let frame = simulate_tof(&cfg, &Monitor::noop())?;
            write_tof_frame(&a.out, &frame)
                .with_context(|| format!("writing {}", a.out.display()))?;
            println!(
                "wrote {} ({}x{}, preset {preset}, beta {:.2e}/mm, seed {})",
                a.out.display(),
                a.width,
                a.height,
                cfg.effective_beta_per_mm(),
                a.seed
            );
            Ok(())
        }
    }
}
