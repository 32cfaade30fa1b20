//! The segmenter stage: scans in, masks out, multi-frame history kept between frames.
//!
//! [`SegmenterStage::segment`] is the whole per-scan step (validation, sequence and
//! producer-run bookkeeping, pose decoding, segmentation, the mask header) with no IPC, so
//! unit tests and the offline CLI run exactly what the process runs; as a [`Stage`] it
//! answers each scan with a mask, and [`run`] runs it. A malformed scan is rejected with a
//! counted, logged reason (and an empty mask naming it), and the next scan is served as
//! usual.

use std::collections::BTreeMap;

use groundwork_core::{PointXyz, Pose, SegmentError, Segmenter, SegmenterConfig, pose_from_matrix};
use groundwork_msg::{MaskHeader, MaskStatus, SCHEMA_VERSION, ScanHeader, new_epoch};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::ServiceConfig;
use crate::producer::pose_matrix;
use crate::stage::{Input, Inputs, Outbox, Stage, Topic, Wiring};

/// Segmenter options beyond the shared configuration.
#[derive(Debug, Clone)]
pub struct SegmenterOptions {
    /// The algorithm's configuration.
    pub segmenter: SegmenterConfig,
    /// Stop after this many scans (None: until Ctrl-C).
    pub count: Option<u64>,
    /// Transport benchmark: answer every scan with a mask of the right size without
    /// segmenting (the values are 0).
    pub echo: bool,
}

/// What the segmenter did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SegmenterReport {
    /// Scans received.
    pub received: u64,
    /// Masks published for segmented scans.
    pub segmented: u64,
    /// Rejected scans by reason.
    pub rejected: BTreeMap<&'static str, u64>,
    /// Scans lost between producer and segmenter (gaps in sequence numbers).
    pub dropped: u64,
    /// Masks that reached no subscriber (no consumer attached).
    pub unreceived_masks: u64,
    /// Producer runs seen (a restarted producer is a new run).
    pub producer_runs: u64,
    /// History resets because a new producer run's pose did not continue the history.
    pub history_resets_new_run: u64,
    /// Points beyond the coordinate bound, over all scans (probability 0).
    pub out_of_bounds_points: u64,
}

/// Validates a scan's header and size; `Err` carries the rejection status and a reason.
pub fn validate<P>(
    h: &ScanHeader,
    points: &[P],
    max_points: usize,
) -> Result<(), (MaskStatus, String)> {
    if h.schema_version != SCHEMA_VERSION {
        return Err((
            MaskStatus::BAD_SCHEMA,
            format!(
                "schema version {} (expected {SCHEMA_VERSION})",
                h.schema_version
            ),
        ));
    }
    if h.point_count as usize != points.len() {
        return Err((
            MaskStatus::COUNT_MISMATCH,
            format!(
                "header says {} points, payload has {}",
                h.point_count,
                points.len()
            ),
        ));
    }
    if points.is_empty() {
        return Err((MaskStatus::EMPTY, "scan has no points".into()));
    }
    if points.len() > max_points {
        return Err((
            MaskStatus::TOO_MANY_POINTS,
            format!(
                "{} points, more than the configured maximum of {max_points}",
                points.len()
            ),
        ));
    }
    Ok(())
}

/// The pose a scan header carries, if any (an invalid one is an error).
pub fn decode_pose(h: &ScanHeader) -> Result<Option<Pose>, SegmentError> {
    (h.has_pose == 1)
        .then(|| pose_from_row_major(&h.pose))
        .transpose()
}

/// A pose from a header's 4×4 row-major matrix (the inverse of
/// [`crate::producer::pose_matrix`]), refused if it is not rigid.
pub fn pose_from_row_major(m: &[f64; 16]) -> Result<Pose, SegmentError> {
    pose_from_matrix(&std::array::from_fn(|r| {
        std::array::from_fn(|c| m[4 * r + c])
    }))
}

/// Scans missing between sequence numbers `last` and `next` of one producer run (0 if
/// `next` does not come after `last`). No overflow for any pair.
pub fn sequence_gap(last: u64, next: u64) -> u64 {
    next.saturating_sub(last).saturating_sub(1)
}

fn status_of(e: &SegmentError) -> MaskStatus {
    match e {
        SegmentError::NonFinitePoint { .. } => MaskStatus::NON_FINITE,
        SegmentError::TooManyPoints { .. } => MaskStatus::TOO_MANY_POINTS,
        _ => MaskStatus::OTHER,
    }
}

