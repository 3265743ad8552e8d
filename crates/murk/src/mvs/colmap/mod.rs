//! COLMAP sparse models (`cameras`, `images`, `points3D`), text and binary.
//!
//! Conventions carried over from COLMAP and converted where murk's differ:
//! - Poses are world-to-camera, `x_cam = R(q)·x_world + t`, Hamilton quaternion `(qw, qx, qy, qz)`:
//!   the same as [`Pose`], so they are used unchanged. Scene units are whatever the SfM run chose
//!   (SfM has no metric scale), so depths, planes and `β` are in those units too.
//! - COLMAP puts the **centre of the top-left pixel at (0.5, 0.5)**; murk puts it at (0, 0)
//!   (see [`crate::camera`]). [`ColmapCamera::intrinsics`] therefore subtracts 0.5 from the
//!   principal point and [`ColmapCamera::from_intrinsics`] adds it back. 2D keypoints
//!   ([`Point2D::xy`]) are kept in COLMAP's convention, exactly as stored.
//! - Only undistorted pinhole models (`PINHOLE`, `SIMPLE_PINHOLE`) become [`Intrinsics`]; for
//!   anything else run `colmap image_undistorter` first, which rewrites the model as `PINHOLE`
//!   and the images without distortion.
//!
//! Malformed files fail with `InvalidArgument` naming `colmap.cameras`, `colmap.images` or
//! `colmap.points3D` and saying where (line or byte offset); nothing here panics on file content,
//! and binary counts are checked against the bytes left before anything is allocated.

pub mod binary;
pub mod text;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::mvs::pose::Pose;

/// Field name used in errors about `cameras.txt` / `cameras.bin`.
pub const CAMERAS_FIELD: &str = "colmap.cameras";
/// Field name used in errors about `images.txt` / `images.bin`.
pub const IMAGES_FIELD: &str = "colmap.images";
/// Field name used in errors about `points3D.txt` / `points3D.bin`.
pub const POINTS_FIELD: &str = "colmap.points3D";

/// COLMAP camera models with their ids (binary format) and parameter counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CameraModel {
    /// `f, cx, cy`.
    SimplePinhole,
    /// `fx, fy, cx, cy`.
    Pinhole,
    /// `f, cx, cy, k`.
    SimpleRadial,
    /// `f, cx, cy, k1, k2`.
    Radial,
    /// `fx, fy, cx, cy, k1, k2, p1, p2`.
    OpenCv,
    /// `fx, fy, cx, cy, k1, k2, k3, k4`.
    OpenCvFisheye,
    /// `fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`.
    FullOpenCv,
    /// `fx, fy, cx, cy, omega`.
    Fov,
    /// `f, cx, cy, k`.
    SimpleRadialFisheye,
    /// `f, cx, cy, k1, k2`.
    RadialFisheye,
    /// `fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1`.
    ThinPrismFisheye,
    /// `fx, fy, cx, cy, k0..k5, p0, p1, s0..s3`.
    RadTanThinPrismFisheye,
}

const ALL_MODELS: [CameraModel; 12] = [
    CameraModel::SimplePinhole,
    CameraModel::Pinhole,
    CameraModel::SimpleRadial,
    CameraModel::Radial,
    CameraModel::OpenCv,
    CameraModel::OpenCvFisheye,
    CameraModel::FullOpenCv,
    CameraModel::Fov,
    CameraModel::SimpleRadialFisheye,
    CameraModel::RadialFisheye,
    CameraModel::ThinPrismFisheye,
    CameraModel::RadTanThinPrismFisheye,
];

impl CameraModel {
    /// COLMAP's numeric model id (binary files).
    pub fn id(self) -> i32 {
        match self {
            CameraModel::SimplePinhole => 0,
            CameraModel::Pinhole => 1,
            CameraModel::SimpleRadial => 2,
            CameraModel::Radial => 3,
            CameraModel::OpenCv => 4,
            CameraModel::OpenCvFisheye => 5,
            CameraModel::FullOpenCv => 6,
            CameraModel::Fov => 7,
            CameraModel::SimpleRadialFisheye => 8,
            CameraModel::RadialFisheye => 9,
            CameraModel::ThinPrismFisheye => 10,
            CameraModel::RadTanThinPrismFisheye => 11,
        }
    }

