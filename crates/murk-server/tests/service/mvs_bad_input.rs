//! Bad `MvsDepth` input gets INVALID_ARGUMENT naming the field, and the server keeps serving.

use crate::common;

use common::*;
use murk::image::ImageF32;
use murk::mvs::{PlaneSet, MAX_PLANES};
use murk_server::service::convert::{image_to_proto, MAX_SOURCE_VIEWS};
use murk_server::service::proto::v1 as pb;

const W: usize = 32;
const H: usize = 24;

fn good() -> pb::MvsDepthRequest {
    let scene = mvs_scene(W, H, 5);
    mvs_request(
        &scene,
        pb::CostVolumeKind::Dehazing,
        &PlaneSet::new(1.5, 15.0, 16).unwrap(),
    )
}

async fn submit_err(
    server: &murk_server::server::InProcessServer,
    req: pb::MvsDepthRequest,
) -> String {
    let s = jobs(server).submit_job(mvs_job(req)).await.unwrap_err();
    bad_field(&s)
}

/// A change that breaks one field of a good request.
type Edit = Box<dyn Fn(&mut pb::MvsDepthRequest)>;

fn reference(r: &mut pb::MvsDepthRequest) -> &mut pb::MvsView {
    r.reference.as_mut().expect("reference")
}

fn intrinsics(v: &mut pb::MvsView) -> &mut pb::CameraIntrinsics {
    v.intrinsics.as_mut().expect("intrinsics")
}

#[tokio::test]
async fn bad_mvs_requests_name_the_field_and_the_server_keeps_serving() {
    let server = start(config(4)).await;
    let good = good();
    let cases: Vec<(&str, Edit)> = vec![
        ("sources", Box::new(|r| r.sources.clear())),
        (
            "sources",
            Box::new(|r| r.sources = vec![r.sources[0].clone(); MAX_SOURCE_VIEWS + 1]),
        ),
        (
            "sources[1].image",
            Box::new(|r| {
                r.sources[1].image = Some(image_to_proto(&ImageF32::filled(W - 1, H, 3, 0.5)))
            }),
        ),
        (
            "sources[2].image",
            Box::new(|r| {
                r.sources[2].image = Some(image_to_proto(&ImageF32::filled(W, H, 1, 0.5)))
            }),
        ),
        (
            "reference.intrinsics.fx",
            Box::new(|r| intrinsics(reference(r)).fx = f64::NAN),
        ),
        (
            "reference.intrinsics.cy",
            Box::new(|r| intrinsics(reference(r)).cy = f64::INFINITY),
        ),
        (
            "sources[0].intrinsics.fy",
            Box::new(|r| intrinsics(&mut r.sources[0]).fy = 0.0),
        ),
        (
            "reference.intrinsics.fx",
            Box::new(|r| intrinsics(reference(r)).fx = -200.0),
        ),
        ("sources[3].pose", Box::new(|r| r.sources[3].pose = None)),
        (
            "reference.pose.rotation",
            Box::new(|r| {
                reference(r).pose.as_mut().expect("pose").rotation = vec![1.0; 9];
            }),
        ),
        ("reference.image", Box::new(|r| reference(r).image = None)),
        (
            "far",
            Box::new(|r| {
                r.near = 20.0;
                r.far = 10.0;
            }),
        ),
        (
            "far",
            Box::new(|r| {
                r.near = 5.0;
                r.far = 5.0;
            }),
        ),
        ("near", Box::new(|r| r.near = -1.0)),
        ("near", Box::new(|r| r.near = f64::NAN)),
        (
            "num_planes",
            Box::new(|r| r.num_planes = MAX_PLANES as u32 + 1),
        ),
        ("airlight", Box::new(|r| r.airlight = 0.0)),
        ("airlight", Box::new(|r| r.airlight = 1.5)),
        ("beta", Box::new(|r| r.beta = -0.1)),
        ("beta", Box::new(|r| r.beta = f32::INFINITY)),
        ("cost_volume", Box::new(|r| r.cost_volume = 42)),
        (
            "sgm.p2",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    p1: Some(1.0),
                    p2: Some(0.5),
                    ..Default::default()
                })
            }),
        ),
        (
            "sgm.presmooth_sigma_px",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    presmooth_sigma_px: Some(f32::NAN),
                    ..Default::default()
                })
            }),
        ),
        (
            "sgm.presmooth_sigma_px",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    presmooth_sigma_px: Some(50.0),
                    ..Default::default()
                })
            }),
        ),
        (
            "sgm.contrast_percentile",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    contrast_percentile: Some(f32::NAN),
                    ..Default::default()
                })
            }),
        ),
        (
            "sgm.contrast_max_weight",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    contrast_max_weight: Some(1000.0),
                    ..Default::default()
                })
            }),
        ),
        (
            "sgm.census_weight",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    census_weight: Some(-0.5),
                    ..Default::default()
                })
            }),
        ),
        (
            "sgm.census_weight",
            Box::new(|r| {
                r.sgm = Some(pb::SgmOptions {
                    census_weight: Some(f32::INFINITY),
                    ..Default::default()
                })
            }),
        ),
        (
            "reference.image",
            Box::new(|r| {
                let mut img = ImageF32::filled(W, H, 3, 0.5);
                img.set(3, 4, 1, f32::NAN);
                reference(r).image = Some(image_to_proto(&img));
            }),
        ),
    ];
    for (field, edit) in &cases {
        let mut r = good.clone();
        edit(&mut r);
        assert_eq!(
            submit_err(&server, r).await,
            format!("request.mvs_depth.{field}")
        );
    }
    assert_eq!(server.manager().executed(), 0, "nothing bad was queued");

    // The unary RPC names fields relative to its own request message.
    let mut r = good.clone();
    r.airlight = 1.5;
    let e = recon(&server).mvs_depth(r).await.unwrap_err();
    assert_eq!(bad_field(&e), "airlight");

    // ORDINARY ignores A and β (0 = unset is fine) but still refuses NaN.
    let mut r = good.clone();
    r.cost_volume = pb::CostVolumeKind::Ordinary as i32;
    r.airlight = f32::NAN;
    assert_eq!(
        submit_err(&server, r.clone()).await,
        "request.mvs_depth.airlight"
    );
    r.airlight = 0.0;
    r.beta = 0.0;
    let ok = recon(&server).mvs_depth(r).await.unwrap().into_inner();
    assert!(ok.z_depth.is_some());

    // Still serving: a good request succeeds.
    let ok = recon(&server).mvs_depth(good).await.unwrap().into_inner();
    assert_eq!(ok.z_depth.unwrap().width, W as u32);
    server.stop().await.unwrap();
}
