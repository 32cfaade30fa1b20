//! The detector: a scan and its ground probabilities in, proposals and a cluster id per
//! point out.

use std::time::{Duration, Instant};

use groundwork_core::{
    ConfigError, GroundFrame, PointXyz, SegmentError, SegmenterConfig, check_finite,
};
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use thiserror::Error;

use rayon::prelude::*;

use crate::bbox::{Rect, RectScratch, min_area_rect};
use crate::cluster::{ClusterGrid, Entry};
use crate::config::DetectorConfig;
use crate::ground_map::GroundMap;

thread_local! {
    /// The boxes' scratch (a cluster's footprint, the hull's buffers), one per thread that
    /// fits boxes, kept from scan to scan.
    static RECT_SCRATCH: std::cell::RefCell<(Vec<[f32; 2]>, RectScratch)> = Default::default();
}

/// Why a scan could not be processed (the detector's state is unchanged).
#[derive(Debug, Error)]
pub enum DetectError {
    /// The points themselves (non-finite, too many).
    #[error(transparent)]
    Points(#[from] SegmentError),
    /// Not one probability per point.
    #[error("{got} ground probabilities for {expected} points")]
    ProbabilityCount {
        /// Points.
        expected: usize,
        /// Probabilities.
        got: usize,
    },
    /// A probability outside [0, 1] (or NaN).
    #[error("ground probability {value} of point {index} is not in [0, 1]")]
    BadProbability {
        /// The point.
        index: usize,
        /// Its value.
        value: f32,
    },
}

/// What makes a cluster plainly not an object (a bit set; 0: object-like).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct ProposalFlags(pub u32);

impl ProposalFlags {
    /// Long and thin: a wall, fence or hedge row (`wall_length`, `wall_width`).
    pub const WALL: Self = Self(1);
    /// Longer than `max_length`: building fronts, vegetation masses, merged rows.
    pub const LARGE: Self = Self(2);
    /// Taller than `max_object_height`: trees, poles, buildings.
    pub const TALL: Self = Self(4);
    /// Lowest point more than `floating_height` above the ground: crowns, signs.
    pub const FLOATING: Self = Self(8);
    /// More points than `max_points`.
    pub const MANY_POINTS: Self = Self(16);
    const NAMES: [(Self, &'static str); 5] = [
        (Self::WALL, "wall"),
        (Self::LARGE, "large"),
        (Self::TALL, "tall"),
        (Self::FLOATING, "floating"),
        (Self::MANY_POINTS, "many_points"),
    ];

    /// Whether every flag of `f` is set.
    pub fn contains(self, f: Self) -> bool {
        self.0 & f.0 == f.0
    }

    /// No flag: the cluster looks like an object.
    pub fn is_object_like(self) -> bool {
        self.0 == 0
    }

    /// The names of the flags set.
    pub fn names(self) -> impl Iterator<Item = &'static str> {
        Self::NAMES
            .into_iter()
            .filter(move |(f, _)| self.contains(*f))
            .map(|(_, n)| n)
    }

    /// A proposal's class for viewers and ROS messages: `object`, or the names of its
    /// flags (`wall`, `tall+floating`). Clusters that are plainly not objects are
    /// labelled, not dropped.
    pub fn class_name(self) -> String {
        if self.is_object_like() {
            "object".into()
        } else {
            self.names().collect::<Vec<_>>().join("+")
        }
    }
}

impl std::ops::BitOrAssign for ProposalFlags {
    fn bitor_assign(&mut self, o: Self) {
        self.0 |= o.0;
    }
}

impl Serialize for ProposalFlags {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.names())
    }
}

impl<'de> Deserialize<'de> for ProposalFlags {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let names = Vec::<String>::deserialize(d)?;
        let mut f = Self::default();
        for n in &names {
            let (flag, _) = Self::NAMES
                .into_iter()
                .find(|(_, name)| name == n)
                .ok_or_else(|| serde::de::Error::custom(format!("unknown flag {n:?}")))?;
            f |= flag;
        }
        Ok(f)
    }
}

