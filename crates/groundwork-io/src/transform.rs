//! `tf2_msgs/msg/TFMessage` in CDR: the sensor's mount as a static transform, so that a
//! recording opens in Foxglove or RViz with the cloud placed on the ground frame.

use crate::cdr::{self, put_f64, put_header, put_string, put_u32};

/// The message's type name.
pub const TF_SCHEMA_NAME: &str = "tf2_msgs/msg/TFMessage";

/// Topic of static transforms in ROS 2.
pub const TF_STATIC_TOPIC: &str = "/tf_static";

/// Its definition with its dependencies (the `ros2msg` schema encoding of an MCAP).
pub const TF_SCHEMA_TEXT: &str = concat!(
    "geometry_msgs/TransformStamped[] transforms
================================================================================
MSG: geometry_msgs/TransformStamped
std_msgs/Header header
string child_frame_id
geometry_msgs/Transform transform
",
    header_definitions!(),
    "================================================================================
MSG: geometry_msgs/Transform
geometry_msgs/Vector3 translation
geometry_msgs/Quaternion rotation
================================================================================
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
================================================================================
MSG: geometry_msgs/Quaternion
float64 x
float64 y
float64 z
float64 w
"
);

/// Frame the sensor's mount places scans in: groundwork's ground-aligned frame (on the
/// ground below the sensor, z up), which ROS calls `base_footprint` (REP 120).
pub const GROUND_FRAME: &str = "base_footprint";

/// The frame of a scan that names none (a scan file, a recording without one).
pub const SENSOR_FRAME: &str = "lidar";

/// A rigid transform: where `child` sits in `parent` (translation, metres; rotation as a
/// unit quaternion x, y, z, w).
#[derive(Debug, Clone, PartialEq)]
pub struct StaticTransform {
    /// The parent frame (groundwork's ground-aligned frame).
    pub parent: String,
    /// Translation of the child's origin in the parent, metres.
    pub translation: [f64; 3],
    /// Rotation, parent from child, unit quaternion (x, y, z, w).
    pub rotation: [f64; 4],
}

impl StaticTransform {
    /// The sensor's mount: the sensor frame in [`GROUND_FRAME`].
    pub fn of_mount(
        mount: &groundwork_core::config::MountConfig,
    ) -> Result<Self, groundwork_core::ConfigError> {
        let pose = groundwork_core::config::mount_transform(mount)?;
        let (t, q) = (pose.translation.vector, pose.rotation);
        Ok(Self {
            parent: GROUND_FRAME.into(),
            translation: [t.x, t.y, t.z],
            rotation: [q.i, q.j, q.k, q.w],
        })
    }
}

/// One transform, `child` in `t.parent`, stamped `stamp_ns`, as a little-endian CDR
/// `TFMessage`.
pub fn encode_static_transform(t: &StaticTransform, child: &str, stamp_ns: u64) -> Vec<u8> {
    let mut out = cdr::message();
    put_u32(&mut out, 1);
    put_header(&mut out, stamp_ns, &t.parent);
    put_string(&mut out, child);
    for v in t.translation.iter().chain(&t.rotation) {
        put_f64(&mut out, *v);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn doubles_are_aligned_to_eight_after_the_encapsulation_header() {
        let t = StaticTransform {
            parent: "ground".into(),
            translation: [0.0, 0.0, 1.73],
            rotation: [0.0, 0.0, 0.0, 1.0],
        };
        let m = encode_static_transform(&t, "lidar", 1_500_000_000);
        // 4 (encapsulation) + 4 (count) + 8 (stamp) + 4+7 ("ground") + 1 (pad) + 4+6
        // ("lidar") = 38 bytes, 34 after the header: padded to 40 after it, then 7 doubles.
        assert_eq!(m.len(), 4 + 40 + 56);
        assert_eq!(&m[44 + 16..44 + 24], &1.73f64.to_le_bytes());
        assert_eq!(&m[m.len() - 8..], &1.0f64.to_le_bytes());
    }
}
