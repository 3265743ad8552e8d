//! `Sessions.Stream` end to end against real in-process servers, driven by the generated client:
//! results in order with their frames' metadata and equal to one-shot results, a bad frame that
//! leaves the session going, drop reporting under LATEST, configuration errors, the session
//! limits per tenant, and cancellation when the client goes away.

use crate::common;

use std::time::Duration;

use common::*;
use murk_server::server::ServerConfig;
use murk_server::service::auth::TokenStore;
use murk_server::service::proto::v1 as pb;
use murk_server::service::SessionLimits;
use pb::session_event::Event;
use pb::sessions_client::SessionsClient;
use tokio::sync::mpsc;
use tonic::metadata::MetadataValue;
use tonic::{Code, Status, Streaming};

const ALPHA: &str = "alpha-token-0123456789";
const BETA: &str = "beta-token-9876543210";

/// An open session: frames go in through `tx`, events come out of `events`.
struct Session {
    tx: mpsc::Sender<pb::SessionRequest>,
    events: Streaming<pb::SessionEvent>,
}

impl Session {
    async fn send_frame(&self, frame: pb::SessionFrame) {
        self.tx
            .send(pb::SessionRequest {
                message: Some(pb::session_request::Message::Frame(frame)),
            })
            .await
            .expect("stream open");
    }

    async fn next(&mut self) -> Option<Result<Event, Status>> {
        match self.events.message().await {
            Ok(Some(e)) => Some(Ok(e.event.expect("event set"))),
            Ok(None) => None,
            Err(s) => Some(Err(s)),
        }
    }

    async fn event(&mut self) -> Event {
        self.next().await.expect("an event").expect("not an error")
    }
}

/// Opens a session with `config` as its first message (`None`: send nothing first).
async fn open(
    server: &murk_server::server::InProcessServer,
    first: Option<pb::SessionRequest>,
    token: Option<&str>,
) -> Result<Session, Status> {
    open_at(channel(server), first, token).await
}

/// [`open`] on any channel (a balancer's, say).
async fn open_at(
    channel: tonic::transport::Channel,
    first: Option<pb::SessionRequest>,
    token: Option<&str>,
) -> Result<Session, Status> {
    let (tx, rx) = mpsc::channel::<pb::SessionRequest>(64);
    if let Some(m) = first {
        tx.send(m).await.unwrap();
    }
    let outbound =
        futures::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|m| (m, rx)) });
    let mut request = tonic::Request::new(outbound);
    if let Some(t) = token {
        request.metadata_mut().insert(
            "authorization",
            MetadataValue::try_from(format!("Bearer {t}")).unwrap(),
        );
    }
    let events = SessionsClient::new(channel)
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX)
        .stream(request)
        .await?
        .into_inner();
    Ok(Session { tx, events })
}

fn config_message(config: pb::SessionConfig) -> Option<pb::SessionRequest> {
    Some(pb::SessionRequest {
        message: Some(pb::session_request::Message::Config(config)),
    })
}

/// A ToF session configuration from a one-shot request (its images taken out) and the frame
/// with those images.
fn tof_session(
    mut req: pb::TofDepthRequest,
    policy: pb::QueuePolicy,
    queued: u32,
) -> (pb::SessionConfig, pb::SessionFrame) {
    let frame = pb::SessionFrame {
        amplitude: req.amplitude.take(),
        phase: req.phase.take(),
        ..Default::default()
    };
    let a = frame.amplitude.as_ref().unwrap();
    let config = pb::SessionConfig {
        width: a.width,
        height: a.height,
        method: Some(pb::session_config::Method::Tof(req)),
        queue_policy: policy as i32,
        max_queued_frames: queued,
        frame_deadline_seconds: 0.0,
        tof_scatter_grid: 0,
    };
    (config, frame)
}

fn numbered(frame: &pb::SessionFrame, sequence: u64) -> pb::SessionFrame {
    pb::SessionFrame {
        sequence,
        frame_id: format!("frame-{sequence:03}"),
        stamp: Some(prost_types::Timestamp {
            seconds: 1_700_000_000 + sequence as i64,
            nanos: 500,
        }),
        ..frame.clone()
    }
}

fn started(e: Event) -> pb::SessionStarted {
    match e {
        Event::Started(s) => s,
        other => panic!("expected SessionStarted, got {other:?}"),
    }
}

