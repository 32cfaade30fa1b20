//! The detector stage: scans and masks in, object proposals out (`<prefix>/proposals`).
//!
//! [`DetectorStage::detect`] is the whole per-mask step (pairing the mask with its scan,
//! checks, detection, the proposals header and the per-point ids) with no IPC; as a
//! [`Stage`] it holds each scan and answers its mask with proposals, and [`run`] runs it. A mask that cannot be
//! answered (rejected by the segmenter, its scan no longer held, bad probabilities) is
//! counted by reason and skipped; the next one is served as usual.

use std::collections::BTreeMap;

use groundwork_core::{SegmenterConfig, mount_transform};
use groundwork_detect::{Detections, Detector, DetectorConfig};
use groundwork_msg::{
    MAX_PROPOSALS, MaskHeader, MaskStatus, ProposalRecord, ProposalsHeader, ScanHeader, ScanPoint,
    new_epoch,
};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::ServiceConfig;
use crate::producer::pose_matrix;
use crate::segmenter::pose_from_row_major;
use crate::stage::{Input, Inputs, Outbox, Stage, Topic, Wiring};
use crate::window::ScanWindow;

/// What the detector did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct DetectorReport {
    /// Scans held for their masks.
    pub scans: u64,
    /// Masks received.
    pub masks: u64,
    /// Masks answered with proposals.
    pub detected: u64,
    /// Masks skipped, by reason.
    pub skipped: BTreeMap<&'static str, u64>,
    /// Proposals published.
    pub proposals: u64,
    /// Proposals beyond the message's capacity, left out.
    pub dropped_proposals: u64,
}

/// The detector stage: the detector, the scans waiting for their masks, counters.
#[derive(Debug)]
pub struct DetectorStage {
    detector: Detector,
    window: ScanWindow,
    out: Detections,
    epoch: u64,
    /// Stop after this many masks (None: until stopped).
    count: Option<u64>,
    rejection: Option<String>,
    report: DetectorReport,
    /// The mount the detector works in (row-major, as masks carry it): `sensor.mount`
    /// until a mask carries another.
    mount: [f64; 16],
}

impl DetectorStage {
    /// A stage for the sensor and segmenter `segmenter` describes.
    pub fn new(segmenter: &SegmenterConfig, detector: DetectorConfig) -> anyhow::Result<Self> {
        let mount = pose_matrix(&mount_transform(&segmenter.sensor.mount)?);
        Ok(Self {
            detector: Detector::new(detector, segmenter)?,
            window: ScanWindow::default(),
            out: Detections::default(),
            epoch: new_epoch(),
            count: None,
            rejection: None,
            report: DetectorReport::default(),
            mount,
        })
    }

    /// Stops the stage after `count` masks (None: until stopped).
    pub fn stop_after(mut self, count: Option<u64>) -> Self {
        self.count = count;
        self
    }

    /// A scan was read: its points are held until its mask comes (scans whose header does
    /// not match their payload are not held; their masks will say why).
    pub fn on_scan(&mut self, h: &ScanHeader, points: &[ScanPoint]) {
        if h.point_count as usize == points.len() && !points.is_empty() {
            self.report.scans += 1;
            self.window.hold(h.producer_epoch, h.sequence, points);
        }
    }

    fn skip(&mut self, reason: &'static str, detail: String) -> Option<ProposalsHeader> {
        *self.report.skipped.entry(reason).or_default() += 1;
        self.rejection = Some(detail);
        None
    }

