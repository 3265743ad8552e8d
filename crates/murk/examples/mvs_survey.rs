//! MVS depth in haze on the simulator's rooms (reference Ch. 3.2): L1-rel, L1-inv, sc-inv and
//! C.P. (§3.4.3) of the reference view's depth, per seed and averaged over the seeds, for each
//! combination of the scene and depth options asked for. Prints Markdown tables: the scenes
//! (A, β, the reference's median transmission), one row per seed and variant (with the plane
//! count, the shared lens fall-off found and the wall time of `estimate_depth`), and the means.
//!
//! The scene (`murk::simulate::mvs`): a closed textured room with boxes and spheres, 5 views
//! along a 0.4-unit trajectory, the middle one the reference, depth about 2–12 units, A drawn
//! from `--airlight-range`, β set for a median transmission of the reference drawn from
//! `--median-transmission-range`, Gaussian sensor noise. Depth is `estimate_depth` with the true
//! A and β, the `--sources` views nearest the reference along the trajectory, and
//! `DepthParams::default()` except for the options given. The tables of docs/accuracy.md:
//!
//! ```sh
//! cargo run --release -p murk --example mvs_survey -- --seeds 0-4 --cost ordinary,eq37,dehazing-hard,dehazing-noise-aware,dehazing
//! cargo run --release -p murk --example mvs_survey -- --seeds 5-9 --cost ordinary,eq37,dehazing-hard,dehazing-noise-aware,dehazing
//! cargo run --release -p murk --example mvs_survey -- --seeds 0-4 --clear --cost ordinary
//! cargo run --release -p murk --example mvs_survey -- --seeds 0-4 --paths 5,8
//! cargo run --release -p murk --example mvs_survey -- --seeds 0-4 --p1 0.01,0.05 --p2 0.1,0.5
//! cargo run --release -p murk --example mvs_survey -- --seeds 0-4 --cost dehazing --census-weight 0,0.3,1,3
//! cargo run --release -p murk --example mvs_survey -- --seeds 0-4 --cost dehazing --forward 0,0.5 --vignetting 0,-0.15 --vignetting-compensation on,off
//! cargo run --release -p murk --example mvs_survey -- --seeds 0-4 --cost dehazing --forward 0,0.5 --noise 0.02 --vignetting-compensation on,off
//! cargo run --release -p murk --example mvs_survey -- --seeds 11-13 --cost dehazing --airlight-range 0.5,1.0 --median-transmission-range 0.1,0.4 --points-range --planes auto,34,256
//! ```
//!
//! Each takes seconds to a couple of minutes on two cores (about a second per depth at
//! 256×192×256 with 4 sources); `--width 128 --height 96 --planes 64` is a quick look.

mod common;

use std::time::Instant;

use anyhow::{bail, ensure, Context};
use clap::{Parser, ValueEnum};

use murk::atmosphere::AtmosphereParams;
use murk::metrics::{depth_metrics, DepthMetrics};
use murk::mvs::depth::vignetting::vignette;
use murk::mvs::{
    estimate_depth, planes_for_displacement, Camera, CostKind, DehazingOptions, DehazingResidual,
    DepthParams, PlaneSet, RangePenalty, View, MAX_PLANES,
};
use murk::params::search::plane_range_from_sparse;
use murk::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};
use murk::Monitor;

use common::{mean, parse_seeds, Table};

/// The cost volumes compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Cost {
    /// Eq. 3.1 on the hazy images (needs no A or β).
    Ordinary,
    /// Eq. 3.7 as published: dehazed residual, γ = 3 where a dehazed value leaves [0, 1].
    Eq37,
    /// The observation-space residual with the hard [0, 1] penalty of Eq. 3.7.
    DehazingHard,
    /// The observation-space residual with the penalty widened by 3 noise σ.
    DehazingNoiseAware,
    /// murk's default: the observation-space residual, no range penalty.
    Dehazing,
}

impl Cost {
    /// The library's cost for a scene with airlight and β `atm`.
    fn kind(self, atm: AtmosphereParams) -> CostKind {
        let observation = |range| {
            CostKind::DehazingWith(
                atm,
                DehazingOptions {
                    residual: DehazingResidual::ObservationSpace,
                    range,
                    noise_sigma: None,
                },
            )
        };
        match self {
            Cost::Ordinary => CostKind::Ordinary,
            Cost::Eq37 => CostKind::Dehazing(atm),
            Cost::DehazingHard => observation(RangePenalty::Hard),
            Cost::DehazingNoiseAware => observation(RangePenalty::NoiseAware { k: 3.0 }),
            Cost::Dehazing => CostKind::DehazingWith(atm, DehazingOptions::default()),
        }
    }

