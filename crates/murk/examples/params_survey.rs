//! Accuracy of the scattering parameters `A` and β (reference Ch. 3.3) on simulated scenes,
//! as MAE_A and MAE_β (the metrics of the reference's Table 3.3) with the identifiability
//! verdicts. Each scene is `simulate_mvs` at 256×192 with 5 views (the reference and its 4
//! nearest sources), A ∈ [0.5, 1.0], the reference's median transmission ∈ [0.1, 0.4] and β
//! derived from the room (no range imposed), σ = 0.01 image noise.
//!
//! Two fits:
//! - `--fit search` (default): [`search_scattering`] with [`SearchParams::default`], what
//!   `murk params` runs (the joint fit of A, β and the source gains; the points' ratios, then
//!   the sweep of Algorithm 1 where it does not determine β; `--beta-sweep` forces the sweep).
//!   Also the C.P. of the 256-plane depth with the estimated and the true parameters, and how
//!   many identifiable scenes lie more than 2 standard errors from the truth.
//! - `--fit joint`: the joint fit alone ([`fit_joint`]) with the priors the search gives it,
//!   next to the points' transmission-ratio fit at `A₀`; `--no-falloff` leaves out the lens
//!   fall-off terms.
//!
//! Disturbances of the images (both fits): `--gain` multiplies every source (an exposure step),
//! `--vignetting` darkens every view's corners, `--source-vignetting` only the sources'.
//!
//! ```sh
//! cargo run --release -p murk --example params_survey -- --seeds 500-519
//! cargo run --release -p murk --example params_survey -- --seeds 500-519 --forward 0.5
//! cargo run --release -p murk --example params_survey -- --fit joint --seeds 300-309 --vignetting 0.3
//! ```
//!
//! Prints one Markdown row per scene, then the summary table.

mod common;

use anyhow::{bail, Context};
use clap::{Parser, ValueEnum};

use murk::atmosphere::AtmosphereParams;
use murk::image::ImageF32;
use murk::metrics::depth_metrics;
use murk::mvs::depth::vignetting::vignette;
use murk::mvs::{estimate_depth, CostKind, DehazingOptions, DepthParams, PlaneSet, View};
use murk::params::airlight::{dark_channel_airlight, AirlightEstimator, DarkChannelParams};
use murk::params::joint_fit::{
    fit_joint, JointPriors, FALLOFF_PRIOR_SIGMA, RELATIVE_FALLOFF_PRIOR_SIGMA,
};
use murk::params::point_ratio::beta_from_point_ratios;
use murk::params::search::{
    beta_range_from_points, plane_range_from_sparse, search_scattering, SearchParams, SfmEvidence,
    AIRLIGHT_PRIOR_SIGMA, CNN_AIRLIGHT_ERROR, DARK_CHANNEL_AIRLIGHT_ERROR,
};
use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
use murk::Monitor;

use common::{mean, parse_seeds, Table};

/// Where `A₀` comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Estimator {
    /// The CNN of reference Table 3.1 with the weights compiled into murk.
    Cnn,
    /// The dark-channel rule.
    DarkChannel,
    /// The scene's true A (a given A₀, as `murk params --airlight-source given`).
    True,
}

/// Which estimate is measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Fit {
    /// `search_scattering` with murk's defaults, as `murk params` runs it.
    Search,
    /// The joint fit of A, β, the gains and the fall-offs alone, and the ratio fit at A₀.
    Joint,
}

/// A seed list; an alias so that clap takes the whole list as one value.
type Seeds = Vec<u64>;

