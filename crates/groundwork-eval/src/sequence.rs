//! Running the segmenter over a KITTI-layout sequence folder and scoring it.
//!
//! Layout: `<dir>/velodyne/*.bin`, optional `<dir>/labels/<stem>.label`, optional
//! `<dir>/poses.txt` + `<dir>/calib.txt` (then multi-frame history is available).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use groundwork_core::{FrameReport, GroundMethod, Pose};
use groundwork_io::{
    FormatError, LabelMap, ScanItem, ScanSource, lidar_poses, read_calib_tr, read_poses, read_times,
};
use serde::Serialize;
use thiserror::Error;
use tracing::{info, warn};

use crate::metrics::{Confusion, Metrics, Protocol};

/// Why a sequence could not be evaluated.
#[derive(Debug, Error)]
pub enum SequenceError {
    /// A file could not be read.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The folder does not look like a sequence.
    #[error("{}: {message}", path.display())]
    Layout {
        /// The folder.
        path: PathBuf,
        /// What is missing.
        message: String,
    },
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

/// One sequence of scans: a KITTI-layout folder, a plain folder of scans (any format), a
/// single scan file, or an MCAP recording; with labels and poses where they exist.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Where the scans come from, in order.
    pub source: ScanSource,
    /// Folder of label files, named as the label map says after the scan's stem (for the
    /// index-th message of a recording, the stem is `<index:06>`).
    pub label_dir: Option<PathBuf>,
    /// How the label files are laid out and which classes are ground.
    pub label_map: LabelMap,
    /// LiDAR world pose of each scan (inv(Tr)·P·Tr), where poses and calibration exist.
    pub poses: Option<Vec<Pose>>,
    /// Each scan's time (ns) from a KITTI `<dir>/times.txt`, where one exists.
    pub times: Option<Vec<u64>>,
    /// Read at most this many scans.
    pub limit: Option<usize>,
}

impl Sequence {
    /// Opens `<dir>` (with `velodyne/`), a plain folder of scans, a scan file or a
    /// recording. `poses`/`calib` override the default `<dir>/poses.txt` and
    /// `<dir>/calib.txt` (a file or recording has no default). Poses with a calibration are
    /// KITTI camera poses, moved into the LiDAR frame by its `Tr`; poses without one are
    /// the LiDAR's own (as kiss-icp and most odometry write them), and the log says so.
    /// Without poses, scans have no pose. Labels are `<dir>/labels/` where it exists (see
    /// [`Self::with_labels`]).
    pub fn open(
        dir: &Path,
        poses: Option<&Path>,
        calib: Option<&Path>,
    ) -> Result<Self, SequenceError> {
        let source = ScanSource::open(dir, None)?;
        let folder = dir.is_dir();
        // Labels where every command looks for them; a recording's only beside it in its
        // folder's `labels/` (named by message index).
        let label_dir = match &source {
            ScanSource::Files(_) => groundwork_io::label_folder(dir),
            ScanSource::Recording { .. } => {
                Some(dir.join("labels")).filter(|l| folder && l.is_dir())
            }
        };
        let default = |name: &str| folder.then(|| dir.join(name));
        let poses_path = poses
            .map(Path::to_path_buf)
            .or_else(|| default("poses.txt"));
        let calib_path = calib
            .map(Path::to_path_buf)
            .or_else(|| default("calib.txt"));
        // A file named on the command line must exist; the defaults are looked for.
        for given in [poses, calib].into_iter().flatten() {
            if !given.is_file() {
                return Err(SequenceError::Layout {
                    path: given.to_path_buf(),
                    message: "no such file".into(),
                });
            }
        }
        let poses_path = poses_path.filter(|p| p.is_file());
        let calib_path = calib_path.filter(|c| c.is_file());
        let poses = match (poses_path, calib_path) {
            (Some(p), c) => {
                let read = read_poses(&p)?;
                if let Some(n) = source.len_hint().filter(|&n| read.len() < n) {
                    return Err(SequenceError::Layout {
                        path: p,
                        message: format!("{} poses for {n} scans", read.len()),
                    });
                }
                match c {
                    Some(c) => {
                        info!(
                            "{}: KITTI camera poses, moved into the LiDAR frame by Tr of {}",
                            p.display(),
                            c.display()
                        );
                        Some(lidar_poses(&read, &read_calib_tr(&c)?))
                    }
                    None => {
                        warn!(
                            "{}: no calibration beside it: the poses are taken as the LiDAR's own (world from sensor); give --calib if they are KITTI camera poses",
                            p.display()
                        );
                        Some(read)
                    }
                }
            }
            (None, Some(c)) if calib.is_some() => {
                return Err(SequenceError::Layout {
                    path: c,
                    message: "a calibration without poses: give --poses too".into(),
                });
            }
            _ => None,
        };
        let times = match default("times.txt").filter(|t| t.is_file()) {
            Some(t) => {
                let read = read_times(&t)?;
                if let Some(n) = source.len_hint().filter(|&n| read.len() < n) {
                    return Err(SequenceError::Layout {
                        path: t,
                        message: format!("{} times for {n} scans", read.len()),
                    });
                }
                Some(read)
            }
            None => None,
        };
        Ok(Self {
            source,
            label_dir,
            label_map: LabelMap::semantickitti(),
            poses,
            times,
            limit: None,
        })
    }

