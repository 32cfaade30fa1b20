//! The zone model's near edge, from where the sensor first sees ground.
//!
//! A preset's near edge (`zones.min_range`) is set for its own mount: the HDL-64E's 2.7 m
//! keeps the KITTI car's roof out and lies inside the 3.7 m where its lowest beam meets the
//! road. Mounted lower, or pitched, the same sensor sees ground much nearer, and every
//! ground point inside the near edge is called non-ground. With the mount found, the
//! ground near the sensor is plain to see: the points within a band of the ground plane.

use groundwork_core::config::ZoneConfig;
use groundwork_core::point::Pose;
use nalgebra::Point3;
use serde::Serialize;

use crate::mount::{FrameMount, median};

/// Settings of the near-edge fit.
#[derive(Debug, Clone, PartialEq)]
pub struct NearEdgeConfig {
    /// Points within this height of the ground plane count as ground, metres.
    pub ground_band: f64,
    /// Per scan, the near edge of ground is this quantile of its ground points' range.
    pub quantile: f64,
    /// The zone model's near edge is put at this fraction of that range.
    pub margin: f64,
    /// A scan with fewer ground points than this does not count.
    pub min_points: usize,
}

impl Default for NearEdgeConfig {
    fn default() -> Self {
        Self {
            ground_band: 0.15,
            quantile: 0.01,
            margin: 0.9,
            min_points: 200,
        }
    }
}

/// Where the scans first see ground.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NearGround {
    /// Median over the scans of each scan's near edge of ground, metres.
    pub range: f64,
    /// Scans that counted.
    pub scans: usize,
}

/// One scan's near edge of ground (sensor frame, `mount`: ground-aligned from sensor):
/// the `quantile` of the horizontal range of its points within `ground_band` of the ground
/// plane, beyond `ego_radius`; `None` if fewer than `min_points` such points.
pub fn scan_near_ground(
    points: &[[f32; 3]],
    mount: &Pose,
    ego_radius: f64,
    cfg: &NearEdgeConfig,
) -> Option<f64> {
    let mut ranges: Vec<f64> = points
        .iter()
        .filter_map(|p| {
            let q = mount * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            let r = q.x.hypot(q.y);
            (q.z.abs() <= cfg.ground_band && r > ego_radius && r.is_finite()).then_some(r)
        })
        .collect();
    if ranges.len() < cfg.min_points.max(1) {
        return None;
    }
    let k = ((ranges.len() as f64 * cfg.quantile) as usize).min(ranges.len() - 1);
    Some(*ranges.select_nth_unstable_by(k, f64::total_cmp).1)
}

/// [`scan_near_ground`] on the scan's own view of the mount ([`crate::frame_mount`]): the
/// ground near the sensor is what that plane fits best.
pub fn view_near_ground(
    points: &[[f32; 3]],
    view: &FrameMount,
    ego_radius: f64,
    cfg: &NearEdgeConfig,
) -> Option<f64> {
    scan_near_ground(points, &view.pose()?, ego_radius, cfg)
}

/// The median of the scans' near edges; `None` with fewer than three.
pub fn combine_near_ground(mut edges: Vec<f64>) -> Option<NearGround> {
    edges.retain(|e| e.is_finite());
    if edges.len() < 3 {
        return None;
    }
    Some(NearGround {
        range: median(&mut edges),
        scans: edges.len(),
    })
}

/// [`scan_near_ground`] of every scan on one mount, combined.
pub fn near_ground<S: AsRef<[[f32; 3]]>>(
    scans: &[S],
    mount: &Pose,
    ego_radius: f64,
    cfg: &NearEdgeConfig,
) -> Option<NearGround> {
    combine_near_ground(
        scans
            .iter()
            .filter_map(|s| scan_near_ground(s.as_ref(), mount, ego_radius, cfg))
            .collect(),
    )
}

/// `zones` with the near edge moved in to `margin` × `near.range` (to the centimetre) where
/// that lies more than 10 cm inside the zones' own (never out, never inside `ego_radius`);
/// `None` if it does not move. The other boundaries stay where they were, written out.
pub fn zones_with_near_edge(
    zones: &ZoneConfig,
    near: &NearGround,
    ego_radius: f64,
    cfg: &NearEdgeConfig,
) -> Option<ZoneConfig> {
    let mut boundaries = zones.resolved_boundaries().ok()?;
    let edge = ((near.range * cfg.margin).max(ego_radius) * 100.0).round() / 100.0;
    // NaN (no range) fails the test and moves nothing.
    if edge.is_nan() || edge >= boundaries[0] - 0.1 {
        return None;
    }
    boundaries[0] = edge;
    Some(ZoneConfig {
        min_range: edge,
        boundaries: Some(boundaries),
        ..zones.clone()
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

    use super::*;
    use groundwork_core::config::{MountConfig, mount_transform};

    /// Flat ground from 1.2 m out seen by a sensor 0.6 m up, a wall 3 m high at 5 m and
    /// hits on the vehicle inside 0.5 m: the near edge is the ground's, not the wall's or
    /// the body's, and the zones move in to 0.9 of it.
    #[test]
    fn the_near_edge_is_where_the_ground_starts() {
        let mount = mount_transform(&MountConfig {
            height: 0.6,
            ..Default::default()
        })
        .unwrap();
        let mut scan = Vec::new();
        for i in 0..2_000 {
            let a = f64::from(i) * 0.0314;
            for r in [1.2, 1.5, 2.0, 3.0, 4.0] {
                scan.push([(r * a.cos()) as f32, (r * a.sin()) as f32, -0.6]);
            }
            // The wall, from its foot up, and the vehicle's body.
            scan.push([5.0, (a.sin() * 2.0) as f32, (a.cos() * 1.5 + 0.9) as f32]);
            scan.push([(0.3 * a.cos()) as f32, (0.3 * a.sin()) as f32, -0.55]);
        }
        let scans = vec![scan.clone(), scan.clone(), scan];
        let cfg = NearEdgeConfig::default();
        let near = near_ground(&scans, &mount, 0.5, &cfg).unwrap();
        assert!((near.range - 1.2).abs() < 1e-3, "{near:?}");
        assert_eq!(near.scans, 3);
        let zones = ZoneConfig::default();
        let moved = zones_with_near_edge(&zones, &near, 0.5, &cfg).unwrap();
        assert_eq!(moved.min_range, 1.08);
        let (before, after) = (
            zones.resolved_boundaries().unwrap(),
            moved.resolved_boundaries().unwrap(),
        );
        assert_eq!(after[0], 1.08);
        assert_eq!(after[1..], before[1..]);
        // Never outwards, and never for a few centimetres.
        let far = NearGround {
            range: 4.0,
            scans: 3,
        };
        assert!(zones_with_near_edge(&zones, &far, 0.5, &cfg).is_none());
        let close = NearGround {
            range: zones.min_range / 0.9 - 0.05,
            scans: 3,
        };
        assert!(zones_with_near_edge(&zones, &close, 0.5, &cfg).is_none());
        // Two scans cannot tell.
        assert!(near_ground(&scans[..2], &mount, 0.5, &cfg).is_none());
    }
}
