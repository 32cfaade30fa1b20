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

/// Partial sums of one point over the components seen so far.
#[derive(Debug, Clone, Copy)]
struct Partial {
    max: f32,
    sum: f32,
    flat: f32,
    orient: f32,
    elev: f32,
}

const NONE: Partial = Partial {
    max: EMPTY,
    sum: 0.0,
    flat: 0.0,
    orient: 0.0,
    elev: 0.0,
};

impl Partial {
    /// Streaming log-sum-exp merge.
    #[inline]
    fn merge(&mut self, o: &Partial) {
        if o.sum == 0.0 {
            return;
        }
        let m = self.max.max(o.max);
        let a = exp_nonpositive(self.max - m);
        let b = exp_nonpositive(o.max - m);
        self.max = m;
        self.sum = a * self.sum + b * o.sum;
        self.flat = a * self.flat + b * o.flat;
        self.orient = a * self.orient + b * o.orient;
        self.elev = a * self.elev + b * o.elev;
    }

    #[inline]
    fn probability(&self) -> f32 {
        if self.sum > 0.0 {
            let inv = 1.0 / self.sum;
            ((self.flat * inv) * (self.orient * inv) * (self.elev * inv)).clamp(0.0, 1.0)
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
    acc: Vec<Partial>,
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
    s.acc.clear();
    s.acc.resize(s.order.len(), NONE);
    let runs = split_runs(&s.start, &mut s.acc);
    let (xs, ys, zs) = (&s.x, &s.y, &s.z);
    runs.into_par_iter()
        .with_max_len(1)
        .for_each_init(RunScratch::default, |rs, (seg, a, acc)| {
            let (x, y, z) = (
                &xs[a..a + acc.len()],
                &ys[a..a + acc.len()],
                &zs[a..a + acc.len()],
            );
            for f in frames {
                match f.transform {
                    None => rs.eval(f.model.query_table().segment(seg), x, y, z, acc),
                    Some(t) => rs.eval_moved(zones, f.model.query_table(), t, policy, x, y, z, acc),
                }
            }
        });
    out.fill(0.0);
    for (&i, a) in s.order.iter().zip(&s.acc) {
        out[i as usize] = a.probability();
    }
}

/// Mutable per-segment slices of the running sums, with each segment's index and offset.
fn split_runs<'a>(
    start: &[u32],
    mut acc: &'a mut [Partial],
) -> Vec<(u32, usize, &'a mut [Partial])> {
    let mut runs = Vec::new();
    for (seg, w) in start.windows(2).enumerate() {
        let len = (w[1] - w[0]) as usize;
        let (head, tail) = acc.split_at_mut(len);
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

/// Per-thread buffers for evaluating one run of points against one segment.
#[derive(Debug, Default)]
struct RunScratch {
    l: Vec<f32>,
    max: Vec<f32>,
    sum: Vec<f32>,
    flat: Vec<f32>,
    orient: Vec<f32>,
    elev: Vec<f32>,
    // For past frames: the run moved into that frame, its bins there, and the run
    // regrouped by those bins.
    mx: Vec<f32>,
    my: Vec<f32>,
    mz: Vec<f32>,
    bins: Vec<u32>,
    groups: Vec<(u32, u32)>,
    perm: Vec<u32>,
    gx: Vec<f32>,
    gy: Vec<f32>,
    gz: Vec<f32>,
    parts: Vec<Partial>,
}

impl RunScratch {
    /// Partial sums of a run against a past frame: the points are moved into that frame
    /// and binned there (vectorised), regrouped by the segment they fall into (a run of
    /// one compact segment spreads over only a few past segments), and each group is
    /// evaluated like a current-frame run.
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
        acc: &mut [Partial],
    ) {
        let n = acc.len();
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
        // Distinct answering segments of this run with their counts (few: linear search).
        self.groups.clear();
        for b in self.bins.iter_mut() {
            *b = segment_of(*b, policy).unwrap_or(NEAR);
            if *b == NEAR || table.segment(*b).is_empty() {
                *b = NEAR;
                continue;
            }
            match self.groups.iter_mut().find(|g| g.0 == *b) {
                Some(g) => g.1 += 1,
                None => self.groups.push((*b, 1)),
            }
        }
        let mut offset = 0;
        for g in self.groups.iter_mut() {
            let c = g.1;
            g.1 = offset;
            offset += c;
        }
        let total = offset as usize;
        self.perm.resize(total, 0);
        for v in [&mut self.gx, &mut self.gy, &mut self.gz] {
            v.resize(total, 0.0);
        }
        let mut cursor: Vec<(u32, u32)> = self.groups.clone();
        for (j, &b) in self.bins.iter().enumerate() {
            if b == NEAR {
                continue;
            }
            let Some(g) = cursor.iter_mut().find(|g| g.0 == b) else {
                continue;
            };
            let k = g.1 as usize;
            self.perm[k] = j as u32;
            self.gx[k] = self.mx[j];
            self.gy[k] = self.my[j];
            self.gz[k] = self.mz[j];
            g.1 += 1;
        }
        self.parts.clear();
        self.parts.resize(total, NONE);
        let groups = std::mem::take(&mut self.groups);
        let (gx, gy, gz, mut parts) = (
            std::mem::take(&mut self.gx),
            std::mem::take(&mut self.gy),
            std::mem::take(&mut self.gz),
            std::mem::take(&mut self.parts),
        );
        for (i, &(seg, start)) in groups.iter().enumerate() {
            let end = groups.get(i + 1).map_or(total, |g| g.1 as usize);
            let r = start as usize..end;
            self.eval(
                table.segment(seg),
                &gx[r.clone()],
                &gy[r.clone()],
                &gz[r.clone()],
                &mut parts[r],
            );
        }
        for (&j, p) in self.perm.iter().zip(&parts) {
            acc[j as usize].merge(p);
        }
        (self.groups, self.gx, self.gy, self.gz, self.parts) = (groups, gx, gy, gz, parts);
    }

    /// Partial sums of a run of points against the components of their own segment in
    /// straight loops over points (vectorised), merged into `acc`.
    fn eval(&mut self, comps: &[QComp], xs: &[f32], ys: &[f32], zs: &[f32], acc: &mut [Partial]) {
        let n = acc.len();
        if comps.is_empty() {
            return;
        }
        let k = comps.len();
        self.l.resize(k * n, 0.0);
        // Log-densities, component-major.
        for (c, q) in comps.iter().enumerate() {
            let row = &mut self.l[c * n..(c + 1) * n];
            let p = q.p;
            for (((r, &x), &y), &z) in row.iter_mut().zip(xs).zip(ys).zip(zs) {
                let (dx, dy, dz) = (x - q.m[0], y - q.m[1], z - q.m[2]);
                let d = p[0] * dx * dx
                    + p[3] * dy * dy
                    + p[5] * dz * dz
                    + 2.0 * (p[1] * dx * dy + p[2] * dx * dz + p[4] * dy * dz);
                *r = q.c - 0.5 * d;
            }
        }
        self.max.clear();
        self.max.extend_from_slice(&self.l[..n]);
        for c in 1..k {
            for (m, &l) in self.max.iter_mut().zip(&self.l[c * n..(c + 1) * n]) {
                *m = m.max(l);
            }
        }
        for v in [
            &mut self.sum,
            &mut self.flat,
            &mut self.orient,
            &mut self.elev,
        ] {
            v.clear();
            v.resize(n, 0.0);
        }
        let (sum, flat, orient, elev) = (
            &mut self.sum,
            &mut self.flat,
            &mut self.orient,
            &mut self.elev,
        );
        for (c, q) in comps.iter().enumerate() {
            for ((((&l, &m), s), (f, o)), e) in self.l[c * n..(c + 1) * n]
                .iter()
                .zip(&self.max)
                .zip(sum.iter_mut())
                .zip(flat.iter_mut().zip(orient.iter_mut()))
                .zip(elev.iter_mut())
            {
                let d = l - m;
                let w = if d < -LOG_CUTOFF {
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
        for (j, a) in acc.iter_mut().enumerate() {
            a.merge(&Partial {
                max: self.max[j],
                sum: sum[j],
                flat: flat[j],
                orient: orient[j],
                elev: elev[j],
            });
        }
    }
}
