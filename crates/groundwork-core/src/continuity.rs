//! Ground continuity: a step after the query, where the papers are silent
//! (docs/algorithm.md, "Ground continuity").
//!
//! A segment's mixture explains its points with a few Gaussians. Where ground meets a wall,
//! a kerb or a parked car, the ground points at the foot of the object often fall to the
//! object's component, or a small segment holds no ground-like component at all, and
//! points lying on the road are called non-ground. Their neighbours across the segment
//! border are confident ground at the same height. This step raises an uncertain point
//! towards ground where it lies at the height of confident ground within a metre of it.
//!
//! It is built to keep the output stable (issue 41): every rule is a ramp, not a cut, and
//! the ground height is a weighted mean splatted bilinearly onto grid nodes, so the raised
//! probability is a continuous function of every coordinate and probability. The sums are
//! integers (fixed point), so they are exact in any order: a permuted scan gives the same
//! nodes, and the same output permuted.

use rayon::prelude::*;
use wide::f64x4;

use crate::config::{ContinuityConfig, Sigmoid};
use crate::fastmath::round_i32;
use crate::likelihood::inverted_sigmoid;
use crate::model::FrameModel;
use crate::zones::{BEYOND, NEAR};

/// Fixed-point scale of a confident point's weight (a weight of 1 is 2¹⁶).
pub(crate) const WEIGHT_ONE: f64 = 65_536.0;
/// Fixed-point scale of heights (2⁻¹⁶ m, 15 µm: far below any tolerance).
pub(crate) const HEIGHT_ONE: f64 = 65_536.0;
/// Heights are clamped to ±this (m) before the fixed-point sum, so that no sum can wrap
/// for any scan the segmenter accepts (2⁹ m · 2¹⁶ · 2¹⁶ per point, 2²⁰ points: < 2⁶¹).
pub(crate) const HEIGHT_CLAMP: f64 = 512.0;

/// The grid of one scan, kept between scans.
#[derive(Debug, Default, Clone)]
pub(crate) struct ContinuityScratch {
    /// Per node: Σ weight, Σ weight · height (fixed point); all zero between scans.
    /// One grid of sums per part of the scan splatted in parallel.
    sums: Vec<Vec<[i64; 2]>>,
    /// Per part: its uncertain points inside the grid (index in the scan, cell, height as
    /// f32 bits), listed while splatting so that raising reads only them, and screens them
    /// without a scattered load of their heights.
    candidates: Vec<Vec<[u32; 3]>>,
    /// Per node: the confident ground's height (m) and how far the node is trusted (0: no
    /// confident point reaches it).
    nodes: Vec<[f32; 2]>,
    /// Per cell (the square right of and above node (i, j), same index): the heights an
    /// uncertain point in it can match, the lowest trusted node height within reach less
    /// the cutoff and the highest plus it (empty: +∞, −∞). Most uncertain points lie far
    /// from any such height and are passed over with one lookup.
    bounds: Vec<[f32; 2]>,
    /// Scratch of the same size for the bounds' first pass (along rows).
    row_bounds: Vec<[f32; 2]>,
}

/// The paper's elevation likelihood of a single point: its height above the lowest
/// inlier of its own segment. A flat car roof or bonnet the mixtures already half call
/// ground is level with itself; this keeps its other points from rising with it.
pub(crate) struct Elevation<'a> {
    /// Segment of each point (`zones::NEAR`, or with the `zones::BEYOND` bit).
    pub bins: &'a [u32],
    /// The scan's fitted model (each segment's lowest inlier).
    pub model: &'a FrameModel,
    pub sigmoid: Sigmoid,
}

impl Elevation<'_> {
    /// 1 where a point's segment has no model to judge it by.
    fn likelihood(&self, i: usize, z: f64) -> f64 {
        let b = self.bins[i];
        if b == NEAR {
            return 0.0;
        }
        let lowest = self.model.lowest_inlier(b & !BEYOND);
        if lowest.is_nan() {
            1.0
        } else {
            inverted_sigmoid(z - f64::from(lowest), self.sigmoid)
        }
    }
}

