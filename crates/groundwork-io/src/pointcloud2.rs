//! ROS 2 `sensor_msgs/msg/PointCloud2` in its CDR wire form (as MCAP recordings from
//! rosbag2 store it): decoding honours `fields`, `point_step`, `row_step`, `is_bigendian`
//! and `is_dense`; encoding writes x, y, z, intensity and `ground_probability`.
//!
//! The CDR is read by hand: the message is fixed, the `cdr` crate allocates every
//! sequence length it reads before checking it against the buffer, and copies `data`
//! byte by byte. Here every length is checked against the bytes that remain, and the point
//! data is borrowed, not copied.

use std::path::Path;

use groundwork_core::Point;

use crate::cdr::{self, put_header, put_string, put_u32};
use crate::error::FormatError;
use crate::scan::{NonFinite, Scan, checked_count};

/// The schema name rosbag2 records.
pub const SCHEMA_NAME: &str = "sensor_msgs/msg/PointCloud2";

/// The schema text (ros2msg, with its dependencies) that viewers use to decode what
/// [`encode`] writes.
pub const SCHEMA_TEXT: &str = concat!(
    "std_msgs/Header header
uint32 height
uint32 width
PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
",
    header_definitions!(),
    "================================================================================
MSG: sensor_msgs/PointField
uint8 INT8    = 1
uint8 UINT8   = 2
uint8 INT16   = 3
uint8 UINT16  = 4
uint8 INT32   = 5
uint8 UINT32  = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8
string name
uint32 offset
uint8  datatype
uint32 count
"
);

/// The name of the field [`encode`] adds.
pub const PROBABILITY_FIELD: &str = "ground_probability";

const FLOAT32: u8 = 7;

/// One entry of `fields`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PointField {
    /// Field name (`x`, `intensity`, ...).
    pub name: String,
    /// Byte offset within a point.
    pub offset: u32,
    /// ROS datatype code (1 INT8 ... 8 FLOAT64).
    pub datatype: u8,
    /// Elements.
    pub count: u32,
}

fn datatype_size(t: u8) -> Option<usize> {
    match t {
        1 | 2 => Some(1),
        3 | 4 => Some(2),
        5..=7 => Some(4),
        8 => Some(8),
        _ => None,
    }
}

/// A CDR cursor: alignment is relative to the end of the 4-byte encapsulation header.
struct Cdr<'a> {
    buf: &'a [u8],
    pos: usize,
    little: bool,
}

