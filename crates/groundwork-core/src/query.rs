//! The query (paper §III-E) and its multi-frame form (§III-F).
//!
//! A point's responsibilities are normalised over its own segment's components and the past
//! frames' components that answer for it; its ground probability is the product of the three
//! responsibility-weighted likelihoods. With one frame this is exactly the single-frame
//! query. Which past components answer is [`PastQuery`]: those of the past segment the
//! point falls into in each frame (`PerFrame`, the paper's), or those whose footprint reaches
//! the point's own segment (`Regridded`, the default; see `regrid`). The regridded query
//! evaluates the past frames that share an anchor (`crate::history`) together, in the
//! anchor's frame, and skips the components a bound shows negligible for a whole vector.
//!
//! Implementation: the points are grouped by their segment in the query scan (with the
//! fit's groups, see the `grouping` module). Each run is evaluated 16 points per SIMD
//! vector, and each vector against every frame while it stays in registers: against its
//! own segment's components for the query scan's model; for a past frame the vector is
//! moved into that frame, binned there and evaluated against each distinct segment it
//! falls into. Per-point sums (Σw, Σw·p_λ,
//! Σw·p_θ, Σw·p_e) are kept relative to a reference log-density, the query scan's best
//! component; past frames add to them without rescaling, and a log-sum-exp merge takes over
//! only where a component would exceed the reference by 2^86 (e^60).

pub mod equation;

use std::cell::RefCell;

use nalgebra::{Isometry3, Matrix3, Point3};
use rayon::prelude::*;

use crate::config::{BeyondRangePolicy, PastQuery};
use crate::simd::{LANES, Vf, Vi, lane_min, load_f64};
use wide::bytemuck::cast;

#[cfg(target_arch = "x86_64")]
mod avx512;
mod regrid;
use regrid::{RegriddedTable, SegmentRuns};

use crate::fastmath::{exp2_from, exp2_v};
use crate::gmm::{Evaluator, Sym3, half_precision_factor};
use crate::grouping::QueryGroups;
use crate::grouping::SegmentedPoints;
use crate::model::FrameModel;
use crate::zones::LaneBinner;

use crate::zones::{BEYOND, NEAR};

// Log-densities are in bits (log2) throughout: weights are then 2^d, without a
// multiplication by log2(e) in every exponential.

/// Components further below the reference than this (bits) carry a weight under
/// 2^-43 ≈ 1e-13 relative: they count as 0 (and would only produce denormals).
const LOG_CUTOFF: f32 = 43.0;

/// How far (bits) a component may exceed a point's running reference before the sums are
/// rescaled: weights stay below 2^86 ≈ 1e26, far from f32 overflow.
const LOG_HEADROOM: f32 = 86.0;

/// Past components further below the reference than this count as this far below.
const LOG_FLOOR: f32 = 86.0;

/// Log-density floor for "no component seen yet": finite so that merges never compute
/// −∞ − (−∞).
const EMPTY: f32 = -1e30;

/// f32 copy of a frame's components, structure of arrays, for the vectorised query.
#[derive(Debug, Clone, Default)]
pub(crate) struct QueryTable {
    /// Components of segment s are `start[s]..start[s+1]`.
    start: Vec<u32>,
    comps: Vec<QComp>,
    /// Per segment, the largest log-density any of its components reaches (its largest c).
    peak: Vec<f32>,
}

/// One component for the query: log2 N(x) = c − |U·x − b|², where UᵀU = log2(e)·P/2 (P
/// the precision, U upper triangular: `u` holds its rows' non-zero entries), b = U·mean and
/// c is the log-normaliser in bits. Folding the mean, the ½ and the base in makes a
/// log-density nine fused multiply-adds; the cancellation in U·x − b costs about
/// |U·x|·6e-8 ≈ 1e-5 even 80 m out, far below what matters in a weight.
#[derive(Debug, Clone, Copy, Default)]
struct QComp {
    u: [f32; 6],
    b: [f32; 3],
    c: f32,
    flat: f32,
    orient: f32,
    elev: f32,
}

impl QueryTable {
    pub(crate) fn new(model: &FrameModel) -> Self {
        Self::build(model, |e| (e.precision, e.mean))
    }

    /// The model's components expressed in another frame, `to` mapping the model's
    /// ground-aligned frame into it: mean R·μ + t, precision R·P·Rᵀ (the log-normaliser
    /// does not change).
    pub(crate) fn moved(model: &FrameModel, to: &Isometry3<f64>) -> Self {
        let r = to.rotation.to_rotation_matrix().into_inner();
        Self::build(model, |e| {
            let p = &e.precision;
            let p = Matrix3::new(p[0], p[1], p[2], p[1], p[3], p[4], p[2], p[4], p[5]);
            let p = r * p * r.transpose();
            let mean = to * Point3::from(e.mean);
            (
                [
                    p[(0, 0)],
                    p[(0, 1)],
                    p[(0, 2)],
                    p[(1, 1)],
                    p[(1, 2)],
                    p[(2, 2)],
                ],
                mean.coords.into(),
            )
        })
    }

    /// The table of `model`'s components, each given by `eval`'s precision and mean.
    fn build(model: &FrameModel, eval: impl Fn(&Evaluator) -> (Sym3, [f64; 3])) -> Self {
        let mut start = Vec::with_capacity(model.segment_count() + 1);
        let mut comps: Vec<QComp> = Vec::with_capacity(model.components().len());
        let mut peak = Vec::with_capacity(model.segment_count());
        start.push(0);
        // Scaling U and b by √log2(e) puts |U·x − b|² in bits.
        let bits = std::f64::consts::LOG2_E.sqrt();
        for s in 0..model.segment_count() {
            for g in model.segment(s as u32) {
                let (precision, mean) = eval(&g.eval);
                let (u, b) = half_precision_factor(&precision, &mean);
                comps.push(QComp {
                    u: u.map(|v| (v * bits) as f32),
                    b: b.map(|v| (v * bits) as f32),
                    c: (g.eval.log_coef * std::f64::consts::LOG2_E) as f32,
                    flat: g.flatness as f32,
                    orient: g.orientation as f32,
                    elev: g.elevation as f32,
                });
            }
            let first = *start.last().unwrap_or(&0) as usize;
            peak.push(comps[first..].iter().map(|q| q.c).fold(EMPTY, f32::max));
            start.push(comps.len() as u32);
        }
        Self { start, comps, peak }
    }

