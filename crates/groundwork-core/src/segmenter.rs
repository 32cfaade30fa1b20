//! The segmenter stage: validates a scan, fits it, queries it (with history) and keeps the
//! state that lives between frames. The same stage runs in tests, benchmarks, the offline
//! CLI and the service process.

use std::time::{Duration, Instant};

use nalgebra::Isometry3;
use rayon::prelude::*;
use tracing::{debug, info, warn};

use crate::mount_watch::{MountWatch, ObservedMount};

use crate::config::{PastQuery, SegmenterConfig};
use crate::config::{mount_transform, roll_pitch_of, vertical_in_sensor};
use crate::continuity::{ContinuityScratch, Elevation, raise_continuous_ground};
use crate::error::{ConfigError, SegmentError};
use crate::grouping::SegmentedPoints;
use crate::grouping::{GroundPoints, SegmentCounts, group_points};
use crate::height_filter::HeightFilter;
use crate::history::History;
use crate::model::{FrameModel, fit_frame};
use crate::point::{PointXyz, Pose, check_finite};
use crate::probability::ProbabilityMap;
use crate::query::{OutputTally, QueryFrame, QueryRules, QueryScratch, query_grouped};
use crate::simd::LANES;
use crate::terrain::{TerrainChange, TerrainScratch, follow_terrain};
use crate::zones::NEAR;
use crate::zones::{LaneBinner, ZoneModel};

/// Rows of [R | t] applied to a block of points (structure of arrays), in f64. Written as
/// plain loops over the lanes so that they become f64 vector operations.
#[inline(always)]
fn transform_block(rows: &[[f64; 4]; 3], p: &[[f32; LANES]; 3]) -> [[f64; LANES]; 3] {
    let (px, py, pz) = (
        p[0].map(f64::from),
        p[1].map(f64::from),
        p[2].map(f64::from),
    );
    let mut g = [[0.0; LANES]; 3];
    for (row, g) in rows.iter().zip(&mut g) {
        for k in 0..LANES {
            g[k] = row[0] * px[k] + row[1] * py[k] + row[2] * pz[k] + row[3];
        }
    }
    g
}

/// What happened to one scan.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameReport {
    /// Points in the scan.
    pub points: usize,
    /// Points inside the near disc (min range / ego radius): probability 0.
    pub near_points: usize,
    /// Points beyond max range.
    pub beyond_points: usize,
    /// Points beyond the coordinate bound (`sensor.max_coordinate`): probability 0, not
    /// counted in `near_points`.
    pub out_of_bounds_points: usize,
    /// Segments that ended with at least one component.
    pub fitted_segments: usize,
    /// Components over all segments.
    pub components: usize,
    /// EM iterations summed over segments.
    pub em_iterations: u64,
    /// Points excluded from elevation references as outliers.
    pub outliers: u64,
    /// Components vetoed by the zone-1 height filter.
    pub height_filtered: u64,
    /// Models queried (1 = single frame).
    pub frames_queried: usize,
    /// Whether the scan came with a pose.
    pub posed: bool,
    /// Whether this scan's pose jump cleared the history.
    pub history_cleared: bool,
    /// Ground points at the configured threshold.
    pub ground_points: usize,
    /// Binning + EM + likelihoods.
    pub fit_time: Duration,
    /// Query (all frames).
    pub query_time: Duration,
}

/// Counters over the segmenter's life.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SegmenterCounters {
    /// Scans segmented.
    pub scans: u64,
    /// Scans rejected (bad input).
    pub rejected: u64,
    /// Scans that came without a pose (segmented single-frame).
    pub without_pose: u64,
    /// Times the history was cleared, for any reason (the sum of the next three).
    pub history_resets: u64,
    /// ... because the pose jumped beyond the configured limits.
    pub resets_pose_jump: u64,
    /// ... because the sensor time jumped beyond `history.max_time_gap` or ran backwards.
    pub resets_time_gap: u64,
    /// ... because the caller asked ([`Segmenter::reset_history`]: a new sequence, a new
    /// producer run whose pose does not continue the history).
    pub resets_requested: u64,
    /// Points beyond the coordinate bound, over all scans.
    pub out_of_bounds_points: u64,
    /// Probabilities that came out non-finite and were written as 0 (a defect, logged as
    /// an error; none is known).
    pub non_finite_outputs: u64,
}

