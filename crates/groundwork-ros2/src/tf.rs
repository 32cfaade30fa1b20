//! Poses for the multi-frame history from ROS's transform tree (`/tf` and `/tf_static`):
//! each cloud gets its frame's pose in a fixed frame (`odom` by default) at its stamp, as
//! tf2's `lookupTransform(fixed, cloud frame, stamp)` would give it.
//!
//! The tree keeps, per child frame, its parent and either one static transform or the
//! stamped samples of a moving one (each answered at a stamp as an odometry track is:
//! [`PoseTrack::at`]). A lookup walks from each of the two frames up to the tree's root and
//! composes the transforms on the way; frames whose roots differ are not connected. As in
//! tf2, a frame has one parent: a transform naming another parent re-parents the frame.

use std::collections::HashMap;

use crate::msg::{TFMessage, TransformStamped};
use crate::pose::{Pose, PoseTrack, pose_of, stamp_ns};

/// Frames held at most: a flood of invented frame names does not grow the bridge.
pub const MAX_FRAMES: usize = 1000;
/// Longest chain from a frame to its root (a tree deeper than this is taken for a loop).
pub const MAX_DEPTH: usize = 64;

/// How a frame hangs from its parent.
#[derive(Debug, Clone)]
enum Link {
    /// From `/tf_static`: the same at every stamp.
    Static(Pose),
    /// From `/tf`: stamped samples.
    Moving(PoseTrack),
}

/// One frame's parent and its transform (parent from child).
#[derive(Debug, Clone)]
struct Edge {
    parent: String,
    link: Link,
}

/// The transform tree as seen so far.
#[derive(Debug, Clone, Default)]
pub struct TfTree {
    edges: HashMap<String, Edge>,
}

impl TfTree {
    /// Frames that have a parent.
    pub fn len(&self) -> usize {
        self.edges.len()
    }

    /// Whether no transform has been taken.
    pub fn is_empty(&self) -> bool {
        self.edges.is_empty()
    }

    /// Takes the transforms of one message (`is_static`: from `/tf_static`). Returns how
    /// many were taken and, for the others, why each was refused (no time, no pose, a frame
    /// its own parent, an empty name, too many frames).
    pub fn add(&mut self, msg: &TFMessage, is_static: bool) -> (usize, Vec<String>) {
        let mut refused = Vec::new();
        let mut taken = 0;
        for t in &msg.transforms {
            match self.add_one(t, is_static) {
                Ok(()) => taken += 1,
                Err(e) => refused.push(e),
            }
        }
        (taken, refused)
    }

    fn add_one(&mut self, t: &TransformStamped, is_static: bool) -> Result<(), String> {
        // tf2 ignores a leading slash (ROS 1's frame names had one).
        let parent = t.header.frame_id.trim_start_matches('/');
        let child = t.child_frame_id.trim_start_matches('/');
        let what = || format!("transform {parent:?} -> {child:?}");
        if parent.is_empty() || child.is_empty() {
            return Err(format!("{}: a frame has no name", what()));
        }
        if parent == child {
            return Err(format!("{}: a frame cannot be its own parent", what()));
        }
        let (v, q) = (&t.transform.translation, &t.transform.rotation);
        let pose = pose_of([v.x, v.y, v.z], [q.x, q.y, q.z, q.w])
            .map_err(|e| format!("{}: {e}", what()))?;
        if !self.edges.contains_key(child) && self.edges.len() >= MAX_FRAMES {
            return Err(format!("{}: more than {MAX_FRAMES} frames", what()));
        }
        let link = if is_static {
            Link::Static(pose)
        } else {
            let stamp = stamp_ns(&t.header.stamp).map_err(|e| format!("{}: {e}", what()))?;
            let mut track = match self.edges.remove(child) {
                // The same moving link: one more sample.
                Some(Edge {
                    parent: p,
                    link: Link::Moving(track),
                }) if p == parent => track,
                // New, re-parented, or static before: its samples start afresh.
                _ => PoseTrack::default(),
            };
            track.add(stamp, pose);
            Link::Moving(track)
        };
        self.edges.insert(
            child.to_string(),
            Edge {
                parent: parent.to_string(),
                link,
            },
        );
        Ok(())
    }

