//! A job's error as three strings (kind and two details), for stores outside the process: the
//! Redis job records and the embedded default's record log.

use murk::error::MurkError;

/// `(kind, a, b)` of an error, as the record stores it.
pub(crate) fn encode_error(e: &MurkError) -> (&'static str, String, String) {
    match e {
        MurkError::InvalidArgument { field, reason } => ("invalid", field.clone(), reason.clone()),
        MurkError::OverLimit { field, reason } => ("over_limit", field.clone(), reason.clone()),
        MurkError::Cancelled => ("cancelled", String::new(), String::new()),
        MurkError::ShuttingDown => ("shutting_down", String::new(), String::new()),
        MurkError::Numerical(m) => ("numerical", m.clone(), String::new()),
        MurkError::Internal(m) => ("internal", m.clone(), String::new()),
        MurkError::Io { path, reason } => ("io", path.clone(), reason.clone()),
        MurkError::DataLoss(m) => ("data_loss", m.clone(), String::new()),
    }
}

/// Inverse of [`encode_error`]; an unknown kind (a newer version's) reads as internal.
pub(crate) fn decode_error(kind: &str, a: &str, b: &str) -> MurkError {
    match kind {
        "invalid" => MurkError::invalid(a, b),
        "over_limit" => MurkError::over_limit(a, b),
        "cancelled" | "" => MurkError::Cancelled,
        "shutting_down" => MurkError::ShuttingDown,
        "numerical" => MurkError::Numerical(a.to_string()),
        "data_loss" => MurkError::DataLoss(a.to_string()),
        "io" => MurkError::Io {
            path: a.to_string(),
            reason: b.to_string(),
        },
        _ => MurkError::Internal(a.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_error_survives_the_record() {
        for e in [
            MurkError::invalid("phase", "must be finite"),
            MurkError::over_limit("support_r", "needs 5 GB"),
            MurkError::Cancelled,
            MurkError::ShuttingDown,
            MurkError::Numerical("diverged".into()),
            MurkError::DataLoss("journal entry corrupted".into()),
            MurkError::Internal("panic".into()),
            MurkError::Io {
                path: "/x".into(),
                reason: "gone".into(),
            },
        ] {
            let (k, a, b) = encode_error(&e);
            assert_eq!(decode_error(k, &a, &b), e);
        }
    }
}
