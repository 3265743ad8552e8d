//! [`JobSnapshot`] → `murk.v1.Job`.

use std::time::SystemTime;

use prost::Message;
use tonic::Status;

use crate::jobs::{JobSnapshot, JobState};
use crate::service::proto::v1 as pb;
use crate::service::status::job_error;

/// `SystemTime` → protobuf `Timestamp`.
pub fn timestamp(t: SystemTime) -> prost_types::Timestamp {
    prost_types::Timestamp::from(t)
}

fn state(s: JobState) -> pb::JobState {
    match s {
        JobState::Queued => pb::JobState::Queued,
        JobState::Running => pb::JobState::Running,
        JobState::Succeeded => pb::JobState::Succeeded,
        JobState::Failed => pb::JobState::Failed,
        JobState::Cancelled => pb::JobState::Cancelled,
    }
}

/// Builds the wire job. The stored result is decoded into it unless `omit_result`, or unless
/// the whole message would exceed `max_message_bytes` (the unary result limit: larger messages
/// break clients left at gRPC's default 4 MiB receive limit); then `result_omitted` is set and
/// the client fetches the result with `GetJobResult`.
pub fn job_to_proto(
    s: &JobSnapshot,
    omit_result: bool,
    max_message_bytes: usize,
) -> Result<pb::Job, Status> {
    let error = match &s.error {
        Some(err) if s.state != JobState::Succeeded => {
            Some(pb::job::Outcome::Error(job_error(err)))
        }
        _ => None,
    };
    let mut job = pb::Job {
        id: s.id.clone(),
        state: state(s.state) as i32,
        progress: s.progress,
        stage: s.stage.clone(),
        create_time: Some(timestamp(s.create_time)),
        start_time: s.start_time.map(timestamp),
        end_time: s.end_time.map(timestamp),
        cached: s.cached,
        method: s.method.clone(),
        outcome: error,
        result_size_bytes: s.result.as_ref().map_or(0, |b| b.len() as u64),
        result_omitted: false,
    };
    if let Some(bytes) = &s.result {
        // The result field as it would be encoded: tag, length, payload.
        let with_result =
            job.encoded_len() + 1 + prost::length_delimiter_len(bytes.len()) + bytes.len();
        if omit_result || with_result > max_message_bytes {
            job.result_omitted = true;
        } else {
            job.outcome = Some(pb::job::Outcome::Result(
                pb::JobResult::decode(bytes.as_slice())
                    .map_err(|e| Status::internal(format!("stored result is corrupt: {e}")))?,
            ));
        }
    }
    Ok(job)
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    #[test]
    fn result_is_left_out_exactly_when_the_message_would_pass_the_limit() {
        let result = pb::JobResult {
            method: Some(pb::job_result::Method::TofDepth(
                pb::TofDepthResult::default(),
            )),
        }
        .encode_to_vec();
        let snap = JobSnapshot::from_cache("ab", "tof_depth", Arc::new(result.clone()));
        let full = job_to_proto(&snap, false, usize::MAX).unwrap();
        assert!(!full.result_omitted && full.outcome.is_some());
        assert_eq!(full.result_size_bytes, result.len() as u64);
        let exact = full.encoded_len();
        let fits = job_to_proto(&snap, false, exact).unwrap();
        assert_eq!(fits, full, "a message of exactly the limit is sent whole");
        let over = job_to_proto(&snap, false, exact - 1).unwrap();
        assert!(over.result_omitted && over.outcome.is_none());
        assert!(over.encoded_len() < exact);
        let asked = job_to_proto(&snap, true, usize::MAX).unwrap();
        assert!(asked.result_omitted && asked.outcome.is_none());
    }
}
