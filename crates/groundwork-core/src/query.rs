//! The query (paper §III-E) and its multi-frame form (§III-F).
//!
//! A point's responsibilities are normalised over every component of every segment it falls
//! into, across all queried frames; its ground probability is the product of the three
//! responsibility-weighted likelihoods. With one frame this is exactly the single-frame
//! query.
//!
//! Implementation: the points are grouped once by their segment in the query scan (counting
//! sort). Each run is then evaluated frame by frame, 16 points per SIMD vector: against its
//! own segment's components for the query scan's model; for a past frame the vector is
//! moved into that frame, binned there and evaluated against each distinct segment it falls
//! into. Per-point sums are merged across frames with a streaming log-sum-exp (max, Σw,
//! Σw·p_λ, Σw·p_θ, Σw·p_e).

use nalgebra::Isometry3;
use rayon::prelude::*;

use crate::config::BeyondRangePolicy;
use crate::simd::{LANES, Vf, Vi, load, store};
use wide::bytemuck::cast;

use crate::fastmath::exp_nonpositive_v;
use crate::model::FrameModel;
use crate::zones::{Bin, LaneBinner, ZoneModel};

/// Packed bin of a point in its own scan: segment index, `BEYOND` flag, or `NEAR`.
pub(crate) const NEAR: u32 = u32::MAX;
pub(crate) const BEYOND: u32 = 1 << 31;

#[inline]
pub(crate) fn pack(bin: Bin) -> u32 {
    match bin {
        Bin::Near => NEAR,
        Bin::Segment(s) => s,
        Bin::Beyond(s) => s | BEYOND,
    }
}

/// Segment whose model answers for a packed bin, or `None` if no model is asked.
#[inline]
fn segment_of(packed: u32, policy: BeyondRangePolicy) -> Option<u32> {
    if packed == NEAR {
        None
    } else if packed & BEYOND != 0 {
        match policy {
            BeyondRangePolicy::OuterRing => Some(packed & !BEYOND),
            BeyondRangePolicy::NonGround => None,
        }
    } else {
        Some(packed)
    }
}

/// Components further below the best one than this (in log-density) carry a weight under
/// e^-30 ≈ 1e-13 relative: they are skipped (and would only produce denormals).
const LOG_CUTOFF: f32 = 30.0;

/// Log-density floor for "no component seen yet": finite so that merges never compute
/// −∞ − (−∞).
const EMPTY: f32 = -1e30;

/// f32 copy of a frame's components, structure of arrays, for the vectorised query.
#[derive(Debug, Clone, Default)]
pub(crate) struct QueryTable {
    /// Components of segment s are `start[s]..start[s+1]`.
    start: Vec<u32>,
    comps: Vec<QComp>,
}

#[derive(Debug, Clone, Copy)]
struct QComp {
    m: [f32; 3],
    p: [f32; 6],
    c: f32,
    flat: f32,
    orient: f32,
    elev: f32,
}

impl QueryTable {
    pub(crate) fn new(model: &FrameModel) -> Self {
        let mut start = Vec::with_capacity(model.segment_count() + 1);
        let mut comps = Vec::with_capacity(model.components().len());
        start.push(0);
        for s in 0..model.segment_count() {
            for g in model.segment(s as u32) {
                comps.push(QComp {
                    m: g.eval.mean.map(|v| v as f32),
                    p: g.eval.precision.map(|v| v as f32),
                    c: g.eval.log_coef as f32,
                    flat: g.flatness as f32,
                    orient: g.orientation as f32,
                    elev: g.elevation as f32,
                });
            }
            start.push(comps.len() as u32);
        }
        Self { start, comps }
    }

    #[inline]
    fn segment(&self, s: u32) -> &[QComp] {
        let s = s as usize;
        match (self.start.get(s), self.start.get(s + 1)) {
            (Some(&a), Some(&b)) => &self.comps[a as usize..b as usize],
            _ => &[],
        }
    }
}

