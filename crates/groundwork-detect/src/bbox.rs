//! Oriented boxes in the ground plane: the minimum-area rectangle around a cluster's
//! footprint (convex hull, then one candidate rectangle per hull edge).
//!
//! Chosen over L-shape fitting: it is exact, needs no angle search (L-shape fitting scores
//! ~90 candidate headings against every point, which alone would eat the time budget of a
//! scan with 50 000 clustered points), and on a car seen from a corner the hull's long edges
//! are its sides, so the headings agree. Seen from one side only, both methods see a line:
//! the box is then as wide as the visible points (see docs/detector.md).

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

/// Bins along x of the interior filter.
const BINS: usize = 32;

/// Scratch of [`min_area_rect`], reused between calls.
#[derive(Debug, Clone, Default)]
pub struct RectScratch {
    local: Vec<[f64; 2]>,
    hull: Vec<[f64; 2]>,
    sample: Vec<[f64; 2]>,
    inner: Vec<[f64; 2]>,
    /// Per bin, the inner hull's edges over it.
    edges: Vec<BinEdges>,
}

/// Most inner-hull edges over one bin.
const EDGES: usize = 8;

/// The inner hull's edges over one bin: origins and directions, x then y.
#[derive(Debug, Clone, Copy, Default)]
struct BinEdges {
    o: [[f64; EDGES]; 2],
    d: [[f64; EDGES]; 2],
}

impl BinEdges {
    /// No point is strictly left of a zero-length edge: the bin keeps all its points.
    const KEEP: Self = Self {
        o: [[0.0; EDGES]; 2],
        d: [[0.0; EDGES]; 2],
    };
}

/// Drops points that cannot be on the hull, before the hull's sort (a wall or a hedge row
/// holds thousands of points, nearly all inside). The lowest and highest point of each of
/// [`BINS`] slices along x, with the leftmost and rightmost points, span an inner hull; a
/// point strictly left of every inner-hull edge over its slice (the same products as
/// [`convex_hull`]'s test) is strictly inside it, so inside the full hull and not one of its
/// vertices. Edges are given to slices by the very function that gives points theirs, which
/// is monotone in x: an edge over a point's x is always among those tested.
fn discard_interior(s: &mut RectScratch) {
    let pts = &mut s.local;
    if pts.len() < 4 * BINS {
        return;
    }
    let (mut lo, mut hi) = (pts[0], pts[0]);
    for p in pts.iter() {
        if p[0] < lo[0] {
            lo = *p;
        }
        if p[0] > hi[0] {
            hi = *p;
        }
    }
    let width = hi[0] - lo[0];
    if width <= 0.0 {
        return;
    }
    let scale = BINS as f64 / width;
    // x − lo ≥ 0: a 32-bit conversion (a 64-bit unsigned one has no instruction here).
    let bin = |x: f64| (((x - lo[0]) * scale) as i32).min(BINS as i32 - 1) as usize;
    let mut low = [[0.0, f64::INFINITY]; BINS];
    let mut high = [[0.0, f64::NEG_INFINITY]; BINS];
    for p in pts.iter() {
        let b = bin(p[0]);
        // Selects, not branches: which point is lowest in its bin is not predictable.
        low[b] = if p[1] < low[b][1] { *p } else { low[b] };
        high[b] = if p[1] > high[b][1] { *p } else { high[b] };
    }
    s.sample.clear();
    s.sample.extend([lo, hi]);
    for (l, h) in low.iter().zip(&high) {
        if l[1].is_finite() {
            s.sample.extend([*l, *h]);
        }
    }
    convex_hull(&mut s.sample, &mut s.inner);
    let m = s.inner.len();
    if m < 3 {
        return;
    }
    // Each bin's edges as (origin, direction), padded to `EDGES` by repeating one; a bin
    // with more (a curve crossing it in small steps) is not filtered.
    s.edges.clear();
    s.edges.resize(BINS, BinEdges::default());
    let mut count = [0usize; BINS];
    for k in 0..m {
        let (o, a) = (s.inner[k], s.inner[(k + 1) % m]);
        let over = bin(o[0].min(a[0]))..=bin(o[0].max(a[0]));
        for (e, n) in s.edges[over.clone()].iter_mut().zip(&mut count[over]) {
            if *n < EDGES {
                e.o[0][*n] = o[0];
                e.o[1][*n] = o[1];
                e.d[0][*n] = a[0] - o[0];
                e.d[1][*n] = a[1] - o[1];
            }
            *n += 1;
        }
    }
    for (e, &n) in s.edges.iter_mut().zip(&count) {
        if n == 0 || n > EDGES {
            *e = BinEdges::KEEP;
        }
        for k in n..EDGES {
            e.o[0][k] = e.o[0][0];
            e.o[1][k] = e.o[1][0];
            e.d[0][k] = e.d[0][0];
            e.d[1][k] = e.d[1][0];
        }
    }
    let edges = &s.edges;
    pts.retain(|p| {
        let e = &edges[bin(p[0])];
        // `cross(o, o + d, p) > 0` for every edge, without a branch.
        let mut inside = true;
        for k in 0..EDGES {
            inside &= e.d[0][k] * (p[1] - e.o[1][k]) - e.d[1][k] * (p[0] - e.o[0][k]) > 0.0;
        }
        !inside
    });
}

