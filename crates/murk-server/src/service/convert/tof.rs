//! `TofDepthRequest` → ([`TofInput`], [`TofParams`]) and [`TofOutput`] → `TofDepthResult`.

use rayon::prelude::*;

use super::image::{image_to_proto, mono_image_from_proto, ImageLimits};
use super::outputs::{Delivery, Encoding, OutputField, OutputSelection, Quantity};
use crate::service::proto::v1 as pb;
use murk::camera::Intrinsics;
use murk::error::{MurkError, Result};
use murk::image::ImageF32;
use murk::tof::{
    measured_points, unmeasured_range_std_m, BilateralParams, IrlsChannelParams, PriorCoupling,
    ScatterChannels, TofInput, TofOutput, TofParams, DEFAULT_MAX_POINT_RANGE_STD_M,
};

use super::geometry::{intrinsics_from_proto, intrinsics_to_proto, points_to_proto};

/// A request's point cloud: through which camera, keeping which pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TofPoints {
    /// The camera's intrinsics.
    pub intrinsics: Intrinsics,
    /// The largest `range_std_m` of a point, metres.
    pub max_range_std_m: f32,
}

/// The request's `return_points` and `max_point_range_std_m`: `None` when no points were asked
/// for. Errors name `return_points` (no intrinsics) or `max_point_range_std_m`.
pub fn tof_points_from_proto(req: &pb::TofDepthRequest) -> Result<Option<TofPoints>> {
    let max = req.max_point_range_std_m;
    if !max.is_finite() || max < 0.0 {
        return Err(MurkError::invalid(
            "max_point_range_std_m",
            format!("must be finite and ≥ 0 (0 = {DEFAULT_MAX_POINT_RANGE_STD_M} m), got {max}"),
        ));
    }
    if !req.return_points {
        return Ok(None);
    }
    let k = req.intrinsics.as_ref().ok_or_else(|| {
        MurkError::invalid(
            "return_points",
            "points need the camera's intrinsics: set intrinsics",
        )
    })?;
    Ok(Some(TofPoints {
        intrinsics: intrinsics_from_proto(k),
        max_range_std_m: if max == 0.0 {
            DEFAULT_MAX_POINT_RANGE_STD_M
        } else {
            max
        },
    }))
}

/// The image fields of `TofDepthResult`, in message order.
pub const TOF_OUTPUTS: &[OutputField] = &[
    OutputField {
        name: "range_m",
        quantity: Quantity::Metres,
    },
    OutputField {
        name: "z_depth_m",
        quantity: Quantity::Metres,
    },
    OutputField {
        name: "raw_range_m",
        quantity: Quantity::Metres,
    },
    OutputField {
        name: "mask",
        quantity: Quantity::UnitInterval,
    },
    OutputField {
        name: "scatter_amplitude",
        quantity: Quantity::Unbounded,
    },
    OutputField {
        name: "scatter_phase",
        quantity: Quantity::Radians,
    },
    OutputField {
        name: "weight_amplitude",
        quantity: Quantity::UnitInterval,
    },
    OutputField {
        name: "weight_phase",
        quantity: Quantity::UnitInterval,
    },
    OutputField {
        name: "corrected_amplitude",
        quantity: Quantity::Unbounded,
    },
    OutputField {
        name: "corrected_phase",
        quantity: Quantity::Radians,
    },
    OutputField {
        name: "raw_z_depth_m",
        quantity: Quantity::Metres,
    },
    OutputField {
        name: "range_std_m",
        quantity: Quantity::Metres,
    },
];

/// The result images and encoding a ToF request asks for; errors name `outputs.…`. A session's
/// compact default is the z-depth (the range without intrinsics), the mask and `range_std_m`.
pub fn tof_outputs_from_proto(
    req: &pb::TofDepthRequest,
    delivery: Delivery,
) -> Result<OutputSelection> {
    let depth = if req.intrinsics.is_some() {
        "z_depth_m"
    } else {
        "range_m"
    };
    OutputSelection::from_proto(
        req.outputs.as_ref(),
        TOF_OUTPUTS,
        &[depth, "mask", "range_std_m"],
        delivery,
    )
    .map_err(|e| e.within("outputs"))
}