    /// COLMAP's model name (text files).
    pub fn name(self) -> &'static str {
        match self {
            CameraModel::SimplePinhole => "SIMPLE_PINHOLE",
            CameraModel::Pinhole => "PINHOLE",
            CameraModel::SimpleRadial => "SIMPLE_RADIAL",
            CameraModel::Radial => "RADIAL",
            CameraModel::OpenCv => "OPENCV",
            CameraModel::OpenCvFisheye => "OPENCV_FISHEYE",
            CameraModel::FullOpenCv => "FULL_OPENCV",
            CameraModel::Fov => "FOV",
            CameraModel::SimpleRadialFisheye => "SIMPLE_RADIAL_FISHEYE",
            CameraModel::RadialFisheye => "RADIAL_FISHEYE",
            CameraModel::ThinPrismFisheye => "THIN_PRISM_FISHEYE",
            CameraModel::RadTanThinPrismFisheye => "RAD_TAN_THIN_PRISM_FISHEYE",
        }
    }

    /// Number of parameters the model stores.
    pub fn num_params(self) -> usize {
        match self {
            CameraModel::SimplePinhole => 3,
            CameraModel::Pinhole => 4,
            CameraModel::SimpleRadial => 4,
            CameraModel::Radial => 5,
            CameraModel::OpenCv => 8,
            CameraModel::OpenCvFisheye => 8,
            CameraModel::FullOpenCv => 12,
            CameraModel::Fov => 5,
            CameraModel::SimpleRadialFisheye => 4,
            CameraModel::RadialFisheye => 5,
            CameraModel::ThinPrismFisheye => 12,
            CameraModel::RadTanThinPrismFisheye => 16,
        }
    }

    /// Model with binary id `id`, if known.
    pub fn from_id(id: i32) -> Option<Self> {
        ALL_MODELS.iter().copied().find(|m| m.id() == id)
    }

    /// Model named `name` (COLMAP spelling), if known.
    pub fn from_name(name: &str) -> Option<Self> {
        ALL_MODELS.iter().copied().find(|m| m.name() == name)
    }
}

/// One COLMAP camera (intrinsics shared by any number of images).
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    /// Camera id.
    pub id: u32,
    /// Camera model.
    pub model: CameraModel,
    /// Image width, pixels.
    pub width: u64,
    /// Image height, pixels.
    pub height: u64,
    /// Model parameters in COLMAP's order and pixel convention; `model.num_params()` of them.
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// murk intrinsics of an undistorted pinhole camera, principal point shifted by −0.5 px from
    /// COLMAP's pixel convention to murk's. Fails naming `model` for distorting models (with the
    /// advice to run COLMAP's image undistorter) and `params` for a wrong parameter count or
    /// non-finite / non-positive values; callers prefix the camera's path.
    pub fn intrinsics(&self) -> Result<Intrinsics> {
        if self.params.len() != self.model.num_params() {
            return Err(MurkError::invalid(
                "params",
                format!(
                    "{} needs {} parameters, got {}",
                    self.model.name(),
                    self.model.num_params(),
                    self.params.len()
                ),
            ));
        }
        let p = &self.params;
        let k = match self.model {
            CameraModel::SimplePinhole => Intrinsics::new(p[0], p[0], p[1] - 0.5, p[2] - 0.5),
            CameraModel::Pinhole => Intrinsics::new(p[0], p[1], p[2] - 0.5, p[3] - 0.5),
            other => {
                return Err(MurkError::invalid(
                    "model",
                    format!(
                        "camera {} uses the distorting model {}; murk needs undistorted pinhole \
                         cameras (PINHOLE or SIMPLE_PINHOLE): run COLMAP's image_undistorter \
                         (`colmap image_undistorter --input_path <sparse> --output_path <out>`) \
                         first and use its images and sparse model",
                        self.id,
                        other.name()
                    ),
                ))
            }
        };
        k.validate().map_err(|e| e.within("params"))?;
        Ok(k)
    }

    /// A `PINHOLE` camera for murk intrinsics `k` (principal point shifted by +0.5 px into
    /// COLMAP's convention). Fails naming `skew` when `k` has skew, which COLMAP cannot store.
    pub fn from_intrinsics(id: u32, k: &Intrinsics, width: u64, height: u64) -> Result<Self> {
        k.validate()?;
        if k.skew != 0.0 {
            return Err(MurkError::invalid(
                "skew",
                format!("COLMAP pinhole cameras have no skew, got {}", k.skew),
            ));
        }
        Ok(Self {
            id,
            model: CameraModel::Pinhole,
            width,
            height,
            params: vec![k.fx, k.fy, k.cx + 0.5, k.cy + 0.5],
        })
    }
}

