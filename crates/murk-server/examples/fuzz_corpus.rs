//! Writes the request fuzzer's seed corpus, `crates/murk-server/tests/fuzz-corpus/*.pb`: one
//! small valid `murk.v1.JobRequest` per method, from the simulators. Rerun it when a request
//! message changes so the seeds stay valid (a test checks that they do).
//!
//! `cargo run -p murk-server --example fuzz_corpus [-- --out DIR]`

use std::path::PathBuf;

use murk::atmosphere::AtmosphereParams;
use murk::mvs::{PlaneSet, RectifiedRig, StereoRange, View};
use murk::params::sparse::{selected_points, PointSelection};
use murk::ps::PsParams;
use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
use murk::simulate::ps::{simulate_ps, PsSimConfig};
use murk::simulate::tof::{simulate_tof, TofSimConfig};
use murk::Monitor;
use murk_server::service::convert::{
    mvs_request_to_proto, params_request_to_proto, ps_request_to_proto, simulated_tof_request,
    stereo_request_to_proto,
};
use murk_server::service::proto::v1 as pb;
use prost::Message;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let out = match args.iter().position(|a| a == "--out") {
        Some(i) => PathBuf::from(
            args.get(i + 1)
                .ok_or_else(|| anyhow::anyhow!("--out DIR"))?,
        ),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-corpus"),
    };
    std::fs::create_dir_all(&out)?;
    let quiet = Monitor::noop();
    use pb::job_request::Method;

    let tof_cfg = TofSimConfig {
        seed: 1,
        ..TofSimConfig::with_size(16, 12)
    };
    let frame = simulate_tof(&tof_cfg, &quiet)?;
    let tof = Method::TofDepth(simulated_tof_request(&frame, &tof_cfg));

    let mvs_scene = simulate_mvs(
        &MvsSimConfig {
            seed: 2,
            num_views: 3,
            ..MvsSimConfig::with_size(16, 12)
        },
        &quiet,
    )?;
    let views: Vec<View<'_>> = mvs_scene.hazy_views();
    let sources: Vec<View<'_>> = (0..views.len())
        .filter(|&i| i != mvs_scene.reference)
        .map(|i| views[i])
        .collect();
    let mvs = Method::MvsDepth(mvs_request_to_proto(
        &views[mvs_scene.reference],
        &sources,
        pb::CostVolumeKind::Dehazing,
        Some(AtmosphereParams {
            airlight: mvs_scene.airlight,
            beta: mvs_scene.beta,
        }),
        Some(&PlaneSet::new(1.5, 15.0, 8)?),
    ));

    let params_scene = simulate_mvs(
        &MvsSimConfig {
            seed: 3,
            num_views: 3,
            beta_range: Some([0.4, 0.8]),
            ..MvsSimConfig::with_size(40, 30)
        },
        &quiet,
    )?;
    let (reference, sources) = params_scene.reference_and_sources();
    let points = selected_points(
        &params_scene.sparse,
        &params_scene.views[params_scene.reference].name,
        PointSelection::ObservedInReference,
    )?;
    let params = Method::ScatteringParams(params_request_to_proto(
        &reference,
        &sources,
        &points,
        pb::AirlightSource::DarkChannel,
        0.0,
    ));

    let pair = simulate_mvs(
        &MvsSimConfig {
            seed: 4,
            rectified_pair: true,
            num_views: 2,
            ..MvsSimConfig::with_size(24, 18)
        },
        &quiet,
    )?;
    let rig = RectifiedRig::new(
        pair.views[0].intrinsics,
        -pair.views[1].pose.translation()[0],
    );
    let mut stereo = stereo_request_to_proto(
        &pair.views[0].hazy,
        &pair.views[1].hazy,
        &rig,
        Some(StereoRange::Depth {
            near: 1.5,
            far: 15.0,
        }),
        Some(AtmosphereParams {
            airlight: pair.airlight,
            beta: pair.beta,
        }),
    );
    stereo.num_planes = 8;
    let stereo = Method::RectifiedStereo(stereo);

    let ps_sim = simulate_ps(&PsSimConfig::with_size(16, 16), &quiet)?;
    let ps = Method::PhotometricStereo(ps_request_to_proto(
        &ps_sim.capture,
        &PsParams {
            initial_distance_mm: ps_sim.initial_distance_mm,
            support_r: 5,
            max_iterations: 2,
            ..PsParams::default()
        },
    ));

    for (name, method) in [
        ("tof_depth", tof),
        ("mvs_depth", mvs),
        ("scattering_params", params),
        ("rectified_stereo", stereo),
        ("photometric_stereo", ps),
    ] {
        let bytes = pb::JobRequest {
            method: Some(method),
        }
        .encode_to_vec();
        let path = out.join(format!("{name}.pb"));
        std::fs::write(&path, &bytes)?;
        println!("wrote {} ({} bytes)", path.display(), bytes.len());
    }
    Ok(())
}
