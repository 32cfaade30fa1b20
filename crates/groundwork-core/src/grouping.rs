//! The scan's binned points grouped by segment, once for the fit and the query together.
//!
//! The fit wants the in-range points of each segment contiguous (f64, structure of
//! arrays); the query wants the same groups plus, under the `OuterRing` policy, the
//! beyond-range points answered by the outer ring, and for every input point its place
//! among the grouped ones (to gather the probabilities back into input order). One
//! counting sort serves both: the query reads its coordinates from the fit's groups, and
//! only the beyond-range points are stored apart. The sort runs as two tasks, one per
//! core: the first copies the segments below a split, the second the segments from the
//! split on while it writes every point's place (see [`group_points`]). On one thread
//! one task does it all, in one pass over the bins.

use crate::config::BeyondRangePolicy;
use crate::zones::{BEYOND, NEAR};

/// Points of one scan in the ground-aligned frame, grouped by segment (structure of arrays).
#[derive(Debug, Clone, Default)]
pub struct SegmentedPoints {
    /// x of every in-range point, segment by segment.
    pub xs: Vec<f64>,
    /// y, likewise.
    pub ys: Vec<f64>,
    /// z, likewise.
    pub zs: Vec<f64>,
    /// Points of segment s are at `start[s]..start[s+1]`.
    pub start: Vec<u32>,
}

/// A scan's points in the ground-aligned frame, in input order (structure of arrays: the
/// transform writes whole vectors of each coordinate).
#[derive(Debug, Clone, Default)]
pub(crate) struct GroundPoints {
    pub(crate) x: Vec<f64>,
    pub(crate) y: Vec<f64>,
    pub(crate) z: Vec<f64>,
}

impl GroundPoints {
    pub(crate) fn resize(&mut self, n: usize) {
        for v in [&mut self.x, &mut self.y, &mut self.z] {
            v.resize(n, 0.0);
        }
    }

    pub(crate) fn truncate(&mut self, n: usize) {
        for v in [&mut self.x, &mut self.y, &mut self.z] {
            v.truncate(n);
        }
    }
}

/// Points per segment of a scan, in range and beyond it: the counting sort's first pass,
/// taken while binning, a chunk of the scan per task (so that the sort does not read the
/// bins twice).
#[derive(Debug, Clone, Default)]
pub(crate) struct SegmentCounts {
    /// In-range points of segment s at `[s]`, beyond-range points whose outer-ring segment
    /// is s at `[segments + s]`.
    counts: Vec<u32>,
}

impl SegmentCounts {
    /// The counts of `bins` (packed) in a zone model of `segments` segments.
    pub(crate) fn of(bins: &[u32], segments: usize) -> Self {
        let mut counts = vec![0; 2 * segments];
        // Consecutive points mostly share a segment (a sensor sweeps one sector after the
        // other): a run is counted once. A memory increment per point waited on the
        // previous one's store.
        for (b, run) in runs(bins) {
            if let Some(key) = bin_key(b, segments) {
                counts[key] += run.len() as u32;
            }
        }
        Self { counts }
    }

    /// Points in range and points beyond it (the bins that are not `NEAR`).
    pub(crate) fn totals(&self) -> (usize, usize) {
        let (inside, outside) = self.counts.split_at(self.counts.len() / 2);
        let sum = |c: &[u32]| c.iter().map(|&n| n as usize).sum::<usize>();
        (sum(inside), sum(outside))
    }

    /// The counts of two chunks of one scan together.
    pub(crate) fn add(mut self, o: &Self) -> Self {
        if self.counts.is_empty() {
            return o.clone();
        }
        for (a, b) in self.counts.iter_mut().zip(&o.counts) {
            *a += b;
        }
        self
    }

    /// The counting sort's offsets: `start[s]..start[s+1]` will hold the in-range points of
    /// segment s. Returns their number.
    pub(crate) fn offsets(&self, segments: usize, start: &mut Vec<u32>) -> usize {
        prefix_sums(&self.counts[..self.counts.len() / 2], segments, start)
    }

    /// Offsets of the beyond-range points grouped by the outer-ring segment that answers for
    /// them: `start[s]..start[s+1]` for segment s. Returns their number.
    pub(crate) fn beyond_offsets(&self, segments: usize, start: &mut Vec<u32>) -> usize {
        prefix_sums(&self.counts[self.counts.len() / 2..], segments, start)
    }
}

