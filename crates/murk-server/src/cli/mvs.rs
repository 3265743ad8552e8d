//! `murk mvs`: multi-view stereo depth in haze from a COLMAP sparse model and its images.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};

use murk::atmosphere::AtmosphereParams;
use murk::io::{preview_range, read_image, write_colormap_png, write_exr, DecodeLimits};
use murk::metrics::{depth_metrics, DepthMetrics};
use murk::mvs::colmap::{read_colmap_dir, ColmapModel};
use murk::mvs_io::{
    backproject, find_gt_depth, find_scene_metadata, load_view, model_unit_in_scene_units,
    nearest_sources, unit_note, write_ply, LoadedView, PlyFormat,
};
use murk::params::search::plane_range_from_sparse;
use murk::params::sparse::{selected_points, PointSelection, SparseDepth};
use murk::ImageF32;
use murk_server::server::{InProcessServer, ServerConfig};
use murk_server::service::convert::{
    image_from_proto, mvs_request_to_proto, ImageLimits, MAX_SOURCE_VIEWS,
};
use murk_server::service::proto::v1 as pb;

use super::client::{connect, run_job};

/// The cost volume, as named on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum CostVolumeArg {
    /// Eq. 3.1 on the hazy images; needs no airlight or beta.
    Ordinary,
    /// murk's dehazing volume (observation-space residual; the measured best).
    Dehazing,
    /// The reference's Eq. 3.7 as published.
    Eq37,
}

impl CostVolumeArg {
    /// The wire enum.
    pub fn wire(self) -> pb::CostVolumeKind {
        match self {
            CostVolumeArg::Ordinary => pb::CostVolumeKind::Ordinary,
            CostVolumeArg::Dehazing => pb::CostVolumeKind::Dehazing,
            CostVolumeArg::Eq37 => pb::CostVolumeKind::DehazingEq37,
        }
    }
}

/// Overrides of the depth pipeline's matching and aggregation (`SgmOptions`), shared by
/// `murk mvs` and `murk stereo`.
#[derive(Args, Debug, Default)]
pub struct DepthFlags {
    /// σ of the Gaussian applied to every view before the cost volume, pixels, 0..=4
    /// (0 = none; server default 0.8). Lower it for noise-free or already denoised images.
    #[arg(long)]
    pub presmooth_sigma: Option<f32>,
    /// Largest contrast-normalisation weight of the costs, 1..=64 (1 = off; server default 4).
    #[arg(long)]
    pub contrast_max_weight: Option<f32>,
    /// Skip the source–reference consistency check (on by default: pixels whose match a source
    /// contradicts get confidence 0 and a depth filled from their neighbours).
    #[arg(long)]
    pub no_consistency_check: bool,
    /// Do not estimate and compensate the sources' exposure gains relative to the reference (on by
    /// default: a source a few percent brighter or darker than the reference otherwise ruins the
    /// dehazing cost).
    #[arg(long)]
    pub no_exposure_compensation: bool,
    /// Weight of the census term of the matching cost, 0..=3 (0 = off; server default 0).
    #[arg(long)]
    pub census_weight: Option<f32>,
    /// Do not estimate and divide out the lens's radial fall-off (vignetting), shared by every
    /// view (on by default).
    #[arg(long)]
    pub no_vignetting_compensation: bool,
    /// Reject depth speckles smaller than this many pixels (0 = off; server default W·H/3000).
    #[arg(long)]
    pub speckle_max_size: Option<u32>,
    /// SGM path directions: 5 (one top-to-bottom pass that keeps no volume; server default), 8
    /// (upward paths too: two passes over a stored volume) or 4 (horizontal and vertical).
    #[arg(long)]
    pub paths: Option<u32>,
    /// Memory bound of the cost volume with 8 or 4 paths, MiB: larger volumes are processed in
    /// horizontal strips (server default 96; the peak is about 1.25 times this plus the images).
    #[arg(long)]
    pub volume_budget_mib: Option<u32>,
}

impl DepthFlags {
    /// The wire overrides; `None` when every flag keeps the server's default.
    pub fn wire(&self) -> Option<pb::SgmOptions> {
        let o = pb::SgmOptions {
            presmooth_sigma_px: self.presmooth_sigma,
            contrast_max_weight: self.contrast_max_weight,
            consistency_check: self.no_consistency_check.then_some(false),
            exposure_compensation: self.no_exposure_compensation.then_some(false),
            census_weight: self.census_weight,
            vignetting_compensation: self.no_vignetting_compensation.then_some(false),
            speckle_max_size_px: self.speckle_max_size,
            volume_budget_mib: self.volume_budget_mib,
            num_paths: self.paths,
            ..Default::default()
        };
        (o != pb::SgmOptions::default()).then_some(o)
    }
}

