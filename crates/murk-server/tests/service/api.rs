//! End-to-end tests of the gRPC API against a real in-process server on an ephemeral port.

use crate::common;

use std::time::{Duration, Instant};

use common::*;
use murk_server::service::proto::v1 as pb;
use tonic::Code;

#[tokio::test]
async fn health_is_serving_and_reflection_lists_services() {
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::{health_check_response::ServingStatus, HealthCheckRequest};
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;

    let server = start(config(4)).await;
    let mut health = HealthClient::new(channel(&server));
    for service in ["", "murk.v1.Jobs", "murk.v1.Reconstruction"] {
        let r = health
            .check(HealthCheckRequest {
                service: service.into(),
            })
            .await
            .expect("health check")
            .into_inner();
        assert_eq!(r.status(), ServingStatus::Serving, "service {service:?}");
    }

    let mut refl = ServerReflectionClient::new(channel(&server));
    let req = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut stream = refl
        .server_reflection_info(futures::stream::iter([req]))
        .await
        .expect("reflection")
        .into_inner();
    let resp = stream.message().await.unwrap().expect("one response");
    let Some(MessageResponse::ListServicesResponse(list)) = resp.message_response else {
        panic!("unexpected reflection response");
    };
    let names: Vec<_> = list.service.iter().map(|s| s.name.as_str()).collect();
    for want in [
        "murk.v1.Jobs",
        "murk.v1.Reconstruction",
        "grpc.health.v1.Health",
    ] {
        assert!(names.contains(&want), "{want} missing from {names:?}");
    }
    server.stop().await.unwrap();
}

