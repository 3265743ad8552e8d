//! `RectifiedStereoRequest` → [`StereoInput`] and [`RectifiedDepth`] → `RectifiedStereoResult`.
//!
//! As for `MvsDepthRequest`, everything the library would reject is checked at submission, with
//! field names relative to `RectifiedStereoRequest` (`left`, `right`, `intrinsics.fx`,
//! `baseline`, `max_disparity_px`, `sgm.p2`, ...).

use super::geometry::{intrinsics_from_proto, intrinsics_to_proto, points_to_proto};
use super::image::{image_from_proto, image_to_proto, ImageLimits};
use super::mvs::{canonical_sgm, canonicalize_cost, cost_of, sgm_of};
use super::outputs::{Delivery, OutputField, OutputSelection, Quantity};
use crate::service::proto::v1 as pb;
use murk::atmosphere::AtmosphereParams;
use murk::error::{MurkError, Result};
use murk::image::ImageF32;
use murk::monitor::Monitor;
use murk::mvs::cost_volume::MAX_VOXELS;
use murk::mvs::{estimate_rectified, RectifiedDepth, RectifiedOptions, RectifiedRig, StereoRange};
use murk::mvs_io::ColoredPoint;

/// A decoded and fully validated `RectifiedStereoRequest`, owning its images.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoInput {
    /// Left (reference) image.
    pub left: ImageF32,
    /// Right image, the left's shape.
    pub right: ImageF32,
    /// The rig.
    pub rig: RectifiedRig,
    /// Range, plane count (resolved), cost and aggregation parameters.
    pub options: RectifiedOptions,
    /// The wire kind (UNSPECIFIED resolved), echoed in the result.
    pub wire_kind: pb::CostVolumeKind,
    /// Whether the result carries the point cloud.
    pub return_points: bool,
    /// The result images asked for, and their encoding.
    pub outputs: OutputSelection,
}

/// The image fields of `RectifiedStereoResult`, in message order.
pub const STEREO_OUTPUTS: &[OutputField] = &[
    // In the baseline's unit, which the server does not know: quantised on its own range.
    OutputField {
        name: "z_depth",
        quantity: Quantity::Unbounded,
    },
    OutputField {
        name: "disparity",
        quantity: Quantity::Unbounded,
    },
    OutputField {
        name: "confidence",
        quantity: Quantity::UnitInterval,
    },
];

/// The result images and encoding a rectified-stereo request asks for; errors name `fields[i]`
/// or `encoding` (callers prefix `outputs`). A session's compact default is the z-depth and the
/// confidence.
pub fn stereo_outputs_from_proto(
    outputs: Option<&pb::OutputOptions>,
    delivery: Delivery,
) -> Result<OutputSelection> {
    OutputSelection::from_proto(
        outputs,
        STEREO_OUTPUTS,
        &["z_depth", "confidence"],
        delivery,
    )
}

impl StereoInput {
    /// Runs [`estimate_rectified`]; with `return_points`, also the point cloud.
    pub fn estimate(&self, monitor: &Monitor) -> Result<(RectifiedDepth, Vec<ColoredPoint>)> {
        let out = estimate_rectified(&self.left, &self.right, &self.rig, &self.options, monitor)
            .map_err(|e| match e {
                MurkError::InvalidArgument { field, reason } => {
                    MurkError::invalid(wire_field(&field), reason)
                }
                other => other,
            })?;
        let points = if self.return_points {
            out.points(&self.rig, &self.left)?
        } else {
            Vec::new()
        };
        Ok((out, points))
    }
}

/// A library field of the rectified estimate as the request names it: the aggregation
/// parameters `depth.…` are `sgm.…`, and the pair, which the library treats as a reference
/// view and one source view, is `left` and `right`.
fn wire_field(field: &str) -> String {
    for (library, wire) in [
        ("depth.", "sgm."),
        ("reference.image", "left"),
        ("sources[0].image", "right"),
    ] {
        if let Some(rest) = field.strip_prefix(library) {
            return format!("{wire}{rest}");
        }
    }
    field.to_string()
}

