//! Per-scan outputs: `.prob` (little-endian f32 ground probability per point) and
//! `.ground` (u8 per point, 1 = ground), both in input point order.

use std::fs;
use std::path::{Path, PathBuf};

use crate::error::FormatError;
use crate::recording::RecordingWriter;

/// Where per-scan results go: `.prob`/`.ground` files in a folder, or one MCAP recording
/// (PointCloud2 with `ground_probability`) for a path ending in `.mcap`.
#[derive(Debug)]
pub enum OutputTarget {
    /// A folder of `.prob` / `.ground` files.
    Files(PathBuf),
    /// One recording.
    Recording(Box<RecordingWriter>),
}

impl OutputTarget {
    /// A recording for a path ending in `.mcap`, a folder otherwise; missing folders (the
    /// recording's parent) are created.
    pub fn create(path: &Path) -> Result<Self, FormatError> {
        let recording = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("mcap"));
        let dir = if recording {
            path.parent().filter(|d| !d.as_os_str().is_empty())
        } else {
            Some(path)
        };
        if let Some(dir) = dir {
            fs::create_dir_all(dir).map_err(|e| FormatError::io(dir, e))?;
        }
        Ok(if recording {
            Self::Recording(Box::new(RecordingWriter::create(path)?))
        } else {
            Self::Files(path.to_path_buf())
        })
    }
}

/// Writes `<dir>/<stem>.prob` and `<dir>/<stem>.ground`, each first to a temporary name and
/// then renamed, so that a crash never leaves a half-written file under the final name; the
/// `.ground` file is renamed last, so its presence means both are complete.
pub fn write_outputs(
    dir: &Path,
    stem: &str,
    probabilities: &[f32],
    threshold: f32,
) -> Result<(), FormatError> {
    let prob: Vec<u8> = probabilities.iter().flat_map(|p| p.to_le_bytes()).collect();
    let ground: Vec<u8> = probabilities
        .iter()
        .map(|&p| u8::from(p >= threshold))
        .collect();
    write_atomic(&dir.join(format!("{stem}.prob")), &prob)?;
    write_atomic(&dir.join(format!("{stem}.ground")), &ground)
}

/// Writes `path` through `<path>.partial` and a rename: a reader never sees it half-written.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FormatError> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = std::path::PathBuf::from(tmp);
    fs::write(&tmp, bytes).map_err(|e| FormatError::io(&tmp, e))?;
    fs::rename(&tmp, path).map_err(|e| FormatError::io(path, e))
}

/// Whether `<dir>/<stem>.prob` and `.ground` are both complete outputs for one scan: present
/// under their final names, 4 bytes per point and 1 byte per point for the same count.
pub fn outputs_complete(dir: &Path, stem: &str) -> bool {
    let len = |ext: &str| fs::metadata(dir.join(format!("{stem}.{ext}"))).map(|m| m.len());
    match (len("prob"), len("ground")) {
        (Ok(p), Ok(g)) => g > 0 && p == 4 * g,
        _ => false,
    }
}

/// Reads a `.prob` file.
pub fn read_prob(path: &Path) -> Result<Vec<f32>, FormatError> {
    let bytes = fs::read(path).map_err(|e| FormatError::io(path, e))?;
    if bytes.len() % 4 != 0 {
        return Err(FormatError::Size {
            path: path.to_path_buf(),
            size: bytes.len() as u64,
            record: 4,
        });
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_round_trip_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = [0.0, 0.49, 0.5, 1.0];
        write_outputs(dir.path(), "000007", &p, 0.5).unwrap();
        assert_eq!(read_prob(&dir.path().join("000007.prob")).unwrap(), p);
        assert_eq!(
            fs::read(dir.path().join("000007.ground")).unwrap(),
            [0, 0, 1, 1]
        );
        assert!(outputs_complete(dir.path(), "000007"));
        // No temporary file is left behind.
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 2);
        // A missing or truncated half makes the pair incomplete.
        fs::write(dir.path().join("000007.prob"), [0u8; 12]).unwrap();
        assert!(!outputs_complete(dir.path(), "000007"));
        fs::remove_file(dir.path().join("000007.ground")).unwrap();
        assert!(!outputs_complete(dir.path(), "000007"));
    }
}