/// The segmenter stage: its algorithm state and counters, no IPC.
#[derive(Debug)]
pub struct SegmenterStage {
    seg: Segmenter,
    echo: bool,
    max_points: usize,
    epoch: u64,
    /// Stop after this many scans (None: until stopped).
    count: Option<u64>,
    /// (producer epoch, sequence) of the last scan.
    last: Option<(u64, u64)>,
    /// Why the last scan was rejected.
    rejection: Option<String>,
    report: SegmenterReport,
}

impl SegmenterStage {
    /// A stage with an empty history; `max_points` is the service's limit (the sensor
    /// configuration's applies too).
    pub fn new(opts: &SegmenterOptions, max_points: usize) -> anyhow::Result<Self> {
        Ok(Self {
            max_points: max_points.min(opts.segmenter.sensor.max_points),
            seg: Segmenter::new(opts.segmenter.clone())?,
            echo: opts.echo,
            epoch: new_epoch(),
            count: opts.count,
            last: None,
            rejection: None,
            report: SegmenterReport::default(),
        })
    }

    /// Length of the mask that answers this scan: its point count if it passes the header
    /// checks, 0 if it will be rejected.
    pub fn mask_len<P>(&self, h: &ScanHeader, points: &[P]) -> usize {
        match validate(h, points, self.max_points) {
            Ok(()) => points.len(),
            Err(_) => 0,
        }
    }

    /// Handles one scan: writes its probabilities into `out` (which must hold
    /// [`SegmenterStage::mask_len`] values) and returns the mask header. Never fails: a bad
    /// scan becomes a rejection status, counted (the reason in
    /// [`SegmenterStage::last_rejection`]).
    pub fn segment<P: PointXyz + Sync>(
        &mut self,
        h: &ScanHeader,
        points: &[P],
        received_ns: u64,
        out: &mut [f32],
    ) -> MaskHeader {
        self.rejection = None;
        let r = &mut self.report;
        r.received += 1;
        let new_run = match self.last {
            Some((e, s)) if e == h.producer_epoch => {
                r.dropped += sequence_gap(s, h.sequence);
                false
            }
            Some(_) => true,
            None => {
                r.producer_runs += 1;
                false
            }
        };
        self.last = Some((h.producer_epoch, h.sequence));
        let mut header = MaskHeader {
            scan_sequence: h.sequence,
            producer_epoch: h.producer_epoch,
            sensor_timestamp_ns: h.sensor_timestamp_ns,
            source_index: h.source_index,
            frame_id: h.frame_id,
            stamps: h.stamps,
            segmenter_epoch: self.epoch,
            // One mask per scan received, rejected or not.
            mask_sequence: r.received - 1,
            ..MaskHeader::default()
        };
        header.stamps.segmenter_received_ns = received_ns;
        let pose = decode_pose(h);
        if new_run {
            // A new producer run: its history is only ours to keep if its pose continues
            // it (a driver restart on a moving car); otherwise the frames are of another
            // recording, another place or another clock.
            self.report.producer_runs += 1;
            let continues = matches!(&pose, Ok(Some(p)) if self.seg.continues_history(p));
            if !continues && self.seg.reset_history() {
                self.report.history_resets_new_run += 1;
                info!(
                    producer_epoch = h.producer_epoch,
                    "new producer run: multi-frame history cleared"
                );
            }
        }
        // The mount this scan is segmented with (a correcting mount check moves it after the
        // scan, for the next one).
        let mount = pose_matrix(&self.seg.mount_in_use());
        let outcome = validate(h, points, self.max_points).and_then(|()| {
            if out.len() != points.len() {
                return Err((
                    MaskStatus::OTHER,
                    format!(
                        "mask holds {} values for {} points",
                        out.len(),
                        points.len()
                    ),
                ));
            }
            if self.echo {
                return Ok(None);
            }
            let pose = pose.map_err(|e| (MaskStatus::OTHER, e.to_string()))?;
            let time = (h.sensor_timestamp_ns != 0).then_some(h.sensor_timestamp_ns);
            // The segmenter reads the scan in shared memory and writes the probabilities
            // straight into the loaned mask: no copies.
            self.seg
                .segment_stamped(points, pose.as_ref(), time, out)
                .map(Some)
                .map_err(|e| (status_of(&e), e.to_string()))
        });
        match outcome {
            Ok(r) => {
                self.report.segmented += 1;
                header.point_count = points.len() as u32;
                if let Some(r) = r {
                    header.ground_points = r.ground_points as u32;
                    header.frames_queried = r.frames_queried as u32;
                    header.fit_us = r.fit_time.as_micros() as u32;
                    header.query_us = r.query_time.as_micros() as u32;
                    header.out_of_bounds_points = r.out_of_bounds_points as u32;
                    header.has_mount = 1;
                    header.mount = mount;
                    self.report.out_of_bounds_points += r.out_of_bounds_points as u64;
                }
            }
            Err((status, reason)) => {
                *self.report.rejected.entry(status.name()).or_default() += 1;
                self.rejection = Some(reason);
                header.status = status;
                header.point_count = 0;
            }
        }
        header
    }

