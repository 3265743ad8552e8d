//! `murk params`: airlight and scattering coefficient by Algorithm 1 (reference Ch. 3.3) from a
//! COLMAP model (sparse points + cameras) and its images, then the depth with them.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};

use murk::io::{read_image, DecodeLimits};
use murk::metrics::depth_metrics;
use murk::mvs::colmap::read_colmap_dir;
use murk::mvs_io::{
    backproject, find_gt_depth, find_scene_metadata, model_unit_in_scene_units, unit_note,
    write_ply, LoadedView, PlyFormat,
};
use murk::params::pose_error::SfmTracks;
use murk::params::sparse::PointSelection;
use murk_server::service::convert::{observations_to_proto, params_request_to_proto};
use murk_server::service::proto::v1 as pb;

use super::mvs::{
    load_views, print_metrics_header, print_metrics_row, reference_sparse_depth,
    run_here_or_remote, use_encoded_images, write_mvs_result,
};

/// Where the initial airlight comes from, as named on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AirlightArg {
    /// The server's configured estimator (the CNN unless configured otherwise).
    Server,
    /// The CNN of the reference's Table 3.1.
    Cnn,
    /// The dark-channel prior's brightest-pixel rule.
    DarkChannel,
    /// --airlight.
    Given,
}

impl AirlightArg {
    fn wire(self) -> pb::AirlightSource {
        match self {
            AirlightArg::Server => pb::AirlightSource::Unspecified,
            AirlightArg::Cnn => pb::AirlightSource::Cnn,
            AirlightArg::DarkChannel => pb::AirlightSource::DarkChannel,
            AirlightArg::Given => pb::AirlightSource::Given,
        }
    }
}

/// Options of `murk params`.
#[derive(Args, Debug)]
pub struct ParamsArgs {
    /// The images are sRGB-encoded (what most cameras write to 8-bit PNG and JPEG): decode them to
    /// linear light first, as the haze model needs; A is then reported in linear units.
    #[arg(long)]
    pub srgb: bool,
    /// COLMAP sparse model folder (cameras/images/points3D, .txt or .bin; detected).
    #[arg(long)]
    pub model: PathBuf,
    /// Folder holding the model's images.
    #[arg(long)]
    pub images: PathBuf,
    /// Name of the reference image, as in the model.
    #[arg(long)]
    pub reference: String,
    /// Source images by name, comma-separated (default: the --num-sources nearest cameras).
    #[arg(long, value_delimiter = ',', conflicts_with = "num_sources")]
    pub sources: Vec<String>,
    /// Number of source images picked by camera distance when --sources is not given.
    #[arg(long)]
    pub num_sources: Option<usize>,
    /// Initial airlight A0.
    #[arg(long, value_enum, default_value_t = AirlightArg::Server)]
    pub airlight_source: AirlightArg,
    /// A0 for --airlight-source given, in (0, 1].
    #[arg(long)]
    pub airlight: Option<f32>,
    /// Every SfM point in front of the reference camera, not only those whose track includes
    /// the reference image.
    #[arg(long)]
    pub all_points: bool,
    /// Lower end of the beta range, per model unit (default: from the SfM points, the beta that
    /// gives the median point a transmission of 0.98). An estimate below it is clamped and
    /// reported.
    #[arg(long)]
    pub beta_min: Option<f32>,
    /// Upper end of the beta range, per model unit (default: from the SfM points, the beta that
    /// gives the median point a transmission of 0.02).
    #[arg(long)]
    pub beta_max: Option<f32>,
    /// Values of beta in the first step (default 10).
    #[arg(long)]
    pub beta_steps: Option<u32>,
    /// Values per axis of the A x beta grid (default 4).
    #[arg(long)]
    pub grid_steps: Option<u32>,
    /// Always take beta0 from the sweep of Eq. 3.10 and refine it on the grid (the published
    /// Algorithm 1) instead of from the SfM points when they pin it down.
    #[arg(long)]
    pub beta_sweep: bool,
    /// Keep A = A0 from the estimator instead of fitting A, beta and a gain per source jointly
    /// to the SfM points' intensities (beta then comes from the points' ratios at A0).
    #[arg(long, conflicts_with = "beta_sweep")]
    pub no_joint_fit: bool,
    /// Planes of the final depth (default: about one per pixel of the largest displacement
    /// across the range); the range comes from the SfM points unless --near/--far are given.
    #[arg(long)]
    pub planes: Option<u32>,
    /// Nearest plane z-depth, scene units (with --far).
    #[arg(long, requires = "far")]
    pub near: Option<f64>,
    /// Farthest plane z-depth, scene units (with --near).
    #[arg(long, requires = "near")]
    pub far: Option<f64>,
    /// Output folder (created): params.json (A*, beta*, their standard errors,
    /// identifiability, units, the searches run), depth files as `murk mvs` writes them,
    /// residuals.csv.
    #[arg(long)]
    pub out: PathBuf,
    /// Take the SfM poses as exact: send no observations, so the standard errors leave out the
    /// poses' share (computed by default from where the model's points were seen in the views).
    #[arg(long)]
    pub no_pose_error: bool,
    /// Server URL; without it a server is started in this process.
    #[arg(long, env = "MURK_SERVER")]
    pub server: Option<String>,
}