/// The search range a request asks for: the depth range, the disparity range, or `None` for the
/// default. Errors name `near`, `far` or `min_disparity_px` when the request mixes or halves
/// them.
fn range_of(req: &pb::RectifiedStereoRequest, width: usize) -> Result<Option<StereoRange>> {
    let by_depth = req.near != 0.0 || req.far != 0.0;
    let by_disparity = req.min_disparity_px.is_some() || req.max_disparity_px.is_some();
    match (by_depth, by_disparity) {
        (true, true) => Err(MurkError::invalid(
            "near",
            "give the depth range (near, far) or the disparity range, not both",
        )),
        (true, false) => {
            if req.near == 0.0 || req.far == 0.0 {
                return Err(MurkError::invalid(
                    if req.near == 0.0 { "near" } else { "far" },
                    "the depth range needs both near and far",
                ));
            }
            Ok(Some(StereoRange::Depth {
                near: req.near,
                far: req.far,
            }))
        }
        (false, true) => {
            let (min_px, max_px) = StereoRange::default_disparities(width);
            Ok(Some(StereoRange::Disparity {
                min_px: req.min_disparity_px.map_or(min_px, f64::from),
                max_px: req.max_disparity_px.map_or(max_px, f64::from),
            }))
        }
        (false, false) => Ok(None),
    }
}

/// Rewrites `req` into its canonical form before it is hashed into a job id: the cost volume
/// resolved (airlight and β zeroed for ORDINARY), the SGM defaults written out and an unset
/// `right_cx` written as `intrinsics.cx`.
pub fn canonicalize_stereo_request(req: &mut pb::RectifiedStereoRequest) {
    canonicalize_cost(&mut req.cost_volume, &mut req.airlight, &mut req.beta);
    if let Some(sgm) = canonical_sgm(req.sgm.as_ref()) {
        req.sgm = Some(sgm);
    }
    if req.right_cx.is_none() {
        req.right_cx = req.intrinsics.as_ref().map(|k| k.cx);
    }
    // An invalid selection is left as sent, for validation to reject.
    if let Ok(sel) = stereo_outputs_from_proto(req.outputs.as_ref(), Delivery::OneShot) {
        req.outputs = Some(sel.to_proto());
    }
}

/// A rectified-stereo request's settings, validated for frames of one size: everything but the
/// images (the one-shot request's, or a session's for every frame).
#[derive(Clone, Debug, PartialEq)]
pub struct StereoConfig {
    /// The frame size the settings were checked for, pixels.
    pub dims: (usize, usize),
    /// The rig.
    pub rig: RectifiedRig,
    /// Range, plane count (resolved), cost and aggregation parameters.
    pub options: RectifiedOptions,
    /// The wire kind (UNSPECIFIED resolved).
    pub wire_kind: pb::CostVolumeKind,
    /// Whether results carry the point cloud.
    pub return_points: bool,
    /// The result images asked for, and their encoding (`delivery`'s defaults resolved).
    pub outputs: OutputSelection,
}

impl StereoConfig {
    /// Validates `req`'s settings (its images are ignored) for `width × height` pairs delivered
    /// to `delivery`. Errors name `intrinsics.…`, `baseline`, `right_cx`, the range's fields,
    /// `num_planes`, `cost_volume`, `airlight`, `beta`, `sgm.…` or `outputs.…`.
    pub fn from_proto(
        req: &pb::RectifiedStereoRequest,
        width: usize,
        height: usize,
        delivery: Delivery,
    ) -> Result<Self> {
        let (wire_kind, cost) = cost_of(req.cost_volume, req.airlight, req.beta)?;
        let k = req
            .intrinsics
            .as_ref()
            .ok_or_else(|| MurkError::invalid("intrinsics", "required"))?;
        let intrinsics = intrinsics_from_proto(k);
        let rig = RectifiedRig {
            intrinsics,
            baseline: req.baseline,
            right_cx: req.right_cx.unwrap_or(intrinsics.cx),
        };
        rig.validate()?;
        let depth = sgm_of(req.sgm.as_ref());
        depth.validate().map_err(|e| e.within("sgm"))?;
        if req.num_planes == 1 {
            return Err(MurkError::invalid(
                "num_planes",
                "need at least 2 planes (0 = one per pixel of disparity)",
            ));
        }
        let range = range_of(req, width)?;
        let requested = (req.num_planes != 0).then_some(req.num_planes as usize);
        let planes = rig.planes(
            range.unwrap_or_else(|| StereoRange::default_for_width(width)),
            requested,
        )?;
        let voxel_bound = MAX_VOXELS / (width * height).max(1);
        let num_planes = match requested {
            Some(n) if n > voxel_bound => {
                return Err(MurkError::invalid(
                    "num_planes",
                    format!(
                        "{width}x{height} pixels x {n} planes exceeds the cost-volume limit of \
                         {MAX_VOXELS} voxels; use fewer planes or smaller images"
                    ),
                ))
            }
            Some(n) => n,
            None => planes.num_planes.min(voxel_bound.max(2)),
        };
        Ok(Self {
            dims: (width, height),
            rig,
            options: RectifiedOptions {
                range,
                num_planes: Some(num_planes),
                cost,
                depth,
            },
            wire_kind,
            return_points: req.return_points,
            outputs: stereo_outputs_from_proto(req.outputs.as_ref(), delivery)
                .map_err(|e| e.within("outputs"))?,
        })
    }