/// Decodes and fully validates a one-shot ToF request: the input, the parameters and the
/// outputs asked for. Field names are relative to `TofDepthRequest`.
pub fn tof_from_proto(
    req: &pb::TofDepthRequest,
    limits: &ImageLimits,
) -> Result<(TofInput, TofParams, OutputSelection, Option<TofPoints>)> {
    let (amplitude, phase) =
        tof_images_from_proto(req.amplitude.as_ref(), req.phase.as_ref(), limits)?;
    let intrinsics = req.intrinsics.as_ref().map(intrinsics_from_proto);
    let input = TofInput {
        amplitude,
        phase,
        intrinsics,
    };
    input.validate()?;
    let (w, h) = input.amplitude.dims();
    let params = tof_params_from_proto(req, w, h)?;
    let outputs = tof_outputs_from_proto(req, Delivery::OneShot)?;
    let points = tof_points_from_proto(req)?;
    Ok((input, params, outputs, points))
}

/// Decodes the amplitude and phase images of a request or a frame (one channel each); errors
/// name `amplitude…` or `phase…`.
pub fn tof_images_from_proto(
    amplitude: Option<&pb::Image>,
    phase: Option<&pb::Image>,
    limits: &ImageLimits,
) -> Result<(ImageF32, ImageF32)> {
    let image = |name: &str, i: Option<&pb::Image>| {
        i.ok_or_else(|| MurkError::invalid(name, "required"))
            .and_then(|i| mono_image_from_proto(i, limits).map_err(|e| e.within(name)))
    };
    Ok((image("amplitude", amplitude)?, image("phase", phase)?))
}

/// A request's parameters (its images aside), validated for `width × height` frames: what a
/// sensor session checks once for all its frames. Errors name `intrinsics.…`,
/// `modulation_frequency_hz`, `light_position_m` or `options.…`.
pub fn tof_params_from_proto(
    req: &pb::TofDepthRequest,
    width: usize,
    height: usize,
) -> Result<TofParams> {
    if let Some(k) = &req.intrinsics {
        intrinsics_from_proto(k)
            .validate()
            .map_err(|e| e.within("intrinsics"))?;
    }
    let params = params_from_proto(req)?;
    params
        .validate_for_frames(width, height, req.intrinsics.is_some())
        .map_err(|e| match e {
            MurkError::InvalidArgument { field, reason }
                if field != "modulation_frequency_hz" && field != "light_position_m" =>
            {
                MurkError::invalid(format!("options.{}", proto_field_name(&field)), reason)
            }
            other => other,
        })?;
    Ok(params)
}

/// Library parameter paths → proto field paths where they differ.
fn proto_field_name(field: &str) -> String {
    field
        .replace("gamma[0]", "gamma_quadratic")
        .replace("gamma[1]", "gamma_symmetry")
        .replace("gamma[2]", "gamma_smoothness")
}

fn params_from_proto(req: &pb::TofDepthRequest) -> Result<TofParams> {
    let mut p = TofParams {
        modulation_frequency_hz: req.modulation_frequency_hz,
        ..TofParams::default()
    };
    p.light_position_m = req.light_position_m.as_ref().map(|v| [v.x, v.y, v.z]);
    let Some(o) = &req.options else {
        return Ok(p);
    };
    if let Some(v) = o.patches_x {
        p.patches_x = v as usize;
    }
    if let Some(v) = o.patches_y {
        p.patches_y = v as usize;
    }
    p.symmetry_row = o.symmetry_row.or(p.symmetry_row);
    irls_from_proto(o.amplitude.as_ref(), &mut p.amplitude);
    irls_from_proto(o.phase.as_ref(), &mut p.phase);
    if let Some(v) = o.coarse_iterations {
        p.coarse_iterations = v as usize;
    }
    if let Some(v) = o.fine_iterations {
        p.fine_iterations = v as usize;
    }
    if let Some(b) = &o.bilateral {
        p.bilateral = if b.disabled {
            None
        } else {
            let d = BilateralParams::default();
            Some(BilateralParams {
                radius: b.radius.map_or(d.radius, |r| r as usize),
                sigma_space_px: b.sigma_space_px.unwrap_or(d.sigma_space_px),
                sigma_range_rel: b.sigma_range_rel.unwrap_or(d.sigma_range_rel),
            })
        };
    }
    if let Some(t) = o.mask_threshold {
        p.mask_threshold = t;
    }
    if let Some(t) = o.convergence_tolerance {
        p.convergence_tolerance = t;
    }
    p.channels = match pb::TofChannels::try_from(o.channels) {
        Ok(pb::TofChannels::Unspecified) => p.channels,
        Ok(pb::TofChannels::Phasor) => ScatterChannels::Phasor,
        Ok(pb::TofChannels::AmplitudePhase) => ScatterChannels::AmplitudePhase,
        Err(_) => {
            return Err(MurkError::invalid(
                "options.channels",
                format!("unknown ToF channels {}", o.channels),
            ))
        }
    };
    if o.alternating_prior {
        p.prior_coupling = PriorCoupling::Alternating;
    }
    irls_from_proto(o.phasor.as_ref(), &mut p.phasor);
    if let Some(v) = o.coarse_subdivision {
        p.coarse_subdivision = v as usize;
    }
    if let Some(q) = o.coarse_quantile {
        p.coarse_quantile = q;
    }
    Ok(p)
}

