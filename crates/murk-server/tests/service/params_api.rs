//! `ScatteringParams` (Algorithm 1) through the real server: unary and Jobs API agree, the
//! result is complete and consistent, and bad input gets INVALID_ARGUMENT naming the field.

use crate::common;

use common::*;
use murk::params::sparse::{selected_points, PointSelection};
use murk::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};
use murk::Monitor;
use murk_server::service::convert::{
    observations_to_proto, params_request_to_proto, MAX_SPARSE_POINTS,
};
use murk_server::service::proto::v1 as pb;

pub(crate) fn scene(w: usize, h: usize, seed: u64) -> MvsScene {
    let cfg = MvsSimConfig {
        seed,
        beta_range: Some([0.4, 0.8]),
        ..MvsSimConfig::with_size(w, h)
    };
    simulate_mvs(&cfg, &Monitor::noop()).expect("simulate")
}

pub(crate) fn request(
    scene: &MvsScene,
    source: pb::AirlightSource,
    airlight: f32,
) -> pb::ScatteringParamsRequest {
    let (reference, sources) = scene.reference_and_sources();
    let points = selected_points(
        &scene.sparse,
        &scene.views[scene.reference].name,
        PointSelection::ObservedInReference,
    )
    .unwrap();
    params_request_to_proto(&reference, &sources, &points, source, airlight)
}

/// A forward-moving room at 128×96 whose points determine A and β.
fn forward_scene() -> MvsScene {
    let cfg = MvsSimConfig {
        seed: 5,
        beta_range: Some([0.4, 0.8]),
        forward_motion: 0.5,
        ..MvsSimConfig::with_size(128, 96)
    };
    simulate_mvs(&cfg, &Monitor::noop()).expect("simulate")
}

fn observation(point: u32, view: u32) -> pb::SparsePointObservation {
    pb::SparsePointObservation {
        point,
        view,
        x: 10.0,
        y: 10.0,
    }
}

/// The request's `sparse_point_observations`: where the scene's model saw its points in the
/// reference (view 0) and the request's sources (view 1 + i), in murk's pixel convention.
fn with_observations(scene: &MvsScene, req: &mut pb::ScatteringParamsRequest) {
    let tracks = scene.sfm_tracks(req.sources.len()).unwrap();
    assert_eq!(tracks.points.len(), req.sparse_points.len());
    req.sparse_point_observations = observations_to_proto(&tracks);
}

fn job(req: pb::ScatteringParamsRequest) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        request: Some(pb::JobRequest {
            method: Some(pb::job_request::Method::ScatteringParams(req)),
        }),
        omit_result: false,
    }
}

