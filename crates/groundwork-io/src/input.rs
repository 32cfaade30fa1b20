//! What a command is pointed at: a scan file, a folder of scans (any mix of formats; a
//! KITTI sequence folder with `velodyne/`), or an MCAP recording. Each is a sequence of
//! scans in order, read one at a time.

use std::path::{Path, PathBuf};

use crate::error::FormatError;
use crate::recording::RecordingReader;
use crate::scan::{InputKind, Scan, list_scans, read_scan, scan_stem};

/// Where the scans of one input come from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ScanSource {
    /// Scan files in this order.
    Files(Vec<PathBuf>),
    /// The PointCloud2 messages of one topic of a recording (None: its first
    /// PointCloud2 topic).
    Recording {
        /// The MCAP file.
        path: PathBuf,
        /// The topic to read.
        topic: Option<String>,
    },
}

/// One scan of an input, or why it could not be read.
#[derive(Debug)]
pub struct ScanItem {
    /// Place in its input, from 0 (unreadable scans count too, so poses stay aligned).
    pub index: usize,
    /// Name for outputs: the file's stem, or `<recording stem>_<index:06>`.
    pub name: String,
    /// The scan.
    pub scan: Result<Scan, FormatError>,
    /// Recorded time (recordings only), ns.
    pub log_time_ns: Option<u64>,
    /// Topic (recordings only).
    pub topic: Option<String>,
}

impl ScanSource {
    /// Resolves a path: a folder (its `velodyne/` if present) lists its scan files; an
    /// MCAP recording is a source of its own; any other file is one scan.
    pub fn open(path: &Path, topic: Option<&str>) -> Result<Self, FormatError> {
        if path.is_dir() {
            let velodyne = path.join("velodyne");
            let dir = if velodyne.is_dir() {
                velodyne
            } else {
                path.to_path_buf()
            };
            let files = list_scans(&dir)?;
            if files.is_empty() {
                return Err(FormatError::Unsupported {
                    path: dir,
                    expected: "a folder holding scan files",
                });
            }
            return Ok(Self::Files(files));
        }
        match InputKind::detect(path)? {
            InputKind::Recording => Ok(Self::Recording {
                path: path.to_path_buf(),
                topic: topic.map(str::to_string),
            }),
            InputKind::Scan(_) => Ok(Self::Files(vec![path.to_path_buf()])),
        }
    }

    /// Scans in the source, where known without reading it (files: yes; recordings: no).
    pub fn len_hint(&self) -> Option<usize> {
        match self {
            Self::Files(f) => Some(f.len()),
            Self::Recording { .. } => None,
        }
    }

    /// Reads the scans in order, at most `max_points` points each.
    pub fn scans(&self, max_points: usize) -> ScanIter {
        match self {
            Self::Files(files) => ScanIter::Files {
                files: files.clone(),
                next: 0,
                max_points,
            },
            Self::Recording { path, topic } => ScanIter::Recording {
                stem: scan_stem(path),
                reader: RecordingReader::open(path, topic.as_deref(), max_points)
                    .map(Box::new)
                    .map_err(Some),
                next: 0,
            },
        }
    }
}

/// The scans of a [`ScanSource`], in order.
#[derive(Debug)]
pub enum ScanIter {
    /// From files.
    Files {
        /// The files.
        files: Vec<PathBuf>,
        /// Next to read.
        next: usize,
        /// Point limit.
        max_points: usize,
    },
    /// From a recording (the error of opening it is reported once, as the first item).
    Recording {
        /// Name prefix for outputs.
        stem: String,
        /// The reader, or the error opening it (taken when reported).
        reader: Result<Box<RecordingReader>, Option<FormatError>>,
        /// Messages reported so far.
        next: usize,
    },
}

impl Iterator for ScanIter {
    type Item = ScanItem;

    fn next(&mut self) -> Option<ScanItem> {
        match self {
            Self::Files {
                files,
                next,
                max_points,
            } => {
                let path = files.get(*next)?;
                let item = ScanItem {
                    index: *next,
                    name: scan_stem(path),
                    scan: read_scan(path, *max_points),
                    log_time_ns: None,
                    topic: None,
                };
                *next += 1;
                Some(item)
            }
            Self::Recording { stem, reader, next } => {
                let item = match reader {
                    Err(e) => {
                        let e = e.take()?;
                        ScanItem {
                            index: 0,
                            name: format!("{stem}_{:06}", 0),
                            scan: Err(e),
                            log_time_ns: None,
                            topic: None,
                        }
                    }
                    Ok(r) => {
                        let index = *next;
                        match r.next()? {
                            Ok(rec) => ScanItem {
                                index: rec.index,
                                name: format!("{stem}_{:06}", rec.index),
                                scan: Ok(rec.scan),
                                log_time_ns: Some(rec.log_time_ns),
                                topic: Some(rec.topic),
                            },
                            Err(e) => ScanItem {
                                index,
                                name: format!("{stem}_{index:06}"),
                                scan: Err(e),
                                log_time_ns: None,
                                topic: r.topic().map(str::to_string),
                            },
                        }
                    }
                };
                *next = item.index + 1;
                Some(item)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use groundwork_core::Point;

    use crate::recording::RecordingWriter;
    use crate::scan::write_kitti_bin;

    #[test]
    fn files_and_recordings_read_alike_and_bad_scans_keep_their_place() {
        let dir = tempfile::tempdir().unwrap();
        write_kitti_bin(&dir.path().join("000000.bin"), &[Point::new(1.0, 0.0, 0.0)]).unwrap();
        std::fs::write(dir.path().join("000001.bin"), [1u8, 2, 3]).unwrap();
        write_kitti_bin(&dir.path().join("000002.bin"), &[Point::new(2.0, 0.0, 0.0)]).unwrap();
        let src = ScanSource::open(dir.path(), None).unwrap();
        let items: Vec<_> = src.scans(10).collect();
        assert_eq!(items.len(), 3);
        assert!(items[1].scan.is_err());
        assert_eq!((items[2].index, items[2].name.as_str()), (2, "000002"));

        let rec = dir.path().join("drive.mcap");
        let mut w = RecordingWriter::create(&rec).unwrap();
        for k in 0..2u64 {
            let s = Scan::dense(vec![Point::new(k as f32 + 1.0, 0.0, 0.0)]);
            w.write("/lidar", &s, &[0.0], 100 * k).unwrap();
        }
        w.finish().unwrap();
        let src = ScanSource::open(&rec, None).unwrap();
        assert_eq!(src.len_hint(), None);
        let items: Vec<_> = src.scans(10).collect();
        assert_eq!(items.len(), 2);
        assert_eq!(items[1].name, "drive_000001");
        assert_eq!(items[1].log_time_ns, Some(100));
        assert_eq!(items[1].scan.as_ref().unwrap().points[0].x, 2.0);

        // A folder with nothing to read, and a recording that is not one.
        let empty = tempfile::tempdir().unwrap();
        assert!(ScanSource::open(empty.path(), None).is_err());
        std::fs::write(dir.path().join("junk.mcap"), b"not mcap").unwrap();
        let items: Vec<_> = ScanSource::open(&dir.path().join("junk.mcap"), None)
            .unwrap()
            .scans(10)
            .collect();
        assert_eq!(items.len(), 1);
        let e = items[0].scan.as_ref().unwrap_err().to_string();
        assert!(e.contains("junk.mcap"), "{e}");
    }
}
