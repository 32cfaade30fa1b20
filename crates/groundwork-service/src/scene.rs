//! The proposals as Foxglove draws them (`foxglove.SceneUpdate`): one box per proposal in
//! the ground frame, for the live view and for recordings alike.

use foxglove::messages::{
    Color, CubePrimitive, KeyValuePair, Pose, Quaternion, SceneEntity, SceneEntityDeletion,
    SceneUpdate, Timestamp, Vector3, scene_entity_deletion,
};
use groundwork_detect::ProposalFlags;
use groundwork_io::transform::GROUND_FRAME;
use groundwork_msg::ProposalsHeader;

/// A scan's proposals as boxes, stamped `stamp_ns`: the last scan's boxes go (a deletion
/// of all), this scan's come.
pub fn proposals(h: &ProposalsHeader, stamp_ns: u64) -> SceneUpdate {
    let n = (h.proposal_count as usize).min(h.records.len());
    let entities = h.records[..n]
        .iter()
        .map(|r| {
            let flags = ProposalFlags(r.flags);
            let ([x, y, z], [qx, qy, qz, qw]) = (r.box_center(), r.box_rotation());
            let [sx, sy, sz] = r.box_size();
            // Object-like boxes green, flagged ones (walls, trees, ...) faint grey.
            let color = if flags.is_object_like() {
                Color {
                    r: 0.2,
                    g: 0.85,
                    b: 0.3,
                    a: 0.5,
                }
            } else {
                Color {
                    r: 0.6,
                    g: 0.6,
                    b: 0.6,
                    a: 0.25,
                }
            };
            SceneEntity {
                timestamp: Some(timestamp(stamp_ns)),
                frame_id: GROUND_FRAME.into(),
                id: r.id.to_string(),
                metadata: vec![
                    KeyValuePair {
                        key: "class".into(),
                        value: flags.class_name(),
                    },
                    KeyValuePair {
                        key: "points".into(),
                        value: r.points.to_string(),
                    },
                ],
                cubes: vec![CubePrimitive {
                    pose: Some(Pose {
                        position: Some(Vector3 { x, y, z }),
                        orientation: Some(Quaternion {
                            x: qx,
                            y: qy,
                            z: qz,
                            w: qw,
                        }),
                    }),
                    size: Some(Vector3 {
                        x: sx,
                        y: sy,
                        z: sz,
                    }),
                    color: Some(color),
                }],
                ..Default::default()
            }
        })
        .collect();
    SceneUpdate {
        deletions: vec![SceneEntityDeletion {
            timestamp: Some(timestamp(stamp_ns)),
            r#type: scene_entity_deletion::Type::All as i32,
            id: String::new(),
        }],
        entities,
    }
}

/// A Foxglove timestamp of nanoseconds since the epoch.
pub fn timestamp(ns: u64) -> Timestamp {
    // u64 nanoseconds end in 2554: seconds fit u32 until 2106, later saturate.
    let sec = u32::try_from(ns / 1_000_000_000).unwrap_or(u32::MAX);
    Timestamp::new(sec, (ns % 1_000_000_000) as u32)
}
