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
    backproject, find_gt_depth, find_scene_metadata, write_ply, LoadedView, PlyFormat,
};
use murk::params::sparse::{selected_points, PointSelection, SparseDepth};
use murk::service::convert::params_request_to_proto;
use murk::service::proto::v1 as pb;

use super::mvs::{
    load_views, print_metrics_header, print_metrics_row, run_here_or_remote, use_encoded_images,
    write_mvs_result,
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
    /// Lower end of the beta search range, per scene unit (default 0.4).
    #[arg(long)]
    pub beta_min: Option<f32>,
    /// Upper end of the beta search range, per scene unit (default 0.8).
    #[arg(long)]
    pub beta_max: Option<f32>,
    /// Values of beta in the first step (default 10).
    #[arg(long)]
    pub beta_steps: Option<u32>,
    /// Values per axis of the A x beta grid (default 4).
    #[arg(long)]
    pub grid_steps: Option<u32>,
    /// Always take beta0 from the sweep of Eq. 3.10 and refine it on the grid (the published
    /// Algorithm 1) instead of from the SfM points' transmission ratios when they pin it down.
    #[arg(long)]
    pub beta_sweep: bool,
    /// Planes of the final depth (default 256); the range comes from the SfM points unless
    /// --near/--far are given.
    #[arg(long)]
    pub planes: Option<u32>,
    /// Nearest plane z-depth, scene units (with --far).
    #[arg(long, requires = "far")]
    pub near: Option<f64>,
    /// Farthest plane z-depth, scene units (with --near).
    #[arg(long, requires = "near")]
    pub far: Option<f64>,
    /// Output folder (created): depth files as `murk mvs` writes them, residuals.csv.
    #[arg(long)]
    pub out: PathBuf,
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
    let points = selected_points(&model, &reference.name, selection)?;
    if points.is_empty() {
        bail!("the model has no 3D points");
    }
    println!(
        "{} SfM points project into {} pixels of the reference view",
        points.len(),
        SparseDepth::from_points(
            &points,
            &reference.intrinsics,
            &reference.pose,
            reference.image.width(),
            reference.image.height()
        )?
        .len()
    );
    let source_views: Vec<_> = sources.iter().map(LoadedView::view).collect();
    let mut request = params_request_to_proto(
        &reference.view(),
        &source_views,
        &points,
        a.airlight_source.wire(),
        a.airlight.unwrap_or(0.0),
    );
    use_encoded_images(
        request
            .reference
            .iter_mut()
            .chain(request.sources.iter_mut()),
        std::iter::once(&reference).chain(&sources),
    );
    request.beta_min = a.beta_min;
    request.beta_max = a.beta_max;
    request.beta_steps = a.beta_steps;
    if a.beta_sweep {
        request.beta_from_points = Some(false);
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
    println!(
        "job {}{}: A* = {:.4}, beta* = {:.5} per scene unit (A0 = {:.4} from {}, beta0 = {:.5}); \
         mean residual {:.4} scene units over {} SfM pixels",
        &job.id[..12.min(job.id.len())],
        if job.cached { " (cached)" } else { "" },
        r.airlight,
        r.beta,
        r.airlight_initial,
        source_name(r.airlight_source),
        r.beta_initial,
        r.residual,
        r.num_sparse_points
    );
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
                "not reliable, beta0 from the sweep"
            }
        );
    }
    if let Some(meta) = find_scene_metadata(&a.model)? {
        println!(
            "ground truth ({}): A = {:.4} (error {:+.4}), beta = {:.5} (error {:+.5})",
            meta.path.display(),
            meta.atmosphere.airlight,
            r.airlight - meta.atmosphere.airlight,
            meta.atmosphere.beta,
            r.beta - meta.atmosphere.beta
        );
    }
    if let Some(gt_path) = find_gt_depth(&a.images, &reference.name) {
        let gt = read_image(&gt_path, &limits)
            .with_context(|| format!("reading ground truth {}", gt_path.display()))?;
        let m = depth_metrics(&images.z_depth, &gt, None)?;
        print_metrics_header();
        print_metrics_row("estimated", &m, r.depth_seconds, "");
    }
    Ok(())
}

/// `stage,airlight,beta,residual` per evaluation.
fn write_residuals_csv(path: &Path, r: &pb::ScatteringParamsResult) -> anyhow::Result<()> {
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
    );
    writeln!(f, "stage,airlight,beta,residual")?;
    for g in &r.grid {
        let stage = match pb::SearchStage::try_from(g.stage) {
            Ok(pb::SearchStage::Beta) => "beta",
            Ok(pb::SearchStage::Joint) => "joint",
            _ => "unknown",
        };
        writeln!(f, "{stage},{},{},{}", g.airlight, g.beta, g.residual)?;
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
