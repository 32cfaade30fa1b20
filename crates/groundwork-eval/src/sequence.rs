//! Running the segmenter over a sequence (`groundwork_io::Sequence`) and scoring it.
//!
//! Layout: `<dir>/velodyne/*.bin`, optional `<dir>/labels/<stem>.label`, optional
//! `<dir>/poses.txt` + `<dir>/calib.txt` (then multi-frame history is available).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use groundwork_core::{FrameReport, GroundMethod};
use groundwork_io::{FormatError, ScanItem, Sequence};
use serde::Serialize;
use thiserror::Error;
use tracing::warn;

use groundwork_io::{Confusion, Metrics, Protocol, Reliability, ReliabilityBin};

/// Why a sequence could not be evaluated.
#[derive(Debug, Error)]
pub enum SequenceError {
    /// A file could not be read.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A scan could not be read (an evaluation skips it and lists it).
    #[error("{0}")]
    Scan(String),
    /// The segmenter rejected a scan.
    #[error("{}: {source}", path.display())]
    Segment {
        /// The scan file.
        path: PathBuf,
        /// Why.
        source: groundwork_core::SegmentError,
    },
}

/// One scan's outcome.
#[derive(Debug, Clone, Serialize)]
pub struct ScanResult {
    /// File stem.
    pub name: String,
    /// Points in the scan.
    pub points: usize,
    /// Confusion counts, if the scan has labels.
    pub confusion: Option<Confusion>,
    /// Probabilities against the labels, if the scan has labels (pooled in the report).
    #[serde(skip)]
    pub reliability: Option<Reliability>,
    /// Metrics, if the scan has labels.
    pub metrics: Option<Metrics>,
    /// Models queried.
    pub frames_queried: usize,
    /// Fit time, ms.
    pub fit_ms: f64,
    /// Query time, ms.
    pub query_ms: f64,
    /// Fit + query, ms.
    pub total_ms: f64,
}

/// A scan the evaluation could not score, and why.
#[derive(Debug, Clone, Serialize)]
pub struct SkippedScan {
    /// Its name (file stem, or `<recording>_<index>`).
    pub name: String,
    /// Why: unreadable, rejected by the method, or labels that do not fit it.
    pub reason: String,
}

/// A whole evaluation.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Scans that could not be scored (not in `scans`, not pooled): an evaluation with
    /// any is incomplete, and the CLI says so and exits 1.
    pub skipped: Vec<SkippedScan>,
    /// Method evaluated (`gmm`, `pseudolabeler`, `ransac`).
    pub method: &'static str,
    /// Protocol used.
    pub protocol: Protocol,
    /// History length configured.
    pub history_frames: u32,
    /// Per scan.
    pub scans: Vec<ScanResult>,
    /// Pooled counts over labeled scans.
    pub pooled: Confusion,
    /// Pooled metrics.
    pub pooled_metrics: Metrics,
    /// How often points are ground at each probability, pooled (ten bins).
    pub reliability: Vec<ReliabilityBin>,
    /// The expected calibration error of those bins.
    pub expected_calibration_error: f64,
    /// Labeled scans.
    pub labeled_scans: usize,
    /// Median segmentation time (fit + query) per scan, ms.
    pub median_ms: f64,
    /// Scans per second at that median.
    pub scans_per_second: f64,
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// Segments every scan of the sequence in order (so history builds up) with any method and
/// scores the labeled ones. `on_scan` is called after each scan (progress reporting). A scan
/// that cannot be read, is rejected, or whose labels do not fit is skipped and listed in
/// [`EvalReport::skipped`]; the others are scored.
pub fn evaluate(
    seq: &Sequence,
    segmenter: &mut dyn GroundMethod,
    protocol: Protocol,
    mut on_scan: impl FnMut(&ScanResult),
) -> Result<EvalReport, SequenceError> {
    let max = segmenter.max_points();
    let thr = segmenter.threshold();
    let mut scans = Vec::with_capacity(seq.len_hint().unwrap_or(0));
    let mut pooled = Confusion::default();
    let mut reliability = Reliability::default();
    let mut probs = Vec::new();
    let mut skipped = Vec::new();
    for item in seq.scans(max) {
        match score_one(seq, segmenter, protocol, thr, &item, &mut probs) {
            Ok(r) => {
                if let Some(c) = &r.confusion {
                    pooled.merge(c);
                }
                if let Some(c) = &r.reliability {
                    reliability.merge(c);
                }
                on_scan(&r);
                scans.push(r);
            }
            Err(e) => {
                warn!("skipped: {e}");
                skipped.push(SkippedScan {
                    name: item.name.clone(),
                    reason: e.to_string(),
                });
            }
        }
    }
    let labeled_scans = scans.iter().filter(|s| s.confusion.is_some()).count();
    if labeled_scans == 0 {
        warn!("no scan of the sequence has labels: only timing is reported");
    }
    let median_ms = median(scans.iter().map(|s| s.total_ms).collect());
    Ok(EvalReport {
        skipped,
        protocol,
        method: segmenter.name(),
        history_frames: segmenter.history_frames(),
        pooled_metrics: pooled.metrics(),
        pooled,
        reliability: reliability.bins(),
        expected_calibration_error: reliability.expected_calibration_error(),
        labeled_scans,
        median_ms,
        scans_per_second: if median_ms > 0.0 {
            1e3 / median_ms
        } else {
            0.0
        },
        scans,
    })
}

