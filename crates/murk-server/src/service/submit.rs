//! Shared path of every submission (Jobs.SubmitJob and the unary RPCs): canonical form, size
//! check, content-hash id, dedupe/cache lookup before any decoding, then decode + validate +
//! queue.

use std::time::Instant;

use prost::Message;
use sha2::{Digest, Sha256};
use tonic::Status;

use super::convert::{
    canonicalize_mvs_request, canonicalize_params_request, canonicalize_ps_request,
    canonicalize_stereo_request, mvs_from_proto, mvs_to_proto, params_from_proto, ps_from_proto,
    ps_to_proto, stereo_from_proto, stereo_to_proto, tof_from_proto, tof_to_proto, AirlightService,
    ImageLimits,
};
use super::proto::v1 as pb;
use super::status::{submit_status, to_status};
use crate::jobs::{JobBackend, Submitted, Work};
use murk::error::MurkError;
use murk::tof::estimate_tof_depth;

/// Bumped whenever an algorithm's output for the same request may change, so cached results of
/// older code are never served for new submissions.
pub const ALGORITHM_VERSION: &str = "murk-algorithms-20";

/// Limits enforced per request. (The request size itself is the transport's: see
/// `service::oversize`.)
#[derive(Clone, Copy, Debug)]
pub struct RequestLimits {
    /// Per-image limits.
    pub images: ImageLimits,
    /// Largest forward-scatter kernel a photometric-stereo job may store, bytes.
    pub max_ps_kernel_bytes: usize,
}

/// Default unary result limit: gRPC's default client receive limit (4 MiB).
pub const DEFAULT_MAX_UNARY_RESULT_BYTES: usize = 4 << 20;

/// What every gRPC handler shares.
#[derive(Clone)]
pub struct ServiceState {
    /// The job system (embedded, or shared through Redis).
    pub jobs: std::sync::Arc<dyn JobBackend>,
    /// Request limits.
    pub limits: RequestLimits,
    /// Largest message a unary response may carry (a Job with its result, or a Reconstruction
    /// result); larger results are left out of Jobs messages and refused by the Reconstruction
    /// RPCs, pointing to `Jobs.GetJobResult`.
    pub max_unary_result_bytes: usize,
    /// The airlight estimators (scattering-parameter requests).
    pub airlight: AirlightService,
    /// Whose identical requests share results.
    pub cache_scope: CacheScope,
}

/// Whose identical requests share a job and its cached result.
///
/// With `Global`, tenant B's request identical to tenant A's finished one is answered from the
/// cache at once (`cached = true`), which tells B that somebody ran that exact input: a side
/// channel between tenants, traded for compute. With `Tenant`, each tenant's requests have job
/// ids of their own (the id's hash covers the tenant), so nothing is shared and nothing is
/// learned. The default tenant (no authentication) is the same under both.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum CacheScope {
    /// Results are shared only within a tenant.
    Tenant,
    /// Results are shared between tenants.
    Global,
}

impl CacheScope {
    /// The scope a server uses unless configured: per tenant when it authenticates clients
    /// (tenants exist to be kept apart), global otherwise (there is only one tenant).
    pub fn default_for(authenticated: bool) -> Self {
        if authenticated {
            CacheScope::Tenant
        } else {
            CacheScope::Global
        }
    }
}

/// Hex SHA-256 over the algorithm version, `model` (the identity of any learned model the
/// request uses, empty otherwise) and the request's protobuf encoding. prost encodes fields in
/// tag order and murk's messages have no maps, so equal requests hash equally; the model part
/// keeps results computed with other weights (another replica's, or before a redeploy) from
/// being served from a shared cache. Under [`CacheScope::Tenant`] an authenticated `tenant` is
/// hashed too, so its ids (and cached results) are its own; the default tenant's ids are the
/// same under both scopes.
pub fn job_id(req: &pb::JobRequest, model: &str, tenant: &str, scope: CacheScope) -> String {
    job_id_of_encoded(&req.encode_to_vec(), model, tenant, scope)
}

