//! ROS 2 bags in and out: sensor frames read from an MCAP file of CDR-encoded ROS 2 messages
//! (rosbag2's default storage since Iron), and results written as ROS 2 messages to an MCAP
//! file that Foxglove and RViz open. `murk bag` streams the frames through a sensor session.
//!
//! The container is the maintained `mcap` crate and the message encoding `cdr-encoding`; only
//! the message definitions murk needs are written out ([`msgs`]).

pub mod cdr;
pub mod frames;
pub mod images;
pub mod msgs;
pub mod pairing;
pub mod pointcloud;
pub mod reader;
pub mod writer;

/// What can go wrong with a bag; each names the file, or the topic and the stamp.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The file is not a readable MCAP file (truncated, corrupt, a record over the limit).
    #[error("{path}: {message} (at byte {offset})")]
    Container {
        /// The file.
        path: String,
        /// Bytes read when it went wrong.
        offset: u64,
        /// What is wrong.
        message: String,
    },
    /// A message murk needs cannot be used.
    #[error("{topic}, message {at}: {message}")]
    Message {
        /// Its topic.
        topic: String,
        /// Its stamp or log time.
        at: String,
        /// What is wrong.
        message: String,
    },
    /// Images came without their camera's intrinsics.
    #[error(
        "{info_topic}: no sensor_msgs/CameraInfo for the image on {image_topic} at {stamp}; \
         murk needs the camera's intrinsics (record the camera_info topic, or name it with the \
         --*-info flag)"
    )]
    MissingCameraInfo {
        /// The CameraInfo topic that stayed silent.
        info_topic: String,
        /// The image topic that needed it.
        image_topic: String,
        /// The first image's stamp.
        stamp: String,
    },
}
