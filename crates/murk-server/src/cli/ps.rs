//! `murk ps`: photometric stereo in turbid media (reference Ch. 4) on a capture folder.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Args, ValueEnum};

use murk::image::ImageF32;
use murk::io::{write_colormap_png, write_exr, write_png_rgb8};
use murk::metrics::mean_angular_error_deg;
use murk::ps::mesh::{depth_mesh, encode_ply_mesh};
use murk::ps::physics::{FacetEmission, FarField};
use murk::ps::DistanceMode;
use murk::ps::{PsMode, PsParams, PsResult};
use murk::simulate::ps::read_ps_capture;
use murk_server::service::convert::{ps_from_result, ps_request_to_proto};
use murk_server::service::proto::v1 as pb;

use super::mvs::run_here_or_remote;

/// Which scattering effects to remove, as named on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ModeArg {
    /// Backscatter, surface-camera and source-surface forward scatter (the reference's method).
    Full,
    /// Backscatter subtraction and attenuation only (the baseline [15]).
    BackscatterOnly,
}

/// `--far-field`: how the scatter from outside the kernel support is modelled.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum FarFieldArg {
    /// κ_p·(Σ of dA_q·L_s(q) outside p's support), κ_p computed per kernel build: exact for
    /// uniform L_s only (murk's default before the blocks).
    PerPixel,
    /// The reference's constant C = ε·Σ_q L_s(q) with ε from Eq. 4.53.
    ConstantEpsilon,
    /// The outside of the support summed on coarse blocks inside the operator (murk's default):
    /// follows L_s whatever it is.
    Blocks,
}

/// `--facet-emission`: how a surface facet radiates into the medium.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum FacetEmissionArg {
    /// L_s·dA·cos θ, the physics of a Lambertian surface (murk's default).
    Lambertian,
    /// L_s·dA in every direction: Eq. 4.41 as published.
    Isotropic,
}

impl From<FacetEmissionArg> for FacetEmission {
    fn from(a: FacetEmissionArg) -> Self {
        match a {
            FacetEmissionArg::Lambertian => FacetEmission::Lambertian,
            FacetEmissionArg::Isotropic => FacetEmission::Isotropic,
        }
    }
}

/// Options of `murk ps`.
#[derive(Args, Debug)]
pub struct PsArgs {
    /// Capture folder in the layout of `murk simulate ps` (meta.json, image_*.exr,
    /// background_*.exr, mask.png); see docs/photometric-stereo.md for bringing your own captures.
    #[arg(long)]
    pub capture: PathBuf,
    /// Output folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Server URL; default: run a server in this process.
    #[arg(long)]
    pub server: Option<String>,
    /// z-distance of the initial plane, mm: the mean z-depth of the object's visible surface
    /// (default: meta.json's initial_distance_mm; without either murk searches for it). murk
    /// fits the distance to the lights' 1/d² fall-off, so this is a starting guess unless
    /// --fix-distance is given.
    #[arg(long)]
    pub initial_distance_mm: Option<f64>,
    /// Kernel support r (odd).
    #[arg(long, default_value_t = 61)]
    pub support_r: usize,
    /// Let the server choose r from the object's size (≈ 0.55 × the mask's larger side) and,
    /// unless --far-cell is given, the far cell.
    #[arg(long, conflicts_with = "support_r")]
    pub auto_support: bool,
    /// Far-field cell size of the kernel, pixels (1 = the reference's exact r×r window;
    /// default 3, or chosen by the server with --auto-support).
    #[arg(long)]
    pub far_cell: Option<usize>,
    /// Radius within which the kernel is kept per pixel, pixels.
    #[arg(long, default_value_t = murk::ps::pipeline::DEFAULT_NEAR_RADIUS_PX)]
    pub near_radius_px: usize,
    /// Iteration cap.
    #[arg(long, default_value_t = 5)]
    pub iterations: usize,
    /// Stop when the mean depth change falls below this fraction (0 = run every iteration).
    #[arg(long, default_value_t = 1e-3)]
    pub tolerance: f64,
    /// Reuse an earlier iteration's kernel while the shape has moved less than this fraction of
    /// its mean depth since it was built (0 = rebuild it every iteration).
    #[arg(long, default_value_t = 1e-3)]
    pub kernel_rebuild_tolerance: f64,
    /// Full model or the backscatter-only baseline.
    #[arg(long, value_enum, default_value_t = ModeArg::Full)]
    pub mode: ModeArg,
    /// Keep Eq. 4.55's linearisation G(T, n·l) ≈ G(T, 1)·n·l (the reference as published)
    /// instead of refining normals on the exact G.
    #[arg(long)]
    pub linear_g: bool,
    /// Model of the forward scatter from outside the support.
    #[arg(long, value_enum, default_value_t = FarFieldArg::Blocks)]
    pub far_field: FarFieldArg,
    /// How a facet radiates into the medium in the surface-camera forward scatter.
    #[arg(long, value_enum, default_value_t = FacetEmissionArg::Lambertian)]
    pub facet_emission: FacetEmissionArg,
    /// Keep the mean depth at --initial-distance-mm instead of estimating it (the reference as
    /// published).
    #[arg(long)]
    pub fix_distance: bool,
    /// Do not add back the backscatter beyond the surface that the no-object image's
    /// subtraction removed in excess (the reference as published).
    #[arg(long)]
    pub no_backscatter_tail: bool,
}

