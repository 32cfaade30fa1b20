//! The ROS 2 messages the bridge reads and writes, as serde types in the field order of
//! their `.msg` definitions (CDR has no field names: order and types are the contract).

use serde::{Deserialize, Serialize};

use groundwork_io::pointcloud2::{CloudData, CloudRef, PointField};

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds since 1970 (ROS time).
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// A stamp in ns since 1970 (seconds saturate at `i32::MAX`, in 2038).
    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: i32::try_from(ns / 1_000_000_000).unwrap_or(i32::MAX),
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time.
    pub stamp: Time,
    /// Coordinate frame of the data.
    pub frame_id: String,
}

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: Header,
    /// Rows (1: unorganized).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The point layout.
    pub fields: Vec<PointField>,
    /// Multi-byte values are big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points: one buffer, not a sequence of bytes one by one.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    /// No point has a non-finite coordinate.
    pub is_dense: bool,
}

impl PointCloud2 {
    /// The message as the format crate reads it.
    pub fn view(&self) -> CloudRef<'_> {
        CloudRef {
            stamp_sec: self.header.stamp.sec,
            stamp_nanosec: self.header.stamp.nanosec,
            frame_id: &self.header.frame_id,
            height: self.height,
            width: self.width,
            fields: &self.fields,
            is_bigendian: self.is_bigendian,
            point_step: self.point_step,
            row_step: self.row_step,
            data: &self.data,
            is_dense: self.is_dense,
        }
    }

    /// An output cloud with the input's header and byte order.
    pub fn from_data(header: Header, is_bigendian: bool, d: CloudData) -> Self {
        Self {
            header,
            height: d.height,
            width: d.width,
            fields: d.fields,
            is_bigendian,
            point_step: d.point_step,
            row_step: d.row_step,
            data: d.data,
            is_dense: d.is_dense,
        }
    }
}

/// `geometry_msgs/msg/Point`; also the layout of `geometry_msgs/msg/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
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
    /// w.
    pub w: f64,
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position.
    pub position: Vector3,
    /// Orientation.
    pub orientation: Quaternion,
}

/// A row-major 6 × 6 covariance (x, y, z, rotations about x, y, z): a fixed array of 36
/// float64, which CDR writes without a length (serde derives arrays up to 32 only).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Serialize for Covariance {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut t = s.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visit;
        impl<'de> serde::de::Visitor<'de> for Visit {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("36 float64")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut a: A,
            ) -> Result<Covariance, A::Error> {
                let mut c = [0.0; 36];
                for (i, v) in c.iter_mut().enumerate() {
                    *v = a
                        .next_element()?
                        .ok_or_else(|| serde::de::Error::invalid_length(i, &self))?;
                }
                Ok(Covariance(c))
            }
        }
        d.deserialize_tuple(36, Visit)
    }
}

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Its covariance (all zero: unknown).
    pub covariance: Covariance,
}

/// `geometry_msgs/msg/Twist`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity.
    pub linear: Vector3,
    /// Angular velocity.
    pub angular: Vector3,
}

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// Its covariance.
    pub covariance: Covariance,
}

/// `nav_msgs/msg/Odometry`: the pose of `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// Stamp, and the fixed frame the pose is in (`odom`, `map`).
    pub header: Header,
    /// The frame whose pose it is (`base_link`, or a LiDAR odometry's sensor frame).
    pub child_frame_id: String,
    /// The pose.
    pub pose: PoseWithCovariance,
    /// The velocity (unused).
    pub twist: TwistWithCovariance,
}

/// `vision_msgs/msg/ObjectHypothesis` (vision_msgs 4: Humble and later).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectHypothesis {
    /// Class name.
    pub class_id: String,
    /// Confidence.
    pub score: f64,
}

/// `vision_msgs/msg/ObjectHypothesisWithPose`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectHypothesisWithPose {
    /// Class and score.
    pub hypothesis: ObjectHypothesis,
    /// Where.
    pub pose: PoseWithCovariance,
}

/// `vision_msgs/msg/BoundingBox3D`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BoundingBox3D {
    /// Centre and orientation.
    pub center: Pose,
    /// Extent along the box's own x, y, z.
    pub size: Vector3,
}

/// `vision_msgs/msg/Detection3D` (vision_msgs 4: no source cloud).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Detection3D {
    /// Stamp and frame.
    pub header: Header,
    /// Class hypotheses.
    pub results: Vec<ObjectHypothesisWithPose>,
    /// The box.
    pub bbox: BoundingBox3D,
    /// Identifier within the message.
    pub id: String,
}

/// `vision_msgs/msg/Detection3DArray`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Detection3DArray {
    /// Stamp and frame.
    pub header: Header,
    /// The detections.
    pub detections: Vec<Detection3D>,
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds.
    pub nanosec: u32,
}

/// `std_msgs/msg/ColorRGBA`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRGBA {
    /// Red, 0–1.
    pub r: f32,
    /// Green.
    pub g: f32,
    /// Blue.
    pub b: f32,
    /// Opacity.
    pub a: f32,
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Stamp and frame.
    pub header: Header,
    /// `jpeg`, `png`.
    pub format: String,
    /// The image.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/UVCoordinate`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UVCoordinate {
    /// u.
    pub u: f32,
    /// v.
    pub v: f32,
}

