//! What a command is pointed at: a scan file, a folder of scans (any mix of formats; a
//! KITTI sequence folder with `velodyne/`), or an MCAP recording. Each is a sequence of
//! scans in order, read one at a time.
//!
//! The reader is chosen from the file, never from a flag: first by the name's extension,
//! then (for any other name) by the magic bytes at its start.
//!
//! | format | extension | magic |
//! |---|---|---|
//! | KITTI velodyne (4 × f32 LE: x, y, z, intensity) | `.bin` | — |
//! | nuScenes (5 × f32 LE: x, y, z, intensity, ring) | `.pcd.bin` | — |
//! | PCD ascii / binary / binary_compressed | `.pcd` | `# .PCD`, `VERSION`, `FIELDS` |
//! | PLY ascii / binary | `.ply` | `ply` |
//! | MCAP recording of PointCloud2 (many scans) | `.mcap` | `\x89MCAP` |
//! | rosbag2 SQLite bag file of PointCloud2 (many scans) | `.db3` | `SQLite format 3` |

use std::fs;
use std::path::{Path, PathBuf};

use crate::error::FormatError;
use crate::recording::RecordingReader;
use crate::scan::Scan;

/// A single-scan file format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanFormat {
    /// KITTI / SemanticKITTI velodyne `.bin`: x, y, z, intensity as f32.
    KittiBin,
    /// nuScenes `.pcd.bin`: x, y, z, intensity, ring index as f32.
    NuScenesBin,
    /// Point Cloud Library `.pcd` (ascii, binary or binary_compressed).
    Pcd,
    /// Stanford `.ply` vertices (ascii or binary).
    Ply,
}

/// What a file holds: one scan, or a recording of many.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputKind {
    /// One scan in this format.
    Scan(ScanFormat),
    /// A recording of ROS 2 `sensor_msgs/msg/PointCloud2` messages: MCAP, or rosbag2's
    /// SQLite storage.
    Recording,
}

/// The names a reader accepts, for error messages.
pub const SUPPORTED: &str = "KITTI .bin, nuScenes .pcd.bin, .pcd, .ply, or a recording of PointCloud2 (.mcap, or a rosbag2 .db3)";

const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

impl InputKind {
    /// The kind its name says, if the extension is known.
    pub fn from_name(path: &Path) -> Option<Self> {
        // Lossy: a name that is not UTF-8 is still a scan by its extension.
        let name = path.file_name()?.to_string_lossy().to_ascii_lowercase();
        let kind = if name.ends_with(".pcd.bin") {
            Self::Scan(ScanFormat::NuScenesBin)
        } else if name.ends_with(".bin") {
            Self::Scan(ScanFormat::KittiBin)
        } else if name.ends_with(".pcd") {
            Self::Scan(ScanFormat::Pcd)
        } else if name.ends_with(".ply") {
            Self::Scan(ScanFormat::Ply)
        } else if name.ends_with(".mcap") || name.ends_with(".db3") {
            Self::Recording
        } else {
            return None;
        };
        Some(kind)
    }

    /// The kind the first bytes of a file say, if they carry a known magic.
    pub fn from_magic(head: &[u8]) -> Option<Self> {
        let text = |prefix: &[u8]| head.starts_with(prefix);
        if head.starts_with(MCAP_MAGIC) || head.starts_with(crate::rosbag2::MAGIC) {
            Some(Self::Recording)
        } else if text(b"ply\n") || text(b"ply\r\n") {
            Some(Self::Scan(ScanFormat::Ply))
        } else if text(b"# .PCD") || text(b"VERSION") || text(b"FIELDS") {
            Some(Self::Scan(ScanFormat::Pcd))
        } else {
            None
        }
    }

