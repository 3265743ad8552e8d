//! The `murk` binary end to end: simulate a frame to disk, then run the ToF client against a real
//! server and check the files it writes.

use crate::common;

use std::process::{Command, Output};

use common::*;
use murk_server::service::proto::v1 as pb;

fn murk() -> Command {
    Command::new(env!("CARGO_BIN_EXE_murk"))
}

/// The run's stdout; fails the test with both streams when the run failed.
fn succeeded(out: &Output) -> String {
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{:?}\nstdout: {stdout}\nstderr: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[tokio::test]
async fn simulate_then_tof_client_writes_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let frame = dir.path().join("frame");
    let out = dir.path().join("out");
    let st = murk()
        .args(["simulate", "tof", "--preset", "thick", "--seed", "4"])
        .args(["--width", "64", "--height", "53", "--out"])
        .arg(&frame)
        .status()
        .unwrap();
    assert!(st.success());
    for f in ["amplitude.exr", "phase.exr", "gt_range_m.exr", "meta.json"] {
        assert!(frame.join(f).exists(), "{f} missing");
    }

    let server = start(config(4)).await;
    let url = server.url();
    let (frame2, out2) = (frame.clone(), out.clone());
    let output = tokio::task::spawn_blocking(move || {
        murk()
            .args(["tof", "--server", &url, "--frame"])
            .arg(&frame2)
            .arg("--out")
            .arg(&out2)
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    succeeded(&output);
    for f in [
        "range_m.exr",
        "z_depth_m.exr",
        "mask.exr",
        "scatter_phase.exr",
        "range_m.png",
        "raw_range_m.png",
        "mask.png",
        "points.ply",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    assert_eq!(server.manager().executed(), 1);

    // Only the images asked for, compact on the wire: the same files, quantised.
    let (url, frame2) = (server.url(), frame.clone());
    let compact = dir.path().join("compact");
    let out3 = compact.clone();
    let output = tokio::task::spawn_blocking(move || {
        murk()
            .args(["tof", "--server", &url, "--frame"])
            .arg(&frame2)
            .args(["--outputs", "z_depth_m,mask", "--encoding", "png", "--out"])
            .arg(&out3)
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    succeeded(&output);
    let mut written: Vec<String> = std::fs::read_dir(&compact)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    written.sort();
    assert_eq!(
        written,
        ["mask.exr", "mask.png", "z_depth_m.exr", "z_depth_m.png"]
    );
    let read = |p: &std::path::Path| murk::io::read_image(p, &Default::default()).unwrap();
    assert_eq!(read(&compact.join("mask.exr")), read(&out.join("mask.exr")));
    let (url, frame2) = (server.url(), frame.clone());
    let bad_output = tokio::task::spawn_blocking(move || {
        murk()
            .args(["tof", "--server", &url, "--frame"])
            .arg(&frame2)
            .args(["--outputs", "depth", "--out"])
            .arg(&compact)
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(!bad_output.status.success());
    assert!(
        String::from_utf8_lossy(&bad_output.stderr).contains("outputs.fields[0]"),
        "{}",
        String::from_utf8_lossy(&bad_output.stderr)
    );

    // Bad flags fail with a message, not a panic.
    let bad = murk()
        .args(["tof", "--server", &server.url(), "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--frame"));
    server.stop().await.unwrap();
}

#[tokio::test]
async fn graceful_shutdown_aborts_running_jobs_retryably_after_the_grace_period() {
    let server = start(config(4)).await;
    let mut c = jobs(&server);
    let id = submit_running_long_job(&mut c).await;
    let manager = server.manager().clone();
    server.stop().await.unwrap();
    let snap = manager.get("", &id).unwrap().snapshot();
    // Stopped by the server, not cancelled by anyone: FAILED with a retryable error.
    assert_eq!(snap.state, murk_server::jobs::JobState::Failed);
    assert_eq!(snap.error, Some(murk::MurkError::ShuttingDown));
}

/// `murk serve` as a separate process on an ephemeral port: the bound address from its log.
fn spawn_server(extra: &[&str]) -> (std::process::Child, String) {
    let mut cmd = murk();
    cmd.args(["serve", "--addr", "127.0.0.1:0", "--workers", "2"])
        .args(extra);
    common::spawn_serve(cmd)
}

#[cfg(unix)]
#[tokio::test]
async fn sigterm_exits_within_the_grace_period_plus_one_second() {
    let (mut child, url) = spawn_server(&["--shutdown-grace-secs", "1"]);
    let mut c = pb::jobs_client::JobsClient::connect(url).await.unwrap();
    let id = submit_running_long_job(&mut c).await;
    assert_eq!(id.len(), 64);
    let sent = std::time::Instant::now();
    // SAFETY: kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    let status = tokio::task::spawn_blocking(move || child.wait())
        .await
        .unwrap()
        .unwrap();
    let took = sent.elapsed();
    assert!(status.success(), "{status:?}");
    assert!(
        took < std::time::Duration::from_secs(2),
        "exit took {took:?} with a 1 s grace period"
    );
}

#[test]
fn exposing_an_unauthenticated_server_needs_an_explicit_flag() {
    let out = murk()
        .args(["serve", "--addr", "0.0.0.0:0"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--allow-unauthenticated"), "{err}");
    // The environment form takes the usual spellings of true and false (containers set `1`).
    for off in ["0", "false", "no"] {
        let out = murk()
            .args(["serve", "--addr", "0.0.0.0:0"])
            .env("MURK_ALLOW_UNAUTHENTICATED", off)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{off}");
    }
    let mut cmd = murk();
    cmd.args(["serve", "--addr", "0.0.0.0:0"])
        .env("MURK_ALLOW_UNAUTHENTICATED", "1");
    let (mut child, _) = spawn_serve(cmd);
    child.kill().unwrap();
    child.wait().unwrap();
    let bad_log = murk()
        .args(["serve"])
        .env("MURK_LOG", "json")
        .output()
        .unwrap();
    assert!(!bad_log.status.success());
    assert!(
        String::from_utf8_lossy(&bad_log.stderr).contains("--log-format"),
        "{}",
        String::from_utf8_lossy(&bad_log.stderr)
    );
}

#[test]
fn simulate_mvs_then_mvs_client_writes_depth_and_point_cloud() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let out = dir.path().join("out");
    let sim = murk()
        .args([
            "simulate", "mvs", "--seed", "2", "--width", "64", "--height", "48",
        ])
        .arg("--out")
        .arg(&scene)
        .output()
        .unwrap();
    succeeded(&sim);
    let said = String::from_utf8_lossy(&sim.stdout);
    assert!(
        said.contains("airlight A =") && said.contains("median transmission"),
        "{said}"
    );
    for f in [
        "meta.json",
        "sparse/cameras.txt",
        "sparse/images.txt",
        "sparse/points3D.txt",
    ] {
        assert!(scene.join(f).exists(), "{f} missing");
    }
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scene.join("meta.json")).unwrap()).unwrap();
    let reference = meta["reference"].as_str().unwrap().to_string();
    assert!(scene.join("images").join(&reference).exists());
    assert!(scene.join("clear").join(&reference).exists());

    // No --server: the client starts one in-process. A and β come from meta.json.
    let run = murk()
        .env_remove("MURK_SERVER")
        .args(["mvs", "--reference", &reference, "--num-sources", "2"])
        .args(["--near", "1.5", "--far", "15", "--planes", "32"])
        .arg("--model")
        .arg(scene.join("sparse"))
        .arg("--images")
        .arg(scene.join("images"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = succeeded(&run);
    assert!(stdout.contains("ground-truth airlight"), "{stdout}");
    assert!(
        stdout.contains("C.P."),
        "GT depth is found and scored: {stdout}"
    );
    for f in [
        "depth.exr",
        "inverse_depth.exr",
        "confidence.exr",
        "depth.png",
        "points.ply",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // Depth options reach the server; an out-of-range one is refused with its field named.
    let bad = murk()
        .env_remove("MURK_SERVER")
        .args(["mvs", "--reference", &reference, "--num-sources", "2"])
        .args(["--planes", "32", "--presmooth-sigma", "9"])
        .arg("--model")
        .arg(scene.join("sparse"))
        .arg("--images")
        .arg(scene.join("images"))
        .arg("--out")
        .arg(dir.path().join("out-bad"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("sgm.presmooth_sigma_px"), "{err}");
    // A valid binary PLY: header, then exactly `vertex` records of 3 floats + 3 bytes. With the
    // default --min-confidence 0 every pixel is a point.
    let ply = std::fs::read(out.join("points.ply")).unwrap();
    let end = ply
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("end_header")
        + 11;
    let header = std::str::from_utf8(&ply[..end]).unwrap();
    assert!(
        header.starts_with("ply\nformat binary_little_endian 1.0\n"),
        "{header}"
    );
    for p in ["x", "y", "z"] {
        assert!(header.contains(&format!("property float {p}\n")));
    }
    for p in ["red", "green", "blue"] {
        assert!(header.contains(&format!("property uchar {p}\n")));
    }
    let count: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .expect("vertex element")
        .parse()
        .unwrap();
    assert_eq!(count, 64 * 48);
    assert_eq!(ply.len() - end, count * 15);

    // A model without scene metadata needs A and β for the dehazing volume: a clear error.
    let bare = dir.path().join("bare");
    std::fs::create_dir_all(&bare).unwrap();
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        std::fs::copy(scene.join("sparse").join(f), bare.join(f)).unwrap();
    }
    let bad = murk()
        .env_remove("MURK_SERVER")
        .args(["mvs", "--reference", &reference, "--model"])
        .arg(&bare)
        .arg("--images")
        .arg(scene.join("images"))
        .arg("--out")
        .arg(dir.path().join("out2"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("--airlight"), "{err}");
}

#[test]
fn simulate_mvs_then_params_estimates_and_writes_the_residual_grid() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let out = dir.path().join("out");
    let sim = murk()
        .args([
            "simulate", "mvs", "--seed", "3", "--width", "96", "--height", "72",
        ])
        .args(["--beta-range", "0.4,0.8"])
        .arg("--out")
        .arg(&scene)
        .output()
        .unwrap();
    succeeded(&sim);
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scene.join("meta.json")).unwrap()).unwrap();
    let reference = meta["reference"].as_str().unwrap().to_string();
    let beta = meta["beta"].as_f64().unwrap();
    assert!((0.4..=0.8).contains(&beta), "{meta}");
    let run = murk()
        .env_remove("MURK_SERVER")
        .args(["params", "--reference", &reference, "--num-sources", "2"])
        .args(["--beta-steps", "3", "--grid-steps", "2", "--planes", "32"])
        .args(["--airlight-source", "dark-channel", "--beta-sweep"])
        .args(["--beta-min", "0.4", "--beta-max", "0.8"])
        .arg("--model")
        .arg(scene.join("sparse"))
        .arg("--images")
        .arg(scene.join("images"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = succeeded(&run);
    assert!(
        stdout.contains("A* =") && stdout.contains("beta* ="),
        "{stdout}"
    );
    assert!(stdout.contains("ground truth"), "{stdout}");
    let csv = std::fs::read_to_string(out.join("residuals.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines[0], "stage,airlight,beta,residual");
    // 3 beta values, then 2 beta values at A0 (delta_airlight defaults to 0).
    assert_eq!(lines.len(), 1 + 3 + 2, "{csv}");
    assert!(lines[1].starts_with("beta,") && lines[4].starts_with("joint,"));
    for f in ["depth.exr", "confidence.exr", "depth.png", "points.ply"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // params.json: the estimates, what is known about them, the range, the searches, units.
    let params: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("params.json")).unwrap()).unwrap();
    assert_eq!(params["format"], "murk.scattering_params");
    assert!(params["airlight"].as_f64().unwrap() > 0.0 && params["beta"].as_f64().is_some());
    // The published sweep: β* is a guess, and said to be one.
    assert_eq!(params["identifiable"], false, "{params}");
    assert!(params["beta_std_error"].is_null());
    assert_eq!(params["beta_source"], "the sweep of Eq. 3.10");
    assert_eq!(params["beta_range"]["from_points"], false);
    assert_eq!(params["searches"].as_array().unwrap().len(), 3 + 2);
    assert!(params["units"]["beta"]
        .as_str()
        .unwrap()
        .contains("per model unit"));
    assert!(params["joint_fit"]["equations"].as_u64().unwrap() > 0);
    // No conflict between the points' A and A₀ is reported as such, not left out.
    assert!(params["airlight_conflict"].is_null(), "{params}");
    // The joint fit did not determine β either, and the warning says why, with its numbers.
    let warnings = params["warnings"].as_array().unwrap();
    assert_eq!(warnings.len(), 1, "{params}");
    let warning = warnings[0].as_str().unwrap();
    assert!(
        warning.contains("standard error of") && warning.contains("RMS depth difference"),
        "{warning}"
    );
    assert!(stdout.contains("NOT identifiable"), "{stdout}");
    // A given airlight without --airlight-source given is refused by the CLI.
    let bad = murk()
        .args(["params", "--reference", &reference, "--airlight", "0.9"])
        .arg("--model")
        .arg(scene.join("sparse"))
        .arg("--images")
        .arg(scene.join("images"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!bad.status.success());
}

#[test]
fn train_airlight_evaluate_scores_weights_and_names_a_bad_file() {
    let ok = murk()
        .args([
            "train",
            "airlight",
            "--evaluate",
            "embedded",
            "--eval-scenes",
            "2",
        ])
        .output()
        .unwrap();
    let stdout = succeeded(&ok);
    assert!(stdout.contains("A ~ U[0.4, 1], varied scenes"), "{stdout}");
    let all = stdout
        .lines()
        .find(|l| l.contains("      2 "))
        .unwrap_or_else(|| panic!("no row of both scenes in:\n{stdout}"));
    let mae: f64 = all.split_whitespace().nth(5).unwrap().parse().unwrap();
    assert!(mae.is_finite() && mae < 0.3, "{all}");

    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("junk.bpk");
    std::fs::write(&junk, b"not a burnpack").unwrap();
    for (file, says) in [
        (dir.path().join("missing.bpk"), "reading"),
        (junk, "airlight_weights"),
    ] {
        let bad = murk()
            .args(["train", "airlight", "--eval-scenes", "2", "--evaluate"])
            .arg(&file)
            .output()
            .unwrap();
        assert!(!bad.status.success());
        let err = String::from_utf8_lossy(&bad.stderr);
        assert!(err.contains(says), "{err}");
    }
}

#[test]
fn simulate_ps_textured_works_with_the_default_albedo_and_names_a_bad_one() {
    let dir = tempfile::tempdir().unwrap();
    let sim = |extra: &[&str]| {
        murk()
            .args(["simulate", "ps", "--textured", "--seed", "1"])
            .args(["--width", "32", "--height", "32", "--far-stride", "4"])
            .args(extra)
            .arg("--out")
            .arg(dir.path().join("capture"))
            .output()
            .unwrap()
    };
    let ok = sim(&[]);
    succeeded(&ok);
    let meta = std::fs::read_to_string(dir.path().join("capture/meta.json")).unwrap();
    assert!(meta.contains("\"textured\": true"), "{meta}");
    let bad = sim(&["--albedo", "0.9"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("albedo"));
}

#[test]
fn simulate_ps_then_ps_client_writes_normals_depth_and_mesh() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("capture");
    let out = dir.path().join("out");
    let st = murk()
        .args(["simulate", "ps", "--shape", "vase", "--seed", "2"])
        .args(["--width", "48", "--height", "48", "--out"])
        .arg(&capture)
        .status()
        .unwrap();
    assert!(st.success());
    for f in [
        "meta.json",
        "image_00.exr",
        "background_07.exr",
        "mask.png",
        "gt_normals.exr",
        "gt_depth_mm.exr",
        "gt_albedo.exr",
        "gt_reflected_03.exr",
    ] {
        assert!(capture.join(f).exists(), "{f} missing");
    }
    // No --server: the command starts its own server in-process.
    let output = murk()
        .args(["ps", "--support-r", "13", "--iterations", "2", "--capture"])
        .arg(&capture)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = succeeded(&output);
    for f in [
        "normals.exr",
        "normals.png",
        "albedo.exr",
        "depth_mm.exr",
        "depth.png",
        "mesh.ply",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // Ground truth is in the folder, so the per-iteration table has an error column filled in.
    let row = stdout
        .lines()
        .find(|l| l.trim_start().starts_with("1 "))
        .unwrap_or_else(|| panic!("no iteration row in:\n{stdout}"));
    let err: f64 = row.split_whitespace().nth(1).unwrap().parse().unwrap();
    assert!(err.is_finite() && err < 30.0, "{row}");
    let ply = std::fs::read(out.join("mesh.ply")).unwrap();
    let header = String::from_utf8_lossy(&ply[..ply.len().min(400)]);
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0"));
    assert!(header.contains("element face"));
}

#[tokio::test]
async fn kill_9_then_restart_requeues_accepted_jobs_from_the_journal() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().to_str().unwrap().to_string();
    let (mut child, url) = spawn_server(&["--cache-dir", &cache, "--concurrent-jobs", "1"]);
    let mut c = pb::jobs_client::JobsClient::connect(url).await.unwrap();
    // A long job runs; a small one waits behind it. Both were acknowledged.
    let long_id = submit_running_long_job(&mut c).await;
    let small = c
        .submit_job(job(tof_request(48, 36, 11)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(small.state, pb::JobState::Queued as i32);
    child.kill().unwrap(); // SIGKILL: no shutdown path runs
    child.wait().unwrap();

    let (mut child, url) = spawn_server(&["--cache-dir", &cache, "--concurrent-jobs", "1"]);
    let mut c = pb::jobs_client::JobsClient::connect(url).await.unwrap();
    let get = |id: &str| pb::GetJobRequest {
        id: id.to_string(),
        omit_result: true,
    };
    for id in [&long_id, &small.id] {
        let j = c
            .get_job(get(id))
            .await
            .expect("record re-queued")
            .into_inner();
        assert!(
            j.state == pb::JobState::Queued as i32 || j.state == pb::JobState::Running as i32,
            "{j:?}"
        );
    }
    // The long one would take a while: cancel it, and the small one runs to completion.
    c.cancel_job(pb::CancelJobRequest {
        id: long_id.clone(),
    })
    .await
    .unwrap();
    let seen = watch_to_end(&mut c, &small.id).await;
    assert_eq!(state(seen.last().unwrap()), pb::JobState::Succeeded);
    child.kill().unwrap();
    child.wait().unwrap();
    // Both ended: nothing is left to re-run.
    let left = std::fs::read_dir(dir.path().join("journal"))
        .unwrap()
        .count();
    assert_eq!(left, 0, "journal emptied as jobs ended");

    // Their records survive the next kill -9 too (the record log), with their outcomes.
    let (mut child, url) = spawn_server(&["--cache-dir", &cache, "--concurrent-jobs", "1"]);
    let mut c = pb::jobs_client::JobsClient::connect(url).await.unwrap();
    let long = c
        .get_job(get(&long_id))
        .await
        .expect("record back")
        .into_inner();
    assert_eq!(long.state, pb::JobState::Cancelled as i32, "{long:?}");
    let small = c
        .get_job(get(&small.id))
        .await
        .expect("record back")
        .into_inner();
    assert_eq!(small.state, pb::JobState::Succeeded as i32, "{small:?}");
    child.kill().unwrap();
    child.wait().unwrap();
}

/// `murk tof` follows its job across a server crash: the server is killed (-9) while the job
/// runs and restarted on the same port and cache directory, the journal re-queues the job under
/// the same id, and the client, attaching to the job again, writes its outputs.
#[tokio::test]
async fn the_tof_client_follows_its_job_across_a_server_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (frame, out) = (dir.path().join("frame"), dir.path().join("out"));
    // A full-size frame: about 2 s of compute, long enough to be caught running.
    let st = murk()
        .args(["simulate", "tof", "--seed", "6", "--out"])
        .arg(&frame)
        .status()
        .unwrap();
    assert!(st.success());
    let cache = dir.path().join("cache").to_str().unwrap().to_string();
    let addr = format!("127.0.0.1:{}", common::redis_server::free_port());
    let serve = || {
        let mut cmd = murk();
        cmd.args([
            "serve",
            "--addr",
            &addr,
            "--workers",
            "2",
            "--cache-dir",
            &cache,
        ]);
        common::spawn_serve(cmd)
    };
    let (mut a, url) = serve();
    let client = murk()
        .args(["tof", "--server", &url, "--frame"])
        .arg(&frame)
        .arg("--out")
        .arg(&out)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut c = pb::jobs_client::JobsClient::connect(url.clone())
        .await
        .unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        let jobs = c
            .list_jobs(pb::ListJobsRequest::default())
            .await
            .unwrap()
            .into_inner()
            .jobs;
        if jobs.iter().any(|j| j.state == pb::JobState::Running as i32) {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "the job never ran");
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    a.kill().unwrap(); // SIGKILL: the client's watch breaks mid-job
    a.wait().unwrap();
    drop(c);
    let (mut b, _) = serve();
    let output = tokio::time::timeout(
        std::time::Duration::from_secs(120),
        tokio::task::spawn_blocking(move || client.wait_with_output()),
    )
    .await
    .expect("the client finished")
    .unwrap()
    .unwrap();
    b.kill().unwrap();
    b.wait().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(out.join("range_m.exr").exists(), "{stderr}");
}

#[test]
fn simulate_a_rectified_pair_then_stereo_writes_depth_disparity_and_points() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("pair");
    let out = dir.path().join("out");
    succeeded(
        &murk()
            .args(["simulate", "mvs", "--rectified-pair", "--seed", "2"])
            .args(["--width", "96", "--height", "64", "--out"])
            .arg(&scene)
            .output()
            .unwrap(),
    );
    // The rig from the simulator's COLMAP model: PINHOLE fx fy cx cy (COLMAP's principal point
    // is 0.5 px from murk's pixel-centre convention), and the right camera's translation.
    let cameras = std::fs::read_to_string(scene.join("sparse/cameras.txt")).unwrap();
    let k: Vec<f64> = cameras
        .lines()
        .find(|l| l.contains("PINHOLE"))
        .unwrap()
        .split_whitespace()
        .skip(4)
        .map(|v| v.parse().unwrap())
        .collect();
    let intrinsics = format!("{},{},{},{}", k[0], k[1], k[2] - 0.5, k[3] - 0.5);
    let images = std::fs::read_to_string(scene.join("sparse/images.txt")).unwrap();
    let tx: f64 = images
        .lines()
        .find(|l| l.ends_with("view_01.png"))
        .unwrap()
        .split_whitespace()
        .nth(5)
        .unwrap()
        .parse()
        .unwrap();
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scene.join("meta.json")).unwrap()).unwrap();
    let stereo = |baseline: f64| {
        murk()
            .env_remove("MURK_SERVER")
            .arg("stereo")
            .arg("--left")
            .arg(scene.join("images/view_00.png"))
            .arg("--right")
            .arg(scene.join("images/view_01.png"))
            .args(["--intrinsics", &intrinsics])
            .args(["--baseline", &baseline.to_string()])
            .args(["--depth-range", "1.5,15"])
            .args(["--airlight", &meta["airlight"].to_string()])
            .args(["--beta", &meta["beta"].to_string()])
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap()
    };
    let said = succeeded(&stereo(-tx));
    assert!(said.contains("dehazing cost volume"), "{said}");
    for f in [
        "depth.exr",
        "disparity.exr",
        "confidence.exr",
        "points.ply",
        "depth.png",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let limits = murk::io::DecodeLimits::default();
    let z = murk::io::read_image(&out.join("depth.exr"), &limits).unwrap();
    assert_eq!(z.dims(), (96, 64));
    // The cloud's header counts the points the summary names.
    let ply = std::fs::read(out.join("points.ply")).unwrap();
    let header = String::from_utf8_lossy(&ply[..200.min(ply.len())]).into_owned();
    let count: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .unwrap()
        .parse()
        .unwrap();
    assert!(said.contains(&format!("; {count} points")), "{said}");
    assert!(count > 96 * 64 / 2, "{count} points");

    let bad = stereo(0.0);
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("baseline"), "{err}");
}

#[test]
fn a_simulated_tof_sequence_streams_through_a_session() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    let out = dir.path().join("out");
    let said = succeeded(
        &murk()
            .args(["simulate", "tof", "--frames", "3", "--cut-every", "2"])
            .args([
                "--fog-drift",
                "0.5",
                "--width",
                "64",
                "--height",
                "53",
                "--out",
            ])
            .arg(&seq)
            .output()
            .unwrap(),
    );
    assert!(said.contains("scene cuts before frames [2]"), "{said}");
    let meta = |k: usize| -> serde_json::Value {
        let path = seq.join(format!("frame_{k:04}/meta.json"));
        serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
    };
    // The fog drifts from frame to frame; after the cut the next seed's scene.
    assert_ne!(meta(0)["beta_per_mm"], meta(1)["beta_per_mm"]);
    assert_eq!(meta(0)["config"]["seed"], meta(1)["config"]["seed"]);
    assert_ne!(meta(1)["config"]["seed"], meta(2)["config"]["seed"]);
    assert_ne!(meta(0)["scene"], meta(1)["scene"]);

    let said = succeeded(
        &murk()
            .env_remove("MURK_SERVER")
            .args(["tof", "--sequence"])
            .arg(&seq)
            .args(["--outputs", "z_depth_m,mask", "--encoding", "png", "--out"])
            .arg(&out)
            .output()
            .unwrap(),
    );
    assert!(
        said.contains("3 frames sent, 3 computed, 0 failed, 0 dropped"),
        "{said}"
    );
    for k in 0..3 {
        for f in ["z_depth_m.exr", "mask.exr"] {
            assert!(out.join(format!("frame_{k:04}/{f}")).exists(), "{k}: {f}");
        }
        assert!(!out.join(format!("frame_{k:04}/range_m.exr")).exists());
    }
    // A grid outside its range ends the session before any frame, naming the field.
    let bad = murk()
        .env_remove("MURK_SERVER")
        .args(["tof", "--sequence"])
        .arg(&seq)
        .args(["--scatter-grid", "5", "--out"])
        .arg(dir.path().join("bad"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let said = String::from_utf8_lossy(&bad.stderr);
    assert!(said.contains("tof_scatter_grid"), "{said}");
}

#[test]
fn a_simulated_stereo_sequence_streams_through_a_session() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("seq");
    let said = succeeded(
        &murk()
            .args(["simulate", "stereo", "--frames", "3", "--width", "96"])
            .args(["--height", "72", "--seed", "2", "--out"])
            .arg(&seq)
            .output()
            .unwrap(),
    );
    // The printed next step is the command that streams the sequence.
    let next = said
        .lines()
        .find_map(|l| l.strip_prefix("next: murk "))
        .unwrap_or_else(|| panic!("{said}"));
    let meta = |k: usize| -> serde_json::Value {
        let path = seq.join(format!("frame_{k:04}/meta.json"));
        serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
    };
    // One rig and one haze; the rig moves, so the scene's depths change.
    assert_eq!(meta(0)["beta"], meta(2)["beta"]);
    assert_eq!(meta(0)["baseline"], meta(2)["baseline"]);
    assert_eq!(meta(2)["time_s"], 0.2);
    let depth = |k: usize| {
        murk::io::read_image(
            &seq.join(format!("frame_{k:04}/depth.exr")),
            &murk::io::DecodeLimits::default(),
        )
        .unwrap()
    };
    assert_ne!(depth(0).data(), depth(2).data());
    let said = succeeded(
        &murk()
            .env_remove("MURK_SERVER")
            .args(next.split_whitespace())
            .output()
            .unwrap(),
    );
    assert!(
        said.contains("3 frames sent, 3 computed, 0 failed, 0 dropped"),
        "{said}"
    );
    for k in 0..3 {
        for f in ["depth.exr", "points.ply"] {
            assert!(
                seq.join(format!("result/frame_{k:04}/{f}")).exists(),
                "{k}: {f}"
            );
        }
    }
}