/// Runs `murk ps`.
pub fn run(a: PsArgs) -> anyhow::Result<()> {
    let folder = read_ps_capture(&a.capture)
        .with_context(|| format!("reading capture {}", a.capture.display()))?;
    let initial = a.initial_distance_mm.or(folder.initial_distance_mm);
    if initial.is_none() {
        anyhow::ensure!(
            !a.fix_distance,
            "--fix-distance needs a distance: pass --initial-distance-mm (meta.json has none)"
        );
        println!("no initial distance given: murk searches for it from the lights' fall-off");
    }
    let initial = initial.unwrap_or(0.0);
    let params = PsParams {
        initial_distance_mm: initial,
        support_r: a.support_r,
        far_cell: a.far_cell.unwrap_or(murk::ps::pipeline::DEFAULT_FAR_CELL),
        near_radius_px: a.near_radius_px,
        max_iterations: a.iterations,
        tolerance: a.tolerance,
        kernel_rebuild_tolerance: a.kernel_rebuild_tolerance,
        mode: match a.mode {
            ModeArg::Full => PsMode::Full,
            ModeArg::BackscatterOnly => PsMode::BackscatterOnly,
        },
        exact_g: !a.linear_g,
        far_field: match a.far_field {
            FarFieldArg::PerPixel => FarField::PerPixel,
            FarFieldArg::ConstantEpsilon => FarField::ConstantEpsilon,
            FarFieldArg::Blocks => FarField::Blocks,
        },
        facet_emission: a.facet_emission.into(),
        backscatter_tail: !a.no_backscatter_tail,
        distance: if a.fix_distance {
            DistanceMode::Fixed
        } else {
            DistanceMode::Estimate
        },
        ..PsParams::default()
    };
    let mut request = ps_request_to_proto(&folder.capture, &params);
    request.return_iteration_normals = folder.gt_normals.is_some();
    if a.auto_support {
        request.auto_support = true;
        request.support_r = 0;
        if a.far_cell.is_none() {
            request.far_cell = 0;
        }
    }
    let (job, result) = run_here_or_remote(
        a.server.as_deref(),
        pb::JobRequest {
            method: Some(pb::job_request::Method::PhotometricStereo(request)),
        },
        "ps",
    )?;
    let Some(pb::job_result::Method::PhotometricStereo(r)) = result.method else {
        anyhow::bail!("the server returned a result of another method");
    };
    let out = ps_from_result(&r, &folder.capture.mask)?;
    write_ps_result(&a.out, &folder.capture.intrinsics, &out)?;
    print_iteration_table(&out, folder.gt_normals.as_deref());
    println!(
        "kernel support r = {} px, far cell {} px",
        out.support_r, out.far_cell
    );
    print_distance(&out);
    println!(
        "job {}{}: {:.2} s; wrote {}",
        job.id,
        if job.cached { " (cached)" } else { "" },
        out.total_s,
        a.out.display()
    );
    Ok(())
}