/// Runs `murk params`.
pub fn run(a: ParamsArgs) -> anyhow::Result<()> {
    if (a.airlight_source == AirlightArg::Given) != a.airlight.is_some() {
        bail!("--airlight goes with --airlight-source given (and that needs --airlight)");
    }
    let model = read_colmap_dir(&a.model)
        .with_context(|| format!("reading the COLMAP model in {}", a.model.display()))?;
    let limits = DecodeLimits::default();
    let (reference, sources) = load_views(
        &model,
        &a.images,
        &a.reference,
        &a.sources,
        a.num_sources,
        &limits,
    )?;
    let selection = if a.all_points {
        PointSelection::All
    } else {
        PointSelection::ObservedInReference
    };
    let source_names: Vec<&str> = sources.iter().map(|s| s.name.as_str()).collect();
    let tracks = SfmTracks::from_colmap(&model, &reference.name, selection, &source_names)?;
    let points = &tracks.points;
    if points.is_empty() {
        bail!("the model has no 3D points");
    }
    let sparse = reference_sparse_depth(&model, &reference, selection)?;
    println!(
        "{} SfM points project into {} pixels of the reference view",
        points.len(),
        sparse.len()
    );
    let source_views: Vec<_> = sources.iter().map(LoadedView::view).collect();
    let mut request = params_request_to_proto(
        &reference.view(),
        &source_views,
        points,
        a.airlight_source.wire(),
        a.airlight.unwrap_or(0.0),
    );
    // The points' tracks: the fit samples a point only in the sources that saw it, and the
    // observations give the poses' uncertainty.
    if !a.no_pose_error {
        request.sparse_point_observations = observations_to_proto(&tracks);
    }
    request.sparse_point_sources = tracks.seen_by;
    use_encoded_images(
        request
            .reference
            .iter_mut()
            .chain(request.sources.iter_mut()),
        std::iter::once(&reference).chain(&sources),
        a.srgb,
    );
    request.beta_min = a.beta_min;
    request.beta_max = a.beta_max;
    request.beta_steps = a.beta_steps;
    if a.beta_sweep {
        request.beta_from_points = Some(false);
        request.joint_fit = Some(false);
    }
    if a.no_joint_fit {
        request.joint_fit = Some(false);
    }
    request.grid_steps = a.grid_steps;
    request.num_planes = a.planes.unwrap_or(0);
    request.near = a.near.unwrap_or(0.0);
    request.far = a.far.unwrap_or(0.0);
    let job_request = pb::JobRequest {
        method: Some(pb::job_request::Method::ScatteringParams(request)),
    };
    let (job, result) = run_here_or_remote(a.server.as_deref(), job_request, "params")?;
    let Some(pb::job_result::Method::ScatteringParams(r)) = result.method else {
        bail!("server returned a result of another method");
    };
    let depth = r.depth.as_ref().context("result lacks the depth")?;
    let images = write_mvs_result(&a.out, depth)?;
    write_residuals_csv(&a.out.join("residuals.csv"), &r)?;
    std::fs::write(
        a.out.join("params.json"),
        serde_json::to_string_pretty(&params_json(&r, &job.id))? + "\n",
    )
    .context("writing params.json")?;
    let cloud = backproject(
        &images.z_depth,
        &images.confidence,
        &reference.image,
        &reference.intrinsics,
        &reference.pose,
        0.0,
    )?;
    write_ply(
        &a.out.join("points.ply"),
        &cloud,
        PlyFormat::BinaryLittleEndian,
    )?;
    let pm = |v: Option<f64>| v.map_or(String::new(), |e| format!(" ± {e:.4}"));
    println!(
        "job {}{}: A* = {:.4}{}, beta* = {:.5}{} per model unit ({}; A0 = {:.4} from {}); \
         mean residual {:.4} model units over {} SfM pixels",
        &job.id[..12.min(job.id.len())],
        if job.cached { " (cached)" } else { "" },
        r.airlight,
        pm(r.airlight_std_error),
        r.beta,
        pm(r.beta_std_error),
        beta_source_name(r.beta_source),
        r.airlight_initial,
        source_name(r.airlight_source),
        r.residual,
        r.num_sparse_points
    );
    for w in &r.warnings {
        println!("warning: {w}");
    }
    if !r.identifiable {
        // A fitted beta* keeps its (wide) standard error; a swept one has none.
        let what = if r.beta_std_error.is_some() {
            "beta* is the points' best estimate, no better than its standard error says"
        } else {
            "beta* is a guess"
        };
        println!(
            "warning: beta is NOT identifiable from these views ({}); {what}",
            identifiability_text(r.identifiability)
        );
    }
    let bound = matches!(
        pb::BetaBound::try_from(r.beta_bound),
        Ok(pb::BetaBound::Min | pb::BetaBound::Max)
    );
    let range = format!(
        "[{:.5}, {:.5}]{}",
        r.beta_min,
        r.beta_max,
        if r.beta_range_from_points {
            " (from the SfM points)"
        } else {
            ""
        }
    );
    if bound && r.beta_unclamped != r.beta {
        println!(
            "warning: the estimate {:.5} lies outside the beta range {range} and was clamped to \
             {:.5}; widen --beta-min/--beta-max",
            r.beta_unclamped, r.beta
        );
    } else if bound {
        println!(
            "warning: the sweep's smallest residual lies at the end of the beta range {range}: the \
             minimum may lie beyond it"
        );
    }
    if let Some(j) = &r.joint_fit {
        println!(
            "joint fit of A, beta, the source gains and the lens fall-off: A {:.4} ± {:.4}, beta \
             {:.5} ± {:.5}, gains [{}], corners at {:.3} of the centre's brightness, over {} \
             equations from {} points (RMS depth difference {:.4} model units); {}",
            j.airlight,
            j.airlight_std_error,
            j.beta,
            j.beta_std_error,
            j.source_gains
                .iter()
                .map(|g| format!("{g:.3}"))
                .collect::<Vec<_>>()
                .join(", "),
            1.0 + j.vignetting_falloff,
            j.equations,
            j.points,
            j.rms_depth_difference,
            identifiability_text(j.identifiability)
        );
        if let Some(c) = super::source_corners(j.source_falloffs.iter().copied()) {
            println!(
                "joint fit: the sources' own lens fall-off, corners at {c} of the reference's"
            );
        }
    }
    if let Some(p) = &r.pose_error {
        let share = match (p.airlight_std_error, p.beta_std_error) {
            (Some(a), Some(b)) => format!("A ± {a:.4}, beta ± {b:.5} of the errors above"),
            _ => format!("not computed: {}", p.undetermined),
        };
        println!(
            "SfM poses: {} observations of {} points (reprojection error {:.2} px) place the \
             sources to within {:.2} degrees of rotation and {:.1} degrees of baseline direction \
             (1 sigma); their share: {share}",
            p.observations,
            p.points,
            p.reprojection_rms_px,
            p.max_rotation_std_deg,
            p.max_baseline_direction_std_deg
        );
    }
    if let Some(s) = &r.sampling {
        let share = match (s.airlight_std_error, s.beta_std_error) {
            (Some(a), Some(b)) => format!("A ± {a:.4}, beta ± {b:.5} of the errors above"),
            _ => "unknown: the refit failed".to_string(),
        };
        println!(
            "SfM keypoints: sampled with a {:.1} px blur instead of {:.1} px the fit moves; its \
             share: {share}",
            s.wide_blur_px, s.base_blur_px
        );
    }
    if let Some(p) = &r.relief {
        println!(
            "SfM points: {} in the reference lie a median {:.1} % of their depth off one plane \
             tilted {:.0} degrees from facing it{}",
            p.points,
            100.0 * p.relief,
            p.tilt_deg,
            if p.ambiguous {
                " (flat: the poses may be wrong with small errors)"
            } else {
                ""
            }
        );
    }
    println!(
        "times: airlight {:.3} s, search ({} depth evaluations) {:.2} s, final depth {:.2} s \
         ({} planes over z {:.3}..{:.3}); outputs in {}",
        r.airlight_seconds,
        r.grid.len(),
        r.search_seconds,
        r.depth_seconds,
        depth.num_planes,
        depth.near,
        depth.far,
        a.out.display()
    );
    if let Some(f) = &r.point_ratio {
        println!(
            "beta from the points' transmission ratios: {:.5} ± {:.5} over {} equations \
             (RMS depth difference {:.4}, {} sources, consistency chi2 {:.1}); {}",
            f.beta,
            f.std_error,
            f.equations,
            f.rms_depth_difference,
            f.sources,
            f.source_consistency_chi2,
            if f.used {
                "used as beta0"
            } else {
                "not reliable"
            }
        );
    }
    // Ground truth of a simulated scene, compared in one unit: a model reconstructed by SfM from
    // the simulator's images has its own scale, measured here from the SfM points against the
    // ground-truth depth at their pixels (β per model unit = β per scene unit × the scale).
    let meta = find_scene_metadata(&a.model)?;
    let gt = match find_gt_depth(&a.images, &reference.name) {
        Some(p) => Some(
            read_image(&p, &limits)
                .with_context(|| format!("reading ground truth {}", p.display()))?,
        ),
        None => None,
    };
    let scale = gt
        .as_ref()
        .and_then(|g| model_unit_in_scene_units(&sparse, g));
    if let Some(meta) = &meta {
        let s = f64::from(scale.unwrap_or(1.0));
        println!(
            "ground truth ({}): A = {:.4} (error {:+.4}), beta = {:.5} per model unit (error \
             {:+.5}){}",
            meta.path.display(),
            meta.atmosphere.airlight,
            r.airlight - meta.atmosphere.airlight,
            f64::from(meta.atmosphere.beta) * s,
            f64::from(r.beta) - f64::from(meta.atmosphere.beta) * s,
            unit_note(scale)
        );
    }
    if let Some(gt) = &gt {
        let mut z = images.z_depth.clone();
        let s = scale.unwrap_or(1.0);
        for v in z.data_mut() {
            *v *= s;
        }
        let m = depth_metrics(&z, gt, None)?;
        print_metrics_header();
        print_metrics_row("estimated", &m, r.depth_seconds, &unit_note(scale));
    }
    Ok(())
}

