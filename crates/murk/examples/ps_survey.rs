//! Photometric stereo in turbid water (reference Ch. 4) on the simulator's scenes, in the
//! reference's synthetic setting (§4.4.1: 300×300, f = 550 px, β = σ = 5·10⁻³ /mm, 8 lights on a
//! 120 mm ring, noise-free), started from a fronto-parallel plane and run for 5 iterations.
//!
//! For each shape it prints the reference's Table 4.1: the mean angular error of the normals
//! after each iteration, for murk's defaults from every start given by `--init`, and from the
//! true mean depth for the backscatter-only baseline of Tsiotsios et al.; then one iteration from
//! the true shape (the reference's "input GT"); each with the depth error and the final mean
//! depth. A summary table
//! follows: the error after the last iteration per shape and start. `--variants` adds one row per
//! alternative model (one setting changed from the defaults, and the published model as a whole);
//! `--error-floors` adds the normal solve's error on the simulator's true reflected component.
//!
//! ```sh
//! cargo run --release -p murk --example ps_survey -- --shape sphere,bumps,vase --init 1.0,0.8,0.9,1.1,1.2,0
//! cargo run --release -p murk --example ps_survey -- --shape sphere --variants --error-floors
//! cargo run --release -p murk --example ps_survey -- --side 96 --support-r 25   # a quick look
//! ```

mod common;

use std::time::Instant;

use anyhow::Context;
use clap::{Parser, ValueEnum};

use common::Table;
use murk::metrics::mean_angular_error_deg;
use murk::ps::near_light::{solve_normals, ShadingModel};
use murk::ps::physics::{FacetEmission, FarField, GTable};
use murk::ps::pipeline::back_project;
use murk::ps::{photometric_stereo, DistanceMode, PsMode, PsParams, PsResult};
use murk::simulate::ps::{simulate_ps, PsShape, PsSimCapture, PsSimConfig};
use murk::Monitor;

/// The simulated object.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum ShapeArg {
    /// A sphere of radius 50 mm at 250 mm (the reference's object).
    Sphere,
    /// A sphere whose radius varies by ±6 %.
    Bumps,
    /// A surface of revolution with concave parts and cast shadows.
    Vase,
}

impl ShapeArg {
    fn shape(self) -> PsShape {
        match self {
            Self::Sphere => PsShape::Sphere,
            Self::Bumps => PsShape::Bumps,
            Self::Vase => PsShape::Vase,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Sphere => "sphere",
            Self::Bumps => "bumps",
            Self::Vase => "vase",
        }
    }
}

/// Photometric stereo in turbid water on the simulator's scenes: the reference's Table 4.1.
#[derive(Parser)]
struct Args {
    /// Objects to simulate, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "sphere")]
    shape: Vec<ShapeArg>,
    /// Image side, pixels; the focal length scales with it, so the object keeps its share of the
    /// frame (300 is the reference's setting).
    #[arg(long, default_value_t = 300)]
    side: usize,
    /// Kernel support r (odd): the side of the window K̂ keeps around each pixel (Eq. 4.51).
    #[arg(long, default_value_t = 81)]
    support_r: usize,
    /// Give the object a smooth albedo pattern (0.6 ± 40 %) instead of a uniform 0.8.
    #[arg(long)]
    textured: bool,
    /// Starting distances as factors of the true mean depth of the visible surface,
    /// comma-separated; 0 gives no distance (murk searches for it).
    #[arg(long, value_delimiter = ',', default_value = "1.0")]
    init: Vec<f64>,
    /// Also run, from the true mean depth, each alternative model: one setting changed from the
    /// defaults, and the published model (all of the reference's choices together).
    #[arg(long)]
    variants: bool,
    /// Also print the normal solve's error on the simulator's true reflected component and
    /// true shape: the floor of the photometric step with Eq. 4.55's linear G and the exact G.
    #[arg(long)]
    error_floors: bool,
}

/// Iterations per run (the reference's Table 4.1 has 5).
const ITERATIONS: usize = 5;