    /// The frames from `frame` up to its root, `frame` first.
    fn ancestry<'a>(&'a self, frame: &'a str) -> Result<Vec<&'a str>, String> {
        let mut chain = vec![frame];
        while let Some(edge) = self.edges.get(chain[chain.len() - 1]) {
            if chain.len() > MAX_DEPTH {
                return Err(format!(
                    "frame {frame:?} is more than {MAX_DEPTH} frames from a root (a loop?)"
                ));
            }
            chain.push(&edge.parent);
        }
        Ok(chain)
    }

    /// The pose of `chain[0]` in `chain[n]` at `stamp`, through the links between them.
    fn along(&self, chain: &[&str], stamp: u64) -> Result<Pose, String> {
        let mut pose = Pose::identity();
        for &child in chain {
            // Every frame but the last of an ancestry has an edge.
            let Some(edge) = self.edges.get(child) else {
                break;
            };
            let step = match &edge.link {
                Link::Static(p) => *p,
                Link::Moving(track) => track.at(stamp).ok_or_else(|| {
                    format!(
                        "no transform {:?} -> {child:?} within {} ms of the stamp",
                        edge.parent,
                        crate::pose::HOLD_NS / 1_000_000
                    )
                })?,
            };
            pose = step * pose;
        }
        Ok(pose)
    }