/// One model to query, with the transform from the query scan's ground-aligned frame into
/// that model's ground-aligned frame (`None` for the query scan's own model).
#[derive(Debug, Clone, Copy)]
pub struct QueryFrame<'a> {
    /// The fitted model.
    pub model: &'a FrameModel,
    /// Query frame → model frame.
    pub transform: Option<&'a Isometry3<f64>>,
}

/// Running sums per point over the components seen so far, structure of arrays so that
/// merges vectorise: the largest log-density `max`, and relative to it Σw, Σw·p_λ, Σw·p_θ
/// and Σw·p_e.
#[derive(Debug, Default)]
struct Sums {
    max: Vec<f32>,
    sum: Vec<f32>,
    flat: Vec<f32>,
    orient: Vec<f32>,
    elev: Vec<f32>,
}

impl Sums {
    /// `n` points with no component seen yet.
    fn reset(&mut self, n: usize) {
        for v in [
            &mut self.sum,
            &mut self.flat,
            &mut self.orient,
            &mut self.elev,
        ] {
            v.clear();
            v.resize(n, 0.0);
        }
        self.max.clear();
        self.max.resize(n, EMPTY);
    }

    fn slices(&mut self) -> SumsMut<'_> {
        SumsMut {
            max: &mut self.max,
            sum: &mut self.sum,
            flat: &mut self.flat,
            orient: &mut self.orient,
            elev: &mut self.elev,
        }
    }
}

/// Mutable view of a range of [`Sums`].
#[derive(Debug)]
struct SumsMut<'a> {
    max: &'a mut [f32],
    sum: &'a mut [f32],
    flat: &'a mut [f32],
    orient: &'a mut [f32],
    elev: &'a mut [f32],
}

impl<'a> SumsMut<'a> {
    fn len(&self) -> usize {
        self.max.len()
    }

    fn split_at(self, mid: usize) -> (SumsMut<'a>, SumsMut<'a>) {
        let (max, max2) = self.max.split_at_mut(mid);
        let (sum, sum2) = self.sum.split_at_mut(mid);
        let (flat, flat2) = self.flat.split_at_mut(mid);
        let (orient, orient2) = self.orient.split_at_mut(mid);
        let (elev, elev2) = self.elev.split_at_mut(mid);
        (
            SumsMut {
                max,
                sum,
                flat,
                orient,
                elev,
            },
            SumsMut {
                max: max2,
                sum: sum2,
                flat: flat2,
                orient: orient2,
                elev: elev2,
            },
        )
    }
}