    /// Handles one mask: the proposals header, with the per-point ids in
    /// [`DetectorStage::clusters`] (ids of proposals left out for capacity are 0); `None`
    /// (counted, reason in [`DetectorStage::last_rejection`]) if it cannot be answered.
    pub fn detect(
        &mut self,
        m: &MaskHeader,
        probabilities: &[f32],
        received_ns: u64,
    ) -> Option<ProposalsHeader> {
        self.rejection = None;
        self.report.masks += 1;
        // The scan leaves the window whatever happens: its mask came.
        let points = self.window.take(m.producer_epoch, m.scan_sequence);
        if m.status != MaskStatus::OK {
            return self.skip(
                "mask_rejected",
                format!(
                    "the segmenter rejected scan {}: {}",
                    m.scan_sequence,
                    m.status.name()
                ),
            );
        }
        let Some(points) = points else {
            return self.skip(
                "scan_missing",
                format!(
                    "scan {} is not held (unseen, or more than {} scans ago)",
                    m.scan_sequence,
                    crate::window::SCAN_WINDOW
                ),
            );
        };
        if m.point_count as usize != probabilities.len() || probabilities.len() != points.len() {
            return self.skip(
                "bad_mask",
                format!(
                    "mask of scan {} holds {} values (header: {}) for {} points",
                    m.scan_sequence,
                    probabilities.len(),
                    m.point_count,
                    points.len()
                ),
            );
        }
        // The ground-aligned frame the segmenter used: it moves where the segmenter
        // corrects its mount, and the detector's ground map and boxes move with it.
        if m.has_mount == 1 && self.mount != m.mount {
            match pose_from_row_major(&m.mount) {
                Ok(mount) => {
                    self.detector.set_mount(&mount);
                    self.mount = m.mount;
                }
                Err(e) => {
                    return self.skip(
                        "bad_mask",
                        format!("mask of scan {}: its mount: {e}", m.scan_sequence),
                    );
                }
            }
        }
        let report = match self.detector.detect(&points, probabilities, &mut self.out) {
            Ok(r) => r,
            Err(e) => return self.skip("bad_input", format!("scan {}: {e}", m.scan_sequence)),
        };
        let mut h = ProposalsHeader {
            point_count: points.len() as u32,
            scan_sequence: m.scan_sequence,
            producer_epoch: m.producer_epoch,
            sensor_timestamp_ns: m.sensor_timestamp_ns,
            source_index: m.source_index,
            stamps: m.stamps,
            detector_received_ns: received_ns,
            detector_epoch: self.epoch,
            detect_us: report.time.as_micros() as u32,
            ..ProposalsHeader::default()
        };
        let kept = self.out.proposals.len().min(MAX_PROPOSALS);
        for (slot, p) in h.records.iter_mut().zip(&self.out.proposals) {
            *slot = record(p);
        }
        h.proposal_count = kept as u32;
        h.dropped_proposals = (self.out.proposals.len() - kept) as u32;
        if h.dropped_proposals > 0 {
            // Their points carry no id a reader could look up.
            for c in &mut self.out.clusters {
                if *c as usize > MAX_PROPOSALS {
                    *c = 0;
                }
            }
        }
        self.report.detected += 1;
        self.report.proposals += kept as u64;
        self.report.dropped_proposals += u64::from(h.dropped_proposals);
        Some(h)
    }

    /// The per-point proposal ids of the last answered mask, in scan order.
    pub fn clusters(&self) -> &[u32] {
        &self.out.clusters
    }

    /// Why the last mask was not answered (None if it was).
    pub fn last_rejection(&self) -> Option<&str> {
        self.rejection.as_deref()
    }

    /// The counters so far.
    pub fn report(&self) -> &DetectorReport {
        &self.report
    }
}

/// Detector options beyond the shared configuration.
#[derive(Debug, Clone)]
pub struct DetectorOptions {
    /// The sensor and segmenter configuration (mount, ranges, threshold).
    pub segmenter: SegmenterConfig,
    /// The detector's parameters.
    pub detector: DetectorConfig,
    /// Stop after this many masks (None: until Ctrl-C).
    pub count: Option<u64>,
}

impl Stage for DetectorStage {
    const NAME: &'static str = "detector";
    // Like the consumer, only masks wake the detector: the scan a mask answers is queued by
    // then.
    const WIRING: Wiring = Wiring {
        wakes_on: Some(Topic::Masks),
        reads: &[Topic::Scans],
        publishes: Some(Topic::Proposals),
        parallel: true,
        unique: true,
    };
    type Report = DetectorReport;

