//! COLMAP text format: `cameras.txt`, `images.txt` (two lines per image), `points3D.txt`.
//! Lines starting with `#` and blank lines are skipped, except the keypoint line that follows
//! every image line, which may be empty.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::str::FromStr;

use super::{
    CameraModel, ColmapCamera, ColmapImage, Point2D, Point3D, TrackElement, CAMERAS_FIELD,
    IMAGES_FIELD, POINTS_FIELD,
};
use crate::error::{MurkError, Result};
use crate::mvs::pose::Pose;

fn err(field: &str, label: &str, line_no: usize, reason: impl std::fmt::Display) -> MurkError {
    MurkError::invalid(field, format!("{label}:{line_no}: {reason}"))
}

fn parse<T: FromStr>(tok: &str, what: &str, field: &str, label: &str, line_no: usize) -> Result<T> {
    tok.parse::<T>().map_err(|_| {
        err(
            field,
            label,
            line_no,
            format!("cannot parse {what} from `{tok}`"),
        )
    })
}

/// Data lines with their 1-based numbers: skips comments and blank lines.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

/// Parses `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`. `label` names the file in errors.
pub fn parse_cameras(text: &str, label: &str) -> Result<BTreeMap<u32, ColmapCamera>> {
    let f = CAMERAS_FIELD;
    let mut out = BTreeMap::new();
    for (n, line) in data_lines(text) {
        let tok: Vec<&str> = line.split_whitespace().collect();
        if tok.len() < 4 {
            return Err(err(
                f,
                label,
                n,
                "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]",
            ));
        }
        let id: u32 = parse(tok[0], "CAMERA_ID", f, label, n)?;
        let model = CameraModel::from_name(tok[1])
            .ok_or_else(|| err(f, label, n, format!("unknown camera model `{}`", tok[1])))?;
        let width: u64 = parse(tok[2], "WIDTH", f, label, n)?;
        let height: u64 = parse(tok[3], "HEIGHT", f, label, n)?;
        let params = tok[4..]
            .iter()
            .map(|t| parse::<f64>(t, "a camera parameter", f, label, n))
            .collect::<Result<Vec<_>>>()?;
        if params.len() != model.num_params() {
            return Err(err(
                f,
                label,
                n,
                format!(
                    "{} needs {} parameters, got {}",
                    model.name(),
                    model.num_params(),
                    params.len()
                ),
            ));
        }
        let cam = ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        };
        if out.insert(id, cam).is_some() {
            return Err(err(f, label, n, format!("duplicate camera id {id}")));
        }
    }
    Ok(out)
}