/// A ramp from 0 at `from` to 1 at `to`, continuous (so that no decision hangs on a
/// rounding bit), as a multiplication by the reciprocal of its width: continuity's and the
/// terrain's per-point rules take it once or twice a point, and a division costs several
/// multiplications. Within about 1.5 ulp of (v − from) / (to − from), clamped.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Ramp {
    from: f64,
    scale: f64,
}

impl Ramp {
    pub(crate) fn new([from, to]: [f64; 2]) -> Self {
        Self {
            from,
            scale: 1.0 / (to - from),
        }
    }

    #[inline(always)]
    pub(crate) fn at(self, v: f64) -> f64 {
        ((v - self.from) * self.scale).clamp(0.0, 1.0)
    }

    /// [`Ramp::at`] in four lanes, with the same bits (`fast_clamp` keeps a −0 as `clamp`
    /// does; no lane is NaN: the scan's coordinates are finite).
    #[inline(always)]
    pub(crate) fn at4(self, v: f64x4) -> f64x4 {
        ((v - f64x4::splat(self.from)) * f64x4::splat(self.scale))
            .fast_clamp(f64x4::ZERO, f64x4::ONE)
    }
}

/// Grid geometry: nodes `side × side`, node (i, j) at (origin + i·cell, origin + j·cell).
#[derive(Debug, Clone, Copy)]
struct Grid {
    side: usize,
    origin: f64,
    inv_cell: f64,
}

impl Grid {
    /// The grid of `cell` over ±`extent`, one node beyond on each side.
    fn new(extent: f64, cell: f64) -> Self {
        let side = (2.0 * extent / cell).ceil() as usize + 2;
        Self {
            side,
            origin: -(side as f64 - 1.0) * cell / 2.0,
            inv_cell: 1.0 / cell,
        }
    }

    /// Place of (x, y) in node units, if its four nodes are inside.
    #[inline(always)]
    fn place(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let (u, v) = (
            (x - self.origin) * self.inv_cell,
            (y - self.origin) * self.inv_cell,
        );
        let hi = (self.side - 1) as f64;
        (u >= 0.0 && v >= 0.0 && u < hi && v < hi).then_some((u, v))
    }
}

/// Raises the uncertain points of `out` (one probability per point, the scan's points in
/// the ground-aligned frame `x`, `y`, `z`) that lie at the height of confident ground next
/// to them. `extent` is the half-width of the grid (m): points beyond it are left alone.
/// Returns how many points it lifted from below `threshold` to at or above it.
pub(crate) fn raise_continuous_ground(
    cfg: &ContinuityConfig,
    extent: f64,
    (x, y, z): (&[f64], &[f64], &[f64]),
    elevation: &Elevation,
    out: &mut [f32],
    threshold: f32,
    scratch: &mut ContinuityScratch,
) -> usize {
    if !cfg.enabled || out.is_empty() {
        return 0;
    }
    let grid = Grid::new(extent, cfg.cell);
    let side = grid.side;
    // The scan in as many parts as there are worker threads, each splatted into its own
    // grid (integer sums: the parts add up to the same nodes in any split).
    let parts = rayon::current_num_threads().clamp(1, 8);
    if scratch.nodes.len() != side * side || scratch.sums.len() != parts {
        scratch.sums = vec![vec![[0, 0]; side * side]; parts];
        scratch.candidates = vec![Vec::new(); parts];
        scratch.nodes = vec![[0.0, 0.0]; side * side];
        scratch.bounds = vec![[0.0, 0.0]; side * side];
        scratch.row_bounds = vec![[0.0, 0.0]; side * side];
    }
    let rule = RaiseRule::new(cfg);
    let part = out.len().div_ceil(parts);
    scratch
        .sums
        .par_iter_mut()
        .zip(scratch.candidates.par_iter_mut())
        .enumerate()
        .for_each(|(k, (sums, candidates))| {
            let r = (k * part).min(out.len())..((k + 1) * part).min(out.len());
            candidates.clear();
            splat_confident(
                cfg,
                &rule,
                &grid,
                (sums, candidates),
                r.start,
                (&x[r.clone()], &y[r.clone()], &z[r.clone()]),
                &out[r],
            );
        });
    // Each node's height and trust, once; the sums are zeroed for the next scan.
    let support = Ramp::new([0.0, cfg.support]);
    let (sums, nodes) = (&mut scratch.sums, &mut scratch.nodes);
    for (i, node) in nodes.iter_mut().enumerate() {
        let [mut w, mut wh] = [0i64, 0i64];
        for grid in sums.iter_mut() {
            let [a, b] = std::mem::take(&mut grid[i]);
            w = w.wrapping_add(a);
            wh = wh.wrapping_add(b);
        }
        *node = if w > 0 {
            [
                (wh as f64 / w as f64 / HEIGHT_ONE) as f32,
                support.at(w as f64 / WEIGHT_ONE) as f32,
            ]
        } else {
            [0.0, 0.0]
        };
    }
    height_bounds(
        &grid,
        &scratch.nodes,
        rule.zero,
        rule.cutoff,
        &mut scratch.row_bounds,
        &mut scratch.bounds,
    );
    // Raise each uncertain point by its best node: nearness × trust × height match. Each
    // point reads the nodes and writes only its own probability; one lookup of its cell's
    // bounds passes over most of them.
    let (nodes, bounds): (&[[f32; 2]], &[[f32; 2]]) = (&scratch.nodes, &scratch.bounds);
    out.par_chunks_mut(part)
        .zip(scratch.candidates.par_iter())
        .enumerate()
        .map(|(k, (out, candidates))| {
            let first = k * part;
            let mut lifted = 0;
            for &[i, cell, h] in candidates {
                let [lo, up] = bounds[cell as usize];
                let h = f32::from_bits(h);
                if !(h > lo && h < up) {
                    continue;
                }
                let i = i as usize;
                let p = &mut out[i - first];
                let raised = rule.raised(&grid, nodes, (x[i], y[i], z[i]), *p, || {
                    elevation.likelihood(i, z[i])
                });
                if let Some(r) = raised {
                    lifted += usize::from(*p < threshold && r >= threshold);
                    *p = r;
                }
            }
            lifted
        })
        .sum()
}