/// Why the multi-frame history was cleared.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HistoryReset {
    /// The pose jumped beyond `history.max_translation_jump` / `max_rotation_jump`.
    PoseJump,
    /// The sensor time jumped beyond `history.max_time_gap`, or ran backwards.
    TimeGap,
    /// The caller asked (a new sequence, a new producer run).
    Requested,
}

/// The GMM ground segmenter with its between-frame state.
#[derive(Debug)]
pub struct Segmenter {
    cfg: SegmenterConfig,
    zones: ZoneModel,
    /// The zone model as SIMD constants, for binning this scan and the query.
    binner: LaneBinner,
    /// `sensor.mount`.
    configured_mount: Isometry3<f64>,
    /// The mount scans are segmented with: `sensor.mount`, unless `mount_check.mode =
    /// "correct"` moved it.
    mount: Isometry3<f64>,
    height: HeightFilter,
    mount_watch: MountWatch,
    history: History,
    /// Sensor time of the last stamped scan, ns.
    last_time_ns: Option<u64>,
    counters: SegmenterCounters,
    // Scratch reused between frames so steady-state segmentation does not allocate more.
    ground: GroundPoints,
    bins: Vec<u32>,
    /// Points per segment of `bins`, counted while binning.
    counts: SegmentCounts,
    sorted: SegmentedPoints,
    query_scratch: QueryScratch,
    continuity: ContinuityScratch,
    terrain: TerrainScratch,
    /// Layouts 1.. of `zones.layouts` (`SegmenterConfig::layout`), each a whole segmenter
    /// with its own history, and their probabilities of the current scan.
    layouts: Vec<(Segmenter, Vec<f32>)>,
    /// The last step: equation values to calibrated probabilities (`[probability] map`).
    map: ProbabilityMap,
}

