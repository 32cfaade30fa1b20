//! Solids the objects of a scene are built from, and where a ray first enters them.

use glam::{DQuat, DVec2, DVec3};

/// A solid in world coordinates (z up).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// A box turned about z: centre, half extents, yaw (radians).
    Box {
        /// Centre of the box.
        center: DVec3,
        /// Half length (x), half width (y), half height (z) in the box's frame.
        half: DVec3,
        /// Rotation about z.
        yaw: f64,
    },
    /// A box turned freely: a car standing on sloped ground, tilted with the ground under
    /// its wheels (an upright box sinks into a street steeper than its clearance allows).
    TiltedBox {
        /// Centre of the box.
        center: DVec3,
        /// Half extents in the box's frame.
        half: DVec3,
        /// World from box.
        rotation: DQuat,
    },
    /// An upright cylinder with a flat top.
    Cylinder {
        /// Centre of its bottom disc.
        base: DVec3,
        /// Radius, metres.
        radius: f64,
        /// Height, metres.
        height: f64,
    },
    /// An axis-aligned ellipsoid (bushes, tree crowns, boulders).
    Ellipsoid {
        /// Centre.
        center: DVec3,
        /// Semi-axes along x, y, z.
        radii: DVec3,
    },
}

impl Shape {
    /// Horizontal bounding circle: centre and radius.
    pub fn footprint(&self) -> (DVec2, f64) {
        match *self {
            Shape::Box { center, half, .. } => (center.truncate(), half.truncate().length()),
            Shape::TiltedBox { center, half, .. } => (center.truncate(), half.length()),
            Shape::Cylinder { base, radius, .. } => (base.truncate(), radius),
            Shape::Ellipsoid { center, radii } => (center.truncate(), radii.x.max(radii.y)),
        }
    }

    /// Distance along the ray `o + t·d` (unit `d`) at which it enters the solid, if it does
    /// so within (`t_min`, `t_max`). A ray starting inside never hits.
    pub fn hit(&self, o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> Option<f64> {
        let t = match *self {
            Shape::Box { center, half, yaw } => {
                let (s, c) = yaw.sin_cos();
                let rot = |v: DVec3| DVec3::new(c * v.x + s * v.y, -s * v.x + c * v.y, v.z);
                slab(rot(o - center), rot(d), half)?
            }
            Shape::TiltedBox {
                center,
                half,
                rotation,
            } => {
                let inverse = rotation.inverse();
                slab(inverse * (o - center), inverse * d, half)?
            }
            Shape::Cylinder {
                base,
                radius,
                height,
            } => cylinder(o - base, d, radius, height)?,
            Shape::Ellipsoid { center, radii } => {
                let (o, d) = ((o - center) / radii, d / radii);
                let (a, b, c) = (d.length_squared(), o.dot(d), o.length_squared() - 1.0);
                if c <= 0.0 {
                    return None;
                }
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return None;
                }
                (-b - disc.sqrt()) / a
            }
        };
        (t > t_min && t < t_max).then_some(t)
    }
}