/// `visualization_msgs/msg/MeshFile`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    /// Its name.
    pub filename: String,
    /// Its bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/Marker` (Humble and later: with texture and mesh file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    /// Stamp and frame.
    pub header: Header,
    /// Namespace of the id.
    pub ns: String,
    /// Id within the namespace.
    pub id: i32,
    /// Shape (1: cube).
    #[serde(rename = "type")]
    pub kind: i32,
    /// 0 add or modify, 2 delete, 3 delete all.
    pub action: i32,
    /// Where.
    pub pose: Pose,
    /// Size.
    pub scale: Vector3,
    /// Colour.
    pub color: ColorRGBA,
    /// How long it stays (0: until replaced).
    pub lifetime: Duration,
    /// Follows its frame.
    pub frame_locked: bool,
    /// Line and point shapes' points.
    pub points: Vec<Vector3>,
    /// Their colours.
    pub colors: Vec<ColorRGBA>,
    /// Texture (unused).
    pub texture_resource: String,
    /// Texture image (unused).
    pub texture: CompressedImage,
    /// Texture coordinates (unused).
    pub uv_coordinates: Vec<UVCoordinate>,
    /// Text shapes' text.
    pub text: String,
    /// Mesh (unused).
    pub mesh_resource: String,
    /// Mesh file (unused).
    pub mesh_file: MeshFile,
    /// Mesh materials (unused).
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    /// A cube.
    pub const CUBE: i32 = 1;
    /// Add or replace.
    pub const ADD: i32 = 0;
    /// Remove every marker of the namespace.
    pub const DELETE_ALL: i32 = 3;

    /// A marker of `kind` doing `action`, everything else empty.
    pub fn new(header: Header, ns: &str, id: i32, kind: i32, action: i32) -> Self {
        Self {
            header,
            ns: ns.into(),
            id,
            kind,
            action,
            pose: Pose {
                position: Vector3::default(),
                orientation: Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: 0.0,
                    w: 1.0,
                },
            },
            scale: Vector3::default(),
            color: ColorRGBA::default(),
            lifetime: Duration::default(),
            frame_locked: false,
            points: Vec::new(),
            colors: Vec::new(),
            texture_resource: String::new(),
            texture: CompressedImage::default(),
            uv_coordinates: Vec::new(),
            text: String::new(),
            mesh_resource: String::new(),
            mesh_file: MeshFile::default(),
            mesh_use_embedded_materials: false,
        }
    }
}

/// `visualization_msgs/msg/MarkerArray`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    /// The markers.
    pub markers: Vec<Marker>,
}

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp and the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// Child in parent.
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TFMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// The serde form travels as the hand-written CDR of the format crate does: a cloud
    /// encoded for a recording decodes through serde into the same scan.
    #[test]
    fn serde_cdr_agrees_with_the_recording_encoder() {
        use groundwork_io::Scan;
        use groundwork_io::pointcloud2::{decode, decode_cloud, encode};
        let pts: Vec<_> = (0..7)
            .map(|i| groundwork_core::Point::new(i as f32, -(i as f32), 0.25 * i as f32))
            .collect();
        let scan = Scan::dense(pts);
        let probs: Vec<f32> = (0..7).map(|i| i as f32 / 7.0).collect();
        let bytes = encode(&scan, &probs, 1_700_000_001_000_000_002, "velodyne");
        // CDR encapsulation header (4 bytes), then the message.
        let (msg, _): (PointCloud2, usize) =
            cdr_encoding::from_bytes::<PointCloud2, byteorder::LittleEndian>(&bytes[4..]).unwrap();
        assert_eq!(msg.header.frame_id, "velodyne");
        assert_eq!(msg.view().stamp_ns(), Some(1_700_000_001_000_000_002));
        assert_eq!(Time::from_ns(1_700_000_001_000_000_002), msg.header.stamp);
        let label = Path::new("m");
        assert_eq!(
            decode_cloud(label, &msg.view(), 100).unwrap(),
            decode(label, &bytes, 100).unwrap()
        );
        // And back: serde's CDR is the recording encoder's, byte for byte.
        let again = cdr_encoding::to_vec::<PointCloud2, byteorder::LittleEndian>(&msg).unwrap();
        assert_eq!(again, bytes[4..]);
    }

    /// A static transform through serde is the recording writer's TFMessage, byte for byte.
    #[test]
    fn serde_tf_agrees_with_the_recording_encoder() {
        use groundwork_io::transform::{StaticTransform, encode_static_transform};
        let t = StaticTransform {
            parent: "base_footprint".into(),
            translation: [0.1, -0.2, 1.73],
            rotation: [0.0, 0.0, 0.5f64.sin(), 0.5f64.cos()],
        };
        let bytes = encode_static_transform(&t, "velodyne", 1_700_000_000_000_000_001);
        let [x, y, z, w] = t.rotation;
        let ours = TFMessage {
            transforms: vec![TransformStamped {
                header: Header {
                    stamp: Time {
                        sec: 1_700_000_000,
                        nanosec: 1,
                    },
                    frame_id: "base_footprint".into(),
                },
                child_frame_id: "velodyne".into(),
                transform: Transform {
                    translation: Vector3 {
                        x: 0.1,
                        y: -0.2,
                        z: 1.73,
                    },
                    rotation: Quaternion { x, y, z, w },
                },
            }],
        };
        let serde = cdr_encoding::to_vec::<TFMessage, byteorder::LittleEndian>(&ours).unwrap();
        assert_eq!(serde, bytes[4..]);
    }

    /// A fixed array of 36 float64 has no length on the wire and comes back whole.
    #[test]
    fn covariance_is_36_bare_float64() {
        let c = Covariance(std::array::from_fn(|i| i as f64));
        let bytes = cdr_encoding::to_vec::<Covariance, byteorder::LittleEndian>(&c).unwrap();
        assert_eq!(bytes.len(), 36 * 8);
        let (back, _) =
            cdr_encoding::from_bytes::<Covariance, byteorder::LittleEndian>(&bytes).unwrap();
        assert_eq!(back, c);
    }
}
