//! `murk simulate ...`.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Subcommand};

use murk::simulate::mvs::{simulate_mvs, write_mvs_scene, MvsSimConfig};
use murk::simulate::ps::{simulate_ps, write_ps_capture, PsShape, PsSimConfig};
use murk::simulate::stereo_sequence::write_stereo_frame;
use murk::simulate::tof::{simulate_tof, FogPreset, TofSimConfig};
use murk::simulate::{
    simulate_tof_sequence_frame, write_tof_frame, StereoMotion, StereoSequence, TofMotion,
};
use murk::Monitor;

/// What to simulate.
#[derive(Subcommand, Debug)]
pub enum SimulateCommand {
    /// A foggy CW-ToF frame with ground truth (amplitude, phase, GT range, mask, scatter), or
    /// with --frames a sequence of them while objects move and the fog drifts.
    Tof(SimTofArgs),
    /// A hazy multi-view scene with ground truth (hazy + clear images, GT depth, COLMAP model).
    Mvs(SimMvsArgs),
    /// A photometric-stereo capture in turbid water with ground truth (per light an image with
    /// and without the object, GT normals, depth, albedo, mask).
    Ps(SimPsArgs),
    /// A rectified stereo rig moving through a hazy room: one folder per pair (left.png,
    /// right.png, the left view's GT depth.exr, meta.json), the layout `murk stereo --sequence`
    /// streams.
    Stereo(SimStereoArgs),
}

/// Options of `murk simulate stereo`.
#[derive(Args, Debug)]
pub struct SimStereoArgs {
    /// Output folder (created): OUT/frame_0000, OUT/frame_0001, ...
    #[arg(long)]
    pub out: PathBuf,
    /// Scene seed: the room, the airlight and the haze.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width (the focal length scales with it, so the field of view is kept).
    #[arg(long, default_value_t = 256)]
    pub width: usize,
    /// Image height.
    #[arg(long, default_value_t = 192)]
    pub height: usize,
    /// Number of pairs.
    #[arg(long, default_value_t = 10)]
    pub frames: usize,
    /// Frames per second of the rig.
    #[arg(long, default_value_t = 10.0)]
    pub fps: f64,
    /// Speed along the optical axis, scene units per second.
    #[arg(long, default_value_t = 0.5)]
    pub forward_per_s: f64,
    /// Speed to the right, scene units per second.
    #[arg(long, default_value_t = 0.0)]
    pub sideways_per_s: f64,
}

/// The object of `murk simulate ps`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ShapeArg {
    /// A sphere (the reference's synthetic object).
    Sphere,
    /// A vase-like surface of revolution with concave parts.
    Vase,
    /// A bumpy sphere (radius ±6 %).
    Bumps,
}

