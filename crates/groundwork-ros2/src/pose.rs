//! Timed poses, as odometry and TF give them: a track of stamped samples that answers the
//! pose at any stamp near them, and the checks that turn a ROS message into a pose.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::msg::Time;

/// A rigid transform (parent from child; for a scan, world from sensor).
pub type Pose = Isometry3<f64>;

/// Samples kept per track: five seconds of a 100 Hz odometry or transform.
pub const KEEP: usize = 500;

/// How far past the newest sample (or before the oldest) a stamp may lie and still get a
/// pose, extrapolated at the last known motion: odometry and TF published at 10–100 Hz may
/// trail a cloud by a sample or two. Further: no pose (the scan is segmented on its own).
pub const HOLD_NS: u64 = 100_000_000;

/// A ROS stamp in ns since 1970; a stamp before 1970 or with nanoseconds past a second is
/// no time.
pub fn stamp_ns(t: &Time) -> Result<u64, String> {
    u64::try_from(t.sec)
        .ok()
        .filter(|_| t.nanosec < 1_000_000_000)
        .map(|s| s * 1_000_000_000 + u64::from(t.nanosec))
        .ok_or_else(|| format!("stamp {}.{:09} is no time", t.sec, t.nanosec))
}

/// A pose from a translation and a quaternion (x, y, z, w), or why it is none: a value
/// that is not finite, or a quaternion too short to be a rotation. The quaternion is
/// normalised (drivers round theirs).
pub fn pose_of(translation: [f64; 3], [x, y, z, w]: [f64; 4]) -> Result<Pose, String> {
    let q = Quaternion::new(w, x, y, z);
    if translation
        .iter()
        .chain(&[x, y, z, w])
        .any(|v| !v.is_finite())
    {
        return Err("a value is not finite".into());
    }
    if q.norm() < 1e-6 {
        return Err("the rotation is a zero quaternion".into());
    }
    let [tx, ty, tz] = translation;
    Ok(Pose::from_parts(
        Translation3::new(tx, ty, tz),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// Stamped poses of one thing, in stamp order, at most [`KEEP`].
#[derive(Debug, Clone, Default)]
pub struct PoseTrack {
    samples: VecDeque<(u64, Pose)>,
}

impl PoseTrack {
    /// Samples held.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether no sample is held.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Adds a sample (samples may come out of order); one with the stamp of a held sample
    /// replaces it; the oldest goes beyond [`KEEP`].
    pub fn add(&mut self, stamp: u64, pose: Pose) {
        let at = self.samples.partition_point(|&(s, _)| s < stamp);
        match self.samples.get_mut(at) {
            Some((s, held)) if *s == stamp => *held = pose,
            _ => self.samples.insert(at, (stamp, pose)),
        }
        if self.samples.len() > KEEP {
            self.samples.pop_front();
        }
    }

    /// The pose at `stamp`: a sample's own at its stamp; between two samples, the motion
    /// between them in proportion; up to [`HOLD_NS`] outside them, the nearest two
    /// samples' motion carried on. `None`: no sample near enough.
    pub fn at(&self, stamp: u64) -> Option<Pose> {
        let n = self.samples.len();
        let after = self.samples.partition_point(|&(s, _)| s <= stamp);
        Some(match (after, self.samples.get(after.wrapping_sub(1))) {
            (_, Some(&(s, p))) if s == stamp => p,
            (0, _) => {
                let &(s, p) = self.samples.front()?;
                (s - stamp <= HOLD_NS).then_some(())?;
                match self.samples.get(1) {
                    Some(&(s1, p1)) => between((s, p), (s1, p1), stamp),
                    None => p,
                }
            }
            (a, _) if a == n => {
                let &(s, p) = self.samples.back()?;
                (stamp - s <= HOLD_NS).then_some(())?;
                match n.checked_sub(2).and_then(|i| self.samples.get(i)) {
                    Some(&(s0, p0)) => between((s0, p0), (s, p), stamp),
                    None => p,
                }
            }
            (a, _) => between(self.samples[a - 1], self.samples[a], stamp),
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

#[cfg(test)]
mod tests {
    use super::*;

    const S: u64 = 1_000_000_000;

    fn at_x(x: f64, yaw: f64) -> Pose {
        pose_of(
            [x, 0.0, 0.0],
            [0.0, 0.0, (0.5 * yaw).sin(), (0.5 * yaw).cos()],
        )
        .unwrap()
    }

    #[test]
    fn a_stamp_between_samples_gets_the_motion_in_proportion() {
        let mut t = PoseTrack::default();
        // Out of order, as two topics may interleave.
        t.add(100 * S + S / 10, at_x(1.0, 0.2));
        t.add(100 * S, at_x(0.0, 0.0));
        let p = t.at(100 * S + S / 40).unwrap();
        assert!((p.rotation.angle() - 0.05).abs() < 1e-12);
        // On the arc from the first pose to the second, a quarter of the way.
        assert_eq!(t.at(100 * S + S / 10).unwrap().translation.vector.x, 1.0);
        assert!(p.translation.vector.x > 0.2 && p.translation.vector.x < 0.3);
    }

    #[test]
    fn near_the_ends_the_motion_carries_on_and_far_from_them_there_is_no_pose() {
        let mut t = PoseTrack::default();
        assert!(t.at(5 * S).is_none());
        t.add(5 * S, at_x(0.0, 0.0));
        t.add(5 * S + S / 10, at_x(1.0, 0.0));
        let ahead = t.at(5 * S + S / 10 + S / 20).unwrap();
        assert!((ahead.translation.vector.x - 1.5).abs() < 1e-12);
        let before = t.at(5 * S - S / 20).unwrap();
        assert!((before.translation.vector.x + 0.5).abs() < 1e-12);
        assert!(t.at(5 * S + S / 10 + HOLD_NS + 1).is_none());
        assert!(t.at(5 * S - HOLD_NS - 1).is_none());
    }

    #[test]
    fn the_track_is_bounded_and_a_stamp_seen_before_replaces() {
        let mut t = PoseTrack::default();
        for k in 0..(KEEP as u64 + 20) {
            t.add(S + k * 1000, at_x(0.0, 0.0));
        }
        assert_eq!(t.len(), KEEP);
        t.add(S + 1000 * (KEEP as u64 + 19), at_x(9.0, 0.0));
        assert_eq!(t.len(), KEEP);
        let last = t.at(S + 1000 * (KEEP as u64 + 19)).unwrap();
        assert_eq!(last.translation.vector.x, 9.0);
    }

    #[test]
    fn values_that_are_no_pose_or_no_time_are_refused() {
        assert!(pose_of([f64::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).is_err());
        assert!(pose_of([0.0; 3], [0.0, 0.0, 0.0, 0.0]).is_err());
        assert!(pose_of([0.0; 3], [0.0, f64::INFINITY, 0.0, 1.0]).is_err());
        // A rounded quaternion is normalised.
        let p = pose_of([0.0; 3], [0.0, 0.0, 0.0, 0.999]).unwrap();
        assert!((p.rotation.quaternion().norm() - 1.0).abs() < 1e-12);
        assert!(
            stamp_ns(&Time {
                sec: -1,
                nanosec: 0
            })
            .is_err()
        );
        assert!(
            stamp_ns(&Time {
                sec: 1,
                nanosec: 1_000_000_000
            })
            .is_err()
        );
        assert_eq!(stamp_ns(&Time { sec: 2, nanosec: 5 }), Ok(2 * S + 5));
    }
}
