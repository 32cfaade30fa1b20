//! SemanticKITTI labels and KITTI odometry poses and calibration.

use std::path::Path;

use groundwork_core::{Pose, pose_from_matrix};

use crate::error::FormatError;
use crate::labels::label_count;
use crate::scan::read_records;

/// Reads a SemanticKITTI `.label` file (u32 per point: semantic id in the low 16 bits,
/// instance id in the high 16 bits) and returns the semantic ids. The label count must
/// match the scan's point count.
pub fn read_labels(path: &Path, points: usize) -> Result<Vec<u16>, FormatError> {
    let bytes = read_records(path, 4, |labels| label_count(path, labels, points))?;
    Ok(bytes
        .chunks_exact(4)
        .map(|b| u16::from_le_bytes([b[0], b[1]]))
        .collect())
}

fn parse_row_major_3x4(path: &Path, line: usize, vals: &[f64]) -> Result<Pose, FormatError> {
    if vals.len() != 12 {
        return Err(FormatError::parse(
            path,
            line,
            format!("expected 12 numbers (3×4 row-major), found {}", vals.len()),
        ));
    }
    let mut m = [[0.0; 4]; 4];
    for r in 0..3 {
        m[r].copy_from_slice(&vals[4 * r..4 * r + 4]);
    }
    m[3] = [0.0, 0.0, 0.0, 1.0];
    pose_from_matrix(&m).map_err(|e| FormatError::parse(path, line, e.to_string()))
}

/// A TUM line: time, translation, unit quaternion (x, y, z, w).
fn parse_tum(path: &Path, line: usize, v: &[f64]) -> Result<Pose, FormatError> {
    let q = nalgebra::Quaternion::new(v[7], v[4], v[5], v[6]);
    if (q.norm() - 1.0).abs() > 1e-3 {
        return Err(FormatError::parse(
            path,
            line,
            format!(
                "TUM quaternion (qx qy qz qw) has norm {:.6}, not 1",
                q.norm()
            ),
        ));
    }
    Ok(Pose::from_parts(
        nalgebra::Translation3::new(v[1], v[2], v[3]),
        nalgebra::UnitQuaternion::from_quaternion(q),
    ))
}

fn parse_numbers(path: &Path, line: usize, text: &str) -> Result<Vec<f64>, FormatError> {
    text.split_whitespace()
        .map(|t| {
            t.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    FormatError::parse(path, line, format!("not a finite number: {t:?}"))
                })
        })
        .collect()
}