/// A packed bin's key among the counts: its segment for a point in range, `segments` plus
/// the outer-ring segment that answers for it beyond range, `None` near the sensor.
#[inline(always)]
fn bin_key(b: u32, segments: usize) -> Option<usize> {
    let beyond = if b & BEYOND != 0 { segments } else { 0 };
    (b != NEAR).then_some((b & !BEYOND) as usize + beyond)
}

/// `start` = 0 and the running sums of the first `segments` counts; returns the last.
fn prefix_sums(counts: &[u32], segments: usize, start: &mut Vec<u32>) -> usize {
    start.clear();
    start.push(0);
    let mut total = 0;
    for s in 0..segments {
        total += counts.get(s).copied().unwrap_or(0);
        start.push(total);
    }
    total as usize
}

/// An input point that no model answers for.
pub(crate) const UNQUERIED: u32 = u32::MAX;

/// What the query needs beside the fit's groups.
#[derive(Debug, Default)]
pub(crate) struct QueryGroups {
    /// Per input point, its place among the grouped points (`UNQUERIED` if it has none):
    /// in-range points are numbered as in the fit's groups, beyond-range points after them.
    pub(crate) place: Vec<u32>,
    /// Beyond-range points grouped by the segment that answers for them (outer ring).
    pub(crate) beyond: GroundPoints,
    /// Beyond-range points of segment s are at `beyond_start[s]..beyond_start[s+1]`.
    pub(crate) beyond_start: Vec<u32>,
}

/// Share of the in-range points the first task copies: the second also writes every
/// point's place. Measured on KITTI scans (scratch timers per task, shares 0.55–0.8): the
/// two tasks take the same time at 0.75, 0.28–0.29 ms each.
const FIRST_TASK_SHARE: f64 = 0.75;

/// Groups the binned points (`bins` packed as [`crate::zones::LaneBinner::bin_block`]
/// gives them, `counts` their per-segment counts) for the fit into `sorted` and, with a
/// policy, for the query into `q`. Input order is kept within every group.
pub(crate) fn group_points(
    sorted: &mut SegmentedPoints,
    q: &mut QueryGroups,
    ground: &GroundPoints,
    bins: &[u32],
    counts: &SegmentCounts,
    segments: usize,
    policy: Option<BeyondRangePolicy>,
) {
    let total = counts.offsets(segments, &mut sorted.start);
    for v in [&mut sorted.xs, &mut sorted.ys, &mut sorted.zs] {
        v.resize(total, 0.0);
    }
    let start = &sorted.start;
    // The split: the first segment whose group starts past the first task's share. On one
    // thread the task that must read every point (the second, with a policy) takes all
    // segments, and the other, empty, reads nothing: one pass over the bins, not two.
    let split = if rayon::current_num_threads() == 1 {
        if policy.is_some() { 0 } else { segments }
    } else {
        let share = (total as f64 * FIRST_TASK_SHARE) as u32;
        start[..segments]
            .iter()
            .position(|&a| a >= share)
            .unwrap_or(segments)
    };
    let at = start[split] as usize;
    let (x0, x1) = sorted.xs.split_at_mut(at);
    let (y0, y1) = sorted.ys.split_at_mut(at);
    let (z0, z1) = sorted.zs.split_at_mut(at);
    let first = Copy {
        segments: 0..split,
        start,
        out: [x0, y0, z0],
    };
    let second = Copy {
        segments: split..segments,
        start,
        out: [x1, y1, z1],
    };
    match policy {
        None => {
            rayon::join(|| first.run(bins, ground), || second.run(bins, ground));
        }
        Some(policy) => {
            let outer_ring = policy == BeyondRangePolicy::OuterRing;
            let beyond = if outer_ring {
                counts.beyond_offsets(segments, &mut q.beyond_start)
            } else {
                q.beyond_start.clear();
                0
            };
            q.beyond.resize(beyond);
            q.place.resize(bins.len(), UNQUERIED);
            rayon::join(
                || first.run(bins, ground),
                || second.run_with_places(bins, ground, outer_ring, q, total),
            );
        }
    }
}

/// One task's share of the grouping: the in-range points of `segments`, copied into
/// `out`, which starts where the first of them goes.
struct Copy<'a> {
    segments: std::ops::Range<usize>,
    start: &'a [u32],
    out: [&'a mut [f64]; 3],
}

