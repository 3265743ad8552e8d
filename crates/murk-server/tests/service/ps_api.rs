//! Photometric stereo through the API: the unary RPC and the Jobs API agree, results are cached,
//! progress reaches the stream, and bad input gets INVALID_ARGUMENT naming the field without
//! anything being queued.

use crate::common;

use common::*;
use murk::image::ImageF32;
use murk::metrics::mean_angular_error_deg;
use murk::ps::{PsMode, PsParams};
use murk::simulate::ps::{simulate_ps, PsSimCapture, PsSimConfig};
use murk::Monitor;
use murk_server::service::convert::{image_to_proto, ps_from_result, ps_request_to_proto};
use murk_server::service::proto::v1 as pb;

const SIDE: usize = 48;

fn capture() -> PsSimCapture {
    simulate_ps(&PsSimConfig::with_size(SIDE, SIDE), &Monitor::noop()).expect("simulate")
}

fn request(sim: &PsSimCapture) -> pb::PhotometricStereoRequest {
    ps_request_to_proto(
        &sim.capture,
        &PsParams {
            initial_distance_mm: sim.initial_distance_mm,
            support_r: 13,
            max_iterations: 3,
            ..PsParams::default()
        },
    )
}

fn job(req: pb::PhotometricStereoRequest) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        request: Some(pb::JobRequest {
            method: Some(pb::job_request::Method::PhotometricStereo(req)),
        }),
        omit_result: false,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unary_and_jobs_agree_and_the_result_is_cached() {
    let sim = capture();
    let server = start(config(4)).await;
    let mut req = request(&sim);
    req.return_iteration_normals = true;
    let unary = recon(&server)
        .photometric_stereo(req.clone())
        .await
        .expect("unary call")
        .into_inner();
    let out = ps_from_result(&unary, &sim.capture.mask).unwrap();
    assert_eq!(out.normals_history.len(), out.iterations.len());
    let err = mean_angular_error_deg(&out.normals, &sim.gt_normals, &sim.capture.mask).unwrap();
    // 48×48 is far below the method's working size; this checks plumbing, not accuracy (the
    // accuracy tests run in the library at 96×96 and the table in docs/accuracy.md at 300×300).
    assert!(err < 15.0, "mean angular error {err}°");
    let depth_ok = out
        .depth_mm
        .iter()
        .zip(&sim.capture.mask)
        .all(|(z, &m)| !m || (z.is_finite() && *z > 0.0));
    assert!(depth_ok, "depth must be finite and positive on the object");

    let submitted = jobs(&server)
        .submit_job(job(req))
        .await
        .unwrap()
        .into_inner();
    assert!(
        submitted.cached,
        "same request, same id: served from the cache"
    );
    let Some(pb::job::Outcome::Result(r)) = submitted.outcome else {
        panic!("cached job carries its result");
    };
    let Some(pb::job_result::Method::PhotometricStereo(again)) = r.method else {
        panic!("result of another method");
    };
    assert_eq!(again, unary);
    assert_eq!(server.manager().executed(), 1);
    server.stop().await.unwrap();
}