    fn process(
        &mut self,
        input: Input<'_>,
        received_ns: u64,
        out: &mut Outbox,
    ) -> anyhow::Result<()> {
        match input {
            Input::Scan(h, points) => self.on_scan(h, points),
            Input::Mask(m, probabilities) => match self.detect(m, probabilities, received_ns) {
                Some(h) => {
                    out.send_proposals(&self.out.clusters, h)?;
                }
                None => warn!(
                    sequence = m.scan_sequence,
                    "no proposals: {}",
                    self.last_rejection().unwrap_or("unknown")
                ),
            },
            _ => {}
        }
        Ok(())
    }

    fn done(&self) -> bool {
        self.count.is_some_and(|c| self.report.masks >= c)
    }

    fn log_state(&self) {
        let r = &self.report;
        info!(masks = r.masks, detected = r.detected, proposals = r.proposals, skipped = ?r.skipped, "detector state");
    }

    fn stop(self, _: &Inputs) -> anyhow::Result<DetectorReport> {
        let r = self.report;
        info!(
            masks = r.masks,
            detected = r.detected,
            proposals = r.proposals,
            dropped_proposals = r.dropped_proposals,
            skipped = ?r.skipped,
            "detector stopped"
        );
        Ok(r)
    }
}

/// Runs the detector until `count` masks were handled or a termination signal arrives.
pub fn run(cfg: &ServiceConfig, opts: &DetectorOptions) -> anyhow::Result<DetectorReport> {
    crate::stage::run(cfg, || {
        Ok(DetectorStage::new(&opts.segmenter, opts.detector.clone())?.stop_after(opts.count))
    })
}