#[tokio::test]
async fn unary_and_jobs_agree_and_the_result_is_complete() {
    let server = start(config(4)).await;
    let s = scene(96, 72, 3);
    let mut req = request(&s, pb::AirlightSource::DarkChannel, 0.0);
    // Small and quick: 3 + 2×2 evaluations.
    req.beta_steps = Some(3);
    req.grid_steps = Some(2);
    req.delta_airlight = Some(0.05);
    req.num_planes = 32;
    req.search_planes = 16;
    // The published plain argmin, so A*, β* must be the grid's minimum.
    req.min_improvement_t = Some(0.0);
    // The published sweep for β₀ over the reference's range (murk's default tries the points
    // first and takes the range from their depths).
    req.beta_from_points = Some(false);
    req.joint_fit = Some(false);
    req.beta_min = Some(0.4);
    req.beta_max = Some(0.8);
    req.delta_beta = Some(0.05);
    let unary = recon(&server)
        .scattering_params(req.clone())
        .await
        .expect("unary")
        .into_inner();
    assert_eq!(unary.grid.len(), 3 + 4);
    assert!(unary.point_ratio.is_none(), "the points were not asked for");
    assert_eq!(unary.beta_source, pb::BetaSource::Sweep as i32);
    assert!(!unary.identifiable && unary.beta_std_error.is_none());
    assert!(!unary.beta_range_from_points && (unary.beta_min, unary.beta_max) == (0.4, 0.8));
    assert!(
        unary.joint_fit.is_some(),
        "the joint fit runs for the verdict"
    );
    assert_eq!(
        unary.airlight_source,
        pb::AirlightSource::DarkChannel as i32
    );
    assert!((0.35..=0.85).contains(&unary.beta), "{}", unary.beta);
    let best = unary
        .grid
        .iter()
        .map(|g| g.residual)
        .fold(f64::INFINITY, f64::min);
    assert_eq!(
        unary.residual, best,
        "A*, beta* is the argmin of the evaluations"
    );
    assert!(unary
        .grid
        .iter()
        .any(|g| g.airlight == unary.airlight && g.beta == unary.beta));
    assert!((unary.airlight_initial - s.airlight).abs() < 0.1);
    let depth = unary.depth.as_ref().expect("depth");
    assert_eq!(depth.num_planes, 32);
    assert!(depth.near > 0.0 && depth.far > depth.near);
    let z = depth.z_depth.as_ref().unwrap();
    assert_eq!((z.width, z.height), (96, 72));

    // The same request through the Jobs API is the same job (content hash) and result.
    let mut client = jobs(&server);
    let submitted = client.submit_job(job(req)).await.unwrap().into_inner();
    assert!(
        submitted.cached,
        "resubmission hits the cache: {submitted:?}"
    );
    let last = client
        .get_job(pb::GetJobRequest {
            id: submitted.id.clone(),
            omit_result: false,
        })
        .await
        .unwrap()
        .into_inner();
    let Some(pb::job::Outcome::Result(r)) = &last.outcome else {
        panic!("no result: {last:?}")
    };
    let Some(pb::job_result::Method::ScatteringParams(p)) = &r.method else {
        panic!("other method")
    };
    assert_eq!(p.airlight, unary.airlight);
    assert_eq!(p.beta, unary.beta);
    assert_eq!(last.method, "scattering_params");
}

