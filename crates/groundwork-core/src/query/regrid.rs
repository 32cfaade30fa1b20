//! The past frames' components regridded into the query scan
//! ([`PastQuery::Regridded`](crate::config::PastQuery::Regridded)).
//!
//! Once per query, each past component's mean and horizontal σ are moved into the query
//! scan's ground-aligned frame, and the component is listed in every query-scan segment its
//! footprint reaches: the segments of its mean and of the mean ± `spread` σ along x, y and
//! the diagonals. A point is then normalised against its own segment's components and that
//! segment's past list, one run per anchor (past frames that share one, see
//! `crate::history`), each component evaluated in its anchor's frame on the point moved
//! there: no binning per point and past frame, one move per anchor. Each run also holds its
//! components sixteen at a time as lanes ([`BoundBlock`]): one bound per block and vector
//! of points lists the components that can matter to the vector. The per-frame query (the paper's) bins every point in every past frame;
//! a vector of neighbours straddles a past cell's edge in 4 of 10 frames there, and each
//! side costs a full vector's evaluation.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::{EMPTY, LANES, Move, NEAR, QComp, QueryFrame, Vf, answering_segment};
use crate::config::BeyondRangePolicy;
use crate::gmm::{Sym3, quad_form};
use crate::zones::LaneBinner;

/// Footprint samples, in σ along x and y: the mean, the four axis points and the four
/// corners.
const SAMPLES: [(f64, f64); 9] = [
    (0.0, 0.0),
    (1.0, 0.0),
    (-1.0, 0.0),
    (0.0, 1.0),
    (0.0, -1.0),
    (1.0, 1.0),
    (1.0, -1.0),
    (-1.0, 1.0),
    (-1.0, -1.0),
];

/// The past frames' components per query-scan segment. A component is evaluated in its
/// anchor's frame (its own frame if it has none), on a vector of points moved there: past
/// frames that share an anchor are one run, and one move.
#[derive(Debug, Default)]
pub(super) struct RegriddedTable {
    /// Query scan → anchor frame, per anchor.
    pub(super) moves: Vec<Move>,
    /// Runs of segment s are `seg_start[s]..seg_start[s+1]`.
    seg_start: Vec<u32>,
    runs: Vec<PastRun>,
    comps: Vec<QComp>,
    /// Each run's components sixteen at a time, as lanes: `blocks[run.block..]`.
    blocks: Vec<BoundBlock>,
}

/// Components of the past frames of one anchor for one segment: `comps[start..end]`, and
/// the largest log-density they reach.
#[derive(Debug, Clone, Copy)]
pub(super) struct PastRun {
    /// Index of the anchor's move.
    pub(super) anchor: u32,
    start: u32,
    end: u32,
    /// First of its `(end − start).div_ceil(16)` bound blocks.
    block: u32,
    pub(super) peak: f32,
}

impl RegriddedTable {
    /// The runs of past components that answer for segment `s`.
    #[inline]
    pub(super) fn runs(&self, s: u32) -> &[PastRun] {
        let s = s as usize;
        match (self.seg_start.get(s), self.seg_start.get(s + 1)) {
            (Some(&a), Some(&b)) => &self.runs[a as usize..b as usize],
            _ => &[],
        }
    }

    /// A run's components.
    #[inline]
    pub(super) fn comps(&self, run: &PastRun) -> &[QComp] {
        &self.comps[run.start as usize..run.end as usize]
    }

    /// Components in the longest run of segment `s`.
    pub(super) fn longest_run(&self, s: u32) -> usize {
        self.runs(s)
            .iter()
            .map(|r| (r.end - r.start) as usize)
            .max()
            .unwrap_or(0)
    }

    /// A run's components as bound blocks: block k holds components 16k.. of the run.
    #[inline]
    pub(super) fn blocks(&self, run: &PastRun) -> &[BoundBlock] {
        let n = (run.end - run.start).div_ceil(LANES as u32);
        &self.blocks[run.block as usize..(run.block + n) as usize]
    }

