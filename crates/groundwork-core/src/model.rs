//! A fitted frame: every segment's components with their ground likelihoods.

use rayon::prelude::*;

use crate::config::SegmenterConfig;
use crate::fastmath::round_i32;
use crate::gmm::{EmScratch, Evaluator, Gaussian, fit_segment_with};
use crate::grouping::SegmentedPoints;
use crate::likelihood::{flatness, inverted_sigmoid};
use crate::query::QueryTable;

/// A component with its three ground likelihoods (paper §III-C).
#[derive(Debug, Clone, Copy)]
pub struct GroundComponent {
    /// The fitted Gaussian (ground-aligned frame of its scan).
    pub gaussian: Gaussian,
    /// p_{g,λ}: flatness likelihood.
    pub flatness: f64,
    /// p_{g,θ}: orientation likelihood.
    pub orientation: f64,
    /// p_{g,e}: elevation likelihood.
    pub elevation: f64,
    pub(crate) eval: Evaluator,
}

impl GroundComponent {
    /// The component's own ground likelihood, the product of the three.
    pub fn ground_likelihood(&self) -> f64 {
        self.flatness * self.orientation * self.elevation
    }
}

/// Per-segment fitting statistics.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SegmentStats {
    /// EM iterations run.
    pub iterations: u32,
    /// Points below the lowest retained component by more than τ_o.
    pub outliers: u32,
    /// Components ignored by the zone-1 height filter.
    pub height_filtered: u32,
    /// Height of the segment's lowest inlier (the paper's elevation reference), if it has
    /// a model.
    pub lowest_inlier: Option<f64>,
}

/// One scan's fitted model, segment by segment.
#[derive(Debug, Clone, Default)]
pub struct FrameModel {
    /// `components[start[s]..start[s+1]]` belong to segment s.
    start: Vec<u32>,
    components: Vec<GroundComponent>,
    /// The same components in f32, laid out for the vectorised query.
    table: QueryTable,
    /// Per segment: the height of its lowest inlier (NaN without a model).
    lowest_inliers: Vec<f32>,
}

impl FrameModel {
    /// A model of `lowest_inliers.len()` segments without components, for tests of what
    /// reads the references.
    #[cfg(test)]
    pub(crate) fn with_lowest_inliers(lowest_inliers: Vec<f32>) -> Self {
        Self {
            start: vec![0; lowest_inliers.len() + 1],
            lowest_inliers,
            ..Self::default()
        }
    }

    /// Height of segment `s`'s lowest inlier, the paper's elevation reference (NaN if it
    /// has no model).
    #[inline]
    pub fn lowest_inlier(&self, s: u32) -> f32 {
        self.lowest_inliers
            .get(s as usize)
            .copied()
            .unwrap_or(f32::NAN)
    }

    /// Components of segment `s` (empty if it has no model).
    #[inline]
    pub fn segment(&self, s: u32) -> &[GroundComponent] {
        let s = s as usize;
        match (self.start.get(s), self.start.get(s + 1)) {
            (Some(&a), Some(&b)) => &self.components[a as usize..b as usize],
            _ => &[],
        }
    }

    /// Segments in the model.
    pub fn segment_count(&self) -> usize {
        self.start.len().saturating_sub(1)
    }

    /// All components of all segments.
    pub fn components(&self) -> &[GroundComponent] {
        &self.components
    }

    pub(crate) fn query_table(&self) -> &QueryTable {
        &self.table
    }

    /// Segments that hold at least one component.
    pub fn fitted_segments(&self) -> usize {
        self.start.windows(2).filter(|w| w[1] > w[0]).count()
    }
}

thread_local! {
    /// EM's buffers, one set per thread, reused from segment to segment and scan to scan
    /// (fresh ones cost an allocation per buffer and segment; every use overwrites them).
    static EM_SCRATCH: std::cell::RefCell<EmScratch> = std::cell::RefCell::new(EmScratch::default());
}

/// The lowest of `zs` at or above `cut` (∞ if none) and how many lie below it. Eight
/// running minima and counts, one per lane: a single `min` chain with a branch ran one
/// point per `minsd` latency (4 % of a scan's time for a pass over every point).
fn lowest_inlier(zs: &[f64], cut: f64) -> (f64, u32) {
    const W: usize = 8;
    let (mut lo, mut below) = ([f64::INFINITY; W], [0u32; W]);
    let chunks = zs.chunks_exact(W);
    let tail = chunks.remainder();
    for c in chunks {
        for l in 0..W {
            let inlier = c[l] >= cut;
            lo[l] = if inlier && c[l] < lo[l] { c[l] } else { lo[l] };
            below[l] += u32::from(!inlier);
        }
    }
    for (l, &z) in tail.iter().enumerate() {
        let inlier = z >= cut;
        lo[l] = if inlier && z < lo[l] { z } else { lo[l] };
        below[l] += u32::from(!inlier);
    }
    (
        lo.into_iter().fold(f64::INFINITY, f64::min),
        below.iter().sum(),
    )
}

