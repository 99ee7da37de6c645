//! The ROS 2 messages moma speaks, as plain serde structs in the field order of their `.msg`
//! definitions (ROS 2 Jazzy), so that ros2-client's CDR encoding is the wire format `rmw` uses.
//!
//! Only the messages the node and the replay need are here. Byte payloads (`uint8[]`) are
//! `serde_bytes::ByteBuf`: CDR writes them as one length and the bytes, instead of one serde call
//! per byte (a 640×480 32FC1 image is 1.2 MB).

use ros2_client::{Message, MessageTypeName, ServiceTypeName};
use serde::{Deserialize, Serialize};
use serde_bytes::ByteBuf;

/// `builtin_interfaces/msg/Time`: seconds and nanoseconds since the epoch (or since the
/// replay's start: a stamp only has to identify a frame).
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
)]
pub struct Time {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds, `< 1e9`.
    pub nanosec: u32,
}

impl Time {
    /// The stamp as seconds.
    pub fn as_secs_f64(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time of the data.
    pub stamp: Time,
    /// Coordinate frame of the data (the camera's optical frame: x right, y down, z forward).
    pub frame_id: String,
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Stamp and frame.
    pub header: Header,
    /// Rows, pixels.
    pub height: u32,
    /// Columns, pixels.
    pub width: u32,
    /// Pixel encoding (`rgb8`, `bgr8`, `rgba8`, `bgra8`, `mono8`, `16UC1`, `32FC1`, …).
    pub encoding: String,
    /// 1 when multi-byte values are big-endian.
    pub is_bigendian: u8,
    /// Bytes per row (≥ width × bytes per pixel).
    pub step: u32,
    /// `step × height` bytes.
    pub data: ByteBuf,
}
impl Message for Image {}

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// Leftmost column, pixels.
    pub x_offset: u32,
    /// Top row, pixels.
    pub y_offset: u32,
    /// Rows, pixels.
    pub height: u32,
    /// Columns, pixels.
    pub width: u32,
    /// Whether the region should be rectified.
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Stamp and frame.
    pub header: Header,
    /// Rows, pixels.
    pub height: u32,
    /// Columns, pixels.
    pub width: u32,
    /// `plumb_bob`, `rational_polynomial`, … (moma assumes rectified images).
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Intrinsic matrix, row-major: `[fx 0 cx; 0 fy cy; 0 0 1]`, pixels.
    pub k: [f64; 9],
    /// Rectification rotation, row-major.
    pub r: [f64; 9],
    /// Projection matrix, row-major 3×4.
    pub p: [f64; 12],
    /// Horizontal binning (0 or 1: none).
    pub binning_x: u32,
    /// Vertical binning (0 or 1: none).
    pub binning_y: u32,
    /// Region of interest (all zero: the full image).
    pub roi: RegionOfInterest,
}
impl Message for CameraInfo {}

/// `sensor_msgs/msg/PointField`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointField {
    /// Field name (`x`, `y`, `z`, `rgb`).
    pub name: String,
    /// Byte offset within a point.
    pub offset: u32,
    /// [`PointField::FLOAT32`], …
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

impl PointField {
    /// `sensor_msgs/msg/PointField` datatype of a 32-bit float.
    pub const FLOAT32: u8 = 7;
}

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: Header,
    /// Rows (the image's: an organised cloud).
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// The fields of one point.
    pub fields: Vec<PointField>,
    /// Whether the data are big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// `row_step × height` bytes.
    pub data: ByteBuf,
    /// False when some points are invalid (NaN).
    pub is_dense: bool,
}
impl Message for PointCloud2 {}

/// `geometry_msgs/msg/Point` (metres).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x, metres.
    pub x: f64,
    /// y, metres.
    pub y: f64,
    /// z, metres.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w (scalar part).
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position, metres.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseArray {
    /// Stamp and frame.
    pub header: Header,
    /// The poses.
    pub poses: Vec<Pose>,
}
impl Message for PoseArray {}

/// `std_msgs/msg/String`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StringMsg {
    /// The text.
    pub data: String,
}
impl Message for StringMsg {}

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyValue {
    /// Key.
    pub key: String,
    /// Value.
    pub value: String,
}