/// Options of `murk mvs`.
#[derive(Args, Debug)]
pub struct MvsArgs {
    /// COLMAP sparse model folder (cameras/images/points3D, .txt or .bin; detected).
    #[arg(long)]
    pub model: PathBuf,
    /// Folder holding the model's images (names as in images.txt/.bin).
    #[arg(long)]
    pub images: PathBuf,
    /// Name of the reference image (whose depth is estimated), as in the model.
    #[arg(long)]
    pub reference: String,
    /// Source images by name, comma-separated (default: the --num-sources nearest cameras).
    #[arg(long, value_delimiter = ',', conflicts_with = "num_sources")]
    pub sources: Vec<String>,
    /// Number of source images to pick by camera distance when --sources is not given.
    #[arg(long)]
    pub num_sources: Option<usize>,
    /// Airlight A in (0, 1] (default: the ground truth of a scene from `murk simulate mvs`).
    #[arg(long, requires = "beta")]
    pub airlight: Option<f32>,
    /// Scattering coefficient beta, per scene unit (with --airlight).
    #[arg(long, requires = "airlight")]
    pub beta: Option<f32>,
    /// Cost volume.
    #[arg(long, value_enum, default_value_t = CostVolumeArg::Dehazing)]
    pub cost_volume: CostVolumeArg,
    /// Nearest plane z-depth, model units (with --far; default: 0.75 × the 1st percentile of the
    /// depths of the SfM points the reference sees).
    #[arg(long, requires = "far")]
    pub near: Option<f64>,
    /// Farthest plane z-depth, model units (with --near; default: 1.5 × their 99th percentile).
    #[arg(long, requires = "near")]
    pub far: Option<f64>,
    /// Number of planes, uniform in inverse depth (default: about one per pixel of the largest
    /// displacement of a reference pixel in any source across the range, 16 to 256).
    #[arg(long)]
    pub planes: Option<u32>,
    /// Matching and aggregation overrides.
    #[command(flatten)]
    pub depth: DepthFlags,
    /// Points below this confidence are left out of points.ply (0 keeps all).
    #[arg(long, default_value_t = 0.0)]
    pub min_confidence: f32,
    /// The images are sRGB-encoded (what most cameras write to 8-bit PNG and JPEG): decode them to
    /// linear light first, as the haze model needs. Then --airlight is in linear units too.
    #[arg(long)]
    pub srgb: bool,
    /// Write points.ply as ASCII instead of binary little-endian.
    #[arg(long)]
    pub ascii_ply: bool,
    /// Output folder (created).
    #[arg(long)]
    pub out: PathBuf,
    /// Server URL; without it a server is started in this process.
    #[arg(long, env = "MURK_SERVER")]
    pub server: Option<String>,
}

/// Default number of sources picked by distance (the reference evaluates with a handful of
/// neighbouring views).
const DEFAULT_NUM_SOURCES: usize = 4;

/// Largest request the in-process server accepts: the client and server share the machine, so
/// the network-facing default (32 MiB) would only refuse large local captures.
const IN_PROCESS_MAX_REQUEST_BYTES: usize = 1 << 30;