/// [`job_id`] of a request already encoded (the submit path keeps the bytes for the journal).
fn job_id_of_encoded(encoded: &[u8], model: &str, tenant: &str, scope: CacheScope) -> String {
    let mut h = Sha256::new();
    h.update(ALGORITHM_VERSION.as_bytes());
    h.update([0u8]);
    h.update(model.as_bytes());
    h.update([0u8]);
    if scope == CacheScope::Tenant && !tenant.is_empty() {
        // Length-prefixed, so no tenant name can collide with another's plus request bytes.
        h.update(b"tenant");
        h.update((tenant.len() as u64).to_le_bytes());
        h.update(tenant.as_bytes());
    }
    h.update(encoded);
    hex::encode(h.finalize())
}

/// The learned model a (canonical) request depends on: the airlight CNN's digest for
/// scattering-parameter requests that use it, empty otherwise.
fn model_of(req: &pb::JobRequest, airlight: &AirlightService) -> String {
    match &req.method {
        Some(pb::job_request::Method::ScatteringParams(p))
            if p.airlight_source == pb::AirlightSource::Cnn as i32 =>
        {
            airlight.model_digest()
        }
        _ => String::new(),
    }
}

/// Method name of a request (`tof_depth`, ...).
pub fn method_name(m: &pb::job_request::Method) -> &'static str {
    match m {
        pb::job_request::Method::TofDepth(_) => "tof_depth",
        pb::job_request::Method::MvsDepth(_) => "mvs_depth",
        pb::job_request::Method::ScatteringParams(_) => "scattering_params",
        pb::job_request::Method::PhotometricStereo(_) => "photometric_stereo",
        pb::job_request::Method::RectifiedStereo(_) => "rectified_stereo",
    }
}

/// Validates, deduplicates and queues a request for `tenant`. Errors name fields relative to the method's
/// request message; `prefix` is where that message sits in the RPC's own message
/// (`Some("request")` for SubmitJob → `request.tof_depth.phase`; `None` for unary RPCs, whose
/// message *is* the method request → `phase`).
pub async fn submit(
    state: &ServiceState,
    tenant: &str,
    mut req: pb::JobRequest,
    prefix: Option<&str>,
) -> Result<Submitted, Status> {
    canonicalize(&mut req, &state.airlight);
    let Some(method) = req.method.as_ref() else {
        let e = MurkError::invalid("method", "one method (e.g. tof_depth) must be set");
        return Err(to_status(&prefix.map_or(e.clone(), |p| e.within(p))));
    };
    let name = method_name(method);
    let named = |e: MurkError| match prefix {
        Some(p) => e.within(&format!("{p}.{name}")),
        None => e,
    };
    // One encoding serves the content hash and, with a journal, the copy kept on disk until the
    // job ends.
    let encoded = req.encode_to_vec();
    let id = job_id_of_encoded(
        &encoded,
        &model_of(&req, &state.airlight),
        tenant,
        state.cache_scope,
    );
    if let Some(found) = state
        .jobs
        .find(tenant, &id, name)
        .await
        .map_err(|e| submit_status(&e))?
    {
        return Ok(found);
    }
    // Under overload, refuse before paying for decoding (the queue is checked again on insert).
    if state
        .jobs
        .queue_full()
        .await
        .map_err(|e| submit_status(&e))?
    {
        return Err(submit_status(&state.jobs.refusal()));
    }
    let limits = state.limits;
    let airlight = state.airlight.clone();
    let request = state.jobs.wants_request().then_some(encoded);
    // Decoding megapixel PNG/EXR is CPU work: keep it off the async runtime's threads.
    let work = tokio::task::spawn_blocking(move || build_work(req, &limits, &airlight))
        .await
        .map_err(|e| Status::internal(format!("decoder task failed: {e}")))?
        .map_err(|e| to_status(&named(e)))?;
    state
        .jobs
        .submit(tenant, &id, name, work, request)
        .await
        .map_err(|e| submit_status(&e))
}