/// murk's default over the API: A and β from the joint fit to the points, with standard errors
/// and the identifiability verdict, a single depth evaluation in the search (walking trajectory
/// at 128×96; docs/accuracy.md); and the points' ratios when the joint fit is turned off.
#[tokio::test]
async fn default_request_fits_a_and_beta_to_the_points_and_reports_the_fit() {
    let server = start(config(4)).await;
    let s = forward_scene();
    // A₀ given 0.06 off: the joint fit moves A to the data.
    let mut req = request(&s, pb::AirlightSource::Given, s.airlight - 0.06);
    req.num_planes = 32;
    req.search_planes = 16;
    let out = recon(&server)
        .scattering_params(req.clone())
        .await
        .expect("unary")
        .into_inner();
    assert_eq!(out.beta_source, pb::BetaSource::JointFit as i32);
    assert!(out.identifiable);
    assert_eq!(
        out.identifiability,
        pb::Identifiability::Identifiable as i32
    );
    assert_eq!(out.grid.len(), 1);
    assert!((out.airlight - s.airlight).abs() < 0.03, "{out:?}");
    assert!((out.beta - s.beta).abs() < 0.05, "{out:?}");
    let (se_a, se_b) = (out.airlight_std_error.unwrap(), out.beta_std_error.unwrap());
    assert!(se_a > 0.0 && se_b > 0.0 && se_b < 0.15 * f64::from(out.beta));
    let joint = out.joint_fit.expect("joint fit reported");
    assert_eq!(joint.source_gains.len(), s.views.len() - 1);
    assert!(joint.points >= 60, "{joint:?}");
    assert!(out.beta_range_from_points && out.beta_bound == pb::BetaBound::Unspecified as i32);
    assert!(out.airlight_conflict.is_none() && out.warnings.is_empty());

    // A₀ given 0.2 off, far beyond its stated error (the prior's scale): the points still place
    // A, and the disagreement is reported, with a sentence for the user.
    let mut far = req.clone();
    far.airlight = s.airlight - 0.2;
    let off = recon(&server)
        .scattering_params(far)
        .await
        .expect("unary")
        .into_inner();
    let conflict = off.airlight_conflict.expect("conflict reported");
    assert_eq!(conflict.airlight_initial, f64::from(s.airlight - 0.2));
    // A given A₀'s typical error is the prior's scale the request states (here the default).
    assert_eq!(
        conflict.airlight_initial_error,
        f64::from(murk::params::search::AIRLIGHT_PRIOR_SIGMA)
    );
    assert!(conflict.sigmas > 3.0, "{conflict:?}");
    assert!((conflict.fitted_airlight - f64::from(s.airlight)).abs() < 0.05);
    assert!(!off.identifiable, "{off:?}");
    assert_eq!(off.warnings.len(), 1);
    assert!(off.warnings[0].contains("SfM model"), "{:?}", off.warnings);

    // The points' tracks: masks naming every source change nothing (the same job), and masks
    // saying no source saw any point leave the fit without equations.
    let every = (1u32 << req.sources.len()) - 1;
    let mut tracked = req.clone();
    tracked.sparse_point_sources = vec![every; req.sparse_points.len()];
    let same = recon(&server)
        .scattering_params(tracked.clone())
        .await
        .expect("unary")
        .into_inner();
    assert_eq!((same.airlight, same.beta), (out.airlight, out.beta));
    tracked.sparse_point_sources = vec![0; req.sparse_points.len()];
    let unseen = recon(&server)
        .scattering_params(tracked)
        .await
        .expect("unary")
        .into_inner();
    assert_eq!(
        unseen.identifiability,
        pb::Identifiability::TooFewPoints as i32,
        "{unseen:?}"
    );
    assert_eq!(unseen.joint_fit.as_ref().expect("reported").equations, 0);
    // The verdict comes with its numbers and what would help.
    assert!(
        unseen
            .warnings
            .iter()
            .any(|w| w.contains("0 usable equations from 0 points") && w.contains("SIFT")),
        "{:?}",
        unseen.warnings
    );

    // Without the joint fit: β₀ from the points' ratios at the given A₀ (here the true A).
    req.airlight = s.airlight;
    req.joint_fit = Some(false);
    let out = recon(&server)
        .scattering_params(req)
        .await
        .expect("unary")
        .into_inner();
    assert_eq!(out.beta_source, pb::BetaSource::PointRatio as i32);
    let fit = out.point_ratio.expect("the fit is reported");
    assert!(fit.used && fit.equations >= 300, "{fit:?}");
    assert_eq!(out.grid.len(), 1);
    assert_eq!(out.beta, out.beta_initial);
    assert!(
        (out.beta - s.beta).abs() < 0.05,
        "β {} vs true {}",
        out.beta,
        s.beta
    );
    server.stop().await.unwrap();
}

