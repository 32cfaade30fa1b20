//! Point cloud files. The reader is chosen from the file, never from a flag: first by the
//! name's extension, then (for any other name) by the magic bytes at its start.
//!
//! | format | extension | magic |
//! |---|---|---|
//! | KITTI velodyne (4 × f32 LE: x, y, z, intensity) | `.bin` | — |
//! | nuScenes (5 × f32 LE: x, y, z, intensity, ring) | `.pcd.bin` | — |
//! | PCD ascii / binary / binary_compressed | `.pcd` | `# .PCD`, `VERSION`, `FIELDS` |
//! | PLY ascii / binary | `.ply` | `ply` |
//! | MCAP recording of PointCloud2 (many scans) | `.mcap` | `\x89MCAP` |

use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};

use groundwork_core::Point;

use crate::error::FormatError;

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
    /// An MCAP recording (ROS 2 `sensor_msgs/msg/PointCloud2` messages).
    Recording,
}

/// The names a reader accepts, for error messages.
pub const SUPPORTED: &str =
    "KITTI .bin, nuScenes .pcd.bin, .pcd, .ply or an .mcap recording of PointCloud2";

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
        } else if name.ends_with(".mcap") {
            Self::Recording
        } else {
            return None;
        };
        Some(kind)
    }

    /// The kind the first bytes of a file say, if they carry a known magic.
    pub fn from_magic(head: &[u8]) -> Option<Self> {
        let text = |prefix: &[u8]| head.starts_with(prefix);
        if head.starts_with(MCAP_MAGIC) {
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
        let mut n = 0;
        while n < head.len() {
            match file.read(&mut head[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(FormatError::io(path, e)),
            }
        }
        Self::from_magic(&head[..n]).ok_or_else(|| FormatError::Unsupported {
            path: path.to_path_buf(),
            expected: SUPPORTED,
        })
    }
}

/// One scan as read from a file or a recorded message.
///
/// `points` holds only points with finite coordinates. Formats that mark missing returns
/// with NaN placeholders (an organized or non-dense PCD or PointCloud2) lose those points
/// here; `source_index` then maps every point back to its record, so that an output per
/// record (`.prob`, a written PointCloud2) still lines up with the input.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scan {
    /// Finite points in record order (sensor frame, metres).
    pub points: Vec<Point>,
    /// Record index of each point, where records were left out (`None`: point i is
    /// record i).
    pub source_index: Option<Vec<u32>>,
    /// Records in the input, placeholders included.
    pub records: usize,
    /// Rows × columns of an organized cloud (height > 1), as the input gave them.
    pub organized: Option<(u32, u32)>,
    /// Sensor time of the scan, ns, where the format carries one.
    pub stamp_ns: Option<u64>,
    /// Coordinate frame name, where the format carries one (PointCloud2 `frame_id`).
    pub frame_id: Option<String>,
}

/// What a reader does with a record whose x, y or z is NaN or infinite.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum NonFinite {
    /// Corruption: the whole file is an error naming the first such record.
    Reject,
    /// A no-return placeholder the format allows: left out, mapped back.
    Skip,
}

impl Scan {
    /// A scan whose every record is a point.
    pub fn dense(points: Vec<Point>) -> Self {
        Self {
            records: points.len(),
            points,
            ..Self::default()
        }
    }

    /// Builds a scan from decoded records, applying the format's rule for non-finite
    /// coordinates. An empty result is an error.
    pub(crate) fn from_records(
        path: &Path,
        records: Vec<Point>,
        rule: NonFinite,
    ) -> Result<Self, FormatError> {
        if records.is_empty() {
            return Err(FormatError::Empty {
                path: path.to_path_buf(),
            });
        }
        let finite = |p: &Point| p.x.is_finite() && p.y.is_finite() && p.z.is_finite();
        let Some(first_bad) = records.iter().position(|p| !finite(p)) else {
            return Ok(Self::dense(records));
        };
        if rule == NonFinite::Reject {
            let p = records[first_bad];
            return Err(FormatError::NonFinite {
                path: path.to_path_buf(),
                index: first_bad,
                x: p.x,
                y: p.y,
                z: p.z,
            });
        }
        let n = records.len();
        let (mut points, mut index) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for (i, p) in records.into_iter().enumerate() {
            if finite(&p) {
                points.push(p);
                index.push(i as u32);
            }
        }
        if points.is_empty() {
            return Err(FormatError::malformed(
                path,
                format!("none of its {n} points has finite coordinates"),
            ));
        }
        Ok(Self {
            points,
            source_index: Some(index),
            records: n,
            ..Self::default()
        })
    }

