//! Poses for the multi-frame history from a `nav_msgs/Odometry` topic: each cloud gets the
//! world pose of its sensor at its stamp, from the odometry samples around that stamp.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::msg::Odometry;

/// A rigid transform (world from frame).
pub type Pose = Isometry3<f64>;

/// Samples kept: five seconds of a 100 Hz odometry.
const KEEP: usize = 500;

/// How far past the newest sample (or before the oldest) a stamp may lie and still get a
/// pose, extrapolated at the last known motion: odometry published at 10–100 Hz may trail
/// a cloud by a sample or two. Further: no pose (the scan is segmented on its own).
pub const HOLD_NS: u64 = 100_000_000;

/// The odometry samples seen, in stamp order.
#[derive(Debug)]
pub struct OdomTrack {
    samples: VecDeque<(u64, Pose)>,
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
            samples: VecDeque::with_capacity(KEEP),
            child_frame: String::new(),
            base_from_sensor,
        }
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether no sample is held.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Adds one sample. A sample that is no pose (a stamp before 1970, a non-finite value,
    /// a zero quaternion) is refused with the reason; one with the stamp of a held sample
    /// replaces it.
    pub fn add(&mut self, odom: &Odometry) -> Result<(), String> {
        let t = &odom.header.stamp;
        let stamp = u64::try_from(t.sec)
            .ok()
            .filter(|_| t.nanosec < 1_000_000_000)
            .map(|s| s * 1_000_000_000 + u64::from(t.nanosec))
            .ok_or_else(|| format!("odometry stamp {}.{:09} is no time", t.sec, t.nanosec))?;
        let (p, q) = (&odom.pose.pose.position, &odom.pose.pose.orientation);
        let q = Quaternion::new(q.w, q.x, q.y, q.z);
        let values = [p.x, p.y, p.z, q.w, q.i, q.j, q.k];
        if values.iter().any(|v| !v.is_finite()) || q.norm() < 1e-6 {
            return Err(format!("odometry at {stamp} ns holds no pose"));
        }
        let pose = Pose::from_parts(
            Translation3::new(p.x, p.y, p.z),
            UnitQuaternion::from_quaternion(q),
        );
        let at = self.samples.partition_point(|&(s, _)| s < stamp);
        match self.samples.get_mut(at) {
            Some((s, held)) if *s == stamp => *held = pose,
            _ => self.samples.insert(at, (stamp, pose)),
        }
        if self.samples.len() > KEEP {
            self.samples.pop_front();
        }
        self.child_frame.clone_from(&odom.child_frame_id);
        Ok(())
    }

    /// The world pose of a scan in `frame` stamped `stamp_ns`: the odometry's pose at that
    /// stamp (a sample's own at its stamp; between two samples, the motion between them in
    /// proportion; up to [`HOLD_NS`] outside them, the nearest two samples' motion carried
    /// on), composed with the mount unless the odometry is the pose of `frame` itself.
    /// `None`: no sample near enough.
    pub fn sensor_pose(&self, frame: &str, stamp_ns: u64) -> Option<Pose> {
        let n = self.samples.len();
        let after = self.samples.partition_point(|&(s, _)| s <= stamp_ns);
        let odom = match (after, self.samples.get(after.wrapping_sub(1))) {
            (_, Some(&(s, p))) if s == stamp_ns => p,
            (0, _) => {
                let &(s, p) = self.samples.front()?;
                (s - stamp_ns <= HOLD_NS).then_some(())?;
                match self.samples.get(1) {
                    Some(&(s1, p1)) => between((s, p), (s1, p1), stamp_ns),
                    None => p,
                }
            }
            (a, _) if a == n => {
                let &(s, p) = self.samples.back()?;
                (stamp_ns - s <= HOLD_NS).then_some(())?;
                match n.checked_sub(2).and_then(|i| self.samples.get(i)) {
                    Some(&(s0, p0)) => between((s0, p0), (s, p), stamp_ns),
                    None => p,
                }
            }
            (a, _) => between(self.samples[a - 1], self.samples[a], stamp_ns),
        };
        Some(match &self.base_from_sensor {
            Some(mount) if self.child_frame != frame => odom * mount,
            _ => odom,
        })
    }
}

/// The pose at `t` on the motion from sample `a` to sample `b` (at constant velocity in
/// `a`'s frame; `t` may lie outside them).
fn between((ta, pa): (u64, Pose), (tb, pb): (u64, Pose), t: u64) -> Pose {
    if tb == ta {
        return pb;
    }
    let f = (t as f64 - ta as f64) / (tb as f64 - ta as f64);
    let step = pa.inverse() * pb;
    let scaled = Pose::from_parts(
        Translation3::from(step.translation.vector * f),
        UnitQuaternion::from_scaled_axis(step.rotation.scaled_axis() * f),
    );
    pa * scaled
}

/// A pose as the scan header's row-major 4×4 matrix.
pub fn row_major(p: &Pose) -> [f64; 16] {
    let m = p.to_homogeneous();
    std::array::from_fn(|i| m[(i / 4, i % 4)])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{
        Covariance, Header, Pose as RosPose, PoseWithCovariance, Quaternion as RosQ, Time, Twist,
        TwistWithCovariance, Vector3 as RosV,
    };
    use nalgebra::Vector3;

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
    fn a_stamp_between_samples_gets_the_motion_in_proportion() {
        let mut t = OdomTrack::new(None);
        // Out of order, as two topics may interleave.
        t.add(&odom(100 * S + S / 10, 1.0, 0.2, "lidar")).unwrap();
        t.add(&odom(100 * S, 0.0, 0.0, "lidar")).unwrap();
        let p = t.sensor_pose("lidar", 100 * S + S / 40).unwrap();
        assert!((p.rotation.angle() - 0.05).abs() < 1e-12);
        // On the arc from the first pose to the second, a quarter of the way.
        let exact = t.sensor_pose("lidar", 100 * S + S / 10).unwrap();
        assert_eq!(exact.translation.vector.x, 1.0);
        assert!(p.translation.vector.x > 0.2 && p.translation.vector.x < 0.3);
    }

    #[test]
    fn near_the_ends_the_motion_carries_on_and_far_from_them_there_is_no_pose() {
        let mut t = OdomTrack::new(None);
        assert!(t.sensor_pose("lidar", 5 * S).is_none());
        t.add(&odom(5 * S, 0.0, 0.0, "lidar")).unwrap();
        t.add(&odom(5 * S + S / 10, 1.0, 0.0, "lidar")).unwrap();
        let ahead = t.sensor_pose("lidar", 5 * S + S / 10 + S / 20).unwrap();
        assert!((ahead.translation.vector.x - 1.5).abs() < 1e-12);
        let before = t.sensor_pose("lidar", 5 * S - S / 20).unwrap();
        assert!((before.translation.vector.x + 0.5).abs() < 1e-12);
        assert!(
            t.sensor_pose("lidar", 5 * S + S / 10 + HOLD_NS + 1)
                .is_none()
        );
        assert!(t.sensor_pose("lidar", 5 * S - HOLD_NS - 1).is_none());
    }

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

    #[test]
    fn row_major_is_the_header_layout() {
        let p = Pose::from_parts(Translation3::new(1.0, 2.0, 3.0), UnitQuaternion::identity());
        let m = row_major(&p);
        assert_eq!([m[3], m[7], m[11], m[15]], [1.0, 2.0, 3.0, 1.0]);
    }
}
