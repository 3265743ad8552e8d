//! `murk tof`: a client for ToF depth in fog, one frame or a streamed sequence.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::Args;

use murk::camera::Intrinsics;
use murk::io::{preview_range, read_image, write_colormap_png, write_exr, DecodeLimits};
use murk::mvs_io::{write_ply, PlyFormat};
use murk::simulate::{read_tof_capture, TofCapture};
use murk::ImageF32;
use murk_server::service::convert::{
    image_from_proto, image_to_proto, points_from_proto, tof_request_to_proto, ImageLimits,
    TOF_OUTPUTS,
};
use murk_server::service::proto::v1 as pb;

use super::mvs::run_here_or_remote;
use super::outputs::OutputFlags;
use super::session::{frame_dirs, LoadFrame, SequenceFlags, WriteResult};
use std::sync::Arc;

/// Options of `murk tof`.
#[derive(Args, Debug)]
pub struct TofArgs {
    /// Server URL; without it a server is started in this process (as `murk mvs` and
    /// `murk ps` do).
    #[arg(long, env = "MURK_SERVER")]
    pub server: Option<String>,
    /// A folder in the simulator's layout (amplitude.exr, phase.exr, optional meta.json).
    #[arg(long, conflicts_with_all = ["amplitude", "phase", "sequence"])]
    pub frame: Option<PathBuf>,
    /// Amplitude image (EXR, PNG 8/16-bit or TIFF).
    #[arg(long, requires = "phase", conflicts_with = "sequence")]
    pub amplitude: Option<PathBuf>,
    /// Phase image in radians (EXR/float TIFF); for integer PNG/TIFF use --phase-scale.
    #[arg(long, requires = "amplitude")]
    pub phase: Option<PathBuf>,
    /// Multiplier applied to the decoded phase (e.g. 6.2831853 for a 16-bit PNG of 0..2π).
    #[arg(long, default_value_t = 1.0)]
    pub phase_scale: f32,
    /// Modulation frequency, Hz (overrides meta.json).
    #[arg(long)]
    pub frequency_hz: Option<f64>,
    /// Intrinsics "fx,fy,cx,cy" in pixels (overrides meta.json); enables z-depth.
    #[arg(long)]
    pub intrinsics: Option<String>,
    /// Light source position "x,y,z" in the camera frame, metres (overrides meta.json); with
    /// intrinsics, range is solved exactly for the emitter's offset from the lens.
    #[arg(long)]
    pub light_position_m: Option<String>,
    /// Cap on the fine IRLS iterations (default 150; the reference's is 50).
    #[arg(long)]
    pub fine_iterations: Option<u32>,
    /// Coarse IRLS iterations (default: the reference's 5).
    #[arg(long)]
    pub coarse_iterations: Option<u32>,
    /// Row about which the symmetry prior mirrors the image.
    #[arg(long)]
    pub symmetry_row: Option<f64>,
    /// Output folder (created): one EXR per result image fetched, colour-mapped PNG previews of
    /// the range, and with intrinsics the measured pixels as points.ply.
    #[arg(long)]
    pub out: PathBuf,
    /// Which result images to fetch, and their encoding.
    #[command(flatten)]
    pub outputs: OutputFlags,
    /// Streaming a sequence of frames.
    #[command(flatten)]
    pub stream: SequenceFlags,
    /// With --sequence: frames computed from the previous frame's answer solve the scatter on
    /// blocks of this many pixels a side, 1..=4 (1: at full size; default 2); frames computed
    /// from scratch solve their coarse level there.
    #[arg(long, requires = "sequence")]
    pub scatter_grid: Option<u32>,
}

