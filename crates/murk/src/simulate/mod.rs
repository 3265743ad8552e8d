//! Simulators producing synthetic captures with ground truth.
//!
//! [`simulate_tof`] renders a CW-ToF amplitude/phase frame of a seeded scene in homogeneous fog
//! (model in [`tof`]'s docs). [`write_tof_frame`] / [`read_tof_frame`] store it in a folder:
//!
//! ```text
//! <dir>/
//!   meta.json               format "murk.tof_frame" v1: modulation_frequency_hz, intrinsics,
//!                           light_position_m
//!                           {fx, fy, cx, cy, skew} (pixels, pixel-centre origin), beta_per_mm,
//!                           units, and for simulations the full config and scene
//!   amplitude.exr           observed amplitude α̃ (1 channel "Y", f32, sensor units)
//!   phase.exr               observed phase φ̃, radians in [0, 2π)
//!   amplitude_clear.exr     same scene without fog or noise          (simulation only)
//!   phase_clear.exr                                                 (simulation only)
//!   scatter_amplitude.exr   fog-only phasor α_s, φ_s (GT, Eq. 5.5)   (simulation only)
//!   scatter_phase.exr                                               (simulation only)
//!   gt_range_m.exr          distance along the ray to the surface, m (simulation only)
//!   gt_z_depth_m.exr        z-depth of the surface, m                (simulation only)
//!   gt_mask.png             16-bit gray, 65535 = lit object (measurable), 0 = else (simulation only)
//!   gt_object_mask.png      16-bit gray, 65535 = any object pixel, lit or not (simulation only)
//!   preview_*.png           Turbo-coloured previews, for people only
//! ```
//!
//! Real captures use the same layout with only `amplitude.exr`, `phase.exr` and (optionally)
//! `meta.json` holding `modulation_frequency_hz`, `intrinsics` and `light_position_m` (the
//! emitter in the camera frame, metres); read them with
//! [`read_tof_capture`].

pub mod mvs;
pub mod ps;
pub mod scene;
pub mod stereo_sequence;
pub mod tof;
pub mod tof_sequence;

use std::path::Path;

use serde::{Deserialize, Serialize};

pub use scene::{Scene, SceneLayout, SceneObject, Shape};
pub use stereo_sequence::{StereoFrame, StereoMotion, StereoSequence};
pub use tof::{
    scatter_along_ray, simulate_tof, wrap_phase, FogPreset, Phasor, TofSimConfig, TofSimFrame,
    MAX_SIM_PIXELS, MAX_SIM_SIDE,
};
pub use tof_sequence::{simulate_tof_sequence_frame, TofMotion};

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::io::{self, DecodeLimits};

/// `format` tag of `meta.json`.
pub const TOF_FRAME_FORMAT: &str = "murk.tof_frame";

#[derive(Serialize, Deserialize)]
pub(crate) struct IntrinsicsJson {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    #[serde(default)]
    skew: f64,
}

impl From<Intrinsics> for IntrinsicsJson {
    fn from(k: Intrinsics) -> Self {
        Self {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            skew: k.skew,
        }
    }
}

impl From<IntrinsicsJson> for Intrinsics {
    fn from(k: IntrinsicsJson) -> Self {
        Intrinsics {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            skew: k.skew,
        }
    }
}

#[derive(Serialize, Deserialize)]
struct TofMeta {
    #[serde(default)]
    format: Option<String>,
    #[serde(default)]
    version: Option<u32>,
    #[serde(default)]
    modulation_frequency_hz: Option<f64>,
    #[serde(default)]
    intrinsics: Option<IntrinsicsJson>,
    /// Light source in the camera frame, metres.
    #[serde(default)]
    light_position_m: Option<[f64; 3]>,
    #[serde(default)]
    beta_per_mm: Option<f64>,
    #[serde(default)]
    units: Option<serde_json::Value>,
    #[serde(default)]
    config: Option<TofSimConfig>,
    #[serde(default)]
    scene: Option<Scene>,
}

const IMAGE_FILES: [&str; 8] = [
    "amplitude.exr",
    "phase.exr",
    "amplitude_clear.exr",
    "phase_clear.exr",
    "scatter_amplitude.exr",
    "scatter_phase.exr",
    "gt_range_m.exr",
    "gt_z_depth_m.exr",
];