/// Segments and scores one scan.
fn score_one(
    seq: &Sequence,
    segmenter: &mut dyn GroundMethod,
    protocol: Protocol,
    thr: f32,
    item: &ScanItem,
    probs: &mut Vec<f32>,
) -> Result<ScanResult, SequenceError> {
    let scan = item
        .scan
        .as_ref()
        .map_err(|e| SequenceError::Scan(e.to_string()))?;
    let points = &scan.points;
    let pose = seq.pose(item.index);
    probs.resize(points.len(), 0.0);
    let t = Instant::now();
    let report: FrameReport = segmenter
        .segment_scan(points, pose, probs)
        .map_err(|source| SequenceError::Segment {
            path: PathBuf::from(&item.name),
            source,
        })?;
    let total = t.elapsed();
    let (confusion, reliability) = match seq.label_path(item) {
        Some(l) => {
            // Labels are per record of the input: placeholders the reader left out are
            // scored as the non-ground they were given (probability 0).
            let labels = seq.label_map.read(&l, scan.records)?;
            let all = scan.expand(probs, 0.0);
            (
                Some(Confusion::from_predictions(&all, &labels, protocol, thr)),
                Some(Reliability::from_predictions(&all, &labels, protocol)),
            )
        }
        None => (None, None),
    };
    Ok(ScanResult {
        name: item.name.clone(),
        points: points.len(),
        metrics: confusion.as_ref().map(Confusion::metrics),
        confusion,
        reliability,
        frames_queried: report.frames_queried,
        fit_ms: ms(report.fit_time),
        query_ms: ms(report.query_time),
        total_ms: ms(total),
    })
}

/// Several methods' pooled figures on the same scans, one row each.
pub fn side_by_side(reports: &[EvalReport]) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    if let Some(r) = reports.first() {
        let _ = writeln!(
            s,
            "protocol {}, {} scans ({} labeled), pooled over labeled scans",
            r.protocol,
            r.scans.len(),
            r.labeled_scans
        );
    }
    let _ = writeln!(
        s,
        "{:<14} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>9}",
        "method", "frames", "prec", "recall", "F1", "acc", "IoU_g", "IoU_ng", "mIoU", "ms/scan"
    );
    for r in reports {
        let m = &r.pooled_metrics;
        let _ = writeln!(
            s,
            "{:<14} {:>7} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>7.2} {:>9.1}",
            r.method,
            r.history_frames,
            m.precision,
            m.recall,
            m.f1,
            m.accuracy,
            m.iou_ground,
            m.iou_nonground,
            m.miou,
            r.median_ms
        );
    }
    if let Some(r) = reports.first() {
        for k in &r.skipped {
            let _ = writeln!(s, "skipped {}: {}", k.name, k.reason);
        }
    }
    s
}

/// Median of a list (mean of the middle two for even lengths); 0 for an empty list.
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

impl EvalReport {
    /// A table a person reads at a glance.
    pub fn to_table(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "method {}, protocol {}, {} history frame(s), {} scans ({} labeled)",
            self.method,
            self.protocol,
            self.history_frames,
            self.scans.len(),
            self.labeled_scans
        );
        let _ = writeln!(
            s,
            "{:<10} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8}",
            "scan",
            "prec",
            "recall",
            "F1",
            "acc",
            "IoU_g",
            "IoU_ng",
            "mIoU",
            "frames",
            "fit ms",
            "query ms"
        );
        let row = |s: &mut String,
                   name: &str,
                   m: Option<&Metrics>,
                   frames: String,
                   fit: String,
                   q: String| {
            let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2}"));
            let _ = writeln!(
                s,
                "{:<10} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7} {:>8} {:>8}",
                name,
                f(m.map(|m| m.precision)),
                f(m.map(|m| m.recall)),
                f(m.map(|m| m.f1)),
                f(m.map(|m| m.accuracy)),
                f(m.map(|m| m.iou_ground)),
                f(m.map(|m| m.iou_nonground)),
                f(m.map(|m| m.miou)),
                frames,
                fit,
                q
            );
        };
        for r in &self.scans {
            row(
                &mut s,
                &r.name,
                r.metrics.as_ref(),
                r.frames_queried.to_string(),
                format!("{:.2}", r.fit_ms),
                format!("{:.2}", r.query_ms),
            );
        }
        row(
            &mut s,
            "pooled",
            (self.labeled_scans > 0).then_some(&self.pooled_metrics),
            String::new(),
            String::new(),
            String::new(),
        );
        if self.labeled_scans > 0 && self.method == "gmm" {
            // Whether a probability says how often points are ground (docs/accuracy.md).
            let bins: Vec<String> = self
                .reliability
                .iter()
                .map(|b| format!("{:.2}:{:.2}", b.mean_probability, b.ground_fraction))
                .collect();
            let _ = writeln!(
                s,
                "reliability: ECE {:.3}; per bin mean probability:ground fraction {}",
                self.expected_calibration_error,
                bins.join(" ")
            );
        }
        let _ = writeln!(
            s,
            "median {:.2} ms per scan (fit + query) = {:.1} scans/s",
            self.median_ms, self.scans_per_second
        );
        for k in &self.skipped {
            let _ = writeln!(s, "skipped {}: {}", k.name, k.reason);
        }
        s
    }
}