/// `diagnostic_msgs/msg/DiagnosticStatus`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// [`DiagnosticStatus::OK`], `WARN`, `ERROR` or `STALE`.
    pub level: u8,
    /// Name of what is reported on.
    pub name: String,
    /// What happened, in words.
    pub message: String,
    /// Hardware id (the camera frame).
    pub hardware_id: String,
    /// Figures.
    pub values: Vec<KeyValue>,
}

impl DiagnosticStatus {
    /// Level: all is well.
    pub const OK: u8 = 0;
    /// Level: warning.
    pub const WARN: u8 = 1;
    /// Level: error.
    pub const ERROR: u8 = 2;
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    /// Stamp (of the frame reported on, when there is one) and frame.
    pub header: Header,
    /// The statuses.
    pub status: Vec<DiagnosticStatus>,
}
impl Message for DiagnosticArray {}

/// `std_srvs/srv/Trigger` request (an empty message: IDL gives it one dummy byte).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TriggerRequest {
    /// Always 0 (`structure_needs_at_least_one_member`).
    pub structure_needs_at_least_one_member: u8,
}
impl Message for TriggerRequest {}

/// `std_srvs/srv/Trigger` response.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TriggerResponse {
    /// Whether the request succeeded.
    pub success: bool,
    /// What happened, in words.
    pub message: String,
}
impl Message for TriggerResponse {}

/// ROS 2 type names of the messages above.
pub mod types {
    use super::{MessageTypeName, ServiceTypeName};

    /// `sensor_msgs/msg/Image`.
    pub fn image() -> MessageTypeName {
        MessageTypeName::new("sensor_msgs", "Image")
    }
    /// `sensor_msgs/msg/CameraInfo`.
    pub fn camera_info() -> MessageTypeName {
        MessageTypeName::new("sensor_msgs", "CameraInfo")
    }
    /// `sensor_msgs/msg/PointCloud2`.
    pub fn point_cloud2() -> MessageTypeName {
        MessageTypeName::new("sensor_msgs", "PointCloud2")
    }
    /// `geometry_msgs/msg/PoseArray`.
    pub fn pose_array() -> MessageTypeName {
        MessageTypeName::new("geometry_msgs", "PoseArray")
    }
    /// `std_msgs/msg/String`.
    pub fn string() -> MessageTypeName {
        MessageTypeName::new("std_msgs", "String")
    }
    /// `diagnostic_msgs/msg/DiagnosticArray`.
    pub fn diagnostic_array() -> MessageTypeName {
        MessageTypeName::new("diagnostic_msgs", "DiagnosticArray")
    }
    /// `std_srvs/srv/Trigger`.
    pub fn trigger() -> ServiceTypeName {
        ServiceTypeName::new("std_srvs", "Trigger")
    }
}

/// A message from an RTPS serialized payload: the 4-byte encapsulation header (`CDR_BE` 0x0000
/// or `CDR_LE` 0x0001, two option bytes) and the CDR body, decoded as RustDDS decodes what the
/// node receives (the fuzzer's entry point).
///
/// # Errors
/// [`crate::RosError::Malformed`]: a payload shorter than its header, another representation,
/// or a body that does not decode as `T`.
pub fn from_cdr_payload<T: serde::de::DeserializeOwned>(payload: &[u8]) -> crate::Result<T> {
    use byteorder::{BigEndian, LittleEndian};
    let (head, body) = payload
        .split_at_checked(4)
        .ok_or_else(|| crate::RosError::malformed("payload shorter than its 4-byte header"))?;
    let decoded = match [head[0], head[1]] {
        [0x00, 0x00] => cdr_encoding::from_bytes::<T, BigEndian>(body),
        [0x00, 0x01] => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        other => {
            return Err(crate::RosError::malformed(format!(
                "representation {other:02x?} is not plain CDR"
            )));
        }
    };
    decoded
        .map(|(m, _)| m)
        .map_err(|e| crate::RosError::malformed(format!("CDR: {e}")))
}

/// `message` as an RTPS serialized payload (`CDR_LE` header and body).
///
/// # Errors
/// [`crate::RosError::Malformed`] when serde refuses the value.
pub fn to_cdr_payload<T: Serialize>(message: &T) -> crate::Result<Vec<u8>> {
    let mut out = vec![0x00, 0x01, 0x00, 0x00];
    out.extend(
        cdr_encoding::to_vec::<T, byteorder::LittleEndian>(message)
            .map_err(|e| crate::RosError::malformed(format!("CDR: {e}")))?,
    );
    Ok(out)
}