/// Each cell's bounds (see `ContinuityScratch::bounds`): the trusted node heights in the
/// box of nodes a point in the cell can reach (`zero` node units), widened by `cutoff`.
/// Separable: the window's extremes along one axis into `rows`, then along the other.
fn height_bounds(
    grid: &Grid,
    nodes: &[[f32; 2]],
    zero: f64,
    cutoff: f32,
    rows: &mut [[f32; 2]],
    bounds: &mut [[f32; 2]],
) {
    let side = grid.side;
    // A point at u in [i, i + 1) reaches nodes n with |n − u| < zero: i + 1 − r ..= i + r.
    let r = zero.ceil() as usize;
    let window = |i: usize| (i + 1).saturating_sub(r)..(i + r + 1).min(side);
    const EMPTY: [f32; 2] = [f32::INFINITY, f32::NEG_INFINITY];
    let widen = |acc: &mut [f32; 2], [lo, hi]: [f32; 2]| {
        *acc = [acc[0].min(lo), acc[1].max(hi)];
    };
    for (row, node_row) in rows.chunks_exact_mut(side).zip(nodes.chunks_exact(side)) {
        for (j, b) in row.iter_mut().enumerate() {
            *b = EMPTY;
            for &[h, t] in &node_row[window(j)] {
                if t > 0.0 {
                    widen(b, [h - cutoff, h + cutoff]);
                }
            }
        }
    }
    for (i, out) in bounds.chunks_exact_mut(side).enumerate() {
        out.fill(EMPTY);
        for n in window(i) {
            for (b, &o) in out.iter_mut().zip(&rows[n * side..(n + 1) * side]) {
                widen(b, o);
            }
        }
    }
}

