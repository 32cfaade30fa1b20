//! The query (paper §III-E) and its multi-frame form (§III-F).
//!
//! A point's responsibilities are normalised over every component of every segment it falls
//! into, across all queried frames; its ground probability is the product of the three
//! responsibility-weighted likelihoods. With one frame this is exactly the single-frame
//! query.
//!
//! Implementation: per frame, the query points are grouped by the segment they fall into in
//! that frame (counting sort), each segment's run is evaluated against its components in
//! straight f32 loops that the compiler vectorises, and the per-point partial sums are
//! merged across frames with a streaming log-sum-exp (max, Σw, Σw·p_λ, Σw·p_θ, Σw·p_e).

use nalgebra::Isometry3;
use rayon::prelude::*;

use crate::config::BeyondRangePolicy;
use crate::fastmath::exp_nonpositive;
use crate::model::FrameModel;
use crate::zones::{Bin, ZoneModel};

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

/// Running log-sum-exp state of points over the components seen so far, structure of
/// arrays: for each point the best log-density `max` and Σw, Σw·p_λ, Σw·p_θ, Σw·p_e with
/// w = e^{l − max}.
#[derive(Debug, Default)]
struct Sums {
    max: Vec<f32>,
    sum: Vec<f32>,
    flat: Vec<f32>,
    orient: Vec<f32>,
    elev: Vec<f32>,
}

/// A mutable window of [`Sums`] (one run of points).
#[derive(Debug)]
struct SumsMut<'a> {
    max: &'a mut [f32],
    sum: &'a mut [f32],
    flat: &'a mut [f32],
    orient: &'a mut [f32],
    elev: &'a mut [f32],
}

impl Sums {
    fn reset(&mut self, n: usize) {
        self.max.clear();
        self.max.resize(n, EMPTY);
        for v in [
            &mut self.sum,
            &mut self.flat,
            &mut self.orient,
            &mut self.elev,
        ] {
            v.clear();
            v.resize(n, 0.0);
        }
    }