/// Horizontal range (no `hypot`: its overflow care costs several times a square root and
/// coordinates here are bounded by `sensor.max_coordinate`).
#[inline]
fn range(x: f64, y: f64) -> f64 {
    (x * x + y * y).sqrt()
}

/// The lowest inlier of a segment per band of horizontal range: the terrain-following
/// elevation reference (`ground.elevation_window`).
struct RangeProfile {
    /// Range of band 0's inner edge, metres.
    r0: f64,
    /// Lowest inlier height per band (∞ where a band has none).
    lows: Vec<f64>,
    /// The lower envelope of the lows as a line in range (see `envelope`).
    line: Option<(f64, f64)>,
}

impl RangeProfile {
    /// Band width, metres: fine enough that a band's edge moves a window by little.
    const BAND: f64 = 0.25;

    fn new(xs: &[f64], ys: &[f64], zs: &[f64], cut: f64) -> Self {
        // Blocks of points: squared ranges and then bands in straight loops that vectorise
        // (one square root per point, a correctly rounded root being monotonic: the
        // extremes on squared ranges give the same bits), the lows in a scalar pass that
        // keeps the current band's low in a register (points come band after band, and a
        // min through memory serialised on store-to-load forwarding).
        const BLOCK: usize = 64;
        let mut r2 = [0.0f64; BLOCK];
        let (mut lo2, mut hi2) = ([f64::INFINITY; 4], [f64::NEG_INFINITY; 4]);
        for (bx, by) in xs.chunks(BLOCK).zip(ys.chunks(BLOCK)) {
            for (r, (&x, &y)) in r2.iter_mut().zip(bx.iter().zip(by)) {
                *r = x * x + y * y;
            }
            // A last, partial block repeats its first point: the extremes stay.
            let first = r2[0];
            r2[bx.len()..].fill(first);
            for four in r2.chunks_exact(4) {
                for l in 0..4 {
                    lo2[l] = if four[l] < lo2[l] { four[l] } else { lo2[l] };
                    hi2[l] = if four[l] > hi2[l] { four[l] } else { hi2[l] };
                }
            }
        }
        let lo = lo2.into_iter().fold(f64::INFINITY, f64::min).sqrt();
        let hi = hi2.into_iter().fold(f64::NEG_INFINITY, f64::max).sqrt();
        if !(lo.is_finite() && hi.is_finite()) {
            return Self {
                r0: 0.0,
                lows: Vec::new(),
                line: None,
            };
        }
        // Segments are bounded (at most the zone model's outer ring); the cap only guards
        // against an absurd configuration.
        let bands = (((hi - lo) / Self::BAND) as usize + 1).min(1 << 16);
        let last = (bands - 1) as f64;
        let mut band = [0u32; BLOCK];
        // Four tables of lows, point i into table i % 4, merged after: a min through memory
        // waits on the store before it only every fourth point, and outliers (below `cut`)
        // count as +∞ instead of a branch. A minimum is the same in any order.
        let mut four = vec![f64::INFINITY; 4 * bands];
        for ((bx, by), bz) in xs.chunks(BLOCK).zip(ys.chunks(BLOCK)).zip(zs.chunks(BLOCK)) {
            for (b, (&x, &y)) in band.iter_mut().zip(bx.iter().zip(by)) {
                // r ≥ lo, so the band is at least 0, and below 2¹⁶.
                *b = round_i32(((range(x, y) - lo) / Self::BAND).min(last).floor()) as u32;
            }
            for (i, (&b, &z)) in band[..bz.len()].iter().zip(bz).enumerate() {
                let z = if z < cut { f64::INFINITY } else { z };
                if let Some(low) = four.get_mut(4 * b as usize + i % 4) {
                    *low = if z < *low { z } else { *low };
                }
            }
        }
        let lows: Vec<f64> = four
            .chunks_exact(4)
            .map(|l| l[0].min(l[1]).min(l[2].min(l[3])))
            .collect();
        let line = Self::envelope(&lows);
        Self { r0: lo, lows, line }
    }

