//! Bearer-token authentication and tenants, as a tower layer in front of every gRPC service.
//!
//! The token file has one `TENANT TOKEN` pair per line (`#` starts a comment). A request carries
//! `authorization: Bearer TOKEN`; a known token puts its [`Tenant`] into the request's extensions,
//! where the handlers read it to scope job records. A missing or unknown token is answered
//! UNAUTHENTICATED before any handler runs. Health checks and reflection stay open so load
//! balancers and tools such as grpcurl work without credentials.
//!
//! Tokens are stored as SHA-256 digests and every lookup compares the presented token's digest
//! with *every* stored digest in constant time, so neither the position of a match nor the
//! length of a common prefix shows in the response time.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};
use std::task::{Context, Poll};

use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;
use thiserror::Error;
use tonic::body::Body;
use tower::{Layer, Service};

use super::grpc_metrics::GrpcMetrics;

/// The authenticated caller, in the request extensions. Without authentication every caller is
/// the default tenant `""`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Tenant(pub String);

impl Tenant {
    /// The tenant of a request: the authenticated one, else the default tenant `""`.
    pub fn of<T>(request: &tonic::Request<T>) -> String {
        request
            .extensions()
            .get::<Tenant>()
            .map(|t| t.0.clone())
            .unwrap_or_default()
    }
}

/// Shortest token accepted: 16 characters (e.g. `openssl rand -hex 16` gives 32).
pub const MIN_TOKEN_LEN: usize = 16;

/// A token file that cannot be used.
#[derive(Debug, Error)]
pub enum TokenFileError {
    /// The file could not be read.
    #[error("reading token file {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A line is malformed.
    #[error("token file line {line}: {reason}")]
    Line {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// No token at all: every request would be refused.
    #[error("token file has no `TENANT TOKEN` lines")]
    Empty,
}

#[derive(Debug)]
struct Entry {
    tenant: String,
    digest: [u8; 32],
}

/// The tokens in force; re-read from their file on demand (SIGHUP in `murk serve`).
#[derive(Clone, Debug)]
pub struct TokenStore {
    path: Option<PathBuf>,
    entries: Arc<RwLock<Arc<Vec<Entry>>>>,
}

impl TokenStore {
    /// Reads `path` (see the module docs for the format).
    pub fn from_file(path: &Path) -> Result<Self, TokenFileError> {
        let entries = read_file(path)?;
        Ok(Self {
            path: Some(path.to_path_buf()),
            entries: Arc::new(RwLock::new(Arc::new(entries))),
        })
    }

    /// Tokens given in the file format directly (tests, embedding).
    pub fn from_text(text: &str) -> Result<Self, TokenFileError> {
        Ok(Self {
            path: None,
            entries: Arc::new(RwLock::new(Arc::new(parse(text)?))),
        })
    }

    /// Re-reads the file. On error the tokens in force stay unchanged. Returns the number of
    /// tokens now in force.
    pub fn reload(&self) -> Result<usize, TokenFileError> {
        let Some(path) = &self.path else {
            return Ok(self.len());
        };
        let fresh = Arc::new(read_file(path)?);
        let n = fresh.len();
        *self.entries.write().unwrap_or_else(|p| p.into_inner()) = fresh;
        Ok(n)
    }

    /// Number of tokens in force.
    pub fn len(&self) -> usize {
        self.snapshot().len()
    }

    /// True when no token is in force (never after a successful load).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn snapshot(&self) -> Arc<Vec<Entry>> {
        self.entries
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The tenant owning `token`, comparing against every stored token in constant time.
    pub fn authenticate(&self, token: &[u8]) -> Option<String> {
        let digest: [u8; 32] = Sha256::digest(token).into();
        let entries = self.snapshot();
        let mut found = None;
        for e in entries.iter() {
            // No early exit: every entry is compared whatever matched before.
            if bool::from(e.digest.ct_eq(&digest)) {
                found = Some(e.tenant.clone());
            }
        }
        found
    }
}

fn read_file(path: &Path) -> Result<Vec<Entry>, TokenFileError> {
    let text = std::fs::read_to_string(path).map_err(|source| TokenFileError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse(&text)
}

fn parse(text: &str) -> Result<Vec<Entry>, TokenFileError> {
    let mut entries = Vec::new();
    let mut seen = HashSet::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let bad = |reason: String| TokenFileError::Line {
            line: i + 1,
            reason,
        };
        let mut parts = line.split_whitespace();
        let (Some(tenant), Some(token), None) = (parts.next(), parts.next(), parts.next()) else {
            return Err(bad("expected `TENANT TOKEN`".into()));
        };
        if tenant.len() > 64
            || !tenant
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b))
        {
            return Err(bad(format!(
                "tenant `{tenant}` must be 1-64 characters of A-Z a-z 0-9 . _ -"
            )));
        }
        if token.len() < MIN_TOKEN_LEN {
            return Err(bad(format!(
                "token of tenant `{tenant}` is shorter than {MIN_TOKEN_LEN} characters"
            )));
        }
        let digest: [u8; 32] = Sha256::digest(token.as_bytes()).into();
        if !seen.insert(digest) {
            return Err(bad("token appears twice".into()));
        }
        entries.push(Entry {
            tenant: tenant.to_string(),
            digest,
        });
    }
    if entries.is_empty() {
        return Err(TokenFileError::Empty);
    }
    Ok(entries)
}

