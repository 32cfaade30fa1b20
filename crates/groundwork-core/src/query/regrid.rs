//! The past frames' components regridded into the query scan
//! ([`PastQuery::Regridded`](crate::config::PastQuery::Regridded)).
//!
//! Once per query, each past component's mean and horizontal σ are moved into the query
//! scan's ground-aligned frame, and the component is listed in every query-scan segment its
//! footprint reaches: the segments of its mean and of the mean ± `spread` σ along x, y and
//! the diagonals. A point is then normalised against its own segment's components and that
//! segment's past list, one run per past frame, each component evaluated in its own frame on
//! the point moved there (the per-frame query's arithmetic): no binning per point and past
//! frame. The per-frame query (the paper's) bins every point in every past frame;
//! a vector of neighbours straddles a past cell's edge in 4 of 10 frames there, and each
//! side costs a full vector's evaluation.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::{EMPTY, LANES, Move, NEAR, QComp, QueryFrame, answering_segment};
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

/// The past frames' components per query-scan segment. A component stays in its own
/// frame's form and a vector of points is moved into that frame to evaluate it, exactly as
/// in the per-frame query: only the rule for which components answer differs.
#[derive(Debug, Default)]
pub(super) struct RegriddedTable {
    /// Query scan → past frame, per past frame.
    pub(super) moves: Vec<Move>,
    /// Runs of segment s are `seg_start[s]..seg_start[s+1]`.
    seg_start: Vec<u32>,
    runs: Vec<PastRun>,
    comps: Vec<QComp>,
}

/// Components of one past frame for one segment: `comps[start..end]`, and the largest
/// log-density they reach.
#[derive(Debug, Clone, Copy)]
pub(super) struct PastRun {
    pub(super) frame: u32,
    start: u32,
    end: u32,
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

    /// The table for the past frames (each with its query → past transform): per segment,
    /// the components whose footprint reaches it, oldest frame first, in each frame's order.
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
        // (and the sums' rounding) does not depend on the threads, and each frame's
        // components are one run.
        let segments = binner.segment_count();
        let mut count = vec![0u32; segments + 1];
        for &(seg, _) in keyed.iter().flatten() {
            count[seg as usize + 1] += 1;
        }
        for s in 0..segments {
            count[s + 1] += count[s];
        }
        let mut next = count.clone();
        let mut comps = vec![QComp::default(); count[segments] as usize];
        let mut frame_of = vec![0u32; comps.len()];
        for (f, (frame, keys)) in past.iter().zip(&keyed).enumerate() {
            let table = frame.model.query_table();
            for &(seg, i) in keys {
                let at = &mut next[seg as usize];
                comps[*at as usize] = table.comps[i as usize];
                frame_of[*at as usize] = f as u32;
                *at += 1;
            }
        }
        let mut seg_start = Vec::with_capacity(segments + 1);
        let mut runs = Vec::new();
        for w in count.windows(2) {
            seg_start.push(runs.len() as u32);
            let (mut a, b) = (w[0] as usize, w[1] as usize);
            while a < b {
                let frame = frame_of[a];
                let end = a + frame_of[a..b].iter().take_while(|&&f| f == frame).count();
                let peak = comps[a..end].iter().map(|q| q.c).fold(EMPTY, f32::max);
                runs.push(PastRun {
                    frame,
                    start: a as u32,
                    end: end as u32,
                    peak,
                });
                a = end;
            }
        }
        seg_start.push(runs.len() as u32);
        let moves = past
            .iter()
            .map(|f| f.transform.map_or(Move::IDENTITY, Move::new))
            .collect();
        Self {
            moves,
            seg_start,
            runs,
            comps,
        }
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
