//! `RectifiedStereo` end to end against a real in-process server: a rectified pair described by
//! its rig (intrinsics, baseline) gets the same depth as the same pair described as two posed
//! views through `MvsDepth`, far better than chance on a simulated hazy scene, with the point
//! cloud on request; and bad rigs are refused naming the field.

use crate::common;

use common::*;
use murk::atmosphere::AtmosphereParams;
use murk::image::ImageF32;
use murk::metrics::depth_metrics;
use murk::monitor::Monitor;
use murk::mvs::{PlaneSet, RectifiedRig, StereoRange};
use murk::simulate::mvs::{simulate_mvs, MvsScene, MvsSimConfig};
use murk_server::service::convert::{
    image_from_proto, points_from_proto, stereo_request_to_proto, ImageLimits,
};
use murk_server::service::proto::v1 as pb;

fn decode(img: Option<pb::Image>) -> ImageF32 {
    image_from_proto(&img.expect("image present"), &ImageLimits::default()).expect("decodes")
}

/// The simulator's 128×96 rectified pair (seed 2): left view 0, the right one `baseline` along
/// +x.
fn pair() -> (MvsScene, RectifiedRig) {
    let cfg = MvsSimConfig {
        seed: 2,
        rectified_pair: true,
        num_views: 2,
        ..MvsSimConfig::with_size(128, 96)
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop()).expect("simulate");
    let baseline = -scene.views[1].pose.translation()[0];
    let rig = RectifiedRig::new(scene.views[0].intrinsics, baseline);
    (scene, rig)
}

fn request(scene: &MvsScene, rig: &RectifiedRig, planes: &PlaneSet) -> pb::RectifiedStereoRequest {
    let mut req = stereo_request_to_proto(
        &scene.views[0].hazy,
        &scene.views[1].hazy,
        rig,
        Some(StereoRange::Depth {
            near: planes.near,
            far: planes.far,
        }),
        Some(AtmosphereParams {
            airlight: scene.airlight,
            beta: scene.beta,
        }),
    );
    req.num_planes = planes.num_planes as u32;
    req
}

#[tokio::test]
async fn a_rig_gets_the_depth_of_the_same_pair_as_posed_views() {
    let (scene, rig) = pair();
    let planes = PlaneSet::new(1.5, 15.0, 32).unwrap();
    let server = start(config(4)).await;
    let mut recon = recon(&server);

    let mut req = request(&scene, &rig, &planes);
    req.return_points = true;
    let stereo = recon
        .rectified_stereo(req.clone())
        .await
        .expect("rectified stereo")
        .into_inner();
    let mvs = recon
        .mvs_depth(mvs_request(&scene, pb::CostVolumeKind::Dehazing, &planes))
        .await
        .expect("mvs depth")
        .into_inner();
    // The same plane sweep: the same depth and confidence, bit for bit.
    assert_eq!(stereo.z_depth, mvs.z_depth);
    assert_eq!(stereo.confidence, mvs.confidence);
    assert_eq!(stereo.num_planes, 32);
    assert_eq!(stereo.cost_volume, pb::CostVolumeKind::Dehazing as i32);

    let z = decode(stereo.z_depth.clone());
    let m = depth_metrics(&z, &scene.views[0].depth, None).expect("metrics");
    // Chance (a constant depth at the ground truth's median) is about 22 %.
    assert!(m.c_p > 0.5, "C.P. {}", m.c_p);

    // Disparity is fx·B/z, and the cloud holds the confident pixels.
    let d = decode(stereo.disparity.clone());
    let fb = rig.intrinsics.fx * rig.baseline;
    for (dv, zv) in d.data().iter().zip(z.data()).step_by(97) {
        assert!((f64::from(*dv) - fb / f64::from(*zv)).abs() < 1e-3);
    }
    let points = points_from_proto(stereo.points.as_ref().expect("points")).unwrap();
    let confident = decode(stereo.confidence.clone())
        .data()
        .iter()
        .filter(|&&c| c > 0.0)
        .count();
    assert_eq!(points.len(), confident);
    assert!((stereo.max_disparity_px - (fb / 1.5) as f32).abs() < 1e-3);

    // Without points the cloud is absent, and an equivalent request is one cached job.
    req.return_points = false;
    let plain = recon.rectified_stereo(req.clone()).await.unwrap();
    assert!(plain.get_ref().points.is_none());
    let mut same = req.clone();
    same.right_cx = Some(rig.intrinsics.cx);
    let again = recon.rectified_stereo(same).await.unwrap();
    assert_eq!(
        plain.metadata().get("x-murk-job-id"),
        again.metadata().get("x-murk-job-id")
    );
    server.stop().await.unwrap();
}

#[tokio::test]
async fn bad_rigs_and_pairs_are_refused_naming_the_field() {
    let (scene, rig) = pair();
    let planes = PlaneSet::new(1.5, 15.0, 32).unwrap();
    let server = start(config(4)).await;
    let mut recon = recon(&server);
    let good = request(&scene, &rig, &planes);
    let cases: Vec<(pb::RectifiedStereoRequest, &str)> = vec![
        (
            pb::RectifiedStereoRequest {
                baseline: 0.0,
                ..good.clone()
            },
            "baseline",
        ),
        (
            pb::RectifiedStereoRequest {
                right_cx: Some(f64::NAN),
                ..good.clone()
            },
            "right_cx",
        ),
        (
            pb::RectifiedStereoRequest {
                intrinsics: None,
                ..good.clone()
            },
            "intrinsics",
        ),
        (
            pb::RectifiedStereoRequest {
                min_disparity_px: Some(4.0),
                ..good.clone()
            },
            "near",
        ),
        (
            pb::RectifiedStereoRequest {
                right: Some(pb::Image {
                    width: 128,
                    height: 96,
                    channels: 3,
                    data: Some(pb::image::Data::RawF32Le(vec![0; 12])),
                    ..Default::default()
                }),
                ..good.clone()
            },
            "right",
        ),
        (
            pb::RectifiedStereoRequest {
                airlight: 0.0,
                ..good.clone()
            },
            "airlight",
        ),
    ];
    for (req, field) in cases {
        let status = recon.rectified_stereo(req).await.unwrap_err();
        let named = bad_field(&status);
        assert!(
            named == field || named.starts_with(&format!("{field}.")),
            "expected {field}, got {named}: {}",
            status.message()
        );
    }
    server.stop().await.unwrap();
}