/// Reads a trajectory, one pose per scan in scan order: KITTI odometry `poses.txt` (12
/// numbers per line, a 3×4 row-major matrix: world from camera, or from the LiDAR where
/// there is no calibration) or the TUM format (8 numbers per line: time, tx, ty, tz, qx,
/// qy, qz, qw; time is not used, line i is scan i; lines starting with `#` are comments).
pub fn read_poses(path: &Path) -> Result<Vec<Pose>, FormatError> {
    let text = crate::file::read_text(path, crate::file::MAX_TEXT_BYTES)?;
    let mut poses = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() || line.trim_start().starts_with('#') {
            continue;
        }
        let vals = parse_numbers(path, i + 1, line)?;
        poses.push(if vals.len() == 8 {
            parse_tum(path, i + 1, &vals)?
        } else {
            parse_row_major_3x4(path, i + 1, &vals)?
        });
    }
    if poses.is_empty() {
        return Err(FormatError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(poses)
}

/// Reads a KITTI odometry `times.txt`: one time per scan in seconds (`1.036224e-01`),
/// returned in ns. Times must be finite, ≥ 0 and never decrease.
pub fn read_times(path: &Path) -> Result<Vec<u64>, FormatError> {
    let text = crate::file::read_text(path, crate::file::MAX_TEXT_BYTES)?;
    let mut times: Vec<u64> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let vals = parse_numbers(path, i + 1, line)?;
        let [t] = vals[..] else {
            return Err(FormatError::parse(
                path,
                i + 1,
                format!("{} numbers, a time is one", vals.len()),
            ));
        };
        // 2^64 ns is 584 years: anything near it is not a scan time.
        if !(0.0..1.0e10).contains(&t) {
            return Err(FormatError::parse(
                path,
                i + 1,
                format!("{t} s is not a time since the sequence (or 1970) began"),
            ));
        }
        // Plain decimals are read digit by digit: an f64 holds a 1970-based time to only
        // ~0.2 µs, and a stamp written back must be the stamp read.
        let ns = exact_ns(line.trim()).unwrap_or_else(|| (t * 1e9).round() as u64);
        if times.last().is_some_and(|&last| ns < last) {
            return Err(FormatError::parse(path, i + 1, "time runs back"));
        }
        times.push(ns);
    }
    if times.is_empty() {
        return Err(FormatError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(times)
}

/// `seconds[.fraction]` (at most 9 decimals) in ns exactly; None for other notations.
fn exact_ns(text: &str) -> Option<u64> {
    let (int, frac) = text.split_once('.').unwrap_or((text, ""));
    if int.is_empty()
        || frac.len() > 9
        || !(int.bytes().chain(frac.bytes())).all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let frac_ns: u64 = format!("{frac:0<9}").parse().ok()?;
    int.parse::<u64>()
        .ok()?
        .checked_mul(1_000_000_000)?
        .checked_add(frac_ns)
}

/// Writes a `times.txt` in seconds with nine decimals (KITTI's own files use `1.036224e-01`;
/// both read back, these exactly).
pub fn write_times(path: &Path, times_ns: &[u64]) -> Result<(), FormatError> {
    crate::output::write_atomic(path, times_text(times_ns).as_bytes())
}

/// The text [`write_times`] writes.
pub fn times_text(times_ns: &[u64]) -> String {
    times_ns
        .iter()
        .map(|&t| format!("{}.{:09}\n", t / 1_000_000_000, t % 1_000_000_000))
        .collect()
}

/// Reads `Tr` (velodyne → camera) from a KITTI odometry `calib.txt`.
pub fn read_calib_tr(path: &Path) -> Result<Pose, FormatError> {
    let text = crate::file::read_text(path, crate::file::MAX_TEXT_BYTES)?;
    for (i, line) in text.lines().enumerate() {
        if let Some(rest) = line.strip_prefix("Tr:") {
            let vals = parse_numbers(path, i + 1, rest)?;
            return parse_row_major_3x4(path, i + 1, &vals);
        }
    }
    Err(FormatError::parse(path, 0, "no line starting with \"Tr:\""))
}

/// LiDAR world poses from camera poses: inv(Tr) · P_i · Tr.
pub fn lidar_poses(camera: &[Pose], tr: &Pose) -> Vec<Pose> {
    let tr_inv = tr.inverse();
    camera.iter().map(|p| tr_inv * p * tr).collect()
}

/// Writes a SemanticKITTI `.label` file: one little-endian u32 per point (class id in the
/// low 16 bits, instance id in the high 16).
pub fn write_labels(path: &Path, labels: &[u32]) -> Result<(), FormatError> {
    crate::output::write_atomic(path, &labels_bytes(labels))
}

/// The bytes [`write_labels`] writes.
pub fn labels_bytes(labels: &[u32]) -> Vec<u8> {
    labels.iter().flat_map(|l| l.to_le_bytes()).collect()
}

/// Writes KITTI odometry `poses.txt`: one pose per line, the top three rows of a
/// row-major 4×4 matrix.
pub fn write_poses(path: &Path, poses: &[[[f64; 4]; 4]]) -> Result<(), FormatError> {
    crate::output::write_atomic(path, poses_text(poses).as_bytes())
}

/// The text [`write_poses`] writes.
pub fn poses_text(poses: &[[[f64; 4]; 4]]) -> String {
    let mut text = String::new();
    for m in poses {
        let row: Vec<String> = m[..3]
            .iter()
            .flatten()
            .map(|v| format!("{v:.9e}"))
            .collect();
        text.push_str(&row.join(" "));
        text.push('\n');
    }
    text
}

/// Writes a KITTI odometry `calib.txt` holding only `Tr` (velodyne → camera), for
/// sequences whose poses are the LiDAR's own (`Tr` = identity).
pub fn write_calib_tr(path: &Path, tr: &[[f64; 4]; 4]) -> Result<(), FormatError> {
    crate::output::write_atomic(path, calib_tr_text(tr).as_bytes())
}

/// The text [`write_calib_tr`] writes.
pub fn calib_tr_text(tr: &[[f64; 4]; 4]) -> String {
    let row: Vec<String> = tr[..3]
        .iter()
        .flatten()
        .map(|v| format!("{v:.9e}"))
        .collect();
    format!("Tr: {}\n", row.join(" "))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    #[test]
    fn kitti_times_read_in_ns_and_bad_ones_name_their_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("times.txt");
        // KITTI odometry's own notation.
        fs::write(&p, "0.000000e+00\n1.036224e-01\n\n2.072538e-01\n").unwrap();
        assert_eq!(read_times(&p).unwrap(), [0, 103_622_400, 207_253_800]);
        write_times(&p, &[0, 103_622_400, 1_700_000_000_123_456_768]).unwrap();
        assert_eq!(
            read_times(&p).unwrap(),
            [0, 103_622_400, 1_700_000_000_123_456_768]
        );
        for (text, what) in [
            ("0.1\n0.05\n", ":2: time runs back"),
            ("0.1 0.2\n", ":1: 2 numbers"),
            ("nan\n", ":1: not a finite number"),
            ("-1\n", ":1: -1 s is not a time"),
            ("", "empty"),
        ] {
            fs::write(&p, text).unwrap();
            let e = read_times(&p).unwrap_err().to_string();
            assert!(e.contains("times.txt") && e.contains(what), "{text:?}: {e}");
        }
    }

    #[test]
    fn written_poses_calibration_and_labels_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (
            pose_from_matrix(&[
                [1.0, 0.0, 0.0, 2.0],
                [0.0, 1.0, 0.0, 3.0],
                [0.0, 0.0, 1.0, 4.0],
                [0.0, 0.0, 0.0, 1.0],
            ])
            .unwrap(),
            pose_from_matrix(&[
                [0.0, -1.0, 0.0, 1.5],
                [1.0, 0.0, 0.0, -2.0],
                [0.0, 0.0, 1.0, 0.25],
                [0.0, 0.0, 0.0, 1.0],
            ])
            .unwrap(),
        );
        let m = |p: &Pose| {
            let h = p.to_homogeneous();
            std::array::from_fn(|r| std::array::from_fn(|c| h[(r, c)]))
        };
        let poses = dir.path().join("poses.txt");
        write_poses(&poses, &[m(&a), m(&b)]).unwrap();
        let back = read_poses(&poses).unwrap();
        assert_eq!(back.len(), 2);
        assert!((back[1].to_homogeneous() - b.to_homogeneous()).abs().max() < 1e-9);
        let calib = dir.path().join("calib.txt");
        write_calib_tr(&calib, &m(&Pose::identity())).unwrap();
        assert_eq!(read_calib_tr(&calib).unwrap(), Pose::identity());
        let labels = dir.path().join("0.label");
        write_labels(&labels, &[40 | (3 << 16), 10]).unwrap();
        assert_eq!(read_labels(&labels, 2).unwrap(), vec![40, 10]);
    }

    #[test]
    fn tum_trajectories_read_as_the_same_poses_as_kitti_rows() {
        let dir = tempfile::tempdir().unwrap();
        // Identity, then 1 m forward turned 90° left about z.
        let (h, c) = (
            std::f64::consts::FRAC_1_SQRT_2,
            "# time tx ty tz qx qy qz qw\n",
        );
        let tum = dir.path().join("traj.tum");
        fs::write(
            &tum,
            format!("{c}0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 {h} {h}\n"),
        )
        .unwrap();
        let kitti = dir.path().join("poses.txt");
        fs::write(
            &kitti,
            "1 0 0 0 0 1 0 0 0 0 1 0\n0 -1 0 1 1 0 0 0 0 0 1 0\n",
        )
        .unwrap();
        let (a, b) = (read_poses(&tum).unwrap(), read_poses(&kitti).unwrap());
        assert_eq!(a.len(), 2);
        for (p, q) in a.iter().zip(&b) {
            let d = (p.to_homogeneous() - q.to_homogeneous()).abs().max();
            assert!(d < 1e-9, "{p} vs {q}");
        }
        fs::write(&tum, "0.0 0 0 0 0 0 0 2\n").unwrap();
        let e = read_poses(&tum).unwrap_err().to_string();
        assert!(e.contains("traj.tum:1") && e.contains("norm"), "{e}");
    }

    #[test]
    fn labels_keep_the_semantic_half_and_must_match_the_scan() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("0.label");
        let raw: Vec<u8> = [40u32 | (7 << 16), 72, 10]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        fs::write(&p, &raw).unwrap();
        assert_eq!(read_labels(&p, 3).unwrap(), vec![40, 72, 10]);
        let e = read_labels(&p, 4).unwrap_err().to_string();
        assert!(e.contains("0.label") && e.contains("3 labels"), "{e}");
        fs::write(&p, &raw[..5]).unwrap();
        assert!(read_labels(&p, 1).is_err());
    }

    #[test]
    fn poses_and_calib_parse_and_reject_garbage() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("poses.txt");
        fs::write(&p, "1 0 0 1  0 1 0 2  0 0 1 3\n1 0 0 4 0 1 0 5 0 0 1 6\n").unwrap();
        let poses = read_poses(&p).unwrap();
        assert_eq!(poses.len(), 2);
        assert!((poses[1].translation.vector.z - 6.0).abs() < 1e-12);
        fs::write(&p, "1 0 0 1 0 1 0 2 0 0 1\n").unwrap();
        let e = read_poses(&p).unwrap_err().to_string();
        assert!(e.contains("poses.txt:1") && e.contains("12 numbers"), "{e}");
        fs::write(&p, "1 0 0 nan 0 1 0 2 0 0 1 3\n").unwrap();
        assert!(read_poses(&p).is_err());

        let c = dir.path().join("calib.txt");
        fs::write(&c, "P0: 1 2 3\nTr: 0 -1 0 0  0 0 -1 0  1 0 0 -0.3\n").unwrap();
        let tr = read_calib_tr(&c).unwrap();
        // Camera-from-velodyne: velodyne x (forward) becomes camera z.
        let v = tr * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!((v.z - 0.7).abs() < 1e-12);
        fs::write(&c, "P0: 1 2 3\n").unwrap();
        assert!(read_calib_tr(&c).is_err());
    }
}
