//! `MvsDepthRequest` → [`MvsInput`] and [`DepthResult`] → `MvsDepthResult`.
//!
//! Everything the library would reject is checked here, at submission, so a bad request is
//! refused with `INVALID_ARGUMENT` naming the proto field instead of being queued and failing
//! later. Field names are relative to `MvsDepthRequest` (`sources[1].image`,
//! `reference.intrinsics.fx`, `near`, `airlight`, `sgm.p2`, ...); the submit path adds the outer
//! prefix (`request.mvs_depth.`) for `Jobs.SubmitJob`.

use super::geometry::{intrinsics_from_proto, intrinsics_to_proto};
use super::image::{image_from_proto, image_to_proto, ImageLimits};
use crate::service::proto::v1 as pb;
use murk::atmosphere::AtmosphereParams;
use murk::camera::Intrinsics;
use murk::error::{MurkError, Result};
use murk::image::ImageF32;
use murk::monitor::Monitor;
use murk::mvs::cost_volume::MAX_VOXELS;
use murk::mvs::{
    estimate_depth, planes_for_displacement, Camera, CostKind, DehazingOptions, DepthParams,
    DepthResult, PlaneSet, Pose, View,
};

/// Largest number of source views per request. Every source adds a full pass over the cost
/// volume (the cost is the mean over sources), while the reference (§3.2.3) uses a handful of
/// nearby views; 16 bounds a request's work at 16 × the one-source cost.
pub const MAX_SOURCE_VIEWS: usize = 16;

/// One decoded, validated view.
#[derive(Clone, Debug, PartialEq)]
pub struct MvsViewInput {
    /// The image (1 or 3 channels, finite).
    pub image: ImageF32,
    /// Pinhole intrinsics, pixels.
    pub intrinsics: Intrinsics,
    /// World-to-camera pose, scene units.
    pub pose: Pose,
}

impl MvsViewInput {
    /// The library's borrowed view.
    pub fn view(&self) -> View<'_> {
        View {
            image: &self.image,
            intrinsics: self.intrinsics,
            pose: self.pose,
        }
    }
}

/// A decoded and fully validated `MvsDepthRequest`, owning its images so the job can outlive the
/// request.
#[derive(Clone, Debug, PartialEq)]
pub struct MvsInput {
    /// The view whose depth is estimated.
    pub reference: MvsViewInput,
    /// The other views (1 ..= [`MAX_SOURCE_VIEWS`]).
    pub sources: Vec<MvsViewInput>,
    /// Plane set, defaults resolved.
    pub planes: PlaneSet,
    /// The library's cost kind.
    pub kind: CostKind,
    /// The wire kind it came from (UNSPECIFIED resolved), echoed in the result.
    pub wire_kind: pb::CostVolumeKind,
    /// Aggregation parameters, defaults resolved.
    pub sgm: DepthParams,
}

impl MvsInput {
    /// Runs [`estimate_depth`]. Library errors name library paths (`planes.near`,
    /// `atmosphere.beta`); they are mapped back to the proto's field names. (Validation at
    /// submission makes such errors unexpected; the mapping keeps them useful if the library's
    /// rules ever become stricter than this module's.)
    pub fn estimate(&self, monitor: &Monitor) -> Result<DepthResult> {
        let reference = self.reference.view();
        let sources: Vec<View<'_>> = self.sources.iter().map(MvsViewInput::view).collect();
        estimate_depth(
            &reference,
            &sources,
            &self.planes,
            self.kind,
            &self.sgm,
            monitor,
        )
        .map_err(|e| match e {
            MurkError::InvalidArgument { field, reason } => {
                MurkError::invalid(library_field_to_proto(&field), reason)
            }
            other => other,
        })
    }
}