/// Writes `frame` into `dir` (created if missing) in the layout of the module docs.
pub fn write_tof_frame(dir: &Path, frame: &TofSimFrame) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| io::io_error(dir, e))?;
    let images = [
        &frame.amplitude,
        &frame.phase,
        &frame.amplitude_clear,
        &frame.phase_clear,
        &frame.scatter_amplitude,
        &frame.scatter_phase,
        &frame.gt_range_m,
        &frame.gt_z_depth_m,
    ];
    for (name, img) in IMAGE_FILES.iter().zip(images) {
        io::write_exr(&dir.join(name), img)?;
    }
    io::write_png16(&dir.join("gt_mask.png"), &frame.gt_mask, 0.0, 1.0)?;
    io::write_png16(
        &dir.join("gt_object_mask.png"),
        &frame.gt_object_mask,
        0.0,
        1.0,
    )?;

    let meta = TofMeta {
        format: Some(TOF_FRAME_FORMAT.to_string()),
        version: Some(1),
        modulation_frequency_hz: Some(frame.config.modulation_frequency_hz),
        intrinsics: Some(frame.intrinsics.into()),
        light_position_m: Some(frame.config.light_position_m()),
        beta_per_mm: Some(frame.config.effective_beta_per_mm()),
        units: Some(serde_json::json!({
            "amplitude": "linear sensor units",
            "phase": "radians in [0, 2pi)",
            "gt_range_m": "metres along the viewing ray",
            "gt_z_depth_m": "metres along the optical axis",
            "beta_per_mm": "per millimetre",
            "intrinsics": "pixels, origin at the centre of the top-left pixel",
            "scene": "metres, camera frame (+x right, +y down, +z forward)",
        })),
        config: Some(frame.config.clone()),
        scene: Some(frame.scene.clone()),
    };
    let json = serde_json::to_vec_pretty(&meta)
        .map_err(|e| MurkError::Numerical(format!("serialising meta.json: {e}")))?;
    io::write_file(&dir.join("meta.json"), &json)?;

    // Previews: ranges chosen for legibility; they carry no data.
    let amp_hi = percentile(&frame.amplitude, 0.99).max(1e-6);
    let preview = |name: &str, img: &ImageF32, lo: f32, hi: f32| {
        io::write_colormap_png(&dir.join(name), img, lo, hi, None)
    };
    let tau = std::f32::consts::TAU;
    preview("preview_amplitude.png", &frame.amplitude, 0.0, amp_hi)?;
    preview("preview_phase.png", &frame.phase, 0.0, tau)?;
    preview(
        "preview_scatter_amplitude.png",
        &frame.scatter_amplitude,
        0.0,
        percentile(&frame.scatter_amplitude, 0.99).max(1e-6),
    )?;
    let range_hi = percentile(&frame.gt_range_m, 1.0).max(1e-3);
    preview("preview_gt_range_m.png", &frame.gt_range_m, 0.0, range_hi)?;
    Ok(())
}

/// The `q`-quantile of the finite samples (0 when there are none).
fn percentile(img: &ImageF32, q: f64) -> f32 {
    let mut v: Vec<f32> = img
        .data()
        .iter()
        .copied()
        .filter(|x| x.is_finite())
        .collect();
    if v.is_empty() {
        return 0.0;
    }
    let i = (((v.len() - 1) as f64) * q.clamp(0.0, 1.0)).round() as usize;
    let (_, x, _) = v.select_nth_unstable_by(i, f32::total_cmp);
    *x
}

fn read_meta(dir: &Path, required: bool) -> Result<Option<TofMeta>> {
    let path = dir.join("meta.json");
    if !required && !path.exists() {
        return Ok(None);
    }
    let text = std::fs::read(&path).map_err(|e| io::io_error(&path, e))?;
    let meta: TofMeta = serde_json::from_slice(&text)
        .map_err(|e| MurkError::invalid("meta.json", format!("not valid frame metadata: {e}")))?;
    if let Some(f) = &meta.format {
        if f != TOF_FRAME_FORMAT {
            return Err(MurkError::invalid(
                "meta.json.format",
                format!("expected {TOF_FRAME_FORMAT:?}, got {f:?}"),
            ));
        }
    }
    Ok(Some(meta))
}

