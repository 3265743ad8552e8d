//! Every numeric field of every method's request, at the extremes a careless or hostile client
//! sends: ±1e30, ±1e300 (f32 fields: ±3e38), 1e-30, 1e-300 and subnormals, 0, the largest and
//! most negative integers, unknown enum values. Fields are found from the API's own descriptors,
//! so a field added later is covered without touching this test.
//!
//! Each mutated request goes to the unary RPC of a real in-process server. The answer must be a
//! result or INVALID_ARGUMENT whose `google.rpc.BadRequest` names a field that exists in the
//! request (never an internal variable such as `b` or `points_mm`), and it must come within the
//! deadline: never INTERNAL, never a hang.

use crate::common;

use std::time::Duration;

use common::*;
use murk::atmosphere::AtmosphereParams;
use murk::monitor::Monitor;
use murk::mvs::{PlaneSet, RectifiedRig, StereoRange};
use murk::ps::PsParams;
use murk::simulate::mvs::{simulate_mvs, MvsSimConfig};
use murk::simulate::ps::{simulate_ps, PsSimConfig};
use murk_server::service::convert::{ps_request_to_proto, stereo_request_to_proto};
use murk_server::service::proto::v1 as pb;
use murk_server::service::proto::FILE_DESCRIPTOR_SET;
use prost::Message;
use prost_reflect::{
    DescriptorPool, DynamicMessage, FieldDescriptor, Kind, MessageDescriptor, ReflectMessage, Value,
};
use tonic::Code;
use tonic_types::StatusExt;

/// Longest a single call may take: a tiny scene at any setting finishes well within it.
const DEADLINE: Duration = Duration::from_secs(20);

/// Calls slower than this are printed, to keep the survey's cost in view.
const SLOW: Duration = Duration::from_secs(2);

/// Deepest nesting followed from the request (Image inside View inside the request is 2).
const MAX_DEPTH: usize = 4;

/// One step from a message into a field (and, for a repeated field, its first element).
#[derive(Clone)]
struct Step {
    field: FieldDescriptor,
    first_element: bool,
}

/// A numeric field reachable from the request, as steps and as the dotted name errors use.
#[derive(Clone)]
struct NumericField {
    steps: Vec<Step>,
    name: String,
}

/// Every numeric (float, integer, enum) field reachable from `msg`: set fields, absent singular
/// ones (they are created when mutated), and the first element of non-empty repeated ones.
/// Absent members of a (real) oneof are skipped: setting one would switch the oneof.
fn numeric_fields(msg: &DynamicMessage, prefix: &[Step], name: &str, out: &mut Vec<NumericField>) {
    if prefix.len() >= MAX_DEPTH {
        return;
    }
    for field in msg.descriptor().fields() {
        if field.is_map() {
            continue;
        }
        let present = msg.has_field(&field);
        // proto3 `optional` fields sit in a synthetic oneof of their own: those are set freely.
        let real_oneof = field.containing_oneof().is_some_and(|o| !o.is_synthetic());
        if real_oneof && !present {
            continue;
        }
        let list_len = match msg.get_field(&field).as_ref() {
            Value::List(v) => Some(v.len()),
            _ => None,
        };
        if field.is_list() && list_len == Some(0) {
            continue;
        }
        let step = Step {
            field: field.clone(),
            first_element: field.is_list(),
        };
        let mut steps = prefix.to_vec();
        steps.push(step);
        let child_name = match (name.is_empty(), field.is_list()) {
            (true, false) => field.name().to_string(),
            (true, true) => format!("{}[0]", field.name()),
            (false, false) => format!("{name}.{}", field.name()),
            (false, true) => format!("{name}.{}[0]", field.name()),
        };
        match field.kind() {
            Kind::Message(desc) => {
                let child = match msg.get_field(&field).as_ref() {
                    Value::Message(m) => m.clone(),
                    Value::List(v) => match v.first() {
                        Some(Value::Message(m)) => m.clone(),
                        _ => continue,
                    },
                    _ => DynamicMessage::new(desc.clone()),
                };
                // Well-known wrapper types and timestamps are not murk's numbers.
                if desc.full_name().starts_with("google.") {
                    continue;
                }
                numeric_fields(&child, &steps, &child_name, out);
            }
            Kind::String | Kind::Bytes | Kind::Bool => {}
            _ => out.push(NumericField {
                steps,
                name: child_name,
            }),
        }
    }
}