    /// Extension first, then magic bytes.
    pub fn detect(path: &Path) -> Result<Self, FormatError> {
        if let Some(kind) = Self::from_name(path) {
            return Ok(kind);
        }
        let mut head = [0u8; 16];
        let (mut file, _) = crate::file::open_regular(path)?;
        let n = crate::file::read_head(path, &mut file, &mut head)?;
        Self::from_magic(&head[..n]).ok_or_else(|| FormatError::Unsupported {
            path: path.to_path_buf(),
            expected: SUPPORTED,
        })
    }
}

/// Reads a single-scan file of any supported format (see the module documentation).
/// Rejects truncated files, lying headers, empty scans, non-finite coordinates (where the
/// format has no placeholders) and scans of more than `max_points` records, the latter
/// checked before the points are read.
pub fn read_scan(path: &Path, max_points: usize) -> Result<Scan, FormatError> {
    match InputKind::detect(path)? {
        InputKind::Scan(ScanFormat::KittiBin) => crate::bin::read(path, max_points, 4),
        InputKind::Scan(ScanFormat::NuScenesBin) => crate::bin::read(path, max_points, 5),
        InputKind::Scan(ScanFormat::Pcd) => crate::pcd::read(path, max_points),
        InputKind::Scan(ScanFormat::Ply) => crate::ply::read(path, max_points),
        InputKind::Recording => Err(FormatError::malformed(
            path,
            "an MCAP recording holds many scans: give it as an input of its own (like a folder)",
        )),
    }
}

/// The single-scan files of a folder, any mix of formats, sorted by name. Files without a
/// known extension are included when their magic bytes say they are scans; recordings are
/// not scans of a folder (give them as inputs of their own).
///
/// An entry named as a scan is listed whatever it is, so that a dangling symlink, a FIFO
/// or a device named `000042.bin` reaches the reader and is reported and counted as a
/// scan that could not be read, never skipped in silence; names that are not UTF-8 are
/// read too (outputs take their lossy name).
pub fn list_scans(dir: &Path) -> Result<Vec<PathBuf>, FormatError> {
    list_folder(dir).map(|c| c.scans)
}

/// What a folder holds, from one listing of it: its single-scan files (as
/// [`list_scans`] gives them) and its MCAP recordings, each sorted by name.
#[derive(Debug, Default)]
pub struct FolderContents {
    /// The single-scan files.
    pub scans: Vec<PathBuf>,
    /// The recordings.
    pub recordings: Vec<PathBuf>,
}

/// Lists a folder's scans and recordings (see [`FolderContents`]).
pub fn list_folder(dir: &Path) -> Result<FolderContents, FormatError> {
    let mut found = FolderContents::default();
    for entry in fs::read_dir(dir).map_err(|e| FormatError::io(dir, e))? {
        let path = entry.map_err(|e| FormatError::io(dir, e))?.path();
        match kind_in_folder(&path) {
            Some(InputKind::Scan(_)) => found.scans.push(path),
            Some(InputKind::Recording) => found.recordings.push(path),
            None => {}
        }
    }
    found.scans.sort();
    found.recordings.sort();
    Ok(found)
}

/// What a folder's entry is, by its name, else (for a regular file without an extension)
/// by its magic bytes.
fn kind_in_folder(path: &Path) -> Option<InputKind> {
    InputKind::from_name(path).or_else(|| {
        // Only unnamed regular files are sniffed: a `.label`, `.txt` or `.prob` is never
        // a scan, and sniffing a FIFO would block.
        (path.extension().is_none() && path.is_file())
            .then(|| InputKind::detect(path).ok())
            .flatten()
    })
}

