//! What every method here does before it looks at a scan: check it, and move it into the
//! ground-aligned frame of the sensor's mount (x forward, y left, z up), leaving out the
//! ego vehicle's own returns and the no-return placeholders some drivers send at the
//! sensor's origin. The same sensor standardisation as the GMM segmenter's, for the methods
//! beside it (PseudoLabeler, RANSAC) and the detector.

use crate::config::mount_transform;
use crate::error::{ConfigError, SegmentError};
use crate::point::{PointXyz, Pose, check_finite};
use glam::{Affine3A, Vec3A};
use rayon::prelude::*;

/// The frame a method works in.
#[derive(Debug, Clone, Copy)]
pub struct GroundFrame {
    mount: Affine3A,
    ego_radius_sq: f32,
    max_points: usize,
}

/// A scan in the ground-aligned frame.
#[derive(Debug, Clone, Default)]
pub struct Prepared {
    /// Every point, transformed, in input order.
    pub xyz: Vec<[f32; 3]>,
    /// Whether a point takes part (false: inside the ego radius, or exactly at the sensor's
    /// origin, the placeholder Ouster and Livox drivers send for a missing return;
    /// probability 0).
    pub usable: Vec<bool>,
}

impl GroundFrame {
    /// The frame of a sensor mounted by `mount` (ground-aligned from sensor), whose points
    /// within `ego_radius` metres horizontally belong to the vehicle, and which never sends
    /// more than `max_points`.
    pub fn new(mount: &Pose, ego_radius: f64, max_points: usize) -> Self {
        Self {
            mount: Affine3A::IDENTITY,
            ego_radius_sq: (ego_radius * ego_radius) as f32,
            max_points,
        }
        .with_mount(mount)
    }

    /// The frame a segmenter configuration describes: its mount, ego radius and maximum.
    pub fn from_config(cfg: &crate::SegmenterConfig) -> Result<Self, ConfigError> {
        let mount = mount_transform(&cfg.sensor.mount)?;
        Ok(Self::new(
            &mount,
            cfg.sensor.ego_radius,
            cfg.sensor.max_points,
        ))
    }

    /// The same frame for a sensor mounted by `mount` (ego radius and maximum kept).
    pub fn with_mount(&self, mount: &Pose) -> Self {
        let h = mount.to_homogeneous();
        let col = |c: usize| Vec3A::new(h[(0, c)] as f32, h[(1, c)] as f32, h[(2, c)] as f32);
        Self {
            mount: Affine3A::from_cols(col(0), col(1), col(2), col(3)),
            ..*self
        }
    }

    /// Largest scan accepted.
    pub fn max_points(&self) -> usize {
        self.max_points
    }

    /// The identity frame with no ego radius.
    pub fn identity(max_points: usize) -> Self {
        Self {
            mount: Affine3A::IDENTITY,
            ego_radius_sq: 0.0,
            max_points,
        }
    }

    /// Checks a scan: finite coordinates, at most the maximum.
    pub fn check<P: PointXyz + Sync>(&self, points: &[P]) -> Result<(), SegmentError> {
        self.check_size(points)?;
        check_finite(points)
    }

    /// Checks a scan's size alone (at most the maximum), for a caller that tests the
    /// coordinates in a pass of its own.
    pub fn check_size<P>(&self, points: &[P]) -> Result<(), SegmentError> {
        if points.len() > self.max_points {
            return Err(SegmentError::TooManyPoints {
                points: points.len(),
                max: self.max_points,
            });
        }
        Ok(())
    }

    /// A point (sensor frame) in the ground-aligned frame.
    #[inline]
    pub fn to_ground(&self, [x, y, z]: [f32; 3]) -> [f32; 3] {
        self.mount.transform_point3a(Vec3A::new(x, y, z)).to_array()
    }

    /// Checks a scan (finite coordinates, size, one output slot per point) and transforms
    /// it. Rejected scans leave `out` untouched.
    pub fn prepare<P: PointXyz + Sync>(
        &self,
        points: &[P],
        out: &[f32],
    ) -> Result<Prepared, SegmentError> {
        if out.len() != points.len() {
            return Err(SegmentError::OutputSize {
                expected: points.len(),
                got: out.len(),
            });
        }
        self.check(points)?;
        let (xyz, usable) = points
            .par_iter()
            .map(|p| {
                let s = p.xyz();
                let q = self.to_ground(s);
                let usable = s != [0.0; 3] && q[0] * q[0] + q[1] * q[1] >= self.ego_radius_sq;
                (q, usable)
            })
            .unzip();
        Ok(Prepared { xyz, usable })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MountConfig;

    #[test]
    fn placeholders_at_the_origin_and_the_ego_disc_are_left_out() {
        let mount = MountConfig {
            height: 1.4,
            pitch: 0.1,
            ..Default::default()
        };
        let pose = mount_transform(&mount).unwrap();
        let points = [
            [0.0f32, 0.0, 0.0],
            [-0.0, 0.0, -0.0],
            [1e-3, 0.0, 0.0],
            [5.0, 1.0, -1.4],
        ];
        // No ego radius: only the exact origin is a placeholder (a Livox or Ouster driver's
        // missing return), not a point a millimetre from it.
        let p = GroundFrame::new(&pose, 0.0, 10)
            .prepare(&points, &[0.0; 4])
            .unwrap();
        assert_eq!(p.usable, [false, false, true, true]);
        // The origin is moved like any point (it sits at the sensor's height).
        assert!((p.xyz[0][2] - 1.4).abs() < 1e-6);
        // With an ego radius, the disc too.
        let p = GroundFrame::new(&pose, 2.0, 10)
            .prepare(&points, &[0.0; 4])
            .unwrap();
        assert_eq!(p.usable, [false, false, false, true]);
    }
}
