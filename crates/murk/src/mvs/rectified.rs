//! Rectified stereo: the commonest robot rig, a calibrated pair whose image rows are epipolar
//! lines (left and right images, the rectified intrinsics and a baseline, as a ROS `CameraInfo`
//! pair or a Middlebury `calib.txt` gives them), through the plane sweep of the reference's
//! Ch. 3.2 with two views.
//!
//! Geometry: the left camera is the world frame; the right camera has the same orientation and
//! its centre at `(baseline, 0, 0)`, so its world-to-camera translation is `(−baseline, 0, 0)`.
//! Both share `fx`, `fy` and `cy`; the right principal point's x may differ (`right_cx`, whose
//! offset `doffs = right_cx − cx` is Middlebury's). A point at z-depth `z` then has disparity
//!
//! ```text
//! d = u_left − u_right = fx·B / z − doffs,   z = fx·B / (d + doffs)
//! ```
//!
//! in pixels, and the plane sweep's fronto-parallel planes, uniform in inverse depth (Eq. 3.2),
//! are uniform in disparity: the default is one plane per pixel of the disparity range, which
//! resolves every integer disparity, with sub-plane refinement between them.

use crate::camera::Intrinsics;
use crate::error::{MurkError, Result};
use crate::image::ImageF32;
use crate::monitor::Monitor;
use crate::mvs::cost_volume::{CostKind, View};
use crate::mvs::depth::{estimate_depth_from_prior, DepthParams, DepthPrior, DepthResult};
use crate::mvs::plane_sweep::{PlaneSet, MAX_PLANES};
use crate::mvs::pose::Pose;
use crate::mvs_io::{backproject, ColoredPoint};

/// Largest default disparity range, pixels: a quarter of the image width up to this. 256 is
/// what OpenCV's StereoSGBM users commonly configure for VGA to HD pairs.
pub const DEFAULT_MAX_DISPARITY_PX: f64 = 256.0;

/// A calibrated, rectified stereo rig.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RectifiedRig {
    /// Rectified intrinsics of the left (reference) camera, pixels, with the origin at the
    /// centre of the top-left pixel (a ROS/OpenCV principal point as it is). Skew must be 0.
    pub intrinsics: Intrinsics,
    /// Distance of the right camera's centre along the left camera's +x axis, scene units
    /// (metres, say); depths, points and β are in the same unit.
    pub baseline: f64,
    /// The right camera's principal point x, pixels (equal to `intrinsics.cx` for most rigs;
    /// Middlebury's `doffs` is the difference).
    pub right_cx: f64,
}

impl RectifiedRig {
    /// A rig whose two cameras share the principal point.
    pub fn new(intrinsics: Intrinsics, baseline: f64) -> Self {
        Self {
            intrinsics,
            baseline,
            right_cx: intrinsics.cx,
        }
    }

    /// Checks intrinsics (no skew), baseline (finite, `> 0`) and `right_cx` (finite, within
    /// `camera::MAX_PRINCIPAL_OFFSET_PX`). Errors name
    /// `intrinsics.…`, `baseline` or `right_cx`.
    pub fn validate(&self) -> Result<()> {
        self.intrinsics
            .validate()
            .map_err(|e| e.within("intrinsics"))?;
        if self.intrinsics.skew != 0.0 {
            return Err(MurkError::invalid(
                "intrinsics.skew",
                format!(
                    "a rectified camera has no skew, got {}",
                    self.intrinsics.skew
                ),
            ));
        }
        if !(self.baseline.is_finite() && self.baseline > 0.0) {
            return Err(MurkError::invalid(
                "baseline",
                format!(
                    "must be finite and > 0 (the right camera lies along the left's +x axis), \
                     got {}",
                    self.baseline
                ),
            ));
        }
        if !self.right_cx.is_finite() {
            return Err(MurkError::invalid(
                "right_cx",
                format!("must be finite, got {}", self.right_cx),
            ));
        }
        if self.right_cx.abs() > crate::camera::MAX_PRINCIPAL_OFFSET_PX {
            return Err(MurkError::invalid(
                "right_cx",
                format!(
                    "{} px is beyond ±{:e} px",
                    self.right_cx,
                    crate::camera::MAX_PRINCIPAL_OFFSET_PX
                ),
            ));
        }
        Ok(())
    }