/// Paths that never need a token: health checks (load balancers, orchestrators) and
/// reflection (service discovery by grpcurl and friends).
fn is_open(path: &str) -> bool {
    path.starts_with("/grpc.health.v1.Health/") || path.starts_with("/grpc.reflection.")
}

/// The bearer token of a request, if it carries one.
fn bearer(req: &http::Request<Body>) -> Option<&[u8]> {
    let v = req.headers().get(http::header::AUTHORIZATION)?.as_bytes();
    let (scheme, token) = v.split_at(v.iter().position(|&b| b == b' ')?);
    scheme
        .eq_ignore_ascii_case(b"bearer")
        .then(|| token.trim_ascii())
}

/// Installs [`AuthService`]; with no store every request passes as the default tenant. Each
/// request that passes (health checks and reflection aside) is counted per tenant in
/// `murk_tenant_requests_total`.
#[derive(Clone, Debug, Default)]
pub struct AuthLayer {
    store: Option<TokenStore>,
    metrics: GrpcMetrics,
}

impl AuthLayer {
    /// Authentication with `store`, or none, counting requests into `metrics`.
    pub fn new(store: Option<TokenStore>, metrics: GrpcMetrics) -> Self {
        Self { store, metrics }
    }
}

impl<S> Layer<S> for AuthLayer {
    type Service = AuthService<S>;
    fn layer(&self, inner: S) -> Self::Service {
        AuthService {
            inner,
            store: self.store.clone(),
            metrics: self.metrics.clone(),
        }
    }
}

/// See [`AuthLayer`].
#[derive(Clone, Debug)]
pub struct AuthService<S> {
    inner: S,
    store: Option<TokenStore>,
    metrics: GrpcMetrics,
}

impl<S> Service<http::Request<Body>> for AuthService<S>
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
        let open = is_open(req.uri().path());
        if self.store.is_none() && !open {
            self.metrics.tenant_request("");
        }
        if let Some(store) = &self.store {
            if !open {
                let tenant = bearer(&req).and_then(|t| store.authenticate(t));
                match tenant {
                    Some(t) => {
                        self.metrics.tenant_request(&t);
                        req.extensions_mut().insert(Tenant(t));
                    }
                    None => {
                        let message = if req.headers().contains_key(http::header::AUTHORIZATION) {
                            "unknown bearer token"
                        } else {
                            "missing `authorization: Bearer TOKEN` metadata"
                        };
                        let status = tonic::Status::unauthenticated(message);
                        return Box::pin(async move { Ok(status.into_http()) });
                    }
                }
            }
        }
        Box::pin(inner.call(req))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_comments_and_finds_tenants() {
        let store = TokenStore::from_text(
            "# fleet tokens\nalpha 0123456789abcdef0123\n\n  beta   fedcba9876543210fedc  # ops\n",
        )
        .unwrap();
        assert_eq!(store.len(), 2);
        assert_eq!(
            store.authenticate(b"0123456789abcdef0123").as_deref(),
            Some("alpha")
        );
        assert_eq!(
            store.authenticate(b"fedcba9876543210fedc").as_deref(),
            Some("beta")
        );
        assert_eq!(store.authenticate(b"0123456789abcdef012"), None);
        assert_eq!(store.authenticate(b""), None);
    }

    #[test]
    fn malformed_files_name_the_line() {
        for (text, line) in [
            ("alpha\n", 1),
            ("a 0123456789abcdef\nb short\n", 2),
            ("bad/tenant 0123456789abcdef\n", 1),
            ("a 0123456789abcdef\nb 0123456789abcdef\n", 2),
            ("a 0123456789abcdef extra\n", 1),
        ] {
            match TokenStore::from_text(text) {
                Err(TokenFileError::Line { line: l, .. }) => assert_eq!(l, line, "{text:?}"),
                other => panic!("{text:?}: {other:?}"),
            }
        }
        assert!(matches!(
            TokenStore::from_text("# nothing\n"),
            Err(TokenFileError::Empty)
        ));
    }

    #[test]
    fn reload_swaps_tokens_and_keeps_them_on_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tokens");
        std::fs::write(&path, "a 0123456789abcdef\n").unwrap();
        let store = TokenStore::from_file(&path).unwrap();
        std::fs::write(&path, "b fedcba9876543210\n").unwrap();
        assert_eq!(store.reload().unwrap(), 1);
        assert_eq!(store.authenticate(b"0123456789abcdef"), None);
        assert_eq!(
            store.authenticate(b"fedcba9876543210").as_deref(),
            Some("b")
        );
        std::fs::write(&path, "broken\n").unwrap();
        assert!(store.reload().is_err());
        assert_eq!(
            store.authenticate(b"fedcba9876543210").as_deref(),
            Some("b")
        );
    }

    #[test]
    fn bearer_scheme_is_case_insensitive() {
        let req = http::Request::builder()
            .header("authorization", "bearer  tok123")
            .body(Body::empty())
            .unwrap();
        assert_eq!(bearer(&req), Some(&b"tok123"[..]));
        let basic = http::Request::builder()
            .header("authorization", "Basic dXNlcg==")
            .body(Body::empty())
            .unwrap();
        assert_eq!(bearer(&basic), None);
    }
}