fn read_channel(dir: &Path, name: &str, dims: Option<(usize, usize)>) -> Result<ImageF32> {
    let limits = DecodeLimits {
        max_pixels: MAX_SIM_PIXELS as u64,
        max_channels: 1,
    };
    let img = io::read_image(&dir.join(name), &limits).map_err(|e| e.within(name))?;
    if let Some((w, h)) = dims {
        if img.dims() != (w, h) {
            return Err(MurkError::invalid(
                name,
                format!(
                    "size {}x{} differs from amplitude.exr's {w}x{h}",
                    img.width(),
                    img.height()
                ),
            ));
        }
    }
    Ok(img)
}

/// Reads a frame written by [`write_tof_frame`]; every file of the layout must be present.
pub fn read_tof_frame(dir: &Path) -> Result<TofSimFrame> {
    let meta = read_meta(dir, true)?.ok_or_else(|| MurkError::invalid("meta.json", "missing"))?;
    let config = meta
        .config
        .ok_or_else(|| MurkError::invalid("meta.json.config", "missing (not a simulated frame)"))?;
    let scene = meta
        .scene
        .ok_or_else(|| MurkError::invalid("meta.json.scene", "missing (not a simulated frame)"))?;
    let intrinsics: Intrinsics = meta
        .intrinsics
        .map(Into::into)
        .unwrap_or_else(|| config.intrinsics());
    intrinsics
        .validate()
        .map_err(|e| e.within("meta.json.intrinsics"))?;
    let amplitude = read_channel(dir, IMAGE_FILES[0], None)?;
    let dims = Some(amplitude.dims());
    let mut rest = Vec::with_capacity(7);
    for name in &IMAGE_FILES[1..] {
        rest.push(read_channel(dir, name, dims)?);
    }
    let gt_mask = read_channel(dir, "gt_mask.png", dims)?;
    let gt_object_mask = read_channel(dir, "gt_object_mask.png", dims)?;
    let mut it = rest.into_iter();
    let mut next = || {
        it.next()
            .ok_or_else(|| MurkError::Numerical("frame images".into()))
    };
    Ok(TofSimFrame {
        config,
        intrinsics,
        scene,
        amplitude,
        phase: next()?,
        amplitude_clear: next()?,
        phase_clear: next()?,
        scatter_amplitude: next()?,
        scatter_phase: next()?,
        gt_range_m: next()?,
        gt_z_depth_m: next()?,
        gt_mask,
        gt_object_mask,
    })
}

/// The part of a frame folder a real capture provides.
#[derive(Clone, Debug, PartialEq)]
pub struct TofCapture {
    /// Observed amplitude.
    pub amplitude: ImageF32,
    /// Observed phase, radians.
    pub phase: ImageF32,
    /// Intrinsics from `meta.json`, if given.
    pub intrinsics: Option<Intrinsics>,
    /// Modulation frequency from `meta.json`, if given.
    pub modulation_frequency_hz: Option<f64>,
    /// Light source position (camera frame, metres) from `meta.json`, if given.
    pub light_position_m: Option<[f64; 3]>,
}