/// Adds every confident point's height to its four nodes, weighted by its confidence and
/// its bilinear share. Blocks of points are prepared in straight loops that vectorise
/// (node, four weights, height), then added; consecutive points mostly share their nodes,
/// so their sums run in registers until the nodes change. Integer sums: the order
/// changes nothing.
fn splat_confident(
    cfg: &ContinuityConfig,
    rule: &RaiseRule,
    grid: &Grid,
    (sums, candidates): (&mut [[i64; 2]], &mut Vec<[u32; 3]>),
    first: usize,
    (x, y, z): (&[f64], &[f64], &[f64]),
    out: &[f32],
) {
    const BLOCK: usize = 64;
    let side = grid.side;
    let hi = (side - 1) as f64;
    let [c0, c1] = cfg.confident;
    let inv_confident = 1.0 / (c1 - c0);
    let mut base = u32::MAX;
    let mut run = [[0i64; 2]; 4];
    let flush = |sums: &mut [[i64; 2]], base: u32, run: &[[i64; 2]; 4]| {
        if base == u32::MAX {
            return;
        }
        let b = base as usize;
        for (k, add) in [b, b + 1, b + side, b + side + 1].into_iter().zip(run) {
            sums[k][0] = sums[k][0].wrapping_add(add[0]);
            sums[k][1] = sums[k][1].wrapping_add(add[1]);
        }
    };
    let (mut nodes, mut weights, mut heights) =
        ([u32::MAX; BLOCK], [[0i32; 4]; BLOCK], [0i32; BLOCK]);
    let (mut cells, mut uncertain) = ([0u32; BLOCK], [false; BLOCK]);
    for (b, (((bx, by), bz), bp)) in x
        .chunks(BLOCK)
        .zip(y.chunks(BLOCK))
        .zip(z.chunks(BLOCK))
        .zip(out.chunks(BLOCK))
        .enumerate()
    {
        for k in 0..bp.len() {
            let p = bp[k];
            let c = ((f64::from(p) - c0) * inv_confident).clamp(0.0, 1.0);
            let u = (bx[k] - grid.origin) * grid.inv_cell;
            let v = (by[k] - grid.origin) * grid.inv_cell;
            // NaN probabilities and places fail every comparison: not splatted, not raised.
            let inside = (u >= 0.0) & (v >= 0.0) & (u < hi) & (v < hi);
            let (iu, iv) = (u.floor(), v.floor());
            let (fu, fv) = (u - iu, v - iv);
            // Outside the grid the index is garbage (wrapping, never a panic) and unused.
            // The point's cell, the square above and right of its node (the same index).
            let node = (round_i32(iu) as u32)
                .wrapping_mul(side as u32)
                .wrapping_add(round_i32(iv) as u32);
            cells[k] = node;
            nodes[k] = if inside & (c > 0.0) { node } else { u32::MAX };
            uncertain[k] = inside & rule.may_rise(p);
            let cw = c * WEIGHT_ONE;
            weights[k] = [
                round_i32(cw * (1.0 - fu) * (1.0 - fv)),
                round_i32(cw * (1.0 - fu) * fv),
                round_i32(cw * fu * (1.0 - fv)),
                round_i32(cw * fu * fv),
            ];
            heights[k] = round_i32(bz[k].clamp(-HEIGHT_CLAMP, HEIGHT_CLAMP) * HEIGHT_ONE);
        }
        for k in 0..bp.len() {
            if uncertain[k] {
                candidates.push([
                    (first + b * BLOCK + k) as u32,
                    cells[k],
                    (bz[k] as f32).to_bits(),
                ]);
            }
            if nodes[k] == u32::MAX {
                continue;
            }
            if nodes[k] != base {
                flush(sums, base, &run);
                base = nodes[k];
                run = [[0; 2]; 4];
            }
            let h = i64::from(heights[k]);
            for (acc, &w) in run.iter_mut().zip(&weights[k]) {
                let w = i64::from(w);
                acc[0] = acc[0].wrapping_add(w);
                acc[1] = acc[1].wrapping_add(w.wrapping_mul(h));
            }
        }
    }
    flush(sums, base, &run);
}

/// The raising rule with its constants worked out once.
struct RaiseRule {
    uncertain: [f64; 2],
    /// Rises from 0 to 1 across `uncertain`.
    gate: Ramp,
    probability: f64,
    /// Nearness in node units: 1 within `full`, 0 from `zero` on.
    full: f64,
    zero: f64,
    /// Height match: 1 within the tolerance, 0 from `cutoff` on; `band` is
    /// 1 / (cutoff − tolerance), worked out here rather than per point.
    band: f32,
    cutoff: f32,
}

impl RaiseRule {
    fn new(cfg: &ContinuityConfig) -> Self {
        Self {
            uncertain: cfg.uncertain,
            gate: Ramp::new(cfg.uncertain),
            probability: cfg.probability,
            full: cfg.reach / cfg.cell / 2.0,
            zero: cfg.reach / cfg.cell,
            band: 1.0 / (cfg.height_cutoff as f32 - cfg.height_tolerance as f32),
            cutoff: cfg.height_cutoff as f32,
        }
    }