    /// The name printed in the tables.
    fn name(self) -> &'static str {
        match self {
            Cost::Ordinary => "ordinary (Eq. 3.1)",
            Cost::Eq37 => "Eq. 3.7 as published",
            Cost::DehazingHard => "dehazing, hard [0, 1] penalty",
            Cost::DehazingNoiseAware => "dehazing, noise-aware penalty",
            Cost::Dehazing => "dehazing (default)",
        }
    }
}

/// A fixed plane count, or `auto`: about one plane per pixel of displacement, as `murk mvs`
/// picks it.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Planes {
    /// About one plane per pixel of the largest displacement, 16 to 256.
    Auto,
    /// This many.
    Count(usize),
}

impl std::fmt::Display for Planes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Planes::Auto => write!(f, "auto"),
            Planes::Count(n) => write!(f, "{n}"),
        }
    }
}

/// `auto` or a plane count.
fn parse_planes(text: &str) -> Result<Planes, String> {
    if text == "auto" {
        return Ok(Planes::Auto);
    }
    match text.parse::<usize>() {
        Ok(n) if (1..=MAX_PLANES).contains(&n) => Ok(Planes::Count(n)),
        _ => Err(format!("`{text}`: a count in 1..={MAX_PLANES} or `auto`")),
    }
}

/// On or off.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum OnOff {
    /// Enabled.
    On,
    /// Disabled.
    Off,
}

/// MVS depth in haze on simulated rooms: accuracy per seed and cost volume.
///
/// Options that take a comma-separated list (`--forward`, `--noise`, `--vignetting` for the
/// scenes; `--cost`, `--planes`, `--p1`, `--p2`, `--presmooth-sigma`, `--contrast-max-weight`,
/// `--paths`, `--census-weight`, `--vignetting-compensation` for the depth) are compared: every
/// combination is one row per seed.
#[derive(Parser, Debug)]
struct Args {
    /// Seeds of the simulated rooms: `0-4`, `5-9`, `0,3,7`.
    #[arg(long, default_value = "0-4")]
    seeds: String,
    /// Image width, pixels (the focal length scales with it).
    #[arg(long, default_value_t = 256)]
    width: usize,
    /// Image height, pixels.
    #[arg(long, default_value_t = 192)]
    height: usize,
    /// Source views, nearest the reference along the trajectory first (1–4).
    #[arg(long, default_value_t = 4)]
    sources: usize,
    /// Spread of the camera centres along the optical axis, scene units (0 = lateral motion).
    #[arg(long, value_delimiter = ',', default_value = "0")]
    forward: Vec<f64>,
    /// Standard deviation of the Gaussian sensor noise, pixel-value units.
    #[arg(long, value_delimiter = ',', default_value = "0.01")]
    noise: Vec<f32>,
    /// Range A is drawn from: `LO,HI`.
    #[arg(long, value_delimiter = ',', default_value = "0.7,1.0")]
    airlight_range: Vec<f32>,
    /// Range the reference's median transmission is drawn from: `LO,HI`.
    #[arg(long, value_delimiter = ',', default_value = "0.2,0.4")]
    median_transmission_range: Vec<f64>,
    /// The haze-free images instead of the hazy ones (ordinary cost only).
    #[arg(long)]
    clear: bool,
    /// Lens fall-off `a` applied to every view, gain `1 + a·r²` with r = 1 at the corners
    /// (-0.15 = corners 15 % darker).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0",
        allow_negative_numbers = true
    )]
    vignetting: Vec<f32>,
    /// Cost volumes.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "ordinary,dehazing"
    )]
    cost: Vec<Cost>,
    /// Plane counts (uniform in inverse depth), or `auto`.
    #[arg(long, value_delimiter = ',', default_value = "256", value_parser = parse_planes)]
    planes: Vec<Planes>,
    /// Nearest plane's z-depth, scene units.
    #[arg(long, default_value_t = 1.5)]
    near: f64,
    /// Farthest plane's z-depth, scene units.
    #[arg(long, default_value_t = 15.0)]
    far: f64,
    /// Planes over the range of the SfM points the reference sees, as `murk mvs` sets it
    /// (instead of --near/--far).
    #[arg(long)]
    points_range: bool,
    /// SGM path counts: 5, 8 or 4.
    #[arg(long, value_delimiter = ',', default_value = "5")]
    paths: Vec<usize>,
    /// Weights of the census term (0 = off).
    #[arg(long, value_delimiter = ',', default_value = "0")]
    census_weight: Vec<f32>,
    /// The lens fall-off estimate and compensation.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "on")]
    vignetting_compensation: Vec<OnOff>,
    /// SGM's `P1`, cost units (default: the library's).
    #[arg(long, value_delimiter = ',')]
    p1: Vec<f32>,
    /// SGM's `P2`, cost units, at least `P1` (default: the library's).
    #[arg(long, value_delimiter = ',')]
    p2: Vec<f32>,
    /// σ of the views' Gaussian pre-smoothing, pixels (default: the library's).
    #[arg(long, value_delimiter = ',')]
    presmooth_sigma: Vec<f32>,
    /// Largest contrast-normalisation weight, 1 = off (default: the library's).
    #[arg(long, value_delimiter = ',')]
    contrast_max_weight: Vec<f32>,
}

