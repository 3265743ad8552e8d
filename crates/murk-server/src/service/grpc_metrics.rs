//! Per-RPC metrics as a tower layer: `murk_grpc_requests_total{method,code}` and
//! `murk_grpc_request_duration_seconds{method}`; and `murk_tenant_requests_total{tenant}`,
//! counted by the authentication layer, which knows the tenant.
//!
//! The status code of a gRPC response is in its headers when the handler failed at once
//! (a trailers-only response) and in its trailers otherwise, after the last message; the layer
//! reads the headers and, failing that, watches the body for the trailers. A body dropped before
//! its trailers (the client went away mid-stream) counts as CANCELLED.

use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Instant;

use bytes::Bytes;
use http_body::{Body as HttpBody, Frame, SizeHint};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use tonic::body::Body;
use tonic::Code;
use tower::{Layer, Service};

/// Labels of `murk_grpc_requests_total`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RpcCode {
    /// `package.Service/Method`, or `other` (see [`method_label`]).
    pub method: &'static str,
    /// gRPC status code name (`OK`, `INVALID_ARGUMENT`, ...).
    pub code: &'static str,
}

/// Labels of `murk_grpc_request_duration_seconds`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RpcMethod {
    /// `package.Service/Method`, or `other`.
    pub method: &'static str,
}

/// Labels of `murk_tenant_requests_total`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct TenantLabel {
    /// The authenticated tenant, or [`NO_TENANT`] without authentication. Tenants come from the
    /// operator's token file, so the label set is bounded by it.
    pub tenant: String,
}

/// The tenant label of requests served without authentication (not a valid tenant name, so it
/// cannot collide with one).
pub const NO_TENANT: &str = "(none)";

/// Every RPC the server serves. Paths outside this list are counted as `other`: the layer sits
/// in front of authentication, so a label per arbitrary path would let anyone grow the metric
/// set without bound.
const METHODS: &[&str] = &[
    "murk.v1.Jobs/SubmitJob",
    "murk.v1.Jobs/GetJob",
    "murk.v1.Jobs/WatchJob",
    "murk.v1.Jobs/CancelJob",
    "murk.v1.Jobs/ListJobs",
    "murk.v1.Jobs/GetJobResult",
    "murk.v1.Reconstruction/TofDepth",
    "murk.v1.Reconstruction/MvsDepth",
    "murk.v1.Reconstruction/ScatteringParams",
    "murk.v1.Reconstruction/PhotometricStereo",
    "murk.v1.Reconstruction/RectifiedStereo",
    "murk.v1.Sessions/Stream",
    "grpc.health.v1.Health/Check",
    "grpc.health.v1.Health/Watch",
    "grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
    "grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
];

/// The metric label of a request path: the method's name when murk serves it, else `other`.
pub fn method_label(path: &str) -> &'static str {
    let name = path.trim_start_matches('/');
    METHODS
        .iter()
        .find(|m| **m == name)
        .copied()
        .unwrap_or("other")
}

fn latency_histogram() -> Histogram {
    // 0.1 ms … ~100 s: cache-hit round trips up to long unary waits.
    Histogram::new(exponential_buckets(1e-4, 2.5, 16))
}

/// The RPC metric families. Cheap to clone (shared).
#[derive(Clone, Debug)]
pub struct GrpcMetrics {
    requests: Family<RpcCode, Counter>,
    duration: Family<RpcMethod, Histogram, fn() -> Histogram>,
    tenants: Family<TenantLabel, Counter>,
}

impl Default for GrpcMetrics {
    fn default() -> Self {
        Self {
            requests: Family::default(),
            duration: Family::new_with_constructor(latency_histogram),
            tenants: Family::default(),
        }
    }
}

impl GrpcMetrics {
    /// Registers the families (names relative to the registry's `murk` prefix).
    pub fn register(&self, registry: &mut Registry) {
        registry.register(
            "grpc_requests",
            "gRPC requests by method and status code",
            self.requests.clone(),
        );
        registry.register(
            "grpc_request_duration_seconds",
            "Time from request headers to the status, by method (streams: until the stream ends)",
            self.duration.clone(),
        );
        registry.register(
            "tenant_requests",
            "RPCs that passed authentication, by tenant ((none) without authentication; health \
             checks and reflection are not counted)",
            self.tenants.clone(),
        );
    }

    /// Counts one authenticated request of `tenant` (`""`: no authentication).
    pub fn tenant_request(&self, tenant: &str) {
        let tenant = if tenant.is_empty() { NO_TENANT } else { tenant };
        self.tenants
            .get_or_create(&TenantLabel {
                tenant: tenant.to_string(),
            })
            .inc();
    }

    fn record(&self, method: &'static str, code: Code, started: Instant) {
        self.requests
            .get_or_create(&RpcCode {
                method,
                code: code_name(code),
            })
            .inc();
        self.duration
            .get_or_create(&RpcMethod { method })
            .observe(started.elapsed().as_secs_f64());
    }
}

