//! The mount the segmenter observes, scan after scan, against the one it was configured
//! with: a plane through the means of the ground components near the sensor, smoothed over
//! scans. The height filter tracks height segment by segment; this tracks the whole ground's
//! height and tilt, so that a mount typed wrong (degrees for radians, a sensor knocked on
//! its bracket) is reported, once, with numbers. In `warn` mode it only observes: no output
//! changes. In `correct` mode it also moves the mount in use towards what it observes,
//! slowly and with a lock (`MountWatch::correct`).

use nalgebra::{Matrix4, Translation3, UnitQuaternion, Vector3, Vector4};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::{MountCheckConfig, MountCheckMode, roll_pitch_of, vertical_in_sensor};
use crate::model::FrameModel;
use crate::point::Pose;

/// The mount as the segmenter sees it in the ground it fits.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ObservedMount {
    /// Sensor height above the observed ground, metres.
    pub height: f64,
    /// Roll, radians (mount convention: Rz(yaw)·Ry(pitch)·Rx(roll)).
    pub roll: f64,
    /// Pitch, radians.
    pub pitch: f64,
    /// Angle between the configured and the observed vertical, radians.
    pub tilt_from_configured: f64,
    /// Observed height minus configured height, metres.
    pub height_from_configured: f64,
    /// Scans that contributed.
    pub scans: u64,
    /// The mount in use: `sensor.mount` unless `correct` mode moved it. Height, metres.
    pub applied_height: f64,
    /// Roll of the mount in use, radians.
    pub applied_roll: f64,
    /// Pitch of the mount in use, radians.
    pub applied_pitch: f64,
    /// `correct` mode: whether the mount in use is moving (false: locked).
    pub correcting: bool,
    /// `correct` mode: scans after which the mount in use moved.
    pub corrected_scans: u64,
}

/// The observation over scans, in the sensor's own frame: it does not depend on the mount
/// the scans were segmented with, so it stays valid while `correct` moves that mount.
#[derive(Debug, Clone, Default)]
pub(crate) struct MountWatch {
    /// Smoothed ground vertical (unit), sensor frame.
    up: Vector3<f64>,
    /// Smoothed height of the sensor above the observed ground, metres.
    height: f64,
    scans: u64,
    warned: bool,
    correcting: bool,
    /// While correcting: the target where it has stayed (within a quarter of the
    /// tolerances) for `settled` scans, each step reaching it.
    settle: Option<(Vector3<f64>, f64)>,
    settled: u32,
    /// While locked: consecutive scans whose target lay beyond the tolerances.
    beyond: u32,
    /// Whether the bound on corrections was reported.
    bound_warned: bool,
    corrected_scans: u64,
}

/// What one observed scan asks of the segmenter.
#[derive(Debug, Default)]
pub(crate) struct MountVerdict {
    /// The observation, the first time it disagrees beyond the tolerances: log it.
    pub warn: Option<ObservedMount>,
    /// `correct` mode: the mount to segment the next scan with.
    pub apply: Option<Pose>,
}

/// Fewest ground components a scan's plane is fitted to (three unknowns). 12 left a
/// VLP-16 2.2 m up on a synthetic street (one ring per segment beyond 10 m) without a plane
/// in 55 of 200 scans, too few for `correct` to lock within them; 8: in 41.
const MIN_COMPONENTS: usize = 8;

