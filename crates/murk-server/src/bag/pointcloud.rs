//! `sensor_msgs/PointCloud2` from murk's points: an unordered cloud (height 1) of
//! little-endian float32 `x, y, z` in the camera's frame (metres; x right, y down, z forward,
//! the optical frame of REP 103), plus `rgb` (PCL's packing: 0x00RRGGBB in a float32's bits) or
//! `intensity`.

use murk::camera::Intrinsics;
use murk::mvs_io::ColoredPoint;
use murk::ImageF32;

use super::msgs::{Header, PointCloud2, PointField, POINT_FIELD_FLOAT32};

fn field(name: &str, offset: u32) -> PointField {
    PointField {
        name: name.into(),
        offset,
        datatype: POINT_FIELD_FLOAT32,
        count: 1,
    }
}

fn cloud(header: &Header, last: &str, data: Vec<u8>) -> PointCloud2 {
    const STEP: u32 = 16;
    let n = data.len() as u32 / STEP;
    PointCloud2 {
        header: header.clone(),
        height: 1,
        width: n,
        fields: vec![field("x", 0), field("y", 4), field("z", 8), field(last, 12)],
        is_bigendian: false,
        point_step: STEP,
        row_step: STEP * n,
        data,
        is_dense: true,
    }
}

/// Coloured points (stereo) as `x, y, z, rgb`.
pub fn rgb_cloud(header: &Header, points: &[ColoredPoint]) -> PointCloud2 {
    let mut data = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in p.xyz {
            data.extend_from_slice(&(v as f32).to_le_bytes());
        }
        let [r, g, b] = p.rgb.map(u32::from);
        data.extend_from_slice(&((r << 16) | (g << 8) | b).to_le_bytes());
    }
    cloud(header, "rgb", data)
}

/// Points with an intensity (ToF: the amplitude) as `x, y, z, intensity`.
pub fn intensity_cloud(header: &Header, points: &[([f32; 3], f32)]) -> PointCloud2 {
    let mut data = Vec::with_capacity(points.len() * 16);
    for (xyz, i) in points {
        for v in xyz.iter().chain([i]) {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    cloud(header, "intensity", data)
}

/// The pixels `keep` accepts, with a finite positive z-depth (metres), back-projected through
/// `k` (`(x, y, z) = z·K⁻¹(u, v, 1)`), each with its `intensity`.
pub fn backproject_with_intensity(
    z_depth_m: &ImageF32,
    intensity: &[f32],
    k: &Intrinsics,
    keep: impl Fn(usize) -> bool,
) -> Vec<([f32; 3], f32)> {
    let w = z_depth_m.width();
    z_depth_m
        .data()
        .iter()
        .enumerate()
        .filter(|(i, z)| z.is_finite() && **z > 0.0 && keep(*i))
        .map(|(i, &z)| {
            let ray = k.ray((i % w) as f64, (i / w) as f64);
            let s = f64::from(z) / ray.z;
            let xyz = [ray.x * s, ray.y * s, f64::from(z)].map(|v| v as f32);
            (xyz, intensity.get(i).copied().unwrap_or(0.0))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_are_consistent() {
        let c = rgb_cloud(
            &Header::default(),
            &[ColoredPoint {
                xyz: [1.0, 2.0, 3.0],
                rgb: [255, 128, 1],
            }; 3],
        );
        assert_eq!(c.data.len() as u32, c.row_step * c.height);
        assert_eq!(c.row_step, c.point_step * c.width);
        assert_eq!(c.width, 3);
        let rgb = u32::from_le_bytes(c.data[12..16].try_into().unwrap());
        assert_eq!(rgb, 0xFF8001);
        let t = intensity_cloud(&Header::default(), &[([0.5, 0.0, 2.0], 0.25)]);
        assert_eq!(t.fields[3].name, "intensity");
        assert_eq!(f32::from_le_bytes(t.data[12..16].try_into().unwrap()), 0.25);
    }

    #[test]
    fn backprojected_points_reproject_onto_their_pixels() {
        let k = Intrinsics::new(100.0, 110.0, 1.5, 1.0);
        let z = ImageF32::from_vec(3, 2, 1, vec![2.0, 0.0, 3.0, f32::NAN, 4.0, 5.0]).unwrap();
        let pts = backproject_with_intensity(&z, &[0.1, 0.2, 0.3, 0.4, 0.5, 0.6], &k, |i| i != 5);
        // 0 m and NaN are no measurement; pixel 5 is refused by `keep`
        assert_eq!(pts.len(), 3);
        for ((p, i), (u, v)) in pts.iter().zip([(0.0, 0.0), (2.0, 0.0), (1.0, 1.0)]) {
            let (pu, pv) = k
                .project([f64::from(p[0]), f64::from(p[1]), f64::from(p[2])])
                .unwrap();
            assert!((pu - u).abs() < 1e-4 && (pv - v).abs() < 1e-4, "{p:?}");
            assert!(*i > 0.0);
        }
    }
}
