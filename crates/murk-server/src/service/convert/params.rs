//! `ScatteringParamsRequest` → [`ParamsInput`] and the search + final depth →
//! `ScatteringParamsResult`.
//!
//! As for MVS, every rule is checked at submission (field names relative to
//! `ScatteringParamsRequest`: `sources[0].image`, `sparse_points`, `beta_max`, ...), including
//! that enough SfM points project into the reference view, so a request that cannot be searched
//! is refused before it is queued.

use std::sync::Arc;
use std::time::Instant;

use super::image::{image_to_proto, ImageLimits};
use super::mvs::{
    auto_planes, sgm_of, sources_from_proto, view_from_proto, view_to_proto, MvsViewInput,
    MAX_SOURCE_VIEWS,
};
use crate::service::proto::v1 as pb;
use murk::atmosphere::AtmosphereParams;
use murk::error::{MurkError, Result};
use murk::monitor::Monitor;
use murk::mvs::cost_volume::MAX_VOXELS;
use murk::mvs::{estimate_depth, CostKind, DehazingOptions, PlaneSet, View, MAX_PLANES};
use murk::params::airlight::{dark_channel_airlight, AirlightEstimator, DarkChannelParams};
use murk::params::joint_fit::{Identifiability, JointFit};
use murk::params::pose_error::{Observation, SfmTracks};
use murk::params::search::{
    plane_range_from_sparse, search_scattering, BetaBound, BetaSource, SearchParams, SearchStage,
    SfmEvidence, CNN_AIRLIGHT_ERROR, DARK_CHANNEL_AIRLIGHT_ERROR, MIN_SPARSE_POINTS,
};
use murk::params::sparse::SparseDepth;

/// Most SfM points per request (COLMAP reconstructions of a few hundred images have ~10⁵).
pub const MAX_SPARSE_POINTS: usize = 1_000_000;
/// Most `sparse_point_observations` per sparse point (a track longer than this many views of
/// one request cannot exist: a request has at most 1 + `MAX_SOURCE_VIEWS` views).
pub const MAX_OBSERVATIONS_PER_POINT: usize = 64;

/// The airlight estimators a server offers: its configured estimator (the CNN, or the dark
/// channel when configured so or fallen back to), used for `AIRLIGHT_SOURCE_UNSPECIFIED`.
#[derive(Clone, Debug)]
pub struct AirlightService {
    /// The configured estimator.
    estimator: Arc<AirlightEstimator>,
    /// Fingerprint of the CNN weights.
    digest: String,
}

impl AirlightService {
    /// The wire source that UNSPECIFIED means on this server.
    pub fn default_source(&self) -> pb::AirlightSource {
        match *self.estimator {
            AirlightEstimator::DarkChannel(_) => pb::AirlightSource::DarkChannel,
            AirlightEstimator::Cnn(_) => pb::AirlightSource::Cnn,
        }
    }

    /// SHA-256 of the CNN's weights (hex), computed once; empty without a CNN.
    pub fn model_digest(&self) -> String {
        self.digest.clone()
    }

    /// Wraps `estimator`, fingerprinting the CNN's weights for job ids.
    pub fn new(estimator: AirlightEstimator) -> Self {
        let digest = match &estimator {
            AirlightEstimator::Cnn(cnn) => format!("airlight-cnn:{}", cnn.digest()),
            AirlightEstimator::DarkChannel(_) => String::new(),
        };
        Self {
            estimator: Arc::new(estimator),
            digest,
        }
    }

    /// Whether the CNN is loaded.
    fn has_cnn(&self) -> bool {
        self.default_source() == pb::AirlightSource::Cnn
    }
}

/// The `sparse_point_sources` mask with a bit for each of `n` sources (n ≤ 32).
fn every_source_mask(n: usize) -> u32 {
    if n >= 32 {
        u32::MAX
    } else {
        (1u32 << n) - 1
    }
}

