//! Poses for the multi-frame history from a `nav_msgs/Odometry` topic: each cloud gets the
//! world pose of its sensor at its stamp, from the odometry samples around that stamp.

use crate::msg::Odometry;
use crate::pose::{PoseTrack, pose_of, stamp_ns};

pub use crate::pose::{HOLD_NS, Pose};

/// The odometry samples seen, in stamp order.
#[derive(Debug)]
pub struct OdomTrack {
    track: PoseTrack,
    /// The frame the newest sample is the pose of (`child_frame_id`).
    child_frame: String,
    /// The sensor in the odometry's child frame when that is the vehicle's base: the
    /// mount (`base_footprint` from sensor).
    base_from_sensor: Option<Pose>,
}

impl OdomTrack {
    /// An empty track; `base_from_sensor` places the sensor on a vehicle whose odometry it
    /// is (see [`OdomTrack::sensor_pose`]).
    pub fn new(base_from_sensor: Option<Pose>) -> Self {
        Self {
            track: PoseTrack::default(),
            child_frame: String::new(),
            base_from_sensor,
        }
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.track.len()
    }

    /// Whether no sample is held.
    pub fn is_empty(&self) -> bool {
        self.track.is_empty()
    }

    /// Adds one sample. A sample that is no pose (a stamp before 1970, a non-finite value,
    /// a zero quaternion) is refused with the reason; one with the stamp of a held sample
    /// replaces it.
    pub fn add(&mut self, odom: &Odometry) -> Result<(), String> {
        let stamp = stamp_ns(&odom.header.stamp).map_err(|e| format!("odometry {e}"))?;
        let (p, q) = (&odom.pose.pose.position, &odom.pose.pose.orientation);
        let pose = pose_of([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
            .map_err(|e| format!("odometry at {stamp} ns holds no pose: {e}"))?;
        self.track.add(stamp, pose);
        self.child_frame.clone_from(&odom.child_frame_id);
        Ok(())
    }

    /// The world pose of a scan in `frame` stamped `stamp_ns`: the odometry's pose at that
    /// stamp ([`PoseTrack::at`]), composed with the mount unless the odometry is the pose
    /// of `frame` itself. `None`: no sample near enough.
    pub fn sensor_pose(&self, frame: &str, stamp_ns: u64) -> Option<Pose> {
        let odom = self.track.at(stamp_ns)?;
        Some(match &self.base_from_sensor {
            Some(mount) if self.child_frame != frame => odom * mount,
            _ => odom,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{
        Covariance, Header, Pose as RosPose, PoseWithCovariance, Quaternion as RosQ, Time, Twist,
        TwistWithCovariance, Vector3 as RosV,
    };
    use crate::pose::KEEP;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn odom(stamp_ns: u64, x: f64, yaw: f64, child: &str) -> Odometry {
        let zero = RosV {
            x: 0.0,
            y: 0.0,
            z: 0.0,
        };
        Odometry {
            header: Header {
                stamp: Time::from_ns(stamp_ns),
                frame_id: "odom".into(),
            },
            child_frame_id: child.into(),
            pose: PoseWithCovariance {
                pose: RosPose {
                    position: RosV { x, y: 0.0, z: 0.0 },
                    orientation: RosQ {
                        x: 0.0,
                        y: 0.0,
                        z: (0.5 * yaw).sin(),
                        w: (0.5 * yaw).cos(),
                    },
                },
                covariance: Covariance([0.0; 36]),
            },
            twist: TwistWithCovariance {
                twist: Twist {
                    linear: zero,
                    angular: zero,
                },
                covariance: Covariance([0.0; 36]),
            },
        }
    }

    const S: u64 = 1_000_000_000;

    #[test]
    fn a_vehicle_odometry_carries_the_sensor_by_its_mount() {
        let mount = Pose::from_parts(
            Translation3::new(0.0, 0.0, 1.73),
            UnitQuaternion::identity(),
        );
        let mut t = OdomTrack::new(Some(mount));
        t.add(&odom(S, 2.0, std::f64::consts::FRAC_PI_2, "base_link"))
            .unwrap();
        let p = t.sensor_pose("velodyne", S).unwrap();
        assert!((p.translation.vector - Vector3::new(2.0, 0.0, 1.73)).norm() < 1e-12);
        // An odometry of the sensor frame itself is its pose as it is.
        t.add(&odom(2 * S, 3.0, 0.0, "velodyne")).unwrap();
        assert_eq!(
            t.sensor_pose("velodyne", 2 * S)
                .unwrap()
                .translation
                .vector
                .z,
            0.0
        );
    }

    #[test]
    fn samples_that_are_no_pose_are_refused_and_the_track_is_bounded() {
        let mut t = OdomTrack::new(None);
        let mut bad = odom(S, f64::NAN, 0.0, "lidar");
        assert!(t.add(&bad).unwrap_err().contains("no pose"));
        bad = odom(S, 0.0, 0.0, "lidar");
        bad.pose.pose.orientation.w = 0.0;
        assert!(t.add(&bad).is_err());
        bad = odom(S, 0.0, 0.0, "lidar");
        bad.header.stamp.sec = -1;
        assert!(t.add(&bad).unwrap_err().contains("no time"));
        for k in 0..(KEEP as u64 + 20) {
            t.add(&odom(S + k * 1000, 0.0, 0.0, "lidar")).unwrap();
        }
        assert_eq!(t.len(), KEEP);
        // The same stamp again replaces, not adds.
        t.add(&odom(S + 1000 * KEEP as u64, 9.0, 0.0, "lidar"))
            .unwrap();
        assert_eq!(t.len(), KEEP);
    }
}
