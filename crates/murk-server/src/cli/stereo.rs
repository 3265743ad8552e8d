//! `murk stereo`: depth of a calibrated, rectified stereo pair in haze, one pair or a streamed
//! sequence.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::Args;

use murk::io::{read_image, sniff_format, DecodeLimits};
use murk::mvs_io::{write_ply, PlyFormat};
use murk::ImageF32;
use murk_server::service::convert::{
    image_from_proto, points_from_proto, ImageLimits, STEREO_OUTPUTS,
};
use murk_server::service::proto::v1 as pb;

use super::mvs::{kind_name, run_here_or_remote, write_depth_images, CostVolumeArg, DepthFlags};
use super::outputs::OutputFlags;
use super::session::{frame_dirs, LoadFrame, SequenceFlags, WriteResult};
use super::tof::{parse_intrinsics, parse_numbers};
use std::sync::Arc;

/// Options of `murk stereo`.
#[derive(Args, Debug)]
pub struct StereoArgs {
    /// Left (reference) image: PNG (8 or 16 bit), EXR or TIFF; grey or RGB.
    #[arg(long, required_unless_present = "sequence", requires = "right")]
    pub left: Option<PathBuf>,
    /// Right image: the left's size and channels.
    #[arg(long, requires = "left")]
    pub right: Option<PathBuf>,
    /// Rectified intrinsics of the left camera "fx,fy,cx,cy", pixels, with the origin at the
    /// centre of the top-left pixel (a ROS/OpenCV principal point as it is; COLMAP's minus 0.5).
    #[arg(long)]
    pub intrinsics: String,
    /// Distance of the right camera's centre along the left camera's +x axis; depths and points
    /// come out in its unit, and --beta is per that unit.
    #[arg(long)]
    pub baseline: f64,
    /// The right camera's principal point x, pixels, when it differs from the left's
    /// (Middlebury's calib.txt: cx of cam1; doffs is the difference).
    #[arg(long)]
    pub right_cx: Option<f64>,
    /// What to search and how.
    #[command(flatten)]
    pub method: StereoMethodFlags,
    /// Output folder (created): depth.exr, disparity.exr, confidence.exr (those fetched, see
    /// --outputs), points.ply, depth.png.
    #[arg(long)]
    pub out: PathBuf,
    /// Which result images to fetch (z_depth, disparity, confidence), and their encoding.
    #[command(flatten)]
    pub outputs: OutputFlags,
    /// Server URL; without it a server is started in this process.
    #[arg(long, env = "MURK_SERVER")]
    pub server: Option<String>,
    /// Streaming a sequence of pairs: one folder per frame holding `left.*` and `right.*`.
    #[command(flatten)]
    pub stream: SequenceFlags,
}

/// The search and the haze of a rectified pair, shared by `murk stereo` and `murk bag`.
#[derive(Args, Debug)]
pub struct StereoMethodFlags {
    /// Depth range "near,far" to search, in the baseline's unit.
    #[arg(long, conflicts_with = "disparity_range")]
    pub depth_range: Option<String>,
    /// Disparity range "min,max" to search, pixels (default: 1 to a quarter of the image width,
    /// at most 256).
    #[arg(long)]
    pub disparity_range: Option<String>,
    /// Number of planes, uniform in disparity (default: one per pixel of disparity).
    #[arg(long)]
    pub planes: Option<u32>,
    /// Airlight A of the haze in (0, 1] (linear units with --srgb).
    #[arg(long, requires = "beta")]
    pub airlight: Option<f32>,
    /// Scattering coefficient β per unit of the baseline (with --airlight).
    #[arg(long, requires = "airlight")]
    pub beta: Option<f32>,
    /// Cost volume (default: dehazing with --airlight and --beta, ordinary without).
    #[arg(long, value_enum)]
    pub cost_volume: Option<CostVolumeArg>,
    /// Matching and aggregation overrides.
    #[command(flatten)]
    pub depth: DepthFlags,
    /// The images are sRGB-encoded (what most cameras write to 8-bit PNG and JPEG): decode them
    /// to linear light first, as the haze model needs.
    #[arg(long)]
    pub srgb: bool,
}

