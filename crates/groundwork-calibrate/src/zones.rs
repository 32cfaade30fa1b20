//! The zone model's near edge, from where the sensor first sees ground, and its inner
//! boundaries, scaled with the sensor's height.
//!
//! A preset's near edge (`zones.min_range`) is set for its own mount: the HDL-64E's 2.7 m
//! keeps the KITTI car's roof out and lies inside the 3.7 m where its lowest beam meets the
//! road. Mounted lower, or pitched, the same sensor sees ground much nearer, and every
//! ground point inside the near edge is called non-ground. With the mount found, the
//! ground near the sensor is plain to see: the points within a band of the ground plane.

use groundwork_core::config::{MountConfig, ZoneConfig, mount_transform};
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

/// The inner zones' boundaries follow the height: beams meet flat ground at ranges in
/// proportion to the sensor's height, so a preset's inner boundaries, set for the beams on
/// its own mount, are scaled by the height found over the preset's. How far, and where.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HeightScale {
    /// Height found over the preset's height, as applied (clamped to [0.25, 2]).
    pub ratio: f64,
    /// The boundaries before (after the near edge moved, if it did) and after, metres.
    pub was: Vec<f64>,
    /// The boundaries written.
    pub boundaries: Vec<f64>,
}

/// Heights within this share of the preset's leave the layout alone: a calibrated height
/// is good to a few centimetres, and a layout moved for that is noise.
pub const HEIGHT_SCALE_DEAD_BAND: f64 = 0.05;

/// `zones` with every inner boundary but the outermost one (for four zones: the first two
/// beyond the near edge) multiplied by `height` over the height of `preset_mount` (the
/// mount the preset's layout was made for), clamped to [0.25, 2], rounded to the
/// centimetre and kept at least a metre apart; the near edge, the outermost inner boundary
/// and `max_range` stay. `None` when the layout does not follow the height
/// (`zones.scale_with_height` off), the ratio is within [`HEIGHT_SCALE_DEAD_BAND`] of 1
/// (or not a number), the zones have fewer than three zones or no boundaries, or they are
/// too narrow to keep a metre between every two.
///
/// Why not the outermost inner boundary: measured on synthetic scans of eight sensors on
/// random mounts (docs/calibration.md), scaling it too gained less on five of them. Far
/// out the beams are nearly level, and their ranges follow the pitch more than the height.
/// Why only where a preset says so: a layout searched on scans from random mounts (the
/// `vlp16`, `os1-64` and `livox` presets) is already the best for every height, and
/// scaling it loses; on `vlp32c` and `os1-128` it gains under 0.1 (docs/dev/calibration-notes.md,
/// "Which layouts follow the height").
pub fn zones_scaled_to_height(
    zones: &ZoneConfig,
    height: f64,
    preset_mount: &MountConfig,
) -> Option<(ZoneConfig, HeightScale)> {
    if !zones.scale_with_height {
        return None;
    }
    // The sensor's origin in the ground-aligned frame (whose origin is on the ground):
    // `height`, or a matrix mount's translation.
    let preset_height = mount_transform(preset_mount).ok()?.translation.vector.z;
    let ratio = height / preset_height;
    if !ratio.is_finite() || ratio <= 0.0 || (ratio - 1.0).abs() < HEIGHT_SCALE_DEAD_BAND {
        return None;
    }
    let ratio = ratio.clamp(0.25, 2.0);
    let was = zones.resolved_boundaries().ok()?;
    let n = was.len();
    if n < 4 {
        return None;
    }
    let mut b = was.clone();
    // Outwards: scaled, at least a metre beyond the one before; then inwards: at least a
    // metre inside the one after (the outermost inner boundary and max_range stay).
    for i in 1..n - 2 {
        b[i] = ((was[i] * ratio).max(b[i - 1] + 1.0) * 100.0).round() / 100.0;
    }
    for i in (1..n - 2).rev() {
        b[i] = b[i].min(b[i + 1] - 1.0);
    }
    if b.windows(2).any(|w| w[1] - w[0] < 1.0 - 1e-6) {
        return None; // zones too narrow to hold a metre each: leave them
    }
    Some((
        ZoneConfig {
            boundaries: Some(b.clone()),
            ..zones.clone()
        },
        HeightScale {
            ratio,
            was,
            boundaries: b,
        },
    ))
}

/// The zones `calibrate` writes for the mount it found: the near edge moved in
/// ([`zones_with_near_edge`], given where the scans first see ground), then the inner
/// boundaries scaled ([`zones_scaled_to_height`], given the height found and the preset's
/// mount). One place for the CLI, Python and the tests to compose the two.
#[derive(Debug, Clone, PartialEq)]
pub struct MountZones {
    /// The zones to write; `None` when neither step moved anything.
    pub zones: Option<ZoneConfig>,
    /// The near edge, if it moved.
    pub near_edge: Option<f64>,
    /// How the inner boundaries were scaled, if they were.
    pub height_scale: Option<HeightScale>,
}

