//! Request ids as a tower layer: each request keeps the caller's `x-request-id` (when it is a
//! sane token) or gets a fresh one; the id is echoed in the response headers and every log line
//! of the request carries it in its span, so a client's report can be matched to server logs.

use std::task::{Context, Poll};

use tonic::body::Body;
use tower::{Layer, Service};
use tracing::Instrument;

/// The request id header.
pub const REQUEST_ID: &str = "x-request-id";

/// The id of a request, in its extensions.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RequestId(pub String);

/// The caller's id if it is 1–128 visible ASCII characters; otherwise none.
fn callers_id(headers: &http::HeaderMap) -> Option<String> {
    let v = headers.get(REQUEST_ID)?.to_str().ok()?;
    (!v.is_empty() && v.len() <= 128 && v.bytes().all(|b| b.is_ascii_graphic()))
        .then(|| v.to_string())
}

fn fresh_id() -> String {
    format!("{:032x}", rand::random::<u128>())
}

/// Installs [`RequestIdService`].
#[derive(Clone, Copy, Debug, Default)]
pub struct RequestIdLayer;

impl<S> Layer<S> for RequestIdLayer {
    type Service = RequestIdService<S>;
    fn layer(&self, inner: S) -> Self::Service {
        RequestIdService { inner }
    }
}

/// See [`RequestIdLayer`].
#[derive(Clone, Debug)]
pub struct RequestIdService<S> {
    inner: S,
}

impl<S> Service<http::Request<Body>> for RequestIdService<S>
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

    fn call(&mut self, mut req: http::Request<Body>) -> Self::Future {
        let mut inner = super::take_ready(&mut self.inner);
        let id = callers_id(req.headers()).unwrap_or_else(fresh_id);
        let span = tracing::info_span!(
            "rpc",
            request_id = %id,
            method = %req.uri().path().trim_start_matches('/')
        );
        req.extensions_mut().insert(RequestId(id.clone()));
        Box::pin(
            async move {
                let mut response = inner.call(req).await?;
                if let Ok(v) = http::HeaderValue::from_str(&id) {
                    response.headers_mut().insert(REQUEST_ID, v);
                }
                Ok(response)
            }
            .instrument(span),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_sane_ids_and_replaces_others() {
        let mut h = http::HeaderMap::new();
        assert_eq!(callers_id(&h), None);
        h.insert(REQUEST_ID, "trip-42/frame-7".parse().unwrap());
        assert_eq!(callers_id(&h).as_deref(), Some("trip-42/frame-7"));
        h.insert(REQUEST_ID, "a b".parse().unwrap());
        assert_eq!(callers_id(&h), None);
        h.insert(REQUEST_ID, "x".repeat(129).parse().unwrap());
        assert_eq!(callers_id(&h), None);
        assert_eq!(fresh_id().len(), 32);
    }
}