/// Parses `images.txt`: per image a line `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and a
/// line of `X Y POINT3D_ID` triples (possibly empty; `POINT3D_ID = −1` means untriangulated).
/// A name may contain single spaces: everything after `CAMERA_ID` is the name.
pub fn parse_images(text: &str, label: &str) -> Result<BTreeMap<u32, ColmapImage>> {
    let f = IMAGES_FIELD;
    let mut out = BTreeMap::new();
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
    while let Some((n, line)) = lines.next() {
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let tok: Vec<&str> = line.split_whitespace().collect();
        if tok.len() < 10 {
            return Err(err(
                f,
                label,
                n,
                "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME",
            ));
        }
        let id: u32 = parse(tok[0], "IMAGE_ID", f, label, n)?;
        let mut nums = [0.0f64; 7];
        for (k, v) in nums.iter_mut().enumerate() {
            *v = parse(tok[1 + k], "a pose value", f, label, n)?;
        }
        let camera_id: u32 = parse(tok[8], "CAMERA_ID", f, label, n)?;
        let name = tok[9..].join(" ");
        let qvec = [nums[0], nums[1], nums[2], nums[3]];
        let tvec = [nums[4], nums[5], nums[6]];
        let pose = Pose::from_colmap(qvec, tvec)
            .map_err(|e| err(f, label, n, format!("image {id}: {e}")))?;
        // The keypoint line always follows, even when empty; a missing one at EOF means none.
        let (pn, pline) = lines.next().unwrap_or((n + 1, ""));
        let ptok: Vec<&str> = pline.split_whitespace().collect();
        if !ptok.len().is_multiple_of(3) {
            return Err(err(
                f,
                label,
                pn,
                format!(
                    "keypoint line of image {id} must hold X Y POINT3D_ID triples, got {} values",
                    ptok.len()
                ),
            ));
        }
        let mut points2d = Vec::with_capacity(ptok.len() / 3);
        for tr in ptok.chunks_exact(3) {
            let x: f64 = parse(tr[0], "keypoint X", f, label, pn)?;
            let y: f64 = parse(tr[1], "keypoint Y", f, label, pn)?;
            let point3d_id = if tr[2] == "-1" {
                None
            } else {
                Some(parse::<u64>(tr[2], "POINT3D_ID", f, label, pn)?)
            };
            points2d.push(Point2D {
                xy: [x, y],
                point3d_id,
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
            return Err(err(f, label, n, format!("duplicate image id {id}")));
        }
    }
    Ok(out)
}

/// Parses `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID POINT2D_IDX)`.
pub fn parse_points3d(text: &str, label: &str) -> Result<BTreeMap<u64, Point3D>> {
    let f = POINTS_FIELD;
    let mut out = BTreeMap::new();
    for (n, line) in data_lines(text) {
        let tok: Vec<&str> = line.split_whitespace().collect();
        if tok.len() < 8 || !(tok.len() - 8).is_multiple_of(2) {
            return Err(err(
                f,
                label,
                n,
                "expected POINT3D_ID X Y Z R G B ERROR followed by IMAGE_ID POINT2D_IDX pairs",
            ));
        }
        let id: u64 = parse(tok[0], "POINT3D_ID", f, label, n)?;
        let mut xyz = [0.0f64; 3];
        for (k, v) in xyz.iter_mut().enumerate() {
            *v = parse(tok[1 + k], "a coordinate", f, label, n)?;
        }
        if xyz.iter().any(|v| !v.is_finite()) {
            return Err(err(
                f,
                label,
                n,
                format!("point {id} has a non-finite position"),
            ));
        }
        let mut rgb = [0u8; 3];
        for (k, v) in rgb.iter_mut().enumerate() {
            *v = parse(tok[4 + k], "a colour (0..=255)", f, label, n)?;
        }
        let error: f64 = parse(tok[7], "ERROR", f, label, n)?;
        let track = tok[8..]
            .chunks_exact(2)
            .map(|pair| {
                Ok(TrackElement {
                    image_id: parse(pair[0], "IMAGE_ID", f, label, n)?,
                    point2d_idx: parse(pair[1], "POINT2D_IDX", f, label, n)?,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let p = Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        };
        if out.insert(id, p).is_some() {
            return Err(err(f, label, n, format!("duplicate point id {id}")));
        }
    }
    Ok(out)
}

// `{}` on f64 prints the shortest decimal that parses back to the same value, so text written
// here round-trips bit-exactly.

/// `cameras.txt` contents in COLMAP's layout.
pub fn format_cameras(cameras: &BTreeMap<u32, ColmapCamera>) -> String {
    let mut s = String::new();
    s.push_str("# Camera list with one line of data per camera:\n");
    s.push_str("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let _ = writeln!(s, "# Number of cameras: {}", cameras.len());
    for c in cameras.values() {
        let _ = write!(s, "{} {} {} {}", c.id, c.model.name(), c.width, c.height);
        for p in &c.params {
            let _ = write!(s, " {p}");
        }
        s.push('\n');
    }
    s
}

/// `images.txt` contents in COLMAP's layout. Fails naming `colmap.images` for a name that is
/// empty or holds line breaks, tabs or leading/trailing/double spaces (it would not read back).
pub fn format_images(images: &BTreeMap<u32, ColmapImage>) -> Result<String> {
    let mut s = String::new();
    let n_obs: usize = images.values().map(|im| im.points2d.len()).sum();
    let mean = if images.is_empty() {
        0.0
    } else {
        n_obs as f64 / images.len() as f64
    };
    s.push_str("# Image list with two lines of data per image:\n");
    s.push_str("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    s.push_str("#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    let _ = writeln!(
        s,
        "# Number of images: {}, mean observations per image: {mean}",
        images.len()
    );
    for im in images.values() {
        let name_ok = !im.name.is_empty()
            && !im.name.contains(['\n', '\r', '\t'])
            && im.name.trim() == im.name
            && !im.name.contains("  ");
        if !name_ok {
            return Err(MurkError::invalid(
                IMAGES_FIELD,
                format!(
                    "image {}: name {:?} cannot be stored in images.txt",
                    im.id, im.name
                ),
            ));
        }
        let [qw, qx, qy, qz] = im.qvec;
        let [tx, ty, tz] = im.tvec;
        let _ = writeln!(
            s,
            "{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}",
            im.id, im.camera_id, im.name
        );
        let mut first = true;
        for p in &im.points2d {
            if !first {
                s.push(' ');
            }
            first = false;
            let _ = match p.point3d_id {
                Some(id) => write!(s, "{} {} {id}", p.xy[0], p.xy[1]),
                None => write!(s, "{} {} -1", p.xy[0], p.xy[1]),
            };
        }
        s.push('\n');
    }
    Ok(s)
}

/// `points3D.txt` contents in COLMAP's layout.
pub fn format_points3d(points: &BTreeMap<u64, Point3D>) -> String {
    let mut s = String::new();
    let n_obs: usize = points.values().map(|p| p.track.len()).sum();
    let mean = if points.is_empty() {
        0.0
    } else {
        n_obs as f64 / points.len() as f64
    };
    s.push_str("# 3D point list with one line of data per point:\n");
    s.push_str("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    let _ = writeln!(
        s,
        "# Number of points: {}, mean track length: {mean}",
        points.len()
    );
    for p in points.values() {
        let [x, y, z] = p.xyz;
        let [r, g, b] = p.rgb;
        let _ = write!(s, "{} {x} {y} {z} {r} {g} {b} {}", p.id, p.error);
        for t in &p.track {
            let _ = write!(s, " {} {}", t.image_id, t.point2d_idx);
        }
        s.push('\n');
    }
    s
}
