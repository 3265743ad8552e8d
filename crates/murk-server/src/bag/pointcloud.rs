//! `sensor_msgs/PointCloud2` from murk's points: an unordered cloud (height 1) of
//! little-endian float32 `x, y, z` in the camera's frame (metres; x right, y down, z forward,
//! the optical frame of REP 103), plus `rgb` (PCL's packing: 0x00RRGGBB in a float32's bits).

use murk::mvs_io::ColoredPoint;

use super::msgs::{Header, PointCloud2, PointField, POINT_FIELD_FLOAT32};

fn field(name: &str, offset: u32) -> PointField {
    PointField {
        name: name.into(),
        offset,
        datatype: POINT_FIELD_FLOAT32,
        count: 1,
    }
}

/// Coloured points (stereo; ToF grey from the direct amplitude) as `x, y, z, rgb`.
pub fn rgb_cloud(header: &Header, points: &[ColoredPoint]) -> PointCloud2 {
    let mut data = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in p.xyz {
            data.extend_from_slice(&(v as f32).to_le_bytes());
        }
        let [r, g, b] = p.rgb.map(u32::from);
        data.extend_from_slice(&((r << 16) | (g << 8) | b).to_le_bytes());
    }
    const STEP: u32 = 16;
    let n = points.len() as u32;
    PointCloud2 {
        header: header.clone(),
        height: 1,
        width: n,
        fields: vec![
            field("x", 0),
            field("y", 4),
            field("z", 8),
            field("rgb", 12),
        ],
        is_bigendian: false,
        point_step: STEP,
        row_step: STEP * n,
        data,
        is_dense: true,
    }
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
    }
}