/// Reads `amplitude.exr`, `phase.exr` and, when present, `meta.json` from `dir` (simulated frames
/// and real captures alike).
pub fn read_tof_capture(dir: &Path) -> Result<TofCapture> {
    let meta = read_meta(dir, false)?;
    let amplitude = read_channel(dir, "amplitude.exr", None)?;
    let phase = read_channel(dir, "phase.exr", Some(amplitude.dims()))?;
    let (intrinsics, modulation_frequency_hz, light_position_m) = match meta {
        Some(m) => (
            m.intrinsics.map(Intrinsics::from),
            m.modulation_frequency_hz,
            m.light_position_m,
        ),
        None => (None, None, None),
    };
    if let Some(k) = &intrinsics {
        k.validate().map_err(|e| e.within("meta.json.intrinsics"))?;
    }
    if let Some(l) = &light_position_m {
        if l.iter().any(|v| !v.is_finite()) {
            return Err(MurkError::invalid(
                "meta.json.light_position_m",
                format!("must be finite, got {l:?}"),
            ));
        }
    }
    Ok(TofCapture {
        amplitude,
        phase,
        intrinsics,
        modulation_frequency_hz,
        light_position_m,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::monitor::Monitor;

    fn approx_eq(a: &serde_json::Value, b: &serde_json::Value) -> bool {
        use serde_json::Value::*;
        match (a, b) {
            (Number(x), Number(y)) => match (x.as_f64(), y.as_f64()) {
                (Some(x), Some(y)) => (x - y).abs() <= 1e-12 * x.abs().max(y.abs()),
                _ => x == y,
            },
            (Array(x), Array(y)) => {
                x.len() == y.len() && x.iter().zip(y).all(|(a, b)| approx_eq(a, b))
            }
            (Object(x), Object(y)) => {
                x.len() == y.len()
                    && x.iter()
                        .all(|(k, v)| y.get(k).is_some_and(|w| approx_eq(v, w)))
            }
            _ => a == b,
        }
    }

    #[test]
    fn frame_write_read_round_trip() {
        let cfg = TofSimConfig {
            seed: 11,
            ..TofSimConfig::with_size(48, 40)
        };
        let frame = simulate_tof(&cfg, &Monitor::noop()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        write_tof_frame(dir.path(), &frame).unwrap();
        for f in IMAGE_FILES.iter().chain(&[
            "gt_mask.png",
            "gt_object_mask.png",
            "meta.json",
            "preview_amplitude.png",
        ]) {
            assert!(dir.path().join(f).is_file(), "{f} missing");
        }
        let back = read_tof_frame(dir.path()).unwrap();
        // Compare piecewise: a failure then names the part instead of dumping every pixel.
        // serde_json's default float parser may be 1 ulp off: metadata is compared to 1e-12.
        let cfgs = [&back.config, &frame.config].map(|c| serde_json::to_value(c).unwrap());
        assert!(approx_eq(&cfgs[0], &cfgs[1]), "config");
        let scenes = [&back.scene, &frame.scene].map(|s| serde_json::to_value(s).unwrap());
        assert!(approx_eq(&scenes[0], &scenes[1]), "scene");
        let (k1, k2) = (back.intrinsics, frame.intrinsics);
        for (a, b) in [
            (k1.fx, k2.fx),
            (k1.fy, k2.fy),
            (k1.cx, k2.cx),
            (k1.cy, k2.cy),
        ] {
            assert!((a - b).abs() <= 1e-12 * b.abs(), "intrinsics");
        }
        for (name, a, b) in [
            ("amplitude", &back.amplitude, &frame.amplitude),
            ("phase", &back.phase, &frame.phase),
            (
                "amplitude_clear",
                &back.amplitude_clear,
                &frame.amplitude_clear,
            ),
            ("phase_clear", &back.phase_clear, &frame.phase_clear),
            (
                "scatter_amplitude",
                &back.scatter_amplitude,
                &frame.scatter_amplitude,
            ),
            ("scatter_phase", &back.scatter_phase, &frame.scatter_phase),
            ("gt_range_m", &back.gt_range_m, &frame.gt_range_m),
            ("gt_z_depth_m", &back.gt_z_depth_m, &frame.gt_z_depth_m),
            ("gt_mask", &back.gt_mask, &frame.gt_mask),
        ] {
            assert!(a == b, "{name} differs after the round trip");
        }

        let cap = read_tof_capture(dir.path()).unwrap();
        assert_eq!(cap.amplitude, frame.amplitude);
        assert_eq!(cap.intrinsics, Some(frame.intrinsics));
        assert_eq!(cap.modulation_frequency_hz, Some(16e6));
    }

    #[test]
    fn capture_without_meta_and_broken_folders() {
        let dir = tempfile::tempdir().unwrap();
        let a = ImageF32::filled(4, 3, 1, 1.0);
        io::write_exr(&dir.path().join("amplitude.exr"), &a).unwrap();
        assert!(matches!(
            read_tof_capture(dir.path()),
            Err(MurkError::Io { .. })
        ));
        io::write_exr(
            &dir.path().join("phase.exr"),
            &ImageF32::filled(3, 3, 1, 0.0),
        )
        .unwrap();
        match read_tof_capture(dir.path()) {
            Err(MurkError::InvalidArgument { field, .. }) => assert_eq!(field, "phase.exr"),
            other => panic!("{other:?}"),
        }
        io::write_exr(&dir.path().join("phase.exr"), &a).unwrap();
        let cap = read_tof_capture(dir.path()).unwrap();
        assert_eq!(cap.intrinsics, None);
        std::fs::write(dir.path().join("meta.json"), b"{not json").unwrap();
        assert!(read_tof_capture(dir.path()).is_err());
        assert!(read_tof_frame(dir.path()).is_err());
    }
}