/// What `params.json` holds: the estimates with their errors, identifiability, the β range
/// and whether it bound, the units, and every evaluation of the search.
fn params_json(r: &pb::ScatteringParamsResult, job_id: &str) -> serde_json::Value {
    let bound = match pb::BetaBound::try_from(r.beta_bound) {
        Ok(pb::BetaBound::Min) => "min",
        Ok(pb::BetaBound::Max) => "max",
        _ => "none",
    };
    serde_json::json!({
        "format": "murk.scattering_params",
        "version": 1,
        "job_id": job_id,
        "airlight": r.airlight,
        "airlight_std_error": r.airlight_std_error,
        "beta": r.beta,
        "beta_std_error": r.beta_std_error,
        "identifiable": r.identifiable,
        "identifiability": identifiability_name(r.identifiability),
        "beta_source": beta_source_name(r.beta_source),
        "beta_range": {
            "min": r.beta_min,
            "max": r.beta_max,
            "from_points": r.beta_range_from_points,
            "bound": bound,
            "beta_unclamped": r.beta_unclamped,
        },
        "airlight_initial": r.airlight_initial,
        "airlight_source": source_name(r.airlight_source),
        "joint_fit": r.joint_fit.as_ref().map(joint_fit_json),
        "airlight_conflict": r.airlight_conflict.as_ref().map(|c| serde_json::json!({
            "fitted_airlight": c.fitted_airlight,
            "fitted_airlight_std_error": c.fitted_airlight_std_error,
            "airlight_initial": c.airlight_initial,
            "airlight_initial_error": c.airlight_initial_error,
            "sigmas": c.sigmas,
        })),
        "warnings": r.warnings,
        "pose_error": r.pose_error.as_ref().map(|p| serde_json::json!({
            "airlight_std_error": p.airlight_std_error,
            "beta_std_error": p.beta_std_error,
            "observations": p.observations,
            "points": p.points,
            "reprojection_rms_px": p.reprojection_rms_px,
            "max_rotation_std_deg": finite_or_null(p.max_rotation_std_deg),
            "max_baseline_direction_std_deg": finite_or_null(p.max_baseline_direction_std_deg),
            "undetermined": (!p.undetermined.is_empty()).then_some(&p.undetermined),
        })),
        "sampling": r.sampling.as_ref().map(|s| serde_json::json!({
            "base_blur_px": s.base_blur_px,
            "wide_blur_px": s.wide_blur_px,
            "refit_airlight": s.refit_airlight,
            "refit_beta": s.refit_beta,
            "airlight_std_error": s.airlight_std_error,
            "beta_std_error": s.beta_std_error,
        })),
        "relief": r.relief.as_ref().map(|p| serde_json::json!({
            "points": p.points,
            "relief": p.relief,
            "tilt_deg": p.tilt_deg,
            "ambiguous": p.ambiguous,
        })),
        "point_ratio": r.point_ratio.as_ref().map(|f| serde_json::json!({
            "beta": f.beta,
            "std_error": finite_or_null(f.std_error),
            "equations": f.equations,
            "used": f.used,
        })),
        "residual": r.residual,
        "sparse_pixels": r.num_sparse_points,
        "searches": r.grid.iter().map(|g| serde_json::json!({
            "stage": stage_name(g.stage),
            "airlight": g.airlight,
            "beta": g.beta,
            "residual": g.residual,
        })).collect::<Vec<_>>(),
        "seconds": {
            "airlight": r.airlight_seconds,
            "search": r.search_seconds,
            "depth": r.depth_seconds,
        },
        "units": {
            "airlight": "pixel value, [0, 1]",
            "beta": "per model unit (the COLMAP model's length unit; per metre for a metric model)",
            "residual": "model units (mean |z - z_sfm| of Eq. 3.9)",
            "depth": "z-depth, model units",
        },
    })
}