    #[inline]
    fn segment(&self, s: u32) -> &[QComp] {
        let s = s as usize;
        match (self.start.get(s), self.start.get(s + 1)) {
            (Some(&a), Some(&b)) => &self.comps[a as usize..b as usize],
            _ => &[],
        }
    }

    /// A segment's components and the largest log-density they reach.
    #[inline]
    fn segment_peak(&self, s: u32) -> (&[QComp], f32) {
        (
            self.segment(s),
            self.peak.get(s as usize).copied().unwrap_or(EMPTY),
        )
    }
}

/// What decides which components answer for a point.
#[derive(Debug, Clone, Copy)]
pub(crate) struct QueryRules {
    /// What a point beyond max range gets.
    pub beyond: BeyondRangePolicy,
    /// How past frames are asked.
    pub past: PastQuery,
    /// A past component's reach, in σ, for [`PastQuery::Regridded`].
    pub spread: f64,
}

/// Segment whose model answers for a packed bin under `policy`, or `None` if no model is
/// asked (near the sensor, or beyond range under `NonGround`).
#[inline]
pub(crate) fn answering_segment(packed: u32, policy: BeyondRangePolicy) -> Option<u32> {
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

/// One model to query, with the transform from the query scan's ground-aligned frame into
/// that model's ground-aligned frame (`None` for the query scan's own model).
#[derive(Debug, Clone, Copy)]
pub(crate) struct QueryFrame<'a> {
    /// The fitted model.
    pub model: &'a FrameModel,
    /// Query frame → model frame.
    pub transform: Option<&'a Isometry3<f64>>,
    /// Where the regridded query evaluates a past frame's components (`None`: in the
    /// frame's own frame, from `model`'s table).
    pub anchored: Option<AnchoredFrame<'a>>,
}

/// A past frame's components in the frame of its anchor (see `crate::history`): past frames
/// with one anchor are evaluated together, on the points moved once into it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct AnchoredFrame<'a> {
    /// Frames with the same anchor id share `transform`.
    pub anchor: u64,
    /// The components in the anchor's frame, in the model's order.
    pub table: &'a QueryTable,
    /// Query frame → anchor frame.
    pub transform: &'a Isometry3<f64>,
}

/// Ground probabilities of a vector of points from their final sums: lane by lane
/// [`equation::ground_probability`], bit for bit on every CPU (tested). Written out in
/// vectors: the AVX-512 build of the query left the lane-by-lane form scalar (a division per
/// point, 15 % of its time with two frames on an Intel Xeon). The clamp is `clamp`'s
/// compares and selects, so a NaN passes as it does there (`fast_max` would turn it into 0
/// on x86 and keep it on NEON).
#[inline(always)]
fn probabilities(s: &LaneSums) -> Vf {
    let inv = Vf::ONE / s.sum;
    let p = (s.flat * inv) * (s.orient * inv) * (s.elev * inv);
    let p = p.simd_lt(Vf::ZERO).select(Vf::ZERO, p);
    let p = p.simd_gt(Vf::ONE).select(Vf::ONE, p);
    s.sum.simd_gt(Vf::ZERO).select(p, Vf::ZERO)
}

/// Reusable buffers of the query.
#[derive(Debug, Default)]
pub(crate) struct QueryScratch {
    /// What the grouping wrote for the query (places, beyond-range points).
    pub(crate) groups: QueryGroups,
    /// Ground probability per grouped point: in-range points first (numbered as the fit's
    /// groups), then beyond-range points.
    prob: Vec<f32>,
}

/// What the query wrote, counted while writing it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct OutputTally {
    /// Probabilities that are not finite (a defect: none is known).
    pub non_finite: usize,
    /// Probabilities at or above the ground threshold.
    pub ground: usize,
}

