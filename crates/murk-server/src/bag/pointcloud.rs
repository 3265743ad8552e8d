//! `sensor_msgs/PointCloud2` from murk's points: an unordered cloud (height 1) of
//! little-endian float32 `x, y, z` in the camera's frame (metres; x right, y down, z forward,
//! the optical frame of REP 103), plus `rgb` (PCL's packing: 0x00RRGGBB in a float32's bits).

use crate::service::convert::check_points;
use crate::service::proto::v1 as pb;

use super::msgs::{Header, PointCloud2, PointField, POINT_FIELD_FLOAT32};

fn field(name: &str, offset: u32) -> PointField {
    PointField {
        name: name.into(),
        offset,
        datatype: POINT_FIELD_FLOAT32,
        count: 1,
    }
}

/// A result's coloured points (stereo; ToF grey from the direct amplitude) as they came from
/// the API ([`pb::PointCloud`]: little-endian `f32` positions, 8-bit colours) as `x, y, z, rgb`,
/// their bytes copied as they are, without widening every position to `f64` and back (a
/// 640×480 pair has about 300 000 points). Errors name `points` when the byte counts do not
/// match the count.
pub fn rgb_cloud_from_api(header: &Header, cloud: &pb::PointCloud) -> murk::Result<PointCloud2> {
    let n = check_points(cloud)?;
    let mut data = Vec::with_capacity(n * 16);
    for (xyz, rgb) in cloud
        .xyz_f32_le
        .chunks_exact(12)
        .zip(cloud.rgb8.chunks_exact(3))
    {
        data.extend_from_slice(xyz);
        data.extend_from_slice(&packed_rgb([rgb[0], rgb[1], rgb[2]]));
    }
    Ok(cloud_of(header, data))
}

/// PCL's packing of a colour: `0x00RRGGBB` in a little-endian 32-bit word.
fn packed_rgb(rgb: [u8; 3]) -> [u8; 4] {
    let [r, g, b] = rgb.map(u32::from);
    ((r << 16) | (g << 8) | b).to_le_bytes()
}

/// An unordered cloud of the 16-byte `x, y, z, rgb` points in `data`.
fn cloud_of(header: &Header, data: Vec<u8>) -> PointCloud2 {
    const STEP: u32 = 16;
    let n = (data.len() / STEP as usize) as u32;
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
    use murk::mvs_io::ColoredPoint;

    /// The cloud by definition: each decoded point's position narrowed to `f32`, its colour
    /// packed.
    fn rgb_cloud(header: &Header, points: &[ColoredPoint]) -> PointCloud2 {
        let mut data = Vec::with_capacity(points.len() * 16);
        for p in points {
            for v in p.xyz {
                data.extend_from_slice(&(v as f32).to_le_bytes());
            }
            data.extend_from_slice(&packed_rgb(p.rgb));
        }
        cloud_of(header, data)
    }

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

    /// The wire's bytes make the cloud the decoded points make, byte for byte; a count that
    /// does not match the bytes names `points`.
    #[test]
    fn the_wires_points_make_the_same_cloud() {
        let points: Vec<ColoredPoint> = (0..50)
            .map(|i| ColoredPoint {
                xyz: [f64::from(i) * 0.37 - 3.0, 1.0 / (1.0 + f64::from(i)), 2.5],
                rgb: [i as u8, (3 * i) as u8, 255 - i as u8],
            })
            .collect();
        let wire = crate::service::convert::points_to_proto(&points);
        let h = Header::default();
        let direct = rgb_cloud_from_api(&h, &wire).unwrap();
        let decoded = rgb_cloud(
            &h,
            &crate::service::convert::points_from_proto(&wire).unwrap(),
        );
        assert_eq!(direct, decoded);
        let short = pb::PointCloud { count: 51, ..wire };
        let e = rgb_cloud_from_api(&h, &short).unwrap_err();
        assert_eq!(e.field(), Some("points"), "{e}");
    }
}