    /// Records left out as placeholders.
    pub fn skipped(&self) -> usize {
        self.records - self.points.len()
    }

    /// Spreads one value per point back over the records, `fill` for left-out ones.
    pub fn expand<T: Copy>(&self, values: &[T], fill: T) -> Vec<T> {
        match &self.source_index {
            None => values.to_vec(),
            Some(index) => {
                let mut out = vec![fill; self.records];
                for (&i, &v) in index.iter().zip(values) {
                    out[i as usize] = v;
                }
                out
            }
        }
    }

    /// The inverse of [`Scan::expand`]: from one value per record (a `.prob` or `.label`
    /// file) the values of the points, in point order. `per_record` must hold
    /// [`Scan::records`] values.
    pub fn select<T: Copy>(&self, per_record: Vec<T>) -> Vec<T> {
        match &self.source_index {
            None => per_record,
            Some(index) => index.iter().map(|&i| per_record[i as usize]).collect(),
        }
    }
}

/// Reads a single-scan file of any supported format (see the module documentation).
/// Rejects truncated files, lying headers, empty scans, non-finite coordinates (where the
/// format has no placeholders) and scans of more than `max_points` records, the latter
/// checked before the points are read.
pub fn read_scan(path: &Path, max_points: usize) -> Result<Scan, FormatError> {
    match InputKind::detect(path)? {
        InputKind::Scan(ScanFormat::KittiBin) => read_float_records(path, max_points, 4),
        InputKind::Scan(ScanFormat::NuScenesBin) => read_float_records(path, max_points, 5),
        InputKind::Scan(ScanFormat::Pcd) => crate::pcd::read(path, max_points),
        InputKind::Scan(ScanFormat::Ply) => crate::ply::read(path, max_points),
        InputKind::Recording => Err(FormatError::malformed(
            path,
            "an MCAP recording holds many scans: give it as an input of its own (like a folder)",
        )),
    }
}

/// The file size, and the number of records it holds, checked against the maximum.
pub(crate) fn checked_count(
    path: &Path,
    records: u64,
    max_points: usize,
) -> Result<usize, FormatError> {
    if records > max_points as u64 {
        return Err(FormatError::TooManyPoints {
            path: path.to_path_buf(),
            points: usize::try_from(records).unwrap_or(usize::MAX),
            max: max_points,
        });
    }
    Ok(records as usize)
}

/// Reads a headerless file of `record`-byte records: its size must be whole records, and
/// `check` vets the record count, both before a byte is read (a wrong file may be huge);
/// a file that changed between the two is an error too.
pub(crate) fn read_records(
    path: &Path,
    record: usize,
    check: impl FnOnce(u64) -> Result<(), FormatError>,
) -> Result<Vec<u8>, FormatError> {
    let (file, size) = crate::file::open_regular(path)?;
    if size % record as u64 != 0 {
        return Err(FormatError::Size {
            path: path.to_path_buf(),
            size,
            record,
        });
    }
    check(size / record as u64)?;
    let mut bytes = Vec::with_capacity(size as usize);
    file.take(size)
        .read_to_end(&mut bytes)
        .map_err(|e| FormatError::io(path, e))?;
    if bytes.len() as u64 != size {
        return Err(FormatError::Size {
            path: path.to_path_buf(),
            size: bytes.len() as u64,
            record,
        });
    }
    Ok(bytes)
}

/// KITTI and nuScenes: headerless little-endian f32 records, x, y, z, intensity first.
fn read_float_records(path: &Path, max_points: usize, floats: usize) -> Result<Scan, FormatError> {
    let record = 4 * floats;
    let bytes = read_records(path, record, |n| {
        checked_count(path, n, max_points).map(|_| ())
    })?;
    let f = |b: &[u8], i: usize| {
        f32::from_le_bytes([b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]])
    };
    let points: Vec<Point> = bytes
        .chunks_exact(record)
        .map(|r| Point {
            x: f(r, 0),
            y: f(r, 1),
            z: f(r, 2),
            intensity: f(r, 3),
        })
        .collect();
    let scan = Scan::from_records(path, points, NonFinite::Reject)?;
    if let Some(why) = implausible_layout(&scan.points) {
        tracing::warn!(
            "{}: {why}: is it another layout (3 floats per point, doubles)? Headerless files are read as {floats} little-endian f32 per point; convert others to PCD or KITTI .bin (docs/formats.md)",
            path.display()
        );
    }
    Ok(scan)
}

