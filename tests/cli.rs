//! The `murk` binary end to end: simulate a frame to disk, then run the ToF client against a real
//! server and check the files it writes.

mod common;

use std::process::Command;

use common::*;

fn murk() -> Command {
    Command::new(env!("CARGO_BIN_EXE_murk"))
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
    assert!(
        output.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    for f in [
        "range_m.exr",
        "z_depth_m.exr",
        "mask.exr",
        "scatter_phase.exr",
        "range_m.png",
        "raw_range_m.png",
        "mask.png",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    assert_eq!(server.manager().executed(), 1);

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
async fn graceful_shutdown_cancels_running_jobs_after_the_grace_period() {
    let server = start(config(4)).await;
    let mut c = jobs(&server);
    let id = submit_running_long_job(&mut c).await;
    let manager = server.manager().clone();
    server.stop().await.unwrap();
    let snap = manager.get(&id).unwrap().snapshot();
    assert_eq!(snap.state, murk::jobs::JobState::Cancelled);
}