/// The extreme values for a field of `kind`.
fn extremes(kind: &Kind) -> Vec<Value> {
    match kind {
        Kind::Double => [
            1e30, -1e30, 1e-30, 1e300, -1e300, 1e-300, 5e-324, -5e-324, 0.0,
        ]
        .into_iter()
        .map(Value::F64)
        .collect(),
        Kind::Float => [
            1e30f32, -1e30, 1e-30, 3e38, -3e38, 1e-38, 1e-45, -1e-45, 0.0,
        ]
        .into_iter()
        .map(Value::F32)
        .collect(),
        Kind::Int32 | Kind::Sint32 | Kind::Sfixed32 => [i32::MIN, -1, 0, i32::MAX]
            .into_iter()
            .map(Value::I32)
            .collect(),
        Kind::Int64 | Kind::Sint64 | Kind::Sfixed64 => [i64::MIN, -1, 0, i64::MAX]
            .into_iter()
            .map(Value::I64)
            .collect(),
        Kind::Uint32 | Kind::Fixed32 => {
            [0, 1 << 31, u32::MAX].into_iter().map(Value::U32).collect()
        }
        Kind::Uint64 | Kind::Fixed64 => {
            [0, 1 << 63, u64::MAX].into_iter().map(Value::U64).collect()
        }
        Kind::Enum(_) => vec![Value::EnumNumber(-1), Value::EnumNumber(999)],
        _ => Vec::new(),
    }
}

/// Sets the field at `steps` in `msg` to `value` (creating absent messages on the way).
fn set(msg: &mut DynamicMessage, steps: &[Step], value: Value) {
    let (step, rest) = steps.split_first().expect("a field");
    let slot = msg.get_field_mut(&step.field);
    let target = if step.first_element {
        match slot {
            Value::List(v) => &mut v[0],
            _ => unreachable!("a repeated field holds a list"),
        }
    } else {
        slot
    };
    if rest.is_empty() {
        *target = value;
    } else if let Value::Message(m) = target {
        set(m, rest, value);
    }
}

/// True when `name` (dotted, with `[k]` indices, as errors name fields) is a field path of
/// `desc`.
fn names_a_field(desc: &MessageDescriptor, name: &str) -> bool {
    let mut current = Some(desc.clone());
    for part in name.split('.') {
        let Some(msg) = current.take() else {
            return false;
        };
        let field_name = part.split('[').next().unwrap_or(part);
        let Some(field) = msg.get_field_by_name(field_name) else {
            return false;
        };
        if let Kind::Message(m) = field.kind() {
            current = Some(m);
        }
    }
    true
}

/// What went wrong with one mutated request.
struct Finding {
    field: String,
    value: String,
    answer: String,
}

