//! COLMAP binary format, little-endian throughout (COLMAP's `Write/ReadBinaryLittleEndian`):
//!
//! - `cameras.bin`: `u64 n`, then per camera `u32 camera_id, i32 model_id, u64 width,
//!   u64 height, f64 params[num_params(model)]`.
//! - `images.bin`: `u64 n`, then per image `u32 image_id, f64 qw qx qy qz, f64 tx ty tz,
//!   u32 camera_id, name bytes + NUL, u64 num_points2D`, then per keypoint `f64 x, f64 y,
//!   u64 point3D_id` (`u64::MAX`, i.e. −1 as i64, = untriangulated).
//! - `points3D.bin`: `u64 n`, then per point `u64 point3D_id, f64 x y z, u8 r g b, f64 error,
//!   u64 track_length`, then per element `u32 image_id, u32 point2D_idx`.
//!
//! Every count is checked against the bytes left (count × smallest record size) before anything
//! is reserved, so a corrupt count cannot trigger a huge allocation.

use std::collections::BTreeMap;

use super::{
    CameraModel, ColmapCamera, ColmapImage, Point2D, Point3D, TrackElement, CAMERAS_FIELD,
    IMAGES_FIELD, POINTS_FIELD,
};
use crate::error::{MurkError, Result};
use crate::mvs::pose::Pose;

/// Bounds-checked little-endian reader over a byte slice; every error names the file and offset.
struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
    field: &'static str,
    label: &'a str,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8], field: &'static str, label: &'a str) -> Self {
        Self {
            bytes,
            pos: 0,
            field,
            label,
        }
    }

    fn err(&self, reason: impl std::fmt::Display) -> MurkError {
        MurkError::invalid(
            self.field,
            format!("{} at byte {}: {reason}", self.label, self.pos),
        )
    }

    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    fn take<const N: usize>(&mut self, what: &str) -> Result<[u8; N]> {
        let end = self
            .pos
            .checked_add(N)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| self.err(format!("file truncated while reading {what}")))?;
        let mut out = [0u8; N];
        out.copy_from_slice(&self.bytes[self.pos..end]);
        self.pos = end;
        Ok(out)
    }

    fn u8(&mut self, what: &str) -> Result<u8> {
        Ok(self.take::<1>(what)?[0])
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(what)?))
    }
    fn i32(&mut self, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(what)?))
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(what)?))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(what)?))
    }

    /// A count of records at least `min_record` bytes each, checked against the bytes left.
    fn count(&mut self, what: &str, min_record: usize) -> Result<usize> {
        let n = self.u64(what)?;
        let cap = self.remaining() / min_record.max(1);
        if n > cap as u64 {
            return Err(self.err(format!(
                "{what} = {n} cannot fit in the {} bytes left (file corrupt or truncated)",
                self.remaining()
            )));
        }
        Ok(n as usize)
    }

    /// NUL-terminated UTF-8 string.
    fn cstr(&mut self, what: &str) -> Result<String> {
        let rest = &self.bytes[self.pos..];
        let len = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| self.err(format!("file truncated inside {what} (no NUL terminator)")))?;
        let s = std::str::from_utf8(&rest[..len])
            .map_err(|e| self.err(format!("{what} is not UTF-8 ({e})")))?
            .to_string();
        self.pos += len + 1;
        Ok(s)
    }

    fn finish(&self) -> Result<()> {
        if self.remaining() != 0 {
            return Err(self.err(format!(
                "{} unexpected trailing bytes after the last record",
                self.remaining()
            )));
        }
        Ok(())
    }
}

/// Smallest camera record: ids, size and the 3 parameters of SIMPLE_PINHOLE.
const MIN_CAMERA_BYTES: usize = 4 + 4 + 8 + 8 + 3 * 8;
/// Smallest image record: id, pose, camera id, empty name's NUL, keypoint count.
const MIN_IMAGE_BYTES: usize = 4 + 7 * 8 + 4 + 1 + 8;
const POINT2D_BYTES: usize = 8 + 8 + 8;
/// Smallest point record: id, xyz, rgb, error, track length.
const MIN_POINT3D_BYTES: usize = 8 + 3 * 8 + 3 + 8 + 8;
const TRACK_ELEMENT_BYTES: usize = 4 + 4;

/// Parses `cameras.bin`; `label` names the file in errors (field `colmap.cameras`).
pub fn parse_cameras(bytes: &[u8], label: &str) -> Result<BTreeMap<u32, ColmapCamera>> {
    let mut r = Reader::new(bytes, CAMERAS_FIELD, label);
    let n = r.count("number of cameras", MIN_CAMERA_BYTES)?;
    let mut out = BTreeMap::new();
    for _ in 0..n {
        let id = r.u32("CAMERA_ID")?;
        let model_id = r.i32("MODEL_ID")?;
        let model = CameraModel::from_id(model_id)
            .ok_or_else(|| r.err(format!("camera {id}: unknown camera model id {model_id}")))?;
        let width = r.u64("WIDTH")?;
        let height = r.u64("HEIGHT")?;
        let mut params = Vec::with_capacity(model.num_params());
        for _ in 0..model.num_params() {
            params.push(r.f64("camera parameters")?);
        }
        let cam = ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        };
        if out.insert(id, cam).is_some() {
            return Err(r.err(format!("duplicate camera id {id}")));
        }
    }
    r.finish()?;
    Ok(out)
}