    /// Offset of the right principal point from the left's, pixels (Middlebury's `doffs`).
    pub fn doffs(&self) -> f64 {
        self.right_cx - self.intrinsics.cx
    }

    /// Z-depth, scene units, of a disparity in pixels: `fx·B / (d + doffs)`; infinite or
    /// negative where `d + doffs ≤ 0` (no point in front of both cameras).
    pub fn depth_of_disparity(&self, disparity_px: f64) -> f64 {
        self.intrinsics.fx * self.baseline / (disparity_px + self.doffs())
    }

    /// Disparity, pixels, of a z-depth in scene units: `fx·B / z − doffs`.
    pub fn disparity_of_depth(&self, z: f64) -> f64 {
        self.intrinsics.fx * self.baseline / z - self.doffs()
    }

    /// The right camera's intrinsics.
    pub fn right_intrinsics(&self) -> Intrinsics {
        Intrinsics {
            cx: self.right_cx,
            ..self.intrinsics
        }
    }

    /// The pair as the plane sweep's reference (left) and source (right) views.
    pub fn views<'a>(
        &self,
        left: &'a ImageF32,
        right: &'a ImageF32,
    ) -> Result<(View<'a>, View<'a>)> {
        Ok((
            View {
                image: left,
                intrinsics: self.intrinsics,
                pose: Pose::identity(),
            },
            View {
                image: right,
                intrinsics: self.right_intrinsics(),
                pose: Pose::translation_only([-self.baseline, 0.0, 0.0])?,
            },
        ))
    }

    /// The plane set for a search range: planes uniform in disparity between the range's
    /// ends, `num_planes` of them or (`None`) one per pixel of disparity plus one, 2 to
    /// [`MAX_PLANES`]. Errors name `min_disparity_px`, `max_disparity_px`, `near`, `far` or
    /// `num_planes`.
    pub fn planes(&self, range: StereoRange, num_planes: Option<usize>) -> Result<PlaneSet> {
        let (near, far) = match range {
            StereoRange::Depth { near, far } => {
                let p = PlaneSet::new(near, far, 2)?;
                (p.near, p.far)
            }
            StereoRange::Disparity { min_px, max_px } => {
                if !(min_px.is_finite() && min_px + self.doffs() > 0.0) {
                    return Err(MurkError::invalid(
                        "min_disparity_px",
                        format!(
                            "must be finite and > −doffs = {} (disparity + doffs = fx·B/z > 0 \
                             in front of the cameras), got {min_px}",
                            -self.doffs()
                        ),
                    ));
                }
                if !(max_px.is_finite() && max_px > min_px) {
                    return Err(MurkError::invalid(
                        "max_disparity_px",
                        format!("must be finite and > min_disparity_px {min_px}, got {max_px}"),
                    ));
                }
                (
                    self.depth_of_disparity(max_px),
                    self.depth_of_disparity(min_px),
                )
            }
        };
        let count = match num_planes {
            Some(n) => n,
            None => {
                let span = self.disparity_of_depth(near) - self.disparity_of_depth(far);
                // `as` saturates: an absurd span lands on the clamp, not on a wrap.
                (span.ceil() as usize)
                    .saturating_add(1)
                    .clamp(2, MAX_PLANES)
            }
        };
        PlaneSet::new(near, far, count)
    }
}

/// The depths a rectified pair is searched over.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StereoRange {
    /// Z-depths, scene units: `0 < near < far`, both finite.
    Depth {
        /// Nearest z-depth.
        near: f64,
        /// Farthest z-depth.
        far: f64,
    },
    /// Disparities, pixels: `−doffs < min_px < max_px`, both finite (the far end is
    /// `min_px`).
    Disparity {
        /// Smallest disparity (the farthest depth).
        min_px: f64,
        /// Largest disparity (the nearest depth).
        max_px: f64,
    },
}

impl StereoRange {
    /// The range used when none is given: disparities from 1 pixel to a quarter of the image
    /// width, at most [`DEFAULT_MAX_DISPARITY_PX`] (and at least 2 pixels more than the start).
    /// Give the range when the scene is known: every plane costs a pass over the image.
    pub fn default_for_width(width: usize) -> Self {
        let (min_px, max_px) = Self::default_disparities(width);
        StereoRange::Disparity { min_px, max_px }
    }