    /// Why the last processed scan was rejected (None if it was segmented).
    pub fn last_rejection(&self) -> Option<&str> {
        self.rejection.as_deref()
    }

    /// A new input sequence (offline: the next folder): the history and the height filter
    /// start afresh, counted as a requested reset; whether frames were dropped.
    pub fn new_sequence(&mut self) -> bool {
        self.last = None;
        self.seg.reset()
    }

    /// Counts a mask that reached no subscriber.
    pub fn count_unreceived(&mut self) {
        self.report.unreceived_masks += 1;
    }

    /// The counters so far.
    pub fn report(&self) -> &SegmenterReport {
        &self.report
    }

    /// The segmenter (history, height filter, counters).
    pub fn segmenter(&self) -> &Segmenter {
        &self.seg
    }
}

impl Stage for SegmenterStage {
    const NAME: &'static str = "segmenter";
    const WIRING: Wiring = Wiring {
        wakes_on: Some(Topic::Scans),
        reads: &[],
        publishes: Some(Topic::Masks),
        parallel: true,
        unique: true,
    };
    type Report = SegmenterReport;

    fn start(&mut self) -> anyhow::Result<()> {
        info!(
            frames = self.seg.config().history.frames,
            echo = self.echo,
            "segmenter ready"
        );
        Ok(())
    }

    /// Answers a scan with its mask: the segmenter reads the scan in shared memory and
    /// writes the probabilities straight into the loaned mask, no copies.
    fn process(
        &mut self,
        input: Input<'_>,
        received_ns: u64,
        out: &mut Outbox,
    ) -> anyhow::Result<()> {
        let Input::Scan(h, points) = input else {
            return Ok(());
        };
        let len = self.mask_len(h, points);
        let mut status = MaskStatus::OK;
        let reached = out.send_mask(len, |mask| {
            let header = self.segment(h, points, received_ns, mask);
            status = header.status;
            header
        })?;
        if reached == 0 {
            self.count_unreceived();
        }
        if let Some(reason) = self.last_rejection() {
            warn!(
                sequence = h.sequence,
                reason = status.name(),
                "rejected scan: {reason}"
            );
        }
        Ok(())
    }

    fn done(&self) -> bool {
        self.count.is_some_and(|c| self.report.received >= c)
    }

    fn log_state(&self) {
        let r = &self.report;
        info!(
            received = r.received,
            segmented = r.segmented,
            rejected = r.rejected.values().sum::<u64>(),
            dropped = r.dropped,
            unreceived_masks = r.unreceived_masks,
            history = self.seg.history_len(),
            "segmenter state"
        );
        self.seg.log_state();
    }

    fn stop(self, _: &Inputs) -> anyhow::Result<SegmenterReport> {
        let r = self.report;
        info!(
            received = r.received,
            segmented = r.segmented,
            rejected = ?r.rejected,
            dropped = r.dropped,
            unreceived_masks = r.unreceived_masks,
            producer_runs = r.producer_runs,
            history_resets = self.seg.counters().history_resets,
            out_of_bounds_points = r.out_of_bounds_points,
            "segmenter stopped"
        );
        Ok(r)
    }
}

/// Runs the segmenter until `count` scans were handled or a termination signal arrives.
pub fn run(cfg: &ServiceConfig, opts: &SegmenterOptions) -> anyhow::Result<SegmenterReport> {
    crate::stage::run(cfg, || SegmenterStage::new(opts, cfg.max_points))
}

#[cfg(test)]
mod tests {
    use super::*;
    use groundwork_msg::ScanPoint;