impl Copy<'_> {
    /// Copies the task's points.
    fn run(self, bins: &[u32], ground: &GroundPoints) {
        let (lo, hi) = (self.segments.start, self.segments.end);
        if lo == hi {
            return;
        }
        let base = self.start[lo] as usize;
        let mut cursor: Vec<usize> = self.start[lo..hi]
            .iter()
            .map(|&a| a as usize - base)
            .collect();
        let [xs, ys, zs] = self.out;
        for (b, run) in runs(bins) {
            let seg = b as usize;
            if b & BEYOND != 0 || seg < lo || seg >= hi {
                continue;
            }
            let j = cursor[seg - lo];
            cursor[seg - lo] = j + run.len();
            copy_run([xs, ys, zs], j, ground, run);
        }
    }

    /// Copies the task's points and writes every point's place for the query (in-range
    /// points numbered as the fit's groups, beyond-range ones from `total` on, into the
    /// beyond groups under `outer_ring`).
    fn run_with_places(
        self,
        bins: &[u32],
        ground: &GroundPoints,
        outer_ring: bool,
        q: &mut QueryGroups,
        total: usize,
    ) {
        let (lo, hi) = (self.segments.start, self.segments.end);
        let segments = self.start.len() - 1;
        let base = self.start[lo] as usize;
        // Keys 0..segments: in-range points of a segment; segments..2·segments: the
        // beyond-range points it answers for. A cursor per key, as a place.
        let mut cursor: Vec<usize> = self.start[..segments]
            .iter()
            .map(|&a| a as usize)
            .chain(
                q.beyond_start
                    .iter()
                    .take(segments)
                    .map(|&a| total + a as usize),
            )
            .collect();
        let [xs, ys, zs] = self.out;
        let QueryGroups { place, beyond, .. } = q;
        let GroundPoints {
            x: bx,
            y: by,
            z: bz,
        } = beyond;
        for (b, run) in runs(bins) {
            // Beyond-range points are asked only under the outer-ring policy.
            let key = bin_key(b, segments).filter(|&k| k < segments || outer_ring);
            let Some(key) = key else {
                place[run].fill(UNQUERIED);
                continue;
            };
            let j = cursor[key];
            cursor[key] = j + run.len();
            if key >= segments {
                copy_run([bx, by, bz], j - total, ground, run.clone());
            } else if key >= lo && key < hi {
                copy_run([xs, ys, zs], j - base, ground, run.clone());
            }
            for (p, k) in place[run].iter_mut().zip(j as u32..) {
                *p = k;
            }
        }
    }
}

/// The runs of equal bins in `bins`: a sensor sweeps one sector after the other, so
/// consecutive points mostly share a segment (about 20 to a run on KITTI scans). A run is
/// looked up and copied once, where a point at a time tested its key and moved a cursor
/// (one thread: 0.94–0.95 of the scan's time on KITTI, 1.00 on the same scans shuffled).
fn runs(bins: &[u32]) -> impl Iterator<Item = (u32, std::ops::Range<usize>)> + '_ {
    let mut i = 0;
    std::iter::from_fn(move || {
        let &b = bins.get(i)?;
        let len = bins[i..]
            .iter()
            .position(|&c| c != b)
            .unwrap_or(bins.len() - i);
        let run = i..i + len;
        i += len;
        Some((b, run))
    })
}

