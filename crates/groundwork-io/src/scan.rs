//! One scan as the readers give it ([`Scan`]: finite points, and where placeholders were
//! left out, the map back to the records), and what every reader shares: the record-count
//! check made before anything is read, and the reading of headerless record files.

use std::io::Read;
use std::path::Path;

use groundwork_core::Point;

use crate::error::FormatError;

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