/// One object proposal. Lengths in metres, angles in radians, all in the sensor's
/// ground-aligned frame: x forward, y left, z up, origin on the ground below the sensor.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Proposal {
    /// 1, 2, … within the scan, nearest first (horizontal range of the centroid): the id
    /// its points carry in the cluster ids.
    pub id: u32,
    /// Mean of its points.
    pub centroid: [f32; 3],
    /// Centre of the oriented box in the ground plane (x, y).
    pub center: [f32; 2],
    /// Heading of the box's long side from the x axis, in (−π/2, π/2].
    pub yaw: f32,
    /// Long side of the box.
    pub length: f32,
    /// Short side of the box.
    pub width: f32,
    /// Local ground height (z) below the box centre; the cluster's lowest point where no
    /// ground was seen within `ground_search` cells.
    pub ground_z: f32,
    /// Lowest point above the local ground.
    pub bottom: f32,
    /// Highest point above the local ground: the object's height.
    pub height: f32,
    /// Points in the cluster.
    pub points: u32,
    /// Why it is plainly not an object, if it is not.
    pub flags: ProposalFlags,
}

/// The output for one scan.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Detections {
    /// Proposals, in id order.
    pub proposals: Vec<Proposal>,
    /// Per input point, in input order: its proposal's id, 0 for ground and unclustered
    /// points.
    pub clusters: Vec<u32>,
}

/// What one scan cost and held.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct DetectionReport {
    /// Non-ground points clustered.
    pub candidates: usize,
    /// Uncertain ground points that joined a cluster.
    pub joined: usize,
    /// Clusters found before the size filter.
    pub clusters: usize,
    /// Clusters dropped for having fewer than `min_points`.
    pub dropped_small: usize,
    /// Wall time.
    #[serde(skip)]
    pub time: Duration,
}

/// A cluster's measures.
#[derive(Debug, Clone, Copy)]
struct Extent {
    count: u32,
    sum: [f64; 3],
    z_min: f32,
    z_max: f32,
    /// Its lowest input index (the tie-break of the id order).
    first: u32,
}

impl Extent {
    /// The measures of a cluster's members (sums in their order).
    fn of<'a>(members: impl Iterator<Item = &'a Maybe>) -> Self {
        let mut e = Self {
            count: 0,
            sum: [0.0; 3],
            z_min: f32::MAX,
            z_max: f32::MIN,
            first: u32::MAX,
        };
        for m in members {
            e.count += 1;
            for (sum, v) in e.sum.iter_mut().zip(m.xyz) {
                *sum += f64::from(v);
            }
            e.z_min = e.z_min.min(m.xyz[2]);
            e.z_max = e.z_max.max(m.xyz[2]);
            e.first = e.first.min(m.index);
        }
        e
    }
}

/// A point that may belong to a cluster: its index, where it is, whether it is ground.
#[derive(Debug, Clone, Copy, Default)]
struct Maybe {
    index: u32,
    xyz: [f32; 3],
    ground: bool,
}

/// Points grouped by cluster (a stable counting sort): cluster c's are
/// `items[start[c]..start[c + 1]]`, in input order.
#[derive(Debug, Default)]
struct Grouped {
    start: Vec<usize>,
    items: Vec<Maybe>,
}

impl Grouped {
    /// Groups `labelled` (a point and its cluster, `u32::MAX` for none) by cluster, of
    /// `clusters` clusters.
    fn group<'a>(
        &mut self,
        labelled: impl Iterator<Item = (&'a Maybe, u32)> + Clone,
        clusters: usize,
    ) {
        // Points of no cluster (`u32::MAX`) are left out; a label beyond `clusters` (none
        // is) would be too.
        let labelled = labelled.filter(move |&(_, c)| (c as usize) < clusters);
        self.start.clear();
        self.start.resize(clusters + 1, 0);
        for (_, c) in labelled.clone() {
            self.start[c as usize + 1] += 1;
        }
        for k in 1..self.start.len() {
            self.start[k] += self.start[k - 1];
        }
        self.items.clear();
        self.items.resize(self.start[clusters], Maybe::default());
        let mut slot = self.start.clone();
        for (m, c) in labelled {
            let s = &mut slot[c as usize];
            self.items[*s] = *m;
            *s += 1;
        }
    }

    /// Cluster c's points.
    fn of(&self, c: u32) -> &[Maybe] {
        &self.items[self.start[c as usize]..self.start[c as usize + 1]]
    }
}

