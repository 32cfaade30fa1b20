//! The mount the segmenter observes, scan after scan, against the one it was configured
//! with: a plane through the means of the ground components near the sensor, smoothed over
//! scans. The height filter tracks height segment by segment; this tracks the whole ground's
//! height and tilt, so that a mount typed wrong (degrees for radians, a sensor knocked on
//! its bracket) is reported, once, with numbers. It only observes: no output changes.

use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

use crate::config::{MountCheckConfig, MountCheckMode, roll_pitch_of};
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
}

/// The observation over scans.
#[derive(Debug, Clone, Default)]
pub(crate) struct MountWatch {
    /// Smoothed ground normal (ground-aligned frame of the configured mount).
    normal: Vector3<f64>,
    /// Smoothed height of the observed ground at the sensor's foot, metres.
    offset: f64,
    scans: u64,
    warned: bool,
}

/// Fewest ground components a scan's plane is fitted to.
const MIN_COMPONENTS: usize = 12;

impl MountWatch {
    /// Adds one fitted scan; returns the observation once, the first time it disagrees
    /// with the configured mount beyond the tolerances (after the warm-up).
    pub(crate) fn observe(
        &mut self,
        model: &FrameModel,
        cfg: &MountCheckConfig,
        mount: &Pose,
        threshold: f64,
    ) -> Option<ObservedMount> {
        if cfg.mode == MountCheckMode::Off {
            return None;
        }
        let (n, z0) = ground_plane(model, cfg.range, threshold)?;
        if self.scans == 0 {
            (self.normal, self.offset) = (n, z0);
        } else {
            let w = cfg.smoothing;
            self.normal = ((1.0 - w) * self.normal + w * n).normalize();
            self.offset = (1.0 - w) * self.offset + w * z0;
        }
        self.scans += 1;
        if self.warned || self.scans < u64::from(cfg.warmup_scans.max(1)) {
            return None;
        }
        let seen = self.observed(mount)?;
        let off = seen.tilt_from_configured.to_degrees() > cfg.max_tilt_deg
            || seen.height_from_configured.abs() > cfg.max_height;
        if off {
            self.warned = true;
            return Some(seen);
        }
        None
    }

    /// The observed mount, once a scan has been observed.
    pub(crate) fn observed(&self, mount: &Pose) -> Option<ObservedMount> {
        if self.scans == 0 {
            return None;
        }
        // The observed ground's normal in the sensor frame gives roll and pitch; the
        // sensor sits (configured height − the ground's height at its foot) above it.
        let (roll, pitch) = roll_pitch_of(&(mount.rotation.inverse() * self.normal));
        let height = (mount.translation.z - self.offset) * self.normal.z;
        Some(ObservedMount {
            height,
            roll,
            pitch,
            tilt_from_configured: self.normal.angle(&Vector3::z()),
            height_from_configured: height - mount.translation.z,
            scans: self.scans,
        })
    }

    pub(crate) fn reset(&mut self) {
        *self = Self::default();
    }
}

/// A plane z = a + b·x + c·y through the means of the ground components within `range`
/// (least squares, twice dropping means more than 0.2 m off): its unit normal and a.
fn ground_plane(model: &FrameModel, range: f64, threshold: f64) -> Option<(Vector3<f64>, f64)> {
    let means: Vec<[f64; 3]> = model
        .components()
        .iter()
        .filter(|c| c.ground_likelihood() >= threshold)
        .map(|c| c.gaussian.mean)
        .filter(|m| m[0].hypot(m[1]) <= range && m.iter().all(|v| v.is_finite()))
        .collect();
    let mut coef = Vector3::zeros();
    let mut keep = vec![true; means.len()];
    for round in 0..3 {
        let (mut a, mut rhs, mut used) = (Matrix3::zeros(), Vector3::zeros(), 0usize);
        for (m, &k) in means.iter().zip(&keep) {
            if k {
                let x = Vector3::new(1.0, m[0], m[1]);
                a += x * x.transpose();
                rhs += m[2] * x;
                used += 1;
            }
        }
        if used < MIN_COMPONENTS {
            return None;
        }
        coef = a.cholesky()?.solve(&rhs);
        if round < 2 {
            for (m, k) in means.iter().zip(keep.iter_mut()) {
                *k = (m[2] - (coef[0] + coef[1] * m[0] + coef[2] * m[1])).abs() <= 0.1;
            }
        }
    }
    Some((Vector3::new(-coef[1], -coef[2], 1.0).normalize(), coef[0]))
}