/// The model's observations add the poses' share to the standard errors and leave the
/// estimates as they were: on the simulator's model (sound poses) the share is small; the
/// same observations 12 px off make the poses uncertain enough that β is `weak_sfm`, with
/// a sentence that names the numbers and what would help.
#[tokio::test]
async fn observations_add_the_poses_share_to_the_errors() {
    let server = start(config(4)).await;
    let s = forward_scene();
    let mut req = request(&s, pb::AirlightSource::Given, s.airlight);
    req.num_planes = 32;
    req.search_planes = 16;
    let plain = recon(&server)
        .scattering_params(req.clone())
        .await
        .expect("unary")
        .into_inner();
    assert!(plain.pose_error.is_none());
    // The points' relief is reported with every estimate; the simulator's room is not flat.
    let relief = plain.relief.expect("the points' relief is reported");
    assert!(
        relief.points >= 10 && relief.relief > 0.04 && !relief.ambiguous,
        "{relief:?}"
    );
    with_observations(&s, &mut req);
    let posed = recon(&server)
        .scattering_params(req.clone())
        .await
        .expect("unary")
        .into_inner();
    assert_eq!((posed.airlight, posed.beta), (plain.airlight, plain.beta));
    let pe = posed
        .pose_error
        .clone()
        .expect("the poses' share is reported");
    assert!(pe.undetermined.is_empty(), "{pe:?}");
    assert!(pe.observations > 0 && pe.points > 60, "{pe:?}");
    let (a, b) = (pe.airlight_std_error.unwrap(), pe.beta_std_error.unwrap());
    let (joint, joint0) = (posed.joint_fit.clone().unwrap(), plain.joint_fit.unwrap());
    assert!((joint.beta_std_error - joint0.beta_std_error.hypot(b)).abs() < 1e-9);
    assert!((joint.airlight_std_error - joint0.airlight_std_error.hypot(a)).abs() < 1e-9);
    assert!(b > 0.0 && b < joint0.beta_std_error, "{pe:?} {joint0:?}");
    assert!(posed.identifiable, "{posed:?}");

    // Every observation 12 px off, alternately in x and y: the poses are uncertain by
    // degrees.
    for (i, o) in req.sparse_point_observations.iter_mut().enumerate() {
        if i % 2 == 0 {
            o.x += 12.0;
        } else {
            o.y -= 12.0;
        }
    }
    let weak = recon(&server)
        .scattering_params(req)
        .await
        .expect("unary")
        .into_inner();
    assert_eq!(
        weak.identifiability,
        pb::Identifiability::WeakSfm as i32,
        "{:?} {:?}",
        weak.pose_error,
        weak.joint_fit
    );
    assert!(!weak.identifiable);
    assert!(
        weak.warnings
            .iter()
            .any(|w| w.contains("poses are too uncertain") && w.contains("longer baseline")),
        "{:?}",
        weak.warnings
    );
    server.stop().await.unwrap();
}

