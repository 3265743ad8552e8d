//! Stereo depth in haze on board, with no server: a calibrated, rectified pair (left and right
//! images, the intrinsics and the baseline, as a ROS `CameraInfo` pair gives them) through the
//! plane sweep with the dehazing cost volume of the reference's Ch. 3.2 (Eq. 3.7) and SGM, with
//! [`murk::mvs::estimate_rectified`].
//!
//! ```sh
//! cargo run --release -p murk --example stereo_embedded -- --left left.png --right right.png \
//!     --intrinsics 1870,1870,339.5,239.5 --baseline 0.16 --depth-range 1.0,3.0 \
//!     --airlight 0.85 --beta 0.6 --out /tmp/stereo-out
//! ```
//!
//! Without `--airlight`/`--beta` the ordinary cost volume (Eq. 3.1) is used. Only the `murk`
//! library crate is linked: no gRPC, no async runtime.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Parser;
use murk::atmosphere::AtmosphereParams;
use murk::camera::Intrinsics;
use murk::io::{read_image, write_colormap_png, write_exr, DecodeLimits};
use murk::mvs::{
    estimate_rectified, CostKind, DehazingOptions, RectifiedOptions, RectifiedRig, StereoRange,
};
use murk::mvs_io::{write_ply, PlyFormat};
use murk::Monitor;

/// Depth of the left view of a rectified pair; writes depth.exr (z-depth in the baseline's
/// unit), disparity.exr (pixels), confidence.exr, points.ply (the confident pixels in the left
/// camera's frame) and depth.png.
#[derive(Parser, Debug)]
struct Args {
    /// Left (reference) image: PNG (8 or 16 bit), EXR or TIFF; grey or RGB.
    #[arg(long)]
    left: PathBuf,
    /// Right image, same size and channels.
    #[arg(long)]
    right: PathBuf,
    /// Rectified intrinsics "fx,fy,cx,cy", pixels, with the origin at the centre of the top-left
    /// pixel (a ROS/OpenCV principal point as it is; COLMAP's minus 0.5).
    #[arg(long, value_parser = numbers::<4>)]
    intrinsics: [f64; 4],
    /// Baseline: the right camera's centre lies this far along the left camera's +x axis, in
    /// scene units (metres, say); depths and β are in the same unit.
    #[arg(long)]
    baseline: f64,
    /// The right camera's principal point x, pixels, when it differs from the left's
    /// (Middlebury's `doffs` is the difference).
    #[arg(long)]
    right_cx: Option<f64>,
    /// Depth range "near,far" to sweep, scene units; default: disparities 1 px to a quarter of
    /// the width (at most 256 px).
    #[arg(long, value_parser = numbers::<2>)]
    depth_range: Option<[f64; 2]>,
    /// Number of planes (uniform in disparity); default: one per pixel of disparity.
    #[arg(long)]
    planes: Option<usize>,
    /// Airlight A of the haze, in (0, 1] (pixel values scaled to [0, 1]).
    #[arg(long, requires = "beta")]
    airlight: Option<f32>,
    /// Scattering coefficient β per scene unit.
    #[arg(long, requires = "airlight")]
    beta: Option<f32>,
    /// Output folder (created).
    #[arg(long)]
    out: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let limits = DecodeLimits::default();
    let left = read_image(&args.left, &limits).context("--left")?;
    let right = read_image(&args.right, &limits).context("--right")?;
    if left.dims() != right.dims() || left.channels() != right.channels() {
        bail!(
            "the images differ: left {:?}×{}, right {:?}×{}",
            left.dims(),
            left.channels(),
            right.dims(),
            right.channels()
        );
    }
    let [fx, fy, cx, cy] = args.intrinsics;
    let rig = RectifiedRig {
        intrinsics: Intrinsics::new(fx, fy, cx, cy),
        baseline: args.baseline,
        right_cx: args.right_cx.unwrap_or(cx),
    };
    let cost = match (args.airlight, args.beta) {
        (Some(airlight), Some(beta)) => {
            let atmosphere = AtmosphereParams { airlight, beta };
            atmosphere.validate()?;
            CostKind::DehazingWith(atmosphere, DehazingOptions::default())
        }
        _ => CostKind::Ordinary,
    };
    let options = RectifiedOptions {
        range: args
            .depth_range
            .map(|[near, far]| StereoRange::Depth { near, far }),
        num_planes: args.planes,
        cost,
        ..RectifiedOptions::default()
    };

    let started = Instant::now();
    let out = estimate_rectified(&left, &right, &rig, &options, &Monitor::noop())?;
    let seconds = started.elapsed().as_secs_f64();

    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    write_exr(&args.out.join("depth.exr"), &out.depth.z_depth)?;
    write_exr(&args.out.join("disparity.exr"), &out.disparity)?;
    write_exr(&args.out.join("confidence.exr"), &out.depth.confidence)?;
    let points = out.points(&rig, &left)?;
    write_ply(
        &args.out.join("points.ply"),
        &points,
        PlyFormat::BinaryLittleEndian,
    )?;
    let (near, far) = (out.planes.near, out.planes.far);
    write_colormap_png(
        &args.out.join("depth.png"),
        &out.depth.z_depth,
        near as f32,
        far as f32,
        None,
    )?;

    let (w, h) = left.dims();
    println!(
        "{w}×{h} pair, {} planes over z {near:.3}–{far:.3} (disparity {:.1}–{:.1} px), {} cost \
         volume: {seconds:.2} s, {} points with confidence > 0 ({:.1} %); wrote {}",
        out.planes.num_planes,
        rig.disparity_of_depth(far),
        rig.disparity_of_depth(near),
        if cost == CostKind::Ordinary {
            "ordinary"
        } else {
            "dehazing"
        },
        points.len(),
        100.0 * points.len() as f64 / (w * h) as f64,
        args.out.display()
    );
    for warning in &out.depth.warnings {
        println!("warning: {warning}");
    }
    Ok(())
}

/// Parses `N` comma-separated numbers, e.g. "fx,fy,cx,cy".
fn numbers<const N: usize>(text: &str) -> Result<[f64; N], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>().map_err(|e| format!("`{v}`: {e}")))
        .collect::<Result<_, _>>()?;
    values
        .try_into()
        .map_err(|v: Vec<f64>| format!("expected {N} comma-separated numbers, got {}", v.len()))
}