    /// The pose of `frame` in `fixed` at `stamp` (ns since 1970): `fixed` from `frame`,
    /// through their nearest common ancestor only (links above it need no sample at the
    /// stamp). An error says why there is none (frames not connected, no sample near the
    /// stamp, a loop).
    pub fn lookup(&self, fixed: &str, frame: &str, stamp: u64) -> Result<Pose, String> {
        let (fixed, frame) = (fixed.trim_start_matches('/'), frame.trim_start_matches('/'));
        let up = self.ancestry(frame)?;
        let down = self.ancestry(fixed)?;
        let Some((a, b)) = up
            .iter()
            .enumerate()
            .find_map(|(a, f)| down.iter().position(|g| g == f).map(|b| (a, b)))
        else {
            return Err(format!(
                "frames {frame:?} and {fixed:?} are not connected (their roots are {:?} and \
                 {:?})",
                up[up.len() - 1],
                down[down.len() - 1]
            ));
        };
        // The chains up to the common frame, without it: its own link is not needed.
        let common_from_frame = self.along(&up[..a], stamp)?;
        let common_from_fixed = self.along(&down[..b], stamp)?;
        Ok(common_from_fixed.inverse() * common_from_frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{Header, Quaternion, Time, Transform, Vector3};
    use nalgebra::{Translation3, UnitQuaternion, Vector3 as V};

    const S: u64 = 1_000_000_000;

    fn tf(parent: &str, child: &str, stamp: u64, [x, y, z]: [f64; 3], yaw: f64) -> TFMessage {
        TFMessage {
            transforms: vec![TransformStamped {
                header: Header {
                    stamp: Time::from_ns(stamp),
                    frame_id: parent.into(),
                },
                child_frame_id: child.into(),
                transform: Transform {
                    translation: Vector3 { x, y, z },
                    rotation: Quaternion {
                        x: 0.0,
                        y: 0.0,
                        z: (0.5 * yaw).sin(),
                        w: (0.5 * yaw).cos(),
                    },
                },
            }],
        }
    }

    fn pose(t: [f64; 3], yaw: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        )
    }

    fn close(a: &Pose, b: &Pose) -> bool {
        (a.translation.vector - b.translation.vector).norm() < 1e-9
            && a.rotation.angle_to(&b.rotation) < 1e-9
    }

    /// map -> odom (static), odom -> base_link (moving), base_link -> velodyne (static).
    fn vehicle() -> TfTree {
        let mut t = TfTree::default();
        t.add(&tf("map", "odom", 0, [100.0, 0.0, 0.0], 1.0), true);
        t.add(&tf("base_link", "velodyne", 0, [1.2, 0.0, 1.73], 0.1), true);
        t.add(
            &tf("odom", "base_link", 10 * S, [0.0, 0.0, 0.0], 0.0),
            false,
        );
        t.add(
            &tf("/odom", "base_link", 10 * S + S / 10, [1.0, 0.0, 0.0], 0.2),
            false,
        );
        t
    }

    #[test]
    fn a_chain_composes_moving_and_static_links_at_the_stamp() {
        let t = vehicle();
        let mount = pose([1.2, 0.0, 1.73], 0.1);
        let at = t.lookup("odom", "velodyne", 10 * S).unwrap();
        assert!(close(&at, &mount));
        let end = t.lookup("odom", "velodyne", 10 * S + S / 10).unwrap();
        assert!(close(&end, &(pose([1.0, 0.0, 0.0], 0.2) * mount)));
        // Half way: the base moved half the way and turned half the angle.
        let mid = t.lookup("odom", "/velodyne", 10 * S + S / 20).unwrap();
        let base = mid * mount.inverse();
        assert!((base.rotation.angle() - 0.1).abs() < 1e-12);
        assert!((base.translation.vector.x - 0.5).abs() < 0.01);
        // Above the fixed frame the tree goes on to map: it does not matter.
        let in_map = t.lookup("map", "velodyne", 10 * S).unwrap();
        assert!(close(&in_map, &(pose([100.0, 0.0, 0.0], 1.0) * mount)));
        // The fixed frame may lie anywhere in the tree: the sensor in the vehicle's base.
        let in_base = t.lookup("base_link", "velodyne", 3 * S).unwrap();
        assert!(close(&in_base, &mount));
        assert!(close(
            &t.lookup("velodyne", "velodyne", 0).unwrap(),
            &Pose::identity()
        ));
    }

    #[test]
    fn no_pose_far_from_the_samples_nor_between_frames_not_connected() {
        let mut t = vehicle();
        let far = t.lookup("odom", "velodyne", 12 * S).unwrap_err();
        assert!(far.contains("\"odom\" -> \"base_link\""), "{far}");
        t.add(&tf("world", "gps", 0, [0.0; 3], 0.0), true);
        let apart = t.lookup("odom", "gps", 10 * S).unwrap_err();
        assert!(apart.contains("not connected"), "{apart}");
        // A frame never seen is its own root: not connected either.
        assert!(t.lookup("odom", "os_lidar", 10 * S).is_err());
    }

    #[test]
    fn a_transform_naming_another_parent_re_parents_the_frame() {
        let mut t = vehicle();
        t.add(
            &tf("base_footprint", "velodyne", 0, [0.0, 0.0, 2.0], 0.0),
            true,
        );
        assert!(t.lookup("odom", "velodyne", 10 * S).is_err());
        let v = t.lookup("base_footprint", "velodyne", 10 * S).unwrap();
        assert_eq!(v.translation.vector, V::new(0.0, 0.0, 2.0));
        // A moving link whose parent changes starts its samples afresh: base_link now
        // hangs from map, and odom (also map's) reaches it through map.
        t.add(&tf("map", "base_link", 11 * S, [5.0, 0.0, 0.0], 0.0), false);
        assert!(t.lookup("map", "base_link", 10 * S).is_err());
        let odom_base = t.lookup("odom", "base_link", 11 * S).unwrap();
        let expected = pose([100.0, 0.0, 0.0], 1.0).inverse() * pose([5.0, 0.0, 0.0], 0.0);
        assert!(close(&odom_base, &expected));
    }

    #[test]
    fn bad_transforms_are_refused_with_their_reason_and_loops_end() {
        let mut t = TfTree::default();
        let mut bad = tf("odom", "base_link", S, [f64::NAN, 0.0, 0.0], 0.0);
        let (taken, refused) = t.add(&bad, false);
        assert_eq!(taken, 0);
        assert!(refused[0].contains("not finite"), "{refused:?}");
        bad = tf("odom", "odom", S, [0.0; 3], 0.0);
        assert!(t.add(&bad, true).1[0].contains("own parent"));
        bad = tf("", "x", S, [0.0; 3], 0.0);
        assert!(t.add(&bad, true).1[0].contains("no name"));
        bad = tf("odom", "base_link", S, [0.0; 3], 0.0);
        bad.transforms[0].header.stamp.sec = -5;
        assert!(t.add(&bad, false).1[0].contains("no time"));
        // A static transform's stamp does not matter.
        assert_eq!(t.add(&bad, true).0, 1);
        // a -> b -> a: a lookup ends with an error, not a hang.
        t.add(&tf("b", "a", 0, [0.0; 3], 0.0), true);
        t.add(&tf("a", "b", 0, [0.0; 3], 0.0), true);
        assert!(t.lookup("odom", "a", S).unwrap_err().contains("loop"));
        for k in 0..MAX_FRAMES + 5 {
            t.add(&tf("odom", &format!("f{k}"), 0, [0.0; 3], 0.0), true);
        }
        assert_eq!(t.len(), MAX_FRAMES);
        let (_, refused) = t.add(&tf("odom", "one_more", 0, [0.0; 3], 0.0), true);
        assert!(refused[0].contains("frames"), "{refused:?}");
    }
}