/// The wire kind (UNSPECIFIED resolved) and the library's cost from a request's cost volume,
/// airlight and β. Errors name `cost_volume`, `airlight` or `beta`.
pub(super) fn cost_of(
    cost_volume: i32,
    airlight: f32,
    beta: f32,
) -> Result<(pb::CostVolumeKind, CostKind)> {
    let wire_kind = resolve_kind(cost_volume)?;
    for (name, v) in [("airlight", airlight), ("beta", beta)] {
        // Checked for every kind: ORDINARY ignores the values, but a NaN is a client bug.
        if !v.is_finite() {
            return Err(MurkError::invalid(name, format!("must be finite, got {v}")));
        }
    }
    let atmosphere = AtmosphereParams { airlight, beta };
    let kind = match wire_kind {
        pb::CostVolumeKind::Ordinary => CostKind::Ordinary,
        pb::CostVolumeKind::DehazingEq37 => CostKind::Dehazing(atmosphere),
        pb::CostVolumeKind::Dehazing | pb::CostVolumeKind::Unspecified => {
            CostKind::DehazingWith(atmosphere, DehazingOptions::default())
        }
    };
    if kind != CostKind::Ordinary {
        // Names `airlight` (A ∉ (0, 1], which includes an unset A = 0) or `beta`.
        atmosphere.validate().map_err(|e| {
            if e.field() == Some("airlight") && airlight == 0.0 {
                MurkError::invalid(
                    "airlight",
                    "required (in (0, 1]) for the dehazing cost volumes; got 0 (unset)",
                )
            } else {
                e
            }
        })?;
    }
    Ok((wire_kind, kind))
}

/// `planes.near` → `near`, `atmosphere.airlight` → `airlight`; other paths already match.
fn library_field_to_proto(field: &str) -> String {
    for prefix in ["planes.", "atmosphere."] {
        if let Some(rest) = field.strip_prefix(prefix) {
            return rest.to_string();
        }
    }
    field.to_string()
}

/// The wire kind with UNSPECIFIED resolved; unknown enum values fail naming `cost_volume`.
fn resolve_kind(v: i32) -> Result<pb::CostVolumeKind> {
    match pb::CostVolumeKind::try_from(v) {
        Ok(pb::CostVolumeKind::Unspecified) => Ok(pb::CostVolumeKind::Dehazing),
        Ok(k) => Ok(k),
        Err(_) => Err(MurkError::invalid(
            "cost_volume",
            format!("unknown cost volume kind {v}"),
        )),
    }
}

/// The plane range a request asks for, 0 meaning the reference's default, and the plane count
/// (`None` for 0: chosen from the views, [`auto_planes`]).
fn planes_of(req: &pb::MvsDepthRequest) -> (f64, f64, Option<usize>) {
    let d = PlaneSet::default();
    (
        if req.near == 0.0 { d.near } else { req.near },
        if req.far == 0.0 { d.far } else { req.far },
        (req.num_planes != 0).then_some(req.num_planes as usize),
    )
}

/// About one plane per pixel of the largest displacement of a reference pixel in any source
/// across `near..far` ([`planes_for_displacement`]), within the voxel limit.
pub(super) fn auto_planes(
    reference: &MvsViewInput,
    sources: &[MvsViewInput],
    near: f64,
    far: f64,
) -> usize {
    let camera = |v: &MvsViewInput| Camera {
        intrinsics: v.intrinsics,
        pose: v.pose,
        width: v.image.width(),
        height: v.image.height(),
    };
    let (w, h) = reference.image.dims();
    let cams: Vec<Camera> = sources.iter().map(camera).collect();
    planes_for_displacement(
        &camera(reference),
        &cams,
        near,
        far,
        MAX_VOXELS / (w * h).max(1),
    )
}

pub(super) fn sgm_of(o: Option<&pb::SgmOptions>) -> DepthParams {
    let mut p = DepthParams::default();
    if let Some(o) = o {
        p.sgm.p1 = o.p1.unwrap_or(p.sgm.p1);
        p.sgm.p2 = o.p2.unwrap_or(p.sgm.p2);
        p.sgm.p2_gradient_scale = o.p2_gradient_scale.unwrap_or(p.sgm.p2_gradient_scale);
        p.sgm.num_paths = o.num_paths.map_or(p.sgm.num_paths, |v| v as usize);
        p.matching.cost_window_radius = o
            .cost_window_radius
            .map_or(p.matching.cost_window_radius, |v| v as usize);
        p.matching.presmooth_sigma_px = o
            .presmooth_sigma_px
            .unwrap_or(p.matching.presmooth_sigma_px);
        p.matching.contrast_percentile = o
            .contrast_percentile
            .unwrap_or(p.matching.contrast_percentile);
        p.matching.contrast_max_weight = o
            .contrast_max_weight
            .unwrap_or(p.matching.contrast_max_weight);
        p.rejection.consistency_check =
            o.consistency_check.unwrap_or(p.rejection.consistency_check);
        p.rejection.consistency_tolerance_planes = o
            .consistency_tolerance_planes
            .unwrap_or(p.rejection.consistency_tolerance_planes);
        if let Some(s) = o.speckle_max_size_px {
            p.rejection.speckle_max_size_px = Some(s as usize);
        }
        p.rejection.speckle_range_planes = o
            .speckle_range_planes
            .unwrap_or(p.rejection.speckle_range_planes);
        p.sgm.volume_budget_mib = o
            .volume_budget_mib
            .map_or(p.sgm.volume_budget_mib, |v| v as usize);
        p.photometric.exposure_compensation = o
            .exposure_compensation
            .unwrap_or(p.photometric.exposure_compensation);
        p.matching.census_weight = o.census_weight.unwrap_or(p.matching.census_weight);
        p.photometric.vignetting_compensation = o
            .vignetting_compensation
            .unwrap_or(p.photometric.vignetting_compensation);
    }
    p
}