    /// Reads labels from this folder instead.
    pub fn with_labels(mut self, dir: PathBuf) -> Self {
        self.label_dir = Some(dir);
        self
    }

    /// Reads labels with this map (`--labels-format`).
    pub fn with_label_map(mut self, map: LabelMap) -> Self {
        self.label_map = map;
        self
    }

    /// Reads the PointCloud2 messages of this topic (recordings only).
    pub fn with_topic(mut self, topic: Option<String>) -> Self {
        if let ScanSource::Recording { topic: t, .. } = &mut self.source {
            *t = topic;
        }
        self
    }

    /// The scans in order (at most `limit`), each at most `max_points` points.
    pub fn scans(&self, max_points: usize) -> impl Iterator<Item = ScanItem> + use<> {
        // A KITTI folder's times.txt times its scans as a recording's log does.
        let times = self.times.clone();
        self.source
            .scans(max_points)
            .take(self.limit.unwrap_or(usize::MAX))
            .map(move |mut item| {
                if item.log_time_ns.is_none() {
                    item.log_time_ns = times.as_ref().and_then(|t| t.get(item.index).copied());
                }
                item
            })
    }

    /// Scans to expect, where known before reading.
    pub fn len_hint(&self) -> Option<usize> {
        let n = self.source.len_hint()?;
        Some(self.limit.map_or(n, |l| l.min(n)))
    }

    /// The pose of the index-th scan, if poses are known.
    pub fn pose(&self, index: usize) -> Option<&Pose> {
        self.poses.as_ref().and_then(|p| p.get(index))
    }

    /// The label file of a scan, if it exists.
    pub fn label_path(&self, item: &ScanItem) -> Option<PathBuf> {
        let stem = match &self.source {
            ScanSource::Files(_) => item.name.clone(),
            ScanSource::Recording { .. } => format!("{:06}", item.index),
        };
        let l = self.label_map.file_for(self.label_dir.as_ref()?, &stem);
        l.is_file().then_some(l)
    }
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
    let mut probs = Vec::new();
    let mut skipped = Vec::new();
    for item in seq.scans(max) {
        match score_one(seq, segmenter, protocol, thr, &item, &mut probs) {
            Ok(r) => {
                if let Some(c) = &r.confusion {
                    pooled.merge(c);
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
    let confusion = match seq.label_path(item) {
        Some(l) => {
            // Labels are per record of the input: placeholders the reader left out are
            // scored as the non-ground they were given (probability 0).
            let labels = seq.label_map.read(&l, scan.records)?;
            let all = scan.expand(probs, 0.0);
            Some(Confusion::from_predictions(&all, &labels, protocol, thr))
        }
        None => None,
    };
    Ok(ScanResult {
        name: item.name.clone(),
        points: points.len(),
        metrics: confusion.as_ref().map(Confusion::metrics),
        confusion,
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