    /// The input of one pair, checked against these settings: the left image of the configured
    /// size, 1 or 3 channels, finite; the right of the left's shape. Errors name `left…` or
    /// `right…`.
    pub fn with_images(&self, left: ImageF32, right: ImageF32) -> Result<StereoInput> {
        let (w, h) = self.dims;
        if left.dims() != (w, h) {
            return Err(MurkError::invalid(
                "left",
                format!(
                    "the pair is {}x{}, the settings are for {w}x{h}",
                    left.width(),
                    left.height()
                ),
            ));
        }
        let (reference, source) = self.rig.views(&left, &right)?;
        reference.validate(None).map_err(|e| e.within("left"))?;
        source
            .validate(Some((w, h, left.channels())))
            .map_err(|e| e.within("right"))?;
        Ok(StereoInput {
            left,
            right,
            rig: self.rig,
            options: self.options,
            wire_kind: self.wire_kind,
            return_points: self.return_points,
            outputs: self.outputs.clone(),
        })
    }
}

/// Decodes the left and right images of a request or a frame; errors name `left…` or
/// `right…`.
pub fn stereo_images_from_proto(
    left: Option<&pb::Image>,
    right: Option<&pb::Image>,
    limits: &ImageLimits,
) -> Result<(ImageF32, ImageF32)> {
    let image = |name: &str, i: Option<&pb::Image>| {
        i.ok_or_else(|| MurkError::invalid(name, "required"))
            .and_then(|i| image_from_proto(i, limits).map_err(|e| e.within(name)))
    };
    Ok((image("left", left)?, image("right", right)?))
}

/// Decodes and fully validates a rectified-stereo request. The settings are checked before the
/// images are decoded where they can be (everything but what depends on the image size).
pub fn stereo_from_proto(
    req: &pb::RectifiedStereoRequest,
    limits: &ImageLimits,
) -> Result<StereoInput> {
    // The settings' size-free checks first (a bad baseline is reported before any decoding).
    let declared = req.left.as_ref().map_or((2, 2), |i| {
        ((i.width as usize).max(2), (i.height as usize).max(2))
    });
    StereoConfig::from_proto(req, declared.0, declared.1, Delivery::OneShot)?;
    let (left, right) = stereo_images_from_proto(req.left.as_ref(), req.right.as_ref(), limits)?;
    let (w, h) = left.dims();
    StereoConfig::from_proto(req, w, h, Delivery::OneShot)?.with_images(left, right)
}

/// A request for a pair (clients: CLI, tests). Images travel as raw f32; `atmosphere` `None`
/// selects the ordinary cost volume.
pub fn stereo_request_to_proto(
    left: &ImageF32,
    right: &ImageF32,
    rig: &RectifiedRig,
    range: Option<StereoRange>,
    atmosphere: Option<AtmosphereParams>,
) -> pb::RectifiedStereoRequest {
    let (near, far, min_disparity_px, max_disparity_px) = match range {
        Some(StereoRange::Depth { near, far }) => (near, far, None, None),
        Some(StereoRange::Disparity { min_px, max_px }) => {
            (0.0, 0.0, Some(min_px as f32), Some(max_px as f32))
        }
        None => (0.0, 0.0, None, None),
    };
    pb::RectifiedStereoRequest {
        left: Some(image_to_proto(left)),
        right: Some(image_to_proto(right)),
        intrinsics: Some(intrinsics_to_proto(&rig.intrinsics)),
        baseline: rig.baseline,
        right_cx: (rig.right_cx != rig.intrinsics.cx).then_some(rig.right_cx),
        near,
        far,
        min_disparity_px,
        max_disparity_px,
        airlight: atmosphere.map_or(0.0, |a| a.airlight),
        beta: atmosphere.map_or(0.0, |a| a.beta),
        cost_volume: if atmosphere.is_some() {
            pb::CostVolumeKind::Dehazing
        } else {
            pb::CostVolumeKind::Ordinary
        } as i32,
        ..Default::default()
    }
}