fn irls_from_proto(o: Option<&pb::IrlsOptions>, p: &mut IrlsChannelParams) {
    let Some(o) = o else { return };
    let [g_quadratic, g_symmetry, g_smoothness] = &mut p.gamma;
    for (dst, src) in [
        (g_quadratic, o.gamma_quadratic),
        (g_symmetry, o.gamma_symmetry),
        (g_smoothness, o.gamma_smoothness),
        (&mut p.c_coarse, o.c_coarse),
        (&mut p.c_fine, o.c_fine),
    ] {
        if let Some(v) = src {
            *dst = v;
        }
    }
}

/// A request for `input` with the reference defaults (clients: CLI, demo, tests, benchmarks).
/// Images travel as raw f32 so nothing is lost to quantisation.
pub fn tof_request_to_proto(
    amplitude: &ImageF32,
    phase_rad: &ImageF32,
    intrinsics: Option<&Intrinsics>,
    modulation_frequency_hz: f64,
    light_position_m: Option<[f64; 3]>,
) -> pb::TofDepthRequest {
    pb::TofDepthRequest {
        amplitude: Some(image_to_proto(amplitude)),
        phase: Some(image_to_proto(phase_rad)),
        modulation_frequency_hz,
        intrinsics: intrinsics.map(intrinsics_to_proto),
        options: None,
        light_position_m: light_position_m.map(|[x, y, z]| pb::Vector3 { x, y, z }),
        outputs: None,
        return_points: false,
        max_point_range_std_m: 0.0,
    }
}

/// The request a camera would send for a simulated frame: its images, the simulator's
/// intrinsics, modulation frequency and light position (tests, examples, benchmarks).
pub fn simulated_tof_request(
    frame: &murk::simulate::TofSimFrame,
    cfg: &murk::simulate::TofSimConfig,
) -> pb::TofDepthRequest {
    tof_request_to_proto(
        &frame.amplitude,
        &frame.phase,
        Some(&frame.intrinsics),
        cfg.modulation_frequency_hz,
        Some(cfg.light_position_m()),
    )
}

/// `depth` with 0 ("no measurement") where `range_std_m` is at its cap `unmeasured`.
fn without_unmeasured(depth: &ImageF32, range_std_m: &ImageF32, unmeasured: f32) -> ImageF32 {
    let mut out = depth.clone();
    for (d, &s) in out.data_mut().iter_mut().zip(range_std_m.data()) {
        if s >= unmeasured {
            *d = 0.0;
        }
    }
    out
}