/// Puts a request into its canonical form before hashing, so requests that mean the same
/// computation (an explicit default vs. an unset field) share one job id and cached result.
fn canonicalize(req: &mut pb::JobRequest, airlight: &AirlightService) {
    match &mut req.method {
        Some(pb::job_request::Method::MvsDepth(m)) => canonicalize_mvs_request(m),
        Some(pb::job_request::Method::ScatteringParams(p)) => {
            canonicalize_params_request(p, airlight)
        }
        // ToF ids hash the request as sent (its options are `optional` fields whose presence is
        // kept as sent).
        Some(pb::job_request::Method::PhotometricStereo(p)) => canonicalize_ps_request(p),
        Some(pb::job_request::Method::RectifiedStereo(s)) => canonicalize_stereo_request(s),
        Some(pb::job_request::Method::TofDepth(_)) | None => {}
    }
}

/// The work of a request from its canonical encoding: for `JobManager::recover` after a restart,
/// and for the replica that claims a job from the shared queue.
pub fn rebuild_work(
    bytes: &[u8],
    limits: &RequestLimits,
    airlight: &AirlightService,
) -> Result<Work, MurkError> {
    let req = pb::JobRequest::decode(bytes)
        .map_err(|e| MurkError::Internal(format!("journalled request does not decode: {e}")))?;
    build_work(req, limits, airlight)
}

/// Decodes and validates the request, returning the closure a worker will run.
fn build_work(
    req: pb::JobRequest,
    request_limits: &RequestLimits,
    airlight: &AirlightService,
) -> Result<Work, MurkError> {
    let limits = &request_limits.images;
    match req.method {
        Some(pb::job_request::Method::TofDepth(t)) => {
            let (input, params, outputs, points) = tof_from_proto(&t, limits)?;
            Ok(Box::new(move |monitor| {
                let out = estimate_tof_depth(&input, &params, monitor)?;
                let result = pb::JobResult {
                    method: Some(pb::job_result::Method::TofDepth(tof_to_proto(
                        &out,
                        &params,
                        &outputs,
                        points.as_ref(),
                    )?)),
                };
                Ok(result.encode_to_vec())
            }))
        }
        Some(pb::job_request::Method::MvsDepth(m)) => {
            // The job captures only the decoded input; the request's encoded images are freed
            // when this arm returns.
            let input = mvs_from_proto(&m, limits)?;
            Ok(Box::new(move |monitor| {
                let started = Instant::now();
                let out = input.estimate(monitor)?;
                let seconds = started.elapsed().as_secs_f64();
                let result = pb::JobResult {
                    method: Some(pb::job_result::Method::MvsDepth(mvs_to_proto(
                        &input, &out, seconds,
                    ))),
                };
                Ok(result.encode_to_vec())
            }))
        }
        Some(pb::job_request::Method::RectifiedStereo(s)) => {
            let input = stereo_from_proto(&s, limits)?;
            Ok(Box::new(move |monitor| {
                let started = Instant::now();
                let (out, points) = input.estimate(monitor)?;
                let seconds = started.elapsed().as_secs_f64();
                let result = pb::JobResult {
                    method: Some(pb::job_result::Method::RectifiedStereo(stereo_to_proto(
                        &input, &out, &points, seconds,
                    )?)),
                };
                Ok(result.encode_to_vec())
            }))
        }
        Some(pb::job_request::Method::ScatteringParams(p)) => {
            let input = params_from_proto(&p, limits, airlight)?;
            Ok(Box::new(move |monitor| {
                let result = pb::JobResult {
                    method: Some(pb::job_result::Method::ScatteringParams(
                        input.run(monitor)?,
                    )),
                };
                Ok(result.encode_to_vec())
            }))
        }
        Some(pb::job_request::Method::PhotometricStereo(p)) => {
            let (capture, params) = ps_from_proto(&p, limits, request_limits.max_ps_kernel_bytes)?;
            let with_history = p.return_iteration_normals;
            Ok(Box::new(move |monitor| {
                let out = murk::ps::photometric_stereo(&capture, &params, monitor)?;
                let result = pb::JobResult {
                    method: Some(pb::job_result::Method::PhotometricStereo(ps_to_proto(
                        &out,
                        with_history,
                    ))),
                };
                Ok(result.encode_to_vec())
            }))
        }
        None => Err(MurkError::invalid("method", "required")),
    }
}