/// A proposal as the proposals message carries it (the message crate knows no detector).
fn record(p: &groundwork_detect::Proposal) -> ProposalRecord {
    ProposalRecord {
        id: p.id,
        points: p.points,
        flags: p.flags.0,
        ground_z: p.ground_z,
        centroid: p.centroid,
        center: p.center,
        yaw: p.yaw,
        length: p.length,
        width: p.width,
        bottom: p.bottom,
        height: p.height,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan() -> Vec<ScanPoint> {
        crate::synthetic::scan(20_000)
            .iter()
            .map(|p| ScanPoint {
                x: p.x,
                y: p.y,
                z: p.z,
                intensity: p.intensity,
            })
            .collect()
    }

    fn headers(seq: u64, n: usize) -> (ScanHeader, MaskHeader) {
        let s = ScanHeader {
            point_count: n as u32,
            sequence: seq,
            producer_epoch: 7,
            ..ScanHeader::default()
        };
        let m = MaskHeader {
            point_count: n as u32,
            scan_sequence: seq,
            producer_epoch: 7,
            ..MaskHeader::default()
        };
        (s, m)
    }

    fn stage() -> DetectorStage {
        let mut cfg = SegmenterConfig::default();
        cfg.sensor.mount.height = 1.73;
        DetectorStage::new(&cfg, DetectorConfig::default()).unwrap()
    }

    #[test]
    fn a_mask_after_its_scan_gets_proposals_and_one_id_per_point() {
        let pts = scan();
        let mut seg = groundwork_core::Segmenter::new({
            let mut c = SegmenterConfig::default();
            c.sensor.mount.height = 1.73;
            c
        })
        .unwrap();
        let mut probs = vec![0.0; pts.len()];
        seg.segment(&pts, None, &mut probs).unwrap();
        let mut s = stage();
        let (sh, mh) = headers(3, pts.len());
        s.on_scan(&sh, &pts);
        let h = s.detect(&mh, &probs, 42).expect("answered");
        assert_eq!((h.scan_sequence, h.point_count), (3, pts.len() as u32));
        assert_eq!(h.detector_received_ns, 42);
        assert!(h.proposal_count > 0, "the synthetic scene has objects");
        assert_eq!(s.clusters().len(), pts.len());
        for r in h.proposals() {
            let n = s.clusters().iter().filter(|&&c| c == r.id).count();
            assert_eq!(n as u32, r.points);
        }
        // The scan left the window with its mask: the same mask again finds nothing.
        assert!(s.detect(&mh, &probs, 43).is_none());
        assert_eq!(s.report().skipped["scan_missing"], 1);
    }

    /// A stage told `sensor.mount` 1.73 m up follows the mount a mask carries (a segmenter
    /// that corrected its own): the same proposals as a stage configured with that mount;
    /// a mask without one leaves the frame as it is, and a mount that is not rigid is
    /// refused and counted.
    #[test]
    fn the_mount_a_mask_carries_is_the_one_detected_in() {
        let pts = scan();
        let tilted = {
            let mut c = SegmenterConfig::default();
            c.sensor.mount.height = 1.9;
            c.sensor.mount.pitch = 0.05;
            c
        };
        let mut seg = groundwork_core::Segmenter::new(tilted.clone()).unwrap();
        let mut probs = vec![0.0; pts.len()];
        seg.segment(&pts, None, &mut probs).unwrap();
        let mount = pose_matrix(&seg.mount_in_use());
        let run = |s: &mut DetectorStage, seq: u64, with_mount: bool| {
            let (sh, mut mh) = headers(seq, pts.len());
            if with_mount {
                mh.has_mount = 1;
                mh.mount = mount;
            }
            s.on_scan(&sh, &pts);
            let h = s.detect(&mh, &probs, 1).expect("answered");
            h.proposals().to_vec()
        };
        let mut told = DetectorStage::new(&tilted, DetectorConfig::default()).unwrap();
        let expected = run(&mut told, 1, false);
        let mut s = stage();
        let before = run(&mut s, 1, false);
        assert_ne!(before, expected, "the mount must matter for this scene");
        assert_eq!(run(&mut s, 2, true), expected);
        // Kept for masks that carry none.
        assert_eq!(run(&mut s, 3, false), expected);
        let (sh, mut mh) = headers(4, pts.len());
        s.on_scan(&sh, &pts);
        mh.has_mount = 1;
        mh.mount[0] = 2.0; // scaled: not a rotation
        assert!(s.detect(&mh, &probs, 1).is_none());
        assert!(s.last_rejection().unwrap().contains("its mount"));
        assert_eq!(s.report().skipped["bad_mask"], 1);
    }

    #[test]
    fn masks_that_cannot_be_answered_are_counted_by_reason() {
        let pts = scan();
        let mut s = stage();
        let (sh, mut mh) = headers(1, pts.len());
        s.on_scan(&sh, &pts);
        mh.status = MaskStatus::NON_FINITE;
        mh.point_count = 0;
        assert!(s.detect(&mh, &[], 1).is_none());
        assert!(s.last_rejection().unwrap().contains("non_finite"));
        // Wrong mask size.
        let (sh, mut mh) = headers(2, pts.len());
        s.on_scan(&sh, &pts);
        mh.point_count = 5;
        assert!(s.detect(&mh, &[0.0; 5], 1).is_none());
        // A probability outside [0, 1].
        let (sh, mh) = headers(3, pts.len());
        s.on_scan(&sh, &pts);
        let mut probs = vec![0.0; pts.len()];
        probs[9] = f32::NAN;
        assert!(s.detect(&mh, &probs, 1).is_none());
        assert!(s.last_rejection().unwrap().contains("point 9"));
        let r = s.report();
        assert_eq!(
            (
                r.skipped["mask_rejected"],
                r.skipped["bad_mask"],
                r.skipped["bad_input"]
            ),
            (1, 1, 1)
        );
        assert_eq!(r.detected, 0);
        // A scan whose header lies about its size is not held.
        let (mut sh, _) = headers(4, pts.len());
        sh.point_count = 3;
        s.on_scan(&sh, &pts);
        assert_eq!(s.report().scans, 3);
    }
}
