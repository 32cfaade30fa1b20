//! Headerless little-endian f32 records: KITTI velodyne `.bin` (x, y, z, intensity) and
//! nuScenes `.pcd.bin` (x, y, z, intensity, ring index).

use std::path::Path;

use groundwork_core::Point;

use crate::error::FormatError;
use crate::scan::{NonFinite, Scan, checked_count, read_records};

/// KITTI and nuScenes: headerless little-endian f32 records, x, y, z, intensity first.
pub(crate) fn read(path: &Path, max_points: usize, floats: usize) -> Result<Scan, FormatError> {
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

/// Writes a KITTI `.bin` scan (used by tests and tools that generate scans) through a
/// temporary name: a failed write leaves no cut scan that would read as a shorter one.
pub fn write_kitti_bin(path: &Path, points: &[Point]) -> Result<(), FormatError> {
    crate::output::write_atomic(path, &kitti_bin_bytes(points))
}

/// The bytes [`write_kitti_bin`] writes.
pub fn kitti_bin_bytes(points: &[Point]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(points.len() * 16);
    for p in points {
        for v in [p.x, p.y, p.z, p.intensity] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