/// Ground probability from a point's final sums: the product of the three
/// responsibility-weighted likelihoods.
#[inline]
fn probability(sum: f32, flat: f32, orient: f32, elev: f32) -> f32 {
    if sum > 0.0 {
        let inv = 1.0 / sum;
        ((flat * inv) * (orient * inv) * (elev * inv)).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Reusable buffers of the query.
#[derive(Debug, Default)]
pub(crate) struct QueryScratch {
    /// Queried points grouped by their segment in the query scan (f32, ground frame).
    x: Vec<f32>,
    y: Vec<f32>,
    z: Vec<f32>,
    /// Input index of each grouped point.
    order: Vec<u32>,
    /// Grouped points of segment s are at `start[s]..start[s+1]`.
    start: Vec<u32>,
    /// Running sums per grouped point.
    acc: Sums,
}

/// Ground probability of every point. `points` are in the query scan's ground-aligned frame
/// and `bins` their packed bins in it. Points near the sensor, beyond range under the
/// `NonGround` policy, or in no fitted segment of any frame get 0.
///
/// The points are grouped once by their segment in the query scan; every frame is then
/// evaluated in that order, so each pass reads and writes memory sequentially and a
/// segment's points (a compact patch of ground) stay in cache while its history is asked.
pub(crate) fn query(
    zones: &ZoneModel,
    frames: &[QueryFrame<'_>],
    points: &[[f64; 3]],
    bins: &[u32],
    policy: BeyondRangePolicy,
    s: &mut QueryScratch,
    out: &mut [f32],
) {
    group(s, points, bins, zones.segment_count(), policy);
    s.acc.reset(s.order.len());
    let runs = split_runs(&s.start, s.acc.slices());
    let (xs, ys, zs) = (&s.x, &s.y, &s.z);
    let binner = LaneBinner::new(zones);
    let moves: Vec<Option<Move>> = frames.iter().map(|f| f.transform.map(Move::new)).collect();
    runs.into_par_iter()
        .with_max_len(1)
        .for_each(|(seg, a, mut acc)| {
            let r = a..a + acc.len();
            let (x, y, z) = (&xs[r.clone()], &ys[r.clone()], &zs[r]);
            for (f, mv) in frames.iter().zip(&moves) {
                let table = f.model.query_table();
                match mv {
                    None => eval_own(table.segment(seg), x, y, z, &mut acc),
                    Some(mv) => eval_moved(&binner, table, mv, policy, x, y, z, &mut acc),
                }
            }
        });
    out.fill(0.0);
    let a = &s.acc;
    for (j, &i) in s.order.iter().enumerate() {
        out[i as usize] = probability(a.sum[j], a.flat[j], a.orient[j], a.elev[j]);
    }
}

/// Per-segment views of the running sums, with each segment's index and offset.
fn split_runs<'a>(start: &[u32], mut acc: SumsMut<'a>) -> Vec<(u32, usize, SumsMut<'a>)> {
    let mut runs = Vec::new();
    for (seg, w) in start.windows(2).enumerate() {
        let len = (w[1] - w[0]) as usize;
        let (head, tail) = acc.split_at(len);
        acc = tail;
        if len > 0 {
            runs.push((seg as u32, w[0] as usize, head));
        }
    }
    // Big runs first: rayon then balances the cores well.
    runs.sort_unstable_by_key(|r| std::cmp::Reverse(r.2.len()));
    runs
}

/// First pass of a counting sort: `start[s]..start[s+1]` will hold the points whose
/// `key(bin)` is segment s (points with key `None` are left out). Returns their number.
pub(crate) fn segment_offsets(
    bins: &[u32],
    segments: usize,
    key: impl Fn(u32) -> Option<u32>,
    start: &mut Vec<u32>,
) -> usize {
    start.clear();
    start.resize(segments + 1, 0);
    for &b in bins {
        if let Some(seg) = key(b) {
            start[seg as usize + 1] += 1;
        }
    }
    for i in 0..segments {
        start[i + 1] += start[i];
    }
    start[segments] as usize
}

/// Counting sort of the queried points by the segment that answers for them in the query
/// scan, into f32 structure-of-arrays.
fn group(
    s: &mut QueryScratch,
    points: &[[f64; 3]],
    bins: &[u32],
    segments: usize,
    policy: BeyondRangePolicy,
) {
    let total = segment_offsets(bins, segments, |b| segment_of(b, policy), &mut s.start);
    s.order.resize(total, 0);
    s.x.resize(total, 0.0);
    s.y.resize(total, 0.0);
    s.z.resize(total, 0.0);
    let mut cursor = s.start[..segments].to_vec();
    for (i, (&b, p)) in bins.iter().zip(points).enumerate() {
        if let Some(seg) = segment_of(b, policy) {
            let c = &mut cursor[seg as usize];
            let j = *c as usize;
            s.order[j] = i as u32;
            s.x[j] = p[0] as f32;
            s.y[j] = p[1] as f32;
            s.z[j] = p[2] as f32;
            *c += 1;
        }
    }
}

/// A rigid transform as f32 lanes: rows of [R | t].
#[derive(Debug, Clone, Copy)]
struct Move([[Vf; 4]; 3]);

impl Move {
    fn new(t: &Isometry3<f64>) -> Self {
        let m = t.to_homogeneous();
        Self(std::array::from_fn(|r| {
            std::array::from_fn(|c| Vf::splat(m[(r, c)] as f32))
        }))
    }

    #[inline(always)]
    fn apply(&self, x: Vf, y: Vf, z: Vf) -> [Vf; 3] {
        self.0
            .map(|[a, b, c, t]| a.mul_add(x, b.mul_add(y, c.mul_add(z, t))))
    }
}

/// Merges into `acc` a run's sums against its own segment's components.
fn eval_own(comps: &[QComp], xs: &[f32], ys: &[f32], zs: &[f32], acc: &mut SumsMut<'_>) {
    if comps.is_empty() {
        return;
    }
    for j in (0..acc.len()).step_by(LANES) {
        let w = LANES.min(acc.len() - j);
        let (x, y, z) = (load(xs, j, w), load(ys, j, w), load(zs, j, w));
        let merged = acc.load(j, w).merge(eval_lanes(comps, x, y, z));
        acc.store(merged, j, w);
    }
}

/// Merges into `acc` a run's sums against a past frame. A vector of points at a time is moved
/// into that frame, binned there, and evaluated against the components of each distinct
/// segment they fall into (points of one compact current segment are neighbours, so
/// nearly every vector falls into a single past segment).
#[allow(clippy::too_many_arguments)]
fn eval_moved(
    binner: &LaneBinner,
    table: &QueryTable,
    mv: &Move,
    policy: BeyondRangePolicy,
    xs: &[f32],
    ys: &[f32],
    zs: &[f32],
    acc: &mut SumsMut<'_>,
) {
    let lane_index = Vi::new(std::array::from_fn(|i| i as i32));
    let no_key = Vi::splat(-1);
    for j in (0..acc.len()).step_by(LANES) {
        let w = LANES.min(acc.len() - j);
        let [x, y, z] = mv.apply(load(xs, j, w), load(ys, j, w), load(zs, j, w));
        // Answering segment per lane, −1 for none (near, beyond under `NonGround`, padding).
        let packed = binner.bin(x, y);
        let beyond = packed.simd_lt(Vi::ZERO) & packed.simd_ne(no_key);
        let keys = match policy {
            BeyondRangePolicy::OuterRing => beyond.select(packed & Vi::splat(i32::MAX), packed),
            BeyondRangePolicy::NonGround => beyond.select(no_key, packed),
        };
        let keys = lane_index.simd_lt(Vi::splat(w as i32)).select(keys, no_key);
        let lanes = keys.to_array();
        let mut todo = !cast::<Vi, Vf>(keys.simd_eq(no_key)).to_bitmask() & ((1 << LANES) - 1);
        let mut part = LaneSums::EMPTY;
        while todo != 0 {
            let seg = lanes[todo.trailing_zeros() as usize];
            let hit = keys.simd_eq(Vi::splat(seg));
            todo &= !cast::<Vi, Vf>(hit).to_bitmask();
            let comps = table.segment(seg as u32);
            if comps.is_empty() {
                continue;
            }
            part = part.select(cast(hit), eval_lanes(comps, x, y, z));
        }
        let merged = acc.load(j, w).merge(part);
        acc.store(merged, j, w);
    }
}

/// Components evaluated together per chunk of points; more are merged block by block.
const BLOCK: usize = 8;

/// [`Sums`] of one vector of points.
#[derive(Debug, Clone, Copy)]
struct LaneSums {
    max: Vf,
    sum: Vf,
    flat: Vf,
    orient: Vf,
    elev: Vf,
}

impl LaneSums {
    const EMPTY: LaneSums = LaneSums {
        max: Vf::new([EMPTY; LANES]),
        sum: Vf::ZERO,
        flat: Vf::ZERO,
        orient: Vf::ZERO,
        elev: Vf::ZERO,
    };

    /// Lanes of `o` where `mask` is set, of `self` elsewhere.
    #[inline(always)]
    fn select(self, mask: Vf, o: LaneSums) -> LaneSums {
        LaneSums {
            max: mask.select(o.max, self.max),
            sum: mask.select(o.sum, self.sum),
            flat: mask.select(o.flat, self.flat),
            orient: mask.select(o.orient, self.orient),
            elev: mask.select(o.elev, self.elev),
        }
    }

    /// Streaming log-sum-exp merge; one exponential: the side with the larger maximum
    /// keeps scale 1.
    #[inline(always)]
    fn merge(self, o: LaneSums) -> LaneSums {
        let e = exp_nonpositive_v(-(self.max - o.max).abs());
        let one = Vf::ONE;
        let self_larger = self.max.simd_ge(o.max);
        let a = self_larger.select(one, e);
        let b = self_larger.select(e, one);
        LaneSums {
            max: self.max.max(o.max),
            sum: self.sum.mul_add(a, o.sum * b),
            flat: self.flat.mul_add(a, o.flat * b),
            orient: self.orient.mul_add(a, o.orient * b),
            elev: self.elev.mul_add(a, o.elev * b),
        }
    }
}

impl SumsMut<'_> {
    #[inline(always)]
    fn load(&self, j: usize, w: usize) -> LaneSums {
        LaneSums {
            max: load(self.max, j, w),
            sum: load(self.sum, j, w),
            flat: load(self.flat, j, w),
            orient: load(self.orient, j, w),
            elev: load(self.elev, j, w),
        }
    }

    #[inline(always)]
    fn store(&mut self, v: LaneSums, j: usize, w: usize) {
        store(v.max, self.max, j, w);
        store(v.sum, self.sum, j, w);
        store(v.flat, self.flat, j, w);
        store(v.orient, self.orient, j, w);
        store(v.elev, self.elev, j, w);
    }
}

/// Sums of one vector of points against up to [`BLOCK`] components.
#[inline(always)]
fn eval_block(comps: &[QComp], x: Vf, y: Vf, z: Vf) -> LaneSums {
    let mut l = [Vf::splat(EMPTY); BLOCK];
    let s = Vf::splat;
    for (lc, q) in l.iter_mut().zip(comps) {
        let (dx, dy, dz) = (x - s(q.m[0]), y - s(q.m[1]), z - s(q.m[2]));
        let p = q.p;
        // d = Δᵀ P Δ with P symmetric (upper triangle p).
        let d = (s(p[0]) * dx).mul_add(dx, (s(p[3]) * dy).mul_add(dy, s(p[5]) * dz * dz));
        let cross = (s(p[1]) * dx).mul_add(dy, (s(p[2]) * dx).mul_add(dz, s(p[4]) * dy * dz));
        *lc = s(q.c) - s(0.5) * cross.mul_add(s(2.0), d);
    }
    let k = comps.len().min(BLOCK);
    let mut max = l[0];
    for lc in &l[1..k] {
        max = max.fast_max(*lc);
    }
    let zero = Vf::ZERO;
    let mut r = LaneSums {
        max,
        sum: zero,
        flat: zero,
        orient: zero,
        elev: zero,
    };
    for (lc, q) in l[..k].iter().zip(comps) {
        let d = *lc - max;
        let live = d.simd_ge(s(-LOG_CUTOFF));
        // Points of one vector are neighbours: a component often matters to none of them.
        if live.none() {
            continue;
        }
        let w = live.select(exp_nonpositive_v(d), zero);
        r.sum += w;
        r.flat = w.mul_add(s(q.flat), r.flat);
        r.orient = w.mul_add(s(q.orient), r.orient);
        r.elev = w.mul_add(s(q.elev), r.elev);
    }
    r
}

/// Sums of a vector of points against a segment's components, [`BLOCK`] components at a time.
#[inline(always)]
fn eval_lanes(comps: &[QComp], x: Vf, y: Vf, z: Vf) -> LaneSums {
    let mut blocks = comps.chunks(BLOCK);
    let Some(first) = blocks.next() else {
        return LaneSums::EMPTY;
    };
    blocks.fold(eval_block(first, x, y, z), |acc, b| {
        acc.merge(eval_block(b, x, y, z))
    })
}