impl MountWatch {
    /// Adds one scan, fitted on the mount `in_use` (`configured` is `sensor.mount`).
    pub(crate) fn observe(
        &mut self,
        model: &FrameModel,
        cfg: &MountCheckConfig,
        (configured, in_use): (&Pose, &Pose),
        threshold: f64,
    ) -> MountVerdict {
        let mut verdict = MountVerdict::default();
        if cfg.mode == MountCheckMode::Off {
            return verdict;
        }
        let Some((n, z0)) = ground_plane(model, cfg.range, threshold) else {
            return verdict;
        };
        // The plane n·p = z0·n_z of the ground-aligned frame in the sensor frame: vertical
        // R⁻¹n, and the sensor (at t) n·t − z0·n_z above it.
        let up = in_use.rotation.inverse() * n;
        let height = n.dot(&in_use.translation.vector) - z0 * n.z;
        if self.scans == 0 {
            (self.up, self.height) = (up, height);
        } else {
            let w = cfg.smoothing;
            self.up = ((1.0 - w) * self.up + w * up).normalize();
            self.height = (1.0 - w) * self.height + w * height;
        }
        self.scans += 1;
        if self.scans < u64::from(cfg.warmup_scans.max(1)) {
            return verdict;
        }
        let seen = self.observed(configured, in_use);
        let off = seen.tilt_from_configured.to_degrees() > cfg.max_tilt_deg
            || seen.height_from_configured.abs() > cfg.max_height;
        if off && !self.warned {
            self.warned = true;
            verdict.warn = Some(seen);
        }
        if cfg.mode == MountCheckMode::Correct {
            verdict.apply = self.correct(cfg, configured, in_use);
        }
        verdict
    }

    /// One step of `correct`. The target is the observation, held within `correct_max_*` of
    /// the configured mount (a mount further off is a mistake to fix in the configuration,
    /// not drift to follow). Locked, the mount in use stays until the target has lain
    /// beyond the tolerances around it (`max_tilt_deg`, `max_height`) for `warmup_scans`
    /// scans in a row: the observation carries a scene's bias (a road's crown, sidewalks
    /// above the road: tenths of a degree, centimetres; a car park full of cars: 20 cm for
    /// a few scans), which is not worth chasing. Unlocked, it turns and lifts towards the
    /// target by at most the rates per scan (a kerb or a ramp in a few scans moves it
    /// little), and locks again once the target has stayed within a quarter of the
    /// tolerances of where it was for `warmup_scans` scans, each step reaching it: the
    /// observation is an average over scans, and the ground it sees changes with the mount
    /// in use, so it moves on for a while after the mount has caught up with it.
    fn correct(
        &mut self,
        cfg: &MountCheckConfig,
        configured: &Pose,
        in_use: &Pose,
    ) -> Option<Pose> {
        let v_cfg = vertical_in_sensor(configured);
        let up = turn_towards(&v_cfg, &self.up, cfg.correct_max_deg.to_radians());
        let h_cfg = configured.translation.z;
        let height = self
            .height
            .clamp(h_cfg - cfg.correct_max_m, h_cfg + cfg.correct_max_m);
        if (up != self.up || height != self.height) && !self.bound_warned {
            self.bound_warned = true;
            warn!(
                tilt_deg = %format!("{:.2}", v_cfg.angle(&self.up).to_degrees()),
                height_m = %format!("{:+.3}", self.height - h_cfg),
                "mount_check: the observed mount lies beyond correct_max_deg / correct_max_m \
                 from sensor.mount; the mount in use stops at the bound: fix sensor.mount \
                 (`groundwork calibrate` finds it)"
            );
        }
        let v = vertical_in_sensor(in_use);
        let (tilt, dh) = (v.angle(&up), height - in_use.translation.z);
        if !self.correcting {
            let within = tilt.to_degrees() <= cfg.max_tilt_deg && dh.abs() <= cfg.max_height;
            self.beyond = if within { 0 } else { self.beyond + 1 };
            if self.beyond < cfg.warmup_scans.max(1) {
                return None;
            }
            self.correcting = true;
            self.beyond = 0;
            (self.settle, self.settled) = (None, 0);
            info!(
                tilt_deg = %format!("{:.2}", tilt.to_degrees()),
                height_m = %format!("{:+.3}", dh),
                "mount_check: correcting the mount in use towards the observed one"
            );
        }
        let (rate, rate_m) = (cfg.correct_rate_deg.to_radians(), cfg.correct_rate_m);
        let next_up = turn_towards(&v, &up, rate);
        let next_height = in_use.translation.z + dh.clamp(-rate_m, rate_m);
        let reached = tilt <= rate && dh.abs() <= rate_m;
        let stayed = self.settle.is_some_and(|(u, h)| {
            u.angle(&up).to_degrees() <= cfg.max_tilt_deg / 4.0
                && (h - height).abs() <= cfg.max_height / 4.0
        });
        (self.settle, self.settled) = match (reached, stayed) {
            (false, _) => (None, 0),
            (true, true) => (self.settle, self.settled + 1),
            (true, false) => (Some((up, height)), 1),
        };
        if self.settled >= cfg.warmup_scans.max(1) {
            self.correcting = false;
            let (roll, pitch) = roll_pitch_of(&next_up);
            info!(
                height_m = %format!("{:.3}", next_height),
                roll_deg = %format!("{:.2}", roll.to_degrees()),
                pitch_deg = %format!("{:.2}", pitch.to_degrees()),
                scans = self.scans,
                "mount_check: the mount in use reached the observed one and is locked"
            );
        }
        self.corrected_scans += 1;
        Some(mount_with_vertical(configured, &next_up, next_height))
    }

