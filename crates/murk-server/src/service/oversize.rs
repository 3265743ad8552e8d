//! One limit and one answer for requests that are too large.
//!
//! The transport enforces `--max-request-bytes` on every request message as it arrives (its
//! length prefix, or what it decompresses to), before anything is decoded: unknown fields and
//! padding count like any other byte. tonic refuses such a message with OUT_OF_RANGE (length
//! prefix) or RESOURCE_EXHAUSTED (decompression), each with its own wording. This layer turns
//! both into the answer gRPC implementations give for an oversize message, RESOURCE_EXHAUSTED,
//! with a message that states the size and the setting. There is no RetryInfo: sending the
//! same request again cannot succeed.

use tonic::body::Body;
use tonic::{Code, Status};
use tower::util::MapResponseLayer;

/// tonic's wording for a length prefix over the limit (`codec/decode.rs`).
const LENGTH_OVER: &str = "Error, decoded message length too large: found ";
/// tonic's wording for a message that decompresses past the limit.
const DECOMPRESSED_OVER: &str = "Error decompressing: size limit";

/// murk's status for a request message over the server's limit, when `s` is tonic's refusal of
/// one; `None` for any other status. The sizes come from tonic's own message, so the sessions'
/// inbound stream and this layer give the same answer without knowing the configuration.
pub fn oversize_request(s: &Status) -> Option<Status> {
    let message = s.message();
    // The first number after `marker` in the message.
    let number_after = |marker: &str| {
        let at = message.find(marker)? + marker.len();
        message[at..]
            .split(|c: char| !c.is_ascii_digit())
            .find(|t| !t.is_empty())
            .and_then(|n| n.parse::<u64>().ok())
    };
    let (what, limit) = match s.code() {
        Code::OutOfRange if message.starts_with(LENGTH_OVER) => (
            format!("request message is {} bytes", number_after("found")?),
            number_after("limit is")?,
        ),
        Code::ResourceExhausted if message.starts_with(DECOMPRESSED_OVER) => (
            "request message decompresses to more bytes".to_string(),
            number_after("size limit")?,
        ),
        _ => return None,
    };
    Some(Status::resource_exhausted(format!(
        "{what} than this server accepts: {limit} bytes (murk serve --max-request-bytes); send \
         fewer or smaller images, or encoded ones (PNG, EXR) instead of raw samples"
    )))
}

/// The layer that applies [`rewrite_oversize`] to every response.
pub type OversizeLayer = MapResponseLayer<fn(http::Response<Body>) -> http::Response<Body>>;

/// [`OversizeLayer`], ready for `Server::layer`.
pub fn oversize_layer() -> OversizeLayer {
    MapResponseLayer::new(rewrite_oversize as fn(_) -> _)
}

/// Replaces tonic's refusal of an oversize request message with [`oversize_request`]'s status.
/// A request message is decoded before the handler runs, so that refusal is always a
/// trailers-only response: its status is in the headers. Other responses pass untouched.
pub fn rewrite_oversize(mut response: http::Response<Body>) -> http::Response<Body> {
    let replaced = Status::from_header_map(response.headers()).and_then(|s| oversize_request(&s));
    if let Some(status) = replaced {
        let headers = response.headers_mut();
        headers.remove("grpc-status-details-bin");
        // Sets grpc-status and grpc-message, replacing tonic's.
        if status.add_header(headers).is_err() {
            tracing::warn!("could not rewrite an oversize-request status");
        }
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_trailers_only_refusal_is_rewritten_and_other_responses_pass() {
        let refusal = Status::out_of_range(
            "Error, decoded message length too large: found 9 bytes, the limit is: 4 bytes",
        )
        .into_http::<Body>();
        let got = Status::from_header_map(rewrite_oversize(refusal).headers()).unwrap();
        assert_eq!(got.code(), Code::ResourceExhausted);
        assert!(got.message().contains("9 bytes"), "{}", got.message());
        let other = Status::not_found("no job").into_http::<Body>();
        let got = Status::from_header_map(rewrite_oversize(other).headers()).unwrap();
        assert_eq!((got.code(), got.message()), (Code::NotFound, "no job"));
        let ok = http::Response::new(Body::empty());
        assert!(rewrite_oversize(ok).headers().is_empty());
    }

    #[test]
    fn tonic_refusals_become_resource_exhausted_and_others_pass() {
        let length = Status::out_of_range(
            "Error, decoded message length too large: found 300000 bytes, the limit is: 262144 bytes",
        );
        let s = oversize_request(&length).unwrap();
        assert_eq!(s.code(), Code::ResourceExhausted);
        assert!(s.message().contains("300000 bytes"), "{}", s.message());
        assert!(s.message().contains("262144"), "{}", s.message());
        let inflated = Status::resource_exhausted(
            "Error decompressing: size limit, of 262144 bytes, exceeded while decompressing message",
        );
        let s = oversize_request(&inflated).unwrap();
        assert_eq!(s.code(), Code::ResourceExhausted);
        assert!(s.message().contains("262144 bytes"), "{}", s.message());
        assert!(
            s.message().contains("--max-request-bytes"),
            "{}",
            s.message()
        );
        for other in [
            Status::out_of_range("page beyond the end"),
            Status::resource_exhausted("job queue is full"),
            Status::invalid_argument("Error, decoded message length too large: found 1 bytes"),
        ] {
            assert!(oversize_request(&other).is_none(), "{other:?}");
        }
    }
}