/// A decoded, validated request.
#[derive(Clone, Debug)]
pub struct ParamsInput {
    /// The reference view.
    pub reference: MvsViewInput,
    /// The sources.
    pub sources: Vec<MvsViewInput>,
    /// Eq. 3.8's sparse depth in the reference view (full resolution).
    pub sparse: SparseDepth,
    /// The points with their observations, when the request carried them: the poses' share of
    /// the standard errors.
    pub tracks: Option<SfmTracks>,
    /// Where `A₀` comes from (UNSPECIFIED resolved).
    pub airlight_source: pb::AirlightSource,
    /// `A₀` for GIVEN.
    pub airlight_given: f32,
    /// Search settings, defaults resolved.
    pub search: SearchParams,
    /// Plane set of the final depth (its range is also the search's).
    pub planes: PlaneSet,
    /// The server's estimators.
    pub airlight: AirlightService,
}

/// Rewrites defaults into explicit values before hashing, so equivalent requests share one job
/// id: UNSPECIFIED airlight source → the server's, unset search settings → the reference's.
/// (near/far = 0 stay 0: "from the SfM points" is itself deterministic in the request.)
pub fn canonicalize_params_request(
    req: &mut pb::ScatteringParamsRequest,
    airlight: &AirlightService,
) {
    let d = SearchParams::default();
    if req.airlight_source == pb::AirlightSource::Unspecified as i32 {
        req.airlight_source = airlight.default_source() as i32;
    }
    // beta_min/beta_max/delta_beta stay unset: "from the SfM points" / "10 % of beta0" are
    // themselves deterministic in the request.
    req.beta_steps.get_or_insert(d.beta_steps as u32);
    req.grid_steps.get_or_insert(d.grid_steps as u32);
    req.delta_airlight.get_or_insert(d.delta_airlight);
    req.delta_px.get_or_insert(d.delta_px as u32);
    req.min_improvement_t.get_or_insert(d.min_improvement_t);
    req.beta_from_points.get_or_insert(d.beta_from_points);
    req.joint_fit.get_or_insert(d.joint_fit);
    req.airlight_prior_sigma
        .get_or_insert(d.airlight_prior_sigma);
    if req.search_planes == 0 {
        req.search_planes = d.search_planes as u32;
    }
    if req.search_downsample == 0 {
        req.search_downsample = d.search_downsample as u32;
    }
    // Every point seen by every source says no more than no masks at all.
    let every = every_source_mask(req.sources.len());
    if !req.sparse_point_sources.is_empty() && req.sparse_point_sources.iter().all(|&m| m == every)
    {
        req.sparse_point_sources.clear();
    }
}