/// The minimum-area rectangle around `pts` (x, y). `scratch` is reused between calls.
/// Computed about the points' first point in f64, so boxes far from the origin keep
/// centimetre precision.
pub fn min_area_rect(pts: &[[f32; 2]], scratch: &mut RectScratch) -> Rect {
    let Some(&[ox, oy]) = pts.first() else {
        return Rect::default();
    };
    scratch.local.clear();
    scratch.local.extend(
        pts.iter()
            .map(|p| [f64::from(p[0] - ox), f64::from(p[1] - oy)]),
    );
    discard_interior(scratch);
    let hull = &mut scratch.hull;
    convex_hull(&mut scratch.local, hull);
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

    /// The hull of `pts` with and without the interior filter.
    fn hulls(pts: &[[f64; 2]]) -> (Vec<[f64; 2]>, Vec<[f64; 2]>, usize) {
        let mut plain = (pts.to_vec(), Vec::new());
        convex_hull(&mut plain.0, &mut plain.1);
        let mut s = RectScratch {
            local: pts.to_vec(),
            ..Default::default()
        };
        discard_interior(&mut s);
        let kept = s.local.len();
        convex_hull(&mut s.local, &mut s.hull);
        (plain.1, s.hull, kept)
    }

    #[test]
    fn the_interior_filter_keeps_the_hull_of_a_dense_footprint() {
        // A car's footprint and a wall's band, filled: most points go, the hull stays.
        let car = box_points([12.0, -3.0], 0.3, 4.4, 1.8);
        for shape in [car, box_points([30.0, 8.0], 1.2, 25.0, 0.6)] {
            let pts: Vec<[f64; 2]> = shape
                .iter()
                .map(|p| [f64::from(p[0]), f64::from(p[1])])
                .collect();
            let (plain, filtered, kept) = hulls(&pts);
            assert_eq!(plain, filtered);
            assert!(kept * 2 < pts.len(), "{kept} of {}", pts.len());
        }
    }

    proptest! {
        #[test]
        fn the_interior_filter_never_changes_the_hull(
            pts in prop::collection::vec((-20i32..20, -20i32..20, 0.0f64..1.0), 0..600),
            step in prop::sample::select(vec![0.05f64, 0.15, 1.0]),
        ) {
            // Coarse coordinates: duplicates, collinear runs and vertical edges are common.
            let pts: Vec<[f64; 2]> = pts
                .iter()
                .map(|&(x, y, jitter)| [f64::from(x) * step, f64::from(y) * step + jitter * f64::from(x % 3 == 0)])
                .collect();
            let (plain, filtered, kept) = hulls(&pts);
            prop_assert_eq!(plain, filtered);
            prop_assert!(kept <= pts.len());
        }

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