    /// The table for the past frames (each with its query → past transform, and its
    /// anchor): per segment, the components whose footprint reaches it, in the order of the
    /// frames and of each frame's components. Frames that share an anchor must be
    /// consecutive in `past`.
    pub(super) fn new(
        binner: &LaneBinner,
        past: &[QueryFrame<'_>],
        policy: BeyondRangePolicy,
        spread: f64,
    ) -> Self {
        let keyed: Vec<Vec<(u32, u32)>> = past
            .par_iter()
            .map(|f| reached_segments(binner, f, policy, spread))
            .collect();
        // Counting sort by segment, stable: within a segment the frames' order, so the table
        // (and the sums' rounding) does not depend on the threads, and the components of
        // the (consecutive) frames of one anchor are one run.
        let segments = binner.segment_count();
        let mut count = vec![0u32; segments + 1];
        for &(seg, _) in keyed.iter().flatten() {
            count[seg as usize + 1] += 1;
        }
        for s in 0..segments {
            count[s + 1] += count[s];
        }
        // Per past frame, where its components are evaluated: consecutive frames with one
        // anchor share a move.
        let mut moves = Vec::new();
        let mut last = None;
        let mut sources = Vec::with_capacity(past.len());
        for f in past {
            let (table, anchor, to) = match f.anchored {
                Some(a) => (a.table, Some(a.anchor), Some(a.transform)),
                None => (f.model.query_table(), None, f.transform),
            };
            if anchor.is_none() || anchor != last {
                moves.push(to.map_or(Move::IDENTITY, Move::new));
            }
            last = anchor;
            sources.push((table, moves.len() as u32 - 1));
        }
        let mut next = count.clone();
        let mut comps = vec![QComp::default(); count[segments] as usize];
        let mut anchor_of = vec![0u32; comps.len()];
        for (&(table, anchor), keys) in sources.iter().zip(&keyed) {
            for &(seg, i) in keys {
                let at = &mut next[seg as usize];
                comps[*at as usize] = table.comps[i as usize];
                anchor_of[*at as usize] = anchor;
                *at += 1;
            }
        }
        let mut seg_start = Vec::with_capacity(segments + 1);
        let mut runs = Vec::new();
        let mut blocks = Vec::with_capacity(comps.len() / 4);
        for w in count.windows(2) {
            seg_start.push(runs.len() as u32);
            let (mut a, b) = (w[0] as usize, w[1] as usize);
            while a < b {
                let anchor = anchor_of[a];
                let end = a + anchor_of[a..b].iter().take_while(|&&f| f == anchor).count();
                let peak = comps[a..end].iter().map(|q| q.c).fold(EMPTY, f32::max);
                runs.push(PastRun {
                    anchor,
                    start: a as u32,
                    end: end as u32,
                    block: blocks.len() as u32,
                    peak,
                });
                blocks.extend(comps[a..end].chunks(LANES).map(BoundBlock::of));
                a = end;
            }
        }
        seg_start.push(runs.len() as u32);
        Self {
            moves,
            seg_start,
            runs,
            comps,
            blocks,
        }
    }
}

/// Up to sixteen components' U (and |U|), b and c (as in [`QComp`]) as lanes, to bound
/// their log-densities over a box of points at once. Lanes past the last component have
/// c = −∞: they reach nothing.
#[derive(Debug, Clone, Copy)]
pub(super) struct BoundBlock {
    pub(super) u: [Vf; 6],
    pub(super) abs_u: [Vf; 6],
    pub(super) b: [Vf; 3],
    pub(super) c: Vf,
}

/// Writes to `live` the indices (within the run) of the components of `blocks` whose
/// log-density may reach `floor` somewhere in the box `lo..=hi`, in order; returns how
/// many. `live` must hold 16 more than the run's components.
#[inline(always)]
pub(super) fn list_reaching<const AVX512: bool>(
    blocks: &[BoundBlock],
    lo: [f32; 3],
    hi: [f32; 3],
    floor: f32,
    live: &mut [u32],
) -> usize {
    #[cfg(target_arch = "x86_64")]
    if AVX512 {
        #[allow(unsafe_code)]
        // SAFETY: `AVX512` is set only inside code compiled with AVX-512F and run after
        // `avx512::available` (as for `LaneSums::add_fixed`).
        return unsafe { super::avx512::list_reaching(blocks, lo, hi, floor, live) };
    }
    let mut n = 0;
    for (k, block) in blocks.iter().enumerate() {
        let reach = block.reaching(lo, hi, floor);
        // Branch-free: every lane's index is written, and kept only if it reaches (then the
        // next is written after it). `kept ≤ i < 16`: the mask only spares a bounds check.
        let out = &mut live[n..n + LANES];
        let mut kept = 0;
        for i in 0..LANES {
            out[kept & (LANES - 1)] = (k * LANES + i) as u32;
            kept += (reach >> i) as usize & 1;
        }
        n += kept;
    }
    n
}

impl BoundBlock {
    pub(super) fn of(comps: &[QComp]) -> Self {
        let mut u = [[0.0; LANES]; 6];
        let mut abs_u = [[0.0; LANES]; 6];
        let mut b = [[0.0; LANES]; 3];
        let mut c = [f32::NEG_INFINITY; LANES];
        for (i, q) in comps.iter().take(LANES).enumerate() {
            for (k, &v) in q.u.iter().enumerate() {
                u[k][i] = v;
                abs_u[k][i] = v.abs();
            }
            for (k, &v) in q.b.iter().enumerate() {
                b[k][i] = v;
            }
            c[i] = q.c;
        }
        Self {
            u: u.map(Vf::new),
            abs_u: abs_u.map(Vf::new),
            b: b.map(Vf::new),
            c: Vf::new(c),
        }
    }