#[derive(Parser, Debug)]
#[command(about = "MAE of A and β (reference Table 3.3) on simulated hazy scenes")]
struct Args {
    /// Scene seeds: `500-519`, `300,301`, ...
    #[arg(long, default_value = "500-519", value_parser = parse_seeds)]
    seeds: Seeds,
    /// What to measure.
    #[arg(long, value_enum, default_value_t = Fit::Search)]
    fit: Fit,
    /// The airlight estimator that gives A₀.
    #[arg(long, value_enum, default_value_t = Estimator::Cnn)]
    estimator: Estimator,
    /// Added to A₀ (then clamped to [0.05, 1]): an estimator that is off by this much.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    a0_offset: f32,
    /// Spread of the camera centres along the optical axis, scene units (0: lateral trajectory).
    #[arg(long, default_value_t = 0.0)]
    forward: f64,
    /// Every source image multiplied by this (clipped to [0, 1]): an exposure step.
    #[arg(long, default_value_t = 1.0)]
    gain: f32,
    /// Every view darkened toward its corners by this fraction (gain 1 − V·r², r = 1 at the
    /// corners).
    #[arg(long, default_value_t = 0.0)]
    vignetting: f32,
    /// The sources' corners darkened by this fraction instead of --vignetting (a source lens
    /// that differs from the reference's); default: --vignetting.
    #[arg(long)]
    source_vignetting: Option<f32>,
    /// Search: the published sweep of Eq. 3.10 and the step-2 grid instead of the points
    /// (`murk params --beta-sweep`).
    #[arg(long)]
    beta_sweep: bool,
    /// Joint fit: no lens fall-off terms (neither the shared one nor the sources' own).
    #[arg(long)]
    no_falloff: bool,
}

/// One simulated scene and its images as the fits see them (with the disturbances).
struct Scene {
    sim: murk::simulate::mvs::MvsScene,
    reference: ImageF32,
    sources: Vec<ImageF32>,
}

impl Scene {
    fn new(seed: u64, args: &Args) -> anyhow::Result<Self> {
        let cfg = MvsSimConfig {
            seed,
            airlight_range: [0.5, 1.0],
            median_transmission_range: [0.1, 0.4],
            forward_motion: args.forward,
            ..MvsSimConfig::default()
        };
        let sim = simulate_mvs(&cfg, &Monitor::noop()).context("simulating the scene")?;
        let (reference, sources) = sim.reference_and_sources();
        // `vignette` multiplies by 1 + a·r²: a fall-off V is a = −V.
        let reference = vignette(reference.image, -args.vignetting);
        let source_vignetting = args.source_vignetting.unwrap_or(args.vignetting);
        let sources = sources
            .iter()
            .map(|v| {
                let mut img = v.image.clone();
                for x in img.data_mut() {
                    *x = (*x * args.gain).clamp(0.0, 1.0);
                }
                vignette(&img, -source_vignetting)
            })
            .collect();
        Ok(Self {
            sim,
            reference,
            sources,
        })
    }

    /// The reference and source views with the disturbed images.
    fn views(&self) -> (View<'_>, Vec<View<'_>>) {
        let (r, s) = self.sim.reference_and_sources();
        let reference = View {
            image: &self.reference,
            ..r
        };
        let sources = s
            .iter()
            .zip(&self.sources)
            .map(|(v, image)| View { image, ..*v })
            .collect();
        (reference, sources)
    }
}

/// A₀ of the reference image (with the offset, clamped to [0.05, 1]).
fn airlight_initial(
    args: &Args,
    cnn: Option<&AirlightEstimator>,
    image: &ImageF32,
    truth: f32,
) -> anyhow::Result<f32> {
    let a0 = match (args.estimator, cnn) {
        (Estimator::Cnn, Some(cnn)) => cnn.estimate(image)?,
        (Estimator::Cnn, None) => bail!("no CNN loaded"),
        (Estimator::DarkChannel, _) => dark_channel_airlight(image, &DarkChannelParams::default())?,
        (Estimator::True, _) => truth,
    };
    Ok((a0 + args.a0_offset).clamp(0.05, 1.0))
}

/// `value ± error` with 4 decimals; `value` alone without an error.
fn pm(value: f64, error: Option<f64>) -> String {
    match error {
        Some(e) => format!("{value:.4} ± {e:.4}"),
        None => format!("{value:.4}"),
    }
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let cnn = match args.estimator {
        Estimator::Cnn => Some(AirlightEstimator::from_config(None, false)?),
        _ => None,
    };
    match args.fit {
        Fit::Search => survey_search(&args, cnn.as_ref()),
        Fit::Joint => survey_joint(&args, cnn.as_ref()),
    }
}