    /// The ends of [`StereoRange::default_for_width`], `(min, max)` pixels.
    pub fn default_disparities(width: usize) -> (f64, f64) {
        (
            1.0,
            (width as f64 / 4.0).clamp(3.0, DEFAULT_MAX_DISPARITY_PX),
        )
    }
}

/// How a rectified pair's depth is estimated.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RectifiedOptions {
    /// Search range; `None` = [`StereoRange::default_for_width`].
    pub range: Option<StereoRange>,
    /// Number of planes; `None` = one per pixel of disparity ([`RectifiedRig::planes`]).
    pub num_planes: Option<usize>,
    /// The photometric cost: [`CostKind::Ordinary`] in clear air, the dehazing volume with the
    /// haze's `A` and `β` (β per scene unit) through haze.
    pub cost: CostKind,
    /// Aggregation, matching, compensation and rejection parameters.
    pub depth: DepthParams,
}

impl Default for RectifiedOptions {
    fn default() -> Self {
        Self {
            range: None,
            num_planes: None,
            cost: CostKind::Ordinary,
            depth: DepthParams::default(),
        }
    }
}

/// Depth of a rectified pair's left view.
#[derive(Clone, Debug, PartialEq)]
pub struct RectifiedDepth {
    /// The plane sweep's result: z-depth (scene units), inverse depth, confidence, the
    /// compensation estimates and warnings.
    pub depth: DepthResult,
    /// Disparity of every left pixel, pixels: `fx·B / z − doffs` of `depth.z_depth`.
    pub disparity: ImageF32,
    /// The plane set searched (defaults resolved).
    pub planes: PlaneSet,
}

impl RectifiedDepth {
    /// The pixels with confidence `> 0` back-projected into the left camera's frame (x right,
    /// y down, z forward; scene units), coloured from `left` (values in `[0, 1]`). Pixels the
    /// consistency check or the speckle filter rejected, whose depth is filled from their
    /// neighbours, are left out.
    pub fn points(&self, rig: &RectifiedRig, left: &ImageF32) -> Result<Vec<ColoredPoint>> {
        backproject(
            &self.depth.z_depth,
            &self.depth.confidence,
            left,
            &rig.intrinsics,
            &Pose::identity(),
            f32::MIN_POSITIVE,
        )
    }
}

/// Depth, disparity and confidence of the left view of a rectified pair (Ch. 3.2 with the right
/// view as the one source). Both images must have the same size and 1 or 3 channels, every
/// sample finite. Errors name `left`, `right`, the rig's fields, the range's or `depth.…`;
/// cancellation through `monitor` returns `Cancelled`.
pub fn estimate_rectified(
    left: &ImageF32,
    right: &ImageF32,
    rig: &RectifiedRig,
    options: &RectifiedOptions,
    monitor: &Monitor,
) -> Result<RectifiedDepth> {
    estimate_rectified_from_prior(left, right, rig, options, &DepthPrior::default(), monitor)
}