/// A scan file's stem without its format suffix (`000042.bin` → `000042`,
/// `n015-…__LIDAR_TOP__1533.pcd.bin` → `n015-…__LIDAR_TOP__1533`, `cloud.pcd` → `cloud`).
pub fn scan_stem(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let lower = name.to_ascii_lowercase();
    for suffix in [".pcd.bin", ".bin", ".pcd", ".ply", ".mcap", ".db3"] {
        if lower.ends_with(suffix) {
            return name[..name.len() - suffix.len()].to_string();
        }
    }
    name
}

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
    /// Recorded time, ns: a recording's log time (or, through a `Sequence`, the time its
    /// folder's `times.txt` gives the scan).
    pub log_time_ns: Option<u64>,
    /// Topic (recordings only).
    pub topic: Option<String>,
    /// The recorded message the scan was decoded from (recordings only): a recording
    /// written from it keeps every field.
    pub message: Option<std::sync::Arc<[u8]>>,
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
            let FolderContents {
                scans: files,
                recordings,
            } = list_folder(&dir)?;
            let names = || {
                let n: Vec<String> = recordings
                    .iter()
                    .map(|r| {
                        r.file_name()
                            .unwrap_or_default()
                            .to_string_lossy()
                            .into_owned()
                    })
                    .collect();
                n.join(", ")
            };
            // A folder is one sequence: its scan files, or its one recording. A recording
            // beside scan files is refused by name, never passed over in silence.
            return match (files.is_empty(), recordings.len()) {
                (false, 0) => Ok(Self::Files(files)),
                (true, 1) => Ok(Self::Recording {
                    path: recordings[0].clone(),
                    topic: topic.map(str::to_string),
                }),
                (true, 0) => Err(FormatError::Unsupported {
                    path: dir,
                    expected: "a folder holding scan files",
                }),
                (true, _) => Err(FormatError::malformed(
                    &dir,
                    format!(
                        "holds the recordings {} and no scan files: a folder is one sequence, \
                         so give each recording as an input of its own",
                        names()
                    ),
                )),
                (false, _) => Err(FormatError::malformed(
                    &dir,
                    format!(
                        "holds {} scan file(s) and the recording(s) {}: a folder is one \
                         sequence of scan files, so give each recording as an input of its own \
                         (and the scans in a folder without it)",
                        files.len(),
                        names()
                    ),
                )),
            };
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
                    message: None,
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
                            message: None,
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
                                message: Some(rec.message),
                            },
                            Err(e) => ScanItem {
                                index,
                                name: format!("{stem}_{index:06}"),
                                scan: Err(e),
                                log_time_ns: None,
                                topic: r.topic().map(str::to_string),
                                message: None,
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
    use crate::bin::write_kitti_bin;
    use crate::recording::RecordingWriter;
    use groundwork_core::Point;

    #[test]
    fn round_trip_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("000001.bin");
        let pts = vec![Point::new(1.0, 2.0, 3.0), Point::new(-1.0, 0.5, -1.7)];
        write_kitti_bin(&p, &pts).unwrap();
        assert_eq!(read_scan(&p, 10).unwrap(), Scan::dense(pts));

        // Too many points, checked before reading.
        let e = read_scan(&p, 1).unwrap_err().to_string();
        assert!(
            e.contains("000001.bin") && e.contains("maximum of 1"),
            "{e}"
        );

        // Truncated: 2 points and 3 bytes of a third.
        let mut bytes = fs::read(&p).unwrap();
        bytes.extend_from_slice(&[0, 0, 128]);
        fs::write(&p, &bytes).unwrap();
        let e = read_scan(&p, 10).unwrap_err().to_string();
        assert!(e.contains("000001.bin") && e.contains("35 bytes"), "{e}");

        // Empty.
        fs::write(&p, []).unwrap();
        let e = read_scan(&p, 10).unwrap_err().to_string();
        assert!(e.contains("empty scan"), "{e}");

        // NaN: KITTI has no placeholders, so it is corruption.
        write_kitti_bin(&p, &[Point::new(1.0, f32::NAN, 0.0)]).unwrap();
        let e = read_scan(&p, 10).unwrap_err().to_string();
        assert!(e.contains("point 0") && e.contains("non-finite"), "{e}");

        // Missing file.
        let e = read_scan(&dir.path().join("nope.bin"), 10)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.bin"), "{e}");

        // Unknown extension and no magic.
        fs::write(dir.path().join("a.txt"), "hello").unwrap();
        let e = read_scan(&dir.path().join("a.txt"), 10)
            .unwrap_err()
            .to_string();
        assert!(e.contains("a.txt") && e.contains("unsupported"), "{e}");
    }

    #[test]
    fn odd_entries_of_a_folder_are_listed_to_be_reported_not_skipped() {
        use std::os::unix::ffi::OsStrExt;
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        write_kitti_bin(&d.join("000000.bin"), &[Point::new(1.0, 0.0, 0.0)]).unwrap();
        std::os::unix::fs::symlink(d.join("gone.bin"), d.join("000001.bin")).unwrap();
        std::os::unix::fs::symlink("/dev/zero", d.join("000002.bin")).unwrap();
        let odd = d.join(std::ffi::OsStr::from_bytes(b"00000\xff.bin"));
        write_kitti_bin(&odd, &[Point::new(2.0, 0.0, 0.0)]).unwrap();
        fs::write(d.join("notes.txt"), "not a scan").unwrap();
        let files = list_scans(d).unwrap();
        assert_eq!(files.len(), 4, "{files:?}");
        let results: Vec<_> = files.iter().map(|f| read_scan(f, 10)).collect();
        assert!(results[0].is_ok());
        let dangling = results[1].as_ref().unwrap_err().to_string();
        assert!(dangling.contains("000001.bin"), "{dangling}");
        let zero = results[2].as_ref().unwrap_err().to_string();
        assert!(
            zero.contains("000002.bin") && zero.contains("device"),
            "{zero}"
        );
        assert_eq!(results[3].as_ref().unwrap().points[0].x, 2.0);
    }

    #[test]
    fn nuscenes_records_are_five_floats() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.pcd.bin");
        let vals: [f32; 10] = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0];
        let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        fs::write(&p, bytes).unwrap();
        let scan = read_scan(&p, 10).unwrap();
        assert_eq!(scan.points.len(), 2);
        assert_eq!(
            scan.points[1],
            Point {
                x: 6.0,
                y: 7.0,
                z: 8.0,
                intensity: 9.0
            }
        );
        assert_eq!(scan_stem(&p), "x");
    }

    #[test]
    fn magic_bytes_decide_for_unknown_names() {
        assert_eq!(
            InputKind::from_magic(b"ply\nformat ascii 1.0\n"),
            Some(InputKind::Scan(ScanFormat::Ply))
        );
        assert_eq!(
            InputKind::from_magic(b"# .PCD v0.7 - Point"),
            Some(InputKind::Scan(ScanFormat::Pcd))
        );
        assert_eq!(
            InputKind::from_magic(b"\x89MCAP0\r\n\x01"),
            Some(InputKind::Recording)
        );
        assert_eq!(InputKind::from_magic(b"\x00\x00\x80?"), None);
        // The name wins where it is known.
        assert_eq!(
            InputKind::from_name(Path::new("a/B.PLY")),
            Some(InputKind::Scan(ScanFormat::Ply))
        );
        assert_eq!(InputKind::from_name(Path::new("scan")), None);
    }

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

        // A folder is one sequence: a recording beside its scans is refused by name, a
        // folder holding only one recording is that recording.
        let e = ScanSource::open(dir.path(), None).unwrap_err().to_string();
        assert!(
            e.contains("drive.mcap") && e.contains("3 scan file(s)"),
            "{e}"
        );
        let only = tempfile::tempdir().unwrap();
        std::fs::copy(&rec, only.path().join("drive.mcap")).unwrap();
        assert_eq!(
            ScanSource::open(only.path(), Some("/lidar")).unwrap(),
            ScanSource::Recording {
                path: only.path().join("drive.mcap"),
                topic: Some("/lidar".into())
            }
        );
        std::fs::copy(&rec, only.path().join("again.mcap")).unwrap();
        let e = ScanSource::open(only.path(), None).unwrap_err().to_string();
        assert!(e.contains("again.mcap, drive.mcap"), "{e}");

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
