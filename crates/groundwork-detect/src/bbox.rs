//! Oriented boxes in the ground plane: the minimum-area rectangle around a cluster's
//! footprint (convex hull, then one candidate rectangle per hull edge).
//!
//! Chosen over L-shape fitting: it is exact, needs no angle search (L-shape fitting scores
//! ~90 candidate headings against every point, which alone would eat the time budget of a
//! scan with 50 000 clustered points), and on a car seen from a corner the hull's long edges
//! are its sides, so the headings agree. Seen from one side only, both methods see a line:
//! the box is then as wide as the visible points (see the README's error table).

/// A box in the ground plane.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Rect {
    /// Centre, metres.
    pub center: [f32; 2],
    /// Heading of the long side, radians in (−π/2, π/2].
    pub yaw: f32,
    /// Long side, metres.
    pub length: f32,
    /// Short side, metres.
    pub width: f32,
}

fn cross(o: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
}

/// Convex hull (Andrew's monotone chain), counter-clockwise, no collinear points. Sorts
/// `pts` in place.
pub fn convex_hull(pts: &mut [[f64; 2]], hull: &mut Vec<[f64; 2]>) {
    hull.clear();
    pts.sort_unstable_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    if pts.len() < 3 {
        hull.extend_from_slice(pts);
        hull.dedup();
        return;
    }
    for &p in pts.iter() {
        while hull.len() >= 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0 {
            hull.pop();
        }
        hull.push(p);
    }
    let lower = hull.len() + 1;
    for &p in pts.iter().rev().skip(1) {
        while hull.len() >= lower && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0 {
            hull.pop();
        }
        hull.push(p);
    }
    hull.pop(); // the first point again
}

/// Drops points strictly inside the octagon of the extreme points in eight directions
/// (Akl–Toussaint): they cannot be on the hull, and a wall's thousands of points shrink to a
/// few dozen before the hull's sort.
fn discard_interior(pts: &mut Vec<[f64; 2]>) {
    if pts.len() < 32 {
        return;
    }
    const DIRS: [[f64; 2]; 8] = [
        [1.0, 0.0],
        [1.0, 1.0],
        [0.0, 1.0],
        [-1.0, 1.0],
        [-1.0, 0.0],
        [-1.0, -1.0],
        [0.0, -1.0],
        [1.0, -1.0],
    ];
    let mut ext = [pts[0]; 8];
    let mut best = [f64::MIN; 8];
    for p in pts.iter() {
        for (k, d) in DIRS.iter().enumerate() {
            let v = p[0] * d[0] + p[1] * d[1];
            if v > best[k] {
                best[k] = v;
                ext[k] = *p;
            }
        }
    }
    // The octagon, counter-clockwise (the directions turn counter-clockwise).
    let mut poly: Vec<[f64; 2]> = ext.to_vec();
    poly.dedup();
    if poly.len() > 1 && poly.first() == poly.last() {
        poly.pop();
    }
    if poly.len() < 3 {
        return;
    }
    // Eight edges always (a short polygon repeats its last edge), tested without branches
    // so the test vectorises; the same products as `cross`, so the octagon's own vertices
    // give exactly 0 and stay.
    let m = poly.len();
    let edge = |e: usize| {
        let e = e.min(m - 1);
        (poly[e], poly[(e + 1) % m])
    };
    let (mut ox, mut oy, mut ax, mut ay) = ([0.0; 8], [0.0; 8], [0.0; 8], [0.0; 8]);
    for e in 0..8 {
        let (o, a) = edge(e);
        (ox[e], oy[e], ax[e], ay[e]) = (o[0], o[1], a[0] - o[0], a[1] - o[1]);
    }
    pts.retain(|p| {
        let mut inside = true;
        for e in 0..8 {
            inside &= ax[e] * (p[1] - oy[e]) - ay[e] * (p[0] - ox[e]) > 0.0;
        }
        !inside
    });
}