    /// The observed mount against `configured`, with the mount `in_use`; once a scan has
    /// been observed.
    pub(crate) fn observed(&self, configured: &Pose, in_use: &Pose) -> ObservedMount {
        let (roll, pitch) = roll_pitch_of(&self.up);
        let (applied_roll, applied_pitch) = roll_pitch_of(&vertical_in_sensor(in_use));
        ObservedMount {
            height: self.height,
            roll,
            pitch,
            tilt_from_configured: self.up.angle(&vertical_in_sensor(configured)),
            height_from_configured: self.height - configured.translation.z,
            scans: self.scans,
            applied_height: in_use.translation.z,
            applied_roll,
            applied_pitch,
            correcting: self.correcting,
            corrected_scans: self.corrected_scans,
        }
    }

    pub(crate) fn scans(&self) -> u64 {
        self.scans
    }

    /// Forgets the observations; the mount in use stays where it is, locked.
    pub(crate) fn reset(&mut self) {
        *self = Self::default();
    }
}

/// `from` turned towards `to` (unit vectors) by at most `limit` radians.
fn turn_towards(from: &Vector3<f64>, to: &Vector3<f64>, limit: f64) -> Vector3<f64> {
    let angle = from.angle(to);
    if angle <= limit {
        return *to;
    }
    match UnitQuaternion::rotation_between(from, to) {
        Some(q) => UnitQuaternion::from_scaled_axis(q.scaled_axis() * (limit / angle)) * from,
        None => *from, // opposite verticals: no defined way to turn; stay
    }
}

/// `configured` tilted by the smallest rotation that makes `up` (sensor frame) its
/// vertical, at `height` above the ground; its yaw and horizontal offset kept.
fn mount_with_vertical(configured: &Pose, up: &Vector3<f64>, height: f64) -> Pose {
    let tilt = UnitQuaternion::rotation_between(&(configured.rotation * up), &Vector3::z())
        .unwrap_or_else(UnitQuaternion::identity);
    let t = configured.translation.vector;
    Pose::from_parts(
        Translation3::new(t.x, t.y, height),
        tilt * configured.rotation,
    )
}

/// A plane z = a + b·x + c·y through the means of the ground components within `range`
/// (least squares, twice keeping only the means from 0.15 m below the plane to 0.05 m
/// above it): its unit normal and a. The band leans down because the ground the mount
/// stands on is the lowest: sidewalks 15 cm above the road and lawns rising behind them
/// are ground too. Kept within ±0.1 m, they put a VLP-16 2.2 m up on a synthetic street
/// (`os1-64` zones) at 1.99 m for tens of scans, past the 0.2 m tolerance; this band: 2.03.
fn ground_plane(model: &FrameModel, range: f64, threshold: f64) -> Option<(Vector3<f64>, f64)> {
    let means: Vec<[f64; 3]> = model
        .components()
        .iter()
        .filter(|c| c.ground_likelihood() >= threshold)
        .map(|c| c.gaussian.mean)
        .filter(|m| m[0].hypot(m[1]) <= range && m.iter().all(|v| v.is_finite()))
        .collect();
    // The ground nearest the sensor where it holds enough components: farther out, terrain
    // that falls or rises away (a crest, rolling ground) is no longer the plane the vehicle
    // stands on.
    let near: Vec<[f64; 3]> = means
        .iter()
        .filter(|m| m[0].hypot(m[1]) <= NEAR_RANGE)
        .copied()
        .collect();
    let dense = near.len() >= DENSE_NEAR_COMPONENTS && all_around(&near);
    dense
        .then(|| plane_through(&near, true))
        .flatten()
        .or_else(|| plane_through(&means, false))
}