/// Decodes and validates a request (canonicalized or not). Scalars are checked before images
/// are decoded.
pub fn params_from_proto(
    req: &pb::ScatteringParamsRequest,
    limits: &ImageLimits,
    airlight: &AirlightService,
) -> Result<ParamsInput> {
    let source = match pb::AirlightSource::try_from(req.airlight_source) {
        Ok(pb::AirlightSource::Unspecified) => airlight.default_source(),
        Ok(s) => s,
        Err(_) => {
            return Err(MurkError::invalid(
                "airlight_source",
                format!("unknown airlight source {}", req.airlight_source),
            ))
        }
    };
    if source == pb::AirlightSource::Cnn && !airlight.has_cnn() {
        return Err(MurkError::invalid(
            "airlight_source",
            "the CNN airlight estimator is not loaded on this server (it runs the dark-channel \
             estimator); ask for AIRLIGHT_SOURCE_DARK_CHANNEL or GIVEN",
        ));
    }
    if source == pb::AirlightSource::Given {
        if !(req.airlight.is_finite() && req.airlight > 0.0 && req.airlight <= 1.0) {
            return Err(MurkError::invalid(
                "airlight",
                format!(
                    "AIRLIGHT_SOURCE_GIVEN needs an airlight in (0, 1], got {}",
                    req.airlight
                ),
            ));
        }
    } else if req.airlight != 0.0 {
        return Err(MurkError::invalid(
            "airlight",
            format!(
                "only used with AIRLIGHT_SOURCE_GIVEN; must be 0 (unset) otherwise, got {}",
                req.airlight
            ),
        ));
    }
    let d = SearchParams::default();
    let or = |v: u32, def: usize| if v == 0 { def } else { v as usize };
    let search = SearchParams {
        beta_min: req.beta_min,
        beta_max: req.beta_max,
        beta_steps: req.beta_steps.map_or(d.beta_steps, |v| v as usize),
        grid_steps: req.grid_steps.map_or(d.grid_steps, |v| v as usize),
        delta_airlight: req.delta_airlight.unwrap_or(d.delta_airlight),
        delta_beta: req.delta_beta,
        delta_px: req.delta_px.map_or(d.delta_px, |v| v as usize),
        search_downsample: or(req.search_downsample, d.search_downsample),
        search_planes: or(req.search_planes, d.search_planes),
        cost: DehazingOptions::default(),
        depth: sgm_of(req.sgm.as_ref()),
        min_improvement_t: req.min_improvement_t.unwrap_or(d.min_improvement_t),
        beta_from_points: req.beta_from_points.unwrap_or(d.beta_from_points),
        joint_fit: req.joint_fit.unwrap_or(d.joint_fit),
        airlight_prior_sigma: req.airlight_prior_sigma.unwrap_or(d.airlight_prior_sigma),
        // How far A₀ is typically off, for the conflict test: measured for the estimators, the
        // caller's own prior scale for a given A₀.
        airlight_initial_error: match source {
            pb::AirlightSource::Given => req.airlight_prior_sigma.unwrap_or(d.airlight_prior_sigma),
            pb::AirlightSource::DarkChannel => DARK_CHANNEL_AIRLIGHT_ERROR,
            _ => CNN_AIRLIGHT_ERROR,
        },
    };
    search.validate()?;
    // 0 = from the views' displacement across the plane range, once both are known.
    let requested_planes = (req.num_planes != 0).then_some(req.num_planes as usize);
    let num_planes = requested_planes.unwrap_or(2);
    if num_planes > MAX_PLANES {
        return Err(MurkError::invalid(
            "num_planes",
            format!("must be in 1..={MAX_PLANES}, got {num_planes}"),
        ));
    }
    if (req.near == 0.0) != (req.far == 0.0) {
        return Err(MurkError::invalid(
            if req.near == 0.0 { "near" } else { "far" },
            "set both near and far, or neither (0 = from the SfM points)",
        ));
    }
    if req.sparse_points.len() > MAX_SPARSE_POINTS {
        return Err(MurkError::invalid(
            "sparse_points",
            format!(
                "at most {MAX_SPARSE_POINTS} points, got {}",
                req.sparse_points.len()
            ),
        ));
    }
    if req.sources.is_empty() || req.sources.len() > MAX_SOURCE_VIEWS {
        return Err(MurkError::invalid(
            "sources",
            format!(
                "need 1 to {MAX_SOURCE_VIEWS} source views, got {}",
                req.sources.len()
            ),
        ));
    }
    let reference =
        view_from_proto(req.reference.as_ref(), None, limits).map_err(|e| e.within("reference"))?;
    let (w, h) = reference.image.dims();
    let sources = sources_from_proto(&req.sources, &reference, limits)?;
    let points: Vec<[f64; 3]> = req.sparse_points.iter().map(|p| [p.x, p.y, p.z]).collect();
    let masks = &req.sparse_point_sources;
    let every = every_source_mask(sources.len());
    if let Some(i) = masks.iter().position(|&m| m & !every != 0) {
        return Err(MurkError::invalid(
            format!("sparse_point_sources[{i}]"),
            format!(
                "mask {:#x} names a source at or above the {} sources given",
                masks[i],
                sources.len()
            ),
        ));
    }
    let sparse = SparseDepth::from_tracked_points(
        &points,
        masks,
        &reference.intrinsics,
        &reference.pose,
        w,
        h,
    )
    // The library names `points[i]` and `seen_by`; the wire fields are `sparse_points[i]` and
    // `sparse_point_sources`.
    .map_err(|e| match e {
        MurkError::InvalidArgument { field, reason } if field == "seen_by" => {
            MurkError::invalid("sparse_point_sources", reason)
        }
        MurkError::InvalidArgument { field, reason } => {
            MurkError::invalid(format!("sparse_{field}"), reason)
        }
        other => other,
    })?;
    let visible = sparse.downsampled(search.search_downsample).len();
    if visible < MIN_SPARSE_POINTS {
        return Err(MurkError::invalid(
            "sparse_points",
            format!(
                "{} of {} points project into the reference view ({visible} distinct pixels at \
                 the search resolution); at least {MIN_SPARSE_POINTS} are needed",
                sparse.len(),
                points.len()
            ),
        ));
    }
    let tracks = tracks_from_proto(req, points, sources.len())?;
    let (near, far) = if req.near == 0.0 {
        plane_range_from_sparse(&sparse).expect("checked non-empty above")
    } else {
        (req.near, req.far)
    };
    let num_planes =
        requested_planes.unwrap_or_else(|| auto_planes(&reference, &sources, near, far));
    let planes = PlaneSet::new(near, far, num_planes)?;
    if w * h * num_planes.max(search.search_planes) > MAX_VOXELS {
        return Err(MurkError::invalid(
            "num_planes",
            format!(
                "{w}x{h} pixels x {num_planes} planes exceeds the cost-volume limit of \
                 {MAX_VOXELS} voxels"
            ),
        ));
    }
    Ok(ParamsInput {
        reference,
        sources,
        sparse,
        tracks,
        airlight_source: source,
        airlight_given: req.airlight,
        search,
        planes,
        airlight: airlight.clone(),
    })
}