    /// Consecutive windows of the given lengths.
    fn split(&mut self, lens: impl Iterator<Item = usize>) -> Vec<SumsMut<'_>> {
        let (mut m, mut s, mut f, mut o, mut e) = (
            &mut self.max[..],
            &mut self.sum[..],
            &mut self.flat[..],
            &mut self.orient[..],
            &mut self.elev[..],
        );
        let mut out = Vec::new();
        for len in lens {
            let (m0, m1) = m.split_at_mut(len);
            let (s0, s1) = s.split_at_mut(len);
            let (f0, f1) = f.split_at_mut(len);
            let (o0, o1) = o.split_at_mut(len);
            let (e0, e1) = e.split_at_mut(len);
            (m, s, f, o, e) = (m1, s1, f1, o1, e1);
            out.push(SumsMut {
                max: m0,
                sum: s0,
                flat: f0,
                orient: o0,
                elev: e0,
            });
        }
        out
    }

    fn probability(&self, j: usize) -> f32 {
        let s = self.sum[j];
        if s > 0.0 {
            let inv = 1.0 / s;
            ((self.flat[j] * inv) * (self.orient[j] * inv) * (self.elev[j] * inv)).clamp(0.0, 1.0)
        } else {
            0.0
        }
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
    // Per-segment windows, big ones first so that rayon balances the cores well.
    let lens = s.start.windows(2).map(|w| (w[1] - w[0]) as usize);
    let starts = &s.start;
    let mut runs: Vec<(u32, usize, SumsMut<'_>)> = s
        .acc
        .split(lens)
        .into_iter()
        .enumerate()
        .map(|(seg, acc)| (seg as u32, starts[seg] as usize, acc))
        .filter(|r| !r.2.max.is_empty())
        .collect();
    runs.sort_unstable_by_key(|r| std::cmp::Reverse(r.2.max.len()));
    let (xs, ys, zs) = (&s.x, &s.y, &s.z);
    runs.into_par_iter().with_max_len(1).for_each_init(
        RunScratch::default,
        |rs, (seg, a, mut acc)| {
            let n = acc.max.len();
            let (x, y, z) = (&xs[a..a + n], &ys[a..a + n], &zs[a..a + n]);
            for f in frames {
                let table = f.model.query_table();
                match f.transform {
                    None => {
                        rs.rows.clear();
                        rs.rows
                            .extend(table.segment(seg).iter().map(|c| (*c, NEAR)));
                        rs.eval(x, y, z, None, &mut acc);
                    }
                    Some(t) => rs.eval_moved(zones, table, t, policy, x, y, z, &mut acc),
                }
            }
        },
    );
    out.fill(0.0);
    for (j, &i) in s.order.iter().enumerate() {
        out[i as usize] = s.acc.probability(j);
    }
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

/// Per-thread buffers for evaluating one run of points.
#[derive(Debug, Default)]
struct RunScratch {
    /// Components to evaluate, each with the segment whose points it answers for
    /// (`NEAR` = every point of the run).
    rows: Vec<(QComp, u32)>,
    l: Vec<f32>,
    part: Sums,
    // For past frames: the run moved into that frame and its bins there.
    mx: Vec<f32>,
    my: Vec<f32>,
    mz: Vec<f32>,
    bins: Vec<u32>,
}

impl RunScratch {
    /// Partial sums of a run against a past frame. The points are moved into that frame
    /// and binned there (vectorised); a run of one compact segment spreads over only a few
    /// past segments, so every point is evaluated against the components of all of them,
    /// masked to its own: more arithmetic than a regrouping, but in straight vectorised
    /// loops, in place, without gathers and scatters.
    #[allow(clippy::too_many_arguments)]
    fn eval_moved(
        &mut self,
        zones: &ZoneModel,
        table: &QueryTable,
        t: &Isometry3<f64>,
        policy: BeyondRangePolicy,
        xs: &[f32],
        ys: &[f32],
        zs: &[f32],
        acc: &mut SumsMut<'_>,
    ) {
        let n = xs.len();
        let m = t.to_homogeneous().cast::<f32>();
        for v in [&mut self.mx, &mut self.my, &mut self.mz] {
            v.resize(n, 0.0);
        }
        for ((((&x, &y), &z), (ox, oy)), oz) in xs
            .iter()
            .zip(ys)
            .zip(zs)
            .zip(self.mx.iter_mut().zip(self.my.iter_mut()))
            .zip(self.mz.iter_mut())
        {
            *ox = m[(0, 0)] * x + m[(0, 1)] * y + m[(0, 2)] * z + m[(0, 3)];
            *oy = m[(1, 0)] * x + m[(1, 1)] * y + m[(1, 2)] * z + m[(1, 3)];
            *oz = m[(2, 0)] * x + m[(2, 1)] * y + m[(2, 2)] * z + m[(2, 3)];
        }
        self.bins.resize(n, 0);
        zones.bin_many(&self.mx, &self.my, &mut self.bins);
        self.rows.clear();
        let mut last = NEAR;
        for b in self.bins.iter_mut() {
            *b = segment_of(*b, policy).unwrap_or(NEAR);
            // Distinct segments of the run (few; neighbours mostly share one).
            if *b != NEAR && *b != last && !self.rows.iter().any(|r| r.1 == *b) {
                self.rows.extend(table.segment(*b).iter().map(|c| (*c, *b)));
            }
            last = *b;
        }
        if self.rows.is_empty() {
            return;
        }
        let (mx, my, mz, bins) = (
            std::mem::take(&mut self.mx),
            std::mem::take(&mut self.my),
            std::mem::take(&mut self.mz),
            std::mem::take(&mut self.bins),
        );
        self.eval(&mx, &my, &mz, Some(&bins), acc);
        (self.mx, self.my, self.mz, self.bins) = (mx, my, mz, bins);
    }

    /// Evaluates `rows` for a run of points (vectorised, component-major) and merges the
    /// result into `acc`. With `bins`, a row only counts for points of its segment.
    fn eval(
        &mut self,
        xs: &[f32],
        ys: &[f32],
        zs: &[f32],
        bins: Option<&[u32]>,
        acc: &mut SumsMut<'_>,
    ) {
        let n = xs.len();
        let k = self.rows.len();
        if k == 0 {
            return;
        }
        self.l.resize(k * n, 0.0);
        for (r, &(q, seg)) in self.rows.iter().enumerate() {
            let row = &mut self.l[r * n..(r + 1) * n];
            let p = q.p;
            for (((o, &x), &y), &z) in row.iter_mut().zip(xs).zip(ys).zip(zs) {
                let (dx, dy, dz) = (x - q.m[0], y - q.m[1], z - q.m[2]);
                let d = p[0] * dx * dx
                    + p[3] * dy * dy
                    + p[5] * dz * dz
                    + 2.0 * (p[1] * dx * dy + p[2] * dx * dz + p[4] * dy * dz);
                *o = q.c - 0.5 * d;
            }
            if let Some(bins) = bins {
                for (o, &b) in row.iter_mut().zip(bins) {
                    *o = if b == seg { *o } else { EMPTY };
                }
            }
        }
        let part = &mut self.part;
        part.reset(n);
        for r in 0..k {
            for (m, &l) in part.max.iter_mut().zip(&self.l[r * n..(r + 1) * n]) {
                *m = m.max(l);
            }
        }
        for (r, &(q, _)) in self.rows.iter().enumerate() {
            for ((((&l, &m), s), (f, o)), e) in self.l[r * n..(r + 1) * n]
                .iter()
                .zip(&part.max)
                .zip(part.sum.iter_mut())
                .zip(part.flat.iter_mut().zip(part.orient.iter_mut()))
                .zip(part.elev.iter_mut())
            {
                let d = l - m;
                // Masked rows (l = EMPTY) and negligible components weigh nothing.
                let w = if d < -LOG_CUTOFF || l <= EMPTY {
                    0.0
                } else {
                    exp_nonpositive(d)
                };
                *s += w;
                *f += w * q.flat;
                *o += w * q.orient;
                *e += w * q.elev;
            }
        }
        // Streaming log-sum-exp merge, a straight loop over the run.
        for j in 0..n {
            let (pm, ps) = (part.max[j], part.sum[j]);
            let am = acc.max[j];
            let m = am.max(pm);
            let a = exp_nonpositive(am - m);
            let b = exp_nonpositive(pm - m);
            let keep = ps == 0.0;
            acc.max[j] = if keep { am } else { m };
            acc.sum[j] = if keep {
                acc.sum[j]
            } else {
                a * acc.sum[j] + b * ps
            };
            acc.flat[j] = if keep {
                acc.flat[j]
            } else {
                a * acc.flat[j] + b * part.flat[j]
            };
            acc.orient[j] = if keep {
                acc.orient[j]
            } else {
                a * acc.orient[j] + b * part.orient[j]
            };
            acc.elev[j] = if keep {
                acc.elev[j]
            } else {
                a * acc.elev[j] + b * part.elev[j]
            };
        }
    }
}
