//! Per-scan outputs: `.prob` (little-endian f32 ground probability per point) and
//! `.ground` (u8 per point, 1 = ground), both in input point order.

use std::fs;
use std::path::Path;

use crate::error::FormatError;

/// Writes `<dir>/<stem>.prob` and `<dir>/<stem>.ground`.
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
    let pp = dir.join(format!("{stem}.prob"));
    fs::write(&pp, prob).map_err(|e| FormatError::io(&pp, e))?;
    let gp = dir.join(format!("{stem}.ground"));
    fs::write(&gp, ground).map_err(|e| FormatError::io(&gp, e))
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
    }
}