impl ParamsInput {
    /// Airlight estimate, search, final depth; the wire result.
    pub fn run(&self, monitor: &Monitor) -> Result<pb::ScatteringParamsResult> {
        let reference = self.reference.view();
        let sources: Vec<View<'_>> = self.sources.iter().map(MvsViewInput::view).collect();
        let t0 = Instant::now();
        let a0 = match self.airlight_source {
            pb::AirlightSource::Given => self.airlight_given,
            pb::AirlightSource::DarkChannel => {
                dark_channel_airlight(reference.image, &DarkChannelParams::default())?
            }
            _ => self.airlight.estimator.estimate(reference.image)?,
        };
        let airlight_seconds = t0.elapsed().as_secs_f64();
        let est = search_scattering(
            &reference,
            &sources,
            SfmEvidence {
                sparse: &self.sparse,
                tracks: self.tracks.as_ref(),
            },
            a0,
            &self.planes,
            &self.search,
            &monitor.sub(0.0, 0.75),
        )
        // The library names its settings `params.…`; on the wire they are top-level fields.
        .map_err(|e| match e {
            MurkError::InvalidArgument { field, reason } => MurkError::invalid(
                field.strip_prefix("params.").unwrap_or(&field).to_string(),
                reason,
            ),
            other => other,
        })?;
        let t1 = Instant::now();
        let kind = CostKind::DehazingWith(
            AtmosphereParams {
                airlight: est.airlight,
                beta: est.beta,
            },
            self.search.cost,
        );
        let depth = estimate_depth(
            &reference,
            &sources,
            &self.planes,
            kind,
            &self.search.depth,
            &monitor.sub(0.75, 1.0),
        )?;
        let depth_seconds = t1.elapsed().as_secs_f64();
        Ok(pb::ScatteringParamsResult {
            airlight: est.airlight,
            beta: est.beta,
            airlight_initial: a0,
            airlight_source: self.airlight_source as i32,
            beta_initial: est.beta_initial,
            residual: est.residual,
            grid: est
                .grid
                .iter()
                .map(|g| pb::ResidualSample {
                    stage: match g.stage {
                        SearchStage::Beta => pb::SearchStage::Beta,
                        SearchStage::Joint => pb::SearchStage::Joint,
                    } as i32,
                    airlight: g.airlight,
                    beta: g.beta,
                    residual: g.residual,
                })
                .collect(),
            num_sparse_points: u32::try_from(est.num_sparse_points).unwrap_or(u32::MAX),
            point_ratio: est.point_ratio.map(|f| pb::PointRatioFit {
                beta: f.beta,
                std_error: f.std_error,
                equations: u32::try_from(f.equations).unwrap_or(u32::MAX),
                rms_depth_difference: f.rms_depth_difference,
                used: f.is_reliable(),
                sources: u32::try_from(f.sources).unwrap_or(u32::MAX),
                source_consistency_chi2: f.source_consistency_chi2,
            }),
            depth: Some(pb::MvsDepthResult {
                z_depth: Some(image_to_proto(&depth.z_depth)),
                inverse_depth: Some(image_to_proto(&depth.inverse_depth)),
                confidence: Some(image_to_proto(&depth.confidence)),
                near: self.planes.near,
                far: self.planes.far,
                num_planes: u32::try_from(self.planes.num_planes).unwrap_or(u32::MAX),
                cost_volume: pb::CostVolumeKind::Dehazing as i32,
                compute_seconds: depth_seconds,
                source_gains: depth.source_gains.clone(),
                vignetting_falloff: depth.vignetting_falloff,
                warnings: depth.warnings.clone(),
                source_falloffs: depth.source_falloffs.clone(),
            }),
            airlight_seconds,
            search_seconds: est.seconds,
            depth_seconds,
            airlight_std_error: est.airlight_std_error,
            beta_std_error: est.beta_std_error,
            identifiable: est.identifiability == Identifiability::Identifiable,
            identifiability: identifiability_to_proto(est.identifiability) as i32,
            beta_source: match est.beta_source {
                BetaSource::JointFit => pb::BetaSource::JointFit,
                BetaSource::PointRatio => pb::BetaSource::PointRatio,
                BetaSource::Sweep => pb::BetaSource::Sweep,
            } as i32,
            beta_min: est.beta_range[0],
            beta_max: est.beta_range[1],
            beta_range_from_points: est.beta_range_from_points,
            beta_bound: match est.beta_bound {
                None => pb::BetaBound::Unspecified,
                Some(BetaBound::Min) => pb::BetaBound::Min,
                Some(BetaBound::Max) => pb::BetaBound::Max,
            } as i32,
            beta_unclamped: est.beta_unclamped,
            joint_fit: est.joint.as_ref().map(joint_fit_to_proto),
            airlight_conflict: est
                .airlight_conflict
                .as_ref()
                .map(|c| pb::AirlightConflict {
                    fitted_airlight: c.fitted_airlight,
                    fitted_airlight_std_error: c.fitted_airlight_std_error,
                    airlight_initial: c.airlight_initial,
                    airlight_initial_error: c.airlight_initial_error,
                    sigmas: c.sigmas,
                }),
            warnings: est.warnings(),
            pose_error: est.pose_error.as_ref().map(|p| pb::PoseError {
                airlight_std_error: p.airlight_std_error,
                beta_std_error: p.beta_std_error,
                observations: u32::try_from(p.observations).unwrap_or(u32::MAX),
                points: u32::try_from(p.points).unwrap_or(u32::MAX),
                reprojection_rms_px: p.reprojection_rms_px,
                max_rotation_std_deg: p.max_rotation_std_deg,
                max_baseline_direction_std_deg: p.max_baseline_direction_std_deg,
                undetermined: p.undetermined.clone().unwrap_or_default(),
            }),
            sampling: est.sampling.map(|s| pb::SamplingShare {
                base_blur_px: s.base_blur_px,
                wide_blur_px: s.wide_blur_px,
                refit_airlight: s.refit.map(|r| r[0]),
                refit_beta: s.refit.map(|r| r[1]),
                airlight_std_error: s.share.map(|r| r[0]),
                beta_std_error: s.share.map(|r| r[1]),
            }),
            relief: est.relief.map(|r| pb::PointRelief {
                points: u32::try_from(r.points).unwrap_or(u32::MAX),
                relief: r.relief,
                tilt_deg: r.tilt_deg,
                ambiguous: r.is_ambiguous(),
            }),
        })
    }
}

