//! `murk simulate ...`.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Subcommand};

use murk::simulate::mvs::{simulate_mvs, write_mvs_scene, MvsSimConfig};
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::write_tof_frame;
use murk::Monitor;

/// What to simulate.
#[derive(Subcommand, Debug)]
pub enum SimulateCommand {
    /// A foggy CW-ToF frame with ground truth (amplitude, phase, GT range, mask, scatter).
    Tof(SimTofArgs),
    /// A hazy multi-view scene with ground truth (hazy + clear images, GT depth, COLMAP model).
    Mvs(SimMvsArgs),
}

/// Options of `murk simulate mvs`.
#[derive(Args, Debug)]
pub struct SimMvsArgs {
    /// Output folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the scene layout, haze and noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width (the focal length scales with it, so the field of view is kept).
    #[arg(long, default_value_t = 256)]
    pub width: usize,
    /// Image height.
    #[arg(long, default_value_t = 192)]
    pub height: usize,
    /// Number of views along the trajectory (default 5; 2 with --rectified-pair).
    #[arg(long)]
    pub views: Option<usize>,
    /// Two views with the same orientation, the source shifted along +x (rectified stereo).
    #[arg(long)]
    pub rectified_pair: bool,
    /// Draw beta (per scene unit) from LO,HI and scale the scene to keep the median transmission
    /// in [0.2, 0.4] (e.g. 0.4,0.8, the reference's indoor setting); default: beta follows from
    /// the room's size.
    #[arg(long, value_delimiter = ',', value_name = "LO,HI")]
    pub beta_range: Option<Vec<f32>>,
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
        SimulateCommand::Mvs(a) => simulate_mvs_scene(&a),
    }
}

fn simulate_mvs_scene(a: &SimMvsArgs) -> anyhow::Result<()> {
    let base = MvsSimConfig::with_size(a.width, a.height);
    if let Some(r) = &a.beta_range {
        anyhow::ensure!(
            r.len() == 2,
            "--beta-range takes two values LO,HI, got {r:?}"
        );
    }
    let cfg = MvsSimConfig {
        seed: a.seed,
        rectified_pair: a.rectified_pair,
        beta_range: a.beta_range.as_deref().map(|r| [r[0], r[1]]),
        num_views: a
            .views
            .unwrap_or(if a.rectified_pair { 2 } else { base.num_views }),
        ..base
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop())?;
    write_mvs_scene(&a.out, &scene).with_context(|| format!("writing {}", a.out.display()))?;
    let reference = scene
        .views
        .get(scene.reference)
        .context("simulated scene has no reference view")?;
    println!(
        "wrote {} ({}x{}, {} views, reference {}, seed {})",
        a.out.display(),
        cfg.width,
        cfg.height,
        scene.views.len(),
        reference.name,
        cfg.seed
    );
    println!(
        "airlight A = {:.4}, beta = {:.5} per scene unit, median transmission of the reference \
         {:.3}",
        scene.airlight, scene.beta, scene.median_transmission
    );
    println!(
        "next: murk mvs --model {0}/sparse --images {0}/images --reference {1} --out {0}/result\n  \
         or:  murk params --model {0}/sparse --images {0}/images --reference {1} --out {0}/params",
        a.out.display(),
        reference.name
    );
    Ok(())
}
