//! The query (paper §III-E) and its multi-frame form (§III-F).
//!
//! A point's responsibilities are normalised over every component of every segment it falls
//! into, across all queried frames; its ground probability is the product of the three
//! responsibility-weighted likelihoods. With one frame this is exactly the single-frame
//! query.

use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use crate::config::BeyondRangePolicy;
use crate::fastmath::exp_nonpositive;
use crate::model::{FrameModel, GroundComponent};
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

/// Components further below the best one than this (in log-density) carry a weight under
/// e^-30 ≈ 1e-13 relative: they are skipped instead of exponentiated.
const LOG_CUTOFF: f64 = 30.0;

/// One model to query, with the transform from the query scan's ground-aligned frame into
/// that model's ground-aligned frame (`None` for the query scan's own model).
#[derive(Debug, Clone, Copy)]
pub struct QueryFrame<'a> {
    /// The fitted model.
    pub model: &'a FrameModel,
    /// Query frame → model frame.
    pub transform: Option<&'a Isometry3<f64>>,
}

/// Segment index to use for a packed bin, or `None` if that bin has no model to ask.
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

/// Ground probability of every point. `points` are in the query scan's ground-aligned frame
/// and `bins` their packed bins in it. Points near the sensor, beyond range under the
/// `NonGround` policy, or in no fitted segment of any frame get 0.
pub(crate) fn query(
    zones: &ZoneModel,
    frames: &[QueryFrame<'_>],
    points: &[[f64; 3]],
    bins: &[u32],
    policy: BeyondRangePolicy,
    out: &mut [f32],
) {
    const CHUNK: usize = 4096;
    out.par_chunks_mut(CHUNK)
        .zip(points.par_chunks(CHUNK).zip(bins.par_chunks(CHUNK)))
        .for_each(|(out, (points, bins))| {
            let mut cand: Vec<(f64, &GroundComponent)> = Vec::with_capacity(64);
            for ((o, p), &b) in out.iter_mut().zip(points).zip(bins) {
                *o = 0.0;
                // Near the sensor (or beyond range, if so configured) is decided by the
                // current scan alone: history never turns such a point into ground.
                if segment_of(b, policy).is_none() {
                    continue;
                }
                cand.clear();
                let mut max = f64::NEG_INFINITY;
                for f in frames {
                    let (q, seg) = match f.transform {
                        None => (*p, segment_of(b, policy)),
                        Some(t) => {
                            let q = t * Point3::new(p[0], p[1], p[2]);
                            let s = segment_of(pack(zones.bin(q.x, q.y)), policy);
                            ([q.x, q.y, q.z], s)
                        }
                    };
                    let Some(seg) = seg else { continue };
                    for c in f.model.segment(seg) {
                        let l = c.eval.log_density(q[0], q[1], q[2]);
                        max = max.max(l);
                        cand.push((l, c));
                    }
                }
                if cand.is_empty() {
                    continue;
                }
                let (mut sum, mut lf, mut lo, mut le) = (0.0, 0.0, 0.0, 0.0);
                for &(l, c) in &cand {
                    let d = l - max;
                    if d < -LOG_CUTOFF {
                        continue;
                    }
                    let w = f64::from(exp_nonpositive(d as f32));
                    sum += w;
                    lf += w * c.flatness;
                    lo += w * c.orientation;
                    le += w * c.elevation;
                }
                let p = (lf / sum) * (lo / sum) * (le / sum);
                *o = p.clamp(0.0, 1.0) as f32;
            }
        });
}