/// Rewrites `req` into its canonical form before it is hashed into a job id, so requests that
/// mean the same computation share one id (and one cached result): defaults written out (0
/// planes/near/far, UNSPECIFIED kind, unset SGM fields), and airlight/β zeroed for ORDINARY,
/// which ignores them. Values that will be rejected (NaN, unknown enum values) are left alone
/// so validation still sees them.
pub fn canonicalize_mvs_request(req: &mut pb::MvsDepthRequest) {
    // num_planes 0 stays 0: "from the views' displacement" is itself deterministic in the request.
    let (near, far, _) = planes_of(req);
    req.near = near;
    req.far = far;
    canonicalize_cost(&mut req.cost_volume, &mut req.airlight, &mut req.beta);
    if let Some(sgm) = canonical_sgm(req.sgm.as_ref()) {
        req.sgm = Some(sgm);
    }
}

/// The canonical cost volume: UNSPECIFIED resolved, and airlight/β zeroed for ORDINARY, which
/// ignores them (unless they are not finite, so validation still sees them).
pub(super) fn canonicalize_cost(cost_volume: &mut i32, airlight: &mut f32, beta: &mut f32) {
    if let Ok(kind) = resolve_kind(*cost_volume) {
        *cost_volume = kind as i32;
        if kind == pb::CostVolumeKind::Ordinary && airlight.is_finite() && beta.is_finite() {
            *airlight = 0.0;
            *beta = 0.0;
        }
    }
}

/// SGM options with every default written out; `None` when a value does not fit its wire type
/// (never, for u32 counts that came from u32s).
pub(super) fn canonical_sgm(o: Option<&pb::SgmOptions>) -> Option<pb::SgmOptions> {
    let p = sgm_of(o);
    let (Ok(num_paths), Ok(radius)) = (
        u32::try_from(p.sgm.num_paths),
        u32::try_from(p.matching.cost_window_radius),
    ) else {
        return None;
    };
    Some(pb::SgmOptions {
        p1: Some(p.sgm.p1),
        p2: Some(p.sgm.p2),
        p2_gradient_scale: Some(p.sgm.p2_gradient_scale),
        num_paths: Some(num_paths),
        cost_window_radius: Some(radius),
        presmooth_sigma_px: Some(p.matching.presmooth_sigma_px),
        contrast_percentile: Some(p.matching.contrast_percentile),
        contrast_max_weight: Some(p.matching.contrast_max_weight),
        consistency_check: Some(p.rejection.consistency_check),
        consistency_tolerance_planes: Some(p.rejection.consistency_tolerance_planes),
        // Unset means "from the image size", itself deterministic in the request.
        speckle_max_size_px: p
            .rejection
            .speckle_max_size_px
            .and_then(|s| u32::try_from(s).ok()),
        speckle_range_planes: Some(p.rejection.speckle_range_planes),
        volume_budget_mib: u32::try_from(p.sgm.volume_budget_mib).ok(),
        exposure_compensation: Some(p.photometric.exposure_compensation),
        census_weight: Some(p.matching.census_weight),
        vignetting_compensation: Some(p.photometric.vignetting_compensation),
    })
}