/// C.P. (%) of the 256-plane depth with `airlight` and `beta` against the scene's true depth.
fn depth_cp(scene: &Scene, planes: &PlaneSet, airlight: f32, beta: f32) -> anyhow::Result<f64> {
    let (reference, sources) = scene.views();
    let kind = CostKind::DehazingWith(
        AtmosphereParams { airlight, beta },
        DehazingOptions::default(),
    );
    let d = estimate_depth(
        &reference,
        &sources,
        planes,
        kind,
        &DepthParams::default(),
        &Monitor::noop(),
    )?;
    let truth = &scene.sim.views[scene.sim.reference].depth;
    Ok(100.0 * depth_metrics(&d.z_depth, truth, None)?.c_p)
}

fn survey_search(args: &Args, cnn: Option<&AirlightEstimator>) -> anyhow::Result<()> {
    let params = SearchParams {
        // The conflict test knows how far each estimator is typically off, as the server does.
        airlight_initial_error: match args.estimator {
            Estimator::Cnn => CNN_AIRLIGHT_ERROR,
            Estimator::DarkChannel => DARK_CHANNEL_AIRLIGHT_ERROR,
            Estimator::True => SearchParams::default().airlight_prior_sigma,
        },
        beta_from_points: !args.beta_sweep,
        joint_fit: !args.beta_sweep,
        ..SearchParams::default()
    };
    let mut scenes = Table::new(&[
        "seed", "A", "A₀", "A*", "β", "β*", "β from", "verdict", "C.P. est", "C.P. GT", "s",
    ]);
    let (mut e_a0, mut e_a, mut e_b, mut cp_est, mut cp_gt, mut secs) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let (mut identifiable, mut beyond_2se) = (0, 0);
    for &seed in &args.seeds {
        let scene = Scene::new(seed, args)?;
        let (reference, sources) = scene.views();
        let sparse = scene.sim.sparse_depth()?;
        let (near, far) = plane_range_from_sparse(&sparse).context("no SfM points")?;
        let planes = PlaneSet::new(near, far, 256)?;
        let (a_true, b_true) = (scene.sim.airlight, scene.sim.beta);
        let a0 = airlight_initial(args, cnn, reference.image, a_true)?;
        let est = search_scattering(
            &reference,
            &sources,
            SfmEvidence::map(&sparse),
            a0,
            &planes,
            &params,
            &Monitor::noop(),
        )?;
        let c_est = depth_cp(&scene, &planes, est.airlight, est.beta)?;
        let c_gt = depth_cp(&scene, &planes, a_true, b_true)?;
        let ok = est.identifiability == murk::params::joint_fit::Identifiability::Identifiable;
        identifiable += usize::from(ok);
        // Honest errors: how often an identifiable β lies more than 2 standard errors off.
        if let (true, Some(se)) = (ok, est.beta_std_error) {
            beyond_2se += usize::from(f64::from((est.beta - b_true).abs()) > 2.0 * se);
        }
        scenes.row(&[
            seed.to_string(),
            format!("{a_true:.4}"),
            format!("{a0:.4}"),
            pm(f64::from(est.airlight), est.airlight_std_error),
            format!("{b_true:.4}"),
            pm(f64::from(est.beta), est.beta_std_error),
            format!("{:?}", est.beta_source),
            est.identifiability.name().to_string(),
            format!("{c_est:.1}"),
            format!("{c_gt:.1}"),
            format!("{:.2}", est.seconds),
        ]);
        e_a0.push(f64::from((a0 - a_true).abs()));
        e_a.push(f64::from((est.airlight - a_true).abs()));
        e_b.push(f64::from((est.beta - b_true).abs()));
        cp_est.push(c_est);
        cp_gt.push(c_gt);
        secs.push(est.seconds);
    }
    scenes.print();
    println!();
    let n = args.seeds.len();
    let mut summary = Table::new(&[
        "A₀",
        "A₀ alone: MAE",
        "MAE_A",
        "MAE_β",
        "identifiable",
        "identifiable, truth > 2 SE off",
        "C.P. est / GT params",
        "search s/scene",
    ]);
    summary.row(&[
        a0_label(args),
        format!("{:.4}", mean(&e_a0)),
        format!("{:.4}", mean(&e_a)),
        format!("{:.4}", mean(&e_b)),
        format!("{identifiable}/{n}"),
        beyond_2se.to_string(),
        format!("{:.1} / {:.1} %", mean(&cp_est), mean(&cp_gt)),
        format!("{:.2}", mean(&secs)),
    ]);
    summary.print();
    Ok(())
}