/// The nearest ground the observation is made from where it is dense all around the
/// sensor, metres (else the plane out to `mount_check.range`).
const NEAR_RANGE: f64 = 12.0;

/// Ground components within [`NEAR_RANGE`] that make it dense enough for the curved fit:
/// spinning 64-beam sensors hold 65–117 (synthetic OS1-64 hill and off-road drives, the
/// KITTI scans), a VLP-16 2.2 m up 23–51, too few rings for a curvature.
const DENSE_NEAR_COMPONENTS: usize = 8 * MIN_COMPONENTS;

/// Whether ground components lie all around the sensor (half [`MIN_COMPONENTS`] in each
/// quadrant at least). Ground on one side (a forward-facing sensor, a pitched sparse one
/// that sees the road behind it only far out) leaves a curvature and a tilt
/// indistinguishable.
fn all_around(means: &[[f64; 3]]) -> bool {
    let mut quadrants = [0usize; 4];
    for m in means {
        quadrants[usize::from(m[0] < 0.0) * 2 + usize::from(m[1] < 0.0)] += 1;
    }
    quadrants.iter().all(|&n| n >= MIN_COMPONENTS / 2)
}

/// The plane of [`ground_plane`] through `means`; with `curved`, the tangent at the
/// sensor's foot of z = a + b·x + c·y + d·(x² + y²), so that ground curving away from the
/// sensor (a crest, a dip, rolling terrain) does not read as a higher or lower mount. Only
/// over dense near ground: components on one or two rings (a sparse sensor) leave the
/// curvature and the height indistinguishable (see [`all_around`]).
fn plane_through(means: &[[f64; 3]], curved: bool) -> Option<(Vector3<f64>, f64)> {
    let terms = |m: &[f64; 3]| {
        let r2 = if curved {
            m[0] * m[0] + m[1] * m[1]
        } else {
            0.0
        };
        Vector4::new(1.0, m[0], m[1], r2)
    };
    let mut coef = Vector4::zeros();
    let mut keep = vec![true; means.len()];
    for round in 0..3 {
        let (mut a, mut rhs, mut used) = (Matrix4::zeros(), Vector4::zeros(), 0usize);
        for (m, &k) in means.iter().zip(&keep) {
            if k {
                let x = terms(m);
                a += x * x.transpose();
                rhs += m[2] * x;
                used += 1;
            }
        }
        if used < MIN_COMPONENTS {
            return None;
        }
        if !curved {
            // The plane alone: the curvature's unknown fixed at 0.
            a[(3, 3)] = 1.0;
        }
        coef = a.cholesky()?.solve(&rhs);
        if round < 2 {
            for (m, k) in means.iter().zip(keep.iter_mut()) {
                let r = m[2] - terms(m).dot(&coef);
                *k = (-0.15..=0.05).contains(&r);
            }
        }
    }
    Some((Vector3::new(-coef[1], -coef[2], 1.0).normalize(), coef[0]))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

    use super::*;
    use crate::config::{MountConfig, mount_transform};

    #[test]
    fn a_turn_stops_at_its_limit_or_at_the_target() {
        let from = Vector3::z();
        let to = Vector3::new(0.3, -0.2, 1.0).normalize();
        let angle = from.angle(&to);
        let half = turn_towards(&from, &to, angle / 2.0);
        assert!((half.angle(&from) - angle / 2.0).abs() < 1e-12);
        assert!((half.angle(&to) - angle / 2.0).abs() < 1e-12);
        assert_eq!(turn_towards(&from, &to, angle * 1.01), to);
    }

    /// The corrected mount has the asked vertical and height, and the configured one's yaw
    /// (a level sensor's forward axis stays where it pointed).
    #[test]
    fn a_corrected_mount_has_the_observed_vertical_and_keeps_the_yaw() {
        let configured = mount_transform(&MountConfig {
            height: 1.0,
            roll: 0.02,
            pitch: -0.01,
            yaw: 0.7,
            matrix: None,
        })
        .unwrap();
        let up = Vector3::new(-0.1, 0.05, 1.0).normalize();
        let m = mount_with_vertical(&configured, &up, 2.2);
        assert!(vertical_in_sensor(&m).angle(&up) < 1e-12);
        assert!((m.translation.z - 2.2).abs() < 1e-15);
        let heading = |p: &Pose| {
            let x = p.rotation * Vector3::x();
            x.y.atan2(x.x)
        };
        assert!((heading(&m) - heading(&configured)).abs() < 0.01);
    }

    /// Ground component means on a road tilted 2 % along x, 0.3 m below the frame's
    /// origin, every 3 m out to 18 m; beside it, 15 cm higher, sidewalk means (two in
    /// five); a stray mean 1.4 m above the road (a car roof).
    fn street(sidewalks: bool) -> Vec<[f64; 3]> {
        let road = |x: f64| -0.3 + 0.02 * x;
        let mut means = Vec::new();
        for i in -6..=6 {
            let x = 3.0 * f64::from(i);
            for y in [-2.5, 0.0, 2.5] {
                means.push([x, y, road(x)]);
            }
            if sidewalks {
                for y in [-6.0, 6.0] {
                    means.push([x, y, road(x) + 0.15]);
                }
            }
        }
        means.push([5.0, 1.0, 1.2]);
        means
    }

    /// The plane stands on the road, not between the road and the sidewalks beside it
    /// (a band of ±0.1 m keeps both and puts it 6 cm up), and drops the stray mean.
    #[test]
    fn the_plane_stands_on_the_lowest_ground() {
        for (sidewalks, curved) in [(false, false), (true, false), (false, true), (true, true)] {
            let (n, a) = plane_through(&street(sidewalks), curved).unwrap();
            let slope = Vector3::new(-0.02, 0.0, 1.0).normalize();
            assert!((a + 0.3).abs() < 1e-9, "{sidewalks} {curved}: {a}");
            assert!(n.angle(&slope) < 1e-9, "{sidewalks} {curved}: {n:?}");
        }
    }

    /// Ground curving away from the sensor (a crest: 2 cm down at 3 m, 32 cm at 12 m):
    /// the curved fit gives the height and the level tangent at the sensor's foot, where a
    /// plane through the same means sits lower by the curvature's mean.
    #[test]
    fn a_crest_is_not_a_higher_mount() {
        let crest: Vec<[f64; 3]> = (-4..=4)
            .flat_map(|i| (-4..=4).map(move |j| (3.0 * f64::from(i), 3.0 * f64::from(j))))
            .filter(|(x, y)| x.hypot(*y) <= 12.0)
            .map(|(x, y)| [x, y, -1.5 - 0.0022 * (x * x + y * y)])
            .collect();
        assert!(crest.len() >= MIN_COMPONENTS && all_around(&crest));
        let (n, a) = plane_through(&crest, true).unwrap();
        assert!(
            (a + 1.5).abs() < 1e-9 && n.angle(&Vector3::z()) < 1e-9,
            "{a} {n:?}"
        );
        let (_, flat) = plane_through(&crest, false).unwrap();
        assert!(flat < -1.6, "{flat}");
        // Ground on one side only is not all around.
        let ahead: Vec<[f64; 3]> = crest.iter().filter(|m| m[0] > 0.0).copied().collect();
        assert!(!all_around(&ahead));
    }

    /// Fewer means than the plane needs give no plane, as do means on one line.
    #[test]
    fn too_few_or_collinear_means_give_no_plane() {
        let few: Vec<[f64; 3]> = street(false).into_iter().take(MIN_COMPONENTS - 1).collect();
        let line: Vec<[f64; 3]> = (0..20).map(|i| [f64::from(i), 0.0, -1.0]).collect();
        for curved in [false, true] {
            assert!(plane_through(&few, curved).is_none());
            assert!(plane_through(&line, curved).is_none());
        }
    }
}