/// Decodes and fully validates an MVS request. Field names are relative to `MvsDepthRequest`.
/// Cheap scalar checks run before any image is decoded.
pub fn mvs_from_proto(req: &pb::MvsDepthRequest, limits: &ImageLimits) -> Result<MvsInput> {
    let (wire_kind, kind) = cost_of(req.cost_volume, req.airlight, req.beta)?;
    let (near, far, requested_planes) = planes_of(req);
    // The range is checked now, the count once the views are decoded.
    PlaneSet::new(near, far, requested_planes.unwrap_or(2))?;
    let sgm = sgm_of(req.sgm.as_ref());
    sgm.validate().map_err(|e| e.within("sgm"))?;
    if req.sources.is_empty() {
        return Err(MurkError::invalid(
            "sources",
            "need at least one source view",
        ));
    }
    if req.sources.len() > MAX_SOURCE_VIEWS {
        return Err(MurkError::invalid(
            "sources",
            format!(
                "at most {MAX_SOURCE_VIEWS} source views, got {}",
                req.sources.len()
            ),
        ));
    }

    let reference =
        view_from_proto(req.reference.as_ref(), None, limits).map_err(|e| e.within("reference"))?;
    let (w, h) = reference.image.dims();
    if let Some(n) = requested_planes {
        let voxels = w.checked_mul(h).and_then(|p| p.checked_mul(n));
        if voxels.is_none_or(|v| v > MAX_VOXELS) {
            return Err(MurkError::invalid(
                "num_planes",
                format!(
                    "{w}x{h} pixels x {n} planes exceeds the cost-volume limit of \
                     {MAX_VOXELS} voxels; use fewer planes or smaller images"
                ),
            ));
        }
    }
    let sources = sources_from_proto(&req.sources, &reference, limits)?;
    let num_planes =
        requested_planes.unwrap_or_else(|| auto_planes(&reference, &sources, near, far));
    let planes = PlaneSet::new(near, far, num_planes)?;
    Ok(MvsInput {
        reference,
        sources,
        planes,
        kind,
        wire_kind,
        sgm,
    })
}

/// The source views, each checked against the reference's size and channel count; errors name
/// `sources[k].…`.
pub(super) fn sources_from_proto(
    sources: &[pb::MvsView],
    reference: &MvsViewInput,
    limits: &ImageLimits,
) -> Result<Vec<MvsViewInput>> {
    let (w, h) = reference.image.dims();
    let shape = (w, h, reference.image.channels());
    sources
        .iter()
        .enumerate()
        .map(|(k, s)| {
            view_from_proto(Some(s), Some(shape), limits)
                .map_err(|e| e.within(&format!("sources[{k}]")))
        })
        .collect()
}

/// One view; `shape` is the reference's `(width, height, channels)` for sources. Errors name
/// `image`, `intrinsics.…` or `pose.…` (or the view itself when it is missing).
pub(super) fn view_from_proto(
    v: Option<&pb::MvsView>,
    shape: Option<(usize, usize, usize)>,
    limits: &ImageLimits,
) -> Result<MvsViewInput> {
    let v = v.ok_or_else(|| MurkError::invalid("", "required"))?;
    let image = v
        .image
        .as_ref()
        .ok_or_else(|| MurkError::invalid("image", "required"))
        .and_then(|i| image_from_proto(i, limits).map_err(|e| e.within("image")))?;
    let k = v
        .intrinsics
        .as_ref()
        .ok_or_else(|| MurkError::invalid("intrinsics", "required"))?;
    let intrinsics = intrinsics_from_proto(k);
    let pose = v
        .pose
        .as_ref()
        .ok_or_else(|| MurkError::invalid("pose", "required (world-to-camera)"))
        .and_then(|p| pose_from_proto(p).map_err(|e| e.within("pose")))?;
    // The library's own check (shape against the reference, channels, finite pixels,
    // intrinsics, pose), run here so bad input is refused before a job is queued.
    View {
        image: &image,
        intrinsics,
        pose,
    }
    .validate(shape)?;
    Ok(MvsViewInput {
        image,
        intrinsics,
        pose,
    })
}

/// `murk.v1.Pose` → [`Pose`], validated; errors name `rotation` or `translation`.
pub fn pose_from_proto(p: &pb::Pose) -> Result<Pose> {
    let r: [f64; 9] = p.rotation.as_slice().try_into().map_err(|_| {
        MurkError::invalid(
            "rotation",
            format!("need 9 values (row-major 3x3), got {}", p.rotation.len()),
        )
    })?;
    let t: [f64; 3] = p.translation.as_slice().try_into().map_err(|_| {
        MurkError::invalid(
            "translation",
            format!("need 3 values, got {}", p.translation.len()),
        )
    })?;
    Pose::from_rows(
        [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]],
        t,
    )
}

