//! What every method here does before it looks at a scan: check it, and move it into the
//! ground-aligned frame of the sensor's mount (x forward, y left, z up), leaving out the
//! ego vehicle's own returns. The same sensor standardisation as the GMM segmenter's.

use glam::{Affine3A, Vec3A};
use groundwork_core::{PointXyz, Pose, SegmentError};
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
    /// Whether a point takes part (false: inside the ego radius; probability 0).
    pub usable: Vec<bool>,
}

impl GroundFrame {
    /// The frame of a sensor mounted by `mount` (ground-aligned from sensor), whose points
    /// within `ego_radius` metres horizontally belong to the vehicle, and which never sends
    /// more than `max_points`.
    pub fn new(mount: &Pose, ego_radius: f64, max_points: usize) -> Self {
        let h = mount.to_homogeneous();
        let col = |c: usize| Vec3A::new(h[(0, c)] as f32, h[(1, c)] as f32, h[(2, c)] as f32);
        Self {
            mount: Affine3A::from_cols(col(0), col(1), col(2), col(3)),
            ego_radius_sq: (ego_radius * ego_radius) as f32,
            max_points,
        }
    }

    /// The frame a segmenter configuration describes: its mount, ego radius and maximum.
    pub fn from_config(
        cfg: &groundwork_core::SegmenterConfig,
    ) -> Result<Self, groundwork_core::ConfigError> {
        let mount = groundwork_core::mount_transform(&cfg.sensor.mount)?;
        Ok(Self::new(
            &mount,
            cfg.sensor.ego_radius,
            cfg.sensor.max_points,
        ))
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

    /// Checks a scan (finite coordinates, size, one output slot per point) and transforms
    /// it. Rejected scans leave `out` untouched.
    pub fn prepare<P: PointXyz + Sync>(
        &self,
        points: &[P],
        out: &[f32],
    ) -> Result<Prepared, SegmentError> {
        if points.len() > self.max_points {
            return Err(SegmentError::TooManyPoints {
                points: points.len(),
                max: self.max_points,
            });
        }
        if out.len() != points.len() {
            return Err(SegmentError::OutputSize {
                expected: points.len(),
                got: out.len(),
            });
        }
        groundwork_core::check_finite(points)?;
        let xyz: Vec<[f32; 3]> = points
            .par_iter()
            .map(|p| {
                let [x, y, z] = p.xyz();
                self.mount.transform_point3a(Vec3A::new(x, y, z)).to_array()
            })
            .collect();
        let usable = xyz
            .iter()
            .map(|q| q[0] * q[0] + q[1] * q[1] >= self.ego_radius_sq)
            .collect();
        Ok(Prepared { xyz, usable })
    }
}

/// σ(x) = 1 / (1 + e^−x).
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `p` if below 0.5, else the largest f32 below 0.5: a non-ground decision whose margin
/// is too small for σ to show in f32 still reads as non-ground.
#[inline]
pub fn below_half(p: f32) -> f32 {
    if p < 0.5 { p } else { BELOW_HALF }
}

/// The largest f32 below 0.5.
const BELOW_HALF: f32 = f32::from_bits(0.5f32.to_bits() - 1);
