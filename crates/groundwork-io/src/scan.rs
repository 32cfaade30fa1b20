//! Point cloud files. The loader is chosen by the file name, not by a flag:
//! `*.pcd.bin` is nuScenes (5 × f32: x, y, z, intensity, ring), `*.bin` is KITTI
//! (4 × f32: x, y, z, intensity), both little-endian.

use std::fs;
use std::path::{Path, PathBuf};

use groundwork_core::Point;

use crate::error::FormatError;

/// Layout of a binary point file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanFormat {
    /// KITTI / SemanticKITTI velodyne `.bin`: x, y, z, intensity as f32.
    KittiBin,
    /// nuScenes `.pcd.bin`: x, y, z, intensity, ring index as f32.
    NuScenesBin,
}

impl ScanFormat {
    /// Picks the format from the file name.
    pub fn from_path(path: &Path) -> Option<Self> {
        let name = path.file_name()?.to_str()?.to_ascii_lowercase();
        if name.ends_with(".pcd.bin") {
            Some(Self::NuScenesBin)
        } else if name.ends_with(".bin") {
            Some(Self::KittiBin)
        } else {
            None
        }
    }

    /// Bytes per point.
    pub fn record_size(self) -> usize {
        match self {
            Self::KittiBin => 16,
            Self::NuScenesBin => 20,
        }
    }
}

/// Reads a scan, rejecting truncated files, empty scans, non-finite coordinates and scans
/// with more than `max_points` points (checked from the file size before reading it).
pub fn read_scan(path: &Path, max_points: usize) -> Result<Vec<Point>, FormatError> {
    let format = ScanFormat::from_path(path).ok_or_else(|| FormatError::Unsupported {
        path: path.to_path_buf(),
        expected: "KITTI .bin or nuScenes .pcd.bin",
    })?;
    let record = format.record_size();
    let size = fs::metadata(path)
        .map_err(|e| FormatError::io(path, e))?
        .len();
    if size % record as u64 != 0 {
        return Err(FormatError::Size {
            path: path.to_path_buf(),
            size,
            record,
        });
    }
    let n = (size / record as u64) as usize;
    if n == 0 {
        return Err(FormatError::Empty {
            path: path.to_path_buf(),
        });
    }
    if n > max_points {
        return Err(FormatError::TooManyPoints {
            path: path.to_path_buf(),
            points: n,
            max: max_points,
        });
    }
    let bytes = fs::read(path).map_err(|e| FormatError::io(path, e))?;
    if bytes.len() != n * record {
        // The file changed between stat and read.
        return Err(FormatError::Size {
            path: path.to_path_buf(),
            size: bytes.len() as u64,
            record,
        });
    }
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
    check_finite(path, &points)?;
    Ok(points)
}

/// Rejects a scan with a NaN or infinite coordinate, naming the first such point.
pub fn check_finite(path: &Path, points: &[Point]) -> Result<(), FormatError> {
    match points
        .iter()
        .position(|p| !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()))
    {
        Some(index) => {
            let p = points[index];
            Err(FormatError::NonFinite {
                path: path.to_path_buf(),
                index,
                x: p.x,
                y: p.y,
                z: p.z,
            })
        }
        None => Ok(()),
    }
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

/// The scan files of a folder (any supported format), sorted by name.
pub fn list_scans(dir: &Path) -> Result<Vec<PathBuf>, FormatError> {
    let mut files: Vec<PathBuf> = fs::read_dir(dir)
        .map_err(|e| FormatError::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && ScanFormat::from_path(p).is_some())
        .collect();
    files.sort();
    Ok(files)
}

/// A scan file's stem without its format suffix (`000042.bin` → `000042`,
/// `n015-…__LIDAR_TOP__1533.pcd.bin` → `n015-…__LIDAR_TOP__1533`).
pub fn scan_stem(path: &Path) -> String {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let lower = name.to_ascii_lowercase();
    for suffix in [".pcd.bin", ".bin"] {
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
    fn round_trip_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("000001.bin");
        let pts = vec![Point::new(1.0, 2.0, 3.0), Point::new(-1.0, 0.5, -1.7)];
        write_kitti_bin(&p, &pts).unwrap();
        assert_eq!(read_scan(&p, 10).unwrap(), pts);

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

        // NaN.
        write_kitti_bin(&p, &[Point::new(1.0, f32::NAN, 0.0)]).unwrap();
        let e = read_scan(&p, 10).unwrap_err().to_string();
        assert!(e.contains("point 0") && e.contains("non-finite"), "{e}");

        // Missing file.
        let e = read_scan(&dir.path().join("nope.bin"), 10)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.bin"), "{e}");

        // Unsupported extension.
        assert!(read_scan(&dir.path().join("a.txt"), 10).is_err());
    }

    #[test]
    fn nuscenes_records_are_five_floats() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.pcd.bin");
        let vals: [f32; 10] = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0];
        let bytes: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        fs::write(&p, bytes).unwrap();
        let pts = read_scan(&p, 10).unwrap();
        assert_eq!(pts.len(), 2);
        assert_eq!(
            pts[1],
            Point {
                x: 6.0,
                y: 7.0,
                z: 8.0,
                intensity: 9.0
            }
        );
        assert_eq!(scan_stem(&p), "x");
    }
}