fn joint_fit_json(j: &pb::JointFit) -> serde_json::Value {
    serde_json::json!({
        "airlight": j.airlight,
        "airlight_std_error": j.airlight_std_error,
        "beta": j.beta,
        "beta_std_error": finite_or_null(j.beta_std_error),
        "source_gains": j.source_gains,
        "vignetting_falloff": j.vignetting_falloff,
        "source_falloffs": j.source_falloffs,
        "equations": j.equations,
        "points": j.points,
        "rms_depth_difference": j.rms_depth_difference,
        "residual_scale": j.residual_scale,
        "identifiability": identifiability_name(j.identifiability),
    })
}

/// Name of a search stage in `params.json` and `residuals.csv`.
fn stage_name(v: i32) -> &'static str {
    match pb::SearchStage::try_from(v) {
        Ok(pb::SearchStage::Beta) => "beta",
        Ok(pb::SearchStage::Joint) => "joint",
        _ => "unknown",
    }
}

fn finite_or_null(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

fn identifiability_name(v: i32) -> &'static str {
    match pb::Identifiability::try_from(v) {
        Ok(pb::Identifiability::Identifiable) => "identifiable",
        Ok(pb::Identifiability::NoDepthDifference) => "no_depth_difference",
        Ok(pb::Identifiability::TooFewPoints) => "too_few_points",
        Ok(pb::Identifiability::FlatResidual) => "flat_residual",
        Ok(pb::Identifiability::AirlightConflict) => "airlight_conflict",
        Ok(pb::Identifiability::AirlightAtBound) => "airlight_at_bound",
        Ok(pb::Identifiability::WeakSfm) => "weak_sfm",
        _ => "unknown",
    }
}