/// Runs `murk tof`.
pub fn run(a: TofArgs) -> anyhow::Result<()> {
    if let Some(dir) = a.stream.sequence.clone() {
        return run_sequence(&a, &dir);
    }
    let limits = DecodeLimits::default();
    let capture = if let Some(dir) = &a.frame {
        read_tof_capture(dir).with_context(|| format!("reading {}", dir.display()))?
    } else {
        let (Some(ap), Some(pp)) = (&a.amplitude, &a.phase) else {
            bail!("give --frame DIR, or --amplitude and --phase, or --sequence DIR");
        };
        TofCapture {
            amplitude: read_image(ap, &limits)?.into_mono()?,
            phase: read_image(pp, &limits)?.into_mono()?,
            intrinsics: None,
            modulation_frequency_hz: None,
            light_position_m: None,
        }
    };
    let request = request_for(&a, capture)?;
    let (job, result) = run_here_or_remote(
        a.server.as_deref(),
        pb::JobRequest {
            method: Some(pb::job_request::Method::TofDepth(request)),
        },
        "tof",
    )?;
    let Some(pb::job_result::Method::TofDepth(r)) = result.method else {
        bail!("server returned a result of another method");
    };
    write_tof_result(&a.out, &r)?;
    println!(
        "job {}{}; outputs in {}",
        &job.id[..12.min(job.id.len())],
        if job.cached { " (cached)" } else { "" },
        a.out.display()
    );
    for w in &r.warnings {
        println!("warning: {w}");
    }
    Ok(())
}

/// `murk tof --sequence DIR`: every frame folder through one sensor session, configured from
/// the first frame (its meta.json and the flags); each result in OUT/<frame>/.
fn run_sequence(a: &TofArgs, dir: &Path) -> anyhow::Result<()> {
    let frames = frame_dirs(dir)?;
    let first = read_tof_capture(&frames[0].1)
        .with_context(|| format!("reading {}", frames[0].1.display()))?;
    let (width, height) = first.amplitude.dims();
    let mut template = request_for(a, first)?;
    template.amplitude = None;
    template.phase = None;
    let mut config = pb::SessionConfig {
        width: width as u32,
        height: height as u32,
        method: Some(pb::session_config::Method::Tof(template)),
        ..Default::default()
    };
    a.stream.apply(&mut config);
    config.tof_scatter_grid = a.scatter_grid.unwrap_or(0);
    let phase_scale = a.phase_scale;
    let load: LoadFrame = Arc::new(move |dir: &Path| {
        let mut c = read_tof_capture(dir)?;
        scale_phase(&mut c.phase, phase_scale);
        Ok(pb::SessionFrame {
            amplitude: Some(image_to_proto(&c.amplitude)),
            phase: Some(image_to_proto(&c.phase)),
            ..Default::default()
        })
    });
    let out = a.out.clone();
    let write: WriteResult = Arc::new(move |name: &str, r: &pb::FrameResult| {
        let Some(pb::frame_result::Outcome::Tof(t)) = &r.outcome else {
            bail!("frame {name}: not a ToF result");
        };
        write_tof_result(&out.join(name), t).map(|_| ())
    });
    a.stream
        .stream_folders(a.server.as_deref(), config, frames, load, write, &a.out)
}

fn scale_phase(phase: &mut ImageF32, scale: f32) {
    if scale != 1.0 {
        for v in phase.data_mut() {
            *v *= scale;
        }
    }
}

/// The one-shot request for a capture and the flags (which override its meta.json).
fn request_for(a: &TofArgs, capture: TofCapture) -> anyhow::Result<pb::TofDepthRequest> {
    let TofCapture {
        amplitude,
        mut phase,
        intrinsics: meta_k,
        modulation_frequency_hz: meta_f,
        light_position_m: meta_light,
    } = capture;
    scale_phase(&mut phase, a.phase_scale);
    let frequency = a
        .frequency_hz
        .or(meta_f)
        .context("modulation frequency unknown: pass --frequency-hz")?;
    let intrinsics = match &a.intrinsics {
        Some(s) => Some(parse_intrinsics(s)?),
        None => meta_k,
    };
    // The correction needs each pixel's ray: a light position without intrinsics is refused when
    // asked for on the command line, and said to be unused when it only came with meta.json.
    let light = match &a.light_position_m {
        Some(_) if intrinsics.is_none() => bail!(
            "--light-position-m needs intrinsics (--intrinsics fx,fy,cx,cy or meta.json): the \
             range correction depends on each pixel's ray"
        ),
        Some(s) => Some(parse_numbers::<3>(s, "--light-position-m", "x,y,z")?),
        None if intrinsics.is_none() && meta_light.is_some() => {
            eprintln!(
                "note: meta.json's light_position_m is not used without intrinsics; range is \
                 half the light path"
            );
            None
        }
        None => meta_light,
    };
    let mut request =
        tof_request_to_proto(&amplitude, &phase, intrinsics.as_ref(), frequency, light);
    let (wants_points, outputs) = a.outputs.split_points(TOF_OUTPUTS)?;
    request.outputs = Some(outputs);
    // With intrinsics the measured pixels can come back as points (points.ply).
    request.return_points = wants_points && request.intrinsics.is_some();
    request.options = Some(pb::TofOptions {
        coarse_iterations: a.coarse_iterations,
        fine_iterations: a.fine_iterations,
        symmetry_row: a.symmetry_row,
        ..Default::default()
    });
    Ok(request)
}