/// Runs `murk mvs`.
pub fn run(a: MvsArgs) -> anyhow::Result<()> {
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

    let kind = a.cost_volume;
    let atmosphere = atmosphere_for(&a)?;
    let mut request = build_request(&reference, &sources, kind, atmosphere, a.srgb);
    // The plane range from the model's points seen by the reference unless given (the API's
    // own default, 0.5…50, knows nothing of the scene or the model's unit); an unset count stays
    // 0 on the wire: the server picks about one plane per pixel of displacement.
    let sparse = reference_sparse_depth(&model, &reference, PointSelection::ObservedInReference)?;
    let (near, far) = match (a.near, a.far) {
        (Some(n), Some(f)) => (n, f),
        _ => match plane_range_from_sparse(&sparse) {
            Some((n, f)) => {
                println!(
                    "planes over z {n:.4}..{f:.4} model units, from the {} SfM points seen \
                         by the reference (--near/--far override)",
                    sparse.len()
                );
                (n, f)
            }
            None => (0.0, 0.0),
        },
    };
    request.near = near;
    request.far = far;
    request.num_planes = a.planes.unwrap_or(0);
    request.sgm = a.depth.wire();

    let job_request = pb::JobRequest {
        method: Some(pb::job_request::Method::MvsDepth(request)),
    };
    let (job, result) = run_here_or_remote(a.server.as_deref(), job_request, "mvs")?;
    let Some(pb::job_result::Method::MvsDepth(r)) = result.method else {
        bail!("server returned a result of another method");
    };
    let images = decode_mvs_result(&r)?;
    let ply_format = if a.ascii_ply {
        PlyFormat::Ascii
    } else {
        PlyFormat::BinaryLittleEndian
    };
    // The point cloud is written while the images are.
    let (written, points) = rayon::join(
        || write_mvs_images(&a.out, &images),
        || -> anyhow::Result<usize> {
            let points = backproject(
                &images.z_depth,
                &images.confidence,
                &reference.image,
                &reference.intrinsics,
                &reference.pose,
                a.min_confidence,
            )?;
            std::fs::create_dir_all(&a.out)
                .with_context(|| format!("creating {}", a.out.display()))?;
            write_ply(&a.out.join("points.ply"), &points, ply_format)?;
            Ok(points.len())
        },
    );
    written?;
    let num_points = points?;
    println!(
        "job {}{}: {} cost volume, {} planes over z {}..{}, {:.2} s; {} points; outputs in {}",
        &job.id[..12.min(job.id.len())],
        if job.cached { " (cached)" } else { "" },
        kind_name(r.cost_volume),
        r.num_planes,
        r.near,
        r.far,
        r.compute_seconds,
        num_points,
        a.out.display()
    );
    for w in &r.warnings {
        println!("warning: {w}");
    }
    if r.vignetting_falloff != 0.0 {
        println!(
            "lens fall-off divided out of every view: corners at {:.3} of the centre's brightness",
            1.0 + r.vignetting_falloff
        );
    }
    if let Some(c) = super::source_corners(r.source_falloffs.iter().map(|&d| f64::from(d))) {
        println!("sources' own lens fall-off divided out: corners at {c} of the reference's");
    }
    if r.source_gains.iter().any(|&g| g != 1.0) {
        // One gain per channel of each source, source-major.
        let per_source = reference.image.channels().max(1);
        let gains: Vec<String> = r
            .source_gains
            .chunks(per_source)
            .map(|g| {
                let g: Vec<String> = g.iter().map(|v| format!("{v:.4}")).collect();
                format!("[{}]", g.join(" "))
            })
            .collect();
        println!(
            "sources' exposure per channel relative to the reference (divided out): {}",
            gains.join(", ")
        );
    }
    if let Some(gt_path) = find_gt_depth(&a.images, &reference.name) {
        let gt = read_image(&gt_path, &limits)
            .with_context(|| format!("reading ground truth {}", gt_path.display()))?;
        // A model reconstructed by SfM from the simulator's images has its own unit: compare in
        // the ground truth's, the scale measured from the model's points.
        let scale = model_unit_in_scene_units(&sparse, &gt);
        let mut z = images.z_depth.clone();
        for v in z.data_mut() {
            *v *= scale.unwrap_or(1.0);
        }
        let m = depth_metrics(&z, &gt, None)
            .with_context(|| format!("comparing with {}", gt_path.display()))?;
        println!(
            "against ground truth {}{}:",
            gt_path.display(),
            unit_note(scale)
        );
        print_metrics_header();
        print_metrics_row(
            kind_name(r.cost_volume),
            &m,
            r.compute_seconds,
            if job.cached { " (cached)" } else { "" },
        );
    }
    Ok(())
}

/// The sparse depth of Eq. 3.8: the model's points picked by `selection`, projected into the
/// reference view.
pub fn reference_sparse_depth(
    model: &ColmapModel,
    reference: &LoadedView,
    selection: PointSelection,
) -> anyhow::Result<SparseDepth> {
    let points = selected_points(model, &reference.name, selection)?;
    Ok(SparseDepth::from_points(
        &points,
        &reference.intrinsics,
        &reference.pose,
        reference.image.width(),
        reference.image.height(),
    )?)
}