impl<'a> Cdr<'a> {
    fn new(buf: &'a [u8]) -> Result<Self, String> {
        match buf {
            [0, 1, _, _, ..] => Ok(Self {
                buf,
                pos: 4,
                little: true,
            }),
            [0, 0, _, _, ..] => Ok(Self {
                buf,
                pos: 4,
                little: false,
            }),
            [a, b, ..] => Err(format!(
                "not plain CDR (encapsulation {a:#04x}{b:02x}; XCDR2 and PL_CDR are not read)"
            )),
            _ => Err("message is shorter than its CDR header".into()),
        }
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], String> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.buf.len())
            .ok_or_else(|| {
                format!(
                    "truncated at {what}: needs {n} bytes at offset {}, message has {}",
                    self.pos,
                    self.buf.len()
                )
            })?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn align(&mut self, n: usize) {
        let rel = self.pos - 4;
        self.pos += (n - rel % n) % n;
    }

    fn u8(&mut self, what: &str) -> Result<u8, String> {
        Ok(self.take(1, what)?[0])
    }

    fn u32(&mut self, what: &str) -> Result<u32, String> {
        self.align(4);
        let b: [u8; 4] = self
            .take(4, what)?
            .try_into()
            .map_err(|_| what.to_string())?;
        Ok(if self.little {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    /// A length-prefixed byte sequence, borrowed.
    fn bytes(&mut self, what: &str) -> Result<&'a [u8], String> {
        let n = self.u32(what)? as usize;
        self.take(n, what)
    }

    fn string(&mut self, what: &str) -> Result<String, String> {
        let b = self.bytes(what)?;
        let b = b.strip_suffix(&[0]).unwrap_or(b);
        String::from_utf8(b.to_vec()).map_err(|_| format!("{what} is not UTF-8"))
    }
}

/// Decodes one CDR-encoded PointCloud2 into a scan. `label` names the message in errors
/// (the file and the message's place in it). Points with a non-finite coordinate are
/// placeholders in a cloud that says `is_dense = false` (left out, mapped back), and an
/// error in one that says it is dense.
pub fn decode(label: &Path, msg: &[u8], max_points: usize) -> Result<Scan, FormatError> {
    decode_with(label, msg, max_points, "intensity").map(|(scan, _)| scan)
}

/// [`decode`], with the named field read into `Point::intensity`; also says whether the
/// message has that field.
fn decode_with(
    label: &Path,
    msg: &[u8],
    max_points: usize,
    value_field: &str,
) -> Result<(Scan, bool), FormatError> {
    let bad = |m: String| FormatError::malformed(label, m);
    let mut c = Cdr::new(msg).map_err(bad)?;
    let sec = c.u32("header.stamp.sec").map_err(bad)? as i32;
    let nanosec = c.u32("header.stamp.nanosec").map_err(bad)?;
    let frame_id = c.string("header.frame_id").map_err(bad)?;
    let height = c.u32("height").map_err(bad)?;
    let width = c.u32("width").map_err(bad)?;
    let n_fields = c.u32("fields").map_err(bad)?;
    // Each field takes at least 16 bytes: a lying count fails here, not in an allocation.
    if n_fields as usize > msg.len() / 16 {
        return Err(bad(format!(
            "{n_fields} fields cannot fit in {} bytes",
            msg.len()
        )));
    }
    let mut fields = Vec::with_capacity(n_fields as usize);
    for _ in 0..n_fields {
        let name = c.string("fields.name").map_err(bad)?;
        let offset = c.u32("fields.offset").map_err(bad)?;
        let datatype = c.u8("fields.datatype").map_err(bad)?;
        let count = c.u32("fields.count").map_err(bad)?;
        fields.push(PointField {
            name,
            offset,
            datatype,
            count,
        });
    }
    let big_endian = c.u8("is_bigendian").map_err(bad)? != 0;
    let point_step = c.u32("point_step").map_err(bad)? as usize;
    let row_step = c.u32("row_step").map_err(bad)? as usize;
    let data = c.bytes("data").map_err(bad)?;
    let dense = c.u8("is_dense").map_err(bad)? != 0;

    let n = checked_count(label, u64::from(height) * u64::from(width), max_points)?;
    if n == 0 {
        return Err(FormatError::Empty {
            path: label.to_path_buf(),
        });
    }
    let (w, h) = (width as usize, height as usize);
    if row_step < w * point_step {
        return Err(bad(format!(
            "row_step {row_step} is shorter than width {w} × point_step {point_step}"
        )));
    }
    let need = (h - 1) * row_step + w * point_step;
    if data.len() < need {
        return Err(bad(format!(
            "data has {} bytes, {h} rows of {w} points (row_step {row_step}, point_step {point_step}) need {need}",
            data.len()
        )));
    }
    let field = |name: &str| -> Result<Option<(usize, u8)>, FormatError> {
        let Some(f) = fields.iter().find(|f| f.name == name) else {
            return Ok(None);
        };
        let size = datatype_size(f.datatype).ok_or_else(|| {
            bad(format!(
                "field {name:?} has unknown datatype {}",
                f.datatype
            ))
        })?;
        if f.offset as usize + size > point_step {
            return Err(bad(format!(
                "field {name:?} at offset {} does not fit in point_step {point_step}",
                f.offset
            )));
        }
        Ok(Some((f.offset as usize, f.datatype)))
    };
    let [x, y, z] = ["x", "y", "z"].map(field);
    let (Some(x), Some(y), Some(z)) = (x?, y?, z?) else {
        return Err(bad("PointCloud2 has no x, y and z fields".into()));
    };
    let intensity = field(value_field)?;
    let read = |p: &[u8], (off, t): (usize, u8)| -> f32 {
        let b = &p[off..];
        macro_rules! get {
            ($ty:ty, $n:expr) => {{
                let a: [u8; $n] = std::array::from_fn(|i| b[i]);
                if big_endian {
                    <$ty>::from_be_bytes(a)
                } else {
                    <$ty>::from_le_bytes(a)
                }
            }};
        }
        match t {
            1 => get!(i8, 1) as f32,
            2 => get!(u8, 1) as f32,
            3 => get!(i16, 2) as f32,
            4 => get!(u16, 2) as f32,
            5 => get!(i32, 4) as f32,
            6 => get!(u32, 4) as f32,
            7 => get!(f32, 4),
            _ => get!(f64, 8) as f32,
        }
    };
    let mut records = Vec::with_capacity(n);
    for r in 0..h {
        let row = &data[r * row_step..];
        for k in 0..w {
            let p = &row[k * point_step..(k + 1) * point_step];
            records.push(Point {
                x: read(p, x),
                y: read(p, y),
                z: read(p, z),
                intensity: intensity.map_or(0.0, |i| read(p, i)),
            });
        }
    }
    let rule = if dense {
        NonFinite::Reject
    } else {
        NonFinite::Skip
    };
    let mut scan = Scan::from_records(label, records, rule)?;
    if h > 1 {
        scan.organized = Some((height, width));
    }
    scan.stamp_ns = u64::try_from(sec)
        .ok()
        .map(|s| s * 1_000_000_000 + u64::from(nanosec));
    scan.frame_id = Some(frame_id);
    Ok((scan, intensity.is_some()))
}

/// Encodes a scan and one probability per point as a little-endian CDR PointCloud2 with
/// fields x, y, z, intensity and `ground_probability` (FLOAT32 each, point_step 20), one
/// point per input record: records the reader left out come back as NaN placeholders with
/// probability 0 (`is_dense = false`), and an organized input keeps its rows.
pub fn encode(scan: &Scan, probabilities: &[f32], stamp_ns: u64, frame_id: &str) -> Vec<u8> {
    let records = scan.records.max(scan.points.len());
    let (height, width) = match scan.organized {
        Some((h, w)) if h as usize * w as usize == records => (h, w),
        _ => (1, records as u32),
    };
    let mut out = cdr::message();
    put_header(&mut out, stamp_ns, frame_id);
    put_u32(&mut out, height);
    put_u32(&mut out, width);
    let names = ["x", "y", "z", "intensity", PROBABILITY_FIELD];
    put_u32(&mut out, names.len() as u32);
    for (i, name) in names.iter().enumerate() {
        put_string(&mut out, name);
        put_u32(&mut out, 4 * i as u32);
        out.push(FLOAT32);
        put_u32(&mut out, 1);
    }
    out.push(0); // is_bigendian
    let point_step = 20u32;
    put_u32(&mut out, point_step);
    put_u32(&mut out, point_step * width);
    put_u32(&mut out, point_step * records as u32);
    let start = out.len();
    let placeholder = [f32::NAN, f32::NAN, f32::NAN, 0.0, 0.0];
    out.resize(start + 20 * records, 0);
    let mut write = |record: usize, v: [f32; 5]| {
        let o = start + 20 * record;
        for (k, x) in v.iter().enumerate() {
            out[o + 4 * k..o + 4 * k + 4].copy_from_slice(&x.to_le_bytes());
        }
    };
    if scan.source_index.is_some() {
        for r in 0..records {
            write(r, placeholder);
        }
    }
    for (i, (p, &prob)) in scan.points.iter().zip(probabilities).enumerate() {
        let r = scan.source_index.as_ref().map_or(i, |s| s[i] as usize);
        write(r, [p.x, p.y, p.z, p.intensity, prob]);
    }
    out.push(u8::from(scan.skipped() == 0)); // is_dense
    out
}

/// The `ground_probability` field of a PointCloud2 written by [`encode`] (or anyone else),
/// one value per record (0 for placeholders), for reading results back.
pub fn decode_probabilities(
    label: &Path,
    msg: &[u8],
    max_points: usize,
) -> Result<Vec<f32>, FormatError> {
    let (scan, found) = decode_with(label, msg, max_points, PROBABILITY_FIELD)?;
    if !found {
        return Err(FormatError::malformed(
            label,
            format!("no {PROBABILITY_FIELD} field"),
        ));
    }
    let values: Vec<f32> = scan.points.iter().map(|p| p.intensity).collect();
    Ok(scan.expand(&values, 0.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encode_then_decode_keeps_points_probabilities_and_placeholders() {
        let label = Path::new("m");
        let recs = vec![
            Point {
                x: 1.0,
                y: 2.0,
                z: 3.0,
                intensity: 0.5,
            },
            Point::new(f32::NAN, f32::NAN, f32::NAN),
            Point {
                x: -4.0,
                y: 5.5,
                z: -0.25,
                intensity: 9.0,
            },
            Point::new(0.0, 0.0, 0.0),
        ];
        let mut scan = Scan::from_records(label, recs, NonFinite::Skip).unwrap();
        scan.organized = Some((2, 2));
        let msg = encode(&scan, &[0.9, 0.1, 0.0], 1_700_000_000_123_456_789, "lidar");
        let back = decode(label, &msg, 10).unwrap();
        assert_eq!(back.points, scan.points);
        assert_eq!(back.source_index, scan.source_index);
        assert_eq!(back.organized, Some((2, 2)));
        assert_eq!(back.stamp_ns, Some(1_700_000_000_123_456_789));
        assert_eq!(back.frame_id.as_deref(), Some("lidar"));
        assert_eq!(
            decode_probabilities(label, &msg, 10).unwrap(),
            vec![0.9, 0.0, 0.1, 0.0]
        );
    }

    #[test]
    fn truncated_and_lying_messages_are_errors() {
        let label = Path::new("rec.mcap (message 0)");
        let scan = Scan::dense(vec![Point::new(1.0, 2.0, 3.0); 4]);
        let msg = encode(&scan, &[0.5; 4], 0, "f");
        for cut in [0, 3, 10, 40, msg.len() - 30, msg.len() - 1] {
            let e = decode(label, &msg[..cut], 10).unwrap_err().to_string();
            assert!(e.starts_with("rec.mcap (message 0)"), "{e}");
        }
        let e = decode(label, &msg, 3).unwrap_err().to_string();
        assert!(e.contains("maximum of 3"), "{e}");
        // A dense cloud may not hold NaN.
        let mut nan = msg.clone();
        let data_start = nan.len() - 1 - 80;
        nan[data_start..data_start + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        let e = decode(label, &nan, 10).unwrap_err().to_string();
        assert!(e.contains("non-finite"), "{e}");
    }
}