/// Why the points of a headerless file do not look like a scan, if they do not: a file
/// of another layout (3 floats per point, whose size happens to divide by 16) reads as
/// points whose "intensity" is a coordinate, negative about half the time, where every
/// sensor's intensity or reflectance is ≥ 0.
pub fn implausible_layout(points: &[Point]) -> Option<String> {
    let bad = points
        .iter()
        .filter(|p| !(p.intensity >= 0.0 && p.intensity.is_finite()))
        .count();
    // A few negative intensities occur in converted data; a tenth never does.
    (bad * 10 > points.len()).then(|| {
        format!(
            "{bad} of {} points have a negative or non-finite intensity",
            points.len()
        )
    })
}

/// Writes a KITTI `.bin` scan (used by tests and tools that generate scans).
pub fn write_kitti_bin(path: &Path, points: &[Point]) -> Result<(), FormatError> {
    let mut bytes = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in [p.x, p.y, p.z, p.intensity] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    fs::write(path, bytes).map_err(|e| FormatError::io(path, e))
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
    let mut files = Vec::new();
    for entry in fs::read_dir(dir).map_err(|e| FormatError::io(dir, e))? {
        let path = entry.map_err(|e| FormatError::io(dir, e))?.path();
        if is_scan_file(&path) {
            files.push(path);
        }
    }
    files.sort();
    Ok(files)
}

fn is_scan_file(path: &Path) -> bool {
    match InputKind::from_name(path) {
        Some(kind) => matches!(kind, InputKind::Scan(_)),
        // Only unnamed regular files are sniffed: a `.label`, `.txt` or `.prob` is never
        // a scan, and sniffing a FIFO would block.
        None => {
            path.extension().is_none()
                && path.is_file()
                && matches!(InputKind::detect(path), Ok(InputKind::Scan(_)))
        }
    }
}

/// A scan file's stem without its format suffix (`000042.bin` → `000042`,
/// `n015-…__LIDAR_TOP__1533.pcd.bin` → `n015-…__LIDAR_TOP__1533`, `cloud.pcd` → `cloud`).
pub fn scan_stem(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let lower = name.to_ascii_lowercase();
    for suffix in [".pcd.bin", ".bin", ".pcd", ".ply", ".mcap"] {
        if lower.ends_with(suffix) {
            return name[..name.len() - suffix.len()].to_string();
        }
    }
    name
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn select_is_the_inverse_of_expand() {
        let scan = Scan {
            points: vec![Point::default(); 3],
            source_index: Some(vec![0, 2, 3]),
            records: 5,
            organized: None,
            stamp_ns: None,
            frame_id: None,
        };
        let per_point = [1.0f32, 2.0, 3.0];
        let per_record = scan.expand(&per_point, 0.0);
        assert_eq!(per_record, [1.0, 0.0, 2.0, 3.0, 0.0]);
        assert_eq!(scan.select(per_record), per_point);
        let dense = Scan::dense(vec![Point::default(); 2]);
        assert_eq!(dense.select(vec![7u32, 8]), [7, 8]);
    }

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
    fn three_floats_per_point_read_as_four_are_flagged() {
        // A scan of 8 points, x, y, z only: 96 bytes, which divides by 16.
        let xyz: Vec<f32> = (0..8)
            .flat_map(|i| [10.0 + i as f32, -3.0 + i as f32, -1.7])
            .collect();
        let as_four: Vec<Point> = xyz
            .chunks_exact(4)
            .map(|c| Point {
                x: c[0],
                y: c[1],
                z: c[2],
                intensity: c[3],
            })
            .collect();
        assert!(implausible_layout(&as_four).is_some());
        let real: Vec<Point> = (0..8)
            .map(|i| Point {
                intensity: 0.1 * i as f32,
                ..Point::new(i as f32, 1.0, -1.7)
            })
            .collect();
        assert_eq!(implausible_layout(&real), None);
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
    fn placeholders_map_back_to_their_records() {
        let p = Path::new("c.pcd");
        let recs = vec![
            Point::new(1.0, 0.0, 0.0),
            Point::new(f32::NAN, f32::NAN, f32::NAN),
            Point::new(2.0, 0.0, 0.0),
        ];
        let s = Scan::from_records(p, recs.clone(), NonFinite::Skip).unwrap();
        assert_eq!(s.points.len(), 2);
        assert_eq!(s.skipped(), 1);
        assert_eq!(s.expand(&[0.25, 0.75], -1.0), vec![0.25, -1.0, 0.75]);
        let e = Scan::from_records(p, recs, NonFinite::Reject).unwrap_err();
        assert!(e.to_string().contains("point 1"), "{e}");
        let all_nan = vec![Point::new(f32::NAN, 0.0, 0.0)];
        assert!(Scan::from_records(p, all_nan, NonFinite::Skip).is_err());
    }
}