/// Encodes the images of the method's output (computed with `params`) that `outputs` selects,
/// and its measured pixels as points when `points` asks for them. In PNG, as in a ROS depth
/// image, the corrected range and z-depth are 0 where the pixel has no measurement (see
/// `ImageEncoding` in common.proto).
pub fn tof_to_proto(
    out: &TofOutput,
    params: &TofParams,
    outputs: &OutputSelection,
    points: Option<&TofPoints>,
) -> Result<pb::TofDepthResult> {
    // The images encode side by side (a PNG deflates on one core; a stream's frame waits for
    // all of them). The two depths travel without their unmeasured pixels' guesses as PNG.
    let fields: [(&str, Option<&ImageF32>, bool); 12] = [
        ("range_m", Some(&out.range_m), true),
        ("z_depth_m", out.z_depth_m.as_ref(), true),
        ("raw_range_m", Some(&out.raw_range_m), false),
        ("raw_z_depth_m", out.raw_z_depth_m.as_ref(), false),
        ("mask", Some(&out.mask), false),
        ("scatter_amplitude", Some(&out.scatter_amplitude), false),
        ("scatter_phase", Some(&out.scatter_phase), false),
        ("weight_amplitude", Some(&out.weight_amplitude), false),
        ("weight_phase", Some(&out.weight_phase), false),
        ("corrected_amplitude", Some(&out.corrected_amplitude), false),
        ("corrected_phase", Some(&out.corrected_phase), false),
        ("range_std_m", Some(&out.range_std_m), false),
    ];
    let encoded: Vec<Option<pb::Image>> = fields
        .par_iter()
        .map(|&(name, img, is_depth)| match img {
            None => Ok(None),
            Some(img) if is_depth && outputs.encoding() == Encoding::Png && outputs.wants(name) => {
                let unmeasured = unmeasured_range_std_m(params.modulation_frequency_hz);
                outputs.encode(name, &without_unmeasured(img, &out.range_std_m, unmeasured))
            }
            Some(img) => outputs.encode(name, img),
        })
        .collect::<Result<_>>()?;
    // Taken in the order of `fields`, as the struct's fields are evaluated as written.
    let mut encoded = encoded.into_iter();
    let mut next = move || encoded.next().flatten();
    Ok(pb::TofDepthResult {
        range_m: next(),
        z_depth_m: next(),
        raw_range_m: next(),
        raw_z_depth_m: next(),
        mask: next(),
        scatter_amplitude: next(),
        scatter_phase: next(),
        weight_amplitude: next(),
        weight_phase: next(),
        corrected_amplitude: next(),
        corrected_phase: next(),
        range_std_m: next(),
        warnings: out.warnings.clone(),
        points: points
            .map(|p| {
                measured_points(
                    out,
                    &p.intrinsics,
                    params.modulation_frequency_hz,
                    p.max_range_std_m,
                )
            })
            .transpose()?
            .map(|p| points_to_proto(&p)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::convert::image::image_from_proto;

    /// A result whose every image is a constant, its field's index.
    fn numbered_output() -> TofOutput {
        let img = |v: f32| ImageF32::filled(4, 3, 1, v);
        TofOutput {
            range_m: img(1.0),
            z_depth_m: Some(img(2.0)),
            raw_range_m: img(3.0),
            raw_z_depth_m: Some(img(4.0)),
            range_std_m: img(12.0),
            mask: img(5.0),
            scatter_amplitude: img(6.0),
            scatter_phase: img(7.0),
            weight_amplitude: img(8.0),
            weight_phase: img(9.0),
            corrected_amplitude: img(10.0),
            corrected_phase: img(11.0),
            warnings: vec![],
        }
    }

    /// Every image field of a result, in the order of `numbered_output`'s values.
    fn images(r: &pb::TofDepthResult) -> [&Option<pb::Image>; 12] {
        [
            &r.range_m,
            &r.z_depth_m,
            &r.raw_range_m,
            &r.raw_z_depth_m,
            &r.mask,
            &r.scatter_amplitude,
            &r.scatter_phase,
            &r.weight_amplitude,
            &r.weight_phase,
            &r.corrected_amplitude,
            &r.corrected_phase,
            &r.range_std_m,
        ]
    }

    #[test]
    fn every_image_travels_in_its_own_field_and_only_those_asked_for() {
        let out = numbered_output();
        let params = TofParams::default();
        let every = pb::TofDepthRequest::default();
        let all = tof_outputs_from_proto(&every, Delivery::OneShot).unwrap();
        let r = tof_to_proto(&out, &params, &all, None).unwrap();
        let got: Vec<Option<f32>> = images(&r)
            .iter()
            .map(|img| {
                img.as_ref()
                    .map(|i| image_from_proto(i, &ImageLimits::default()).unwrap().data()[0])
            })
            .collect();
        let want: Vec<Option<f32>> = (1..=12).map(|v| Some(v as f32)).collect();
        assert_eq!(got, want);

        // A session's compact default: the z-depth (2), the mask (5) and range_std_m (12).
        let with_intrinsics = pb::TofDepthRequest {
            intrinsics: Some(pb::CameraIntrinsics::default()),
            ..Default::default()
        };
        let compact = tof_outputs_from_proto(&with_intrinsics, Delivery::Session).unwrap();
        let r = tof_to_proto(&out, &params, &compact, None).unwrap();
        let present: Vec<usize> = images(&r)
            .iter()
            .enumerate()
            .filter(|(_, img)| img.is_some())
            .map(|(i, _)| i + 1)
            .collect();
        assert_eq!(present, [2, 5, 12]);
    }
}
