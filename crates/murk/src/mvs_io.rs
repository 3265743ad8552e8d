//! Files ↔ multi-view stereo, for clients (`murk mvs`, `murk demo`): calibrated views from a
//! COLMAP sparse model plus an image folder, source-view selection by camera distance, the scene
//! metadata `murk simulate mvs` writes, ground-truth depth in the simulator's layout, and the
//! reference depth back-projected to a coloured point cloud written as PLY.
//!
//! The service never touches files; this module only reads and writes them around the library's
//! public types ([`ColmapModel`], [`ImageF32`], [`Intrinsics`], [`Pose`]).

use std::fmt::Write as _;
use std::path::{Component, Path, PathBuf};

use crate::atmosphere::AtmosphereParams;
use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::io::{self, decode_image, DecodeLimits};
use crate::mvs::colmap::{ColmapModel, IMAGES_FIELD};
use crate::mvs::{Pose, View};
use crate::params::sparse::SparseDepth;
use crate::simulate::mvs::MVS_SCENE_FORMAT;

/// A registered image loaded from disk with its calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadedView {
    /// Image name as in the COLMAP model (relative to the image folder).
    pub name: String,
    /// The image, 1 (grey) or 3 (RGB) channels.
    pub image: ImageF32,
    /// Pinhole intrinsics, pixels (murk convention).
    pub intrinsics: Intrinsics,
    /// World-to-camera pose, scene units.
    pub pose: Pose,
    /// The file's bytes when the decoded image is used unchanged, so a client can send the
    /// original encoding (smaller than raw f32 and identical once decoded); `None` when channels
    /// had to be dropped (alpha).
    pub encoded: Option<Vec<u8>>,
}

impl LoadedView {
    /// The library's borrowed view.
    pub fn view(&self) -> View<'_> {
        View {
            image: &self.image,
            intrinsics: self.intrinsics,
            pose: self.pose,
        }
    }
}

/// `name` as a path below the image folder. COLMAP names are relative (possibly with
/// sub-folders); an absolute name or one with `..` would read outside the folder, so it is
/// refused rather than followed.
fn relative_image_path(name: &str) -> Result<&Path> {
    let p = Path::new(name);
    let ok = !name.is_empty()
        && p.components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    if ok {
        Ok(p)
    } else {
        Err(MurkError::invalid(
            IMAGES_FIELD,
            format!("image name {name:?} is not a relative path inside the image folder"),
        ))
    }
}

/// Loads the registered image `name` from `images_dir` with its intrinsics and pose.
///
/// PNG (8/16-bit), TIFF and EXR are read through [`crate::io`] under `limits`. Grey+alpha keeps
/// grey and RGBA keeps RGB (the cost volumes take 1 or 3 channels). Fails when the image is not
/// in the model (naming `colmap.images`), its camera is not an undistorted pinhole, or the file's
/// size differs from the camera's (the intrinsics would not fit the pixels).
pub fn load_view(
    model: &ColmapModel,
    images_dir: &Path,
    name: &str,
    limits: &DecodeLimits,
) -> Result<LoadedView> {
    let registered = model.image_by_name(name).ok_or_else(|| {
        MurkError::invalid(
            IMAGES_FIELD,
            format!("no registered image named {name:?} in the COLMAP model"),
        )
    })?;
    let intrinsics = model.intrinsics_of(registered)?;
    let path = images_dir.join(relative_image_path(name)?);
    let bytes = std::fs::read(&path).map_err(|e| io::io_error(&path, e))?;
    let field = path.display().to_string();
    let decoded = decode_image(&bytes, limits).map_err(|e| e.within(&field))?;
    if let Some(cam) = model.cameras.get(&registered.camera_id) {
        let (w, h) = decoded.dims();
        if (w as u64, h as u64) != (cam.width, cam.height) {
            return Err(MurkError::invalid(
                field,
                format!(
                    "image is {w}x{h} but its COLMAP camera {} is {}x{}; use the images the \
                     model was made from (e.g. image_undistorter's output)",
                    cam.id, cam.width, cam.height
                ),
            ));
        }
    }
    let (image, encoded) = match decoded.channels() {
        1 | 3 => (decoded, Some(bytes)),
        2 => (decoded.channel(0), None),
        _ => (drop_alpha(&decoded)?, None),
    };
    Ok(LoadedView {
        name: name.to_string(),
        image,
        intrinsics,
        pose: registered.pose,
        encoded,
    })
}