/// Encodes the method's output for the wire, echoing the plane set and cost volume used.
pub fn stereo_to_proto(
    input: &StereoInput,
    out: &RectifiedDepth,
    points: &[ColoredPoint],
    compute_seconds: f64,
) -> Result<pb::RectifiedStereoResult> {
    let planes = out.planes;
    let outputs = &input.outputs;
    Ok(pb::RectifiedStereoResult {
        z_depth: outputs.encode("z_depth", &out.depth.z_depth)?,
        disparity: outputs.encode("disparity", &out.disparity)?,
        confidence: outputs.encode("confidence", &out.depth.confidence)?,
        points: input.return_points.then(|| points_to_proto(points)),
        near: planes.near,
        far: planes.far,
        num_planes: u32::try_from(planes.num_planes).unwrap_or(u32::MAX),
        min_disparity_px: input.rig.disparity_of_depth(planes.far) as f32,
        max_disparity_px: input.rig.disparity_of_depth(planes.near) as f32,
        cost_volume: input.wire_kind as i32,
        compute_seconds,
        right_gains: out.depth.source_gains.clone(),
        vignetting_falloff: out.depth.vignetting_falloff,
        right_falloff: out.depth.source_falloffs.first().copied().unwrap_or(0.0),
        warnings: out.depth.warnings.clone(),
    })
}

#[cfg(test)]
mod tests {
    use super::super::geometry::points_from_proto;
    use super::*;
    use murk::camera::Intrinsics;
    use murk::mvs::CostKind;

    fn field_of(e: MurkError) -> String {
        e.field()
            .unwrap_or_else(|| panic!("expected InvalidArgument, got {e:?}"))
            .to_string()
    }

    #[test]
    fn library_fields_are_named_as_the_request_names_them() {
        assert_eq!(wire_field("depth.p1"), "sgm.p1");
        assert_eq!(wire_field("reference.image"), "left");
        assert_eq!(wire_field("sources[0].image.width"), "right.width");
        assert_eq!(wire_field("baseline"), "baseline");
    }

    fn pair() -> (ImageF32, ImageF32, RectifiedRig) {
        let texture = |x: f64, y: f64| (0.5 + 0.3 * (x * 0.8).sin() * (y * 0.6).cos()) as f32;
        let left = ImageF32::from_fn(48, 32, |x, y| texture(x as f64, y as f64));
        let right = ImageF32::from_fn(48, 32, |x, y| texture(x as f64 + 6.0, y as f64));
        let rig = RectifiedRig::new(Intrinsics::new(60.0, 60.0, 23.5, 15.5), 0.1);
        (left, right, rig)
    }

    fn request() -> pb::RectifiedStereoRequest {
        let (l, r, rig) = pair();
        stereo_request_to_proto(
            &l,
            &r,
            &rig,
            Some(StereoRange::Disparity {
                min_px: 1.0,
                max_px: 12.0,
            }),
            None,
        )
    }

    fn err(req: &pb::RectifiedStereoRequest) -> String {
        field_of(stereo_from_proto(req, &ImageLimits::default()).unwrap_err())
    }

