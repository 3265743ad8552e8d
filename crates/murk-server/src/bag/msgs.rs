//! The ROS 2 messages murk reads and writes, as serde structs laid out field for field like
//! their `.msg` definitions (CDR has no field tags: the order is the format), and the
//! definitions themselves in the `ros2msg` schema encoding that rosbag2, Foxglove and RViz use.
//!
//! Only the messages murk needs are here; the definitions follow ROS 2 Humble through Jazzy,
//! which have not changed them.

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds since the epoch.
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// Nanoseconds since the epoch (negative times saturate at 0).
    pub fn as_nanos(self) -> u64 {
        (i64::from(self.sec).max(0) as u64) * 1_000_000_000 + u64::from(self.nanosec)
    }

    /// As seconds, for messages (`12.345678901 s`).
    pub fn display(self) -> String {
        format!("{}.{:09} s", self.sec, self.nanosec)
    }
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Capture time.
    pub stamp: Time,
    /// Coordinate frame of the data.
    pub frame_id: String,
}

/// `sensor_msgs/Image`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Capture time and camera frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`mono8`, `rgb8`, `32FC1`, ...).
    pub encoding: String,
    /// 1 when multi-byte samples are big-endian.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// The pixels, row-major.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/CompressedImage`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Capture time and camera frame.
    pub header: Header,
    /// `png`, `jpeg`, or image_transport's `"<encoding>; png compressed <mode>"`.
    pub format: String,
    /// The file's bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/RegionOfInterest`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// Left column.
    pub x_offset: u32,
    /// Top row.
    pub y_offset: u32,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Whether the region is in rectified coordinates.
    pub do_rectify: bool,
}

/// `sensor_msgs/CameraInfo`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Capture time and camera frame.
    pub header: Header,
    /// Image rows.
    pub height: u32,
    /// Image columns.
    pub width: u32,
    /// Distortion model name (`plumb_bob`, ...).
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Intrinsics of the raw image, row-major 3×3.
    pub k: [f64; 9],
    /// Rectification rotation, row-major 3×3.
    pub r: [f64; 9],
    /// Projection of the rectified image, row-major 3×4; for the right camera of a stereo pair
    /// `P[3] = Tx = −fx·B` with B the baseline.
    pub p: [f64; 12],
    /// Horizontal binning.
    pub binning_x: u32,
    /// Vertical binning.
    pub binning_y: u32,
    /// Region of interest.
    pub roi: RegionOfInterest,
}

/// `sensor_msgs/PointField`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PointField {
    /// Field name (`x`, `rgb`, ...).
    pub name: String,
    /// Byte offset within a point.
    pub offset: u32,
    /// One of the `PointField` datatype constants ([`POINT_FIELD_FLOAT32`], ...).
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

/// `sensor_msgs/PointField.FLOAT32`.
pub const POINT_FIELD_FLOAT32: u8 = 7;

/// `sensor_msgs/PointCloud2`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Capture time and the frame the points are in.
    pub header: Header,
    /// Rows (1 for an unordered cloud).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The layout of a point.
    pub fields: Vec<PointField>,
    /// Byte order of `data`.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    /// True when no point is invalid (NaN).
    pub is_dense: bool,
}

/// `stereo_msgs/DisparityImage`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DisparityImage {
    /// Capture time and the left camera's frame.
    pub header: Header,
    /// Disparities, `32FC1`, pixels.
    pub image: Image,
    /// Focal length, pixels.
    pub f: f32,
    /// Baseline, metres: depth = f·t / disparity.
    pub t: f32,
    /// The region where disparities may be valid.
    pub valid_window: RegionOfInterest,
    /// Smallest disparity searched, pixels.
    pub min_disparity: f32,
    /// Largest disparity searched, pixels.
    pub max_disparity: f32,
    /// Smallest step of the disparities, pixels.
    pub delta_d: f32,
}

const TIME: &str = "int32 sec\nuint32 nanosec\n";
const HEADER: &str = "builtin_interfaces/Time stamp\nstring frame_id\n";
const IMAGE: &str = "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n\
uint8 is_bigendian\nuint32 step\nuint8[] data\n";
const ROI: &str =
    "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n";