#[tokio::test]
async fn bad_params_requests_name_the_field() {
    let server = start(config(4)).await;
    let s = scene(64, 48, 4);
    let good = request(&s, pb::AirlightSource::Given, 0.8);
    type Edit = Box<dyn Fn(&mut pb::ScatteringParamsRequest)>;
    let far_away = pb::Vector3 {
        x: 0.0,
        y: 0.0,
        z: -5.0,
    };
    let cases: Vec<(&str, Edit)> = vec![
        (
            "sparse_points",
            Box::new(move |r| r.sparse_points = vec![far_away; 50]),
        ),
        ("sparse_points", Box::new(|r| r.sparse_points.truncate(3))),
        ("sparse_points", Box::new(|r| r.sparse_points.clear())),
        (
            "sparse_points",
            Box::new(|r| r.sparse_points = vec![pb::Vector3::default(); MAX_SPARSE_POINTS + 1]),
        ),
        (
            "sparse_points[2]",
            Box::new(|r| r.sparse_points[2].y = f64::NAN),
        ),
        ("beta_max", Box::new(|r| r.beta_max = Some(0.0))),
        ("beta_max", Box::new(|r| r.beta_max = Some(f32::INFINITY))),
        (
            "airlight_prior_sigma",
            Box::new(|r| r.airlight_prior_sigma = Some(0.0)),
        ),
        (
            "beta_max",
            Box::new(|r| {
                r.beta_min = Some(0.5);
                r.beta_max = Some(0.5)
            }),
        ),
        ("beta_min", Box::new(|r| r.beta_min = Some(-0.1))),
        ("beta_min", Box::new(|r| r.beta_min = Some(f32::NAN))),
        ("beta_steps", Box::new(|r| r.beta_steps = Some(0))),
        ("grid_steps", Box::new(|r| r.grid_steps = Some(0))),
        ("grid_steps", Box::new(|r| r.grid_steps = Some(65))),
        ("beta_steps", Box::new(|r| r.beta_steps = Some(1000))),
        (
            "delta_airlight",
            Box::new(|r| r.delta_airlight = Some(-0.1)),
        ),
        ("delta_px", Box::new(|r| r.delta_px = Some(1000))),
        (
            "min_improvement_t",
            Box::new(|r| r.min_improvement_t = Some(-1.0)),
        ),
        ("search_downsample", Box::new(|r| r.search_downsample = 9)),
        ("search_planes", Box::new(|r| r.search_planes = 5000)),
        ("num_planes", Box::new(|r| r.num_planes = 5000)),
        ("near", Box::new(|r| r.far = 10.0)),
        (
            "far",
            Box::new(|r| {
                r.near = 2.0;
                r.far = 1.0
            }),
        ),
        ("airlight", Box::new(|r| r.airlight = 0.0)),
        ("airlight", Box::new(|r| r.airlight = 1.5)),
        (
            "airlight",
            Box::new(|r| r.airlight_source = pb::AirlightSource::DarkChannel as i32),
        ),
        ("airlight_source", Box::new(|r| r.airlight_source = 42)),
        (
            "sparse_point_sources",
            Box::new(|r| r.sparse_point_sources = vec![1; 3]),
        ),
        (
            "sparse_point_sources[1]",
            Box::new(|r| {
                let n = r.sparse_points.len();
                r.sparse_point_sources = vec![1; n];
                // A bit for a source that is not in the request.
                r.sparse_point_sources[1] = 1 << r.sources.len();
            }),
        ),
        (
            "sparse_point_observations[1].view",
            Box::new(|r| {
                r.sparse_point_observations = vec![observation(0, 0); 2];
                r.sparse_point_observations[1].view = 1 + r.sources.len() as u32;
            }),
        ),
        (
            "sparse_point_observations[0].point",
            Box::new(|r| {
                let n = r.sparse_points.len() as u32;
                r.sparse_point_observations = vec![observation(n, 0)];
            }),
        ),
        (
            "sparse_point_observations[0].y",
            Box::new(|r| {
                r.sparse_point_observations = vec![observation(0, 1)];
                r.sparse_point_observations[0].y = f64::INFINITY;
            }),
        ),
        (
            "sparse_point_observations",
            Box::new(|r| {
                let n = r.sparse_points.len();
                r.sparse_point_observations = vec![observation(0, 0); 64 * n + 1];
            }),
        ),
        ("sources", Box::new(|r| r.sources.clear())),
        ("reference", Box::new(|r| r.reference = None)),
        (
            "sources[0].intrinsics.fx",
            Box::new(|r| r.sources[0].intrinsics.as_mut().unwrap().fx = 0.0),
        ),
        (
            "sgm.p2",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    p1: Some(0.5),
                    p2: Some(0.1),
                    ..Default::default()
                })
            }),
        ),
    ];
    let mut client = recon(&server);
    for (field, edit) in cases {
        let mut req = good.clone();
        edit(&mut req);
        let status = client.scattering_params(req).await.unwrap_err();
        assert_eq!(
            status.code(),
            tonic::Code::InvalidArgument,
            "{field}: {status:?}"
        );
        assert_eq!(bad_field(&status), field, "{status:?}");
    }
    // Through SubmitJob the field carries the request's path.
    let mut req = good.clone();
    req.sparse_points.truncate(2);
    let status = jobs(&server).submit_job(job(req)).await.unwrap_err();
    assert_eq!(
        bad_field(&status),
        "request.scattering_params.sparse_points"
    );
    // Still serving.
    let mut ok = good.clone();
    ok.beta_steps = Some(1);
    ok.grid_steps = Some(1);
    ok.search_planes = 8;
    ok.num_planes = 8;
    client
        .scattering_params(ok)
        .await
        .expect("a good request after bad ones");
}