/// Options of `murk simulate ps`. Defaults are the reference's synthetic setting (§4.4.1).
#[derive(Args, Debug)]
pub struct SimPsArgs {
    /// Output folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// The object.
    #[arg(long, value_enum, default_value_t = ShapeArg::Sphere)]
    pub shape: ShapeArg,
    /// Seed of the light intensities, the albedo pattern and the noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width (the focal length scales with it, so the object keeps its share of the frame).
    #[arg(long, default_value_t = 300)]
    pub width: usize,
    /// Image height.
    #[arg(long, default_value_t = 300)]
    pub height: usize,
    /// Scattering coefficient beta, per mm.
    #[arg(long, default_value_t = 5e-3)]
    pub beta_per_mm: f64,
    /// Extinction coefficient sigma, per mm (>= beta).
    #[arg(long, default_value_t = 5e-3)]
    pub sigma_per_mm: f64,
    /// Number of lights on a ring around the camera.
    #[arg(long, default_value_t = 8)]
    pub lights: usize,
    /// Give the object a smooth albedo pattern (±40 % about the mean albedo).
    #[arg(long)]
    pub textured: bool,
    /// The object's (mean) albedo, in (0, 1]; textured, at most 1/1.4. Default: 0.8, or 0.6 with
    /// --textured (the pattern's peaks must stay ≤ 1).
    #[arg(long)]
    pub albedo: Option<f64>,
    /// Standard deviation of additive Gaussian noise, image units.
    #[arg(long, default_value_t = 0.0)]
    pub noise_std: f64,
    /// Far-field sampling stride of the forward-scatter sum (1 = exact, slower).
    #[arg(long, default_value_t = 2)]
    pub far_stride: usize,
    /// How object facets radiate into the water in the surface-camera forward scatter.
    #[arg(long, value_enum, default_value_t = crate::cli::ps::FacetEmissionArg::Lambertian)]
    pub facet_emission: crate::cli::ps::FacetEmissionArg,
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
    /// Draw the airlight A from LO,HI, within (0, 1] (default 0.7,1.0).
    #[arg(long, value_delimiter = ',', value_name = "LO,HI")]
    pub airlight_range: Option<Vec<f32>>,
    /// Draw the reference view's median transmission from LO,HI, within (0, 1) (default
    /// 0.2,0.4; the reference's hazy scenes span 0.1 to 0.4).
    #[arg(long, value_delimiter = ',', value_name = "LO,HI")]
    pub median_transmission_range: Option<Vec<f64>>,
    /// Spread of the camera centres along the optical axis, scene units (default 0: a purely
    /// sideways trajectory). Views then see the same point at different depths, the evidence
    /// that determines beta.
    #[arg(long)]
    pub forward_motion: Option<f64>,
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
    /// Object placement: separated (objects apart, background around them), cluttered (a
    /// large near sphere occluding a panel, plus 1–2 objects) or obstacles (a near object, a
    /// panel seen nearly edge-on at its outline, a thin pole).
    #[arg(long, default_value = "separated")]
    pub layout: String,
    /// Render a sequence of this many frames into OUT/frame_0000, OUT/frame_0001, ... (each in
    /// the one-frame layout, with its ground truth): objects move, the fog drifts, and with
    /// --cut-every the scene changes. `murk tof --sequence OUT` streams it.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Frames per second of the sequence.
    #[arg(long, default_value_t = 10.0, requires = "frames")]
    pub fps: f64,
    /// Fastest an object moves, metres per second (each draws its speed between a third of this
    /// and this).
    #[arg(long, default_value_t = 0.3, requires = "frames")]
    pub max_speed_m_per_s: f64,
    /// Relative amplitude of the fog's drift in beta (a 10 s sine), in [0, 0.9].
    #[arg(long, default_value_t = 0.1, requires = "frames")]
    pub fog_drift: f64,
    /// A new scene (the next seed's layout) every this many frames.
    #[arg(long, requires = "frames")]
    pub cut_every: Option<usize>,
}

/// `murk simulate tof --frames N`: the sequence's frames, rendered in turn.
fn simulate_tof_sequence(a: &SimTofArgs, cfg: &TofSimConfig, frames: usize) -> anyhow::Result<()> {
    if frames == 0 {
        anyhow::bail!("--frames must be at least 1");
    }
    let motion = TofMotion {
        frame_rate_hz: a.fps,
        max_speed_m_per_s: a.max_speed_m_per_s,
        fog_drift: a.fog_drift,
        cut_every: a.cut_every,
        ..TofMotion::default()
    };
    motion.validate()?;
    let mut cuts = Vec::new();
    for index in 0..frames {
        let frame = simulate_tof_sequence_frame(cfg, &motion, index, &Monitor::noop())?;
        let dir = a.out.join(format!("frame_{index:04}"));
        write_tof_frame(&dir, &frame).with_context(|| format!("writing {}", dir.display()))?;
        if motion.is_cut(index) {
            cuts.push(index);
        }
    }
    println!(
        "wrote {frames} frames into {} ({}x{}, {} fps, beta {:.2e}/mm drifting by {:.0} %, \
         objects up to {} m/s, {} layout, seed {}{})",
        a.out.display(),
        a.width,
        a.height,
        a.fps,
        cfg.effective_beta_per_mm(),
        100.0 * a.fog_drift,
        a.max_speed_m_per_s,
        cfg.layout,
        a.seed,
        if cuts.is_empty() {
            String::new()
        } else {
            format!("; scene cuts before frames {cuts:?}")
        }
    );
    Ok(())
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
                layout: a.layout.parse()?,
                ..TofSimConfig::with_size(a.width, a.height)
            };
            if let Some(frames) = a.frames {
                return simulate_tof_sequence(&a, &cfg, frames);
            }
            let frame = simulate_tof(&cfg, &Monitor::noop())?;
            write_tof_frame(&a.out, &frame)
                .with_context(|| format!("writing {}", a.out.display()))?;
            println!(
                "wrote {} ({}x{}, preset {preset}, beta {:.2e}/mm, {} layout, seed {})",
                a.out.display(),
                a.width,
                a.height,
                cfg.effective_beta_per_mm(),
                cfg.layout,
                a.seed
            );
            Ok(())
        }
        SimulateCommand::Mvs(a) => simulate_mvs_scene(&a),
        SimulateCommand::Ps(a) => simulate_ps_capture(&a),
        SimulateCommand::Stereo(a) => simulate_stereo_sequence(&a),
    }
}