/// Entry distance of a ray into the box [−half, half] (ray in the box's frame).
fn slab(o: DVec3, d: DVec3, half: DVec3) -> Option<f64> {
    let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
    for k in 0..3 {
        if d[k].abs() < 1e-12 {
            if o[k].abs() > half[k] {
                return None;
            }
            continue;
        }
        let (a, b) = ((-half[k] - o[k]) / d[k], (half[k] - o[k]) / d[k]);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    (t0 <= t1 && t0 > 0.0).then_some(t0)
}

/// Entry distance into an upright cylinder with its base centre at the origin.
fn cylinder(o: DVec3, d: DVec3, r: f64, h: f64) -> Option<f64> {
    let inside_xy = o.x * o.x + o.y * o.y <= r * r;
    if inside_xy && (0.0..=h).contains(&o.z) {
        return None;
    }
    let mut best = f64::INFINITY;
    // The mantle.
    let a = d.x * d.x + d.y * d.y;
    if a > 1e-12 {
        let b = o.x * d.x + o.y * d.y;
        let c = o.x * o.x + o.y * o.y - r * r;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let t = (-b - disc.sqrt()) / a;
            let z = o.z + t * d.z;
            if t > 0.0 && (0.0..=h).contains(&z) {
                best = t;
            }
        }
    }
    // The top and bottom discs.
    if d.z.abs() > 1e-12 {
        for plane in [0.0, h] {
            let t = (plane - o.z) / d.z;
            let p = o + t * d;
            if t > 0.0 && p.x * p.x + p.y * p.y <= r * r {
                best = best.min(t);
            }
        }
    }
    best.is_finite().then_some(best)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    const X: DVec3 = DVec3::X;

    #[test]
    fn a_tilted_box_turned_about_z_only_is_the_upright_box() {
        let (center, half, yaw) = (DVec3::new(5.0, 1.0, 0.7), DVec3::new(2.2, 0.9, 0.5), 0.6);
        let upright = Shape::Box { center, half, yaw };
        let tilted = Shape::TiltedBox {
            center,
            half,
            rotation: DQuat::from_rotation_z(yaw),
        };
        let o = DVec3::new(0.0, 0.0, 1.8);
        for k in 0..50 {
            let a = -0.5 + 0.02 * f64::from(k);
            let d = DVec3::new(a.cos(), a.sin(), -0.15).normalize();
            let (u, t) = (upright.hit(o, d, 0.0, 100.0), tilted.hit(o, d, 0.0, 100.0));
            assert_eq!(u.is_some(), t.is_some(), "ray {k}");
            if let (Some(u), Some(t)) = (u, t) {
                assert!((u - t).abs() < 1e-9, "ray {k}: {u} {t}");
            }
        }
        // Pitched about its y axis by θ: a ray along x, 0.25 m above the centre, enters the
        // near face where the face's local x is −half.x: at X = (0.25 sin θ − half.x) / cos θ
        // from the centre (the upright box: at −half.x).
        let theta: f64 = 0.1745;
        let pitched = Shape::TiltedBox {
            center,
            half,
            rotation: DQuat::from_rotation_y(theta),
        };
        let (o, d) = (DVec3::new(0.0, 1.0, center.z + 0.25), DVec3::X);
        let t = pitched.hit(o, d, 0.0, 100.0).unwrap();
        let want = center.x + (0.25 * theta.sin() - half.x) / theta.cos();
        assert!((t - want).abs() < 1e-9, "{t} {want}");
        assert!((t - (center.x - half.x)).abs() > 0.005);
    }

    #[test]
    fn a_ray_enters_each_solid_at_its_near_surface() {
        let o = DVec3::ZERO;
        let b = Shape::Box {
            center: DVec3::new(10.0, 0.0, 0.0),
            half: DVec3::new(1.0, 2.0, 1.0),
            yaw: 0.0,
        };
        assert!((b.hit(o, X, 0.0, 100.0).unwrap() - 9.0).abs() < 1e-12);
        // Turned by 90°, its half length now faces the ray.
        let b = Shape::Box {
            center: DVec3::new(10.0, 0.0, 0.0),
            half: DVec3::new(1.0, 2.0, 1.0),
            yaw: std::f64::consts::FRAC_PI_2,
        };
        assert!((b.hit(o, X, 0.0, 100.0).unwrap() - 8.0).abs() < 1e-9);
        let c = Shape::Cylinder {
            base: DVec3::new(5.0, 0.0, -1.0),
            radius: 0.5,
            height: 2.0,
        };
        assert!((c.hit(o, X, 0.0, 100.0).unwrap() - 4.5).abs() < 1e-12);
        // Seen from above, the top disc.
        let down = DVec3::new(0.0, 0.0, -1.0);
        assert!((c.hit(DVec3::new(5.0, 0.0, 3.0), down, 0.0, 100.0).unwrap() - 2.0).abs() < 1e-12);
        let e = Shape::Ellipsoid {
            center: DVec3::new(0.0, 6.0, 0.0),
            radii: DVec3::new(1.0, 2.0, 1.0),
        };
        assert!((e.hit(o, DVec3::Y, 0.0, 100.0).unwrap() - 4.0).abs() < 1e-12);
    }

    #[test]
    fn misses_behind_inside_and_beyond_the_range_are_none() {
        let b = Shape::Box {
            center: DVec3::new(10.0, 0.0, 0.0),
            half: DVec3::ONE,
            yaw: 0.3,
        };
        assert!(b.hit(DVec3::ZERO, -X, 0.0, 100.0).is_none());
        assert!(b.hit(DVec3::ZERO, X, 0.0, 5.0).is_none());
        assert!(b.hit(DVec3::new(10.0, 0.0, 0.0), X, 0.0, 100.0).is_none());
        assert!(b.hit(DVec3::ZERO, DVec3::Y, 0.0, 100.0).is_none());
        let c = Shape::Cylinder {
            base: DVec3::new(5.0, 0.0, -1.0),
            radius: 0.5,
            height: 2.0,
        };
        assert!(c.hit(DVec3::new(0.0, 0.0, 1.5), X, 0.0, 100.0).is_none());
        let e = Shape::Ellipsoid {
            center: DVec3::ZERO,
            radii: DVec3::ONE,
        };
        assert!(e.hit(DVec3::ZERO, X, 0.0, 100.0).is_none());
    }
}