/// Ground probability of every point [`group_points`](crate::grouping::group_points)
/// grouped into `sorted` and `s` (the query scan's points in its ground-aligned frame).
/// Points near the sensor, beyond range under the `NonGround` policy, or in no fitted
/// segment of any frame get 0. Returns the written probabilities' tally against `threshold`
/// (taken on both cores while writing, not in a serial pass after).
///
/// The points are grouped once by their segment in the query scan, so that a vector of
/// them is a compact patch of ground, mostly in one cell of every past frame too.
pub(crate) fn query_grouped(
    binner: &LaneBinner,
    frames: &[QueryFrame<'_>],
    rules: QueryRules,
    threshold: f32,
    sorted: &SegmentedPoints,
    s: &mut QueryScratch,
    out: &mut [f32],
) -> OutputTally {
    let g = &s.groups;
    let in_range = sorted.xs.len();
    s.prob.resize(in_range + g.beyond.x.len(), 0.0);
    let (near, far) = s.prob.split_at_mut(in_range);
    let mut runs = split_runs(&sorted.start, [&sorted.xs, &sorted.ys, &sorted.zs], near);
    runs.extend(split_runs(
        &g.beyond_start,
        [&g.beyond.x, &g.beyond.y, &g.beyond.z],
        far,
    ));
    // Big runs first: rayon then balances the cores well.
    runs.sort_unstable_by_key(|r| std::cmp::Reverse(r.prob.len()));
    // Regridded: the past frames become one table over the query scan's segments, and each
    // point is asked only there.
    let (frames, regridded) = match (rules.past, frames.split_first()) {
        (PastQuery::Regridded, Some((own, past))) if !past.is_empty() => (
            std::slice::from_ref(own),
            Some(RegriddedTable::new(
                binner,
                past,
                rules.beyond,
                rules.spread,
            )),
        ),
        _ => (frames, None),
    };
    let asked = Asked {
        binner,
        frames: frames
            .iter()
            .map(|f| (f.model.query_table(), f.transform.map(Move::new)))
            .collect(),
        regridded: regridded.as_ref(),
        policy: rules.beyond,
    };
    runs.into_par_iter()
        .with_max_len(1)
        .for_each(|r| PAST_RUNS.with_borrow_mut(|past| eval_run(&asked, r, past)));
    // Back into input order: a gather per input point, so both cores share it.
    let prob = &s.prob;
    let (non_finite, ground) = out
        .par_chunks_mut(GATHER_CHUNK)
        .zip(s.groups.place.par_chunks(GATHER_CHUNK))
        .map(|(out, place)| {
            let (mut non_finite, mut ground) = (0, 0);
            for (o, &j) in out.iter_mut().zip(place) {
                let p = prob.get(j as usize).copied().unwrap_or(0.0);
                *o = p;
                non_finite += usize::from(!p.is_finite());
                ground += usize::from(p >= threshold);
            }
            (non_finite, ground)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    OutputTally { non_finite, ground }
}

thread_local! {
    /// Per worker, the buffers a segment's past components are gathered into.
    static PAST_RUNS: RefCell<SegmentRuns> = RefCell::default();
}

/// Input points per task of the final gather.
const GATHER_CHUNK: usize = 16 * 1024;

/// The grouped points of one segment and their probabilities.
struct Run<'a> {
    seg: u32,
    xyz: [&'a [f64]; 3],
    prob: &'a mut [f32],
}

/// What every run of one query asks: the frames' tables (with the move into each past
/// frame), the past frames' regridded table, the binning, and the beyond-range policy.
struct Asked<'a> {
    binner: &'a LaneBinner,
    frames: Vec<(&'a QueryTable, Option<Move>)>,
    /// The past frames' components per query-scan segment ([`PastQuery::Regridded`]); the
    /// past frames are then not in `frames`.
    regridded: Option<&'a RegriddedTable<'a>>,
    policy: BeyondRangePolicy,
}

/// Per-segment runs of grouped points (`start` their offsets, an empty `start` none).
fn split_runs<'a>(start: &[u32], xyz: [&'a [f64]; 3], mut prob: &'a mut [f32]) -> Vec<Run<'a>> {
    let mut runs = Vec::new();
    for (seg, w) in start.windows(2).enumerate() {
        let (a, b) = (w[0] as usize, w[1] as usize);
        let (head, tail) = prob.split_at_mut(b - a);
        prob = tail;
        if b > a {
            runs.push(Run {
                seg: seg as u32,
                xyz: xyz.map(|v| &v[a..b]),
                prob: head,
            });
        }
    }
    runs
}

/// A rigid transform as f32 lanes: rows of [R | t].
#[derive(Debug, Clone, Copy)]
struct Move([[Vf; 4]; 3]);

impl Move {
    const IDENTITY: Move = {
        let (o, i) = (Vf::ZERO, Vf::ONE);
        Move([[i, o, o, o], [o, i, o, o], [o, o, i, o]])
    };

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

/// Ground probabilities of a run of points (all in query-scan segment `seg`) from their
/// sums over every frame, a vector of points at a time: the vector stays in registers while
/// all frames are asked. For a past frame the vector is moved into that frame, binned there,
/// and evaluated against the components of each distinct segment it falls into (points of
/// one compact current segment are neighbours, so nearly every vector falls into a single
/// past segment).
fn eval_run(asked: &Asked<'_>, run: Run<'_>, past: &mut SegmentRuns) {
    // With one frame there are no past components, and the AVX-512 build of the rest
    // measured 1–4 % slower.
    #[cfg(target_arch = "x86_64")]
    if (asked.frames.len() > 1 || asked.regridded.is_some()) && crate::cpu::avx512() {
        #[allow(unsafe_code)]
        // SAFETY: the CPU has every feature eval_run_avx512 is compiled with.
        unsafe {
            eval_run_avx512(asked, run, past)
        };
        return;
    }
    eval_run_with::<false>(asked, run, past)
}

/// [`eval_run`] compiled for AVX-512: 32 vector registers for the portable code, and the
/// past components' loop in 512-bit registers ([`avx512::add_fixed`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
fn eval_run_avx512(asked: &Asked<'_>, run: Run<'_>, past: &mut SegmentRuns) {
    eval_run_with::<true>(asked, run, past)
}

/// [`eval_run`]; `AVX512` only inside [`eval_run_avx512`] (the past components' loop is then
/// [`avx512::add_fixed`], which must be inlined into code compiled with AVX-512).
#[inline(always)]
fn eval_run_with<const AVX512: bool>(
    &Asked {
        binner,
        ref frames,
        regridded,
        policy,
    }: &Asked<'_>,
    Run {
        seg,
        xyz: [xs, ys, zs],
        prob,
    }: Run<'_>,
    past: &mut SegmentRuns,
) {
    let lane_index = Vi::new(std::array::from_fn(|i| i as i32));
    let no_key = Vi::splat(-1);
    // Per frame, the last three past segments vectors fell into, latest first: neighbours
    // mostly fall into the same ones, and a cheap test confirms it (or the vector is
    // binned). More than one, because 43 % of vectors straddle a past cell's edge; three
    // made the 16-frame query 3 % faster than two.
    let mut guess = vec![[u32::MAX; 3]; frames.len()];
    // The segment's past components (regridded), gathered once for all its vectors.
    if let Some(table) = regridded {
        table.gather(seg, past);
    }
    // Indices of the past components of a run that can matter to the current vector.
    let mut live = vec![0u32; regridded.map_or(0, |_| past.longest_run() + LANES)];
    for j in (0..prob.len()).step_by(LANES) {
        let w = LANES.min(prob.len() - j);
        let (x, y, z) = (load_f64(xs, j, w), load_f64(ys, j, w), load_f64(zs, j, w));
        let real = lane_index.simd_lt(Vi::splat(w as i32));
        let real_f: Vf = cast(real);
        let last_lane = 1u32 << (w - 1);
        let mut sums = LaneSums::EMPTY;
        // The lowest reference over the real lanes once the query scan's own model is in
        // (references only grow): a past segment whose peak is within the headroom of it
        // cannot overflow, and skips the check.
        let mut low = EMPTY;
        for ((table, mv), guess) in frames.iter().zip(guess.iter_mut()) {
            let Some(mv) = mv else {
                // The query scan's own model: every lane is in segment `seg`.
                let comps = table.segment(seg);
                if !comps.is_empty() {
                    sums = sums.merge(eval_lanes(comps, x, y, z));
                }
                low = lane_min(real_f.select(sums.max, Vf::splat(f32::INFINITY)));
                continue;
            };
            let moved = mv.apply(x, y, z);
            let (x, y) = (moved[0], moved[1]);
            let [g0, g1, g2] = *guess;
            let in0 = binner.inside(g0, x, y) & real_f;
            if in0.to_bitmask() == real_f.to_bitmask() {
                sums.add_segment::<AVX512>(table.segment_peak(g0), low, &moved, real_f);
                continue;
            }
            let in1 = binner.inside(g1, x, y) & real_f;
            let in2 = binner.inside(g2, x, y) & real_f;
            if (in0 | in1 | in2).to_bitmask() == real_f.to_bitmask() {
                // A lane inside two cells by the margin cannot be: each lane is in one.
                for (g, hit) in [(g0, in0), (g1, in1), (g2, in2)] {
                    if hit.any() {
                        sums.add_segment::<AVX512>(table.segment_peak(g), low, &moved, hit);
                    }
                }
                // The next vector continues where this one ends: its cell first.
                let last = if in0.to_bitmask() & last_lane != 0 {
                    g0
                } else if in1.to_bitmask() & last_lane != 0 {
                    g1
                } else {
                    g2
                };
                *guess = most_recent_first(*guess, last);
                continue;
            }
            // Answering segment per lane, −1 for none (near, beyond under `NonGround`, padding).
            let packed = binner.bin(x, y);
            let beyond = packed.simd_lt(Vi::ZERO) & packed.simd_ne(no_key);
            let keys = match policy {
                BeyondRangePolicy::OuterRing => beyond.select(packed & Vi::splat(i32::MAX), packed),
                BeyondRangePolicy::NonGround => beyond.select(no_key, packed),
            };
            let keys = real.select(keys, no_key);
            let lanes = keys.to_array();
            let mut todo = !cast::<Vi, Vf>(keys.simd_eq(no_key)).to_bitmask() & ((1 << LANES) - 1);
            if todo != 0 {
                // The last lane's segment first.
                let last = lanes[31 - todo.leading_zeros() as usize] as u32;
                *guess = most_recent_first(*guess, last);
            }
            while todo != 0 {
                let seg = lanes[todo.trailing_zeros() as usize];
                let hit = keys.simd_eq(Vi::splat(seg));
                todo &= !cast::<Vi, Vf>(hit).to_bitmask();
                sums.add_segment::<AVX512>(table.segment_peak(seg as u32), low, &moved, cast(hit));
            }
        }
        if let Some(table) = regridded {
            // Every lane is in segment `seg`, and its past components are listed there, one
            // run per anchor; each is evaluated in its anchor's frame.
            for run in past.runs() {
                let Some(mv) = table.moves.get(run.anchor as usize) else {
                    continue;
                };
                let moved = mv.apply(x, y, z);
                let comps = past.comps(run);
                if run.peak - low > LOG_HEADROOM {
                    // The rescaling path: every component.
                    sums.add_segment::<AVX512>((comps, run.peak), low, &moved, real_f);
                    continue;
                }
                // Only the components that can reach 2^-LOG_CUTOFF of some lane's reference
                // in the vector's bounding box (4 in 10 do not, KITTI frame 5 against 15
                // past frames): below it a weight is under the f32 rounding of the sums,
                // each at least the reference's 1.
                let lo = moved.map(|v| lane_min(real_f.select(v, Vf::splat(f32::INFINITY))));
                let hi = moved.map(|v| -lane_min(real_f.select(-v, Vf::splat(f32::INFINITY))));
                let n = regrid::list_reaching::<AVX512>(
                    past.blocks(run),
                    lo,
                    hi,
                    low - LOG_CUTOFF,
                    &mut live,
                );
                let listed = live[..n].iter().map(|&i| &comps[i as usize]);
                sums.add_fixed::<AVX512>(listed, &moved, real_f);
            }
        }
        // The sums are final: every frame has been asked for these points.
        prob[j..j + w].copy_from_slice(&probabilities(&sums).to_array()[..w]);
    }
}

/// The guesses with `seg` moved to the front, the others kept in order of recency (the
/// oldest drops out if `seg` was not among them).
#[inline(always)]
fn most_recent_first([a, b, c]: [u32; 3], seg: u32) -> [u32; 3] {
    if seg == a {
        [a, b, c]
    } else if seg == b {
        [b, a, c]
    } else {
        [seg, a, b]
    }
}

/// Components evaluated together per chunk of points; more are merged block by block.
const BLOCK: usize = 8;

/// The sums (Σw, Σw·p_λ, Σw·p_θ, Σw·p_e) of one vector of points; `max` is the reference:
/// the largest log-density when the sums were last rescaled.
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
        let e = exp2_v(-(self.max - o.max).abs());
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

    /// Adds weights `w` of component `q` (relative to the reference).
    #[inline(always)]
    fn add_weight(&mut self, w: Vf, q: &QComp) {
        let s = Vf::splat;
        self.sum += w;
        self.flat = w.mul_add(s(q.flat), self.flat);
        self.orient = w.mul_add(s(q.orient), self.orient);
        self.elev = w.mul_add(s(q.elev), self.elev);
    }

    /// Adds, in the lanes of `hit`, the weight of component `q` relative to `reference`;
    /// returns the log-density over the reference.
    #[inline(always)]
    fn add_component(&mut self, q: &QComp, x: Vf, y: Vf, z: Vf, reference: Vf, hit: Vf) -> Vf {
        let (d, w) = weight(q, x, y, z, reference, hit);
        self.add_weight(w, q);
        d
    }

    /// Adds, in the lanes of `hit`, the weights of `comps` relative to the running maximum
    /// kept as a fixed reference (the caller knows that none exceeds it by more than
    /// [`LOG_HEADROOM`]).
    #[inline(always)]
    fn add_fixed<'c, const AVX512: bool>(
        &mut self,
        comps: impl Iterator<Item = &'c QComp>,
        p: &[Vf; 3],
        hit: Vf,
    ) {
        let reference = self.max;
        #[cfg(target_arch = "x86_64")]
        if AVX512 {
            let sums = [self.sum, self.flat, self.orient, self.elev];
            #[allow(unsafe_code)]
            // SAFETY: `AVX512` is set only inside `eval_run_avx512`, which is compiled with
            // AVX-512F and called only after `cpu::avx512`.
            let [sum, flat, orient, elev] =
                unsafe { avx512::add_fixed(comps, p, reference, hit, sums) };
            (self.sum, self.flat, self.orient, self.elev) = (sum, flat, orient, elev);
            return;
        }
        // Two components at a time: their dependency chains overlap (−1.5 % on one
        // thread, 16 frames, AVX2 code on Zen 4).
        let [x, y, z] = *p;
        let mut comps = comps;
        while let Some(q0) = comps.next() {
            let Some(q1) = comps.next() else {
                self.add_component(q0, x, y, z, reference, hit);
                break;
            };
            let (_, w0) = weight(q0, x, y, z, reference, hit);
            let (_, w1) = weight(q1, x, y, z, reference, hit);
            self.add_weight(w0, q0);
            self.add_weight(w1, q1);
        }
    }

    /// Adds, in the lanes of `hit`, the weights of a segment's components relative to the
    /// running maximum, which is kept as a fixed reference: one pass in registers, no
    /// rescaling and no extra exponential. If a component exceeds the reference by more
    /// than [`LOG_HEADROOM`] in some lane (or the lane has seen no component yet), that
    /// pass is dropped and the segment is merged with rescaling instead, so that nothing
    /// overflows.
    #[inline(always)]
    fn add_segment<const AVX512: bool>(
        &mut self,
        (comps, peak): (&[QComp], f32),
        low: f32,
        p: &[Vf; 3],
        hit: Vf,
    ) {
        let [x, y, z] = *p;
        let s = Vf::splat;
        if peak - low <= LOG_HEADROOM {
            // No component can exceed any lane's reference by more than the headroom.
            self.add_fixed::<AVX512>(comps.iter(), p, hit);
            return;
        }
        let mut next = *self;
        let mut top = s(EMPTY);
        for q in comps {
            top = top.fast_max(next.add_component(q, x, y, z, self.max, hit));
        }
        let over = top.simd_gt(s(LOG_HEADROOM));
        *self = if cast::<Vf, Vi>(over & hit).any() {
            self.select(hit, self.merge(eval_lanes(comps, x, y, z)))
        } else {
            next
        };
    }
}

/// Component `q`'s log-density over `reference` at one vector of points, and its weight
/// relative to the reference in the lanes of `hit` (0 elsewhere).
#[inline(always)]
fn weight(q: &QComp, x: Vf, y: Vf, z: Vf, reference: Vf, hit: Vf) -> (Vf, Vf) {
    let d = log_density(q, x, y, z) - reference;
    // Below the floor a weight counts as 2^-86 (≤ 1e-26 of the sums, which hold the
    // reference's weight 1): no compare, and no denormal products.
    (d, exp2_from(d.fast_max(Vf::splat(-LOG_FLOOR))) & hit)
}

/// Log-density (bits) of one vector of points under one component.
#[inline(always)]
fn log_density(q: &QComp, x: Vf, y: Vf, z: Vf) -> Vf {
    let s = Vf::splat;
    let u = q.u;
    let u3 = s(u[5]).mul_sub(z, s(q.b[2]));
    let u2 = s(u[3]).mul_add(y, s(u[4]).mul_sub(z, s(q.b[1])));
    let u1 = s(u[0]).mul_add(x, s(u[1]).mul_add(y, s(u[2]).mul_sub(z, s(q.b[0]))));
    u1.mul_neg_add(u1, u2.mul_neg_add(u2, u3.mul_neg_add(u3, s(q.c))))
}

/// Sums of one vector of points against up to [`BLOCK`] components, relative to their own
/// maximum.
#[inline(always)]
fn eval_block(comps: &[QComp], x: Vf, y: Vf, z: Vf) -> LaneSums {
    let mut l = [Vf::splat(EMPTY); BLOCK];
    for (lc, q) in l.iter_mut().zip(comps) {
        *lc = log_density(q, x, y, z);
    }
    let s = Vf::splat;
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
        r.add_weight(live.select(exp2_v(d), zero), q);
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

    use super::*;
    use crate::config::mount_transform;
    use crate::grouping::{GroundPoints, SegmentCounts, group_points};
    use crate::model::GroundComponent;
    use crate::zones::{Bin, ZoneModel};
    use crate::{Point, Segmenter, SegmenterConfig};
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    #[test]
    fn a_guess_moves_to_the_front_and_the_oldest_drops_out() {
        assert_eq!(most_recent_first([1, 2, 3], 1), [1, 2, 3]);
        assert_eq!(most_recent_first([1, 2, 3], 2), [2, 1, 3]);
        assert_eq!(most_recent_first([1, 2, 3], 3), [3, 1, 2]);
        assert_eq!(most_recent_first([1, 2, 3], 9), [9, 1, 2]);
    }

    /// [`probabilities`] as the AVX-512 query compiles it.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
    fn probabilities_avx512(s: &LaneSums) -> Vf {
        probabilities(s)
    }

    proptest::proptest! {
        /// Sums as the query builds them (a lane's sum 0, or at least the reference's 1
        /// and up to thousands; each weighted likelihood between 0 and its sum), and
        /// smaller ones that it does not build: the vectors give the scalar form's bits, in
        /// the portable build and in the AVX-512 one where the CPU has it.
        #[test]
        fn a_vector_of_probabilities_is_the_scalar_form_lane_by_lane(
            lanes in proptest::collection::vec(
                (
                    proptest::prop_oneof![
                        1 => proptest::strategy::Just(0.0f32),
                        4 => 1.0f32..4096.0,
                        1 => 1e-30f32..1.0,
                        // Subnormal: 1/sum overflows, and 0 · ∞ is a NaN the clamp keeps.
                        1 => 1e-45f32..2e-39,
                    ],
                    proptest::array::uniform3(proptest::prop_oneof![
                        1 => proptest::strategy::Just(0.0f32),
                        3 => 0.0f32..=1.0,
                    ]),
                ),
                LANES,
            )
        ) {
            // Lane i's sum and its k-th weighted likelihood (k = 3: the sum itself).
            let get = |k: usize| {
                Vf::new(std::array::from_fn(|i| {
                    let (sum, shares) = lanes[i];
                    if k == 3 { sum } else { sum * shares[k] }
                }))
            };
            let sums = LaneSums {
                max: Vf::ZERO,
                sum: get(3),
                flat: get(0),
                orient: get(1),
                elev: get(2),
            };
            let expected: Vec<u32> = (0..LANES)
                .map(|i| {
                    let at = |v: Vf| v.to_array()[i];
                    equation::ground_probability(
                        at(sums.sum),
                        at(sums.flat),
                        at(sums.orient),
                        at(sums.elev),
                    )
                        .to_bits()
                })
                .collect();
            let bits = |v: Vf| v.to_array().map(f32::to_bits).to_vec();
            proptest::prop_assert_eq!(bits(probabilities(&sums)), expected.clone());
            #[cfg(target_arch = "x86_64")]
            if crate::cpu::avx512() {
                #[allow(unsafe_code)]
                // SAFETY: the CPU has every feature the function is compiled with.
                let v = unsafe { probabilities_avx512(&sums) };
                proptest::prop_assert_eq!(bits(v), expected);
            }
        }
    }

    /// [`Bin`] in the packed form (for the direct evaluation in tests).
    fn pack(bin: Bin) -> u32 {
        match bin {
            Bin::Near => NEAR,
            Bin::Segment(s) => s,
            Bin::Beyond(s) => s | BEYOND,
        }
    }

    /// A ring-scanned road (sensor frame, sensor 1.73 m up) with a gentle bump, a car-sized
    /// box and a wall, seen from `x0` metres further along x, the road raised by `lift`.
    fn scene(x0: f32, lift: f32) -> Vec<Point> {
        let mut pts = Vec::new();
        // Rings every 0.6 m to 40.8 m, every 2 m to 80 m (the default max range), and
        // three beyond it, which the outer ring answers for.
        let radii = (0..64)
            .map(|ring| 3.0 + ring as f32 * 0.6)
            .chain((0..23).map(|ring| 42.0 + ring as f32 * 2.0));
        for (ring, r) in radii.enumerate() {
            for k in 0..720 {
                let a = k as f32 * std::f32::consts::TAU / 720.0;
                let (x, y) = (r * a.cos(), r * a.sin());
                let bump = 0.15 * (-((x + x0 - 15.0).powi(2) + y * y) / 20.0).exp();
                let wobble = ((ring * 7 + k * 13) % 11) as f32 * 0.002;
                pts.push(Point::new(x, y, -1.73 + lift + bump + wobble));
            }
        }
        for i in 0..40 {
            for k in 0..30 {
                let x = 12.0 + i as f32 * 0.05 - x0;
                pts.push(Point::new(x, 3.0, -1.7 + k as f32 * 0.05));
                pts.push(Point::new(x, -8.0, -1.7 + k as f32 * 0.1));
            }
        }
        pts
    }

    /// A component's term of the equation at a point given in the component's own frame.
    fn term(g: &GroundComponent, q: &Point3<f64>) -> equation::ComponentTerm {
        let e = &g.eval;
        let (dx, dy, dz) = (q.x - e.mean[0], q.y - e.mean[1], q.z - e.mean[2]);
        equation::ComponentTerm {
            log_density: e.log_coef - 0.5 * crate::gmm::quad_form(&e.precision, dx, dy, dz),
            flatness: g.flatness,
            orientation: g.orientation,
            elevation: g.elevation,
        }
    }

    /// The per-frame equation evaluated directly, in f64: every component of the segment
    /// that answers for the point in each frame, normalised together.
    fn per_frame_reference(zones: &ZoneModel, frames: &[QueryFrame<'_>], p: [f64; 3]) -> f64 {
        let mut terms = Vec::new();
        for f in frames {
            let q = f.transform.map_or(Point3::from(p), |t| t * Point3::from(p));
            let Some(seg) =
                answering_segment(pack(zones.bin(q.x, q.y)), BeyondRangePolicy::OuterRing)
            else {
                continue;
            };
            terms.extend(f.model.segment(seg).iter().map(|g| term(g, &q)));
        }
        equation::ground_probability_of(&terms)
    }

    /// Per query-scan segment, the (past frame, component) pairs whose footprint reaches
    /// it, found directly in f64: the mean moved into the query scan, ± `spread` σ along x,
    /// y and the diagonals, each sample binned (at f32 coordinates, as the table bins them).
    fn reached(
        zones: &ZoneModel,
        frames: &[QueryFrame<'_>],
        spread: f64,
    ) -> Vec<Vec<(usize, usize)>> {
        let mut lists = vec![Vec::new(); zones.segment_count()];
        for (f, frame) in frames.iter().enumerate().skip(1) {
            let t = frame.transform.unwrap();
            let back = t.inverse();
            let r = t.rotation.to_rotation_matrix().into_inner();
            for (i, g) in frame.model.components().iter().enumerate() {
                let m = back * Point3::from(g.gaussian.mean);
                let c = &g.gaussian.covariance;
                let cov =
                    nalgebra::Matrix3::new(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5]);
                let turned = r.transpose() * cov * r;
                let (sx, sy) = (turned[(0, 0)].sqrt(), turned[(1, 1)].sqrt());
                let mut segs = Vec::new();
                for dx in [-1.0, 0.0, 1.0] {
                    for dy in [-1.0, 0.0, 1.0] {
                        let x = f64::from((m.x + dx * spread * sx) as f32);
                        let y = f64::from((m.y + dy * spread * sy) as f32);
                        let packed = pack(zones.bin(x, y));
                        if let Some(s) = answering_segment(packed, BeyondRangePolicy::OuterRing)
                            && !segs.contains(&s)
                        {
                            segs.push(s);
                        }
                    }
                }
                for s in segs {
                    lists[s as usize].push((f, i));
                }
            }
        }
        lists
    }

    /// The regridded equation evaluated directly, in f64: the components of the point's own
    /// segment, and every past component whose footprint reaches that segment (`reached`),
    /// evaluated at the point moved into its frame.
    fn regridded_reference(
        zones: &ZoneModel,
        frames: &[QueryFrame<'_>],
        reached: &[Vec<(usize, usize)>],
        p: [f64; 3],
    ) -> f64 {
        let Some(seg) =
            answering_segment(pack(zones.bin(p[0], p[1])), BeyondRangePolicy::OuterRing)
        else {
            return 0.0;
        };
        let mut terms: Vec<_> = frames[0]
            .model
            .segment(seg)
            .iter()
            .map(|g| term(g, &Point3::from(p)))
            .collect();
        for &(f, i) in &reached[seg as usize] {
            let t = frames[f].transform.unwrap();
            terms.push(term(
                &frames[f].model.components()[i],
                &(t * Point3::from(p)),
            ));
        }
        equation::ground_probability_of(&terms)
    }

    /// Frame 0 of [`scene`] fitted with a bad model (the road 0.3 m too high, so that past
    /// frames outrank it by far more than 2^86 on the road and the rescaling path is asked
    /// as well as the fixed-reference one), three past frames seen from 0.8, 1.6 and 2.4 m
    /// behind (the last also turned by 2°), and the query of frame 0's points against all
    /// four under `past`: (segmenter, query-scan model, past models, query → past
    /// transforms, points in the ground-aligned frame, probabilities). With `anchored`,
    /// the past frames share the oldest one's frame as their anchor (as the history keeps
    /// them for the regridded query).
    #[allow(clippy::type_complexity)]
    fn query_scene(
        past_query: PastQuery,
        spread: f64,
        anchored: bool,
    ) -> (
        Segmenter,
        FrameModel,
        Vec<FrameModel>,
        Vec<Isometry3<f64>>,
        Vec<[f64; 3]>,
        Vec<f32>,
    ) {
        let cfg = SegmenterConfig::default();
        let mount = mount_transform(&cfg.sensor.mount).unwrap();
        let mut seg = Segmenter::new(cfg).unwrap();
        let now = scene(0.0, 0.0);
        let model = seg.fit(&scene(0.0, 0.3)).unwrap();
        let past: Vec<_> = [0.8f32, 1.6, 2.4]
            .iter()
            .map(|&x0| seg.fit(&scene(-x0, 0.0)).unwrap())
            .collect();
        let transforms: Vec<Isometry3<f64>> = vec![
            Translation3::new(0.8, 0.0, 0.0).into(),
            Translation3::new(1.6, 0.0, 0.0).into(),
            Isometry3::from_parts(
                Translation3::new(2.4, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, 0.035),
            ),
        ];
        let mut frames = frames_of(&model, &past, &transforms);
        let moved = moved_to_oldest(&past, &transforms);
        if anchored {
            anchor_to_oldest(&mut frames, &moved, &transforms);
        }
        let ground: Vec<[f64; 3]> = now
            .iter()
            .map(|p| {
                let q = mount * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                [q.x, q.y, q.z]
            })
            .collect();
        let zones = seg.zones();
        let bins: Vec<u32> = ground.iter().map(|p| pack(zones.bin(p[0], p[1]))).collect();
        let mut out = vec![0.0; ground.len()];
        let binner = LaneBinner::new(zones);
        let policy = BeyondRangePolicy::OuterRing;
        let mut scratch = QueryScratch::default();
        let counts = SegmentCounts::of(&bins, binner.segment_count());
        let soa = GroundPoints {
            x: ground.iter().map(|p| p[0]).collect(),
            y: ground.iter().map(|p| p[1]).collect(),
            z: ground.iter().map(|p| p[2]).collect(),
        };
        let mut sorted = SegmentedPoints::default();
        group_points(
            &mut sorted,
            &mut scratch.groups,
            &soa,
            &bins,
            &counts,
            binner.segment_count(),
            Some(policy),
        );
        assert!(
            !scratch.groups.beyond.x.is_empty(),
            "the scene must have beyond-range points"
        );
        let rules = QueryRules {
            beyond: policy,
            past: past_query,
            spread,
        };
        let tally = query_grouped(
            &binner,
            &frames,
            rules,
            0.5,
            &sorted,
            &mut scratch,
            &mut out,
        );
        assert_eq!(
            tally.non_finite,
            out.iter().filter(|p| !p.is_finite()).count()
        );
        assert_eq!(tally.ground, out.iter().filter(|&&p| p >= 0.5).count());
        (seg, model, past, transforms, ground, out)
    }

    /// The query scan's model first, then the past ones with their transforms.
    fn frames_of<'a>(
        model: &'a FrameModel,
        past: &'a [FrameModel],
        transforms: &'a [Isometry3<f64>],
    ) -> Vec<QueryFrame<'a>> {
        let mut frames = vec![QueryFrame {
            model,
            transform: None,
            anchored: None,
        }];
        frames.extend(past.iter().zip(transforms).map(|(m, t)| QueryFrame {
            model: m,
            transform: Some(t),
            anchored: None,
        }));
        frames
    }

    /// The past models' components moved into the oldest past frame.
    fn moved_to_oldest(past: &[FrameModel], transforms: &[Isometry3<f64>]) -> Vec<QueryTable> {
        let to_anchor = transforms.last().unwrap();
        past.iter()
            .zip(transforms)
            .map(|(m, t)| QueryTable::moved(m, &(to_anchor * t.inverse())))
            .collect()
    }

    /// The past frames of `frames` (after the query scan's) anchored in the oldest, with
    /// their components from [`moved_to_oldest`].
    fn anchor_to_oldest<'a>(
        frames: &mut [QueryFrame<'a>],
        moved: &'a [QueryTable],
        transforms: &'a [Isometry3<f64>],
    ) {
        for (f, table) in frames[1..].iter_mut().zip(moved) {
            f.anchored = Some(AnchoredFrame {
                anchor: 7,
                table,
                transform: transforms.last().unwrap(),
            });
        }
    }

    /// Every point against its direct evaluation: at most 1 in `rare` may differ by more than
    /// 1e-4 (a point or a footprint sample within float rounding of a bin edge lands in the
    /// neighbour), the others by less; and the road comes out as ground.
    fn assert_matches(
        ground: &[[f64; 3]],
        out: &[f32],
        rare: usize,
        want: impl Fn([f64; 3]) -> f64,
    ) {
        let mut off = 0;
        let mut worst_typical: f64 = 0.0;
        for (p, &got) in ground.iter().zip(out) {
            let diff = (f64::from(got) - want(*p)).abs();
            if diff > 1e-4 {
                off += 1;
            } else {
                worst_typical = worst_typical.max(diff);
            }
        }
        assert!(
            off * rare <= ground.len(),
            "{off} of {} points differ from the direct evaluation by more than 1e-4",
            ground.len()
        );
        assert!(
            worst_typical < 1e-4,
            "worst typical difference {worst_typical}"
        );
        let ground_like = out.iter().filter(|&&p| p > 0.5).count();
        assert!(
            ground_like * 2 > out.len(),
            "the road must come out as ground ({ground_like} of {})",
            out.len()
        );
    }

    #[test]
    fn per_frame_query_matches_the_equation_evaluated_directly() {
        let (seg, model, past, transforms, ground, out) =
            query_scene(PastQuery::PerFrame, 0.0, false);
        let frames = frames_of(&model, &past, &transforms);
        assert_matches(&ground, &out, 2000, |p| {
            per_frame_reference(seg.zones(), &frames, p)
        });
    }

    #[test]
    fn regridded_query_matches_its_equation_evaluated_directly() {
        for (spread, anchored) in [(0.0, false), (0.6, false), (2.0, false), (0.6, true)] {
            let (seg, model, past, transforms, ground, out) =
                query_scene(PastQuery::Regridded, spread, anchored);
            let frames = frames_of(&model, &past, &transforms);
            let lists = reached(seg.zones(), &frames, spread);
            assert_matches(&ground, &out, 2000, |p| {
                regridded_reference(seg.zones(), &frames, &lists, p)
            });
        }
    }

    #[test]
    fn past_frames_sharing_an_anchor_are_one_run_and_one_move() {
        let (seg, model, past, transforms, ..) = query_scene(PastQuery::Regridded, 0.6, false);
        let mut frames = frames_of(&model, &past, &transforms);
        let binner = LaneBinner::new(seg.zones());
        let policy = BeyondRangePolicy::OuterRing;
        let own = RegriddedTable::new(&binner, &frames[1..], policy, 0.6);
        let moved = moved_to_oldest(&past, &transforms);
        anchor_to_oldest(&mut frames, &moved, &transforms);
        let shared = RegriddedTable::new(&binner, &frames[1..], policy, 0.6);
        assert_eq!((own.moves.len(), shared.moves.len()), (3, 1));
        let mut multi = 0;
        for s in 0..binner.segment_count() as u32 {
            let (own, shared) = (gathered(&own, s), gathered(&shared, s));
            assert!(shared.runs().len() <= 1, "segment {s}");
            multi += usize::from(own.runs().len() > 1);
            assert_eq!(listed(&own), listed(&shared), "segment {s}");
        }
        assert!(
            multi > 100,
            "only {multi} segments list more than one past frame"
        );
    }

    #[test]
    fn a_segment_gathered_into_used_buffers_is_gathered_as_into_new_ones() {
        let (seg, model, past, transforms, ..) = query_scene(PastQuery::Regridded, 0.6, false);
        let mut frames = frames_of(&model, &past, &transforms);
        let moved = moved_to_oldest(&past, &transforms);
        anchor_to_oldest(&mut frames[..3], &moved, &transforms);
        let binner = LaneBinner::new(seg.zones());
        let table = RegriddedTable::new(&binner, &frames[1..], BeyondRangePolicy::OuterRing, 1.0);
        let mut used = SegmentRuns::default();
        let (mut longer, mut shorter) = (0, 0);
        // Every segment after every other (so after longer and shorter lists alike).
        for s in (0..binner.segment_count() as u32)
            .rev()
            .chain(0..binner.segment_count() as u32)
        {
            let before = listed(&used);
            table.gather(s, &mut used);
            let fresh = gathered(&table, s);
            assert_eq!(format!("{used:?}"), format!("{fresh:?}"), "segment {s}");
            longer += usize::from(before > listed(&fresh));
            shorter += usize::from(before < listed(&fresh));
        }
        assert!(longer > 50 && shorter > 50, "{longer} {shorter}");
    }

    /// Segment `s`'s past components, gathered into new buffers.
    fn gathered(table: &RegriddedTable<'_>, s: u32) -> SegmentRuns {
        let mut out = SegmentRuns::default();
        table.gather(s, &mut out);
        out
    }

    /// Past components gathered for a segment.
    fn listed(runs: &SegmentRuns) -> usize {
        runs.runs().iter().map(|r| runs.comps(r).len()).sum()
    }

    #[test]
    fn a_wider_footprint_gives_each_segment_more_past_components() {
        let (seg, model, past, transforms, ..) = query_scene(PastQuery::Regridded, 0.0, false);
        let frames = frames_of(&model, &past, &transforms);
        let binner = LaneBinner::new(seg.zones());
        let policy = BeyondRangePolicy::OuterRing;
        let total = |spread| {
            let t = RegriddedTable::new(&binner, &frames[1..], policy, spread);
            (0..binner.segment_count() as u32)
                .map(|s| listed(&gathered(&t, s)))
                .sum::<usize>()
        };
        let all: usize = past.iter().map(|m| m.components().len()).sum();
        let (narrow, wide) = (total(0.0), total(2.0));
        // Spread 0: each component once, in its mean's segment (a few means fall near the
        // sensor and answer nowhere).
        assert!(narrow <= all && narrow * 10 >= all * 9, "{narrow} of {all}");
        assert!(wide > narrow, "{wide} against {narrow}");
    }
}