/// Parses `images.bin`; `label` names the file in errors (field `colmap.images`).
pub fn parse_images(bytes: &[u8], label: &str) -> Result<BTreeMap<u32, ColmapImage>> {
    let mut r = Reader::new(bytes, IMAGES_FIELD, label);
    let n = r.count("number of images", MIN_IMAGE_BYTES)?;
    let mut out = BTreeMap::new();
    for _ in 0..n {
        let id = r.u32("IMAGE_ID")?;
        let mut qvec = [0.0; 4];
        for v in &mut qvec {
            *v = r.f64("quaternion")?;
        }
        let mut tvec = [0.0; 3];
        for v in &mut tvec {
            *v = r.f64("translation")?;
        }
        let pose = Pose::from_colmap(qvec, tvec).map_err(|e| r.err(format!("image {id}: {e}")))?;
        let camera_id = r.u32("CAMERA_ID")?;
        let name = r.cstr("image name")?;
        let np = r.count("number of keypoints", POINT2D_BYTES)?;
        let mut points2d = Vec::with_capacity(np);
        for _ in 0..np {
            let x = r.f64("keypoint x")?;
            let y = r.f64("keypoint y")?;
            let pid = r.u64("POINT3D_ID")?;
            points2d.push(Point2D {
                xy: [x, y],
                point3d_id: (pid != u64::MAX).then_some(pid),
            });
        }
        let im = ColmapImage {
            id,
            camera_id,
            name,
            qvec,
            tvec,
            pose,
            points2d,
        };
        if out.insert(id, im).is_some() {
            return Err(r.err(format!("duplicate image id {id}")));
        }
    }
    r.finish()?;
    Ok(out)
}

/// Parses `points3D.bin`; `label` names the file in errors (field `colmap.points3D`).
pub fn parse_points3d(bytes: &[u8], label: &str) -> Result<BTreeMap<u64, Point3D>> {
    let mut r = Reader::new(bytes, POINTS_FIELD, label);
    let n = r.count("number of points", MIN_POINT3D_BYTES)?;
    let mut out = BTreeMap::new();
    for _ in 0..n {
        let id = r.u64("POINT3D_ID")?;
        let mut xyz = [0.0; 3];
        for v in &mut xyz {
            *v = r.f64("position")?;
        }
        if xyz.iter().any(|v| !v.is_finite()) {
            return Err(r.err(format!("point {id} has a non-finite position")));
        }
        let rgb = [r.u8("colour")?, r.u8("colour")?, r.u8("colour")?];
        let error = r.f64("ERROR")?;
        let nt = r.count("track length", TRACK_ELEMENT_BYTES)?;
        let mut track = Vec::with_capacity(nt);
        for _ in 0..nt {
            track.push(TrackElement {
                image_id: r.u32("track IMAGE_ID")?,
                point2d_idx: r.u32("track POINT2D_IDX")?,
            });
        }
        let p = Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        };
        if out.insert(id, p).is_some() {
            return Err(r.err(format!("duplicate point id {id}")));
        }
    }
    r.finish()?;
    Ok(out)
}

/// `cameras.bin` bytes.
pub fn encode_cameras(cameras: &BTreeMap<u32, ColmapCamera>) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend((cameras.len() as u64).to_le_bytes());
    for c in cameras.values() {
        b.extend(c.id.to_le_bytes());
        b.extend(c.model.id().to_le_bytes());
        b.extend(c.width.to_le_bytes());
        b.extend(c.height.to_le_bytes());
        for p in &c.params {
            b.extend(p.to_le_bytes());
        }
    }
    b
}

/// `images.bin` bytes. Fails naming `colmap.images` for a name containing NUL.
pub fn encode_images(images: &BTreeMap<u32, ColmapImage>) -> Result<Vec<u8>> {
    let mut b = Vec::new();
    b.extend((images.len() as u64).to_le_bytes());
    for im in images.values() {
        if im.name.as_bytes().contains(&0) {
            return Err(MurkError::invalid(
                IMAGES_FIELD,
                format!("image {}: name contains NUL", im.id),
            ));
        }
        b.extend(im.id.to_le_bytes());
        for v in im.qvec.iter().chain(&im.tvec) {
            b.extend(v.to_le_bytes());
        }
        b.extend(im.camera_id.to_le_bytes());
        b.extend(im.name.as_bytes());
        b.push(0);
        b.extend((im.points2d.len() as u64).to_le_bytes());
        for p in &im.points2d {
            b.extend(p.xy[0].to_le_bytes());
            b.extend(p.xy[1].to_le_bytes());
            b.extend(p.point3d_id.unwrap_or(u64::MAX).to_le_bytes());
        }
    }
    Ok(b)
}

/// `points3D.bin` bytes.
pub fn encode_points3d(points: &BTreeMap<u64, Point3D>) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend((points.len() as u64).to_le_bytes());
    for p in points.values() {
        b.extend(p.id.to_le_bytes());
        for v in &p.xyz {
            b.extend(v.to_le_bytes());
        }
        b.extend(p.rgb);
        b.extend(p.error.to_le_bytes());
        b.extend((p.track.len() as u64).to_le_bytes());
        for t in &p.track {
            b.extend(t.image_id.to_le_bytes());
            b.extend(t.point2d_idx.to_le_bytes());
        }
    }
    b
}
