//! RANSAC ground plane (Fischler & Bolles), the baseline of both papers' tables: the plane
//! through three random points that holds the most points within the inlier distance,
//! refitted to its inliers by least squares; points within the distance of it are ground.

use std::time::{Duration, Instant};

use glam::Vec3A;
use groundwork_core::{PointXyz, SegmentError};
use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::config::RansacConfig;
use crate::prob::{below_half, sigmoid};
use groundwork_core::GroundFrame;

/// A plane n · p = d with |n| = 1 and n pointing up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Unit normal, z ≥ 0.
    pub normal: [f32; 3],
    /// Offset: n · p = d on the plane.
    pub offset: f32,
}

impl Plane {
    /// Signed distance of `p` above the plane.
    #[inline]
    pub fn distance(&self, p: [f32; 3]) -> f32 {
        Vec3A::from(self.normal).dot(Vec3A::from(p)) - self.offset
    }

    /// The plane through three points, oriented up; None when they are (nearly) collinear.
    pub fn through(a: [f32; 3], b: [f32; 3], c: [f32; 3]) -> Option<Self> {
        let (a, b, c) = (Vec3A::from(a), Vec3A::from(b), Vec3A::from(c));
        let n = (b - a).cross(c - a);
        let len = n.length();
        if len.is_nan() || len <= 1e-6 {
            return None;
        }
        let n = if n.z < 0.0 { -n / len } else { n / len };
        Some(Self {
            normal: n.to_array(),
            offset: n.dot(a),
        })
    }
}

/// What one RANSAC run did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RansacReport {
    /// The plane used for labelling, if any hypothesis was valid.
    pub plane: Option<Plane>,
    /// Inliers of the best hypothesis.
    pub inliers: usize,
    /// Hypotheses rejected as too steep or degenerate.
    pub rejected_hypotheses: u32,
    /// Time spent.
    pub time: Duration,
}

/// The RANSAC plane baseline.
#[derive(Debug, Clone)]
pub struct Ransac {
    cfg: RansacConfig,
    frame: GroundFrame,
}

impl Ransac {
    /// A RANSAC labeller working in `frame`.
    pub fn new(
        cfg: RansacConfig,
        frame: GroundFrame,
    ) -> Result<Self, groundwork_core::ConfigError> {
        cfg.validate()?;
        Ok(Self { cfg, frame })
    }

    /// Its configuration.
    pub fn config(&self) -> &RansacConfig {
        &self.cfg
    }

    /// The frame it works in.
    pub fn frame(&self) -> &GroundFrame {
        &self.frame
    }

    /// Labels one scan: a ground probability per point (≥ 0.5 exactly within the inlier
    /// distance of the plane).
    pub fn label<P: PointXyz + Sync>(
        &self,
        points: &[P],
        out: &mut [f32],
    ) -> Result<RansacReport, SegmentError> {
        let t = Instant::now();
        let p = self.frame.prepare(points, out)?;
        let cfg = &self.cfg;
        let usable: Vec<u32> = (0..points.len() as u32)
            .filter(|&i| p.usable[i as usize])
            .collect();
        let mut report = RansacReport::default();
        out.fill(0.0);
        if usable.len() < 3 {
            report.time = t.elapsed();
            return Ok(report);
        }
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let min_up = cfg.max_tilt_deg.to_radians().cos() as f32;
        let dist = cfg.inlier_distance;
        let mut best: Option<(usize, Plane)> = None;
        for _ in 0..cfg.iterations {
            let pick =
                |rng: &mut ChaCha8Rng| p.xyz[usable[rng.random_range(0..usable.len())] as usize];
            let (a, b, c) = (pick(&mut rng), pick(&mut rng), pick(&mut rng));
            let Some(plane) = Plane::through(a, b, c).filter(|pl| pl.normal[2] >= min_up - 1e-6)
            else {
                report.rejected_hypotheses += 1;
                continue;
            };
            let inliers = usable
                .par_iter()
                .filter(|&&i| plane.distance(p.xyz[i as usize]).abs() <= dist)
                .count();
            if best.is_none_or(|(n, _)| inliers > n) {
                best = Some((inliers, plane));
            }
        }
        let Some((inliers, mut plane)) = best else {
            report.time = t.elapsed();
            return Ok(report);
        };
        report.inliers = inliers;
        if cfg.refit {
            let members: Vec<[f32; 3]> = usable
                .iter()
                .map(|&i| p.xyz[i as usize])
                .filter(|&q| plane.distance(q).abs() <= dist)
                .collect();
            if let Some(refit) = least_squares_plane(&members) {
                plane = refit;
            }
        }
        for &i in &usable {
            let i = i as usize;
            let margin = dist - plane.distance(p.xyz[i]).abs();
            let s = sigmoid(margin / cfg.probability_width);
            out[i] = if margin < 0.0 { below_half(s) } else { s };
        }
        report.plane = Some(plane);
        report.time = t.elapsed();
        Ok(report)
    }
}

