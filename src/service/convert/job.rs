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

/// Builds the wire job; decodes the stored result unless `omit_result`.
pub fn job_to_proto(s: &JobSnapshot, omit_result: bool) -> Result<pb::Job, Status> {
    let outcome = match (&s.result, &s.error) {
        (Some(bytes), _) if !omit_result => Some(pb::job::Outcome::Result(
            pb::JobResult::decode(bytes.as_slice())
                .map_err(|e| Status::internal(format!("stored result is corrupt: {e}")))?,
        )),
        (_, Some(err)) if s.state != JobState::Succeeded => {
            Some(pb::job::Outcome::Error(job_error(err)))
        }
        _ => None,
    };
    Ok(pb::Job {
        id: s.id.clone(),
        state: state(s.state) as i32,
        progress: s.progress,
        stage: s.stage.clone(),
        create_time: Some(timestamp(s.create_time)),
        start_time: s.start_time.map(timestamp),
        end_time: s.end_time.map(timestamp),
        cached: s.cached,
        method: s.method.clone(),
        outcome,
    })
}
