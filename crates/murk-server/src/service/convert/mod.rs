//! Protobuf ↔ domain conversions, one file per message family.

mod geometry;
mod image;
mod job;
mod mvs;
mod outputs;
mod params;
mod ps;
mod stereo;
mod tof;

pub use geometry::{
    check_points, intrinsics_from_proto, intrinsics_to_proto, points_from_proto, points_to_proto,
};
pub use image::{image_from_proto, image_to_proto, mono_image_from_proto, ImageLimits};
pub use job::{job_to_proto, timestamp};
pub use mvs::{
    canonicalize_mvs_request, mvs_from_proto, mvs_request_to_proto, mvs_to_proto, pose_from_proto,
    pose_to_proto, MvsInput, MvsViewInput, MAX_SOURCE_VIEWS,
};
pub use outputs::{Delivery, Encoding, OutputField, OutputSelection, Quantity};
pub use params::{
    canonicalize_params_request, observations_to_proto, params_from_proto, params_request_to_proto,
    AirlightService, ParamsInput, MAX_SPARSE_POINTS,
};
pub use ps::{
    canonicalize_ps_request, ps_from_proto, ps_from_result, ps_request_to_proto, ps_to_proto,
};
pub use stereo::{
    canonicalize_stereo_request, stereo_from_proto, stereo_images_from_proto,
    stereo_outputs_from_proto, stereo_request_to_proto, stereo_to_proto, StereoConfig, StereoInput,
    STEREO_OUTPUTS,
};
pub use tof::{
    simulated_tof_request, tof_from_proto, tof_images_from_proto, tof_outputs_from_proto,
    tof_params_from_proto, tof_points_from_proto, tof_request_to_proto, tof_to_proto, TofPoints,
    TOF_OUTPUTS,
};