fn simulate_stereo_sequence(a: &SimStereoArgs) -> anyhow::Result<()> {
    if a.frames == 0 {
        anyhow::bail!("--frames must be at least 1");
    }
    let seq = StereoSequence::new(
        &MvsSimConfig {
            seed: a.seed,
            ..MvsSimConfig::with_size(a.width, a.height)
        },
        &StereoMotion {
            frame_rate_hz: a.fps,
            forward_m_per_s: a.forward_per_s,
            sideways_m_per_s: a.sideways_per_s,
        },
    )?;
    let progress = indicatif::ProgressBar::new(a.frames as u64);
    for k in 0..a.frames {
        let frame = seq.frame(k, &Monitor::noop())?;
        let dir = a.out.join(format!("frame_{k:04}"));
        write_stereo_frame(&dir, &seq, &frame)
            .with_context(|| format!("writing {}", dir.display()))?;
        progress.inc(1);
    }
    progress.finish_and_clear();
    let k = seq.intrinsics();
    println!(
        "wrote {} ({} pairs of {}x{} at {} Hz, A {:.3}, beta {:.4} per unit, baseline {}, seed {})",
        a.out.display(),
        a.frames,
        a.width,
        a.height,
        a.fps,
        seq.airlight,
        seq.beta,
        seq.baseline(),
        a.seed
    );
    println!(
        "next: murk stereo --sequence {0} --out {0}/result --intrinsics {1},{2},{3},{4} \
         --baseline {5} --airlight {6} --beta {7}",
        a.out.display(),
        k.fx,
        k.fy,
        k.cx,
        k.cy,
        seq.baseline(),
        seq.airlight,
        seq.beta
    );
    Ok(())
}

fn simulate_ps_capture(a: &SimPsArgs) -> anyhow::Result<()> {
    let cfg = PsSimConfig {
        shape: match a.shape {
            ShapeArg::Sphere => PsShape::Sphere,
            ShapeArg::Vase => PsShape::Vase,
            ShapeArg::Bumps => PsShape::Bumps,
        },
        seed: a.seed,
        beta_per_mm: a.beta_per_mm,
        sigma_per_mm: a.sigma_per_mm,
        num_lights: a.lights,
        textured: a.textured,
        albedo: a.albedo.unwrap_or(if a.textured {
            0.6
        } else {
            PsSimConfig::default().albedo
        }),
        noise_std: a.noise_std,
        far_stride: a.far_stride,
        facet_emission: a.facet_emission.into(),
        ..PsSimConfig::with_size(a.width, a.height)
    };
    let started = std::time::Instant::now();
    let sim = simulate_ps(&cfg, &Monitor::noop())?;
    write_ps_capture(&a.out, &sim).with_context(|| format!("writing {}", a.out.display()))?;
    println!(
        "wrote {} ({}x{}, {:?}, {} lights, beta {:.1e}/mm, sigma {:.1e}/mm, {} object pixels, \
         seed {}) in {:.1} s",
        a.out.display(),
        cfg.width,
        cfg.height,
        cfg.shape,
        cfg.num_lights,
        cfg.beta_per_mm,
        cfg.sigma_per_mm,
        sim.capture.mask.iter().filter(|&&b| b).count(),
        cfg.seed,
        started.elapsed().as_secs_f64()
    );
    println!(
        "next: murk ps --capture {0} --out {0}/result --support-r 81",
        a.out.display()
    );
    Ok(())
}

fn simulate_mvs_scene(a: &SimMvsArgs) -> anyhow::Result<()> {
    let base = MvsSimConfig::with_size(a.width, a.height);
    let pair = |flag: &str, r: Option<&[f32]>| -> anyhow::Result<Option<[f32; 2]>> {
        match r {
            None => Ok(None),
            Some(&[lo, hi]) => Ok(Some([lo, hi])),
            Some(r) => anyhow::bail!("{flag} takes two values LO,HI, got {r:?}"),
        }
    };
    let beta_range = pair("--beta-range", a.beta_range.as_deref())?;
    let airlight_range = pair("--airlight-range", a.airlight_range.as_deref())?;
    let median_transmission_range = match a.median_transmission_range.as_deref() {
        None => base.median_transmission_range,
        Some(&[lo, hi]) => [lo, hi],
        Some(r) => anyhow::bail!("--median-transmission-range takes two values LO,HI, got {r:?}"),
    };
    let cfg = MvsSimConfig {
        seed: a.seed,
        rectified_pair: a.rectified_pair,
        beta_range,
        airlight_range: airlight_range.unwrap_or(base.airlight_range),
        median_transmission_range,
        forward_motion: a.forward_motion.unwrap_or(base.forward_motion),
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