#[tokio::test]
async fn submit_watch_result_then_identical_resubmit_is_a_cache_hit() {
    let server = start(config(4)).await;
    let mut c = jobs(&server);
    let req = job(tof_request(64, 53, 3));
    let first = c.submit_job(req.clone()).await.unwrap().into_inner();
    assert_eq!(first.id.len(), 64, "hex sha-256 id");
    assert_eq!(first.method, "tof_depth");
    assert!(!first.cached);

    let seen = watch_to_end(&mut c, &first.id).await;
    let last = seen.last().expect("at least one update");
    assert_eq!(state(last), pb::JobState::Succeeded, "{last:?}");
    assert!(
        seen.windows(2).all(|w| w[0].progress <= w[1].progress),
        "progress never goes back"
    );
    assert!(
        seen.iter().any(|j| j.stage.starts_with("tof.")),
        "watchers see algorithm stages: {:?}",
        seen.iter().map(|j| &j.stage).collect::<Vec<_>>()
    );

    let done = c
        .get_job(pb::GetJobRequest {
            id: first.id.clone(),
            omit_result: false,
        })
        .await
        .unwrap()
        .into_inner();
    let Some(pb::job::Outcome::Result(pb::JobResult {
        method: Some(pb::job_result::Method::TofDepth(r)),
    })) = done.outcome
    else {
        panic!("no result: {done:?}");
    };
    let range = r.range_m.expect("range");
    assert_eq!((range.width, range.height), (64, 53));
    assert!(r.z_depth_m.is_some(), "intrinsics given → z-depth");
    assert!(r.raw_z_depth_m.is_some(), "intrinsics given → raw z-depth");
    let std = r.range_std_m.as_ref().expect("range uncertainty");
    assert_eq!((std.width, std.height), (64, 53));
    assert!(r.warnings.is_empty(), "converged: {:?}", r.warnings);

    let executed = server.manager().executed();
    let again = c.submit_job(req).await.unwrap().into_inner();
    assert_eq!(again.id, first.id);
    assert!(
        again.cached,
        "identical resubmission is served from the cache"
    );
    assert_eq!(state(&again), pb::JobState::Succeeded);
    assert!(matches!(again.outcome, Some(pb::job::Outcome::Result(_))));
    assert_eq!(server.manager().executed(), executed, "no recomputation");

    // The unary RPC shares ids and cache with the job API.
    let unary = recon(&server)
        .tof_depth(tof_request(64, 53, 3))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(unary.range_m.unwrap().width, 64);
    assert_eq!(server.manager().executed(), executed);

    // A fine level cut off by its cap reaches the client as a warning.
    let mut capped = tof_request(64, 53, 3);
    capped.options = Some(pb::TofOptions {
        fine_iterations: Some(2),
        ..Default::default()
    });
    let r = recon(&server).tof_depth(capped).await.unwrap().into_inner();
    assert!(
        r.warnings
            .iter()
            .any(|w| w.contains("fine level stopped at its cap of 2")),
        "{:?}",
        r.warnings
    );

    let list = c
        .list_jobs(pb::ListJobsRequest {
            page_size: 10,
            page_token: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(list.jobs.iter().any(|j| j.id == first.id));
    assert!(list
        .jobs
        .iter()
        .all(|j| j.outcome.is_none() || matches!(j.outcome, Some(pb::job::Outcome::Error(_)))));
    server.stop().await.unwrap();
}

#[tokio::test]
async fn tof_points_are_the_measured_pixels_and_need_intrinsics() {
    let server = start(config(4)).await;
    let mut req = tof_request(64, 53, 3);
    req.return_points = true;
    let r = recon(&server)
        .tof_depth(req.clone())
        .await
        .unwrap()
        .into_inner();
    let cloud = r.points.expect("points were asked for");
    let Some(pb::image::Data::RawF32Le(bytes)) = &r.range_std_m.as_ref().unwrap().data else {
        panic!("a one-shot result is raw f32");
    };
    let std: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let measured = std.iter().filter(|s| **s < 0.1).count();
    assert_eq!(cloud.count as usize, measured);
    assert!(measured > 0 && measured < std.len());
    assert_eq!(cloud.xyz_f32_le.len(), measured * 12);
    // A tighter limit keeps fewer; without intrinsics there is no ray to put a point on.
    req.max_point_range_std_m = 0.01;
    let tight = recon(&server)
        .tof_depth(req.clone())
        .await
        .unwrap()
        .into_inner();
    assert!(tight.points.unwrap().count < cloud.count);
    req.intrinsics = None;
    req.light_position_m = None;
    let e = recon(&server).tof_depth(req.clone()).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("return_points"), "{}", e.message());
    req.max_point_range_std_m = f32::NAN;
    let e = recon(&server).tof_depth(req).await.unwrap_err();
    assert!(
        e.message().contains("max_point_range_std_m"),
        "{}",
        e.message()
    );
    server.stop().await.unwrap();
}

#[tokio::test]
async fn cancelling_a_long_job_ends_it_within_one_second() {
    let server = start(config(4)).await;
    let mut c = jobs(&server);
    let id = submit_running_long_job(&mut c).await;
    let t0 = Instant::now();
    c.cancel_job(pb::CancelJobRequest { id: id.clone() })
        .await
        .unwrap();
    let seen = watch_to_end(&mut c, &id).await;
    let elapsed = t0.elapsed();
    assert_eq!(state(seen.last().unwrap()), pb::JobState::Cancelled);
    assert!(elapsed < Duration::from_secs(1), "took {elapsed:?}");

    // A cancelled job runs again when resubmitted (it is not a cached failure).
    let again = c
        .submit_job(job(long_tof_request(10_000)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(again.id, id);
    assert!(matches!(
        state(&again),
        pb::JobState::Queued | pb::JobState::Running
    ));
    c.cancel_job(pb::CancelJobRequest { id: id.clone() })
        .await
        .unwrap();
    server.stop().await.unwrap();
}

#[tokio::test]
async fn full_queue_gives_resource_exhausted_with_retry_info() {
    use tonic_types::StatusExt;
    let server = start(config(1)).await;
    let mut c = jobs(&server);
    let mut ids = Vec::new();
    let mut refused = None;
    // One running + one queued fill a queue of capacity 1; the third cannot fit.
    for iters in [10_000, 9_999, 9_998] {
        match c.submit_job(job(long_tof_request(iters))).await {
            Ok(j) => ids.push(j.into_inner().id),
            Err(s) => {
                refused = Some(s);
                break;
            }
        }
    }
    let s = refused.expect("a submission must be refused");
    assert_eq!(s.code(), Code::ResourceExhausted, "{s:?}");
    let retry = s
        .get_error_details()
        .retry_info()
        .cloned()
        .expect("RetryInfo");
    // No job has finished yet, so the hint is the configured minimum plus 0-50 % jitter.
    let delay = retry.retry_delay.expect("retry delay");
    assert!(
        delay >= Duration::from_millis(1500) && delay <= Duration::from_millis(2250),
        "{delay:?}"
    );
    for id in ids {
        c.cancel_job(pb::CancelJobRequest { id }).await.unwrap();
    }
    server.stop().await.unwrap();
}

#[tokio::test]
async fn unary_call_honours_deadline_and_cancels_the_abandoned_job() {
    let server = start(config(4)).await;
    let mut r = recon(&server);
    let mut req = tonic::Request::new(long_tof_request(9_000));
    req.set_timeout(Duration::from_millis(300));
    let err = r.tof_depth(req).await.unwrap_err();
    assert!(
        matches!(err.code(), Code::DeadlineExceeded | Code::Cancelled),
        "{err:?}"
    );
    // The job's only caller left: it must end CANCELLED, not run on.
    let mut c = jobs(&server);
    let list = c
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .unwrap()
        .into_inner();
    let id = list.jobs.first().expect("job recorded").id.clone();
    let seen = watch_to_end(&mut c, &id).await;
    assert_eq!(state(seen.last().unwrap()), pb::JobState::Cancelled);
    server.stop().await.unwrap();
}

#[tokio::test]
async fn results_survive_a_restart_through_the_cache_directory() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(4);
    cfg.jobs.cache_dir = Some(dir.path().to_path_buf());
    let req = job(tof_request(48, 40, 5));

    let a = start(cfg.clone()).await;
    let mut c = jobs(&a);
    let j = c.submit_job(req.clone()).await.unwrap().into_inner();
    let seen = watch_to_end(&mut c, &j.id).await;
    assert_eq!(state(seen.last().unwrap()), pb::JobState::Succeeded);
    a.stop().await.unwrap();

    let b = start(cfg).await;
    let mut c = jobs(&b);
    let got = c
        .get_job(pb::GetJobRequest {
            id: j.id.clone(),
            omit_result: false,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(state(&got), pb::JobState::Succeeded);
    // The record as it was (computed, not a cache hit), from the record log, with its result
    // from the cache directory.
    assert!(!got.cached);
    assert!(matches!(got.outcome, Some(pb::job::Outcome::Result(_))));
    let again = c.submit_job(req).await.unwrap().into_inner();
    assert!(again.cached);
    assert_eq!(
        b.manager().executed(),
        0,
        "nothing recomputed after restart"
    );
    b.stop().await.unwrap();
}

#[tokio::test]
async fn an_accepted_job_whose_journal_entry_is_corrupted_fails_with_data_loss_not_not_found() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(4);
    cfg.jobs.cache_dir = Some(dir.path().to_path_buf());
    cfg.shutdown_grace = Duration::ZERO;

    // Accepted and interrupted: its journal entry stays for the restart.
    let a = start(cfg.clone()).await;
    let mut c = jobs(&a);
    let id = c
        .submit_job(job(long_tof_request(10_000)))
        .await
        .unwrap()
        .into_inner()
        .id;
    wait_running(&mut c, &id).await;
    a.stop().await.unwrap();
    let entries: Vec<_> = std::fs::read_dir(dir.path().join("journal"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(entries.len(), 1, "{entries:?}");
    let mut bytes = std::fs::read(&entries[0]).unwrap();
    let n = bytes.len();
    bytes[n / 2] ^= 0x10;
    std::fs::write(&entries[0], bytes).unwrap();

    // The job is reported lost, durably: across a second restart too.
    for round in 0..2 {
        let b = start(cfg.clone()).await;
        let mut c = jobs(&b);
        let got = c
            .get_job(pb::GetJobRequest {
                id: id.clone(),
                omit_result: true,
            })
            .await
            .unwrap_or_else(|e| panic!("round {round}: {e:?}"))
            .into_inner();
        assert_eq!(state(&got), pb::JobState::Failed, "round {round}");
        let Some(pb::job::Outcome::Error(e)) = &got.outcome else {
            panic!("round {round}: an error outcome, got {got:?}");
        };
        assert_eq!(e.code, Code::DataLoss as i32, "round {round}: {e:?}");
        assert!(e.message.contains("resubmit"), "{}", e.message);
        assert!(e.message.contains("journal entry"), "{}", e.message);
        assert_eq!(b.manager().executed(), 0);
        b.stop().await.unwrap();
    }
    assert_eq!(
        std::fs::read_dir(dir.path().join("journal"))
            .unwrap()
            .count(),
        0,
        "the damaged entry is removed once the loss is recorded"
    );
}

#[tokio::test]
async fn unknown_ids_are_not_found() {
    let server = start(config(4)).await;
    let mut c = jobs(&server);
    let e = c
        .get_job(pb::GetJobRequest {
            id: "00".repeat(32),
            omit_result: true,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    // An id that is not a SHA-256 in hex is the caller's error, named, and never echoed: a
    // 15,000-character id comes back as INVALID_ARGUMENT with a short message.
    for id in ["nope".to_string(), "x".repeat(15_000), "AB".repeat(32)] {
        let e = c
            .cancel_job(pb::CancelJobRequest { id: id.clone() })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{}", id.len());
        assert_eq!(bad_field(&e), "id");
        assert!(e.message().len() < 200, "{}", e.message());
        let e = c
            .watch_job(pb::WatchJobRequest {
                id,
                omit_result: true,
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument);
    }
    let e = c
        .list_jobs(pb::ListJobsRequest {
            page_size: 1,
            page_token: "garbage".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(bad_field(&e), "page_token");
    server.stop().await.unwrap();
}