/// The first three channels of a 4-channel image.
fn drop_alpha(img: &ImageF32) -> Result<ImageF32> {
    let c = img.channels();
    let data = img
        .data()
        .chunks_exact(c)
        .flat_map(|p| p.iter().take(3).copied())
        .collect();
    ImageF32::from_vec(img.width(), img.height(), 3, data)
}

/// Names of the `n` registered images whose camera centres are nearest the reference's (nearest
/// first, ties by name). Images at the reference's own position are skipped: with no baseline a
/// source constrains no depth (every plane maps a pixel to the same place).
pub fn nearest_sources(model: &ColmapModel, reference: &str, n: usize) -> Result<Vec<String>> {
    let r = model.image_by_name(reference).ok_or_else(|| {
        MurkError::invalid(
            IMAGES_FIELD,
            format!("no registered image named {reference:?} in the COLMAP model"),
        )
    })?;
    let centre = r.pose.camera_center();
    // "Identical" relative to the scene's scale, which SfM chooses arbitrarily.
    let eps = 1e-9 * centre.coords.norm().max(1.0);
    let mut others: Vec<(f64, &str)> = model
        .images
        .values()
        .filter(|im| im.name != reference)
        .map(|im| {
            let d = nalgebra::distance(&im.pose.camera_center(), &centre);
            (d, im.name.as_str())
        })
        .filter(|(d, _)| *d > eps)
        .collect();
    if others.is_empty() {
        return Err(MurkError::invalid(
            IMAGES_FIELD,
            format!("no registered image other than {reference:?} at a distinct camera position"),
        ));
    }
    others.sort_by(|a, b| a.0.total_cmp(&b.0).then_with(|| a.1.cmp(b.1)));
    Ok(others
        .into_iter()
        .take(n)
        .map(|(_, name)| name.to_string())
        .collect())
}

/// What `murk simulate mvs` recorded about a scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneMetadata {
    /// The `meta.json` it came from.
    pub path: PathBuf,
    /// Ground-truth airlight and β (per scene unit).
    pub atmosphere: AtmosphereParams,
    /// Name of the scene's reference view.
    pub reference: String,
}

/// Looks for the `meta.json` of a simulated scene next to a COLMAP model: in `model_dir` or up to
/// three folders above it (the simulator writes `<scene>/meta.json` and `<scene>/sparse/`; a
/// COLMAP reconstruction of its images typically sits in `<scene>/colmap/sparse/0`). `Ok(None)`
/// when there is none or it is not an MVS scene's; an MVS scene's file that cannot be read is an
/// error.
pub fn find_scene_metadata(model_dir: &Path) -> Result<Option<SceneMetadata>> {
    let candidates = model_dir.ancestors().take(4).map(|d| d.join("meta.json"));
    for path in candidates {
        if !path.is_file() {
            continue;
        }
        let bytes = std::fs::read(&path).map_err(|e| io::io_error(&path, e))?;
        let Ok(v) = serde_json::from_slice::<serde_json::Value>(&bytes) else {
            continue;
        };
        if v.get("format").and_then(|f| f.as_str()) != Some(MVS_SCENE_FORMAT) {
            continue;
        }
        let field = path.display().to_string();
        let number = |key: &str| {
            v.get(key)
                .and_then(serde_json::Value::as_f64)
                .ok_or_else(|| {
                    MurkError::invalid(&field, format!("`{key}` missing or not a number"))
                })
        };
        let atmosphere = AtmosphereParams {
            airlight: number("airlight")? as f32,
            beta: number("beta")? as f32,
        };
        atmosphere.validate().map_err(|e| e.within(&field))?;
        let reference = v
            .get("reference")
            .and_then(|r| r.as_str())
            .unwrap_or_default()
            .to_string();
        return Ok(Some(SceneMetadata {
            path,
            atmosphere,
            reference,
        }));
    }
    Ok(None)
}