/// Reads the reference and the source views (named, or the `num_sources` nearest cameras).
pub fn load_views(
    model: &ColmapModel,
    images: &Path,
    reference: &str,
    sources: &[String],
    num_sources: Option<usize>,
    limits: &DecodeLimits,
) -> anyhow::Result<(LoadedView, Vec<LoadedView>)> {
    let source_names = if sources.is_empty() {
        let n = num_sources.unwrap_or(DEFAULT_NUM_SOURCES);
        if n == 0 || n > MAX_SOURCE_VIEWS {
            bail!("--num-sources must be in 1..={MAX_SOURCE_VIEWS}, got {n}");
        }
        nearest_sources(model, reference, n)?
    } else {
        if sources.len() > MAX_SOURCE_VIEWS {
            bail!(
                "at most {MAX_SOURCE_VIEWS} --sources, got {}",
                sources.len()
            );
        }
        if sources.iter().any(|s| s == reference) {
            bail!("--sources must not contain the reference {reference:?}");
        }
        sources.to_vec()
    };
    let load = |name: &str| {
        load_view(model, images, name, limits).with_context(|| format!("loading image {name:?}"))
    };
    let reference = load(reference)?;
    let sources = source_names
        .iter()
        .map(|n| load(n))
        .collect::<anyhow::Result<Vec<_>>>()?;
    println!(
        "reference {} ({}x{}x{}), sources {}",
        reference.name,
        reference.image.width(),
        reference.image.height(),
        reference.image.channels(),
        source_names.join(", ")
    );
    Ok((reference, sources))
}

/// Runs one job on the server at `url`, or on a server started in this process for it.
pub fn run_here_or_remote(
    url: Option<&str>,
    job_request: pb::JobRequest,
    label: &str,
) -> anyhow::Result<(pb::Job, pb::JobResult)> {
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async {
        match url {
            Some(url) => {
                let mut client = connect(url).await?;
                run_job(&mut client, job_request, label, true).await
            }
            None => {
                let server = InProcessServer::start(ServerConfig {
                    max_request_bytes: IN_PROCESS_MAX_REQUEST_BYTES,
                    ..ServerConfig::default()
                })
                .await?;
                let mut client = connect(&server.url()).await?;
                let out = run_job(&mut client, job_request, label, true).await;
                server.stop().await?;
                out
            }
        }
    })
}

/// Replaces the raw images of a request's views with the files' original encodings where they
/// were used unchanged (smaller on the wire, nothing lost), and marks every image sRGB-encoded
/// when `srgb` (the server then decodes it to linear light).
pub fn use_encoded_images<'a>(
    wire: impl Iterator<Item = &'a mut pb::MvsView>,
    loaded: impl Iterator<Item = &'a LoadedView>,
    srgb: bool,
) {
    for (wire, loaded) in wire.zip(loaded) {
        if let Some(bytes) = &loaded.encoded {
            wire.image = Some(pb::Image {
                data: Some(pb::image::Data::Encoded(bytes.clone())),
                ..Default::default()
            });
        }
        if srgb {
            if let Some(image) = wire.image.as_mut() {
                image.transfer = pb::Transfer::Srgb as i32;
            }
        }
    }
}

/// A and β for the chosen cost volume: the flags, else a simulated scene's ground truth, else an
/// error for the dehazing kinds (ORDINARY needs neither).
fn atmosphere_for(a: &MvsArgs) -> anyhow::Result<Option<AtmosphereParams>> {
    if let (Some(airlight), Some(beta)) = (a.airlight, a.beta) {
        let p = AtmosphereParams { airlight, beta };
        p.validate()?;
        return Ok(Some(p));
    }
    if a.cost_volume == CostVolumeArg::Ordinary {
        return Ok(None);
    }
    // Only the simulator's own model (`<scene>/sparse`) shares the ground truth's unit; a model
    // reconstructed from its images further down has its own scale.
    let own_model = |meta: &murk::mvs_io::SceneMetadata| {
        let dir = meta.path.parent();
        dir == Some(a.model.as_path()) || dir == a.model.parent()
    };
    match find_scene_metadata(&a.model)?.filter(own_model) {
        Some(meta) => {
            println!(
                "using the ground-truth airlight A = {:.4} and beta = {:.5} per scene unit from {} \
                 (a scene written by `murk simulate mvs`)",
                meta.atmosphere.airlight,
                meta.atmosphere.beta,
                meta.path.display()
            );
            Ok(Some(meta.atmosphere))
        }
        None => bail!(
            "the {:?} cost volume needs the scattering parameters: pass --airlight A --beta B \
             (per scene unit; `murk params` estimates them), or use --cost-volume ordinary",
            a.cost_volume
        ),
    }
}

/// The wire request; images travel in their original encoding when it was used unchanged.
fn build_request(
    reference: &LoadedView,
    sources: &[LoadedView],
    kind: CostVolumeArg,
    atmosphere: Option<AtmosphereParams>,
    srgb: bool,
) -> pb::MvsDepthRequest {
    let source_views: Vec<_> = sources.iter().map(LoadedView::view).collect();
    let mut request = mvs_request_to_proto(
        &reference.view(),
        &source_views,
        kind.wire(),
        atmosphere,
        None,
    );
    use_encoded_images(
        request
            .reference
            .iter_mut()
            .chain(request.sources.iter_mut()),
        std::iter::once(reference).chain(sources),
        srgb,
    );
    request
}