/// Sends every extreme of every numeric field of `base` to `path`; returns the mutations
/// whose answer breaks the rules, and how many were sent.
async fn survey(
    server: &murk_server::server::InProcessServer,
    pool: &DescriptorPool,
    message: &str,
    path: &'static str,
    base: &[u8],
) -> (Vec<Finding>, usize) {
    let desc = pool
        .get_message_by_name(message)
        .expect("message in the API");
    let base = DynamicMessage::decode(desc.clone(), base).unwrap();
    let mut fields = Vec::new();
    numeric_fields(&base, &[], "", &mut fields);
    assert!(
        fields.len() > 5,
        "{message}: {} numeric fields",
        fields.len()
    );
    println!(
        "{message}: {}",
        fields
            .iter()
            .map(|f| f.name.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    );
    let mut grpc = tonic::client::Grpc::new(channel(server));
    let mut findings = Vec::new();
    let mut sent = 0;
    for f in &fields {
        let kind = f.steps.last().unwrap().field.kind();
        for value in extremes(&kind) {
            let mut mutated = base.clone();
            set(&mut mutated, &f.steps, value.clone());
            let mut request = tonic::Request::new(mutated.encode_to_vec());
            request.set_timeout(DEADLINE);
            grpc.ready().await.unwrap();
            let started = std::time::Instant::now();
            let answer = grpc
                .unary(
                    request,
                    http::uri::PathAndQuery::from_static(path),
                    RawCodec,
                )
                .await;
            sent += 1;
            let took = started.elapsed();
            if took > SLOW {
                println!("slow: {message} {} = {value:?} took {took:.1?}", f.name);
            }
            let problem = match answer {
                Ok(_) => None,
                // RESOURCE_EXHAUSTED: a valid request over a memory bound, naming the field.
                Err(s) if matches!(s.code(), Code::InvalidArgument | Code::ResourceExhausted) => {
                    match s.get_details_bad_request() {
                        Some(b) if b.field_violations.len() == 1 => {
                            let named = &b.field_violations[0].field;
                            (!names_a_field(&desc, named)).then(|| {
                                format!("names `{named}`, not a request field: {}", s.message())
                            })
                        }
                        _ => Some(format!(
                            "{:?} without one named field: {}",
                            s.code(),
                            s.message()
                        )),
                    }
                }
                Err(s) => Some(format!("{:?}: {}", s.code(), s.message())),
            };
            if let Some(answer) = problem {
                println!("finding: {message} {} = {value:?}: {answer}", f.name);
                findings.push(Finding {
                    field: f.name.clone(),
                    value: format!("{value:?}"),
                    answer,
                });
            }
        }
    }
    (findings, sent)
}

/// Base requests on tiny scenes, so that accepted extremes run quickly.
fn tof() -> pb::TofDepthRequest {
    tof_request(32, 26, 3)
}

fn mvs() -> pb::MvsDepthRequest {
    let scene = mvs_scene(32, 24, 4);
    let planes = PlaneSet::new(1.5, 15.0, 16).unwrap();
    mvs_request(&scene, pb::CostVolumeKind::Dehazing, &planes)
}

fn params() -> pb::ScatteringParamsRequest {
    let scene = crate::params_api::scene(48, 36, 5);
    crate::params_api::request(&scene, pb::AirlightSource::DarkChannel, 0.0)
}

fn stereo() -> pb::RectifiedStereoRequest {
    let cfg = MvsSimConfig {
        seed: 2,
        rectified_pair: true,
        num_views: 2,
        ..MvsSimConfig::with_size(40, 30)
    };
    let scene = simulate_mvs(&cfg, &Monitor::noop()).expect("simulate");
    let baseline = -scene.views[1].pose.translation()[0];
    let rig = RectifiedRig::new(scene.views[0].intrinsics, baseline);
    let mut req = stereo_request_to_proto(
        &scene.views[0].hazy,
        &scene.views[1].hazy,
        &rig,
        Some(StereoRange::Depth {
            near: 1.5,
            far: 15.0,
        }),
        Some(AtmosphereParams {
            airlight: scene.airlight,
            beta: scene.beta,
        }),
    );
    req.num_planes = 16;
    req
}

fn ps() -> pb::PhotometricStereoRequest {
    let sim = simulate_ps(&PsSimConfig::with_size(24, 24), &Monitor::noop()).expect("simulate");
    ps_request_to_proto(
        &sim.capture,
        &PsParams {
            initial_distance_mm: sim.initial_distance_mm,
            support_r: 7,
            max_iterations: 2,
            ..PsParams::default()
        },
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_numeric_field_at_its_extremes_gets_a_result_or_names_a_request_field() {
    let mut cfg = config(64);
    cfg.jobs.concurrent_jobs = 2;
    let server = start(cfg).await;
    let pool = DescriptorPool::decode(FILE_DESCRIPTOR_SET).expect("descriptors");
    let mut report = Vec::new();
    let mut total = 0;
    let requests: [(&str, &'static str, Vec<u8>); 5] = [
        (
            "murk.v1.TofDepthRequest",
            "/murk.v1.Reconstruction/TofDepth",
            tof().encode_to_vec(),
        ),
        (
            "murk.v1.MvsDepthRequest",
            "/murk.v1.Reconstruction/MvsDepth",
            mvs().encode_to_vec(),
        ),
        (
            "murk.v1.ScatteringParamsRequest",
            "/murk.v1.Reconstruction/ScatteringParams",
            params().encode_to_vec(),
        ),
        (
            "murk.v1.RectifiedStereoRequest",
            "/murk.v1.Reconstruction/RectifiedStereo",
            stereo().encode_to_vec(),
        ),
        (
            "murk.v1.PhotometricStereoRequest",
            "/murk.v1.Reconstruction/PhotometricStereo",
            ps().encode_to_vec(),
        ),
    ];
    for (message, path, base) in &requests {
        let (found, sent) = survey(&server, &pool, message, path, base).await;
        println!("{message}: {sent} requests, {} findings", found.len());
        total += sent;
        for f in found {
            report.push(format!("{message} {} = {}: {}", f.field, f.value, f.answer));
        }
    }
    println!("{total} requests in all");
    assert!(
        report.is_empty(),
        "{} of {total} extreme requests broke the rules:\n{}",
        report.len(),
        report.join("\n")
    );
    server.stop().await.unwrap();
}