const CAMERA_INFO: &str = "std_msgs/Header header\nuint32 height\nuint32 width\n\
string distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\n\
uint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n";
const POINT_FIELD: &str = "uint8 INT8 = 1\nuint8 UINT8 = 2\nuint8 INT16 = 3\nuint8 UINT16 = 4\n\
uint8 INT32 = 5\nuint8 UINT32 = 6\nuint8 FLOAT32 = 7\nuint8 FLOAT64 = 8\n\
string name\nuint32 offset\nuint8 datatype\nuint32 count\n";
const POINT_CLOUD2: &str = "std_msgs/Header header\nuint32 height\nuint32 width\n\
sensor_msgs/PointField[] fields\nbool is_bigendian\nuint32 point_step\nuint32 row_step\n\
uint8[] data\nbool is_dense\n";
const DISPARITY_IMAGE: &str = "std_msgs/Header header\nsensor_msgs/Image image\nfloat32 f\n\
float32 t\nsensor_msgs/RegionOfInterest valid_window\nfloat32 min_disparity\n\
float32 max_disparity\nfloat32 delta_d\n";

/// The message types murk writes, with their `ros2msg` schemas.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MessageType {
    /// `sensor_msgs/msg/Image`.
    Image,
    /// `sensor_msgs/msg/CameraInfo`.
    CameraInfo,
    /// `sensor_msgs/msg/PointCloud2`.
    PointCloud2,
    /// `stereo_msgs/msg/DisparityImage`.
    DisparityImage,
}

impl MessageType {
    /// The schema name, as rosbag2 records it.
    pub fn name(self) -> &'static str {
        match self {
            MessageType::Image => "sensor_msgs/msg/Image",
            MessageType::CameraInfo => "sensor_msgs/msg/CameraInfo",
            MessageType::PointCloud2 => "sensor_msgs/msg/PointCloud2",
            MessageType::DisparityImage => "stereo_msgs/msg/DisparityImage",
        }
    }

    /// The `ros2msg` schema: the message's definition, then each type it uses, after a line of
    /// 80 `=` and `MSG: package/Type`.
    pub fn schema(self) -> String {
        let (main, deps): (&str, &[(&str, &str)]) = match self {
            MessageType::Image => (
                IMAGE,
                &[
                    ("std_msgs/Header", HEADER),
                    ("builtin_interfaces/Time", TIME),
                ],
            ),
            MessageType::CameraInfo => (
                CAMERA_INFO,
                &[
                    ("std_msgs/Header", HEADER),
                    ("builtin_interfaces/Time", TIME),
                    ("sensor_msgs/RegionOfInterest", ROI),
                ],
            ),
            MessageType::PointCloud2 => (
                POINT_CLOUD2,
                &[
                    ("std_msgs/Header", HEADER),
                    ("builtin_interfaces/Time", TIME),
                    ("sensor_msgs/PointField", POINT_FIELD),
                ],
            ),
            MessageType::DisparityImage => (
                DISPARITY_IMAGE,
                &[
                    ("std_msgs/Header", HEADER),
                    ("builtin_interfaces/Time", TIME),
                    ("sensor_msgs/Image", IMAGE),
                    ("sensor_msgs/RegionOfInterest", ROI),
                ],
            ),
        };
        let mut s = main.to_string();
        for (name, def) in deps {
            s.push_str(&"=".repeat(80));
            s.push_str("\nMSG: ");
            s.push_str(name);
            s.push('\n');
            s.push_str(def);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schemas_name_every_type_they_use() {
        for t in [
            MessageType::Image,
            MessageType::CameraInfo,
            MessageType::PointCloud2,
            MessageType::DisparityImage,
        ] {
            let s = t.schema();
            for line in s.lines().filter(|l| !l.starts_with('=') && !l.is_empty()) {
                if let Some(rest) = line.strip_prefix("MSG: ") {
                    assert!(rest.contains('/'), "{line}");
                    continue;
                }
                let ty = line
                    .split_whitespace()
                    .next()
                    .unwrap()
                    .trim_end_matches("[]");
                let ty = ty.split('[').next().unwrap();
                if ty.contains('/') {
                    assert!(
                        s.contains(&format!("MSG: {ty}\n")),
                        "{} uses {ty}",
                        t.name()
                    );
                }
            }
        }
    }

    #[test]
    fn time_orders_by_nanoseconds() {
        let a = Time {
            sec: 1,
            nanosec: 999_999_999,
        };
        let b = Time { sec: 2, nanosec: 0 };
        assert_eq!(b.as_nanos() - a.as_nanos(), 1);
        assert_eq!(a.display(), "1.999999999 s");
    }
}
