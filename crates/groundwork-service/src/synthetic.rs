//! Generated scans of any size for benchmarks: a LiDAR-like pattern of 64 beams over a flat
//! road at −1.73 m (sensor frame) with a few box-shaped obstacles.

use groundwork_core::Point;

/// A deterministic scan of exactly `n` points.
pub fn scan(n: usize) -> Vec<Point> {
    let beams = 64usize;
    let per_beam = n.div_ceil(beams).max(1);
    let mut pts = Vec::with_capacity(n);
    'outer: for b in 0..beams {
        // Elevation angles from −24.8° to +2°, like an HDL-64E.
        let elev = (-24.8 + 26.8 * b as f64 / (beams - 1) as f64).to_radians();
        for k in 0..per_beam {
            if pts.len() == n {
                break 'outer;
            }
            let az = std::f64::consts::TAU * k as f64 / per_beam as f64;
            // Range where the beam meets the road, capped at 100 m for upward beams.
            let mut r = if elev < -0.01 {
                (1.73 / (-elev).tan()).min(100.0)
            } else {
                100.0
            };
            // Obstacles: a car-sized box ahead-left and a wall to the right.
            let (c, s) = (az.cos(), az.sin());
            if (0.2..0.5).contains(&az) && r > 10.0 {
                r = 10.0;
            }
            if (4.5..5.0).contains(&az) && r > 7.0 {
                r = 7.0;
            }
            let h = r * elev.tan();
            pts.push(Point {
                x: (r * c) as f32,
                y: (r * s) as f32,
                z: h.max(-1.73) as f32,
                intensity: 0.3,
            });
        }
    }
    pts
}

#[cfg(test)]
mod tests {
    #[test]
    fn has_exactly_the_requested_size_and_finite_points() {
        for n in [0, 1, 1000, 200_000] {
            let s = super::scan(n);
            assert_eq!(s.len(), n);
            assert!(
                s.iter()
                    .all(|p| p.x.is_finite() && p.y.is_finite() && p.z.is_finite())
            );
        }
    }
}
