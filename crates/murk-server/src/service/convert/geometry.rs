//! Camera intrinsics and point clouds, which every method's messages share.

use crate::service::proto::v1 as pb;
use murk::camera::Intrinsics;
use murk::error::{MurkError, Result};
use murk::mvs_io::ColoredPoint;

/// `murk.v1.CameraIntrinsics` → [`Intrinsics`] (unvalidated; callers validate).
pub fn intrinsics_from_proto(k: &pb::CameraIntrinsics) -> Intrinsics {
    Intrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        skew: k.skew,
    }
}

/// [`Intrinsics`] → `murk.v1.CameraIntrinsics`.
pub fn intrinsics_to_proto(k: &Intrinsics) -> pb::CameraIntrinsics {
    pb::CameraIntrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        skew: k.skew,
    }
}

/// Points for the wire: interleaved little-endian f32 positions and 8-bit colours.
pub fn points_to_proto(points: &[ColoredPoint]) -> pb::PointCloud {
    let mut xyz = Vec::with_capacity(points.len() * 12);
    let mut rgb = Vec::with_capacity(points.len() * 3);
    for p in points {
        for v in p.xyz {
            xyz.extend_from_slice(&(v as f32).to_le_bytes());
        }
        rgb.extend_from_slice(&p.rgb);
    }
    pb::PointCloud {
        count: u32::try_from(points.len()).unwrap_or(u32::MAX),
        xyz_f32_le: xyz,
        rgb8: rgb,
    }
}

/// The wire's points, checked: `count` positions and colours.
pub fn points_from_proto(cloud: &pb::PointCloud) -> Result<Vec<ColoredPoint>> {
    check_points(cloud)?;
    Ok(cloud
        .xyz_f32_le
        .chunks_exact(12)
        .zip(cloud.rgb8.chunks_exact(3))
        .map(|(p, c)| ColoredPoint {
            xyz: [0, 4, 8]
                .map(|o| f64::from(f32::from_le_bytes([p[o], p[o + 1], p[o + 2], p[o + 3]]))),
            rgb: [c[0], c[1], c[2]],
        })
        .collect())
}

/// The number of the wire's points, when it holds `count` positions and colours; errors name
/// `points`.
pub fn check_points(cloud: &pb::PointCloud) -> Result<usize> {
    let n = cloud.count as usize;
    if cloud.xyz_f32_le.len() != n * 12 || cloud.rgb8.len() != n * 3 {
        return Err(MurkError::invalid(
            "points",
            format!(
                "{n} points need {} position bytes and {} colour bytes, got {} and {}",
                n * 12,
                n * 3,
                cloud.xyz_f32_le.len(),
                cloud.rgb8.len()
            ),
        ));
    }
    Ok(n)
}