/// Copies the coordinates of input points `run` to `out` from position `at` on.
#[inline(always)]
fn copy_run(out: [&mut [f64]; 3], at: usize, ground: &GroundPoints, run: std::ops::Range<usize>) {
    let to = at..at + run.len();
    for (o, v) in out.into_iter().zip([&ground.x, &ground.y, &ground.z]) {
        for (o, v) in o[to.clone()].iter_mut().zip(&v[run.clone()]) {
            *o = *v;
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

    use super::*;

    #[test]
    fn segment_counts_summed_over_chunks_give_the_sorts_offsets() {
        // In range, near, and beyond range (bit 31) in runs and alone, over 5 segments.
        let bins: Vec<u32> = [0, 0, 3, NEAR, 3, 4 | BEYOND, 4 | BEYOND, 1, NEAR, BEYOND, 4]
            .into_iter()
            .cycle()
            .take(1000)
            .collect();
        let whole = SegmentCounts::of(&bins, 5);
        let summed = bins
            .chunks(37)
            .map(|c| SegmentCounts::of(c, 5))
            .fold(SegmentCounts::default(), |a, b| a.add(&b));
        for beyond in [false, true] {
            let mut want = vec![0u32; 6];
            for &b in &bins {
                if b != NEAR && (b & BEYOND != 0) == beyond {
                    want[(b & !BEYOND) as usize + 1] += 1;
                }
            }
            for k in 1..6 {
                want[k] += want[k - 1];
            }
            let (mut a, mut b) = (Vec::new(), Vec::new());
            let offsets = |c: &SegmentCounts, start: &mut Vec<u32>| {
                if beyond {
                    c.beyond_offsets(5, start)
                } else {
                    c.offsets(5, start)
                }
            };
            assert_eq!(offsets(&whole, &mut a), want[5] as usize);
            assert_eq!(offsets(&summed, &mut b), want[5] as usize);
            assert_eq!(a, want);
            assert_eq!(b, want);
        }
    }

    /// Bins over `segments` segments in runs and alone, near and beyond range among them,
    /// with coordinates that name the point (x = index).
    fn scan(segments: u32, n: usize) -> (Vec<u32>, GroundPoints) {
        let bins: Vec<u32> = (0..n as u32)
            .map(|i| match i % 23 {
                0 => NEAR,
                1 | 2 => (i / 7 % segments) | BEYOND,
                k if k < 12 => i / 40 % segments,
                _ => (i * 7919) % segments,
            })
            .collect();
        let ground = GroundPoints {
            x: (0..n).map(|i| i as f64).collect(),
            y: (0..n).map(|i| -(i as f64)).collect(),
            z: (0..n).map(|i| i as f64 * 0.5).collect(),
        };
        (bins, ground)
    }

    #[test]
    fn one_sort_gives_the_fits_groups_and_the_querys_places() {
        // Two tasks split by share on two threads, one task on one thread.
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(groups_and_places_match_a_stable_sort);
        }
    }

    fn groups_and_places_match_a_stable_sort() {
        for segments in [1u32, 5, 37, 200] {
            let (bins, ground) = scan(segments, 5000);
            let counts = SegmentCounts::of(&bins, segments as usize);
            // The reference: a stable sort by segment, in range and beyond apart.
            let by_segment = |beyond: bool| -> Vec<usize> {
                let mut idx: Vec<usize> = (0..bins.len())
                    .filter(|&i| bins[i] != NEAR && (bins[i] & BEYOND != 0) == beyond)
                    .collect();
                idx.sort_by_key(|&i| bins[i] & !BEYOND);
                idx
            };
            let (inside, outside) = (by_segment(false), by_segment(true));
            for policy in [
                None,
                Some(BeyondRangePolicy::OuterRing),
                Some(BeyondRangePolicy::NonGround),
            ] {
                let (mut sorted, mut q) = (SegmentedPoints::default(), QueryGroups::default());
                let s = segments as usize;
                group_points(&mut sorted, &mut q, &ground, &bins, &counts, s, policy);
                let xs: Vec<f64> = inside.iter().map(|&i| i as f64).collect();
                assert_eq!(sorted.xs, xs, "{segments} segments, {policy:?}");
                let ys: Vec<f64> = inside.iter().map(|&i| -(i as f64)).collect();
                assert_eq!(sorted.ys, ys);
                let zs: Vec<f64> = inside.iter().map(|&i| i as f64 * 0.5).collect();
                assert_eq!(sorted.zs, zs);
                for w in sorted.start.windows(2).enumerate() {
                    let (seg, w) = w;
                    for &i in &inside[w[0] as usize..w[1] as usize] {
                        assert_eq!(bins[i], seg as u32);
                    }
                }
                let Some(policy) = policy else { continue };
                let mut want = vec![UNQUERIED; bins.len()];
                for (j, &i) in inside.iter().enumerate() {
                    want[i] = j as u32;
                }
                if policy == BeyondRangePolicy::OuterRing {
                    for (j, &i) in outside.iter().enumerate() {
                        want[i] = (inside.len() + j) as u32;
                    }
                    let bx: Vec<f64> = outside.iter().map(|&i| i as f64).collect();
                    assert_eq!(q.beyond.x, bx);
                    let by: Vec<f64> = outside.iter().map(|&i| -(i as f64)).collect();
                    assert_eq!(q.beyond.y, by);
                    let bz: Vec<f64> = outside.iter().map(|&i| i as f64 * 0.5).collect();
                    assert_eq!(q.beyond.z, bz);
                    assert_eq!(q.beyond_start.last().copied(), Some(outside.len() as u32));
                } else {
                    assert!(q.beyond.x.is_empty());
                }
                assert_eq!(q.place, want, "{segments} segments, {policy:?}");
            }
        }
    }
}