/// The request's points and `sparse_point_observations` as [`SfmTracks`], `None` without
/// observations. Errors name `sparse_point_observations` or its `[i].point`, `.view`, `.x`
/// and `.y`.
fn tracks_from_proto(
    req: &pb::ScatteringParamsRequest,
    points: Vec<[f64; 3]>,
    sources: usize,
) -> Result<Option<SfmTracks>> {
    let obs = &req.sparse_point_observations;
    if obs.is_empty() {
        return Ok(None);
    }
    let most = MAX_OBSERVATIONS_PER_POINT * points.len();
    if obs.len() > most {
        return Err(MurkError::invalid(
            "sparse_point_observations",
            format!(
                "at most {MAX_OBSERVATIONS_PER_POINT} per sparse point ({most}), got {}",
                obs.len()
            ),
        ));
    }
    let field = |i: usize, name: &str| format!("sparse_point_observations[{i}].{name}");
    let mut observations = Vec::with_capacity(obs.len());
    for (i, o) in obs.iter().enumerate() {
        if o.point as usize >= points.len() {
            return Err(MurkError::invalid(
                field(i, "point"),
                format!("{} but there are {} sparse points", o.point, points.len()),
            ));
        }
        if o.view as usize > sources {
            return Err(MurkError::invalid(
                field(i, "view"),
                format!(
                    "{} but there are {sources} sources (0 = the reference, 1 + i = sources[i])",
                    o.view
                ),
            ));
        }
        for (name, v) in [("x", o.x), ("y", o.y)] {
            if !v.is_finite() {
                return Err(MurkError::invalid(
                    field(i, name),
                    format!("must be finite, got {v}"),
                ));
            }
        }
        observations.push(Observation {
            point: o.point,
            view: o.view,
            pixel: [o.x, o.y],
        });
    }
    Ok(Some(SfmTracks {
        points,
        seen_by: req.sparse_point_sources.clone(),
        observations,
    }))
}