/// `N` comma-separated numbers of `flag`, whose `shape` (e.g. "x,y,z") the error names.
pub(super) fn parse_numbers<const N: usize>(
    s: &str,
    flag: &str,
    shape: &str,
) -> anyhow::Result<[f64; N]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{flag} must be {shape}"))?;
    v.try_into()
        .map_err(|_| anyhow::anyhow!("{flag} must have {N} numbers: {shape}"))
}

/// Intrinsics "fx,fy,cx,cy" of `--intrinsics`, validated.
pub(super) fn parse_intrinsics(s: &str) -> anyhow::Result<Intrinsics> {
    let [fx, fy, cx, cy] = parse_numbers::<4>(s, "--intrinsics", "fx,fy,cx,cy")?;
    let k = Intrinsics::new(fx, fy, cx, cy);
    k.validate()?;
    Ok(k)
}

/// Decoded ToF outputs.
pub struct TofImages {
    /// Corrected range, metres.
    pub range_m: ImageF32,
    /// Raw range, metres.
    pub raw_range_m: ImageF32,
    /// Object mask.
    pub mask: ImageF32,
}

/// Writes every image the result carries as `<field>.exr` into `dir`, with colour-mapped PNG
/// previews of the corrected and raw range and the mask where the result has them, and its
/// points as `points.ply`; returns
/// the main images when it carries all three.
pub fn write_tof_result(dir: &Path, r: &pb::TofDepthResult) -> anyhow::Result<Option<TofImages>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let limits = ImageLimits {
        max_pixels: u64::MAX,
        max_channels: 4,
    };
    let fields = [
        ("range_m", &r.range_m),
        ("range_std_m", &r.range_std_m),
        ("z_depth_m", &r.z_depth_m),
        ("raw_range_m", &r.raw_range_m),
        ("raw_z_depth_m", &r.raw_z_depth_m),
        ("mask", &r.mask),
        ("scatter_amplitude", &r.scatter_amplitude),
        ("scatter_phase", &r.scatter_phase),
        ("weight_amplitude", &r.weight_amplitude),
        ("weight_phase", &r.weight_phase),
        ("corrected_amplitude", &r.corrected_amplitude),
        ("corrected_phase", &r.corrected_phase),
    ];
    let mut decoded = std::collections::HashMap::new();
    for (name, img) in fields {
        if let Some(img) = img {
            let img = image_from_proto(img, &limits).with_context(|| format!("decoding {name}"))?;
            write_exr(&dir.join(format!("{name}.exr")), &img)?;
            decoded.insert(name, img);
        }
    }
    let mask = decoded.get("mask");
    // The corrected range (the z-depth when only that was fetched) sets one colour scale for
    // raw and corrected, so the previews are comparable.
    let (main, raw) = match decoded.get("range_m") {
        Some(range) => (Some(("range_m", range)), decoded.get("raw_range_m")),
        None => (
            decoded.get("z_depth_m").map(|z| ("z_depth_m", z)),
            decoded.get("raw_z_depth_m"),
        ),
    };
    if let Some((name, img)) = main {
        let (lo, hi) = preview_range(img, mask);
        write_colormap_png(&dir.join(format!("{name}.png")), img, lo, hi, mask)?;
        if let Some(raw) = raw {
            write_colormap_png(&dir.join(format!("raw_{name}.png")), raw, lo, hi, mask)?;
        }
    }
    if let Some(mask) = mask {
        write_colormap_png(&dir.join("mask.png"), mask, 0.0, 1.0, None)?;
    }
    if let Some(cloud) = &r.points {
        write_ply(
            &dir.join("points.ply"),
            &points_from_proto(cloud)?,
            PlyFormat::BinaryLittleEndian,
        )?;
    }
    let take = |name: &str| decoded.get(name).cloned();
    Ok(match (take("range_m"), take("raw_range_m"), take("mask")) {
        (Some(range_m), Some(raw_range_m), Some(mask)) => Some(TofImages {
            range_m,
            raw_range_m,
            mask,
        }),
        _ => None,
    })
}