impl Segmenter {
    /// Validates the configuration and builds an empty segmenter.
    pub fn new(cfg: SegmenterConfig) -> Result<Self, ConfigError> {
        cfg.validate()?;
        let zones = ZoneModel::new(&cfg.zones, cfg.sensor.ego_radius)?;
        let mount = mount_transform(&cfg.sensor.mount)?;
        let height = HeightFilter::new(cfg.height_filter.clone(), zones.first_zone_segments());
        let layouts = (1..cfg.zones.layouts)
            .map(|k| Ok((Segmenter::new(cfg.layout(k)?)?, Vec::new())))
            .collect::<Result<_, ConfigError>>()?;
        Ok(Self {
            layouts,
            map: ProbabilityMap::new(&cfg.probability, cfg.ground.ground_threshold),
            history: History::default(),
            last_time_ns: None,
            cfg,
            binner: LaneBinner::new(&zones),
            zones,
            configured_mount: mount,
            mount,
            height,
            mount_watch: MountWatch::default(),
            counters: SegmenterCounters::default(),
            ground: GroundPoints::default(),
            bins: Vec::new(),
            counts: SegmentCounts::default(),
            sorted: SegmentedPoints::default(),
            query_scratch: QueryScratch::default(),
            continuity: ContinuityScratch::default(),
            terrain: TerrainScratch::default(),
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &SegmenterConfig {
        &self.cfg
    }

    /// The zone model in use.
    pub fn zones(&self) -> &ZoneModel {
        &self.zones
    }

    /// The zone-1 height filter's state.
    pub fn height_filter(&self) -> &HeightFilter {
        &self.height
    }

    /// Lifetime counters.
    pub fn counters(&self) -> SegmenterCounters {
        self.counters
    }

    /// Past frames currently held for multi-frame queries.
    pub fn history_len(&self) -> usize {
        self.history.len()
    }

    /// Component count over all stored frames (of every layout): memory use of the history
    /// is proportional.
    pub fn history_components(&self) -> usize {
        self.history.components()
            + self
                .layouts
                .iter()
                .map(|(l, _)| l.history_components())
                .sum::<usize>()
    }

    /// Forgets the history and the height filter (e.g. on a new sequence); counted as a
    /// requested history reset if there was a history. Returns whether frames were dropped.
    pub fn reset(&mut self) -> bool {
        self.height.reset();
        self.mount_watch.reset();
        for (layout, _) in &mut self.layouts {
            layout.reset();
        }
        self.reset_history()
    }

    /// The mount the next scan is segmented with (ground-aligned frame from sensor):
    /// `sensor.mount`, or where `mount_check.mode = "correct"` has moved it.
    pub fn mount_in_use(&self) -> Pose {
        self.mount
    }

    /// The mount observed in the ground fitted so far (`mount_check.mode` `warn` or
    /// `correct`): height, roll and pitch, how far they are from the configured mount, and
    /// the mount in use. None before the first scan with enough ground, or with the check
    /// off.
    pub fn observed_mount(&self) -> Option<ObservedMount> {
        (self.mount_watch.scans() > 0).then(|| {
            self.mount_watch
                .observed(&self.configured_mount, &self.mount)
        })
    }

    /// Forgets the multi-frame history (a new producer run, a new sequence); counted as a
    /// requested reset if there was one. Returns whether frames were dropped.
    pub fn reset_history(&mut self) -> bool {
        self.last_time_ns = None;
        for (layout, _) in &mut self.layouts {
            layout.reset_history();
        }
        self.clear_history(HistoryReset::Requested)
    }

    /// Whether a scan at `pose` would be queried against the stored history: there is one,
    /// and the pose is within the jump limits of its newest frame.
    pub fn continues_history(&self, pose: &Pose) -> bool {
        !self.history.is_empty() && self.pose_jump(pose).is_none()
    }

    fn clear_history(&mut self, why: HistoryReset) -> bool {
        if self.history.is_empty() {
            return false;
        }
        self.history.clear();
        let c = &mut self.counters;
        c.history_resets += 1;
        match why {
            HistoryReset::PoseJump => c.resets_pose_jump += 1,
            HistoryReset::TimeGap => c.resets_time_gap += 1,
            HistoryReset::Requested => c.resets_requested += 1,
        }
        true
    }

    /// Forgets only the zone-1 height filter.
    pub fn reset_height_filter(&mut self) {
        self.height.reset();
        for (layout, _) in &mut self.layouts {
            layout.reset_height_filter();
        }
    }

    /// Fits a model to a scan without touching any between-frame state (height filter,
    /// history): the first half of [`Segmenter::segment`], exposed for benchmarks and
    /// callers that fit once and query many times. With `zones.layouts` > 1: layout 0 only.
    pub fn fit<P: PointXyz + Sync>(&mut self, points: &[P]) -> Result<FrameModel, SegmentError> {
        let out = vec![0.0; points.len()];
        self.check_and_bin(points, None, &out)?;
        self.group(false);
        Ok(self.fit_grouped().0)
    }

    /// Ground probabilities of `points` (this scan's own sensor frame) under one fitted
    /// model, single-frame: the second half of [`Segmenter::segment`] (layout 0's).
    pub fn query_model<P: PointXyz + Sync>(
        &mut self,
        model: &FrameModel,
        points: &[P],
        out: &mut [f32],
    ) -> Result<(), SegmentError> {
        self.check_and_bin(points, None, out)?;
        self.group(true);
        self.query_frames(model, None, out);
        self.continue_ground(model, out);
        self.follow_terrain(out);
        self.calibrate_output(out);
        Ok(())
    }

    /// Ground probabilities of `points` (this scan's own sensor frame, world pose `pose`)
    /// under `model` and the stored history, exactly as [`Segmenter::segment`] queries them,
    /// but without changing the history: for benchmarks and callers that query one scan
    /// several times (layout 0's). Returns the number of models queried.
    pub fn query_model_posed<P: PointXyz + Sync>(
        &mut self,
        model: &FrameModel,
        points: &[P],
        pose: &Pose,
        out: &mut [f32],
    ) -> Result<usize, SegmentError> {
        self.check_and_bin(points, Some(pose), out)?;
        self.group(true);
        let pose = (self.pose_jump(pose).is_none()).then_some(pose);
        let (frames, _) = self.query_frames(model, pose, out);
        self.continue_ground(model, out);
        self.follow_terrain(out);
        self.calibrate_output(out);
        Ok(frames)
    }

    /// Query of the binned and grouped points against `model` and, given the scan's pose,
    /// every stored past frame; without a pose, against `model` alone. Returns the number of
    /// models queried and the tally of what was written. Continuity is the next step
    /// ([`Segmenter::continue_ground`]).
    fn query_frames(
        &mut self,
        model: &FrameModel,
        pose: Option<&Pose>,
        out: &mut [f32],
    ) -> (usize, OutputTally) {
        let transforms = match pose {
            Some(pose) => self.history.transforms(&self.mount, pose),
            None => Vec::new(),
        };
        let mut frames = Vec::with_capacity(self.history.len() + 1);
        frames.push(QueryFrame {
            model,
            transform: None,
            anchored: None,
        });
        frames.extend(self.history.query_frames(&transforms));
        let tally = query_grouped(
            &self.binner,
            &frames,
            QueryRules {
                beyond: self.cfg.zones.beyond_max_range,
                past: self.cfg.history.query,
                spread: self.cfg.history.spread,
            },
            self.cfg.ground.ground_threshold,
            &self.sorted,
            &mut self.query_scratch,
            out,
        );
        (frames.len(), tally)
    }

    /// Ground continuity (after the query): points on ground that continues from confident
    /// ground are raised to it. Returns how many crossed the ground threshold.
    fn continue_ground(&mut self, model: &FrameModel, out: &mut [f32]) -> usize {
        let n = out.len();
        let g = &self.ground;
        raise_continuous_ground(
            &self.cfg.continuity,
            self.cfg.zones.max_range,
            (&g.x[..n], &g.y[..n], &g.z[..n]),
            &Elevation {
                bins: &self.bins[..n],
                model,
                sigmoid: self.cfg.ground.elevation,
            },
            out,
            self.cfg.ground.ground_threshold,
            &mut self.continuity,
        )
    }

    /// Terrain following (after continuity): see `crate::terrain`.
    fn follow_terrain(&mut self, out: &mut [f32]) -> TerrainChange {
        let n = out.len();
        let g = &self.ground;
        follow_terrain(
            &self.cfg.terrain,
            self.cfg.zones.max_range,
            (&g.x[..n], &g.y[..n], &g.z[..n]),
            out,
            self.cfg.ground.ground_threshold,
            &mut self.terrain,
        )
    }

    /// Groups the binned points for the fit and, with `query`, for the query too.
    fn group(&mut self, query: bool) {
        group_points(
            &mut self.sorted,
            &mut self.query_scratch.groups,
            &self.ground,
            &self.bins,
            &self.counts,
            self.zones.segment_count(),
            query.then_some(self.cfg.zones.beyond_max_range),
        );
    }

    fn fit_grouped(&self) -> (FrameModel, Vec<crate::model::SegmentStats>) {
        let height = &self.height;
        let first_zone = self.zones.first_zone_segments();
        fit_frame(&self.sorted, &self.cfg, |s| {
            if s < first_zone {
                height.lower_bound(s)
            } else {
                None
            }
        })
    }

    /// Segments one scan, writing one ground probability in [0, 1] per input point, in
    /// input order, into `out`. `pose` is the sensor's world pose (world from sensor); a
    /// scan without one is segmented single-frame and leaves the history untouched.
    ///
    /// A rejected scan leaves all state untouched.
    pub fn segment<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        pose: Option<&Pose>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError> {
        self.segment_stamped(points, pose, None, out)
    }

    /// [`Segmenter::segment`] with the scan's sensor time (ns, any epoch, monotonic per
    /// sensor): a gap to the previous stamped scan beyond `history.max_time_gap`, or time
    /// running backwards, clears the history before this scan is queried.
    pub fn segment_stamped<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        pose: Option<&Pose>,
        sensor_time_ns: Option<u64>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError> {
        // On a thread of rayon's pool (a no-op when already on one): the scan's parallel
        // steps then run as joins there, instead of each sending its work to the pool
        // while the calling thread sleeps until it is done.
        rayon::scope(|_| self.segment_on_pool(points, pose, sensor_time_ns, out))
    }

    /// [`Segmenter::segment_stamped`], on a thread of the pool.
    fn segment_on_pool<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        pose: Option<&Pose>,
        sensor_time_ns: Option<u64>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError> {
        let mut report = self.segment_layout(points, pose, sensor_time_ns, out)?;
        if !self.layouts.is_empty() {
            self.add_layouts(points, pose, sensor_time_ns, out, &mut report)?;
        }
        // Calibrate: the preset's map to how often points are ground; no point changes
        // side of the (moved) threshold.
        self.calibrate_output(out);
        Ok(report)
    }

    /// Whether each point of the last scan segmented was judged: binned into a segment
    /// (not inside the near edge or the ego radius, not a placeholder, within bounds).
    /// Only those are calibrated ([`crate::probability`]); the others are 0.
    pub fn judged_points(&self, points: usize) -> impl Iterator<Item = bool> + '_ {
        self.bins.iter().take(points).map(|&b| b != NEAR)
    }

    /// The last step: the preset's map to calibrated probabilities, on every point binned
    /// into a segment (the others keep their 0).
    fn calibrate_output(&self, out: &mut [f32]) {
        let bins = &self.bins[..out.len()];
        self.map.apply(out, bins, |&b| b != NEAR);
    }

    /// Layouts 1.. on the same scan, their probabilities averaged with layout 0's in `out`.
    fn add_layouts<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        pose: Option<&Pose>,
        sensor_time_ns: Option<u64>,
        out: &mut [f32],
        report: &mut FrameReport,
    ) -> Result<(), SegmentError> {
        // The other layouts see the same scan (it passed this layout's checks) and keep
        // their own history; their probabilities are added in layout order, so the mean is
        // the same bits on any number of threads and for any order of the points.
        for (layout, probs) in &mut self.layouts {
            probs.resize(points.len(), 0.0);
            let r = layout.segment_layout(points, pose, sensor_time_ns, probs)?;
            report.fit_time += r.fit_time;
            report.query_time += r.query_time;
            report.em_iterations += r.em_iterations;
            report.components += r.components;
            for (o, &p) in out.iter_mut().zip(probs.iter()) {
                *o += p;
            }
        }
        // Each sum is of values in [0, 1], so at most the count, and the division (exact
        // rounding, monotone) keeps the mean in [0, 1].
        let n = (self.layouts.len() + 1) as f32;
        let thr = self.cfg.ground.ground_threshold;
        let mut ground = 0;
        for o in out.iter_mut() {
            *o /= n;
            ground += usize::from(*o >= thr);
        }
        report.ground_points = ground;
        Ok(())
    }

    /// One layout of the zone model: the method on one scan, a call per step
    /// (docs/algorithm.md). Counters, timing and logs are filled by the helpers below it.
    fn segment_layout<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        pose: Option<&Pose>,
        sensor_time_ns: Option<u64>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError> {
        let started = Instant::now();
        // Bin: every point into its zone segment, in the ground-aligned frame. A scan
        // refused here leaves every state untouched.
        let out_of_bounds = self.bin(points, pose, out)?;
        let mut report = self.start_report(points.len(), pose.is_some(), out_of_bounds);
        if let Some(t) = sensor_time_ns {
            report.history_cleared |= self.check_time_gap(t);
        }
        // Group the points of each segment together, for the fit and the query.
        self.group(true);
        // Fit: EM per segment, the components' likelihoods, the terrain reference.
        let (model, stats) = self.fit_grouped();
        // Height filter: the ground's height per near segment, for the next scans' fits.
        self.update_height_filter(&model);
        // Mount watch: the mount the fitted ground shows, against the configured one.
        let mount = self.watch_mount(&model);
        report.fit_time = started.elapsed();
        self.report_fit(&mut report, &model, &stats);

        let queried = Instant::now();
        if let Some(pose) = pose {
            report.history_cleared |= self.check_pose_jump(pose);
        }
        // Query: each point's probability from this scan's model and the history's (the
        // equation: `query::equation`).
        let (frames, tally) = self.query_frames(&model, pose, out);
        // Continuity: ground that continues from confident ground is raised to it.
        let lifted = self.continue_ground(&model, out);
        // Terrain: the confident ground's terrain raises the points at its height and
        // lowers ground standing above it.
        let terrain = self.follow_terrain(out);
        // History: this scan's model, kept for the next scans' queries.
        match pose {
            Some(pose) => self.remember(model, pose),
            None => self.counters.without_pose += 1,
        }
        report.query_time = queried.elapsed();
        report.frames_queried = frames;
        self.finish_output(&mut report, tally, lifted, terrain, out);
        // The corrected mount from the next scan on: this scan was binned, queried and
        // stored in the history on the mount it was fitted with.
        if let Some(m) = mount {
            self.mount = m;
        }
        self.counters.scans += 1;
        log_scan(&report);
        Ok(report)
    }

    /// Checks and bins the scan ([`Segmenter::check_and_bin`]), counting a refusal.
    /// Returns the points beyond the coordinate bound.
    fn bin<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        pose: Option<&Pose>,
        out: &mut [f32],
    ) -> Result<usize, SegmentError> {
        self.check_and_bin(points, pose, out).inspect_err(|_| {
            self.counters.rejected += 1;
        })
    }