fn joint_fit_to_proto(j: &JointFit) -> pb::JointFit {
    pb::JointFit {
        airlight: j.airlight,
        airlight_std_error: j.airlight_std_error,
        beta: j.beta,
        beta_std_error: j.beta_std_error,
        source_gains: j.source_gains.clone(),
        vignetting_falloff: j.vignetting_falloff,
        source_falloffs: j.source_falloffs.clone(),
        equations: u32::try_from(j.equations).unwrap_or(u32::MAX),
        points: u32::try_from(j.points).unwrap_or(u32::MAX),
        rms_depth_difference: j.rms_depth_difference,
        residual_scale: j.residual_scale,
        identifiability: identifiability_to_proto(j.identifiability) as i32,
    }
}

fn identifiability_to_proto(i: Identifiability) -> pb::Identifiability {
    match i {
        Identifiability::Identifiable => pb::Identifiability::Identifiable,
        Identifiability::NoDepthDifference => pb::Identifiability::NoDepthDifference,
        Identifiability::TooFewPoints => pb::Identifiability::TooFewPoints,
        Identifiability::FlatResidual => pb::Identifiability::FlatResidual,
        Identifiability::AirlightConflict => pb::Identifiability::AirlightConflict,
        Identifiability::AirlightAtBound => pb::Identifiability::AirlightAtBound,
        Identifiability::WeakSfm => pb::Identifiability::WeakSfm,
    }
}

/// The `sparse_point_observations` of `tracks` (for clients: the CLI, tests).
pub fn observations_to_proto(tracks: &SfmTracks) -> Vec<pb::SparsePointObservation> {
    tracks
        .observations
        .iter()
        .map(|o| pb::SparsePointObservation {
            point: o.point,
            view: o.view,
            x: o.pixel[0],
            y: o.pixel[1],
        })
        .collect()
}

/// A request for clients (CLI, demo, tests): views as raw f32, SfM points, the airlight source
/// (`airlight` is used with GIVEN only), everything else at the server's defaults.
pub fn params_request_to_proto(
    reference: &View<'_>,
    sources: &[View<'_>],
    sparse_points: &[[f64; 3]],
    airlight_source: pb::AirlightSource,
    airlight: f32,
) -> pb::ScatteringParamsRequest {
    pb::ScatteringParamsRequest {
        reference: Some(view_to_proto(reference)),
        sources: sources.iter().map(view_to_proto).collect(),
        sparse_points: sparse_points
            .iter()
            .map(|p| pb::Vector3 {
                x: p[0],
                y: p[1],
                z: p[2],
            })
            .collect(),
        airlight_source: airlight_source as i32,
        airlight: if airlight_source == pb::AirlightSource::Given {
            airlight
        } else {
            0.0
        },
        ..Default::default()
    }
}
