//! The multi-frame history: the last N_f − 1 fitted frames with their poses, newest first.
//!
//! For the regridded past query the frames also share anchors. A frame joins the current
//! anchor (a frame before it) and keeps a copy of its components expressed in the anchor's
//! ground-aligned frame, converted once when it is stored. A query then moves each vector
//! of points once per anchor instead of once per past frame, and evaluates every past
//! component of an anchor in one run. A new frame starts a new anchor when the current one
//! has gathered N_f − 1 frames (so at most two anchors are ever stored) or lies more than
//! [`MAX_ANCHOR_DISTANCE`] away (so the f32 coordinates of the query stay small).

use std::collections::VecDeque;

use nalgebra::Isometry3;

use crate::model::FrameModel;
use crate::point::Pose;
use crate::query::{AnchoredFrame, QueryFrame, QueryTable};

/// Largest distance (m) between a frame and the anchor it joins. The query evaluates the
/// anchored components at points up to max range plus this far from the anchor's origin in
/// f32; at 40 + 80 m the rounding of a log-density stays below 1e-3 bits.
pub(crate) const MAX_ANCHOR_DISTANCE: f64 = 40.0;

/// A past frame kept for multi-frame queries.
#[derive(Debug, Clone)]
struct PastFrame {
    model: FrameModel,
    /// World from sensor.
    pose: Pose,
    /// Ground-aligned from sensor: the mount it was fitted on (`correct` mode moves it).
    mount: Isometry3<f64>,
    anchor: Anchor,
    /// The components in the anchor's frame; `None` if the frame is its own anchor.
    anchored: Option<QueryTable>,
}

/// The frame whose ground-aligned frame anchored components are expressed in.
#[derive(Debug, Clone, Copy)]
struct Anchor {
    id: u64,
    /// World from sensor.
    pose: Pose,
    /// Ground-aligned from sensor.
    mount: Isometry3<f64>,
}

/// The past frames, newest first, and the anchor new frames join.
#[derive(Debug, Default)]
pub(crate) struct History {
    frames: VecDeque<PastFrame>,
    /// The anchor a new frame joins, and how many stored frames have used it.
    current: Option<(Anchor, usize)>,
    next_id: u64,
}

/// Per stored frame, query scan → past frame and query scan → its anchor (ground-aligned
/// frames both).
pub(crate) type FrameTransforms = [Isometry3<f64>; 2];

impl History {
    pub(crate) fn len(&self) -> usize {
        self.frames.len()
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// World pose of the newest frame.
    pub(crate) fn newest_pose(&self) -> Option<&Pose> {
        self.frames.front().map(|f| &f.pose)
    }

    /// Component count over all stored frames.
    pub(crate) fn components(&self) -> usize {
        self.frames.iter().map(|f| f.model.components().len()).sum()
    }

    pub(crate) fn clear(&mut self) {
        self.frames.clear();
        self.current = None;
    }

    /// Stores a frame fitted at world pose `pose`, keeping at most `keep` frames (the
    /// oldest drops out). With `share_anchors` (the regridded query) it joins the current
    /// anchor or starts a new one; otherwise every frame is its own anchor and nothing is
    /// converted. `mount` maps sensor to ground-aligned coordinates.
    pub(crate) fn push(
        &mut self,
        model: FrameModel,
        pose: Pose,
        keep: usize,
        share_anchors: bool,
        mount: &Isometry3<f64>,
    ) {
        if keep == 0 {
            return;
        }
        while self.frames.len() >= keep {
            self.frames.pop_back();
        }
        let joins = self.current.filter(|(anchor, used)| {
            share_anchors
                && *used < keep
                && (pose.translation.vector - anchor.pose.translation.vector).norm()
                    <= MAX_ANCHOR_DISTANCE
        });
        let (anchor, anchored) = match joins {
            Some((anchor, used)) => {
                let to_anchor = between((&anchor.mount, &anchor.pose), (&pose, mount));
                self.current = Some((anchor, used + 1));
                (anchor, Some(QueryTable::moved(&model, &to_anchor)))
            }
            None => {
                let anchor = Anchor {
                    id: self.next_id,
                    pose,
                    mount: *mount,
                };
                self.next_id += 1;
                self.current = Some((anchor, 1));
                (anchor, None)
            }
        };
        self.frames.push_front(PastFrame {
            model,
            pose,
            mount: *mount,
            anchor,
            anchored,
        });
    }

    /// The transforms of every stored frame for a query scan at world pose `pose`,
    /// segmented on `mount`.
    pub(crate) fn transforms(&self, mount: &Isometry3<f64>, pose: &Pose) -> Vec<FrameTransforms> {
        self.frames
            .iter()
            .map(|f| {
                [
                    between((&f.mount, &f.pose), (pose, mount)),
                    between((&f.anchor.mount, &f.anchor.pose), (pose, mount)),
                ]
            })
            .collect()
    }

    /// The stored frames to query, newest first, with `transforms` from
    /// [`History::transforms`].
    pub(crate) fn query_frames<'a>(
        &'a self,
        transforms: &'a [FrameTransforms],
    ) -> impl Iterator<Item = QueryFrame<'a>> {
        self.frames
            .iter()
            .zip(transforms)
            .map(|(f, [to_past, to_anchor])| QueryFrame {
                model: &f.model,
                transform: Some(to_past),
                anchored: Some(AnchoredFrame {
                    anchor: f.anchor.id,
                    table: f.anchored.as_ref().unwrap_or(f.model.query_table()),
                    transform: to_anchor,
                }),
            })
    }
}

