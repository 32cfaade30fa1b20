//! A fitted frame: every segment's components with their ground likelihoods.

use rayon::prelude::*;

use crate::config::SegmenterConfig;
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
}

/// One scan's fitted model, segment by segment.
#[derive(Debug, Clone, Default)]
pub struct FrameModel {
    /// `components[start[s]..start[s+1]]` belong to segment s.
    start: Vec<u32>,
    components: Vec<GroundComponent>,
    /// The same components in f32, laid out for the vectorised query.
    table: QueryTable,
}

impl FrameModel {
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
    let g = &cfg.ground;
    let comps = fit
        .components
        .iter()
        .map(|gauss| {
            let f = flatness(&gauss.covariance);
            GroundComponent {
                gaussian: *gauss,
                flatness: inverted_sigmoid(f.lambda_min, g.flatness),
                orientation: inverted_sigmoid(f.tilt, g.orientation),
                elevation: inverted_sigmoid(gauss.mean[2] - min_inlier, g.elevation),
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
    };
    let mut stats = Vec::with_capacity(segments);
    model.start.push(0);
    for (_, comps, st) in fitted {
        model.components.extend(comps);
        model.start.push(model.components.len() as u32);
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