/// The canonical upper-case name of a gRPC code, as other gRPC metrics use it.
pub fn code_name(code: Code) -> &'static str {
    match code {
        Code::Ok => "OK",
        Code::Cancelled => "CANCELLED",
        Code::Unknown => "UNKNOWN",
        Code::InvalidArgument => "INVALID_ARGUMENT",
        Code::DeadlineExceeded => "DEADLINE_EXCEEDED",
        Code::NotFound => "NOT_FOUND",
        Code::AlreadyExists => "ALREADY_EXISTS",
        Code::PermissionDenied => "PERMISSION_DENIED",
        Code::ResourceExhausted => "RESOURCE_EXHAUSTED",
        Code::FailedPrecondition => "FAILED_PRECONDITION",
        Code::Aborted => "ABORTED",
        Code::OutOfRange => "OUT_OF_RANGE",
        Code::Unimplemented => "UNIMPLEMENTED",
        Code::Internal => "INTERNAL",
        Code::Unavailable => "UNAVAILABLE",
        Code::DataLoss => "DATA_LOSS",
        Code::Unauthenticated => "UNAUTHENTICATED",
    }
}

fn status_code(headers: &http::HeaderMap) -> Option<Code> {
    headers
        .get("grpc-status")
        .map(|v| Code::from_bytes(v.as_bytes()))
}

/// Installs [`MetricsService`].
#[derive(Clone, Debug)]
pub struct MetricsLayer {
    metrics: GrpcMetrics,
}

impl MetricsLayer {
    /// Records into `metrics`.
    pub fn new(metrics: GrpcMetrics) -> Self {
        Self { metrics }
    }
}

impl<S> Layer<S> for MetricsLayer {
    type Service = MetricsService<S>;
    fn layer(&self, inner: S) -> Self::Service {
        MetricsService {
            inner,
            metrics: self.metrics.clone(),
        }
    }
}

/// See [`MetricsLayer`].
#[derive(Clone, Debug)]
pub struct MetricsService<S> {
    inner: S,
    metrics: GrpcMetrics,
}

impl<S> Service<http::Request<Body>> for MetricsService<S>
where
    S: Service<http::Request<Body>, Response = http::Response<Body>> + Clone + Send + 'static,
    S::Future: Send + 'static,
{
    type Response = http::Response<Body>;
    type Error = S::Error;
    type Future = super::BoxFuture<Self::Response, Self::Error>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<Body>) -> Self::Future {
        let mut inner = super::take_ready(&mut self.inner);
        let metrics = self.metrics.clone();
        let method = method_label(req.uri().path());
        let started = Instant::now();
        Box::pin(async move {
            let response = inner.call(req).await?;
            if let Some(code) = status_code(response.headers()) {
                metrics.record(method, code, started);
                return Ok(response);
            }
            let (parts, body) = response.into_parts();
            let body = MeteredBody {
                inner: body,
                pending: Some(Pending {
                    metrics,
                    method,
                    started,
                }),
            };
            Ok(http::Response::from_parts(parts, Body::new(body)))
        })
    }
}

struct Pending {
    metrics: GrpcMetrics,
    method: &'static str,
    started: Instant,
}

/// A response body that records the status from its trailers (or CANCELLED when dropped
/// before them).
struct MeteredBody {
    inner: Body,
    pending: Option<Pending>,
}

impl MeteredBody {
    fn record(&mut self, code: Code) {
        if let Some(p) = self.pending.take() {
            p.metrics.record(p.method, code, p.started);
        }
    }
}

impl HttpBody for MeteredBody {
    type Data = Bytes;
    type Error = tonic::Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        let polled = Pin::new(&mut self.inner).poll_frame(cx);
        match &polled {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(code) = frame.trailers_ref().and_then(status_code) {
                    self.record(code);
                }
            }
            Poll::Ready(Some(Err(_))) => self.record(Code::Internal),
            Poll::Ready(None) => self.record(Code::Ok),
            Poll::Pending => {}
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

impl Drop for MeteredBody {
    fn drop(&mut self) {
        self.record(Code::Cancelled);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_paths_share_one_label() {
        assert_eq!(
            method_label("/murk.v1.Jobs/SubmitJob"),
            "murk.v1.Jobs/SubmitJob"
        );
        assert_eq!(method_label("/murk.v1.Jobs/Nope"), "other");
        assert_eq!(method_label("/x/y/z"), "other");
    }

    #[test]
    fn requests_are_counted_per_tenant_and_the_default_tenant_has_its_own_label() {
        let m = GrpcMetrics::default();
        let mut registry = Registry::with_prefix("murk");
        m.register(&mut registry);
        m.tenant_request("fleet-a");
        m.tenant_request("fleet-a");
        m.tenant_request("");
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &registry).unwrap();
        assert!(
            text.contains("murk_tenant_requests_total{tenant=\"fleet-a\"} 2"),
            "{text}"
        );
        assert!(
            text.contains("murk_tenant_requests_total{tenant=\"(none)\"} 1"),
            "{text}"
        );
    }
}