    /// A scan's report as binning leaves it.
    fn start_report(&mut self, points: usize, posed: bool, out_of_bounds: usize) -> FrameReport {
        self.counters.out_of_bounds_points += out_of_bounds as u64;
        if out_of_bounds > 0 {
            debug!(points = out_of_bounds, "points beyond the coordinate bound");
        }
        FrameReport {
            points,
            posed,
            out_of_bounds_points: out_of_bounds,
            ..Default::default()
        }
    }

    /// The fit's figures in the report.
    fn report_fit(
        &self,
        report: &mut FrameReport,
        model: &FrameModel,
        stats: &[crate::model::SegmentStats],
    ) {
        for st in stats {
            report.em_iterations += u64::from(st.iterations);
            report.outliers += u64::from(st.outliers);
            report.height_filtered += u64::from(st.height_filtered);
        }
        report.fitted_segments = model.fitted_segments();
        report.components = model.components().len();
        // From the per-segment counts taken while binning: every bin not `NEAR` is in
        // range or beyond it.
        let (in_range, beyond) = self.counts.totals();
        report.near_points = report.points - in_range - beyond - report.out_of_bounds_points;
        report.beyond_points = beyond;
    }

    /// The mount watch on this scan's model: warns (once) where the fitted ground
    /// disagrees with `sensor.mount`, and returns the corrected mount to use from the next
    /// scan on (`mount_check.mode = "correct"`).
    fn watch_mount(&mut self, model: &FrameModel) -> Option<Pose> {
        let verdict = self.mount_watch.observe(
            model,
            &self.cfg.mount_check,
            (&self.configured_mount, &self.mount),
            f64::from(self.cfg.ground.ground_threshold),
        );
        if let Some(seen) = verdict.warn {
            // From the pose, not the config's angles: a mount given as a matrix has none.
            let (roll, pitch) = roll_pitch_of(&vertical_in_sensor(&self.configured_mount));
            warn!(
                scans = seen.scans,
                observed_height_m = %format!("{:.3}", seen.height),
                configured_height_m = %format!("{:.3}", self.configured_mount.translation.z),
                observed_roll_deg = %format!("{:.2}", seen.roll.to_degrees()),
                observed_pitch_deg = %format!("{:.2}", seen.pitch.to_degrees()),
                configured_roll_deg = %format!("{:.2}", roll.to_degrees()),
                configured_pitch_deg = %format!("{:.2}", pitch.to_degrees()),
                tilt_deg = %format!("{:.2}", seen.tilt_from_configured.to_degrees()),
                "the ground the segmenter fits disagrees with sensor.mount (beyond \
                 mount_check's tolerances): check the mount, or find it with `groundwork \
                 calibrate`"
            );
        }
        verdict.apply
    }