    /// A line z = a + b·(r − r0) under the bands' lows: a least-squares fit, refitted three
    /// times to the bands at most `ENVELOPE_SLACK` above it, so that an object hiding the
    /// ground over a few bands (a car, a wall) does not raise it. `None` with fewer than
    /// three bands or a slope steeper than any ground.
    fn envelope(lows: &[f64]) -> Option<(f64, f64)> {
        const ENVELOPE_SLACK: f64 = 0.1;
        const MAX_GRADE: f64 = 0.5;
        let bands = || {
            lows.iter()
                .enumerate()
                .filter(|(_, z)| z.is_finite())
                .map(|(b, &z)| ((b as f64 + 0.5) * Self::BAND, z))
        };
        let mut line: Option<(f64, f64)> = None;
        for _ in 0..4 {
            let (mut n, mut sr, mut sz, mut srr, mut srz) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for (r, z) in bands() {
                if line.is_some_and(|(a, b)| z - (a + b * r) > ENVELOPE_SLACK) {
                    continue;
                }
                (n, sr, sz, srr, srz) = (n + 1.0, sr + r, sz + z, srr + r * r, srz + r * z);
            }
            let det = n * srr - sr * sr;
            if n < 3.0 || det <= 1e-9 {
                return None;
            }
            let b = (n * srz - sr * sz) / det;
            line = Some(((sz - b * sr) / n, b));
        }
        line.filter(|(a, b)| a.is_finite() && b.abs() <= MAX_GRADE)
    }

    /// The terrain-following reference at range `r`: the lowest inlier within `window`
    /// metres, unless the envelope line lies lower there (∞ if there is neither).
    fn reference(&self, r: f64, window: f64) -> f64 {
        if self.lows.is_empty() {
            return f64::INFINITY;
        }
        let last = self.lows.len() as isize - 1;
        let band = |r: f64| (((r - self.r0) / Self::BAND).floor() as isize).clamp(0, last) as usize;
        let (a, b) = (band(r - window), band(r + window));
        let near = self.lows[a..=b]
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        match self.line {
            Some((a, b)) => near.min(a + b * (r - self.r0)),
            None => near,
        }
    }
}

/// Fits the components of one segment and computes their ground likelihoods, with the
/// outlier rule of §III-D. `lower_bound` comes from the zone-1 height filter.
fn fit_ground_segment(
    xs: &[f64],
    ys: &[f64],
    zs: &[f64],
    cfg: &SegmenterConfig,
    lower_bound: Option<f64>,
) -> (Vec<GroundComponent>, SegmentStats) {
    let fit = EM_SCRATCH.with_borrow_mut(|s| fit_segment_with(xs, ys, zs, &cfg.gmm, s));
    let mut stats = SegmentStats {
        iterations: fit.iterations,
        ..Default::default()
    };
    if fit.components.is_empty() {
        return (Vec::new(), stats);
    }
    // Lowest retained component: the height filter may veto components far below the
    // expected ground, but never all of them.
    let lowest_all = fit
        .components
        .iter()
        .map(|g| g.mean[2])
        .fold(f64::INFINITY, f64::min);
    let lowest = match lower_bound {
        Some(lb) => {
            let kept = fit.components.iter().filter(|g| g.mean[2] >= lb);
            let lowest_kept = kept.map(|g| g.mean[2]).fold(f64::INFINITY, f64::min);
            if lowest_kept.is_finite() {
                stats.height_filtered =
                    fit.components.iter().filter(|g| g.mean[2] < lb).count() as u32;
                lowest_kept
            } else {
                lowest_all
            }
        }
        None => lowest_all,
    };
    // Points more than τ_o below the lowest retained mean are outliers (multipath
    // reflections); the segment's ground reference is the lowest remaining point.
    let cut = lowest - cfg.ground.outlier_threshold;
    let (min_inlier, outliers) = lowest_inlier(zs, cut);
    stats.outliers = outliers;
    let mut min_inlier = min_inlier;
    if !min_inlier.is_finite() {
        // Cannot happen (the lowest mean lies above its lowest point), kept for safety.
        min_inlier = lowest;
    }
    stats.lowest_inlier = Some(min_inlier);
    let g = &cfg.ground;
    let w = g.elevation_window;
    let profile = (w > 0.0).then(|| RangeProfile::new(xs, ys, zs, cut));
    let comps = fit
        .components
        .iter()
        .map(|gauss| {
            let f = flatness(&gauss.covariance);
            let reference = match &profile {
                Some(p) => p.reference(range(gauss.mean[0], gauss.mean[1]), w),
                None => min_inlier,
            };
            // Never below the segment's lowest inlier (a band is a subset).
            let reference = if reference.is_finite() {
                reference.max(min_inlier)
            } else {
                min_inlier
            };
            GroundComponent {
                gaussian: *gauss,
                flatness: inverted_sigmoid(f.lambda_min, g.flatness),
                orientation: inverted_sigmoid(f.tilt, g.orientation),
                elevation: inverted_sigmoid(gauss.mean[2] - reference, g.elevation),
                eval: Evaluator::new(gauss).unwrap_or_else(|| Evaluator::unit(gauss)),
            }
        })
        .collect();
    (comps, stats)
}