/// The decoded result images.
pub struct MvsImages {
    /// z-depth, scene units.
    pub z_depth: ImageF32,
    /// Inverse depth, per scene unit.
    pub inverse_depth: ImageF32,
    /// Confidence in [0, 1].
    pub confidence: ImageF32,
}

/// Writes `depth.exr`, `inverse_depth.exr`, `confidence.exr` and a colour-mapped `depth.png`
/// into `dir` (created); returns the decoded images.
pub fn write_mvs_result(dir: &Path, r: &pb::MvsDepthResult) -> anyhow::Result<MvsImages> {
    let images = decode_mvs_result(r)?;
    write_mvs_images(dir, &images)?;
    Ok(images)
}

/// The depth, inverse depth and confidence images of a result.
fn decode_mvs_result(r: &pb::MvsDepthResult) -> anyhow::Result<MvsImages> {
    let limits = ImageLimits {
        max_pixels: u64::MAX,
        max_channels: 4,
    };
    let dec = |name: &str, img: &Option<pb::Image>| -> anyhow::Result<ImageF32> {
        let img = img
            .as_ref()
            .with_context(|| format!("result lacks {name}"))?;
        image_from_proto(img, &limits).with_context(|| format!("decoding {name}"))
    };
    Ok(MvsImages {
        z_depth: dec("z_depth", &r.z_depth)?,
        inverse_depth: dec("inverse_depth", &r.inverse_depth)?,
        confidence: dec("confidence", &r.confidence)?,
    })
}

/// The files of [`write_mvs_result`], written in parallel: each compresses on its own core
/// (the three EXRs' deflate was most of the client's time after the job).
fn write_mvs_images(dir: &Path, images: &MvsImages) -> anyhow::Result<()> {
    write_depth_images(
        dir,
        &[
            ("depth.exr", &images.z_depth),
            ("inverse_depth.exr", &images.inverse_depth),
            ("confidence.exr", &images.confidence),
        ],
        Some(&images.inverse_depth),
    )
}

/// Writes `exrs` into `dir` (created), each compressing on its own core, and, given
/// `inverse_depth` (or anything proportional to it, such as a rectified pair's disparity),
/// `depth.png`, its preview coloured near red, far blue over its 2nd..98th percentile, so a few
/// outliers do not flatten it.
pub(super) fn write_depth_images(
    dir: &Path,
    exrs: &[(&str, &ImageF32)],
    inverse_depth: Option<&ImageF32>,
) -> anyhow::Result<()> {
    use rayon::prelude::*;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let (written, png) = rayon::join(
        || {
            exrs.par_iter().try_for_each(|(name, img)| {
                write_exr(&dir.join(name), img).with_context(|| format!("writing {name}"))
            })
        },
        || {
            inverse_depth.map_or(Ok(()), |inverse_depth| {
                let (lo, hi) = preview_range(inverse_depth, None);
                write_colormap_png(&dir.join("depth.png"), inverse_depth, lo, hi, None)
            })
        },
    );
    written?;
    png?;
    Ok(())
}

/// Display name of a wire cost-volume kind.
pub fn kind_name(v: i32) -> &'static str {
    match pb::CostVolumeKind::try_from(v) {
        Ok(pb::CostVolumeKind::Ordinary) => "ordinary",
        Ok(pb::CostVolumeKind::Dehazing | pb::CostVolumeKind::Unspecified) => "dehazing",
        Ok(pb::CostVolumeKind::DehazingEq37) => "eq37",
        Err(_) => "unknown",
    }
}

/// Header of the metric table printed by `murk mvs` and `murk demo`.
pub fn print_metrics_header() {
    println!(
        "{:<26} {:>8} {:>8} {:>8} {:>9} {:>9}",
        "cost volume", "L1-rel", "L1-inv", "sc-inv", "C.P. [%]", "time [s]"
    );
}

/// One row of that table; `note` is appended (e.g. " (cached)").
pub fn print_metrics_row(name: &str, m: &DepthMetrics, seconds: f64, note: &str) {
    println!(
        "{:<26} {:>8.3} {:>8.4} {:>8.3} {:>9.1} {:>9.2}{note}",
        name,
        m.l1_rel,
        m.l1_inv,
        m.sc_inv,
        100.0 * m.c_p,
        seconds
    );
}