/// The candidates of `batches` and their clusters (`labels`, in the same order).
fn labelled<'a>(
    batches: &'a [Batch],
    labels: &'a [u32],
) -> impl Iterator<Item = (&'a Maybe, u32)> + Clone {
    let candidates = batches.iter().flat_map(|b| b.candidates.iter());
    candidates.zip(labels.iter().copied())
}

/// The members of the clusters: the candidates (in two parts, the batches' first ones and
/// the others, grouped on two cores), then the uncertain ground points joining them.
#[derive(Debug, Default)]
struct Members {
    parts: [Grouped; 2],
    joiners: Grouped,
}

impl Members {
    /// How many candidates cluster c has.
    fn candidates(&self, c: u32) -> usize {
        self.parts.iter().map(|p| p.of(c).len()).sum()
    }

    /// Cluster c's members in input order, then the uncertain ground points joining it.
    fn of(&self, c: u32) -> impl Iterator<Item = &Maybe> {
        let [a, b] = &self.parts;
        a.of(c).iter().chain(b.of(c)).chain(self.joiners.of(c))
    }
}

/// Points per piece of the first passes: several pieces per core, so that a core that
/// wakes late still finds work.
const PIECE: usize = 16_384;

/// One piece of the scan in the first passes.
#[derive(Debug, Default)]
struct Piece {
    /// Its ground points: their ground-map cell and height.
    ground: Vec<(u32, f32)>,
    /// Its non-ground and uncertain ground points.
    maybe: Vec<Maybe>,
    /// Every point of the piece finite, every probability in [0, 1].
    valid: bool,
}

/// Non-ground and uncertain ground points per batch of the second pass. They crowd into a
/// few pieces (on a KITTI scan the first two pieces hold most of them): batches of equal
/// size keep both cores busy where pieces left one idle.
const BATCH: usize = 2048;

/// One batch of the second pass: up to [`BATCH`] of one piece's non-ground and uncertain
/// ground points.
#[derive(Debug, Default)]
struct Batch {
    /// Its piece, and where in the piece's points it starts.
    piece: usize,
    start: usize,
    /// Those of its points in the height band: to cluster, and to join.
    candidates: Vec<Maybe>,
    joiners: Vec<Maybe>,
    /// The candidates' clustering cells (numbered within the batch).
    entries: Vec<Entry>,
}

/// The detector, with scratch reused from scan to scan.
#[derive(Debug)]
pub struct Detector {
    cfg: DetectorConfig,
    frame: GroundFrame,
    threshold: f32,
    min_range: f32,
    grid: ClusterGrid,
    ground: GroundMap,
    pieces: Vec<Piece>,
    batches: Vec<Batch>,
    /// The uncertain ground points in the height band, and their coordinates (looked up
    /// while the candidates are grouped).
    joiners: Vec<Maybe>,
    joiner_xyz: Vec<[f32; 3]>,
    labels: Vec<u32>,
    touched: Vec<Option<u32>>,
    /// The clusters' members, grouped by cluster.
    members: Members,
    /// The clusters kept, in cluster order, and their measures and boxes.
    live: Vec<u32>,
    measured: Vec<(Extent, Rect)>,
}

impl Detector {
    /// Works from now on in the ground-aligned frame of a sensor mounted by `mount` (the
    /// segmenter's mount in use, where it corrects `sensor.mount`).
    pub fn set_mount(&mut self, mount: &groundwork_core::Pose) {
        self.frame = self.frame.with_mount(mount);
    }

    /// A detector for the sensor and segmenter `segmenter` describes (mount, ego radius,
    /// threshold and minimum range where `cfg` leaves them open).
    pub fn new(cfg: DetectorConfig, segmenter: &SegmenterConfig) -> Result<Self, ConfigError> {
        cfg.validate()?;
        let frame = GroundFrame::from_config(segmenter)?;
        let threshold = cfg
            .ground_threshold
            .unwrap_or(segmenter.decision_threshold());
        let min_range = cfg
            .min_range
            .unwrap_or(segmenter.zones.min_range as f32)
            .max(segmenter.sensor.ego_radius as f32);
        Ok(Self {
            grid: ClusterGrid::new(cfg.cell_size, cfg.max_range),
            ground: GroundMap::new(cfg.ground_cell, cfg.max_range, cfg.ground_search),
            cfg,
            frame,
            threshold,
            min_range,
            pieces: Vec::new(),
            batches: Vec::new(),
            joiners: Vec::new(),
            joiner_xyz: Vec::new(),
            labels: Vec::new(),
            touched: Vec::new(),
            members: Members::default(),
            live: Vec::new(),
            measured: Vec::new(),
        })
    }