/// Fits every segment in parallel. `lower_bound(s)` gives the height filter's bound for
/// segment s (only zone-1 segments ever have one).
pub fn fit_frame(
    pts: &SegmentedPoints,
    cfg: &SegmenterConfig,
    lower_bound: impl Fn(usize) -> Option<f64> + Sync,
) -> (FrameModel, Vec<SegmentStats>) {
    let segments = pts.start.len().saturating_sub(1);
    // Big segments first so that rayon's work stealing balances the two cores well.
    let mut order: Vec<usize> = (0..segments).collect();
    order.sort_unstable_by_key(|&s| std::cmp::Reverse(pts.start[s + 1] - pts.start[s]));
    let mut fitted: Vec<(usize, Vec<GroundComponent>, SegmentStats)> = order
        .par_iter()
        .with_max_len(1)
        .map(|&s| {
            let (a, b) = (pts.start[s] as usize, pts.start[s + 1] as usize);
            let (c, st) = fit_ground_segment(
                &pts.xs[a..b],
                &pts.ys[a..b],
                &pts.zs[a..b],
                cfg,
                lower_bound(s),
            );
            (s, c, st)
        })
        .collect();
    fitted.sort_unstable_by_key(|f| f.0);
    let mut model = FrameModel {
        start: Vec::with_capacity(segments + 1),
        components: Vec::with_capacity(fitted.iter().map(|f| f.1.len()).sum()),
        table: QueryTable::default(),
        lowest_inliers: Vec::with_capacity(segments),
    };
    let mut stats = Vec::with_capacity(segments);
    model.start.push(0);
    for (_, comps, st) in fitted {
        model.components.extend(comps);
        model.start.push(model.components.len() as u32);
        model
            .lowest_inliers
            .push(st.lowest_inlier.map_or(f32::NAN, |z| z as f32));
        stats.push(st);
    }
    model.table = QueryTable::new(&model);
    (model, stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat ground patch at z = 0 plus, optionally, a few multipath points 1.5 m below.
    fn patch(outliers: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut xs, mut ys, mut zs) = (vec![], vec![], vec![]);
        for i in 0..20 {
            for j in 0..20 {
                xs.push(5.0 + i as f64 * 0.1);
                ys.push(j as f64 * 0.1);
                zs.push(((i * 7 + j * 3) % 5) as f64 * 0.005);
            }
        }
        for k in 0..outliers {
            xs.push(5.5 + k as f64 * 0.1);
            ys.push(1.0);
            zs.push(-1.5);
        }
        (xs, ys, zs)
    }

    /// Points on z = f(x) for x in `xs_range` (0.1 m apart), y in [0, 2) (0.2 m apart),
    /// with ±1 cm of deterministic roughness.
    fn surface(
        out: &mut (Vec<f64>, Vec<f64>, Vec<f64>),
        (x0, x1): (f64, f64),
        f: impl Fn(f64) -> f64,
    ) {
        let n = ((x1 - x0) / 0.1).round() as usize;
        for i in 0..n {
            for j in 0..10 {
                let x = x0 + i as f64 * 0.1;
                out.0.push(x);
                out.1.push(j as f64 * 0.2);
                out.2
                    .push(f(x) + ((i * 7 + j * 3) % 5) as f64 * 0.005 - 0.01);
            }
        }
    }

    fn with_window(w: f64) -> SegmenterConfig {
        let mut cfg = SegmenterConfig::default();
        cfg.ground.elevation_window = w;
        cfg
    }

    #[test]
    fn the_elevation_reference_follows_a_slope() {
        // A segment 20 m long on a 10 % downhill grade: 2 m of fall from its near end.
        let mut pts = (vec![], vec![], vec![]);
        surface(&mut pts, (10.0, 30.0), |x| -0.1 * (x - 10.0));
        let (xs, ys, zs) = &pts;
        let (follows, _) = fit_ground_segment(xs, ys, zs, &with_window(2.0), None);
        let (wide, _) = fit_ground_segment(xs, ys, zs, &with_window(0.0), None);
        assert!(follows.len() > 1 && wide.len() > 1);
        // Every component of the slope is ground against its own stretch of it...
        for g in &follows {
            assert!(g.elevation > 0.9, "{:?} {}", g.gaussian.mean, g.elevation);
        }
        // ...while the segment-wide reference, its far end 2 m lower, rejects the near half.
        let near = wide.iter().filter(|g| g.gaussian.mean[0] < 18.0);
        assert!(near.clone().count() > 0);
        for g in near {
            assert!(g.elevation < 0.5, "{:?} {}", g.gaussian.mean, g.elevation);
        }
    }

    #[test]
    fn an_object_hiding_the_ground_keeps_the_ground_as_its_reference() {
        // Flat ground at 10–17 m and 27–30 m; between them a box whose face (x = 19 m)
        // starts 0.3 m up and whose roof is 1.5 m up: no ground within 2 m of the roof.
        let mut pts = (vec![], vec![], vec![]);
        surface(&mut pts, (10.0, 17.0), |_| 0.0);
        surface(&mut pts, (27.0, 30.0), |_| 0.0);
        surface(&mut pts, (19.0, 25.0), |_| 1.5);
        for k in 0..12 {
            for j in 0..10 {
                pts.0.push(19.0);
                pts.1.push(j as f64 * 0.2);
                pts.2.push(0.3 + k as f64 * 0.1);
            }
        }
        let (xs, ys, zs) = &pts;
        let (c, _) = fit_ground_segment(xs, ys, zs, &with_window(2.0), None);
        let roof: Vec<_> = c.iter().filter(|g| g.gaussian.mean[2] > 1.2).collect();
        assert!(!roof.is_empty());
        // The envelope line through the ground's bands (z = 0), not the box's own 0.3 m.
        for g in roof {
            assert!(g.elevation < 0.1, "{:?} {}", g.gaussian.mean, g.elevation);
        }
    }

    #[test]
    fn flat_ground_patch_is_ground_with_high_likelihood() {
        let (xs, ys, zs) = patch(0);
        let (c, st) = fit_ground_segment(&xs, &ys, &zs, &SegmenterConfig::default(), None);
        assert!(!c.is_empty());
        assert_eq!(st.outliers, 0);
        for g in &c {
            assert!(g.ground_likelihood() > 0.8, "{g:?}");
        }
    }

    #[test]
    fn points_far_below_the_lowest_component_are_outliers() {
        // Five multipath points 1.5 m below: too few to own a component (τ_N = 10), so the
        // lowest component is the road; they lie > τ_o below it and are excluded from the
        // elevation reference, so the road keeps its high elevation likelihood.
        let (xs, ys, zs) = patch(5);
        let cfg = SegmenterConfig::default();
        let (c, st) = fit_ground_segment(&xs, &ys, &zs, &cfg, None);
        assert_eq!(st.outliers, 5);
        let road = c
            .iter()
            .max_by(|a, b| a.gaussian.weight.total_cmp(&b.gaussian.weight))
            .unwrap();
        assert!(road.elevation > 0.9, "{road:?}");
        // Without the rule (τ_o huge), the outliers become the reference and the road's
        // elevation likelihood collapses.
        let mut no_rule = cfg.clone();
        no_rule.ground.outlier_threshold = 100.0;
        let (c2, st2) = fit_ground_segment(&xs, &ys, &zs, &no_rule, None);
        assert_eq!(st2.outliers, 0);
        let road2 = c2
            .iter()
            .max_by(|a, b| a.gaussian.weight.total_cmp(&b.gaussian.weight))
            .unwrap();
        assert!(road2.elevation < road.elevation - 0.1, "{road2:?}");
    }

    #[test]
    fn height_filter_bound_vetoes_components_below_it() {
        // 40 multipath points: enough for their own component at z = −1.5.
        let (xs, ys, zs) = patch(40);
        let cfg = SegmenterConfig::default();
        let (_, st) = fit_ground_segment(&xs, &ys, &zs, &cfg, None);
        assert_eq!(st.height_filtered, 0);
        assert_eq!(st.outliers, 0, "the multipath component is the lowest one");
        let (c, st) = fit_ground_segment(&xs, &ys, &zs, &cfg, Some(-0.2));
        assert_eq!(st.height_filtered, 1);
        assert_eq!(st.outliers, 40);
        let road = c.iter().find(|g| g.gaussian.mean[2] > -0.1).unwrap();
        assert!(road.elevation > 0.9);
        // A bound above every component vetoes nothing rather than everything.
        let (_, st) = fit_ground_segment(&xs, &ys, &zs, &cfg, Some(10.0));
        assert_eq!(st.height_filtered, 0);
    }
}