/// Writes normals (EXR + PNG), albedo, depth (EXR + colour-mapped PNG) and a PLY mesh.
pub fn write_ps_result(
    dir: &Path,
    intr: &murk::camera::Intrinsics,
    out: &PsResult,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let (w, h) = (out.width, out.height);
    write_exr(
        &dir.join("normals.exr"),
        &ImageF32::from_vec(w, h, 3, out.normals.iter().flatten().copied().collect())?,
    )?;
    // The usual normal-map colouring: RGB = (n + 1) / 2 with y flipped to point up and z
    // towards the viewer, so a sphere looks as in the reference's figures.
    let rgb: Vec<u8> = out
        .normals
        .iter()
        .zip(&out.mask)
        .flat_map(|(n, &m)| {
            if m {
                [n[0], -n[1], -n[2]]
                    .map(|c| ((c + 1.0) * 0.5 * 255.0).round().clamp(0.0, 255.0) as u8)
            } else {
                [0, 0, 0]
            }
        })
        .collect();
    write_png_rgb8(&dir.join("normals.png"), w, h, &rgb)?;
    write_exr(
        &dir.join("albedo.exr"),
        &ImageF32::from_vec(w, h, 1, out.albedo.clone())?,
    )?;
    let depth = ImageF32::from_vec(w, h, 1, out.depth_mm.clone())?;
    write_exr(&dir.join("depth_mm.exr"), &depth)?;
    let finite: Vec<f32> = out
        .depth_mm
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    let lo = finite.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = finite.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    if lo.is_finite() && hi > lo {
        let mask = ImageF32::from_vec(
            w,
            h,
            1,
            out.mask
                .iter()
                .map(|&b| if b { 1.0 } else { 0.0 })
                .collect(),
        )?;
        write_colormap_png(&dir.join("depth.png"), &depth, lo, hi, Some(&mask))?;
    }
    let (v, n, f) = depth_mesh(intr, w, &out.depth_mm, &out.normals, &out.mask);
    std::fs::write(dir.join("mesh.ply"), encode_ply_mesh(&v, &n, &f))
        .with_context(|| format!("writing {}", dir.join("mesh.ply").display()))?;
    Ok(())
}

/// Says where the object's distance came from and warns when a fit hit its search range.
pub fn print_distance(out: &PsResult) {
    if let Some(f) = &out.initial_distance_fit {
        println!(
            "initial distance searched: {:.1} mm ({} px){}",
            f.mean_depth_mm,
            f.pixels,
            if f.at_bound {
                " — at the end of the search range, the distance is not reliable"
            } else {
                ""
            }
        );
    }
    let fits: Vec<_> = out
        .iterations
        .iter()
        .filter_map(|s| s.distance_fit)
        .collect();
    match fits.last() {
        None => println!("distance fixed at the initial distance (not estimated)"),
        Some(f) => {
            println!(
                "distance fitted to the lights' 1/d² fall-off: mean z {:.1} mm (relative residual \
                 {:.2e}, {} px)",
                f.mean_depth_mm, f.objective, f.pixels
            );
            if fits.iter().any(|f| f.at_bound) {
                println!(
                    "warning: a distance fit ended at its search range (±60 % per iteration); \
                     check the initial distance and the light positions"
                );
            }
        }
    }
}

/// Prints one row per iteration; with ground truth also the mean angular error of that
/// iteration's normals (the reference's Table 4.1).
pub fn print_iteration_table(out: &PsResult, gt: Option<&[[f32; 3]]>) {
    println!(
        "{:>4} {:>10} {:>10} {:>12} {:>9} {:>8} {:>8} {:>8}",
        "iter", "error [°]", "Δz/z", "mean z [mm]", "BiCGStab", "K [s]", "solve [s]", "rest [s]"
    );
    for (k, s) in out.iterations.iter().enumerate() {
        let err = match (gt, out.normals_history.get(k)) {
            (Some(gt), Some(n)) => mean_angular_error_deg(n, gt, &out.mask)
                .map(|e| format!("{e:.2}"))
                .unwrap_or_else(|_| "-".into()),
            _ => "-".into(),
        };
        let iters = s.solver_iterations.iter().max().copied().unwrap_or(0);
        let kernel = if s.kernel_reused {
            "reused".to_string()
        } else {
            format!("{:.2}", s.kernel_s)
        };
        println!(
            "{:>4} {:>10} {:>10.4} {:>12.1} {:>9} {:>8} {:>8.2} {:>8.2}",
            s.iteration,
            err,
            s.relative_depth_change,
            s.mean_depth_mm,
            iters,
            kernel,
            s.solve_s,
            s.normals_s + s.integrate_s + s.tail_s
        );
    }
}