type Edit = Box<dyn Fn(&mut pb::PhotometricStereoRequest)>;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_name_the_field_and_nothing_is_queued() {
    let sim = capture();
    let good = request(&sim);
    let server = start(config(4)).await;
    let cases: Vec<(&str, Edit)> = vec![
        ("lights", Box::new(|r| r.lights.truncate(2))),
        (
            "lights",
            // Every light at the same place: directions are coplanar (degenerate).
            Box::new(|r| {
                let p = r.lights[0].position_mm;
                for l in &mut r.lights {
                    l.position_mm = p;
                }
            }),
        ),
        (
            "lights",
            // Lights on a line through the object: rank 1.
            Box::new(|r| {
                for (k, l) in r.lights.iter_mut().enumerate() {
                    l.position_mm = Some(pb::Vector3 {
                        x: 0.0,
                        y: 0.0,
                        z: -10.0 * k as f64 - 10.0,
                    });
                }
            }),
        ),
        (
            "lights[1].image",
            Box::new(|r| {
                r.lights[1].image = Some(image_to_proto(&ImageF32::filled(SIDE - 1, SIDE, 1, 0.1)))
            }),
        ),
        (
            "lights[2].background",
            Box::new(|r| r.lights[2].background = None),
        ),
        (
            "lights[0].image",
            Box::new(|r| {
                let mut img = ImageF32::filled(SIDE, SIDE, 1, 0.1);
                img.set(3, 4, 0, f32::NAN);
                r.lights[0].image = Some(image_to_proto(&img));
            }),
        ),
        (
            "lights[3].intensity",
            Box::new(|r| r.lights[3].intensity = f64::NAN),
        ),
        (
            "lights[3].intensity",
            Box::new(|r| r.lights[3].intensity = 0.0),
        ),
        (
            "lights[4].position_mm",
            Box::new(|r| r.lights[4].position_mm = None),
        ),
        (
            "mask",
            Box::new(|r| r.mask = Some(image_to_proto(&ImageF32::filled(SIDE, SIDE + 1, 1, 1.0)))),
        ),
        (
            "mask",
            Box::new(|r| r.mask = Some(image_to_proto(&ImageF32::filled(SIDE, SIDE, 1, 0.0)))),
        ),
        ("mask", Box::new(|r| r.mask = None)),
        ("support_r", Box::new(|r| r.support_r = 12)),
        ("support_r", Box::new(|r| r.support_r = SIDE as u32 + 1)),
        ("support_r", Box::new(|r| r.support_r = 1)),
        // auto_support with an explicit support as well.
        ("support_r", Box::new(|r| r.auto_support = true)),
        (
            "sigma_per_mm",
            Box::new(|r| r.sigma_per_mm = r.beta_per_mm * 0.5),
        ),
        ("beta_per_mm", Box::new(|r| r.beta_per_mm = -1e-3)),
        ("beta_per_mm", Box::new(|r| r.beta_per_mm = f64::NAN)),
        // 0 means "unknown, estimate it", which a fixed distance cannot use.
        (
            "initial_distance_mm",
            Box::new(|r| {
                r.initial_distance_mm = 0.0;
                r.fix_distance = true;
            }),
        ),
        (
            "initial_distance_mm",
            Box::new(|r| r.initial_distance_mm = -5.0),
        ),
        (
            "initial_distance_mm",
            Box::new(|r| r.initial_distance_mm = f64::INFINITY),
        ),
        ("max_iterations", Box::new(|r| r.max_iterations = 1000)),
        (
            "intrinsics.fx",
            Box::new(|r| r.intrinsics.as_mut().unwrap().fx = 0.0),
        ),
        ("intrinsics", Box::new(|r| r.intrinsics = None)),
        ("mode", Box::new(|r| r.mode = 42)),
        ("far_field", Box::new(|r| r.far_field = 42)),
        ("facet_emission", Box::new(|r| r.facet_emission = 42)),
        ("smoothness_s", Box::new(|r| r.smoothness_s = Some(-1.0))),
        ("shadow_ratio", Box::new(|r| r.shadow_ratio = Some(1.5))),
        (
            "kernel_rebuild_tolerance",
            Box::new(|r| r.kernel_rebuild_tolerance = Some(-0.1)),
        ),
        (
            "kernel_rebuild_tolerance",
            Box::new(|r| r.kernel_rebuild_tolerance = Some(f64::NAN)),
        ),
        (
            "solver_tolerance",
            Box::new(|r| r.solver_tolerance = Some(0.0)),
        ),
        ("tolerance", Box::new(|r| r.tolerance = Some(f64::NAN))),
    ];
    for (field, edit) in &cases {
        let mut r = good.clone();
        edit(&mut r);
        let s = jobs(&server).submit_job(job(r)).await.unwrap_err();
        assert_eq!(
            bad_field(&s),
            format!("request.photometric_stereo.{field}"),
            "case {field}"
        );
    }
    assert_eq!(server.manager().executed(), 0, "nothing bad was queued");
    let mut r = good.clone();
    r.support_r = 14;
    let e = recon(&server).photometric_stereo(r).await.unwrap_err();
    assert_eq!(bad_field(&e), "support_r");
    server.stop().await.unwrap();
}