impl StereoMethodFlags {
    /// A request for a rig (left intrinsics, baseline, the right principal point's x), without
    /// its images.
    pub fn request(
        &self,
        k: pb::CameraIntrinsics,
        baseline: f64,
        right_cx: Option<f64>,
    ) -> anyhow::Result<pb::RectifiedStereoRequest> {
        let (near, far) = match &self.depth_range {
            Some(s) => {
                let [near, far] = parse_numbers::<2>(s, "--depth-range", "near,far")?;
                (near, far)
            }
            None => (0.0, 0.0),
        };
        let (min_disparity_px, max_disparity_px) = match &self.disparity_range {
            Some(s) => {
                let [lo, hi] = parse_numbers::<2>(s, "--disparity-range", "min,max")?;
                (Some(lo as f32), Some(hi as f32))
            }
            None => (None, None),
        };
        let hazy = self.airlight.is_some();
        let cost = self.cost_volume.unwrap_or(if hazy {
            CostVolumeArg::Dehazing
        } else {
            CostVolumeArg::Ordinary
        });
        if cost != CostVolumeArg::Ordinary && !hazy {
            bail!("the {cost:?} cost volume needs the haze: pass --airlight and --beta");
        }
        Ok(pb::RectifiedStereoRequest {
            left: None,
            right: None,
            intrinsics: Some(k),
            baseline,
            right_cx,
            near,
            far,
            min_disparity_px,
            max_disparity_px,
            num_planes: self.planes.unwrap_or(0),
            airlight: self.airlight.unwrap_or(0.0),
            beta: self.beta.unwrap_or(0.0),
            cost_volume: cost.wire() as i32,
            sgm: self.depth.wire(),
            return_points: true,
            outputs: None,
        })
    }
}

/// Runs `murk stereo`.
pub fn run(a: StereoArgs) -> anyhow::Result<()> {
    if let Some(dir) = a.stream.sequence.clone() {
        return run_sequence(&a, &dir);
    }
    let (Some(left), Some(right)) = (&a.left, &a.right) else {
        bail!("give --left and --right, or --sequence DIR");
    };
    let request = build_request(&a, left, right)?;
    let job_request = pb::JobRequest {
        method: Some(pb::job_request::Method::RectifiedStereo(request)),
    };
    let (job, result) = run_here_or_remote(a.server.as_deref(), job_request, "stereo")?;
    let Some(pb::job_result::Method::RectifiedStereo(r)) = result.method else {
        bail!("server returned a result of another method");
    };
    let ((w, h), points) = write_result(&a.out, &r)?;
    println!(
        "job {}{}: {w}×{h} pair, {} cost volume, {} planes over z {:.4}..{:.4} (disparity \
         {:.1}..{:.1} px), {:.2} s; {} points ({:.1} % of pixels); outputs in {}",
        &job.id[..12.min(job.id.len())],
        if job.cached { " (cached)" } else { "" },
        kind_name(r.cost_volume),
        r.num_planes,
        r.near,
        r.far,
        r.min_disparity_px,
        r.max_disparity_px,
        r.compute_seconds,
        points,
        100.0 * points as f64 / (w * h).max(1) as f64,
        a.out.display()
    );
    for w in &r.warnings {
        println!("warning: {w}");
    }
    if r.right_gains.iter().any(|&g| g != 1.0) {
        let g: Vec<String> = r.right_gains.iter().map(|v| format!("{v:.4}")).collect();
        println!(
            "right camera's exposure per channel relative to the left (divided out): [{}]",
            g.join(" ")
        );
    }
    Ok(())
}

/// `murk stereo --sequence DIR`: every frame folder's pair through one sensor session; each
/// result in OUT/<frame>/.
fn run_sequence(a: &StereoArgs, dir: &Path) -> anyhow::Result<()> {
    let frames = frame_dirs(dir)?;
    let (left, right) = pair_in(&frames[0].1)?;
    let dims = read_image(&left, &DecodeLimits::default())
        .with_context(|| format!("reading {}", left.display()))?
        .dims();
    let mut template = build_request(a, &left, &right)?;
    template.left = None;
    template.right = None;
    let mut config = pb::SessionConfig {
        width: dims.0 as u32,
        height: dims.1 as u32,
        method: Some(pb::session_config::Method::Stereo(template)),
        ..Default::default()
    };
    a.stream.apply(&mut config);
    let srgb = a.method.srgb;
    let load: LoadFrame = Arc::new(move |dir: &Path| {
        let (left, right) = pair_in(dir)?;
        Ok(pb::SessionFrame {
            left: Some(encoded_image(&left, "left", srgb)?),
            right: Some(encoded_image(&right, "right", srgb)?),
            ..Default::default()
        })
    });
    let out = a.out.clone();
    let write: WriteResult = Arc::new(move |name: &str, r: &pb::FrameResult| {
        let Some(pb::frame_result::Outcome::Stereo(s)) = &r.outcome else {
            bail!("frame {name}: not a stereo result");
        };
        write_result(&out.join(name), s).map(|_| ())
    });
    a.stream
        .stream_folders(a.server.as_deref(), config, frames, load, write, &a.out)
}