fn identifiability_text(v: i32) -> &'static str {
    match pb::Identifiability::try_from(v) {
        Ok(pb::Identifiability::Identifiable) => "beta determined",
        Ok(pb::Identifiability::NoDepthDifference) => {
            "the views see every point at the same depth (a rectified pair or sideways motion), \
             so every beta explains them equally"
        }
        Ok(pb::Identifiability::TooFewPoints) => "too few usable SfM points",
        Ok(pb::Identifiability::FlatResidual) => "the points' residual is too flat in beta",
        Ok(pb::Identifiability::AirlightConflict) => {
            "the points' A conflicts with the image's airlight estimate: the SfM model may be wrong"
        }
        Ok(pb::Identifiability::AirlightAtBound) => {
            "the points' A sits on the bound of its range, so its error and beta's do not hold"
        }
        Ok(pb::Identifiability::WeakSfm) => {
            "the SfM input (its poses, where it put its points, a flat cloud) cannot pin beta down"
        }
        _ => "unknown",
    }
}

fn beta_source_name(v: i32) -> &'static str {
    match pb::BetaSource::try_from(v) {
        Ok(pb::BetaSource::JointFit) => "joint fit of A, beta and gains to the points",
        Ok(pb::BetaSource::PointRatio) => "the points' ratios at A0",
        Ok(pb::BetaSource::Sweep) => "the sweep of Eq. 3.10",
        _ => "unknown",
    }
}

/// `stage,airlight,beta,residual` per evaluation.
fn write_residuals_csv(path: &Path, r: &pb::ScatteringParamsResult) -> anyhow::Result<()> {
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
    );
    writeln!(f, "stage,airlight,beta,residual")?;
    for g in &r.grid {
        writeln!(
            f,
            "{},{},{},{}",
            stage_name(g.stage),
            g.airlight,
            g.beta,
            g.residual
        )?;
    }
    f.flush()?;
    Ok(())
}

/// Display name of a wire airlight source.
pub fn source_name(v: i32) -> &'static str {
    match pb::AirlightSource::try_from(v) {
        Ok(pb::AirlightSource::Cnn) => "the CNN",
        Ok(pb::AirlightSource::DarkChannel) => "the dark channel",
        Ok(pb::AirlightSource::Given) => "the request",
        _ => "unknown",
    }
}