/// Ground-truth z-depth of image `name` in the simulator's layout: `<images_dir>/../depth/` with
/// the name's extension replaced by `.exr`. `None` when there is no such file.
pub fn find_gt_depth(images_dir: &Path, name: &str) -> Option<PathBuf> {
    let rel = relative_image_path(name).ok()?.with_extension("exr");
    let path = images_dir.parent()?.join("depth").join(rel);
    path.is_file().then_some(path)
}

/// How many ground-truth (scene) units one model unit is: the median of `z_gt / z_sfm` over
/// the SfM pixels. `None` without usable pixels; `Some(1)` within 1 % of 1 (the simulator's own
/// model).
pub fn model_unit_in_scene_units(sparse: &SparseDepth, gt: &ImageF32) -> Option<f32> {
    if gt.dims() != (sparse.width(), sparse.height()) {
        return None;
    }
    let mut ratios: Vec<f32> = sparse
        .samples()
        .iter()
        .map(|s| gt.get(s.x as usize, s.y as usize, 0) / s.z)
        .filter(|r| r.is_finite() && *r > 0.0)
        .collect();
    if ratios.is_empty() {
        return None;
    }
    let mid = ratios.len() / 2;
    let s = *ratios.select_nth_unstable_by(mid, f32::total_cmp).1;
    Some(if (s - 1.0).abs() < 0.01 { 1.0 } else { s })
}

/// A note for printouts when the model's unit differs from the ground truth's ([`model_unit_in_scene_units`]).
pub fn unit_note(scale: Option<f32>) -> String {
    match scale {
        Some(s) if s != 1.0 => format!(
            " (the model's unit is {s:.4} scene units, from its points against the ground truth; \
             compared in one unit)"
        ),
        _ => String::new(),
    }
}

/// A world-space point with a colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColoredPoint {
    /// Position, world frame, scene units.
    pub xyz: [f64; 3],
    /// 8-bit RGB.
    pub rgb: [u8; 3],
}

/// Back-projects every reference pixel with a finite, positive z-depth and confidence ≥
/// `min_confidence` to world coordinates: `x_cam = z·K⁻¹(u, v, 1)`, `x_world = Rᵀ(x_cam − t)`.
/// Colours come from `colour` (values in `[0, 1]`, 1 or ≥ 3 channels; grey is replicated).
/// Fails naming `confidence` or `colour` when their size differs from the depth's.
pub fn backproject(
    z_depth: &ImageF32,
    confidence: &ImageF32,
    colour: &ImageF32,
    intrinsics: &Intrinsics,
    pose: &Pose,
    min_confidence: f32,
) -> Result<Vec<ColoredPoint>> {
    z_depth
        .ensure_channels(1)
        .map_err(|e| e.within("z_depth"))?;
    for (name, img) in [("confidence", confidence), ("colour", colour)] {
        if img.dims() != z_depth.dims() {
            return Err(MurkError::invalid(
                name,
                format!(
                    "size {}x{} differs from the depth's {}x{}",
                    img.width(),
                    img.height(),
                    z_depth.width(),
                    z_depth.height()
                ),
            ));
        }
    }
    let to_world = pose.inverse();
    let k = intrinsics;
    let c = colour.channels();
    let byte = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let mut points = Vec::new();
    for v in 0..z_depth.height() {
        for u in 0..z_depth.width() {
            let z = f64::from(z_depth.get(u, v, 0));
            let conf = confidence.get(u, v, 0);
            // A NaN confidence compares as neither, so it is skipped too.
            let confident = conf >= min_confidence;
            if !z.is_finite() || z <= 0.0 || !confident {
                continue;
            }
            let y = (v as f64 - k.cy) / k.fy;
            let x = (u as f64 - k.cx - k.skew * y) / k.fx;
            let xyz = to_world.transform([x * z, y * z, z]).into();
            let rgb = if c >= 3 {
                [
                    byte(colour.get(u, v, 0)),
                    byte(colour.get(u, v, 1)),
                    byte(colour.get(u, v, 2)),
                ]
            } else {
                [byte(colour.get(u, v, 0)); 3]
            };
            points.push(ColoredPoint { xyz, rgb });
        }
    }
    Ok(points)
}