/// A 2D keypoint of an image, COLMAP pixel convention (top-left pixel centre at (0.5, 0.5)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point2D {
    /// Pixel position `(x, y)`, COLMAP convention.
    pub xy: [f64; 2],
    /// The 3D point it observes, if triangulated (COLMAP's −1 becomes `None`).
    pub point3d_id: Option<u64>,
}

/// One registered image.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    /// Image id.
    pub id: u32,
    /// The camera (intrinsics) it was taken with.
    pub camera_id: u32,
    /// File name relative to the image folder.
    pub name: String,
    /// World-to-camera rotation as stored, `(qw, qx, qy, qz)`; writers emit it unchanged.
    pub qvec: [f64; 4],
    /// World-to-camera translation as stored (scene units); writers emit it unchanged.
    pub tvec: [f64; 3],
    /// The pose built from `qvec`/`tvec` when the image was read or made with
    /// [`ColmapImage::new`]; keep the three consistent when editing by hand.
    pub pose: Pose,
    /// Keypoints (may be empty).
    pub points2d: Vec<Point2D>,
}

impl ColmapImage {
    /// An image with pose `pose` (world-to-camera); the quaternion is derived from its rotation.
    pub fn new(
        id: u32,
        camera_id: u32,
        name: impl Into<String>,
        pose: &Pose,
        points2d: Vec<Point2D>,
    ) -> Result<Self> {
        pose.validate()?;
        let qvec = pose.colmap_qvec();
        let tvec = (*pose.translation()).into();
        Ok(Self {
            id,
            camera_id,
            name: name.into(),
            qvec,
            tvec,
            pose: Pose::from_colmap(qvec, tvec)?,
            points2d,
        })
    }
}

/// One element of a 3D point's track: the image and the index of its keypoint there.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TrackElement {
    /// Image id.
    pub image_id: u32,
    /// Index into that image's [`ColmapImage::points2d`].
    pub point2d_idx: u32,
}

/// A triangulated 3D point.
#[derive(Clone, Debug, PartialEq)]
pub struct Point3D {
    /// Point id.
    pub id: u64,
    /// World position, scene units.
    pub xyz: [f64; 3],
    /// Colour, 8-bit RGB.
    pub rgb: [u8; 3],
    /// Mean reprojection error, pixels (COLMAP writes −1 when unknown).
    pub error: f64,
    /// Observations.
    pub track: Vec<TrackElement>,
}

/// A COLMAP sparse model.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    /// Cameras by id.
    pub cameras: BTreeMap<u32, ColmapCamera>,
    /// Registered images by id.
    pub images: BTreeMap<u32, ColmapImage>,
    /// 3D points by id.
    pub points: BTreeMap<u64, Point3D>,
}

impl ColmapModel {
    /// The image named `name` (exact match), if any.
    pub fn image_by_name(&self, name: &str) -> Option<&ColmapImage> {
        self.images.values().find(|im| im.name == name)
    }

    /// murk intrinsics of `image`'s camera; errors name `colmap.cameras[<id>].…`.
    pub fn intrinsics_of(&self, image: &ColmapImage) -> Result<Intrinsics> {
        let cam = self.cameras.get(&image.camera_id).ok_or_else(|| {
            MurkError::invalid(
                IMAGES_FIELD,
                format!(
                    "image {} ({}) refers to missing camera {}",
                    image.id, image.name, image.camera_id
                ),
            )
        })?;
        cam.intrinsics()
            .map_err(|e| e.within(&format!("{CAMERAS_FIELD}[{}]", cam.id)))
    }