    /// Keeps this scan's model in the history (the newest `history.frames − 1`).
    fn remember(&mut self, model: FrameModel, pose: &Pose) {
        let h = &self.cfg.history;
        let keep = h.frames as usize - 1;
        let share_anchors = h.query == PastQuery::Regridded;
        self.history
            .push(model, *pose, keep, share_anchors, &self.mount);
    }

    /// The ground count, and no NaN ever leaving the segmenter: a non-finite value would be
    /// a defect (none is known) that poisons every consumer's arithmetic. Written as 0 and
    /// counted; the query counted them while writing, so they are rewritten only if any.
    fn finish_output(
        &mut self,
        report: &mut FrameReport,
        tally: OutputTally,
        lifted: usize,
        terrain: TerrainChange,
        out: &mut [f32],
    ) {
        report.ground_points = tally.ground + lifted + terrain.raised - terrain.lowered;
        let non_finite = tally.non_finite as u64;
        if non_finite > 0 {
            for p in out.iter_mut().filter(|p| !p.is_finite()) {
                *p = 0.0;
            }
            let thr = self.cfg.ground.ground_threshold;
            report.ground_points = out.iter().filter(|&&p| p >= thr).count();
            self.counters.non_finite_outputs += non_finite;
            tracing::error!(
                points = non_finite,
                "non-finite ground probabilities written as 0 (a defect: please report)"
            );
        }
    }