/// See [`MountZones`]. `near`: where the scans first see ground (`None`: the edge stays);
/// `height`: the height found and the mount the preset's layout was made for (`None`: the
/// inner boundaries stay).
pub fn zones_for_mount(
    zones: &ZoneConfig,
    near: Option<&NearGround>,
    height: Option<(f64, &MountConfig)>,
    ego_radius: f64,
    cfg: &NearEdgeConfig,
) -> MountZones {
    let moved = near.and_then(|n| zones_with_near_edge(zones, n, ego_radius, cfg));
    let near_edge = moved.as_ref().map(|z| z.min_range);
    let scaled = height
        .and_then(|(h, preset)| zones_scaled_to_height(moved.as_ref().unwrap_or(zones), h, preset));
    match scaled {
        Some((z, how)) => MountZones {
            zones: Some(z),
            near_edge,
            height_scale: Some(how),
        },
        None => MountZones {
            zones: moved,
            near_edge,
            height_scale: None,
        },
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

    use super::*;

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

    #[test]
    fn inner_boundaries_follow_the_height() {
        let at = |height| MountConfig {
            height,
            pitch: 0.1, // the angles do not matter
            ..Default::default()
        };
        // The HDL-64E preset's layout (2.7, 12.36, 22.03, 41.35, 80) on a sensor 0.8 m up
        // instead of 1.73 m: the first two inner boundaries move in by 0.8 / 1.73.
        let zones = ZoneConfig {
            scale_with_height: true,
            ..ZoneConfig::default()
        };
        // A layout that does not follow the height stays where it is.
        let fixed = ZoneConfig::default();
        assert!(zones_scaled_to_height(&fixed, 0.8, &at(1.73)).is_none());
        let (scaled, how) = zones_scaled_to_height(&zones, 0.8, &at(1.73)).unwrap();
        let b = scaled.resolved_boundaries().unwrap();
        let was = zones.resolved_boundaries().unwrap();
        let r = 0.8 / 1.73;
        assert!((how.ratio - r).abs() < 1e-12);
        assert_eq!(how.was, was);
        assert_eq!(how.boundaries, b);
        for i in [1, 2] {
            assert!((b[i] - was[i] * r).abs() <= 0.005, "{b:?}");
        }
        assert_eq!((b[0], b[3], b[4]), (was[0], was[3], was[4]));
        assert_eq!(scaled.min_range, zones.min_range);
        assert_eq!(scaled.rings, zones.rings);
        // A higher sensor: outwards, in order, below the outermost inner boundary.
        let (high, _) = zones_scaled_to_height(&zones, 3.4, &at(1.73)).unwrap();
        let b = high.resolved_boundaries().unwrap();
        assert!(
            b[1] > was[1] && b[2] > was[2] && b[2] <= b[3] - 1.0,
            "{b:?}"
        );
        // Far beyond: clamped at twice, and still a metre apart below 41.35 m.
        let (huge, how) = zones_scaled_to_height(&zones, 20.0, &at(1.73)).unwrap();
        let b = huge.resolved_boundaries().unwrap();
        assert_eq!(how.ratio, 2.0);
        assert!(b.windows(2).all(|w| w[1] >= w[0] + 1.0 - 1e-9), "{b:?}");
        // Within the dead band, or not a height: nothing moves.
        assert!(zones_scaled_to_height(&zones, 1.70, &at(1.73)).is_none());
        assert!(zones_scaled_to_height(&zones, f64::NAN, &at(1.73)).is_none());
        assert!(zones_scaled_to_height(&zones, 1.0, &at(0.0)).is_none());
        // Fewer than three zones: nothing to scale without touching the edges.
        let two = ZoneConfig {
            boundaries: Some(vec![2.0, 10.0, 50.0]),
            rings: vec![1, 1],
            sectors: vec![8, 8],
            ..zones.clone()
        };
        assert!(zones_scaled_to_height(&two, 0.8, &at(1.73)).is_none());
        // Zones a metre wide at most are left alone rather than squeezed.
        let tight = ZoneConfig {
            boundaries: Some(vec![2.0, 2.5, 3.0, 3.5, 50.0]),
            ..zones.clone()
        };
        assert!(zones_scaled_to_height(&tight, 3.0, &at(1.0)).is_none());
    }

    #[test]
    fn the_mount_moves_the_edge_then_scales_from_it() {
        let zones = ZoneConfig {
            scale_with_height: true,
            ..ZoneConfig::default()
        };
        let cfg = NearEdgeConfig::default();
        let preset = MountConfig {
            height: 1.73,
            ..Default::default()
        };
        let near = NearGround {
            range: 1.2,
            scans: 3,
        };
        let h0 = preset.height;
        let both = zones_for_mount(&zones, Some(&near), Some((h0 / 2.0, &preset)), 0.0, &cfg);
        let edge = zones_with_near_edge(&zones, &near, 0.0, &cfg).unwrap();
        let scaled = zones_scaled_to_height(&edge, h0 / 2.0, &preset).unwrap();
        assert_eq!(both.near_edge, Some(edge.min_range));
        assert_eq!(both.zones, Some(scaled.0));
        assert_eq!(both.height_scale, Some(scaled.1));
        // Either step alone, and neither.
        let edge_only = zones_for_mount(&zones, Some(&near), None, 0.0, &cfg);
        assert_eq!(
            (edge_only.zones, edge_only.height_scale),
            (Some(edge), None)
        );
        let height_only = zones_for_mount(&zones, None, Some((h0 / 2.0, &preset)), 0.0, &cfg);
        assert_eq!(height_only.near_edge, None);
        assert_eq!(
            height_only.zones,
            zones_scaled_to_height(&zones, h0 / 2.0, &preset).map(|s| s.0)
        );
        let none = zones_for_mount(&zones, None, Some((h0, &preset)), 0.0, &cfg);
        assert_eq!(
            none,
            MountZones {
                zones: None,
                near_edge: None,
                height_scale: None
            }
        );
    }
}