    /// Lanes (bits) whose component's log-density may reach `floor` somewhere in the box
    /// `lo..=hi`. Over the box each row of U·x − b lies within its value at the centre ± the
    /// row's |U| times the half extents; the nearest value of each interval to 0 bounds
    /// |U·x − b|² from below, so c minus it bounds the log-density from above.
    #[inline(always)]
    pub(super) fn reaching(&self, lo: [f32; 3], hi: [f32; 3], floor: f32) -> u32 {
        let s = Vf::splat;
        let [cx, cy, cz] = std::array::from_fn(|k| s(0.5 * (lo[k] + hi[k])));
        let [hx, hy, hz] = std::array::from_fn(|k| s(0.5 * (hi[k] - lo[k])));
        let [u0, u1, u2, u3, u4, u5] = self.u;
        let [a0, a1, a2, a3, a4, a5] = self.abs_u;
        let [b0, b1, b2] = self.b;
        let m1 = u0.mul_add(cx, u1.mul_add(cy, u2.mul_sub(cz, b0)));
        let r1 = a0.mul_add(hx, a1.mul_add(hy, a2 * hz));
        let m2 = u3.mul_add(cy, u4.mul_sub(cz, b1));
        let r2 = a3.mul_add(hy, a4 * hz);
        let m3 = u5.mul_sub(cz, b2);
        let r3 = a5 * hz;
        let near = |m: Vf, r: Vf| (m.abs() - r).fast_max(Vf::ZERO);
        let (d1, d2, d3) = (near(m1, r1), near(m2, r2), near(m3, r3));
        let top = d1.mul_neg_add(d1, d2.mul_neg_add(d2, d3.mul_neg_add(d3, self.c)));
        top.simd_ge(s(floor)).to_bitmask()
    }
}

/// Every (query-scan segment, component index) pair of one past frame whose component's
/// footprint, moved into the query scan, reaches that segment (a component reaching none,
/// e.g. near the sensor, is left out).
fn reached_segments(
    binner: &LaneBinner,
    frame: &QueryFrame<'_>,
    policy: BeyondRangePolicy,
    spread: f64,
) -> Vec<(u32, u32)> {
    let Some(t) = frame.transform else {
        return Vec::new();
    };
    // Query → past is p' = R·p + t: a past mean μ is Rᵀ(μ − t) here, a covariance RᵀΣR.
    let r = t.rotation.to_rotation_matrix().into_inner();
    let shift = t.translation.vector;
    let samples = if spread > 0.0 {
        &SAMPLES[..]
    } else {
        &SAMPLES[..1]
    };
    let components = frame.model.components();
    let mut out = Vec::with_capacity(components.len() * 2);
    // Sixteen components at a time: their footprint samples are binned as vectors.
    for (b, block) in components.chunks(LANES).enumerate() {
        let mut xs = [[0.0f32; LANES]; SAMPLES.len()];
        let mut ys = [[0.0f32; LANES]; SAMPLES.len()];
        for (i, g) in block.iter().enumerate() {
            let mean = r.transpose() * (Vector3::from(g.gaussian.mean) - shift);
            let sigma = horizontal_sigma(&g.gaussian.covariance, &r);
            for (k, (dx, dy)) in samples.iter().enumerate() {
                xs[k][i] = (mean.x + dx * spread * sigma[0]) as f32;
                ys[k][i] = (mean.y + dy * spread * sigma[1]) as f32;
            }
        }
        // Only the samples in use are binned (spread 0: the mean alone).
        let keys: [[u32; LANES]; SAMPLES.len()] = std::array::from_fn(|k| {
            if k < samples.len() {
                binner.bin_block(xs[k], ys[k])
            } else {
                [NEAR; LANES]
            }
        });
        for i in 0..block.len() {
            let index = (b * LANES + i) as u32;
            let mut seen = [u32::MAX; SAMPLES.len()];
            let mut n = 0;
            for k in &keys[..samples.len()] {
                let Some(seg) = answering_segment(k[i], policy) else {
                    continue;
                };
                if !seen[..n].contains(&seg) {
                    seen[n] = seg;
                    n += 1;
                    out.push((seg, index));
                }
            }
        }
    }
    out
}

/// Standard deviations along the query scan's x and y of a past covariance Σ, turned by
/// the query → past rotation R: the diagonal of RᵀΣR, i.e. cᵀΣc for R's columns c.
fn horizontal_sigma(cov: &Sym3, r: &Matrix3<f64>) -> [f64; 2] {
    [0, 1].map(|k| {
        let c = r.column(k);
        quad_form(cov, c.x, c.y, c.z).max(0.0).sqrt()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::query::log_density;
    use proptest::prelude::*;

    /// A component: U upper triangular with a positive diagonal, anywhere within 60 m.
    fn comp() -> impl Strategy<Value = QComp> {
        (
            proptest::array::uniform6(-3.0f32..3.0),
            proptest::array::uniform3(0.05f32..4.0),
            proptest::array::uniform3(-60.0f32..60.0),
            -20.0f32..20.0,
        )
            .prop_map(|(mut u, diagonal, mean, c)| {
                (u[0], u[3], u[5]) = (diagonal[0], diagonal[1], diagonal[2]);
                // b = U·mean.
                let b = [
                    u[0] * mean[0] + u[1] * mean[1] + u[2] * mean[2],
                    u[3] * mean[1] + u[4] * mean[2],
                    u[5] * mean[2],
                ];
                QComp {
                    u,
                    b,
                    c,
                    ..QComp::default()
                }
            })
    }

    proptest! {
        /// No point of the box has a log-density above the bound: the component of every
        /// lane reaches a floor just below its log-density at a point of the box.
        #[test]
        fn the_bound_holds_at_every_point_of_the_box(
            comps in proptest::collection::vec(comp(), 1..=16),
            lo in proptest::array::uniform3(-50.0f32..50.0),
            size in proptest::array::uniform3(0.0f32..4.0),
            at in proptest::array::uniform3(0.0f32..=1.0),
        ) {
            let hi = std::array::from_fn(|k| lo[k] + size[k]);
            let p: [f32; 3] = std::array::from_fn(|k| lo[k] + at[k] * size[k]);
            let block = BoundBlock::of(&comps);
            for (i, q) in comps.iter().enumerate() {
                let l = log_density(q, Vf::splat(p[0]), Vf::splat(p[1]), Vf::splat(p[2]))
                    .to_array()[0];
                // Rounding: the bound is computed in f32 from other operands.
                let floor = l - 1e-3 * (1.0 + l.abs());
                prop_assert!(
                    block.reaching(lo, hi, floor) >> i & 1 == 1,
                    "component {i}: log-density {l} at {p:?} above the bound"
                );
            }
            // Lanes past the last component reach nothing.
            prop_assert_eq!(block.reaching(lo, hi, -1e30) >> comps.len(), 0);
        }
    }

    #[test]
    fn the_bound_drops_a_component_far_from_the_box_and_keeps_one_inside() {
        // σ = 1 m in x and y, 0.1 m in z (U in √bits: the 1/σ rows scaled as the table does),
        // centred at (10, 0, 0).
        let k = (std::f32::consts::LOG2_E / 2.0).sqrt();
        let u = [k, 0.0, 0.0, k, 0.0, 10.0 * k];
        let q = QComp {
            u,
            b: [10.0 * k, 0.0, 0.0],
            c: 0.0,
            ..QComp::default()
        };
        let block = BoundBlock::of(&[q]);
        let near = block.reaching([9.5, -0.5, -0.05], [10.5, 0.5, 0.05], -1.0);
        // 10 σ away in x: 72 bits down.
        let far = block.reaching([19.5, -0.5, -0.05], [20.5, 0.5, 0.05], -43.0);
        // 1 m above: 10 σ in z.
        let above = block.reaching([9.5, -0.5, 0.95], [10.5, 0.5, 1.05], -43.0);
        assert_eq!((near, far, above), (1, 0, 0));
    }
}
