//! The one place where library errors become gRPC statuses.

use std::time::Duration;

use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

use super::proto::v1 as pb;
use crate::jobs::JobsError;
use murk::error::MurkError;

/// Maps a library error to a status. `InvalidArgument` carries a google.rpc.BadRequest field
/// violation so clients in any language can find the field programmatically; so does
/// `OverLimit` (RESOURCE_EXHAUSTED without RetryInfo: the same request will not fit later).
pub fn to_status(e: &MurkError) -> Status {
    match e {
        MurkError::InvalidArgument { field, reason } => Status::with_error_details(
            Code::InvalidArgument,
            e.to_string(),
            ErrorDetails::with_bad_request_violation(field.clone(), reason.clone()),
        ),
        MurkError::OverLimit { field, reason } => Status::with_error_details(
            Code::ResourceExhausted,
            e.to_string(),
            ErrorDetails::with_bad_request_violation(field.clone(), reason.clone()),
        ),
        MurkError::Cancelled => Status::cancelled("job was cancelled"),
        // Retryable: the work itself is fine, the server stopped it to shut down.
        MurkError::ShuttingDown => Status::with_error_details(
            Code::Unavailable,
            e.to_string(),
            ErrorDetails::with_retry_info(Some(Duration::from_secs(1))),
        ),
        // Not retryable as such: the job must be submitted again.
        MurkError::DataLoss(_) => Status::data_loss(e.to_string()),
        MurkError::Numerical(_) | MurkError::Internal(_) | MurkError::Io { .. } => {
            Status::internal(e.to_string())
        }
    }
}

/// The status of a job that ended without a result (failed, cancelled, or stopped by shutdown).
pub fn ended_without_result(snap: &crate::jobs::JobSnapshot) -> Status {
    snap.error
        .as_ref()
        .map(to_status)
        .unwrap_or_else(|| Status::cancelled("job was cancelled"))
}

/// gRPC code of a library error (for `JobError.code`).
pub fn code_of(e: &MurkError) -> Code {
    to_status(e).code()
}

/// A refused submission: queue full → RESOURCE_EXHAUSTED with google.rpc.RetryInfo.
pub fn submit_status(e: &JobsError) -> Status {
    match e {
        JobsError::QueueFull {
            capacity,
            retry_after,
        } => Status::with_error_details(
            Code::ResourceExhausted,
            format!("job queue is full ({capacity} jobs waiting); retry after {retry_after:?}"),
            ErrorDetails::with_retry_info(Some(*retry_after)),
        ),
        JobsError::ShuttingDown => to_status(&MurkError::ShuttingDown),
        JobsError::Unavailable(why) => Status::with_error_details(
            Code::Unavailable,
            format!("job store unavailable: {why}"),
            ErrorDetails::with_retry_info(Some(Duration::from_secs(1))),
        ),
    }
}

/// A job's error in the `Job.error` field.
pub fn job_error(e: &MurkError) -> pb::JobError {
    pb::JobError {
        code: code_of(e) as i32,
        message: e.to_string(),
        field: e.field().unwrap_or_default().to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn invalid_argument_names_the_field_in_message_and_details() {
        let s = to_status(&MurkError::invalid("tof_depth.phase", "size differs"));
        assert_eq!(s.code(), Code::InvalidArgument);
        assert!(s.message().contains("tof_depth.phase"));
        let details = s.get_error_details();
        let v = &details.bad_request().unwrap().field_violations[0];
        assert_eq!(v.field, "tof_depth.phase");
    }

    #[test]
    fn shutdown_is_retryable_unavailable_not_cancelled() {
        let s = to_status(&MurkError::ShuttingDown);
        assert_eq!(s.code(), Code::Unavailable);
        assert!(s.message().contains("resubmit"));
        assert!(s.get_error_details().retry_info().is_some());
        assert_eq!(
            submit_status(&JobsError::ShuttingDown).code(),
            Code::Unavailable
        );
    }

    #[test]
    fn queue_full_carries_retry_info() {
        let s = submit_status(&JobsError::QueueFull {
            capacity: 3,
            retry_after: Duration::from_secs(2),
        });
        assert_eq!(s.code(), Code::ResourceExhausted);
        let d = s.get_error_details();
        assert_eq!(
            d.retry_info().unwrap().retry_delay,
            Some(Duration::from_secs(2))
        );
    }
}