/// The kernel bound is the server's memory, not a property of the request: a kernel over it is
/// RESOURCE_EXHAUSTED naming the field that sizes it, without RetryInfo (the same request will
/// not fit later), and refused before a job exists.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_kernel_over_the_memory_limit_is_refused_before_any_work_naming_the_support() {
    use tonic_types::StatusExt;
    let sim = capture();
    let mut cfg = config(4);
    cfg.max_ps_kernel_bytes = 64 << 10;
    let server = start(cfg).await;
    let mut r = request(&sim);
    r.support_r = 41;
    let refused = |e: &tonic::Status, field: &str| {
        assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e:?}");
        assert!(e.message().contains("bytes"), "{}", e.message());
        let details = e.get_error_details();
        let violation = details
            .bad_request()
            .and_then(|b| b.field_violations.first());
        assert_eq!(violation.map(|v| v.field.as_str()), Some(field));
        assert!(details.retry_info().is_none(), "not retryable: {e:?}");
    };
    let e = recon(&server)
        .photometric_stereo(r.clone())
        .await
        .unwrap_err();
    refused(&e, "support_r");
    let e = jobs(&server)
        .submit_job(pb::SubmitJobRequest {
            request: Some(pb::JobRequest {
                method: Some(pb::job_request::Method::PhotometricStereo(r.clone())),
            }),
            omit_result: true,
        })
        .await
        .unwrap_err();
    refused(&e, "request.photometric_stereo.support_r");
    // The automatic support cannot fit either.
    let mut auto = r.clone();
    (auto.support_r, auto.auto_support) = (0, true);
    let e = recon(&server).photometric_stereo(auto).await.unwrap_err();
    refused(&e, "support_r");
    assert_eq!(server.manager().executed(), 0, "no work started");
    let listed = jobs(&server)
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert!(listed.jobs.is_empty(), "no job was accepted: {listed:?}");
    // The baseline stores no kernel, so the same request in that mode is fine.
    r.mode = pb::PsMode::BackscatterOnly as i32;
    let ok = recon(&server)
        .photometric_stereo(r)
        .await
        .unwrap()
        .into_inner();
    assert!(ok.normals.is_some());
    server.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_support_follows_the_object_and_is_reported() {
    let sim = capture();
    let server = start(config(4)).await;
    let mut r = request(&sim);
    r.auto_support = true;
    r.support_r = 0;
    r.far_cell = 0;
    r.max_iterations = 1;
    let out = recon(&server)
        .photometric_stereo(r)
        .await
        .expect("auto support")
        .into_inner();
    let expected = murk::ps::choose_support(
        &sim.capture.mask,
        SIDE,
        SIDE,
        murk::ps::pipeline::DEFAULT_NEAR_RADIUS_PX,
        murk::ps::pipeline::DEFAULT_MAX_KERNEL_BYTES,
    )
    .unwrap();
    assert_eq!(
        (out.support_r as usize, out.far_cell as usize),
        (expected.support_r, expected.far_cell)
    );
    assert!(
        expected.support_r > 13 && expected.support_r < SIDE,
        "{expected:?}"
    );
    // An explicit request reports the support it was given; r = 13 lies within the near
    // radius, so the layout is the exact window (cell 1) whatever far_cell says.
    let mut r = request(&sim);
    r.max_iterations = 1;
    let out = recon(&server)
        .photometric_stereo(r)
        .await
        .unwrap()
        .into_inner();
    assert_eq!((out.support_r, out.far_cell), (13, 1));
    server.stop().await.unwrap();
}