/// [`estimate_rectified`] for the next pair of the same rig, with what the previous pair says
/// ([`DepthPrior`]: its photometric corrections, and plane windows of the planes
/// `options.range` and `options.num_planes` give; see [`estimate_depth_from_prior`]).
pub fn estimate_rectified_from_prior(
    left: &ImageF32,
    right: &ImageF32,
    rig: &RectifiedRig,
    options: &RectifiedOptions,
    prior: &DepthPrior<'_>,
    monitor: &Monitor,
) -> Result<RectifiedDepth> {
    rig.validate()?;
    let (reference, source) = rig.views(left, right)?;
    // The views' own errors name `image`: here the image *is* the field.
    let named = |side: &'static str| {
        move |e: MurkError| match e {
            MurkError::InvalidArgument { field, reason } if field == "image" => {
                MurkError::invalid(side, reason)
            }
            other => other.within(side),
        }
    };
    reference.validate(None).map_err(named("left"))?;
    source
        .validate(Some((left.width(), left.height(), left.channels())))
        .map_err(named("right"))?;
    let range = options
        .range
        .unwrap_or_else(|| StereoRange::default_for_width(left.width()));
    let planes = rig.planes(range, options.num_planes)?;
    options.depth.validate().map_err(|e| e.within("depth"))?;
    let depth = estimate_depth_from_prior(
        &reference,
        &[source],
        &planes,
        options.cost,
        &options.depth,
        prior,
        monitor,
    )?;
    let (w, h) = depth.z_depth.dims();
    let disparity = ImageF32::from_vec(
        w,
        h,
        1,
        depth
            .z_depth
            .data()
            .iter()
            .map(|&z| rig.disparity_of_depth(f64::from(z)) as f32)
            .collect(),
    )?;
    Ok(RectifiedDepth {
        depth,
        disparity,
        planes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn rig() -> RectifiedRig {
        RectifiedRig {
            intrinsics: Intrinsics::new(500.0, 500.0, 63.5, 47.5),
            baseline: 0.1,
            right_cx: 71.5,
        }
    }

    proptest! {
        /// Depth and disparity are each other's inverse wherever the point is in front of both
        /// cameras, and the projection through the rig's views lands `d` pixels to the left.
        #[test]
        fn disparity_and_depth_invert_and_match_the_projection(
            z in 0.2f64..100.0, u in 0.0f64..128.0, v in 0.0f64..96.0,
        ) {
            let r = rig();
            let d = r.disparity_of_depth(z);
            prop_assert!((r.depth_of_disparity(d) - z).abs() <= 1e-9 * z);
            let left = ImageF32::filled(4, 4, 1, 0.0);
            let (reference, source) = r.views(&left, &left).unwrap();
            let ray = reference.intrinsics.ray(u, v);
            let p = ray * (z / ray.z);
            let cam = source.pose.rotation() * p + source.pose.translation();
            let (ur, vr) = source.intrinsics.project(cam).unwrap();
            prop_assert!((u - ur - d).abs() < 1e-9 * (1.0 + d.abs()));
            prop_assert!((v - vr).abs() < 1e-9);
        }
    }

    #[test]
    fn default_planes_resolve_every_integer_disparity() {
        let r = rig();
        let p = r
            .planes(
                StereoRange::Disparity {
                    min_px: 4.0,
                    max_px: 68.0,
                },
                None,
            )
            .unwrap();
        assert_eq!(p.num_planes, 65);
        assert!((r.disparity_of_depth(p.near) - 68.0).abs() < 1e-9);
        assert!((r.disparity_of_depth(p.far) - 4.0).abs() < 1e-9);
        // Depth ranges give the same count for the same disparities.
        let q = r
            .planes(
                StereoRange::Depth {
                    near: p.near,
                    far: p.far,
                },
                None,
            )
            .unwrap();
        assert_eq!(q.num_planes, 65);
        assert_eq!(
            StereoRange::default_for_width(640),
            StereoRange::Disparity {
                min_px: 1.0,
                max_px: 160.0
            }
        );
        assert_eq!(
            StereoRange::default_for_width(4000),
            StereoRange::Disparity {
                min_px: 1.0,
                max_px: DEFAULT_MAX_DISPARITY_PX
            }
        );
    }

    #[test]
    fn bad_rigs_and_ranges_name_their_field() {
        let field = |e: MurkError| e.field().unwrap().to_string();
        let mut r = rig();
        r.baseline = 0.0;
        assert_eq!(field(r.validate().unwrap_err()), "baseline");
        let mut r = rig();
        r.intrinsics.skew = 0.5;
        assert_eq!(field(r.validate().unwrap_err()), "intrinsics.skew");
        let mut r = rig();
        r.intrinsics.fx = f64::NAN;
        assert_eq!(field(r.validate().unwrap_err()), "intrinsics.fx");
        let mut r = rig();
        r.right_cx = f64::INFINITY;
        assert_eq!(field(r.validate().unwrap_err()), "right_cx");
        let r = rig(); // doffs = 8
        let range = |min_px, max_px| StereoRange::Disparity { min_px, max_px };
        assert_eq!(
            field(r.planes(range(-8.0, 10.0), None).unwrap_err()),
            "min_disparity_px"
        );
        assert!(r.planes(range(-7.0, 10.0), None).is_ok());
        assert_eq!(
            field(r.planes(range(10.0, 10.0), None).unwrap_err()),
            "max_disparity_px"
        );
        assert_eq!(
            field(r.planes(range(1.0, f64::NAN), None).unwrap_err()),
            "max_disparity_px"
        );
        assert_eq!(
            field(
                r.planes(
                    StereoRange::Depth {
                        near: 2.0,
                        far: 1.0
                    },
                    None
                )
                .unwrap_err()
            ),
            "far"
        );
        assert_eq!(
            field(
                r.planes(range(1.0, 10.0), Some(MAX_PLANES + 1))
                    .unwrap_err()
            ),
            "num_planes"
        );
        let left = ImageF32::filled(8, 6, 3, 0.0);
        let right = ImageF32::filled(8, 5, 3, 0.0);
        let e = estimate_rectified(
            &left,
            &right,
            &rig(),
            &RectifiedOptions::default(),
            &Monitor::noop(),
        )
        .unwrap_err();
        assert_eq!(field(e), "right");
        let mut nan = ImageF32::filled(8, 6, 3, 0.0);
        nan.data_mut()[5] = f32::NAN;
        let e = estimate_rectified(
            &nan,
            &left,
            &rig(),
            &RectifiedOptions::default(),
            &Monitor::noop(),
        )
        .unwrap_err();
        assert_eq!(field(e), "left");
    }

    /// A textured fronto-parallel wall at a known depth seen by a rig with a principal-point
    /// offset: the recovered disparity is the wall's, away from the border the right view does
    /// not see.
    #[test]
    fn recovers_a_wall_through_a_rig_with_doffs() {
        let r = RectifiedRig {
            intrinsics: Intrinsics::new(120.0, 120.0, 47.5, 31.5),
            baseline: 0.2,
            right_cx: 51.5,
        };
        let z = 2.0;
        let d = r.disparity_of_depth(z); // 12 − 4 = 8 px
        let texture = |x: f64, y: f64| {
            (0.5 + 0.2 * (x * 0.9).sin() * (y * 0.7).cos() + 0.15 * (x * 0.31 + y * 0.23).sin())
                as f32
        };
        let (w, h) = (96, 64);
        let left = ImageF32::from_fn(w, h, |x, y| texture(x as f64, y as f64));
        let right = ImageF32::from_fn(w, h, |x, y| texture(x as f64 + d, y as f64));
        let out = estimate_rectified(
            &left,
            &right,
            &r,
            &RectifiedOptions {
                range: Some(StereoRange::Disparity {
                    min_px: 2.0,
                    max_px: 20.0,
                }),
                ..Default::default()
            },
            &Monitor::noop(),
        )
        .unwrap();
        assert_eq!(out.planes.num_planes, 19);
        let mut errors = Vec::new();
        for y in 8..h - 8 {
            for x in 24..w - 8 {
                errors.push((out.disparity.get(x, y, 0) as f64 - d).abs());
            }
        }
        errors.sort_by(f64::total_cmp);
        let median = errors[errors.len() / 2];
        assert!(median < 0.25, "median disparity error {median} px");
        let zmed = {
            let mut zs: Vec<f32> = out.depth.z_depth.data().to_vec();
            zs.sort_by(f32::total_cmp);
            zs[zs.len() / 2]
        };
        assert!((f64::from(zmed) - z).abs() < 0.1, "median depth {zmed}");
        // Without the photometric compensation too (no samples are collected then).
        let mut plain = RectifiedOptions {
            range: Some(StereoRange::Disparity {
                min_px: 2.0,
                max_px: 20.0,
            }),
            ..Default::default()
        };
        plain.depth.photometric.exposure_compensation = false;
        plain.depth.photometric.vignetting_compensation = false;
        let bare = estimate_rectified(&left, &right, &r, &plain, &Monitor::noop()).unwrap();
        assert_eq!(bare.depth.source_gains, vec![1.0]);
        assert_eq!(bare.depth.source_falloffs, vec![0.0]);
        assert!((f64::from(bare.disparity.get(w / 2, h / 2, 0)) - d).abs() < 0.5);
        let points = out.points(&r, &left).unwrap();
        let confident = out
            .depth
            .confidence
            .data()
            .iter()
            .filter(|&&c| c > 0.0)
            .count();
        assert_eq!(points.len(), confident);
        assert!(confident > w * h / 2);
    }
}