/// Maps the ground-aligned frame of the scan at world pose `to` (segmented on `to_mount`)
/// into that of the scan at `from` (on `from_mount`): query scan → past frame, as the query
/// needs it. The mounts differ only while `correct` mode moves the mount in use.
fn between(
    (from_mount, from): (&Isometry3<f64>, &Pose),
    (to, to_mount): (&Pose, &Isometry3<f64>),
) -> Isometry3<f64> {
    from_mount * from.inverse() * to * to_mount.inverse()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

    use super::*;
    use nalgebra::Translation3;

    /// A vehicle driving along x, `step` metres per frame.
    fn pose(step: f64, k: usize) -> Pose {
        Translation3::new(step * k as f64, 0.0, 0.0).into()
    }

    fn anchors(h: &History) -> Vec<u64> {
        let mut ids: Vec<u64> = h.frames.iter().map(|f| f.anchor.id).collect();
        ids.dedup();
        ids
    }

    #[test]
    fn frames_share_at_most_two_anchors_and_an_anchor_keeps_no_copy() {
        let mut h = History::default();
        let mount = Isometry3::identity();
        for k in 0..40 {
            h.push(FrameModel::default(), pose(0.8, k), 15, true, &mount);
            assert!(h.len() <= 15);
            let ids = anchors(&h);
            // Newest first, consecutive per anchor, each anchor id seen once.
            assert!(
                ids.len() <= 2 && ids.windows(2).all(|w| w[0] > w[1]),
                "{ids:?}"
            );
            for f in &h.frames {
                let own = f.anchor.pose == f.pose;
                assert_eq!(
                    own,
                    f.anchored.is_none(),
                    "frame at {}",
                    f.pose.translation.x
                );
            }
        }
        // 40 frames, a new anchor every 15.
        assert_eq!(h.next_id, 3);
    }

    #[test]
    fn a_frame_too_far_from_the_anchor_starts_a_new_one() {
        let mut h = History::default();
        let mount = Isometry3::identity();
        let step = MAX_ANCHOR_DISTANCE / 2.5;
        for k in 0..4 {
            h.push(FrameModel::default(), pose(step, k), 15, true, &mount);
        }
        // Frames 0–2 are within reach of frame 0; frame 3 is not.
        let ids: Vec<u64> = h.frames.iter().map(|f| f.anchor.id).collect();
        assert_eq!(ids, [1, 0, 0, 0]);
    }

    #[test]
    fn without_shared_anchors_every_frame_is_its_own() {
        let mut h = History::default();
        let mount = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 1.73),
            nalgebra::UnitQuaternion::from_euler_angles(0.01, 0.02, 0.0),
        );
        for k in 0..5 {
            h.push(FrameModel::default(), pose(0.8, k), 3, false, &mount);
        }
        assert_eq!(h.len(), 3);
        assert!(h.frames.iter().all(|f| f.anchored.is_none()));
        // Query → past and query → anchor are then one transform.
        let query = pose(0.8, 5);
        for [to_past, to_anchor] in h.transforms(&mount, &query) {
            assert_eq!(to_past, to_anchor);
        }
        // Newest first: the query sensor (its origin, in its ground-aligned frame) is 0.8 m
        // ahead of the newest frame's.
        let newest = &h.transforms(&mount, &query)[0][0];
        let moved = newest * (mount * nalgebra::Point3::origin());
        assert!((moved - mount * nalgebra::Point3::new(0.8, 0.0, 0.0)).norm() < 1e-9);
    }

    /// While `correct` mode moves the mount, each frame keeps the one it was fitted on: a
    /// point fixed in the world, seen in the query's ground-aligned frame (on one mount),
    /// lands where the past frame saw it (on another), for the past frame and its anchor.
    #[test]
    fn frames_fitted_on_other_mounts_map_the_world_consistently() {
        let mount = |h: f64, pitch: f64| {
            Isometry3::from_parts(
                Translation3::new(0.0, 0.0, h),
                nalgebra::UnitQuaternion::from_euler_angles(0.0, pitch, 0.0),
            )
        };
        let mounts = [mount(1.0, 0.0), mount(1.1, 0.03), mount(1.2, 0.06)];
        let mut h = History::default();
        for (k, m) in mounts.iter().enumerate() {
            h.push(FrameModel::default(), pose(0.8, k), 15, true, m);
        }
        let (query, now) = (pose(0.8, 3), mount(1.25, 0.08));
        let world = nalgebra::Point3::new(12.0, -3.0, 0.4);
        let seen_now = now * query.inverse() * world;
        for (f, [to_past, to_anchor]) in h.frames.iter().zip(h.transforms(&now, &query)) {
            let seen_then = f.mount * f.pose.inverse() * world;
            assert!((to_past * seen_now - seen_then).norm() < 1e-9);
            let seen_by_anchor = f.anchor.mount * f.anchor.pose.inverse() * world;
            assert!((to_anchor * seen_now - seen_by_anchor).norm() < 1e-9);
        }
    }
}