/// PLY encodings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlyFormat {
    /// Human-readable text.
    Ascii,
    /// `binary_little_endian 1.0`: compact, what most viewers prefer for large clouds.
    BinaryLittleEndian,
}

/// Encodes points as a PLY file: `float x, y, z` (scene units) and `uchar red, green, blue`.
pub fn encode_ply(points: &[ColoredPoint], format: PlyFormat) -> Vec<u8> {
    let name = match format {
        PlyFormat::Ascii => "ascii",
        PlyFormat::BinaryLittleEndian => "binary_little_endian",
    };
    let mut header = String::new();
    // Writing to a String cannot fail.
    let _ = write!(
        header,
        "ply\nformat {name} 1.0\ncomment murk: reference depth in world coordinates, scene units\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    );
    let mut out = header.into_bytes();
    match format {
        PlyFormat::Ascii => {
            let mut body = String::with_capacity(points.len() * 40);
            for p in points {
                let [x, y, z] = p.xyz.map(|v| v as f32);
                let [r, g, b] = p.rgb;
                let _ = writeln!(body, "{x} {y} {z} {r} {g} {b}");
            }
            out.extend_from_slice(body.as_bytes());
        }
        PlyFormat::BinaryLittleEndian => {
            out.reserve(points.len() * 15);
            for p in points {
                for v in p.xyz {
                    out.extend_from_slice(&(v as f32).to_le_bytes());
                }
                out.extend_from_slice(&p.rgb);
            }
        }
    }
    out
}

/// Writes [`encode_ply`] to `path`.
pub fn write_ply(path: &Path, points: &[ColoredPoint], format: PlyFormat) -> Result<()> {
    io::write_file(path, &encode_ply(points, format))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::field_of;
    use crate::monitor::Monitor;
    use crate::simulate::mvs::{simulate_mvs, write_mvs_scene, MvsSimConfig};

    #[test]
    fn backprojection_lands_on_the_pixel_ray_in_world_coordinates() {
        let k = Intrinsics {
            fx: 40.0,
            fy: 42.0,
            cx: 3.5,
            cy: 2.5,
            skew: 0.3,
        };
        // A camera rotated 90° about y and moved: world-to-camera.
        let pose = Pose::from_rows(
            [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]],
            [0.5, -0.2, 1.0],
        )
        .unwrap();
        let depth = ImageF32::from_fn(8, 6, |x, y| 2.0 + 0.1 * (x + y) as f32);
        let mut conf = ImageF32::filled(8, 6, 1, 1.0);
        conf.set(0, 0, 0, 0.1);
        let colour = ImageF32::filled(8, 6, 1, 0.5);
        let pts = backproject(&depth, &conf, &colour, &k, &pose, 0.5).unwrap();
        assert_eq!(pts.len(), 8 * 6 - 1, "the low-confidence pixel is skipped");
        // Back into the camera: the point must project to its pixel at its depth.
        let first = pts[0];
        let cam = pose.transform(first.xyz);
        let (u, v) = k.project(cam).unwrap();
        assert!((u - 1.0).abs() < 1e-9 && v.abs() < 1e-9, "({u}, {v})");
        assert!((cam[2] - f64::from(depth.get(1, 0, 0))).abs() < 1e-6);
        assert_eq!(first.rgb, [128; 3]);
        let small = ImageF32::filled(4, 6, 1, 1.0);
        let e = backproject(&depth, &small, &colour, &k, &pose, 0.0).unwrap_err();
        assert_eq!(field_of(e), "confidence");
    }

    #[test]
    fn ply_header_and_sizes() {
        let pts = vec![
            ColoredPoint {
                xyz: [1.0, 2.0, 3.0],
                rgb: [255, 0, 7],
            };
            3
        ];
        let bin = encode_ply(&pts, PlyFormat::BinaryLittleEndian);
        let text = String::from_utf8_lossy(&bin);
        assert!(text.starts_with("ply\nformat binary_little_endian 1.0\n"));
        let end = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert!(text.contains("element vertex 3\n"));
        assert_eq!(bin.len() - end, 3 * 15);
        let ascii = String::from_utf8(encode_ply(&pts, PlyFormat::Ascii)).unwrap();
        assert!(ascii.ends_with("end_header\n1 2 3 255 0 7\n1 2 3 255 0 7\n1 2 3 255 0 7\n"));
    }

    #[test]
    fn loads_a_simulated_scene_and_picks_nearest_sources() {
        let scene = simulate_mvs(&MvsSimConfig::with_size(24, 16), &Monitor::noop()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        write_mvs_scene(dir.path(), &scene).unwrap();
        let model_dir = dir.path().join("sparse");
        let model = crate::mvs::colmap::read_colmap_dir(&model_dir).unwrap();
        let reference = &scene.views[scene.reference];

        let meta = find_scene_metadata(&model_dir).unwrap().expect("meta.json");
        assert_eq!(meta.reference, reference.name);
        assert_eq!(meta.atmosphere.airlight, scene.airlight);
        assert_eq!(meta.atmosphere.beta, scene.beta);
        assert!(find_scene_metadata(&dir.path().join("images"))
            .unwrap()
            .is_some());

        let images = dir.path().join("images");
        let v = load_view(&model, &images, &reference.name, &DecodeLimits::default()).unwrap();
        assert_eq!(v.image.dims(), (24, 16));
        assert_eq!(v.image.channels(), 3);
        assert!(v.encoded.is_some());
        assert_eq!(v.pose, reference.pose);
        assert!((v.intrinsics.cx - reference.intrinsics.cx).abs() < 1e-9);
        assert!(find_gt_depth(&images, &reference.name).is_some());
        assert!(find_gt_depth(&images, "nope.png").is_none());

        // The reference is the middle of 5 views on a line: its two neighbours come first.
        let near = nearest_sources(&model, &reference.name, 2).unwrap();
        assert_eq!(near.len(), 2);
        assert!(!near.contains(&reference.name));
        let all = nearest_sources(&model, &reference.name, 10).unwrap();
        assert_eq!(all.len(), scene.views.len() - 1);
        let d = |n: &str| {
            let c = model.image_by_name(n).unwrap().pose.camera_center();
            nalgebra::distance(&c, &reference.pose.camera_center())
        };
        assert!(all.windows(2).all(|w| d(&w[0]) <= d(&w[1])));

        let e = load_view(&model, &images, "missing.png", &DecodeLimits::default()).unwrap_err();
        assert_eq!(field_of(e), IMAGES_FIELD);
        let e = load_view(&model, &images, "../x.png", &DecodeLimits::default()).unwrap_err();
        assert_eq!(field_of(e), IMAGES_FIELD);
    }

    #[test]
    fn identical_positions_are_not_sources() {
        let scene = simulate_mvs(&MvsSimConfig::with_size(16, 12), &Monitor::noop()).unwrap();
        let mut model = scene.sparse.clone();
        let reference = scene.views[scene.reference].name.clone();
        // Every other image moved onto the reference's centre: nothing is left.
        let r_pose = model.image_by_name(&reference).unwrap().pose;
        for im in model.images.values_mut() {
            im.pose = r_pose;
        }
        let e = nearest_sources(&model, &reference, 4).unwrap_err();
        assert_eq!(field_of(e), IMAGES_FIELD);
    }
}