    #[test]
    fn round_trips_and_estimates_a_shifted_texture() {
        let mut req = request();
        req.return_points = true;
        let input = stereo_from_proto(&req, &ImageLimits::default()).unwrap();
        assert_eq!(input.options.cost, CostKind::Ordinary);
        assert_eq!(input.options.num_planes, Some(12));
        let (out, points) = input.estimate(&Monitor::noop()).unwrap();
        let wire = stereo_to_proto(&input, &out, &points, 0.1).unwrap();
        assert_eq!(wire.num_planes, 12);
        assert!((wire.min_disparity_px - 1.0).abs() < 1e-4);
        assert!((wire.max_disparity_px - 12.0).abs() < 1e-4);
        assert_eq!(wire.cost_volume, pb::CostVolumeKind::Ordinary as i32);
        let cloud = wire.points.unwrap();
        assert_eq!(points_from_proto(&cloud).unwrap(), points_round(&points));
        // The disparity at the centre is the shift.
        let d = out.disparity.get(24, 16, 0);
        assert!((d - 6.0).abs() < 0.3, "disparity {d}");
        let mut bad = cloud.clone();
        bad.rgb8.pop();
        assert_eq!(field_of(points_from_proto(&bad).unwrap_err()), "points");
    }

    /// Positions travel as f32.
    fn points_round(points: &[ColoredPoint]) -> Vec<ColoredPoint> {
        points
            .iter()
            .map(|p| ColoredPoint {
                xyz: p.xyz.map(|v| f64::from(v as f32)),
                rgb: p.rgb,
            })
            .collect()
    }

    #[test]
    fn canonical_form_merges_equivalent_requests() {
        let mut a = request();
        let mut b = request();
        b.right_cx = Some(23.5);
        b.airlight = 0.7; // ignored by ORDINARY
        b.sgm = Some(pb::SgmOptions {
            p1: Some(murk::mvs::DepthParams::default().sgm.p1),
            ..Default::default()
        });
        canonicalize_stereo_request(&mut a);
        canonicalize_stereo_request(&mut b);
        assert_eq!(a, b);
        let mut c = request();
        c.right_cx = Some(25.0);
        canonicalize_stereo_request(&mut c);
        assert_ne!(a, c);
    }

    #[test]
    fn errors_name_proto_fields() {
        let good = request();
        let mut r = good.clone();
        r.left = None;
        assert_eq!(err(&r), "left");
        let mut r = good.clone();
        r.right.as_mut().unwrap().width = 47;
        assert!(err(&r).starts_with("right"));
        let (l, _, _) = pair();
        let mut r = good.clone();
        r.right = Some(image_to_proto(&ImageF32::filled(
            l.width(),
            l.height() - 1,
            1,
            0.5,
        )));
        assert_eq!(err(&r), "right.image");
        let mut r = good.clone();
        r.intrinsics = None;
        assert_eq!(err(&r), "intrinsics");
        let mut r = good.clone();
        r.intrinsics.as_mut().unwrap().skew = 1.0;
        assert_eq!(err(&r), "intrinsics.skew");
        let mut r = good.clone();
        r.baseline = -0.1;
        assert_eq!(err(&r), "baseline");
        let mut r = good.clone();
        r.right_cx = Some(f64::NAN);
        assert_eq!(err(&r), "right_cx");
        let mut r = good.clone();
        r.near = 1.0;
        assert_eq!(err(&r), "near");
        let mut r = good.clone();
        r.min_disparity_px = None;
        r.max_disparity_px = None;
        r.far = 3.0;
        assert_eq!(err(&r), "near");
        let mut r = good.clone();
        r.max_disparity_px = Some(0.5);
        assert_eq!(err(&r), "max_disparity_px");
        let mut r = good.clone();
        r.min_disparity_px = Some(0.0);
        assert_eq!(err(&r), "min_disparity_px");
        let mut r = good.clone();
        r.num_planes = 1;
        assert_eq!(err(&r), "num_planes");
        let mut r = good.clone();
        r.num_planes = 2000;
        assert_eq!(err(&r), "num_planes");
        let mut r = good.clone();
        r.cost_volume = pb::CostVolumeKind::Dehazing as i32;
        assert_eq!(err(&r), "airlight");
        r.airlight = 0.8;
        r.beta = f32::NAN;
        assert_eq!(err(&r), "beta");
        let mut r = good.clone();
        r.sgm = Some(pb::SgmOptions {
            num_paths: Some(3),
            ..Default::default()
        });
        assert_eq!(err(&r), "sgm.num_paths");
        // Neither range: the default disparities.
        let mut r = good.clone();
        r.min_disparity_px = None;
        r.max_disparity_px = None;
        let input = stereo_from_proto(&r, &ImageLimits::default()).unwrap();
        assert_eq!(input.options.range, None);
        assert_eq!(input.options.num_planes, Some(12)); // 1 to 48/4 = 12 px
    }
}