    fn check<P: PointXyz + Sync>(
        &self,
        points: &[P],
        pose: Option<&Pose>,
        out: &[f32],
    ) -> Result<(), SegmentError> {
        if out.len() != points.len() {
            return Err(SegmentError::OutputSize {
                expected: points.len(),
                got: out.len(),
            });
        }
        if points.len() > self.cfg.sensor.max_points {
            return Err(SegmentError::TooManyPoints {
                points: points.len(),
                max: self.cfg.sensor.max_points,
            });
        }
        if let Some(p) = pose {
            let ok = p.translation.vector.iter().all(|v| v.is_finite())
                && p.rotation.coords.iter().all(|v| v.is_finite());
            if !ok {
                return Err(SegmentError::InvalidPose("non-finite entry".into()));
            }
        }
        Ok(())
    }

    /// Checks a scan (sizes, pose, every coordinate finite) and bins it; returns the number
    /// of points beyond the coordinate bound. The finite check rides on the binning pass (one
    /// read of the points, on both cores; alone it was a serial 0.3 ms): a scan with a
    /// non-finite coordinate is refused after binning into scratch, before anything that
    /// outlives the call has changed.
    fn check_and_bin<P: PointXyz + Sync>(
        &mut self,
        points: &[P],
        pose: Option<&Pose>,
        out: &[f32],
    ) -> Result<usize, SegmentError> {
        self.check(points, pose, out)?;
        let (out_of_bounds, all_finite) = self.bin_points(points);
        if !all_finite {
            check_finite(points)?; // names the first bad point
        }
        Ok(out_of_bounds)
    }