/// One combination of the compared options.
#[derive(Clone, Debug)]
struct Variant {
    cost: Cost,
    planes: Planes,
    sgm: DepthParams,
    label: String,
}

/// One compared `DepthParams` field: its values, its name in the labels, and how to set it.
type SgmAxis = (Vec<f32>, &'static str, fn(&mut DepthParams, f32));

/// Every combination of the listed options, labelled by the cost volume and the options that
/// take more than one value.
fn variants(a: &Args) -> Vec<Variant> {
    let d = DepthParams::default();
    let mut out: Vec<Variant> = a
        .cost
        .iter()
        .map(|&cost| Variant {
            cost,
            planes: Planes::Auto,
            sgm: d,
            label: cost.name().to_string(),
        })
        .collect();
    out = expand(
        out,
        &a.planes,
        |p| format!("{p} planes"),
        |v, p| v.planes = p,
    );
    let or_default = |v: &[f32], x: f32| if v.is_empty() { vec![x] } else { v.to_vec() };
    let sgm_axes: [SgmAxis; 4] = [
        (or_default(&a.p1, d.sgm.p1), "P1", |s, x| s.sgm.p1 = x),
        (or_default(&a.p2, d.sgm.p2), "P2", |s, x| s.sgm.p2 = x),
        (
            or_default(&a.presmooth_sigma, d.matching.presmooth_sigma_px),
            "pre-smoothing σ",
            |s, x| s.matching.presmooth_sigma_px = x,
        ),
        (
            or_default(&a.contrast_max_weight, d.matching.contrast_max_weight),
            "w_max",
            |s, x| s.matching.contrast_max_weight = x,
        ),
    ];
    for (values, name, set) in sgm_axes {
        out = expand(
            out,
            &values,
            |x| format!("{name} {x}"),
            |v, x| set(&mut v.sgm, x),
        );
    }
    out = expand(
        out,
        &a.paths,
        |n| format!("{n} paths"),
        |v, n| v.sgm.sgm.num_paths = n,
    );
    out = expand(
        out,
        &a.census_weight,
        |x| format!("census {x}"),
        |v, x| v.sgm.matching.census_weight = x,
    );
    expand(
        out,
        &a.vignetting_compensation,
        |c| {
            format!(
                "fall-off compensation {}",
                if c == OnOff::On { "on" } else { "off" }
            )
        },
        |v, c| v.sgm.photometric.vignetting_compensation = c == OnOff::On,
    )
}

/// Each of `variants` once per value of one option, set by `apply`; the value is named in the
/// label (by `label`) only where the option takes more than one.
fn expand<T: Copy>(
    variants: Vec<Variant>,
    values: &[T],
    label: impl Fn(T) -> String,
    apply: impl Fn(&mut Variant, T),
) -> Vec<Variant> {
    let mut out = Vec::with_capacity(variants.len() * values.len());
    for v in variants {
        for &x in values {
            let mut w = v.clone();
            apply(&mut w, x);
            if values.len() > 1 {
                w.label += &format!(", {}", label(x));
            }
            out.push(w);
        }
    }
    out
}

/// How the views of a scene are captured: the compared scene options.
#[derive(Clone, Debug)]
struct Capture {
    forward: f64,
    noise: f32,
    vignetting: f32,
    /// The options that take more than one value, named; empty when none does.
    label: String,
}

/// Every combination of the scene options.
fn captures(a: &Args) -> Vec<Capture> {
    let mut out = vec![Capture {
        forward: 0.0,
        noise: 0.0,
        vignetting: 0.0,
        label: String::new(),
    }];
    let mut axis = |values: Vec<String>, set: &dyn Fn(&mut Capture, usize)| {
        let mut next = Vec::new();
        for c in &out {
            for (i, text) in values.iter().enumerate() {
                let mut d = c.clone();
                set(&mut d, i);
                if values.len() > 1 {
                    if !d.label.is_empty() {
                        d.label += ", ";
                    }
                    d.label += text;
                }
                next.push(d);
            }
        }
        out = next;
    };
    let texts = |name: &str, v: &[String]| -> Vec<String> {
        v.iter().map(|x| format!("{name} {x}")).collect()
    };
    let forward: Vec<String> = a.forward.iter().map(|x| x.to_string()).collect();
    axis(texts("forward", &forward), &|c, i| c.forward = a.forward[i]);
    let noise: Vec<String> = a.noise.iter().map(|x| x.to_string()).collect();
    axis(texts("noise σ", &noise), &|c, i| c.noise = a.noise[i]);
    let vig: Vec<String> = a.vignetting.iter().map(|x| x.to_string()).collect();
    axis(texts("vignetting", &vig), &|c, i| {
        c.vignetting = a.vignetting[i]
    });
    out
}

/// The scene of `seed` captured as `c` (the clear images where asked).
fn scene(a: &Args, seed: u64, c: &Capture) -> anyhow::Result<MvsScene> {
    let cfg = MvsSimConfig {
        seed,
        forward_motion: c.forward,
        noise_sigma: c.noise,
        airlight_range: [a.airlight_range[0], a.airlight_range[1]],
        median_transmission_range: [
            a.median_transmission_range[0],
            a.median_transmission_range[1],
        ],
        ..MvsSimConfig::with_size(a.width, a.height)
    };
    let mut scene =
        simulate_mvs(&cfg, &Monitor::noop()).with_context(|| format!("simulating seed {seed}"))?;
    for view in &mut scene.views {
        if a.clear {
            view.hazy = view.clear.clone();
        }
        if c.vignetting != 0.0 {
            view.hazy = vignette(&view.hazy, c.vignetting);
        }
    }
    Ok(scene)
}

/// One depth estimate: its metrics, plane count, the shared fall-off found, and the wall time
/// of `estimate_depth`, seconds.
struct Outcome {
    metrics: DepthMetrics,
    planes: usize,
    falloff: f32,
    seconds: f64,
}

fn run(a: &Args, scene: &MvsScene, v: &Variant) -> anyhow::Result<Outcome> {
    let (reference, all_sources) = scene.reference_and_sources();
    let sources: Vec<View<'_>> = all_sources.into_iter().take(a.sources).collect();
    let (near, far) = if a.points_range {
        plane_range_from_sparse(&scene.sparse_depth()?)
            .context("the reference sees no SfM points")?
    } else {
        (a.near, a.far)
    };
    let count = match v.planes {
        Planes::Count(n) => n,
        Planes::Auto => {
            let camera = |view: &View<'_>| Camera {
                intrinsics: view.intrinsics,
                pose: view.pose,
                width: view.image.width(),
                height: view.image.height(),
            };
            let cams: Vec<Camera> = sources.iter().map(camera).collect();
            planes_for_displacement(&camera(&reference), &cams, near, far, MAX_PLANES)
        }
    };
    let planes = PlaneSet::new(near, far, count)?;
    let kind = v.cost.kind(AtmosphereParams {
        airlight: scene.airlight,
        beta: scene.beta,
    });
    let t0 = Instant::now();
    let depth = estimate_depth(
        &reference,
        &sources,
        &planes,
        kind,
        &v.sgm,
        &Monitor::noop(),
    )?;
    let seconds = t0.elapsed().as_secs_f64();
    let gt = &scene.views[scene.reference].depth;
    Ok(Outcome {
        metrics: depth_metrics(&depth.z_depth, gt, None)?,
        planes: count,
        falloff: depth.vignetting_falloff,
        seconds,
    })
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let seeds = parse_seeds(&a.seeds).map_err(anyhow::Error::msg)?;
    ensure!(
        a.airlight_range.len() == 2 && a.median_transmission_range.len() == 2,
        "--airlight-range and --median-transmission-range take LO,HI"
    );
    ensure!(
        (1..=4).contains(&a.sources),
        "--sources must be in 1..=4 (5 views)"
    );
    if a.clear && a.cost.iter().any(|&c| c != Cost::Ordinary) {
        bail!("--clear has no haze to remove: use --cost ordinary");
    }
    let variants = variants(&a);
    for v in &variants {
        v.sgm.validate()?;
    }

    let captures = captures(&a);
    // A row's name: the capture's compared options, then the depth's.
    let name = |c: &Capture, v: &Variant| {
        if c.label.is_empty() {
            v.label.clone()
        } else {
            format!("{}; {}", c.label, v.label)
        }
    };

    let mut scenes = Table::new(&["seed", "capture", "A", "β (per unit)", "median t"]);
    let mut rows = Table::new(&[
        "seed",
        "variant",
        "planes",
        "L1-rel",
        "L1-inv",
        "sc-inv",
        "C.P. (%)",
        "fall-off found",
        "time (s)",
    ]);
    // Per capture and variant, in that order: the outcomes over the seeds.
    let mut outcomes: Vec<Vec<Outcome>> = (0..captures.len() * variants.len())
        .map(|_| Vec::new())
        .collect();
    for &seed in &seeds {
        for (ci, c) in captures.iter().enumerate() {
            let scene = scene(&a, seed, c)?;
            scenes.row(&[
                seed.to_string(),
                if c.label.is_empty() {
                    "—".to_string()
                } else {
                    c.label.clone()
                },
                format!("{:.3}", scene.airlight),
                format!("{:.4}", scene.beta),
                format!("{:.3}", scene.median_transmission),
            ]);
            for (vi, v) in variants.iter().enumerate() {
                let label = name(c, v);
                let o = run(&a, &scene, v).with_context(|| format!("seed {seed}, {label}"))?;
                let m = &o.metrics;
                eprintln!(
                    "seed {seed}, {label}: C.P. {:.1} % in {:.2} s",
                    100.0 * m.c_p,
                    o.seconds
                );
                rows.row(&[
                    seed.to_string(),
                    label,
                    o.planes.to_string(),
                    format!("{:.3}", m.l1_rel),
                    format!("{:.4}", m.l1_inv),
                    format!("{:.3}", m.sc_inv),
                    format!("{:.1}", 100.0 * m.c_p),
                    format!("{:.3}", o.falloff),
                    format!("{:.2}", o.seconds),
                ]);
                outcomes[ci * variants.len() + vi].push(o);
            }
        }
    }

    println!(
        "{}×{} {} rooms, {} source(s), planes over {}\n",
        a.width,
        a.height,
        if a.clear { "haze-free" } else { "hazy" },
        a.sources,
        if a.points_range {
            "the SfM points' range".to_string()
        } else {
            format!("z {}…{}", a.near, a.far)
        }
    );
    scenes.print();
    println!();
    rows.print();
    println!();
    let mut means = Table::new(&[
        "variant", "L1-rel", "L1-inv", "sc-inv", "C.P. (%)", "time (s)",
    ]);
    for (ci, c) in captures.iter().enumerate() {
        for (vi, v) in variants.iter().enumerate() {
            let out = &outcomes[ci * variants.len() + vi];
            let avg = |f: fn(&Outcome) -> f64| mean(&out.iter().map(f).collect::<Vec<_>>());
            means.row(&[
                name(c, v),
                format!("{:.3}", avg(|o| o.metrics.l1_rel)),
                format!("{:.4}", avg(|o| o.metrics.l1_inv)),
                format!("{:.3}", avg(|o| o.metrics.sc_inv)),
                format!("{:.1}", 100.0 * avg(|o| o.metrics.c_p)),
                format!("{:.2}", avg(|o| o.seconds)),
            ]);
        }
    }
    println!("Means over seeds {}:\n", a.seeds);
    means.print();
    Ok(())
}