    fn header(epoch: u64, seq: u64, n: usize, x: f64, t_ms: u64) -> ScanHeader {
        let mut pose = ScanHeader::default().pose;
        pose[3] = x;
        ScanHeader {
            point_count: n as u32,
            sequence: seq,
            producer_epoch: epoch,
            sensor_timestamp_ns: t_ms * 1_000_000,
            has_pose: 1,
            pose,
            ..ScanHeader::default()
        }
    }

    fn stage() -> SegmenterStage {
        let mut cfg = SegmenterConfig::default();
        cfg.sensor.mount.height = 1.73;
        cfg.history.frames = 3;
        let opts = SegmenterOptions {
            segmenter: cfg,
            count: None,
            echo: false,
        };
        SegmenterStage::new(&opts, 200_000).unwrap()
    }

    #[test]
    fn a_new_producer_run_keeps_the_history_only_if_its_pose_continues_it() {
        let pts: Vec<ScanPoint> = crate::synthetic::scan(20_000)
            .iter()
            .map(|p| ScanPoint {
                x: p.x,
                y: p.y,
                z: p.z,
                intensity: p.intensity,
            })
            .collect();
        let mut s = stage();
        let mut out = vec![0.0; pts.len()];
        let mut run = |s: &mut SegmenterStage, h: ScanHeader| {
            let m = s.segment(&h, &pts, 1, &mut out);
            assert_eq!(m.status, MaskStatus::OK, "{:?}", s.last_rejection());
            m
        };
        for i in 0..3 {
            let m = run(&mut s, header(1, i, pts.len(), i as f64 * 0.5, i * 100));
            // The mask carries the mount the scan was segmented with: sensor.mount here.
            assert_eq!(m.has_mount, 1);
            assert_eq!(
                m.mount[11], 1.73,
                "the ground lies 1.73 m below: {:?}",
                m.mount
            );
        }
        assert_eq!(s.segmenter().history_len(), 2);
        // A restarted driver on the same drive: pose and clock continue. History kept.
        let m = run(&mut s, header(2, 0, pts.len(), 1.5, 300));
        assert_eq!(m.frames_queried, 3);
        // Another recording that starts elsewhere: history cleared, counted.
        let m = run(&mut s, header(3, 0, pts.len(), 500.0, 400));
        assert_eq!(m.frames_queried, 1);
        let r = s.report();
        assert_eq!((r.producer_runs, r.history_resets_new_run), (3, 1));
        assert_eq!(r.dropped, 0);
        // Sequence numbers jump inside a run: counted as dropped, no overflow at the top.
        run(&mut s, header(3, 5, pts.len(), 500.0, 500));
        run(&mut s, header(3, u64::MAX, pts.len(), 500.0, 600));
        run(&mut s, header(3, 0, pts.len(), 500.0, 700));
        assert_eq!(s.report().dropped, 4 + (u64::MAX - 6));
    }

    #[test]
    fn a_pose_in_a_header_is_row_major_and_reads_back() {
        let (s, c) = 0.3f64.sin_cos();
        let p = pose_from_matrix(&[
            [c, -s, 0.0, 1.0],
            [s, c, 0.0, 2.0],
            [0.0, 0.0, 1.0, 3.0],
            [0.0, 0.0, 0.0, 1.0],
        ])
        .unwrap();
        let m = pose_matrix(&p);
        assert_eq!([m[3], m[7], m[11], m[15]], [1.0, 2.0, 3.0, 1.0]);
        let back = pose_from_row_major(&m).unwrap();
        assert!((back.to_homogeneous() - p.to_homogeneous()).abs().max() < 1e-12);
    }

    #[test]
    fn a_bad_header_gets_an_empty_mask_naming_it() {
        let mut s = stage();
        let pts = vec![ScanPoint::default(); 10];
        let mut h = header(1, 0, 11, 0.0, 0);
        assert_eq!(s.mask_len(&h, &pts), 0);
        let m = s.segment(&h, &pts, 1, &mut []);
        assert_eq!((m.status, m.point_count), (MaskStatus::COUNT_MISMATCH, 0));
        assert_eq!(m.has_mount, 0, "no mount for a scan not segmented");
        assert!(s.last_rejection().unwrap().contains("11"));
        h.point_count = 10;
        h.pose[0] = 2.0; // not a rotation
        let mut out = vec![0.0; 10];
        let m = s.segment(&h, &pts, 1, &mut out);
        assert_eq!(m.status, MaskStatus::OTHER);
        assert!(s.last_rejection().unwrap().contains("pose"));
        assert_eq!(s.report().rejected.values().sum::<u64>(), 2);
    }
}