    /// Its configuration.
    pub fn config(&self) -> &DetectorConfig {
        &self.cfg
    }

    /// The probability at or above which a point is ground.
    pub fn threshold(&self) -> f32 {
        self.threshold
    }

    /// Proposals for one scan (sensor frame) and its ground probabilities (one per point,
    /// input order), written into `out`.
    pub fn detect<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        probabilities: &[f32],
        out: &mut Detections,
    ) -> Result<DetectionReport, DetectError> {
        // On a thread of rayon's pool (a no-op when already on one): the parallel steps
        // then run as joins there, instead of each sending its work to the pool while
        // the calling thread sleeps until it is done.
        rayon::scope(|_| self.detect_on_pool(points, probabilities, out))
    }

    /// [`Detector::detect`], on a thread of the pool. Never inlined: profiles and the
    /// aarch64 check of its vector share (`scripts/vector_share.py`) find it by name.
    #[inline(never)]
    fn detect_on_pool<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        probabilities: &[f32],
        out: &mut Detections,
    ) -> Result<DetectionReport, DetectError> {
        let t = Instant::now();
        if probabilities.len() != points.len() {
            return Err(DetectError::ProbabilityCount {
                expected: points.len(),
                got: probabilities.len(),
            });
        }
        self.frame.check_size(points)?;
        let cfg = &self.cfg;
        let (thr, join) = (self.threshold, cfg.join_probability);
        let (min2, max2) = (self.min_range.powi(2), cfg.max_range.powi(2));

        // One pass over the scan, in pieces on all cores: into the ground-aligned frame;
        // ground points noted for the local ground map, the others (and uncertain ground)
        // kept for the next step.
        let pieces = points.len().div_ceil(PIECE);
        if self.pieces.len() < pieces {
            self.pieces.resize_with(pieces, Piece::default);
        }
        let (frame, ground) = (&self.frame, &self.ground);
        self.pieces[..pieces]
            .par_iter_mut()
            .zip(points.par_chunks(PIECE))
            .zip(probabilities.par_chunks(PIECE))
            .enumerate()
            .for_each(|(k, ((piece, points), probabilities))| {
                piece.ground.clear();
                piece.maybe.clear();
                // The input's checks in the same pass, branch-free: a bad value only
                // marks the piece, and the culprit is looked for after the pass.
                let mut valid = true;
                for (i, (p, &prob)) in points.iter().zip(probabilities).enumerate() {
                    let xyz = p.xyz();
                    valid &= xyz[0].is_finite() & xyz[1].is_finite() & xyz[2].is_finite();
                    valid &= (0.0..=1.0).contains(&prob);
                    let q = frame.to_ground(xyz);
                    let r2 = q[0] * q[0] + q[1] * q[1];
                    if !(min2..=max2).contains(&r2) {
                        continue;
                    }
                    let is_ground = prob >= thr;
                    if is_ground && let Some(c) = ground.cell(q[0], q[1]) {
                        piece.ground.push((c, q[2]));
                    }
                    if !is_ground || prob < join {
                        piece.maybe.push(Maybe {
                            index: (k * PIECE + i) as u32,
                            xyz: q,
                            ground: is_ground,
                        });
                    }
                }
                piece.valid = valid;
            });
        if self.pieces[..pieces].iter().any(|p| !p.valid) {
            // The culprit, probabilities before coordinates: pieces are scratch, nothing
            // else was touched yet.
            if let Some((index, &value)) = probabilities
                .iter()
                .enumerate()
                .find(|(_, p)| !(0.0..=1.0).contains(*p))
            {
                return Err(DetectError::BadProbability { index, value });
            }
            check_finite(points)?;
        }
        let lists: Vec<&[(u32, f32)]> = self.pieces[..pieces]
            .iter()
            .map(|p| &p.ground[..])
            .collect();
        self.ground.fill(&lists);

        // Non-ground points within the height band above the local ground are clustered;
        // uncertain ground points there may join a cluster they touch. Where the ground is
        // unknown, the segmenter's word alone decides.
        let mut batches = 0;
        for (k, piece) in self.pieces[..pieces].iter().enumerate() {
            for start in (0..piece.maybe.len()).step_by(BATCH) {
                if self.batches.len() == batches {
                    self.batches.push(Batch::default());
                }
                (self.batches[batches].piece, self.batches[batches].start) = (k, start);
                batches += 1;
            }
        }
        let batches = &mut self.batches[..batches];
        let (ground, grid, all) = (&self.ground, &self.grid, &self.pieces);
        batches.par_iter_mut().for_each(|batch| {
            batch.candidates.clear();
            batch.joiners.clear();
            batch.entries.clear();
            let maybe = &all[batch.piece].maybe[batch.start..];
            for m in &maybe[..maybe.len().min(BATCH)] {
                if let Some(g) = ground.height(m.xyz[0], m.xyz[1]) {
                    let h = m.xyz[2] - g;
                    if h < cfg.min_height || h > cfg.max_height {
                        continue;
                    }
                } else if m.ground {
                    continue;
                }
                if m.ground {
                    batch.joiners.push(*m);
                } else {
                    // Its cell for the clustering, here on all cores.
                    let k = batch.candidates.len() as u32;
                    batch.entries.extend(grid.entry(m.xyz, k));
                    batch.candidates.push(*m);
                }
            }
        });
        let batches = &*batches;
        self.joiners.clear();
        for batch in batches {
            self.joiners.extend_from_slice(&batch.joiners);
        }
        let mut candidates = 0;
        let runs: Vec<(&[Entry], u32)> = batches
            .iter()
            .map(|p| {
                candidates += p.candidates.len() as u32;
                (&p.entries[..], candidates - p.candidates.len() as u32)
            })
            .collect();
        let candidates = candidates as usize;
        let found = self
            .grid
            .cluster_runs(&runs, candidates, cfg, &mut self.labels);

        // The candidates grouped by cluster, in two parts (the first batches with about half
        // of them, and the others) on two cores, and meanwhile the cluster each uncertain
        // ground point touches; then those grouped.
        self.joiner_xyz.clear();
        self.joiner_xyz.extend(self.joiners.iter().map(|m| m.xyz));
        let (grid, joiner_xyz, touched) = (&mut self.grid, &self.joiner_xyz, &mut self.touched);
        let (mut half, mut before) = (0, 0);
        for p in batches {
            if 2 * before >= candidates {
                break;
            }
            (half, before) = (half + 1, before + p.candidates.len());
        }
        let (first, second) = batches.split_at(half);
        let (labels0, labels1) = self.labels.split_at(before);
        let [part0, part1] = &mut self.members.parts;
        rayon::join(
            || part0.group(labelled(first, labels0), found),
            || {
                rayon::join(
                    || part1.group(labelled(second, labels1), found),
                    || grid.touching(joiner_xyz, cfg, touched),
                )
            },
        );
        let touching = self.touched.iter().map(|c| c.unwrap_or(u32::MAX));
        self.members
            .joiners
            .group(self.joiners.iter().zip(touching), found);

        // Each cluster kept (small ones dropped) measured and boxed on all cores: its
        // candidates in order, then the uncertain ground points that touch it.
        let members = &self.members;
        let kept = |c: u32| members.candidates(c) >= cfg.min_points as usize;
        self.live.clear();
        self.live.extend((0..found as u32).filter(|&c| kept(c)));
        let joined = self.live.iter().map(|&c| members.joiners.of(c).len()).sum();
        self.live
            .par_iter()
            .map(|&c| {
                RECT_SCRATCH.with_borrow_mut(|(footprint, s)| {
                    footprint.clear();
                    footprint.extend(members.of(c).map(|m| [m.xyz[0], m.xyz[1]]));
                    (Extent::of(members.of(c)), min_area_rect(footprint, s))
                })
            })
            .collect_into_vec(&mut self.measured);

        // Numbered nearest first (ties: the first point).
        let mut order: Vec<(f32, u32, u32)> = self
            .measured
            .iter()
            .enumerate()
            .map(|(k, (e, _))| {
                let n = f64::from(e.count);
                let (x, y) = (e.sum[0] / n, e.sum[1] / n);
                ((x * x + y * y).sqrt() as f32, e.first, k as u32)
            })
            .collect();
        order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut id_of = vec![0u32; found];
        for (id, &(_, _, k)) in order.iter().enumerate() {
            id_of[self.live[k as usize] as usize] = id as u32 + 1;
        }
        out.clusters.clear();
        out.clusters.resize(points.len(), 0);
        for &c in &self.live {
            for m in self.members.of(c) {
                out.clusters[m.index as usize] = id_of[c as usize];
            }
        }
        out.proposals.clear();
        for (k, &(_, _, c)) in order.iter().enumerate() {
            let (e, rect) = self.measured[c as usize];
            // Unknown ground: the cluster stands on its lowest point.
            let ground_z = self
                .ground
                .height(rect.center[0], rect.center[1])
                .unwrap_or(e.z_min);
            let n = f64::from(e.count);
            let mut p = Proposal {
                id: k as u32 + 1,
                centroid: [
                    (e.sum[0] / n) as f32,
                    (e.sum[1] / n) as f32,
                    (e.sum[2] / n) as f32,
                ],
                center: rect.center,
                yaw: rect.yaw,
                length: rect.length,
                width: rect.width,
                ground_z,
                bottom: e.z_min - ground_z,
                height: e.z_max - ground_z,
                points: e.count,
                flags: ProposalFlags::default(),
            };
            p.flags = self.flags(&p);
            out.proposals.push(p);
        }
        Ok(DetectionReport {
            candidates,
            joined,
            clusters: found,
            // Every cluster has a candidate: those not kept were too small.
            dropped_small: found - self.live.len(),
            time: t.elapsed(),
        })
    }

    fn flags(&self, p: &Proposal) -> ProposalFlags {
        let c = &self.cfg;
        let mut f = ProposalFlags::default();
        if p.length >= c.wall_length && p.width <= c.wall_width {
            f |= ProposalFlags::WALL;
        }
        if p.length > c.max_length {
            f |= ProposalFlags::LARGE;
        }
        if p.height > c.max_object_height {
            f |= ProposalFlags::TALL;
        }
        if p.bottom > c.floating_height {
            f |= ProposalFlags::FLOATING;
        }
        if p.points > c.max_points {
            f |= ProposalFlags::MANY_POINTS;
        }
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use groundwork_core::Point;
    use proptest::prelude::*;

    fn pt(x: f32, y: f32, z: f32) -> Point {
        Point {
            x,
            y,
            z,
            intensity: 0.0,
        }
    }

    /// A flat road (ground) with two boxes standing on it, 3 m apart.
    fn street() -> (Vec<Point>, Vec<f32>) {
        let (mut pts, mut probs) = (Vec::new(), Vec::new());
        for i in 0..60 {
            for j in 0..40 {
                pts.push(pt(4.0 + 0.5 * i as f32, -10.0 + 0.5 * j as f32, 0.0));
                probs.push(0.95);
            }
        }
        for (cx, cy) in [(12.0f32, 0.0f32), (12.0, 4.0)] {
            for a in 0..20 {
                for b in 0..8 {
                    // The near face and one side of a 4 × 1.8 × 1.5 m car.
                    pts.push(pt(
                        cx - 2.0 + 0.2 * a as f32,
                        cy - 0.9,
                        0.3 + 0.15 * b as f32,
                    ));
                    pts.push(pt(
                        cx - 2.0,
                        cy - 0.9 + 0.09 * a as f32,
                        0.3 + 0.15 * b as f32,
                    ));
                    probs.extend([0.02, 0.02]);
                }
            }
        }
        (pts, probs)
    }

    #[test]
    fn two_cars_on_a_road_are_two_proposals_with_their_points() {
        let (pts, probs) = street();
        let mut d = Detector::new(DetectorConfig::default(), &SegmenterConfig::default()).unwrap();
        let mut out = Detections::default();
        let r = d.detect(&pts, &probs, &mut out).unwrap();
        assert_eq!(out.proposals.len(), 2, "{:?} {r:?}", out.proposals);
        assert_eq!(out.clusters.len(), pts.len());
        for p in &out.proposals {
            assert_eq!(
                out.clusters.iter().filter(|&&c| c == p.id).count(),
                p.points as usize
            );
            assert!(
                (p.height - 1.35).abs() < 0.01 && (p.bottom - 0.3).abs() < 0.01,
                "{p:?}"
            );
            assert!((p.length - 4.0).abs() < 0.25 && p.yaw.abs() < 0.05, "{p:?}");
            assert!(p.flags.is_object_like());
        }
        // Nearest first: the car on the x axis.
        assert!(out.proposals[0].centroid[1].abs() < out.proposals[1].centroid[1].abs());
        // Road points carry no id.
        assert!(out.clusters[..2400].iter().all(|&c| c == 0));
    }

    #[test]
    fn the_thread_count_and_the_scan_cut_into_pieces_and_batches_change_nothing() {
        // A road of 40 000 points, then 120 cars' faces (the non-ground points crowd into
        // the last pieces, some batches short), some of them uncertain ground: every
        // thread count gives the same ids and proposals.
        let (mut pts, mut probs) = (Vec::new(), Vec::new());
        for i in 0..200 {
            for j in 0..200 {
                pts.push(pt(-40.0 + 0.4 * i as f32, -40.0 + 0.4 * j as f32, 0.0));
                probs.push(0.95);
            }
        }
        for k in 0..120 {
            let (cx, cy) = (-36.0 + 6.0 * (k % 12) as f32, -36.0 + 7.0 * (k / 12) as f32);
            for a in 0..30 {
                for b in 0..10 {
                    pts.push(pt(cx + 0.14 * a as f32, cy, 0.1 + 0.15 * b as f32));
                    probs.push(if b == 2 { 0.6 } else { 0.05 });
                }
            }
        }
        assert!(pts.len() > 4 * PIECE && pts.len() - 40_000 > 8 * BATCH);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut d =
                Detector::new(DetectorConfig::default(), &SegmenterConfig::default()).unwrap();
            let mut out = Detections::default();
            let r = pool.install(|| d.detect(&pts, &probs, &mut out)).unwrap();
            (r.clusters, r.joined, out)
        };
        let one = run(1);
        assert!(
            one.0 >= 100 && one.1 > 0,
            "{} clusters, {} joined",
            one.0,
            one.1
        );
        for threads in [2, 3, 5] {
            let other = run(threads);
            assert_eq!((one.0, one.1), (other.0, other.1), "{threads} threads");
            assert_eq!(one.2.clusters, other.2.clusters, "{threads} threads");
            assert_eq!(one.2.proposals, other.2.proposals, "{threads} threads");
        }
    }

    #[test]
    fn a_long_thin_cluster_is_flagged_a_wall() {
        let mut pts = Vec::new();
        for a in 0..100 {
            for b in 0..10 {
                pts.push(pt(10.0, -10.0 + 0.2 * a as f32, 0.3 + 0.2 * b as f32));
            }
        }
        let probs = vec![0.0; pts.len()];
        let mut d = Detector::new(DetectorConfig::default(), &SegmenterConfig::default()).unwrap();
        let mut out = Detections::default();
        d.detect(&pts, &probs, &mut out).unwrap();
        assert_eq!(out.proposals.len(), 1);
        assert!(out.proposals[0].flags.contains(ProposalFlags::WALL));
        assert!(out.proposals[0].flags.contains(ProposalFlags::LARGE));
        assert_eq!(
            out.proposals[0].flags.names().collect::<Vec<_>>(),
            ["wall", "large"]
        );
    }

    #[test]
    fn bad_input_is_an_error_naming_the_problem() {
        let mut d = Detector::new(DetectorConfig::default(), &SegmenterConfig::default()).unwrap();
        let mut out = Detections::default();
        let pts = vec![pt(5.0, 0.0, 0.0), pt(6.0, 0.0, f32::NAN)];
        let e = d.detect(&pts, &[0.0, 0.0], &mut out).unwrap_err();
        assert!(matches!(e, DetectError::Points(_)), "{e}");
        let pts = vec![pt(5.0, 0.0, 0.0), pt(6.0, 0.0, 1.0)];
        let e = d.detect(&pts, &[0.0], &mut out).unwrap_err();
        assert!(
            e.to_string()
                .contains("1 ground probabilities for 2 points")
        );
        let e = d.detect(&pts, &[0.0, f32::NAN], &mut out).unwrap_err();
        assert!(e.to_string().contains("point 1"), "{e}");
        let e = d.detect(&pts, &[0.0, 1.5], &mut out).unwrap_err();
        assert!(matches!(e, DetectError::BadProbability { index: 1, .. }));
        // Checked inside the parallel pass: a bad value in a later piece is still named,
        // probabilities before coordinates, and a rejected scan changes nothing.
        let n = 3 * PIECE;
        let mut pts: Vec<Point> = (0..n)
            .map(|k| {
                pt(
                    5.0 + (k % 200) as f32 * 0.1,
                    (k / 200) as f32 * 0.1 - 12.0,
                    0.5,
                )
            })
            .collect();
        let mut probs = vec![0.0f32; n];
        let mut fresh =
            Detector::new(DetectorConfig::default(), &SegmenterConfig::default()).unwrap();
        let mut expected = Detections::default();
        fresh.detect(&pts, &probs, &mut expected).unwrap();
        assert!(!expected.proposals.is_empty());
        pts[2 * PIECE + 7].z = f32::INFINITY;
        probs[PIECE + 3] = 2.0;
        let e = d.detect(&pts, &probs, &mut out).unwrap_err();
        assert!(
            matches!(e, DetectError::BadProbability { index, .. } if index == PIECE + 3),
            "{e}"
        );
        probs[PIECE + 3] = 0.0;
        let e = d.detect(&pts, &probs, &mut out).unwrap_err();
        assert!(
            matches!(e, DetectError::Points(SegmentError::NonFinitePoint { index, .. }) if index == 2 * PIECE + 7),
            "{e}"
        );
        pts[2 * PIECE + 7].z = 0.5;
        d.detect(&pts, &probs, &mut out).unwrap();
        assert_eq!(out, expected);
        // An empty scan is no error: nothing to propose.
        d.detect::<Point>(&[], &[], &mut out).unwrap();
        assert!(out.proposals.is_empty() && out.clusters.is_empty());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn every_point_gets_one_id_and_proposals_match_their_points(
            raw in prop::collection::vec((-30.0f32..30.0, -30.0f32..30.0, -1.0f32..3.0, 0.0f32..=1.0), 0..400)
        ) {
            let pts: Vec<Point> = raw.iter().map(|&(x, y, z, _)| pt(x, y, z)).collect();
            let probs: Vec<f32> = raw.iter().map(|r| r.3).collect();
            let cfg = DetectorConfig { min_points: 2, ..Default::default() };
            let mut d = Detector::new(cfg, &SegmenterConfig::default()).unwrap();
            let mut out = Detections::default();
            d.detect(&pts, &probs, &mut out).unwrap();
            prop_assert_eq!(out.clusters.len(), pts.len());
            let n = out.proposals.len() as u32;
            prop_assert!(out.clusters.iter().all(|&c| c <= n));
            for (k, p) in out.proposals.iter().enumerate() {
                prop_assert_eq!(p.id, k as u32 + 1);
                prop_assert_eq!(out.clusters.iter().filter(|&&c| c == p.id).count(), p.points as usize);
                prop_assert!(p.points >= 2 && p.length >= p.width && p.width >= 0.0);
            }
            // Sure ground never joins anything.
            for (c, &p) in out.clusters.iter().zip(&probs) {
                prop_assert!(p < 0.8 || *c == 0);
            }
            // Nearest first.
            let r: Vec<f32> = out.proposals.iter().map(|p| p.centroid[0].hypot(p.centroid[1])).collect();
            prop_assert!(r.windows(2).all(|w| w[0] <= w[1]));
            // Deterministic: the same scan again gives the same output.
            let mut again = Detections::default();
            d.detect(&pts, &probs, &mut again).unwrap();
            prop_assert_eq!(&out, &again);
        }
    }
}