/// The row label: estimator and offset.
fn a0_label(args: &Args) -> String {
    let name = match args.estimator {
        Estimator::Cnn => "CNN",
        Estimator::DarkChannel => "dark channel",
        Estimator::True => "true A",
    };
    if args.a0_offset == 0.0 {
        name.to_string()
    } else {
        format!("{name} {:+}", args.a0_offset)
    }
}

fn survey_joint(args: &Args, cnn: Option<&AirlightEstimator>) -> anyhow::Result<()> {
    let mut scenes = Table::new(&[
        "seed",
        "A",
        "β",
        "t_med",
        "A₀",
        "A (fit)",
        "β (fit)",
        "mean gain",
        "fall-off a",
        "verdict",
        "β, ratio fit at A₀",
    ]);
    // Per fit: |A error|, |β error|, identifiable (joint) or reliable (ratio).
    let (mut joint, mut ratio) = ([vec![], vec![]], [vec![], vec![]]);
    let (mut identifiable, mut reliable) = (0, 0);
    for &seed in &args.seeds {
        let scene = Scene::new(seed, args)?;
        let (reference, sources) = scene.views();
        let sparse = scene.sim.sparse_depth()?;
        let (a, b) = (f64::from(scene.sim.airlight), f64::from(scene.sim.beta));
        let a0 = airlight_initial(args, cnn, reference.image, scene.sim.airlight)?;
        let z_med = f64::from(sparse.depth_quantile(0.5).context("no SfM points")?);
        let (falloff_sigma, relative_falloff_sigma) = if args.no_falloff {
            (0.0, 0.0)
        } else {
            (FALLOFF_PRIOR_SIGMA, RELATIVE_FALLOFF_PRIOR_SIGMA)
        };
        // The priors `search_scattering` gives the fit: β starts at the geometric middle of
        // the range the points allow.
        let [lo, hi] = beta_range_from_points(&sparse).context("no SfM points")?;
        let priors = JointPriors {
            airlight: f64::from(a0),
            airlight_sigma: f64::from(AIRLIGHT_PRIOR_SIGMA),
            gain_sigma: 0.2,
            beta_start: f64::from((lo.max(1e-6) * hi).sqrt()),
            falloff_sigma,
            relative_falloff_sigma,
        };
        let fit = fit_joint(&reference, &sources, &sparse, &priors).context("no sources")?;
        let rf = beta_from_point_ratios(&reference, &sources, &sparse, a0);
        joint[0].push((fit.airlight - a).abs());
        joint[1].push((fit.beta - b).abs());
        identifiable += usize::from(fit.is_identifiable());
        if let Some(rf) = &rf {
            ratio[0].push(f64::from(a0 - scene.sim.airlight).abs());
            ratio[1].push((rf.beta - b).abs());
            reliable += usize::from(rf.is_reliable());
        }
        scenes.row(&[
            seed.to_string(),
            format!("{a:.4}"),
            format!("{b:.4}"),
            format!("{:.2}", (-b * z_med).exp()),
            format!("{a0:.4}"),
            pm(fit.airlight, Some(fit.airlight_std_error)),
            pm(fit.beta, Some(fit.beta_std_error)),
            format!("{:.4}", mean(&fit.source_gains)),
            format!("{:.3}", fit.vignetting_falloff),
            fit.identifiability.name().to_string(),
            rf.map_or("—".into(), |r| {
                format!(
                    "{:.4} ({})",
                    r.beta,
                    if r.is_reliable() {
                        "reliable"
                    } else {
                        "unreliable"
                    }
                )
            }),
        ]);
    }
    scenes.print();
    println!();
    let n = args.seeds.len();
    let mut summary = Table::new(&["fit", "MAE_A", "MAE_β", "identifiable / reliable"]);
    summary.row(&[
        format!("joint fit, {} prior", a0_label(args)),
        format!("{:.4}", mean(&joint[0])),
        format!("{:.4}", mean(&joint[1])),
        format!("{identifiable}/{n}"),
    ]);
    summary.row(&[
        format!("ratio fit at the {} A₀ (A = A₀)", a0_label(args)),
        format!("{:.4}", mean(&ratio[0])),
        format!("{:.4}", mean(&ratio[1])),
        format!("{reliable}/{}", ratio[0].len()),
    ]);
    summary.print();
    Ok(())
}