    /// Mount transform and zone binning of every point, in input order. Points beyond the
    /// coordinate bound are binned `NEAR` (probability 0, never fitted) at the origin, so
    /// that no arithmetic ever sees them; returns how many there were, and whether every
    /// coordinate is finite (a non-finite one is binned harmlessly: selects, no lookups).
    fn bin_points<P: PointXyz + Sync>(&mut self, points: &[P]) -> (usize, bool) {
        let n = points.len();
        // Whole blocks throughout (padded, truncated to the scan after): copies of a fixed
        // length stay inline, where a last partial block made every block's copy a
        // `memcpy` call (2 % of a scan).
        let padded = n.div_ceil(LANES) * LANES;
        self.ground.resize(padded);
        self.bins.resize(padded, 0);
        // A rotation matrix costs 9 multiply-adds per point, a unit quaternion about 30.
        let r = self.mount.rotation.to_rotation_matrix().into_inner();
        let t = self.mount.translation.vector;
        let rows: [[f64; 4]; 3] = std::array::from_fn(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)], t[i]]);
        let binner = &self.binner;
        let segments = self.binner.segment_count();
        let bound = self.cfg.max_coordinate() as f32;
        let outside = |p: &P| p.xyz().iter().any(|v| v.abs() > bound);
        // Chunks of whole vectors: each is transformed, then binned 16 points at a time.
        const CHUNK: usize = 256 * LANES;
        let GroundPoints { x, y, z } = &mut self.ground;
        let (out_of_bounds, finite, counts) = x
            .par_chunks_mut(CHUNK)
            .zip(y.par_chunks_mut(CHUNK))
            .zip(z.par_chunks_mut(CHUNK))
            .zip(self.bins.par_chunks_mut(CHUNK))
            .zip(points.par_chunks(CHUNK))
            .map(|((((gx, gy), gz), bins), points)| {
                // Non-finite and out-of-bounds coordinates are counted in lanes while the
                // blocks are transformed (one read of the points), fixed up after only
                // where there is any: a branch in the transform loop kept it from being
                // vectorised. The zero-padded lanes of a last block count as neither.
                let (mut finite, mut out_of_bounds) = (true, 0);
                // Transformed and binned a block at a time, in lanes: the block's x and y
                // go to the binning as f32 lanes straight from the transform.
                let blocks = gx.chunks_exact_mut(LANES).zip(gy.chunks_exact_mut(LANES));
                let blocks = blocks.zip(gz.chunks_exact_mut(LANES));
                let blocks = blocks.zip(bins.chunks_exact_mut(LANES));
                for ((((gx, gy), gz), bins), points) in blocks.zip(points.chunks(LANES)) {
                    let mut p = [[0.0f32; LANES]; 3];
                    for (k, q) in points.iter().enumerate() {
                        [p[0][k], p[1][k], p[2][k]] = q.xyz();
                    }
                    let [px, py, pz] = &p;
                    for k in 0..LANES {
                        let (x, y, z) = (px[k], py[k], pz[k]);
                        finite &= x.is_finite() & y.is_finite() & z.is_finite();
                        out_of_bounds +=
                            usize::from((x.abs() > bound) | (y.abs() > bound) | (z.abs() > bound));
                    }
                    let g = transform_block(&rows, &p);
                    gx.copy_from_slice(&g[0]);
                    gy.copy_from_slice(&g[1]);
                    gz.copy_from_slice(&g[2]);
                    bins.copy_from_slice(
                        &binner.bin_block(g[0].map(|v| v as f32), g[1].map(|v| v as f32)),
                    );
                }
                // A point beyond the bound was binned where it is (binning any value is
                // harmless: selects, no lookups); it moves to the origin, binned near.
                if out_of_bounds > 0 {
                    let ground = gx.iter_mut().zip(gy.iter_mut()).zip(gz.iter_mut());
                    for ((((x, y), z), b), p) in ground.zip(bins.iter_mut()).zip(points) {
                        if outside(p) {
                            (*x, *y, *z, *b) = (0.0, 0.0, 0.0, NEAR);
                        }
                    }
                }
                let counts = SegmentCounts::of(&bins[..points.len()], segments);
                (out_of_bounds, finite, counts)
            })
            .reduce(
                || (0, true, SegmentCounts::default()),
                |a, b| (a.0 + b.0, a.1 & b.1, a.2.add(&b.2)),
            );
        self.counts = counts;
        self.ground.truncate(n);
        self.bins.truncate(n);
        (out_of_bounds, finite)
    }

    /// Feeds each zone-1 segment's ground-component height (weight-averaged over components
    /// at or above the filter's likelihood threshold) into the height filter.
    fn update_height_filter(&mut self, model: &FrameModel) {
        let thr = self.height.min_ground_likelihood();
        for s in 0..self.zones.first_zone_segments() {
            let (mut w, mut h) = (0.0, 0.0);
            for c in model.segment(s as u32) {
                if c.ground_likelihood() >= thr {
                    w += c.gaussian.weight;
                    h += c.gaussian.weight * c.gaussian.mean[2];
                }
            }
            if w > 0.0 {
                self.height.observe(s, h / w);
            }
        }
    }

    /// Translation and rotation from the newest stored pose to `pose`, if beyond the
    /// configured jump limits.
    fn pose_jump(&self, pose: &Pose) -> Option<(f64, f64)> {
        let last = self.history.newest_pose()?;
        let rel = last.inverse() * pose;
        let dt = rel.translation.vector.norm();
        let dr = rel.rotation.angle();
        let h = &self.cfg.history;
        (dt > h.max_translation_jump || dr > h.max_rotation_jump || !dt.is_finite())
            .then_some((dt, dr))
    }

    /// Clears the history if the new pose is too far from the last stored one.
    fn check_pose_jump(&mut self, pose: &Pose) -> bool {
        let Some((dt, dr)) = self.pose_jump(pose) else {
            return false;
        };
        warn!(
            translation_m = dt,
            rotation_rad = dr,
            dropped_frames = self.history.len(),
            "pose jump beyond the configured limit: multi-frame history cleared"
        );
        self.clear_history(HistoryReset::PoseJump)
    }

    /// Clears the history if the sensor time jumped beyond the configured gap or ran
    /// backwards since the last stamped scan.
    fn check_time_gap(&mut self, t: u64) -> bool {
        let last = self.last_time_ns.replace(t);
        let Some(last) = last else {
            return false;
        };
        let gap_s = (t as f64 - last as f64) / 1e9;
        if gap_s >= 0.0 && gap_s <= self.cfg.history.max_time_gap {
            return false;
        }
        let frames = self.history.len();
        let cleared = self.clear_history(HistoryReset::TimeGap);
        if cleared {
            warn!(
                gap_s,
                dropped_frames = frames,
                "sensor time jumped (or ran backwards): multi-frame history cleared"
            );
        }
        cleared
    }

    /// Logs the height filter state (for long runs: call now and then).
    pub fn log_state(&self) {
        let s = self.height.summary();
        info!(
            active_segments = s.active_segments,
            mean_height_m = s.mean_height,
            mean_std_m = s.mean_std,
            history_frames = self.history.len(),
            scans = self.counters.scans,
            rejected = self.counters.rejected,
            without_pose = self.counters.without_pose,
            history_resets = self.counters.history_resets,
            out_of_bounds_points = self.counters.out_of_bounds_points,
            "segmenter state"
        );
    }
}

/// One scan's figures at debug level.
fn log_scan(report: &FrameReport) {
    debug!(
        points = report.points,
        ground = report.ground_points,
        components = report.components,
        em_iterations = report.em_iterations,
        frames = report.frames_queried,
        fit_us = report.fit_time.as_micros() as u64,
        query_us = report.query_time.as_micros() as u64,
        "segmented scan"
    );
}