#[test]
fn request_round_trip_keeps_the_mode_and_far_field() {
    let sim = capture();
    let p = PsParams {
        initial_distance_mm: 200.0,
        mode: PsMode::BackscatterOnly,
        far_field: murk::ps::physics::FarField::ConstantEpsilon,
        ..PsParams::default()
    };
    let r = ps_request_to_proto(&sim.capture, &p);
    assert_eq!(r.mode, pb::PsMode::BackscatterOnly as i32);
    assert_eq!(r.far_field, pb::PsFarField::ConstantEpsilon as i32);
    let d = ps_request_to_proto(&sim.capture, &PsParams::default());
    assert_eq!(d.far_field, pb::PsFarField::Blocks as i32);
    assert_eq!(r.lights.len(), sim.capture.lights.len());
}

/// `sim` with every pixel repeated `k`×`k` times (same scene seen by a camera with `k`× the
/// focal length): a large object for a cheap simulation.
fn upscaled(sim: &PsSimCapture, k: usize) -> murk::ps::PsCapture {
    let mut cap = sim.capture.clone();
    let (w, h) = cap.dims();
    let up = |img: &ImageF32| ImageF32::from_fn(w * k, h * k, |x, y| img.get(x / k, y / k, 0));
    cap.images = cap.images.iter().map(up).collect();
    cap.backgrounds = cap.backgrounds.iter().map(up).collect();
    cap.mask = (0..w * k * h * k)
        .map(|i| sim.capture.mask[(i / (w * k) / k) * w + (i % (w * k)) / k])
        .collect();
    let i = &mut cap.intrinsics;
    i.fx *= k as f64;
    i.fy *= k as f64;
    i.cx = (i.cx + 0.5) * k as f64 - 0.5;
    i.cy = (i.cy + 0.5) * k as f64 - 0.5;
    cap
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_during_the_kernel_build_stops_within_250_ms() {
    let sim = capture();
    let cap = upscaled(&sim, 6);
    // r = 81 with the exact per-pixel window at 288×288: seconds of far-field and kernel build.
    // (At 192×192 without the in-loop checks a cancel took 393 ms; with them it stops at once.)
    let req = ps_request_to_proto(
        &cap,
        &PsParams {
            initial_distance_mm: sim.initial_distance_mm,
            support_r: 81,
            far_cell: 1,
            max_iterations: 2,
            ..PsParams::default()
        },
    );
    let server = start(config(4)).await;
    let mut c = jobs(&server);
    let id = c.submit_job(job(req)).await.unwrap().into_inner().id;
    let mut watch = c
        .watch_job(pb::WatchJobRequest {
            id: id.clone(),
            omit_result: true,
        })
        .await
        .unwrap()
        .into_inner();
    let mut in_kernel = false;
    while let Some(j) = watch.message().await.unwrap() {
        if j.stage.contains("forward-scatter kernel") {
            in_kernel = true;
            break;
        }
        assert_ne!(j.state, pb::JobState::Succeeded as i32, "finished early");
    }
    assert!(in_kernel, "the job reached the kernel build");
    let asked = std::time::Instant::now();
    c.cancel_job(pb::CancelJobRequest { id: id.clone() })
        .await
        .unwrap();
    let mut last = None;
    while let Some(j) = watch.message().await.unwrap() {
        last = Some(j);
    }
    let took = asked.elapsed();
    let last = last.expect("terminal update");
    assert_eq!(last.state, pb::JobState::Cancelled as i32, "{last:?}");
    assert!(
        took < std::time::Duration::from_millis(250),
        "cancel took {took:?} (stage {})",
        last.stage
    );
    server.stop().await.unwrap();
}
