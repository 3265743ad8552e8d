//! The library's one error type. The service layer maps it to `tonic::Status` in exactly one place
//! (`service::status`), so every algorithm reports bad input the same way: with the field named.

use thiserror::Error;

/// Everything a murk algorithm or codec can fail with.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum MurkError {
    /// The caller supplied something unusable; `field` names it (e.g. `tof.amplitude`).
    #[error("invalid argument `{field}`: {reason}")]
    InvalidArgument {
        /// Dotted path of the offending request field.
        field: String,
        /// Human-readable explanation, including the offending value where helpful.
        reason: String,
    },
    /// The request is valid, but doing it would exceed a bound the caller configured on this
    /// process (memory, above all); `field` names the request field that sets the size
    /// (e.g. `support_r`). A smaller request, or a server with a larger bound, does it.
    #[error("over the limit `{field}`: {reason}")]
    OverLimit {
        /// Dotted path of the request field that makes the work too large.
        field: String,
        /// What the work needs against the bound, and how to fit within it.
        reason: String,
    },
    /// The job was cancelled cooperatively (cancel RPC, shutdown, or the caller went away).
    #[error("cancelled")]
    Cancelled,
    /// The server stopped the job because it is shutting down; resubmitting it (to this
    /// server after its restart, or to another replica) runs it again.
    #[error("server shutting down, resubmit")]
    ShuttingDown,
    /// A numerical step failed on valid input (e.g. a solver diverged).
    #[error("numerical failure: {0}")]
    Numerical(String),
    /// A bug or an unexpected condition inside murk (e.g. a worker panicked).
    #[error("internal error: {0}")]
    Internal(String),
    /// A job's stored input was lost (e.g. its journal entry was damaged on disk), so it can
    /// neither run nor be rebuilt; resubmitting it runs it again.
    #[error("data lost: {0}; resubmit the job")]
    DataLoss(String),
    /// Reading or writing a file failed.
    #[error("i/o error on {path}: {reason}")]
    Io {
        /// The file concerned.
        path: String,
        /// The underlying error.
        reason: String,
    },
}

impl MurkError {
    /// Shorthand for [`MurkError::InvalidArgument`].
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        MurkError::InvalidArgument {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// Shorthand for [`MurkError::OverLimit`].
    pub fn over_limit(field: impl Into<String>, reason: impl Into<String>) -> Self {
        MurkError::OverLimit {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// The field an `InvalidArgument` or `OverLimit` names; `None` for other errors.
    pub fn field(&self) -> Option<&str> {
        match self {
            MurkError::InvalidArgument { field, .. } | MurkError::OverLimit { field, .. } => {
                Some(field)
            }
            _ => None,
        }
    }

    /// Prefixes the field of an `InvalidArgument` or `OverLimit` with `prefix.` so nested
    /// validators can name fields relative to themselves and callers add the outer path.
    pub fn within(self, prefix: &str) -> Self {
        let nest = |field: String| {
            if field.is_empty() {
                prefix.to_string()
            } else {
                format!("{prefix}.{field}")
            }
        };
        match self {
            MurkError::InvalidArgument { field, reason } => MurkError::InvalidArgument {
                field: nest(field),
                reason,
            },
            MurkError::OverLimit { field, reason } => MurkError::OverLimit {
                field: nest(field),
                reason,
            },
            other => other,
        }
    }
}

/// Test helper: the field an `InvalidArgument` names; panics on any other error.
#[cfg(test)]
pub(crate) fn field_of(e: MurkError) -> String {
    match e.field() {
        Some(f) => f.to_string(),
        None => panic!("expected InvalidArgument, got {e:?}"),
    }
}

/// Result alias used throughout the library.
pub type Result<T, E = MurkError> = std::result::Result<T, E>;