    /// Whether a point of probability `p` may rise at all: most points are sure either
    /// way. Points at or above the raised probability cannot rise; NaN never does.
    #[inline(always)]
    fn may_rise(&self, p: f32) -> bool {
        let p = f64::from(p);
        p > self.uncertain[0] && p < self.probability
    }

    /// The probability a point of probability `p` is raised to, if it rises.
    #[inline]
    fn raised(
        &self,
        grid: &Grid,
        nodes: &[[f32; 2]],
        (x, y, z): (f64, f64, f64),
        p: f32,
        elevation: impl FnOnce() -> f64,
    ) -> Option<f32> {
        if !self.may_rise(p) {
            return None;
        }
        let p64 = f64::from(p);
        let gate = self.gate.at(p64);
        let (u, v) = grid.place(x, y)?;
        let side = grid.side as isize;
        let (zero, full) = (self.zero, self.full);
        let span = |c: f64| {
            (
                ((c - zero).ceil() as isize).max(0),
                ((c + zero).floor() as isize).min(side - 1),
            )
        };
        let ((u0, u1), (v0, v1)) = (span(u), span(v));
        // In f32 relative to the point (node units): every node is scored branch-free
        // (a skip on the running best mispredicted half the time, and a square root and
        // a division sat on each skipped path).
        let z = z as f32;
        let band = self.band;
        let (zero, fade) = (zero as f32, 1.0 / (zero - full) as f32);
        let (fu, fv) = ((u - u0 as f64) as f32, (v - v0 as f64) as f32);
        let mut best = 0.0f32;
        for (a, nu) in (u0..=u1).enumerate() {
            let du = fu - a as f32;
            let row = &nodes[(nu * side + v0) as usize..=(nu * side + v1) as usize];
            for (b, &[height, trust]) in row.iter().enumerate() {
                let dv = fv - b as f32;
                let fit = ((self.cutoff - (z - height).abs()) * band).clamp(0.0, 1.0);
                let near = ((zero - (du * du + dv * dv).sqrt()) * fade).clamp(0.0, 1.0);
                best = best.max(near * fit * trust);
            }
        }
        // The elevation likelihood (an exponential) only where it can still matter.
        let r = self.probability * f64::from(best) * gate;
        if r <= p64 {
            return None;
        }
        let r = (r * elevation()) as f32;
        (r > p).then_some(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat road at z = 0 (10 cm spacing, x 5–15 m, y −5–5 m) the mixtures call ground
    /// (0.8), with `extra` points appended: (x, y, z, probability).
    fn road(extra: &[(f64, f64, f64, f32)]) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f32>) {
        let (mut x, mut y, mut z, mut p) = (vec![], vec![], vec![], vec![]);
        for i in 0..100 {
            for j in 0..100 {
                // A road with a few millimetres of texture.
                x.push(5.0 + f64::from(i) * 0.1);
                y.push(-5.0 + f64::from(j) * 0.1);
                z.push(f64::from((i * 7 + j * 3) % 5) * 0.002);
                p.push(0.8);
            }
        }
        for &(a, b, c, q) in extra {
            x.push(a);
            y.push(b);
            z.push(c);
            p.push(q);
        }
        (x, y, z, p)
    }

    fn run(cfg: &ContinuityConfig, pts: &(Vec<f64>, Vec<f64>, Vec<f64>, Vec<f32>)) -> Vec<f32> {
        let mut out = pts.3.clone();
        // No model: every point's segment lets it rise as far as its neighbours allow
        // (the elevation gate is the segmenter's, tested there).
        let (bins, model) = (vec![0; out.len()], FrameModel::default());
        let elevation = Elevation {
            bins: &bins,
            model: &model,
            sigmoid: Sigmoid {
                alpha: 4.0,
                beta: 0.8,
            },
        };
        raise_continuous_ground(
            cfg,
            80.0,
            (&pts.0, &pts.1, &pts.2),
            &elevation,
            &mut out,
            0.5,
            &mut ContinuityScratch::default(),
        );
        out
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(24))]