/// The total-least-squares plane of `points` (normal: the covariance's smallest
/// eigenvector), oriented up; None for fewer than three points or a degenerate set.
pub fn least_squares_plane(points: &[[f32; 3]]) -> Option<Plane> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().fold(Vector3::zeros(), |s: Vector3<f64>, p| {
        s + Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
    }) / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) - mean;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov / n);
    let k = eig.eigenvalues.imin();
    let mut normal = eig.eigenvectors.column(k).into_owned();
    if !normal.iter().all(|v| v.is_finite()) || normal.norm() < 0.5 {
        return None;
    }
    if normal.z < 0.0 {
        normal = -normal;
    }
    Some(Plane {
        normal: [normal.x as f32, normal.y as f32, normal.z as f32],
        offset: normal.dot(&mean) as f32,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tilted_plane_is_recovered_exactly_and_walls_are_not_ground() {
        // A 5 % slope with a big wall that has more points than the road.
        let mut pts = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                let (x, y) = (i as f32 * 0.5 - 10.0, j as f32 * 0.5 - 10.0);
                pts.push([x, y, 0.05 * x - 1.7]);
            }
        }
        for i in 0..60 {
            for j in 0..40 {
                pts.push([8.0, i as f32 * 0.3 - 9.0, j as f32 * 0.2 - 1.5]);
            }
        }
        let r = Ransac::new(RansacConfig::default(), GroundFrame::identity(1 << 20)).unwrap();
        let mut out = vec![0.0; pts.len()];
        let rep = r.label(&pts, &mut out).unwrap();
        let pl = rep.plane.unwrap();
        let want = Vec3A::new(-0.05, 0.0, 1.0).normalize();
        assert!(Vec3A::from(pl.normal).dot(want) > 0.9999, "{pl:?}");
        let road = &out[..1600];
        assert!(road.iter().all(|&p| p >= 0.5), "every road point is ground");
        // The wall meets the road near z = −1.3 there: only its lowest rows are ground.
        let wall_ground = out[1600..].iter().filter(|&&p| p >= 0.5).count();
        assert!(wall_ground <= 60 * 4, "{wall_ground}");
        // Same seed, same result.
        let mut again = vec![0.0; pts.len()];
        assert_eq!(r.label(&pts, &mut again).unwrap().plane, rep.plane);
        assert_eq!(out, again);
    }

    #[test]
    fn degenerate_input_gives_no_plane_and_no_ground() {
        let r = Ransac::new(RansacConfig::default(), GroundFrame::identity(100)).unwrap();
        let pts = [[1.0f32, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]];
        let mut out = vec![0.7; 3];
        let rep = r.label(&pts, &mut out).unwrap();
        assert_eq!(rep.plane, None);
        assert_eq!(out, [0.0; 3]);
        let mut out = vec![0.0; 2];
        assert!(r.label(&pts[..2], &mut out).unwrap().plane.is_none());
        let bad = [[1.0f32, f32::NAN, 0.0]];
        assert!(matches!(
            r.label(&bad, &mut [0.0]),
            Err(SegmentError::NonFinitePoint { index: 0, .. })
        ));
    }
}