/// The `left.*` and `right.*` files of a frame folder.
fn pair_in(dir: &Path) -> anyhow::Result<(PathBuf, PathBuf)> {
    let find = |stem: &str| -> anyhow::Result<PathBuf> {
        let mut found = Vec::new();
        for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
            let path = entry?.path();
            if path.file_stem().is_some_and(|s| s == stem) && path.is_file() {
                found.push(path);
            }
        }
        match found.len() {
            1 => Ok(found.remove(0)),
            0 => bail!("{} has no {stem}.* image", dir.display()),
            _ => bail!("{} has several {stem}.* images", dir.display()),
        }
    };
    Ok((find("left")?, find("right")?))
}

/// A file's bytes as an encoded image (the server decodes it), sRGB-tagged when `srgb`.
fn encoded_image(path: &Path, what: &str, srgb: bool) -> anyhow::Result<pb::Image> {
    let bytes = std::fs::read(path).with_context(|| format!("{what} {}", path.display()))?;
    if sniff_format(&bytes).is_none() {
        bail!("{what} {}: not a PNG, TIFF or OpenEXR file", path.display());
    }
    Ok(pb::Image {
        data: Some(pb::image::Data::Encoded(bytes)),
        transfer: if srgb {
            pb::Transfer::Srgb
        } else {
            pb::Transfer::Unspecified
        } as i32,
        ..Default::default()
    })
}

/// Writes the images a result carries (`depth.exr`, `disparity.exr`, `confidence.exr`, a
/// `depth.png` preview) and its points (`points.ply`) into `dir`; returns the image size and
/// the number of points.
fn write_result(
    dir: &Path,
    r: &pb::RectifiedStereoResult,
) -> anyhow::Result<((usize, usize), usize)> {
    let limits = ImageLimits {
        max_pixels: u64::MAX,
        max_channels: 4,
    };
    let decode = |name: &str, img: &Option<pb::Image>| -> anyhow::Result<Option<ImageF32>> {
        img.as_ref()
            .map(|img| image_from_proto(img, &limits).with_context(|| format!("decoding {name}")))
            .transpose()
    };
    let z = decode("z_depth", &r.z_depth)?;
    let disparity = decode("disparity", &r.disparity)?;
    let confidence = decode("confidence", &r.confidence)?;
    let mut exrs = Vec::new();
    for (file, img) in [
        ("depth.exr", &z),
        ("disparity.exr", &disparity),
        ("confidence.exr", &confidence),
    ] {
        if let Some(img) = img {
            exrs.push((file, img));
        }
    }
    let dims = exrs
        .first()
        .map(|(_, img)| img.dims())
        .context("the result carries no image")?;
    // The preview shows inverse depth: the disparity, or 1/z when only the depth was fetched.
    let inverse = match (&disparity, &z) {
        (Some(_), _) => None,
        (None, Some(z)) => Some(ImageF32::from_vec(
            z.width(),
            z.height(),
            1,
            z.data().iter().map(|v| 1.0 / v).collect(),
        )?),
        (None, None) => None,
    };
    write_depth_images(dir, &exrs, disparity.as_ref().or(inverse.as_ref()))?;
    let mut count = 0;
    if let Some(cloud) = &r.points {
        let points = points_from_proto(cloud)?;
        write_ply(
            &dir.join("points.ply"),
            &points,
            PlyFormat::BinaryLittleEndian,
        )?;
        count = points.len();
    }
    Ok((dims, count))
}

/// The request: the image files as they are (the server decodes them), the rig and the range.
fn build_request(
    a: &StereoArgs,
    left: &Path,
    right: &Path,
) -> anyhow::Result<pb::RectifiedStereoRequest> {
    let k = parse_intrinsics(&a.intrinsics)?;
    let mut request = a.method.request(
        pb::CameraIntrinsics {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            skew: 0.0,
        },
        a.baseline,
        a.right_cx,
    )?;
    request.left = Some(encoded_image(left, "--left", a.method.srgb)?);
    request.right = Some(encoded_image(right, "--right", a.method.srgb)?);
    let (wants_points, outputs) = a.outputs.split_points(STEREO_OUTPUTS)?;
    request.outputs = Some(outputs);
    request.return_points = wants_points;
    Ok(request)
}