        /// Screening (the uncertain points listed while splatting, a cell's height bounds)
        /// only passes over points that could not rise: every point gets what scoring it
        /// against the nodes gives.
        #[test]
        fn screening_passes_over_only_points_that_cannot_rise(
            seed in 0u64..1_000_000,
            cell in 0.4f64..2.0,
            reach_cells in 1.0f64..3.5,
        ) {
            use rand::{Rng, SeedableRng};
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            let cfg = ContinuityConfig { cell, reach: reach_cells * cell, ..Default::default() };
            // Rolling ground, boxes on it and points beyond the grid, with every probability.
            let n = 6_000;
            let (mut x, mut y, mut z, mut p) = (vec![], vec![], vec![], vec![]);
            for _ in 0..n {
                let (a, b): (f64, f64) = (rng.random_range(-25.0..25.0), rng.random_range(-25.0..25.0));
                let ground = 0.4 * (a / 3.0).sin() + 0.3 * (b / 5.0).cos();
                let up = if rng.random_bool(0.3) { rng.random_range(0.0..0.3) } else { 0.0 };
                x.push(a);
                y.push(b);
                z.push(ground + up + rng.random_range(-0.02..0.02));
                p.push(rng.random_range(0.0f32..1.0));
            }
            let extent = 20.0;
            let (bins, model) = (vec![0; n], FrameModel::default());
            let elevation = Elevation { bins: &bins, model: &model, sigmoid: Sigmoid { alpha: 4.0, beta: 0.3 } };
            let mut out = p.clone();
            let mut scratch = ContinuityScratch::default();
            raise_continuous_ground(&cfg, extent, (&x, &y, &z), &elevation, &mut out, 0.5, &mut scratch);
            let (grid, rule) = (Grid::new(extent, cell), RaiseRule::new(&cfg));
            let mut risen = 0;
            for i in 0..n {
                let every = rule
                    .raised(&grid, &scratch.nodes, (x[i], y[i], z[i]), p[i], || elevation.likelihood(i, z[i]))
                    .unwrap_or(p[i]);
                proptest::prop_assert_eq!(out[i].to_bits(), every.to_bits(), "point {}", i);
                risen += usize::from(every > p[i]);
            }
            // The scene is one where points do rise (else the comparison proves little).
            proptest::prop_assert!(risen > 50, "{} risen", risen);
        }
    }

    #[test]
    fn an_uncertain_point_on_the_road_rises_and_an_object_does_not() {
        let cfg = ContinuityConfig::default();
        let extra = [
            (15.5, 0.0, 0.01, 0.3), // beside the road, at its height: ground
            (15.5, 1.0, 0.3, 0.3),  // 30 cm up (a kerb top, a bumper): stays
            (15.5, 2.0, 0.05, 0.3), // between tolerance and cutoff: partly
            (15.5, 3.0, 0.0, 0.01), // called surely non-ground: stays
            (20.0, 0.0, 0.0, 0.3),  // 5 m from any confident ground: stays
        ];
        let pts = road(&extra);
        let out = run(&cfg, &pts);
        let tail = &out[10_000..];
        assert!(tail[0] >= 0.5, "{tail:?}");
        assert_eq!(tail[1], 0.3);
        assert!(tail[2] > 0.3 && tail[2] < 0.5, "{tail:?}");
        assert_eq!(tail[3], 0.01);
        assert_eq!(tail[4], 0.3);
        // Confident ground is never lowered, nor raised past `probability`.
        assert!(out[..10_000].iter().all(|&p| p == 0.8));
        // Off: untouched.
        let off = ContinuityConfig {
            enabled: false,
            ..cfg
        };
        assert_eq!(run(&off, &pts), pts.3);
    }

    #[test]
    fn a_flat_roof_the_mixtures_half_call_ground_does_not_spread() {
        // A car roof 1.5 m up, 2 × 2 m, half of it (wrongly) confident ground, half
        // uncertain; and one uncertain point on the road.
        let mut extra = vec![];
        for i in 0..20 {
            for j in 0..20 {
                let p = if j < 10 { 0.8 } else { 0.3 };
                extra.push((20.0 + f64::from(i) * 0.1, f64::from(j) * 0.1, 1.5, p));
            }
        }
        extra.push((15.5, 0.0, 0.01, 0.3));
        let pts = road(&extra);
        let n = pts.3.len();
        let sigmoid = Sigmoid {
            alpha: 4.0,
            beta: 0.8,
        };
        let raise = |model: &FrameModel| {
            let mut out = pts.3.clone();
            let bins = vec![0; n];
            raise_continuous_ground(
                &ContinuityConfig::default(),
                80.0,
                (&pts.0, &pts.1, &pts.2),
                &Elevation {
                    bins: &bins,
                    model,
                    sigmoid,
                },
                &mut out,
                0.5,
                &mut ContinuityScratch::default(),
            );
            out
        };
        let roof_rose = |out: &[f32]| {
            (0..400)
                .filter(|&k| pts.3[10_000 + k] < 0.5 && out[10_000 + k] >= 0.5)
                .count()
        };
        // The segment's lowest inlier is the road: the roof stays, the road point rises.
        let judged = raise(&FrameModel::with_lowest_inliers(vec![0.0]));
        assert_eq!(roof_rose(&judged), 0);
        assert!(judged[n - 1] >= 0.5);
        // Without a model to judge by, the roof would spread.
        let unjudged = raise(&FrameModel::with_lowest_inliers(vec![f32::NAN]));
        assert!(roof_rose(&unjudged) > 100, "{}", roof_rose(&unjudged));
    }

    #[test]
    fn a_permuted_scan_gives_the_same_probabilities_permuted() {
        let cfg = ContinuityConfig::default();
        let extra: Vec<_> = (0..200)
            .map(|k| {
                let k = f64::from(k);
                (
                    4.0 + k * 0.06,
                    -6.0 + k * 0.05,
                    (k * 0.37).sin() * 0.08,
                    0.35,
                )
            })
            .collect();
        let pts = road(&extra);
        let out = run(&cfg, &pts);
        // Reverse and interleave: every float sum would round differently.
        let n = pts.3.len();
        let order: Vec<usize> = (0..n).map(|i| (i * 7919) % n).collect();
        assert_eq!(
            order
                .iter()
                .collect::<std::collections::BTreeSet<_>>()
                .len(),
            n
        );
        let permuted = (
            order.iter().map(|&i| pts.0[i]).collect(),
            order.iter().map(|&i| pts.1[i]).collect(),
            order.iter().map(|&i| pts.2[i]).collect(),
            order.iter().map(|&i| pts.3[i]).collect(),
        );
        let out_p = run(&cfg, &permuted);
        for (k, &i) in order.iter().enumerate() {
            assert_eq!(out_p[k].to_bits(), out[i].to_bits(), "point {i}");
        }
        assert!(out[10_000..].iter().any(|&p| p > 0.5), "some rose");
    }

    #[test]
    fn the_raised_probability_moves_continuously_with_the_coordinates() {
        // A point slid in 1 mm steps across the whole range of every ramp: towards and
        // away from the road (nearness), up through the height band, and the road's
        // points themselves shifted across node boundaries. No step moves it by more
        // than a few per cent of what a 1 mm move of a ramp allows.
        let cfg = ContinuityConfig::default();
        let mut last: Option<f32> = None;
        for step in 0..2000 {
            let d = f64::from(step) * 0.001;
            let pts = road(&[(15.0 + d, 0.3, d * 0.05, 0.3)]);
            let p = run(&cfg, &pts)[10_000];
            if let Some(q) = last {
                assert!((p - q).abs() < 0.03, "step {step}: {q} → {p}");
            }
            last = Some(p);
        }
        // The whole road moved by 0–1 m in 1 mm steps: the point beside it follows.
        let mut last: Option<f32> = None;
        for step in 0..1000 {
            let d = f64::from(step) * 0.001;
            let mut pts = road(&[(15.4, 0.2, 0.0, 0.3)]);
            for v in pts.0.iter_mut().chain(pts.1.iter_mut()) {
                *v += d;
            }
            pts.0[10_000] = 15.4 + d;
            pts.1[10_000] = 0.2 + d;
            let p = run(&cfg, &pts)[10_000];
            if let Some(q) = last {
                assert!((p - q).abs() < 0.01, "shift {d}: {q} → {p}");
            }
            last = Some(p);
        }
    }
}