/// Mean |z − z_gt| over the mask, mm.
fn depth_mae_mm(depth: &[f32], gt: &[f32], mask: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for ((d, g), &m) in depth.iter().zip(gt).zip(mask) {
        if m {
            sum += f64::from((d - g).abs());
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// One run's figures.
struct Run {
    errors_deg: Vec<f64>,
    depth_mae_mm: f64,
    mean_z_mm: f64,
    seconds: f64,
}

fn run(sim: &PsSimCapture, params: &PsParams) -> anyhow::Result<Run> {
    let t = Instant::now();
    let out: PsResult = photometric_stereo(&sim.capture, params, &Monitor::noop())?;
    let seconds = t.elapsed().as_secs_f64();
    let mask = &sim.capture.mask;
    let errors_deg = out
        .normals_history
        .iter()
        .map(|n| mean_angular_error_deg(n, &sim.gt_normals, mask))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Run {
        errors_deg,
        depth_mae_mm: depth_mae_mm(&out.depth_mm, &sim.gt_depth_mm, mask),
        mean_z_mm: out.iterations.last().map_or(f64::NAN, |s| s.mean_depth_mm),
        seconds,
    })
}

/// The alternative models of `--variants`: each changes one of murk's defaults to the
/// reference's published choice (or to murk's per-pixel far field), and the last changes all of
/// the published ones together.
fn variants(base: &PsParams) -> Vec<(&'static str, PsParams)> {
    vec![
        (
            "per-pixel far field (exact for uniform L_s only)",
            PsParams {
                far_field: FarField::PerPixel,
                ..base.clone()
            },
        ),
        (
            "Eq. 4.52 constant ε",
            PsParams {
                far_field: FarField::ConstantEpsilon,
                ..base.clone()
            },
        ),
        (
            "Eq. 4.41 isotropic facet",
            PsParams {
                facet_emission: FacetEmission::Isotropic,
                ..base.clone()
            },
        ),
        (
            "Eq. 4.55 linear G",
            PsParams {
                exact_g: false,
                ..base.clone()
            },
        ),
        (
            "no backscatter tail",
            PsParams {
                backscatter_tail: false,
                ..base.clone()
            },
        ),
        (
            "distance fixed at the start",
            PsParams {
                distance: DistanceMode::Fixed,
                ..base.clone()
            },
        ),
        (
            "as published: constant ε, isotropic facet, linear G, no tail, fixed distance",
            PsParams {
                far_field: FarField::ConstantEpsilon,
                facet_emission: FacetEmission::Isotropic,
                exact_g: false,
                backscatter_tail: false,
                distance: DistanceMode::Fixed,
                ..base.clone()
            },
        ),
    ]
}

/// The normal solve (Eq. 4.57) on the simulator's true reflected component at the true shape,
/// with each shading model, linear and refined on the exact G.
fn error_floors(sim: &PsSimCapture) -> anyhow::Result<Table> {
    let cap = &sim.capture;
    let (w, _) = cap.dims();
    let points = back_project(&cap.intrinsics, w, &sim.gt_depth_mm, &cap.mask);
    let mut table = Table::new(&["shading model", "normals", "mean angular error (°)"]);
    // Direct light alone has no G to refine, so it gets one row.
    for (model, refine) in [
        (ShadingModel::ForwardScatter, false),
        (ShadingModel::ForwardScatter, true),
        (ShadingModel::DirectOnly, false),
    ] {
        let est = solve_normals(
            &sim.gt_reflected,
            &cap.lights,
            &cap.medium,
            GTable::global(),
            model,
            &points,
            &cap.mask,
            w,
            PsParams::default().shadow_ratio,
            refine,
        );
        let err = mean_angular_error_deg(&est.normals, &sim.gt_normals, &cap.mask)?;
        table.row(&[
            match model {
                ShadingModel::ForwardScatter => "direct + source-surface forward scatter",
                ShadingModel::DirectOnly => "direct light only (the baseline's)",
            }
            .to_string(),
            match (model, refine) {
                (ShadingModel::DirectOnly, _) => "Eq. 4.57 without G",
                (_, true) => "refined on the exact G (murk)",
                (_, false) => "Eq. 4.55 linear G (as published)",
            }
            .to_string(),
            format!("{err:.3}"),
        ]);
    }
    Ok(table)
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    anyhow::ensure!(
        args.init.iter().all(|f| f.is_finite() && *f >= 0.0),
        "--init: factors must be finite and >= 0"
    );
    let starts = |f: f64| {
        if f == 0.0 {
            "none".to_string()
        } else if f.fract() == 0.0 {
            format!("{f:.1}×")
        } else {
            format!("{f}×")
        }
    };
    println!(
        "{}×{} px, β = σ = 5e-3 /mm, 8 lights, r = {}, far cells {}×{}, {} iterations, {} albedo",
        args.side,
        args.side,
        args.support_r,
        murk::ps::pipeline::DEFAULT_FAR_CELL,
        murk::ps::pipeline::DEFAULT_FAR_CELL,
        ITERATIONS,
        if args.textured {
            "textured (0.6 ± 40 %)"
        } else {
            "uniform 0.8"
        }
    );
    let mut summary_header = vec!["shape (true mean z)".to_string()];
    summary_header.extend(args.init.iter().map(|&f| format!("start {}", starts(f))));
    let mut summary = Table::new(&summary_header);
    for &shape in &args.shape {
        let defaults = PsSimConfig::default();
        let cfg = PsSimConfig {
            shape: shape.shape(),
            textured: args.textured,
            // The ±40 % pattern must keep the albedo ≤ 1.
            albedo: if args.textured { 0.6 } else { defaults.albedo },
            ..PsSimConfig::with_size(args.side, args.side)
        };
        let sim = simulate_ps(&cfg, &Monitor::noop())
            .with_context(|| format!("simulating the {}", shape.name()))?;
        let truth = sim.initial_distance_mm;
        let object_px = sim.capture.mask.iter().filter(|&&b| b).count();
        println!(
            "\n{}: {object_px} object px, true mean z {truth:.1} mm\n",
            shape.name()
        );
        let base = PsParams {
            support_r: args.support_r,
            max_iterations: ITERATIONS,
            // Every iteration runs, so each column is the same iteration for every row.
            tolerance: 0.0,
            ..PsParams::default()
        };
        let mut header = vec!["method".to_string(), "start".to_string()];
        header.extend((1..=ITERATIONS).map(|i| i.to_string()));
        header.extend(["depth MAE (mm)", "mean z (mm)", "time (s)"].map(String::from));
        let mut table = Table::new(&header);
        let add = |table: &mut Table, name: &str, start: String, r: &Run| {
            let mut cells = vec![name.to_string(), start];
            cells.extend((0..ITERATIONS).map(|i| {
                r.errors_deg
                    .get(i)
                    .map_or(String::new(), |e| format!("{e:.2}"))
            }));
            cells.push(format!("{:.2}", r.depth_mae_mm));
            cells.push(format!("{:.1}", r.mean_z_mm));
            cells.push(format!("{:.1}", r.seconds));
            table.row(&cells);
        };
        let mut summary_row = vec![format!("{} ({truth:.1} mm)", shape.name())];
        for &f in &args.init {
            let params = PsParams {
                initial_distance_mm: truth * f,
                ..base.clone()
            };
            let r = run(&sim, &params)?;
            add(&mut table, "full (murk's defaults)", starts(f), &r);
            summary_row.push(format!(
                "{:.2}°, {:.2} mm, {:.1}",
                r.errors_deg.last().copied().unwrap_or(f64::NAN),
                r.depth_mae_mm,
                r.mean_z_mm
            ));
        }
        summary.row(&summary_row);
        // The comparison rows start from the true mean depth, as the reference's table does.
        let from_truth = PsParams {
            initial_distance_mm: truth,
            ..base.clone()
        };
        let baseline = PsParams {
            mode: PsMode::BackscatterOnly,
            ..from_truth.clone()
        };
        add(
            &mut table,
            "backscatter only (Tsiotsios et al.)",
            starts(1.0),
            &run(&sim, &baseline)?,
        );
        let input_gt = PsParams {
            initial_distance_mm: truth,
            initial_depth_mm: Some(sim.gt_depth_mm.clone()),
            max_iterations: 1,
            ..base.clone()
        };
        add(
            &mut table,
            "full, 1 iteration from the true shape (input GT)",
            "true shape".into(),
            &run(&sim, &input_gt)?,
        );
        if args.variants {
            for (name, params) in variants(&from_truth) {
                add(&mut table, name, starts(1.0), &run(&sim, &params)?);
            }
        }
        println!("Mean angular error of the normals (°) after each iteration:\n");
        table.print();
        if args.error_floors {
            println!(
                "\nNormals from the simulator's true reflected component at the true shape:\n"
            );
            error_floors(&sim)?.print();
        }
    }
    println!(
        "\nAfter {ITERATIONS} iterations (mean angular error, depth MAE, final mean z in mm):\n"
    );
    summary.print();
    Ok(())
}