    /// Checks cross-references: every image's camera exists and every track element names an
    /// existing image and keypoint index.
    pub fn validate_references(&self) -> Result<()> {
        for im in self.images.values() {
            if !self.cameras.contains_key(&im.camera_id) {
                return Err(MurkError::invalid(
                    IMAGES_FIELD,
                    format!(
                        "image {} ({}) refers to missing camera {}",
                        im.id, im.name, im.camera_id
                    ),
                ));
            }
        }
        for p in self.points.values() {
            for el in &p.track {
                let ok = self
                    .images
                    .get(&el.image_id)
                    .is_some_and(|im| (el.point2d_idx as usize) < im.points2d.len());
                if !ok {
                    return Err(MurkError::invalid(
                        POINTS_FIELD,
                        format!(
                            "point {} observes image {} keypoint {}, which does not exist",
                            p.id, el.image_id, el.point2d_idx
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}

/// On-disk flavour of a model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelFormat {
    /// `cameras.txt`, `images.txt`, `points3D.txt`.
    Text,
    /// `cameras.bin`, `images.bin`, `points3D.bin`.
    Binary,
}

impl ModelFormat {
    fn ext(self) -> &'static str {
        match self {
            ModelFormat::Text => "txt",
            ModelFormat::Binary => "bin",
        }
    }

    /// The three file paths of this format in `dir` (cameras, images, points3D).
    pub fn paths(self, dir: &Path) -> [PathBuf; 3] {
        let e = self.ext();
        [
            dir.join(format!("cameras.{e}")),
            dir.join(format!("images.{e}")),
            dir.join(format!("points3D.{e}")),
        ]
    }
}

/// Which format `dir` holds: binary when all three `.bin` files exist, else text when all three
/// `.txt` files exist (COLMAP's own preference order). Fails naming `colmap` otherwise.
pub fn detect_format(dir: &Path) -> Result<ModelFormat> {
    for f in [ModelFormat::Binary, ModelFormat::Text] {
        if f.paths(dir).iter().all(|p| p.is_file()) {
            return Ok(f);
        }
    }
    Err(MurkError::invalid(
        "colmap",
        format!(
            "{} holds no complete COLMAP sparse model (need cameras, images and points3D, all \
             .bin or all .txt)",
            dir.display()
        ),
    ))
}

fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| MurkError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|e| MurkError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

/// Reads the model in `dir` in the format [`detect_format`] finds, and checks cross-references.
pub fn read_colmap_dir(dir: impl AsRef<Path>) -> Result<ColmapModel> {
    let dir = dir.as_ref();
    read_colmap(dir, detect_format(dir)?)
}

/// Reads the model in `dir` in the given format, and checks cross-references.
pub fn read_colmap(dir: impl AsRef<Path>, format: ModelFormat) -> Result<ColmapModel> {
    let [cp, ip, pp] = format.paths(dir.as_ref());
    let (c, i, p) = (read_file(&cp)?, read_file(&ip)?, read_file(&pp)?);
    let label = |p: &Path| p.display().to_string();
    let model = match format {
        ModelFormat::Binary => ColmapModel {
            cameras: binary::parse_cameras(&c, &label(&cp))?,
            images: binary::parse_images(&i, &label(&ip))?,
            points: binary::parse_points3d(&p, &label(&pp))?,
        },
        ModelFormat::Text => ColmapModel {
            cameras: text::parse_cameras(&utf8(c, CAMERAS_FIELD, &cp)?, &label(&cp))?,
            images: text::parse_images(&utf8(i, IMAGES_FIELD, &ip)?, &label(&ip))?,
            points: text::parse_points3d(&utf8(p, POINTS_FIELD, &pp)?, &label(&pp))?,
        },
    };
    model.validate_references()?;
    Ok(model)
}

fn utf8(bytes: Vec<u8>, field: &str, path: &Path) -> Result<String> {
    String::from_utf8(bytes)
        .map_err(|e| MurkError::invalid(field, format!("{}: not UTF-8 text ({e})", path.display())))
}

/// Writes `model` as `cameras.txt`, `images.txt`, `points3D.txt` into `dir` (which must exist),
/// in COLMAP's layout with its comment headers.
pub fn write_colmap_text(dir: impl AsRef<Path>, model: &ColmapModel) -> Result<()> {
    let [cp, ip, pp] = ModelFormat::Text.paths(dir.as_ref());
    write_file(&cp, text::format_cameras(&model.cameras).as_bytes())?;
    write_file(&ip, text::format_images(&model.images)?.as_bytes())?;
    write_file(&pp, text::format_points3d(&model.points).as_bytes())
}

/// Writes `model` as `cameras.bin`, `images.bin`, `points3D.bin` into `dir` (which must exist).
pub fn write_colmap_binary(dir: impl AsRef<Path>, model: &ColmapModel) -> Result<()> {
    let [cp, ip, pp] = ModelFormat::Binary.paths(dir.as_ref());
    write_file(&cp, &binary::encode_cameras(&model.cameras))?;
    write_file(&ip, &binary::encode_images(&model.images)?)?;
    write_file(&pp, &binary::encode_points3d(&model.points))
}

#[cfg(test)]
mod tests;
