//! Input points and rigid transforms.

use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, Translation3, UnitQuaternion};

use crate::error::SegmentError;

/// A LiDAR return as KITTI stores it: x, y, z in metres and intensity, 16 bytes.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Point {
    /// Forward, metres (sensor frame).
    pub x: f32,
    /// Left, metres.
    pub y: f32,
    /// Up, metres.
    pub z: f32,
    /// Return intensity (unused by the segmenter, carried for callers).
    pub intensity: f32,
}

impl Point {
    /// A point with zero intensity.
    pub const fn new(x: f32, y: f32, z: f32) -> Self {
        Self {
            x,
            y,
            z,
            intensity: 0.0,
        }
    }
}

/// Anything the segmenter can read x, y, z from. Lets message and file types be segmented
/// in place, without converting the whole scan first.
pub trait PointXyz {
    /// Coordinates in the sensor frame, metres.
    fn xyz(&self) -> [f32; 3];
}

impl PointXyz for Point {
    #[inline]
    fn xyz(&self) -> [f32; 3] {
        [self.x, self.y, self.z]
    }
}

impl PointXyz for [f32; 3] {
    #[inline]
    fn xyz(&self) -> [f32; 3] {
        *self
    }
}

impl PointXyz for [f32; 4] {
    #[inline]
    fn xyz(&self) -> [f32; 3] {
        [self[0], self[1], self[2]]
    }
}

/// Every coordinate finite, or the error naming the first point that is not. Every method
/// checks its input with this. A branch-free sequential fold (vectorised: about 0.3 ms for
/// 124k points); rayon's find-first machinery cost 1.5–2.8 ms for the same pass.
pub fn check_finite<P: PointXyz + Sync>(points: &[P]) -> Result<(), SegmentError> {
    let all_finite = points.iter().fold(true, |ok, p| {
        let [x, y, z] = p.xyz();
        ok & x.is_finite() & y.is_finite() & z.is_finite()
    });
    if all_finite {
        return Ok(());
    }
    let index = points
        .iter()
        .position(|p| p.xyz().iter().any(|v| !v.is_finite()))
        .unwrap_or(0);
    let [x, y, z] = points[index].xyz();
    Err(SegmentError::NonFinitePoint { index, x, y, z })
}

/// A rigid transform (SE(3)), e.g. the world pose of a sensor (world from sensor).
pub type Pose = Isometry3<f64>;

/// Builds a rigid transform from a 4×4 row-major matrix, rejecting non-finite entries and
/// rotations that are not orthonormal (tolerance 1e-3, then re-orthonormalised).
pub fn pose_from_matrix(m: &[[f64; 4]; 4]) -> Result<Pose, SegmentError> {
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err(SegmentError::InvalidPose("non-finite entry".into()));
    }
    let mat = Matrix4::from_fn(|r, c| m[r][c]);
    let rot: Matrix3<f64> = mat.fixed_view::<3, 3>(0, 0).into_owned();
    let err = (rot.transpose() * rot - Matrix3::identity()).abs().max();
    if err > 1e-3 || rot.determinant() < 0.0 {
        return Err(SegmentError::InvalidPose(format!(
            "rotation part is not a proper rotation (orthonormality error {err:.2e})"
        )));
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rot));
    let translation = Translation3::new(mat[(0, 3)], mat[(1, 3)], mat[(2, 3)]);
    Ok(Isometry3::from_parts(translation, rotation))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_from_matrix_rejects_non_rigid_and_non_finite() {
        let mut m = [[0.0; 4]; 4];
        m[0][0] = 2.0;
        m[1][1] = 1.0;
        m[2][2] = 1.0;
        m[3][3] = 1.0;
        assert!(pose_from_matrix(&m).is_err());
        m[0][0] = f64::NAN;
        assert!(pose_from_matrix(&m).is_err());
        m[0][0] = 1.0;
        m[0][3] = 4.0;
        let p = pose_from_matrix(&m).unwrap();
        assert!((p.translation.x - 4.0).abs() < 1e-12);
    }
}
