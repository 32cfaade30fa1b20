//! A sequence of scans as every command reads it: a KITTI-layout folder
//! (`velodyne/*.bin`, `labels/`, `poses.txt` with `calib.txt`, `times.txt`), a plain folder
//! of scans in any format, a single scan file, or a recording; with its labels, poses and
//! times where they exist.

use std::path::{Path, PathBuf};

use groundwork_core::Pose;
use tracing::{info, warn};

use crate::{
    FormatError, LabelMap, ScanItem, ScanSource, lidar_poses, read_calib_tr, read_poses, read_times,
};

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
    ) -> Result<Self, FormatError> {
        let source = ScanSource::open(dir, None)?;
        let folder = dir.is_dir();
        // Labels where every command looks for them; a recording's only beside it in its
        // folder's `labels/` (named by message index).
        let label_dir = match &source {
            ScanSource::Files(_) => crate::label_folder(dir),
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
                return Err(FormatError::malformed(given, "no such file"));
            }
        }
        let poses_path = poses_path.filter(|p| p.is_file());
        let calib_path = calib_path.filter(|c| c.is_file());
        let poses = match (poses_path, calib_path) {
            (Some(p), c) => {
                let read = read_poses(&p)?;
                if let Some(n) = source.len_hint().filter(|&n| read.len() < n) {
                    return Err(FormatError::malformed(
                        &p,
                        format!("{} poses for {n} scans", read.len()),
                    ));
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
                return Err(FormatError::malformed(
                    &c,
                    "a calibration without poses: give --poses too",
                ));
            }
            _ => None,
        };
        let times = match default("times.txt").filter(|t| t.is_file()) {
            Some(t) => {
                let read = read_times(&t)?;
                if let Some(n) = source.len_hint().filter(|&n| read.len() < n) {
                    return Err(FormatError::malformed(
                        &t,
                        format!("{} times for {n} scans", read.len()),
                    ));
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