/// The minimum-area rectangle around `pts` (x, y). `scratch` is reused between calls.
/// Computed about the points' first point in f64, so boxes far from the origin keep
/// centimetre precision.
pub fn min_area_rect(pts: &[[f32; 2]], scratch: &mut (Vec<[f64; 2]>, Vec<[f64; 2]>)) -> Rect {
    let Some(&[ox, oy]) = pts.first() else {
        return Rect::default();
    };
    let (local, hull) = scratch;
    local.clear();
    local.extend(
        pts.iter()
            .map(|p| [f64::from(p[0] - ox), f64::from(p[1] - oy)]),
    );
    discard_interior(local);
    convex_hull(local, hull);
    /// A candidate rectangle: area, axis, centre, extents along and across the axis.
    struct Candidate {
        area: f64,
        axis: [f64; 2],
        center: [f64; 2],
        along: f64,
        across: f64,
    }
    let mut best: Option<Candidate> = None;
    let m = hull.len();
    if m == 1 {
        return Rect {
            center: [ox + hull[0][0] as f32, oy + hull[0][1] as f32],
            ..Default::default()
        };
    }
    for e in 0..m {
        let (a, b) = (hull[e], hull[(e + 1) % m]);
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let norm = dx.hypot(dy);
        if norm == 0.0 {
            continue;
        }
        let u = [dx / norm, dy / norm];
        let (mut lo_u, mut hi_u, mut lo_v, mut hi_v) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for p in hull.iter() {
            let pu = p[0] * u[0] + p[1] * u[1];
            let pv = -p[0] * u[1] + p[1] * u[0];
            lo_u = lo_u.min(pu);
            hi_u = hi_u.max(pu);
            lo_v = lo_v.min(pv);
            hi_v = hi_v.max(pv);
        }
        let (eu, ev) = (hi_u - lo_u, hi_v - lo_v);
        let area = eu * ev;
        // Ties (a square, a line) keep the first edge: deterministic.
        if best.as_ref().is_none_or(|b| area < b.area - 1e-12) {
            let (cu, cv) = (0.5 * (lo_u + hi_u), 0.5 * (lo_v + hi_v));
            best = Some(Candidate {
                area,
                axis: u,
                center: [cu * u[0] - cv * u[1], cu * u[1] + cv * u[0]],
                along: eu,
                across: ev,
            });
        }
    }
    let Some(Candidate {
        axis: u,
        center: c,
        along: eu,
        across: ev,
        ..
    }) = best
    else {
        return Rect::default();
    };
    // The long side gives the heading.
    let (axis, length, width) = if eu >= ev {
        (u, eu, ev)
    } else {
        ([-u[1], u[0]], ev, eu)
    };
    let mut yaw = axis[1].atan2(axis[0]);
    if yaw <= -std::f64::consts::FRAC_PI_2 {
        yaw += std::f64::consts::PI;
    } else if yaw > std::f64::consts::FRAC_PI_2 {
        yaw -= std::f64::consts::PI;
    }
    Rect {
        center: [ox + c[0] as f32, oy + c[1] as f32],
        yaw: yaw as f32,
        length: length as f32,
        width: width as f32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn box_points(c: [f32; 2], yaw: f32, l: f32, w: f32) -> Vec<[f32; 2]> {
        let (s, co) = yaw.sin_cos();
        let mut v = Vec::new();
        for a in 0..=20 {
            for b in 0..=10 {
                let u = (a as f32 / 20.0 - 0.5) * l;
                let t = (b as f32 / 10.0 - 0.5) * w;
                v.push([c[0] + u * co - t * s, c[1] + u * s + t * co]);
            }
        }
        v
    }

    #[test]
    fn a_turned_box_is_found_again() {
        let mut s = Default::default();
        let r = min_area_rect(&box_points([20.0, -5.0], 0.6, 4.5, 1.8), &mut s);
        assert!((r.yaw - 0.6).abs() < 1e-4, "{r:?}");
        assert!((r.length - 4.5).abs() < 1e-4 && (r.width - 1.8).abs() < 1e-4);
        assert!((r.center[0] - 20.0).abs() < 1e-4 && (r.center[1] + 5.0).abs() < 1e-4);
        // The heading is the long side's, folded into (−π/2, π/2].
        let r = min_area_rect(&box_points([0.0, 0.0], 2.0, 4.0, 1.0), &mut s);
        assert!((r.yaw - (2.0 - std::f32::consts::PI)).abs() < 1e-4, "{r:?}");
    }

    #[test]
    fn degenerate_footprints_give_thin_or_empty_boxes() {
        let mut s = Default::default();
        assert_eq!(min_area_rect(&[], &mut s), Rect::default());
        let one = min_area_rect(&[[3.0, 4.0], [3.0, 4.0]], &mut s);
        assert_eq!((one.center, one.length, one.width), ([3.0, 4.0], 0.0, 0.0));
        let line = min_area_rect(&[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]], &mut s);
        assert!((line.length - 8f32.sqrt()).abs() < 1e-5 && line.width < 1e-6);
        assert!((line.yaw - std::f32::consts::FRAC_PI_4).abs() < 1e-5);
    }

    proptest! {
        #[test]
        fn every_point_lies_in_its_box(pts in prop::collection::vec((-50.0f32..50.0, -50.0f32..50.0), 1..200)) {
            let pts: Vec<[f32; 2]> = pts.into_iter().map(|(x, y)| [x, y]).collect();
            let r = min_area_rect(&pts, &mut Default::default());
            let (s, c) = r.yaw.sin_cos();
            for p in &pts {
                let (dx, dy) = (p[0] - r.center[0], p[1] - r.center[1]);
                let u = dx * c + dy * s;
                let v = -dx * s + dy * c;
                prop_assert!(u.abs() <= r.length / 2.0 + 1e-3 && v.abs() <= r.width / 2.0 + 1e-3);
            }
            prop_assert!(r.length >= r.width && r.yaw > -std::f32::consts::FRAC_PI_2 - 1e-6 && r.yaw <= std::f32::consts::FRAC_PI_2 + 1e-6);
        }
    }
}
