//! Protobuf ↔ domain conversions, one file per message family.

mod image;
mod job;
mod tof;

pub use image::{image_from_proto, image_to_proto, ImageLimits};
pub use job::{job_to_proto, timestamp};
pub use tof::{intrinsics_to_proto, tof_from_proto, tof_request_to_proto, tof_to_proto};