/// [`Pose`] for the wire.
pub fn pose_to_proto(p: &Pose) -> pb::Pose {
    pb::Pose {
        rotation: p.rotation_rows().iter().flatten().copied().collect(),
        translation: p.translation().iter().copied().collect(),
    }
}

pub(super) fn view_to_proto(v: &View<'_>) -> pb::MvsView {
    pb::MvsView {
        image: Some(image_to_proto(v.image)),
        intrinsics: Some(intrinsics_to_proto(&v.intrinsics)),
        pose: Some(pose_to_proto(&v.pose)),
    }
}

/// A request for `reference` against `sources` (clients: CLI, demo, tests). Images travel as raw
/// f32 so nothing is lost to quantisation. `atmosphere` `None` leaves airlight and β unset (fine
/// for ORDINARY only); `planes` `None` leaves the plane range to the server's defaults; SGM
/// parameters are left at their defaults.
pub fn mvs_request_to_proto(
    reference: &View<'_>,
    sources: &[View<'_>],
    cost_volume: pb::CostVolumeKind,
    atmosphere: Option<AtmosphereParams>,
    planes: Option<&PlaneSet>,
) -> pb::MvsDepthRequest {
    pb::MvsDepthRequest {
        reference: Some(view_to_proto(reference)),
        sources: sources.iter().map(view_to_proto).collect(),
        airlight: atmosphere.map_or(0.0, |a| a.airlight),
        beta: atmosphere.map_or(0.0, |a| a.beta),
        near: planes.map_or(0.0, |p| p.near),
        far: planes.map_or(0.0, |p| p.far),
        num_planes: planes.map_or(0, |p| u32::try_from(p.num_planes).unwrap_or(u32::MAX)),
        cost_volume: cost_volume as i32,
        sgm: None,
    }
}

/// Encodes the method's output for the wire, echoing the plane set and cost volume used.
pub fn mvs_to_proto(
    input: &MvsInput,
    out: &DepthResult,
    compute_seconds: f64,
) -> pb::MvsDepthResult {
    pb::MvsDepthResult {
        z_depth: Some(image_to_proto(&out.z_depth)),
        inverse_depth: Some(image_to_proto(&out.inverse_depth)),
        confidence: Some(image_to_proto(&out.confidence)),
        near: input.planes.near,
        far: input.planes.far,
        num_planes: u32::try_from(input.planes.num_planes).unwrap_or(u32::MAX),
        cost_volume: input.wire_kind as i32,
        compute_seconds,
        source_gains: out.source_gains.clone(),
        vignetting_falloff: out.vignetting_falloff,
        warnings: out.warnings.clone(),
        source_falloffs: out.source_falloffs.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use murk::mvs::MAX_PLANES;

    /// The field an `InvalidArgument` names; panics on any other error.
    fn field_of(e: MurkError) -> String {
        match e.field() {
            Some(f) => f.to_string(),
            None => panic!("expected InvalidArgument, got {e:?}"),
        }
    }

    fn view(w: usize, h: usize, tx: f64) -> (ImageF32, Intrinsics, Pose) {
        let img = ImageF32::from_vec(
            w,
            h,
            3,
            (0..w * h * 3).map(|i| (i % 17) as f32 / 17.0).collect(),
        )
        .unwrap();
        let k = Intrinsics::new(50.0, 50.0, (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let pose = Pose::translation_only([tx, 0.0, 0.0]).unwrap();
        (img, k, pose)
    }

    fn request(kind: pb::CostVolumeKind) -> pb::MvsDepthRequest {
        let (ri, rk, rp) = view(16, 12, 0.0);
        let (si, sk, sp) = view(16, 12, -0.1);
        let r = View {
            image: &ri,
            intrinsics: rk,
            pose: rp,
        };
        let s = View {
            image: &si,
            intrinsics: sk,
            pose: sp,
        };
        mvs_request_to_proto(
            &r,
            &[s],
            kind,
            Some(AtmosphereParams {
                airlight: 0.8,
                beta: 0.1,
            }),
            Some(&PlaneSet::new(1.0, 10.0, 8).unwrap()),
        )
    }

    fn err(req: &pb::MvsDepthRequest) -> String {
        field_of(mvs_from_proto(req, &ImageLimits::default()).unwrap_err())
    }

    #[test]
    fn round_trips_and_resolves_defaults() {
        let mut req = request(pb::CostVolumeKind::Unspecified);
        req.near = 0.0;
        req.far = 0.0;
        req.num_planes = 0;
        let input = mvs_from_proto(&req, &ImageLimits::default()).unwrap();
        let d = PlaneSet::default();
        assert_eq!((input.planes.near, input.planes.far), (d.near, d.far));
        // The count from the views: one plane per pixel of the largest displacement.
        assert_eq!(
            input.planes.num_planes,
            auto_planes(&input.reference, &input.sources, d.near, d.far)
        );
        assert!((murk::mvs::AUTO_PLANES_MIN..=murk::mvs::AUTO_PLANES_MAX)
            .contains(&input.planes.num_planes));
        assert_eq!(input.wire_kind, pb::CostVolumeKind::Dehazing);
        assert!(
            matches!(input.kind, CostKind::DehazingWith(_, o) if o == DehazingOptions::default())
        );
        assert_eq!(input.sgm, DepthParams::default());
        assert_eq!(input.sources.len(), 1);
        assert_eq!(
            input.sources[0].pose.translation().as_slice(),
            [-0.1, 0.0, 0.0]
        );
        let eq37 = mvs_from_proto(
            &request(pb::CostVolumeKind::DehazingEq37),
            &ImageLimits::default(),
        )
        .unwrap();
        assert!(matches!(eq37.kind, CostKind::Dehazing(_)));
    }

    #[test]
    fn canonical_form_merges_equivalent_requests() {
        let explicit = {
            let mut r = request(pb::CostVolumeKind::Dehazing);
            r.near = PlaneSet::default().near;
            r.far = PlaneSet::default().far;
            // 0 = from the views in both (a fixed count is another computation).
            r.num_planes = 0;
            r.sgm = Some(pb::SgmOptions {
                p1: Some(DepthParams::default().sgm.p1),
                census_weight: Some(0.0),
                ..Default::default()
            });
            r
        };
        let implicit = {
            let mut r = request(pb::CostVolumeKind::Unspecified);
            r.near = 0.0;
            r.far = 0.0;
            r.num_planes = 0;
            r
        };
        let (mut a, mut b) = (explicit, implicit);
        canonicalize_mvs_request(&mut a);
        canonicalize_mvs_request(&mut b);
        assert_eq!(a, b);
        // The census term is another computation.
        let mut census = a.clone();
        census.sgm.as_mut().unwrap().census_weight = Some(1.0);
        canonicalize_mvs_request(&mut census);
        assert_ne!(census, a);
        assert_eq!(
            mvs_from_proto(&census, &ImageLimits::default())
                .unwrap()
                .sgm
                .matching
                .census_weight,
            1.0
        );
        // ORDINARY ignores the atmosphere, so it does not split the id...
        let mut o1 = request(pb::CostVolumeKind::Ordinary);
        let mut o2 = o1.clone();
        o2.airlight = 0.3;
        canonicalize_mvs_request(&mut o1);
        canonicalize_mvs_request(&mut o2);
        assert_eq!(o1, o2);
        // ...but a NaN survives to be rejected.
        let mut bad = request(pb::CostVolumeKind::Ordinary);
        bad.beta = f32::NAN;
        canonicalize_mvs_request(&mut bad);
        assert_eq!(err(&bad), "beta");
    }

    #[test]
    fn errors_name_proto_fields() {
        let good = request(pb::CostVolumeKind::Dehazing);
        let mut r = good.clone();
        r.sources.clear();
        assert_eq!(err(&r), "sources");
        let mut r = good.clone();
        r.sources = vec![r.sources[0].clone(); MAX_SOURCE_VIEWS + 1];
        assert_eq!(err(&r), "sources");
        let mut r = good.clone();
        r.reference = None;
        assert_eq!(err(&r), "reference");
        let mut r = good.clone();
        r.sources[0].intrinsics.as_mut().unwrap().fy = 0.0;
        assert_eq!(err(&r), "sources[0].intrinsics.fy");
        let mut r = good.clone();
        r.reference
            .as_mut()
            .unwrap()
            .pose
            .as_mut()
            .unwrap()
            .rotation
            .pop();
        assert_eq!(err(&r), "reference.pose.rotation");
        let mut r = good.clone();
        r.reference
            .as_mut()
            .unwrap()
            .pose
            .as_mut()
            .unwrap()
            .rotation[0] = 2.0;
        assert_eq!(err(&r), "reference.pose.rotation");
        let mut r = good.clone();
        r.sources[0].pose = None;
        assert_eq!(err(&r), "sources[0].pose");
        let mut r = good.clone();
        r.cost_volume = 99;
        assert_eq!(err(&r), "cost_volume");
        let mut r = good.clone();
        r.near = 20.0;
        assert_eq!(err(&r), "far");
        let mut r = good.clone();
        r.near = -1.0;
        assert_eq!(err(&r), "near");
        let mut r = good.clone();
        r.num_planes = MAX_PLANES as u32 + 1;
        assert_eq!(err(&r), "num_planes");
        let mut r = good.clone();
        r.airlight = 0.0;
        assert_eq!(err(&r), "airlight");
        let mut r = good.clone();
        r.beta = -0.1;
        assert_eq!(err(&r), "beta");
        let mut r = good.clone();
        r.sgm = Some(pb::SgmOptions {
            num_paths: Some(3),
            ..Default::default()
        });
        assert_eq!(err(&r), "sgm.num_paths");
        let mut r = good.clone();
        r.sgm = Some(pb::SgmOptions {
            presmooth_sigma_px: Some(-0.5),
            ..Default::default()
        });
        assert_eq!(err(&r), "sgm.presmooth_sigma_px");
        let mut r = good.clone();
        r.sgm = Some(pb::SgmOptions {
            contrast_max_weight: Some(0.5),
            ..Default::default()
        });
        assert_eq!(err(&r), "sgm.contrast_max_weight");
        let mut r = good.clone();
        r.sgm = Some(pb::SgmOptions {
            contrast_percentile: Some(101.0),
            ..Default::default()
        });
        assert_eq!(err(&r), "sgm.contrast_percentile");
        for (o, field) in [
            (
                pb::SgmOptions {
                    consistency_tolerance_planes: Some(f32::NAN),
                    ..Default::default()
                },
                "sgm.consistency_tolerance_planes",
            ),
            (
                pb::SgmOptions {
                    speckle_range_planes: Some(-1.0),
                    ..Default::default()
                },
                "sgm.speckle_range_planes",
            ),
            (
                pb::SgmOptions {
                    speckle_max_size_px: Some(u32::MAX),
                    ..Default::default()
                },
                "sgm.speckle_max_size_px",
            ),
            (
                pb::SgmOptions {
                    volume_budget_mib: Some(0),
                    ..Default::default()
                },
                "sgm.volume_budget_mib",
            ),
        ] {
            let mut r = good.clone();
            r.sgm = Some(o);
            assert_eq!(err(&r), field);
        }
        // ORDINARY ignores A and β, but not NaN.
        let mut r = request(pb::CostVolumeKind::Ordinary);
        r.airlight = 0.0;
        r.beta = -1.0;
        assert!(mvs_from_proto(&r, &ImageLimits::default()).is_ok());
        r.airlight = f32::NAN;
        assert_eq!(err(&r), "airlight");
    }

    #[test]
    fn library_paths_map_to_proto_fields() {
        assert_eq!(library_field_to_proto("planes.near"), "near");
        assert_eq!(library_field_to_proto("atmosphere.beta"), "beta");
        assert_eq!(
            library_field_to_proto("sources[2].image"),
            "sources[2].image"
        );
    }

    #[test]
    fn estimates_depth_of_a_tiny_request() {
        let input = mvs_from_proto(
            &request(pb::CostVolumeKind::Ordinary),
            &ImageLimits::default(),
        )
        .unwrap();
        let out = input.estimate(&Monitor::noop()).unwrap();
        assert_eq!(out.z_depth.dims(), (16, 12));
        let wire = mvs_to_proto(&input, &out, 0.5);
        assert_eq!(wire.num_planes, 8);
        assert_eq!(wire.cost_volume, pb::CostVolumeKind::Ordinary as i32);
        assert_eq!(wire.z_depth.unwrap().width, 16);
    }
}