#[tokio::test]
async fn frames_come_back_in_order_with_their_metadata_and_a_bad_frame_leaves_the_session_going() {
    let server = start(config(4)).await;
    let one_shot = tof_request(64, 53, 3);
    let expected = recon(&server)
        .tof_depth(one_shot.clone())
        .await
        .expect("one-shot")
        .into_inner();
    let (mut config, frame) = tof_session(one_shot, pb::QueuePolicy::Fifo, 2);
    // Exact images, to compare with the one-shot result bit for bit.
    if let Some(pb::session_config::Method::Tof(t)) = &mut config.method {
        t.outputs = Some(pb::OutputOptions {
            fields: vec!["range_m".into(), "mask".into()],
            encoding: pb::ImageEncoding::F32 as i32,
        });
    }
    let mut s = open(&server, config_message(config.clone()), None)
        .await
        .expect("session opens");
    let st = started(s.event().await);
    assert_eq!(st.queue_policy, pb::QueuePolicy::Fifo as i32);
    assert_eq!(st.max_queued_frames, 2);

    // Frame 2 has a NaN phase, frame 3 the wrong size; then a second configuration, which is
    // refused while the session goes on.
    let mut nan = numbered(&frame, 2);
    if let Some(pb::image::Data::RawF32Le(b)) = nan.phase.as_mut().and_then(|p| p.data.as_mut()) {
        b[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
    }
    let small = tof_request(32, 26, 3);
    let mut wrong_size = numbered(&frame, 3);
    wrong_size.amplitude = small.amplitude;
    wrong_size.phase = small.phase;
    s.send_frame(numbered(&frame, 1)).await;
    s.send_frame(nan).await;
    s.send_frame(wrong_size).await;
    s.tx.send(config_message(config).unwrap()).await.unwrap();
    s.send_frame(numbered(&frame, 4)).await;
    drop(s.tx.clone());
    let mut results = Vec::new();
    let mut refused = Vec::new();
    while results.len() < 4 {
        match s.event().await {
            Event::Result(r) => results.push(r),
            Event::Refused(e) => refused.push(e),
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(refused.len(), 1);
    assert_eq!(refused[0].field, "config");
    assert_eq!(
        results.iter().map(|r| r.sequence).collect::<Vec<_>>(),
        [1, 2, 3, 4]
    );
    for r in &results {
        assert_eq!(r.frame_id, format!("frame-{:03}", r.sequence));
        assert_eq!(r.stamp.unwrap().seconds, 1_700_000_000 + r.sequence as i64);
        assert!(r.compute_seconds > 0.0 && r.queue_seconds >= 0.0);
    }
    let error = |r: &pb::FrameResult| match &r.outcome {
        Some(pb::frame_result::Outcome::Error(e)) => e.clone(),
        other => panic!("expected an error, got {other:?}"),
    };
    let e2 = error(&results[1]);
    assert_eq!((e2.code, e2.field.as_str()), (3, "frame.phase"));
    let e3 = error(&results[2]);
    assert_eq!((e3.code, e3.field.as_str()), (3, "frame.amplitude"));
    for r in [&results[0], &results[3]] {
        let Some(pb::frame_result::Outcome::Tof(t)) = &r.outcome else {
            panic!("expected a ToF result, got {:?}", r.outcome);
        };
        // The same computation as the one-shot job: the same images, bit for bit.
        assert_eq!(t.range_m, expected.range_m);
        assert_eq!(t.mask, expected.mask);
    }
    // Half-closing the stream ends the session once its frames are answered.
    let tx = s.tx;
    drop(tx);
    assert!(s.events.message().await.unwrap().is_none());
    server.stop().await.unwrap();
}

#[tokio::test]
async fn latest_reports_every_frame_it_drops_and_answers_the_rest() {
    let server = start(config(4)).await;
    // Frames of a few hundred milliseconds (a fixed number of iterations), so that the frames
    // sent at once all arrive while the first computes.
    let mut req = tof_request(64, 53, 5);
    req.options = Some(pb::TofOptions {
        fine_iterations: Some(400),
        convergence_tolerance: Some(0.0),
        ..Default::default()
    });
    let (config, frame) = tof_session(req, pb::QueuePolicy::Latest, 1);
    let mut s = open(&server, config_message(config), None).await.unwrap();
    started(s.event().await);
    // Twelve frames at once: the first is computed while the rest arrive, and a full queue of
    // one gives up its frame to each newer one.
    const N: u64 = 12;
    for k in 1..=N {
        s.send_frame(numbered(&frame, k)).await;
    }
    let tx = s.tx.clone();
    drop(tx);
    let Session { tx, mut events } = s;
    drop(tx);
    let (mut computed, mut dropped) = (Vec::new(), Vec::new());
    while let Some(e) = events.message().await.unwrap() {
        match e.event.unwrap() {
            Event::Result(r) => {
                assert!(matches!(r.outcome, Some(pb::frame_result::Outcome::Tof(_))));
                computed.push(r.sequence);
            }
            Event::Dropped(d) => {
                assert_eq!(d.reason, pb::DropReason::Superseded as i32);
                assert_eq!(d.frame_id, format!("frame-{:03}", d.sequence));
                dropped.push(d.sequence);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    // Every frame is accounted for exactly once; results stay in order, the last frame is
    // always answered, and the queue of one dropped frames.
    let mut all: Vec<u64> = computed.iter().chain(&dropped).copied().collect();
    all.sort_unstable();
    assert_eq!(all, (1..=N).collect::<Vec<_>>());
    assert!(computed.windows(2).all(|w| w[0] < w[1]), "{computed:?}");
    assert_eq!(computed.last(), Some(&N));
    assert!(!dropped.is_empty(), "computed all of {computed:?}");
    let metrics = scrape(server.metrics_addr()).await;
    assert_eq!(
        sample(
            &metrics,
            "murk_session_frames_total{method=\"tof_depth\",outcome=\"superseded\"}"
        ),
        dropped.len() as f64
    );
    server.stop().await.unwrap();
}

/// A rectified stereo session's method for 64×53 frames with `baseline`.
fn stereo_method(baseline: f64) -> pb::session_config::Method {
    pb::session_config::Method::Stereo(pb::RectifiedStereoRequest {
        intrinsics: Some(pb::CameraIntrinsics {
            fx: 50.0,
            fy: 50.0,
            cx: 31.5,
            cy: 26.0,
            skew: 0.0,
        }),
        baseline,
        cost_volume: pb::CostVolumeKind::Ordinary as i32,
        ..Default::default()
    })
}

#[tokio::test]
async fn bad_configurations_end_the_stream_naming_the_field() {
    let server = start(config(4)).await;
    let (config, frame) = tof_session(tof_request(64, 53, 3), pb::QueuePolicy::Latest, 0);
    let cases: Vec<(Option<pb::SessionRequest>, &str)> = vec![
        (
            Some(pb::SessionRequest {
                message: Some(pb::session_request::Message::Frame(frame)),
            }),
            "config",
        ),
        (
            config_message(pb::SessionConfig {
                width: 1,
                ..config.clone()
            }),
            "config.width",
        ),
        (
            config_message(pb::SessionConfig {
                max_queued_frames: 65,
                ..config.clone()
            }),
            "config.max_queued_frames",
        ),
        (
            config_message(pb::SessionConfig {
                frame_deadline_seconds: f64::NAN,
                ..config.clone()
            }),
            "config.frame_deadline_seconds",
        ),
        (
            config_message(pb::SessionConfig {
                tof_scatter_grid: 5,
                ..config.clone()
            }),
            "config.tof_scatter_grid",
        ),
        (
            config_message(pb::SessionConfig {
                method: None,
                ..config.clone()
            }),
            "config.method",
        ),
        (
            config_message(pb::SessionConfig {
                method: Some(pb::session_config::Method::Tof(pb::TofDepthRequest {
                    modulation_frequency_hz: 16.0,
                    ..Default::default()
                })),
                ..config.clone()
            }),
            "config.tof.modulation_frequency_hz",
        ),
        (
            config_message(pb::SessionConfig {
                method: Some(stereo_method(-0.1)),
                ..config.clone()
            }),
            "config.stereo.baseline",
        ),
        (
            config_message(pb::SessionConfig {
                method: Some(stereo_method(0.1)),
                tof_scatter_grid: 2,
                ..config.clone()
            }),
            "config.tof_scatter_grid",
        ),
        (
            config_message(pb::SessionConfig {
                method: Some(pb::session_config::Method::Tof(pb::TofDepthRequest {
                    outputs: Some(pb::OutputOptions {
                        fields: vec!["mask".into(), "depth".into()],
                        encoding: 0,
                    }),
                    amplitude: None,
                    phase: None,
                    ..tof_request(64, 53, 3)
                })),
                ..config.clone()
            }),
            "config.tof.outputs.fields[1]",
        ),
    ];
    for (first, field) in cases {
        let mut s = open(&server, first, None).await.unwrap();
        let status = s.next().await.expect("an answer").unwrap_err();
        assert_eq!(bad_field(&status), field, "{status:?}");
    }
    server.stop().await.unwrap();
}

#[tokio::test]
async fn sessions_are_bounded_per_tenant_and_tenants_do_not_share_the_bound() {
    let server = start(ServerConfig {
        auth: Some(TokenStore::from_text(&format!("alpha {ALPHA}\nbeta {BETA}\n")).unwrap()),
        sessions: SessionLimits {
            max_sessions: 3,
            max_sessions_per_tenant: 2,
            ..SessionLimits::default()
        },
        ..config(4)
    })
    .await;
    let (config, _) = tof_session(tof_request(64, 53, 3), pb::QueuePolicy::Latest, 0);
    let mut a1 = open(&server, config_message(config.clone()), Some(ALPHA))
        .await
        .unwrap();
    let mut a2 = open(&server, config_message(config.clone()), Some(ALPHA))
        .await
        .unwrap();
    started(a1.event().await);
    started(a2.event().await);
    let refused = open(&server, config_message(config.clone()), Some(ALPHA))
        .await
        .err()
        .expect("a third alpha session is refused");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("tenant"), "{refused:?}");
    // Beta has its own bound, within the replica's.
    let mut b1 = open(&server, config_message(config.clone()), Some(BETA))
        .await
        .unwrap();
    started(b1.event().await);
    let full = open(&server, config_message(config.clone()), Some(BETA))
        .await
        .err()
        .expect("the replica is full");
    assert_eq!(full.code(), Code::ResourceExhausted);
    assert!(full.message().contains("replica"), "{full:?}");
    // Without a token there is no session at all.
    let anonymous = open(&server, config_message(config), None)
        .await
        .err()
        .unwrap();
    assert_eq!(anonymous.code(), Code::Unauthenticated);
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_client_that_goes_away_cancels_its_frame() {
    let server = start(config(4)).await;
    // A frame that would compute for minutes unless cancelled.
    let (config, frame) = tof_session(long_tof_request(10_000), pb::QueuePolicy::Fifo, 1);
    let mut s = open(&server, config_message(config), None).await.unwrap();
    started(s.event().await);
    s.send_frame(numbered(&frame, 1)).await;
    let metrics = server.metrics_addr();
    let open_sessions = "murk_sessions_open{method=\"tof_depth\"}";
    assert_eq!(sample(&scrape(metrics).await, open_sessions), 1.0);
    drop(s);
    // The session ends when its frame's computation notices the cancellation (every stage
    // checks within 250 ms), long before the frame would finish.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while sample(&scrape(metrics).await, open_sessions) != 0.0 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the session outlived its client"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // And the pool is free again: a one-shot job runs at once.
    let quick = tokio::time::timeout(
        Duration::from_secs(20),
        recon(&server).tof_depth(tof_request(32, 26, 1)),
    )
    .await
    .expect("the pool is not held by the cancelled frame");
    assert!(quick.is_ok());
    server.stop().await.unwrap();
}

/// A session through the shipped `deploy/nginx.conf` in front of two replicas: its stream is
/// pinned to one replica, and nginx passes a stream whose frames add up to more than the
/// body size it allows other calls (64 MiB).
#[tokio::test]
async fn a_session_streams_through_the_shipped_nginx_config() {
    let (a, b) = (start(config(4)).await, start(config(4)).await);
    let upstreams: Vec<String> = [&a, &b]
        .iter()
        .map(|s| s.url().trim_start_matches("http://").to_string())
        .collect();
    let Some(nginx) = common::nginx::Nginx::start(&upstreams, None) else {
        return;
    };
    let balanced = tonic::transport::Endpoint::from_shared(nginx.url())
        .unwrap()
        .connect_lazy();
    let (config, frame) = tof_session(tof_request(64, 53, 3), pb::QueuePolicy::Fifo, 4);
    let mut s = open_at(balanced, config_message(config), None)
        .await
        .unwrap();
    started(s.event().await);
    // Nine 1024×1024 frames (8 MiB each, refused for their size) and a good one: 72 MiB in all.
    let big = |v: f32| pb::Image {
        width: 1024,
        height: 1024,
        channels: 1,
        data: Some(pb::image::Data::RawF32Le(
            std::iter::repeat_n(v.to_le_bytes(), 1024 * 1024)
                .flatten()
                .collect(),
        )),
        ..Default::default()
    };
    let oversized = pb::SessionFrame {
        amplitude: Some(big(1.0)),
        phase: Some(big(1.0)),
        ..Default::default()
    };
    let sender = {
        let tx = s.tx.clone();
        let frame = frame.clone();
        tokio::spawn(async move {
            for k in 1..=9 {
                let f = numbered(&oversized, k);
                tx.send(pb::SessionRequest {
                    message: Some(pb::session_request::Message::Frame(f)),
                })
                .await
                .unwrap();
            }
            tx.send(pb::SessionRequest {
                message: Some(pb::session_request::Message::Frame(numbered(&frame, 10))),
            })
            .await
            .unwrap();
        })
    };
    let mut answered = Vec::new();
    while answered.len() < 10 {
        match s.event().await {
            Event::Result(r) => answered.push(r),
            other => panic!("unexpected {other:?}"),
        }
    }
    sender.await.unwrap();
    for r in &answered[..9] {
        let Some(pb::frame_result::Outcome::Error(e)) = &r.outcome else {
            panic!("frame {} should be refused for its size", r.sequence);
        };
        assert_eq!(e.field, "frame.amplitude", "{}", e.message);
    }
    assert!(matches!(
        answered[9].outcome,
        Some(pb::frame_result::Outcome::Tof(_))
    ));
    drop(s);
    drop(nginx);
    a.stop().await.unwrap();
    b.stop().await.unwrap();
}

/// A stereo session searches the second pair of a steady scene in a band around the first's
/// disparities: fewer planes, the same depth quality.
#[tokio::test]
async fn a_stereo_session_narrows_its_search_to_the_previous_frames_band() {
    use murk::image::ImageF32;
    use murk::monitor::Monitor;
    use murk::mvs::RectifiedRig;
    use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
    use murk_server::service::convert::{image_from_proto, stereo_request_to_proto, ImageLimits};

    let scene = simulate_mvs(
        &MvsSimConfig {
            seed: 2,
            rectified_pair: true,
            num_views: 2,
            ..MvsSimConfig::with_size(128, 96)
        },
        &Monitor::noop(),
    )
    .unwrap();
    let rig = RectifiedRig::new(
        scene.views[0].intrinsics,
        -scene.views[1].pose.translation()[0],
    );
    let mut template = stereo_request_to_proto(
        &scene.views[0].hazy,
        &scene.views[1].hazy,
        &rig,
        None,
        Some(murk::atmosphere::AtmosphereParams {
            airlight: scene.airlight,
            beta: scene.beta,
        }),
    );
    let frame = pb::SessionFrame {
        left: template.left.take(),
        right: template.right.take(),
        ..Default::default()
    };
    let session = pb::SessionConfig {
        width: 128,
        height: 96,
        method: Some(pb::session_config::Method::Stereo(template)),
        queue_policy: pb::QueuePolicy::Fifo as i32,
        ..Default::default()
    };
    let server = start(config(4)).await;
    let mut s = open(&server, config_message(session), None).await.unwrap();
    started(s.event().await);
    s.send_frame(numbered(&frame, 1)).await;
    s.send_frame(numbered(&frame, 2)).await;
    let mut results = Vec::new();
    while results.len() < 2 {
        match s.event().await {
            Event::Result(r) => match r.outcome {
                Some(pb::frame_result::Outcome::Stereo(st)) => results.push(st),
                other => panic!("expected a stereo result, got {other:?}"),
            },
            other => panic!("unexpected {other:?}"),
        }
    }
    let c_p = |r: &pb::RectifiedStereoResult| {
        let z: ImageF32 =
            image_from_proto(r.z_depth.as_ref().unwrap(), &ImageLimits::default()).unwrap();
        murk::metrics::depth_metrics(&z, &scene.views[0].depth, None)
            .unwrap()
            .c_p
    };
    let (cold, warm) = (&results[0], &results[1]);
    // The default range: 1 px to a quarter of the width, one plane per pixel.
    assert_eq!(cold.num_planes, 32);
    assert!(
        warm.num_planes < cold.num_planes,
        "{} planes after {}",
        warm.num_planes,
        cold.num_planes
    );
    assert!(warm.min_disparity_px > cold.min_disparity_px || warm.max_disparity_px < 32.0);
    let (cp_cold, cp_warm) = (c_p(cold), c_p(warm));
    assert!(cp_warm >= cp_cold - 0.02, "C.P. {cp_warm} after {cp_cold}");
    server.stop().await.unwrap();
}

/// The stream's default result: the z-depth, the mask and range_std_m as PNGs, within half a
/// millimetre of the one-shot float images (the depth 0 where there is no measurement) and, for a
/// 512x424 frame, within 0.6 MB.
#[tokio::test]
async fn a_sessions_default_results_are_compact() {
    use murk::image::ImageF32;
    use murk_server::service::convert::{image_from_proto, ImageLimits};
    use prost::Message;

    let server = start(config(2)).await;
    let mut one_shot = tof_request(512, 424, 11);
    // The session's images, exact, for comparison.
    one_shot.outputs = Some(pb::OutputOptions {
        fields: vec!["z_depth_m".into(), "mask".into(), "range_std_m".into()],
        encoding: pb::ImageEncoding::F32 as i32,
    });
    let exact = recon(&server)
        .tof_depth(one_shot.clone())
        .await
        .expect("one-shot")
        .into_inner();
    assert!(exact.range_m.is_none() && exact.scatter_amplitude.is_none());
    one_shot.outputs = None;
    let (mut config, frame) = tof_session(one_shot, pb::QueuePolicy::Fifo, 1);
    // At full size the session's first frame is the one-shot frame bit for bit (on the default
    // grid its coarse level is solved on block means), so the comparison is the encoding's.
    config.tof_scatter_grid = 1;
    let mut s = open(&server, config_message(config), None).await.unwrap();
    started(s.event().await);
    s.send_frame(numbered(&frame, 1)).await;
    let result = match s.event().await {
        Event::Result(r) => r,
        other => panic!("unexpected {other:?}"),
    };
    let Some(pb::frame_result::Outcome::Tof(t)) = &result.outcome else {
        panic!("expected a ToF result, got {:?}", result.outcome);
    };
    let bytes = result.encoded_len();
    assert!(
        bytes <= 600_000,
        "a 512x424 frame's default result is {bytes} bytes"
    );
    assert!(t.range_m.is_none() && t.raw_range_m.is_none() && t.weight_phase.is_none());
    let decode = |img: &Option<pb::Image>| -> ImageF32 {
        image_from_proto(img.as_ref().expect("image"), &ImageLimits::default()).unwrap()
    };
    let unmeasured = murk::tof::unmeasured_range_std_m(16e6);
    let exact_std = decode(&exact.range_std_m);
    let mut blanked = 0;
    for (name, compact, exact, tolerance) in [
        ("z_depth_m", &t.z_depth_m, &exact.z_depth_m, 0.000_5),
        ("range_std_m", &t.range_std_m, &exact.range_std_m, 0.000_5),
        ("mask", &t.mask, &exact.mask, 0.0),
    ] {
        assert!(
            matches!(
                compact.as_ref().unwrap().data,
                Some(pb::image::Data::Encoded(_))
            ),
            "{name} is not a PNG"
        );
        let (c, e) = (decode(compact), decode(exact));
        for ((a, b), s) in c.data().iter().zip(e.data()).zip(exact_std.data()) {
            if name == "z_depth_m" && *s >= unmeasured {
                // No measurement: 0, as in a ROS depth image.
                assert_eq!(*a, 0.0);
                blanked += 1;
            } else {
                // Half a step, plus the f32 rounding of the affine decode.
                assert!((a - b).abs() <= tolerance + 1e-5, "{name}: {a} for {b}");
            }
        }
    }
    // The simulated frame's objects cover a fraction of it; much of the fog behind has no
    // return above the noise.
    let n = exact_std.data().len();
    assert!(
        blanked > 0 && blanked < n * 3 / 4,
        "{blanked} of {n} pixels without a measurement"
    );
    drop(s.tx);
    server.stop().await.unwrap();
}

/// A ToF session starts each frame from the previous frame's answer: a repeated frame gives the
/// one-shot answer, and a frame of another scene still does, to within the IRLS's convergence
/// (computed again from scratch, with a warning, when too much of the mask changed).
#[tokio::test]
async fn a_tof_session_carries_each_frames_answer_to_the_next() {
    use murk::image::ImageF32;
    use murk_server::service::convert::{image_from_proto, ImageLimits};

    let server = start(config(2)).await;
    let exact = pb::OutputOptions {
        fields: vec!["range_m".into(), "mask".into()],
        encoding: pb::ImageEncoding::F32 as i32,
    };
    let scenes = [tof_request(96, 80, 3), tof_request(96, 80, 9)];
    let mut one_shot = Vec::new();
    for scene in &scenes {
        let mut req = scene.clone();
        req.outputs = Some(exact.clone());
        one_shot.push(recon(&server).tof_depth(req).await.unwrap().into_inner());
    }
    let mut template = scenes[0].clone();
    template.outputs = Some(exact);
    let (config, first) = tof_session(template, pb::QueuePolicy::Fifo, 4);
    let (_, second) = tof_session(scenes[1].clone(), pb::QueuePolicy::Fifo, 4);
    let mut s = open(&server, config_message(config), None).await.unwrap();
    started(s.event().await);
    for (k, frame) in [&first, &first, &second].into_iter().enumerate() {
        s.send_frame(numbered(frame, k as u64 + 1)).await;
    }
    let mut results = Vec::new();
    while results.len() < 3 {
        match s.event().await {
            Event::Result(r) => results.push(r),
            other => panic!("unexpected {other:?}"),
        }
    }
    let mask = |r: &pb::FrameResult| -> ImageF32 {
        let Some(pb::frame_result::Outcome::Tof(t)) = &r.outcome else {
            panic!("expected a ToF result, got {:?}", r.outcome);
        };
        image_from_proto(t.mask.as_ref().unwrap(), &ImageLimits::default()).unwrap()
    };
    let decode = |t: &pb::TofDepthResult| {
        image_from_proto(t.mask.as_ref().unwrap(), &ImageLimits::default()).unwrap()
    };
    for (r, truth) in results
        .iter()
        .zip([&one_shot[0], &one_shot[0], &one_shot[1]])
    {
        let (got, want) = (mask(r), decode(truth));
        let differ = got
            .data()
            .iter()
            .zip(want.data())
            .filter(|(a, b)| a != b)
            .count();
        assert!(
            differ * 100 <= got.data().len(),
            "frame {}: {differ} mask pixels differ from one-shot",
            r.sequence
        );
    }
    // The repeated frame starts from its own answer: nothing to warn about.
    assert!(results[1].warnings.is_empty(), "{:?}", results[1].warnings);
    drop(s.tx);
    server.stop().await.unwrap();
}

#[tokio::test]
async fn a_frame_over_the_request_limit_ends_the_session_with_resource_exhausted() {
    let mut cfg = config(4);
    cfg.max_request_bytes = 64 * 1024;
    let server = start(cfg).await;
    let (config, frame) = tof_session(tof_request(32, 26, 3), pb::QueuePolicy::Fifo, 2);
    let mut s = open(&server, config_message(config), None)
        .await
        .expect("session opens");
    started(s.event().await);
    s.send_frame(numbered(&frame, 1)).await;
    // 200×200 raw f32 amplitude: 160 KB, over the 64 KiB limit.
    let mut big = numbered(&frame, 2);
    if let Some(a) = big.amplitude.as_mut() {
        a.width = 200;
        a.height = 200;
        a.data = Some(pb::image::Data::RawF32Le(vec![0; 200 * 200 * 4]));
    }
    s.send_frame(big).await;
    let status = loop {
        match s.next().await {
            Some(Ok(Event::Result(r))) => assert_eq!(r.sequence, 1),
            Some(Err(status)) => break status,
            other => panic!("expected frame 1's result or the end, got {other:?}"),
        }
    };
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("65536 bytes"), "{status:?}");
    server.stop().await.unwrap();
}
