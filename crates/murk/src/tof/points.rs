//! A ToF result as a point cloud: the measured pixels back-projected along their rays.

use crate::camera::Intrinsics;
use crate::mvs::Pose;
use crate::mvs_io::{backproject, ColoredPoint};
use crate::{ImageF32, MurkError, Result};

use super::{unmeasured_range_std_m, TofOutput};

/// The `range_std_m` above which a pixel is left out of the cloud unless the caller says
/// otherwise, metres. Fog-only pixels, whose direct return is buried in the scatter, carry
/// spreads of metres; objects carry millimetres to centimetres.
pub const DEFAULT_MAX_POINT_RANGE_STD_M: f32 = 0.1;

/// The pixels with a z-depth and a `range_std_m` below `max_range_std_m` (and below the cap of
/// [`unmeasured_range_std_m`]), as points in the camera frame (x right, y down, z forward,
/// metres), grey from the direct amplitude α_d (Eq. 5.8) scaled so that its 99th percentile
/// over the points is white. Fails naming `intrinsics` when `out` has no z-depth (it was
/// computed without them).
pub fn measured_points(
    out: &TofOutput,
    intrinsics: &Intrinsics,
    modulation_frequency_hz: f64,
    max_range_std_m: f32,
) -> Result<Vec<ColoredPoint>> {
    let z = out.z_depth_m.as_ref().ok_or_else(|| {
        MurkError::invalid(
            "intrinsics",
            "points need the camera's intrinsics, with which the z-depth is computed",
        )
    })?;
    if max_range_std_m.is_nan() || max_range_std_m <= 0.0 {
        return Err(MurkError::invalid(
            "max_point_range_std_m",
            format!("must be > 0, got {max_range_std_m}"),
        ));
    }
    let limit = max_range_std_m.min(unmeasured_range_std_m(modulation_frequency_hz));
    let keep: Vec<f32> = out
        .range_std_m
        .data()
        .iter()
        .map(|s| if *s < limit { 1.0 } else { 0.0 })
        .collect();
    let (w, h) = z.dims();
    let keep = ImageF32::from_vec(w, h, 1, keep)?;
    let mut amplitudes: Vec<f32> = out
        .corrected_amplitude
        .data()
        .iter()
        .zip(keep.data())
        .filter(|(a, k)| **k > 0.0 && a.is_finite())
        .map(|(a, _)| *a)
        .collect();
    amplitudes.sort_by(f32::total_cmp);
    let white = amplitudes
        .get(amplitudes.len().saturating_sub(1) * 99 / 100)
        .copied()
        .filter(|v| *v > 0.0)
        .unwrap_or(1.0);
    let grey = ImageF32::from_vec(
        w,
        h,
        1,
        out.corrected_amplitude
            .data()
            .iter()
            .map(|a| a / white)
            .collect(),
    )?;
    backproject(z, &keep, &grey, intrinsics, &Pose::identity(), 0.5)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::monitor::Monitor;
    use crate::simulate::tof::{simulate_tof, TofSimConfig};
    use crate::tof::{estimate_tof_depth, TofInput, TofParams};

    #[test]
    fn points_are_the_measured_pixels_on_their_rays() {
        let cfg = TofSimConfig::with_size(64, 53);
        let scene = simulate_tof(&cfg, &Monitor::noop()).unwrap();
        let params = TofParams::default();
        let k = scene.intrinsics;
        let input = TofInput {
            amplitude: scene.amplitude.clone(),
            phase: scene.phase.clone(),
            intrinsics: Some(k),
        };
        let out = estimate_tof_depth(&input, &params, &Monitor::noop()).unwrap();
        let f = params.modulation_frequency_hz;
        let pts = measured_points(&out, &k, f, DEFAULT_MAX_POINT_RANGE_STD_M).unwrap();
        let z = out.z_depth_m.as_ref().unwrap();
        let kept = out.range_std_m.data().iter().filter(|s| **s < 0.1).count();
        assert_eq!(pts.len(), kept);
        assert!(kept > 0 && kept < z.data().len());
        for p in &pts {
            let (u, v) = k.project(p.xyz).unwrap();
            let (u, v) = (u.round() as usize, v.round() as usize);
            assert!((p.xyz[2] - f64::from(z.get(u, v, 0))).abs() < 1e-4);
        }
        // A looser limit keeps more; the cap keeps out what has no measurement at all.
        let all = measured_points(&out, &k, f, f32::INFINITY).unwrap();
        assert!(all.len() >= pts.len());
        assert!(all.len() < z.data().len() || out.range_std_m.data().iter().all(|s| *s < 2.0));
        let mut no_k = out.clone();
        no_k.z_depth_m = None;
        let e = measured_points(&no_k, &k, f, 0.1).unwrap_err();
        assert!(matches!(e, MurkError::InvalidArgument { ref field, .. } if field == "intrinsics"));
    }
}
