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
use crate::scan::{Scan, checked_count};

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
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
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

/// A PointCloud2 message with its point data borrowed: what [`parse`] reads from CDR, and
/// what a DDS subscriber hands over after its own deserialization. Every reading of the
/// layout goes through [`decode_cloud`], whichever way the message came.
#[derive(Debug, Clone, Copy)]
pub struct CloudRef<'a> {
    /// `header.stamp.sec`.
    pub stamp_sec: i32,
    /// `header.stamp.nanosec`.
    pub stamp_nanosec: u32,
    /// `header.frame_id`.
    pub frame_id: &'a str,
    /// Rows (1: unorganized).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The point layout.
    pub fields: &'a [PointField],
    /// Multi-byte values are big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    pub data: &'a [u8],
    /// No point has a non-finite coordinate.
    pub is_dense: bool,
}

impl CloudRef<'_> {
    /// The header stamp, ns since 1970; `None` before it.
    pub fn stamp_ns(&self) -> Option<u64> {
        u64::try_from(self.stamp_sec)
            .ok()
            .map(|s| s * 1_000_000_000 + u64::from(self.stamp_nanosec))
    }
}

/// A PointCloud2 parsed from CDR: the owned parts of a [`CloudRef`].
#[derive(Debug)]
pub struct Parsed<'a> {
    frame_id: String,
    fields: Vec<PointField>,
    cloud: CloudRef<'a>,
}

impl<'a> Parsed<'a> {
    /// The message, its data borrowed from the CDR buffer.
    pub fn cloud(&self) -> CloudRef<'_> {
        CloudRef {
            frame_id: &self.frame_id,
            fields: &self.fields,
            ..self.cloud
        }
    }
}

/// Parses a CDR-encoded PointCloud2 (every length checked against what remains).
pub fn parse<'a>(label: &Path, msg: &'a [u8]) -> Result<Parsed<'a>, FormatError> {
    let bad = |m: String| FormatError::malformed(label, m);
    let mut c = Cdr::new(msg).map_err(bad)?;
    let stamp_sec = c.u32("header.stamp.sec").map_err(bad)? as i32;
    let stamp_nanosec = c.u32("header.stamp.nanosec").map_err(bad)?;
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
    let is_bigendian = c.u8("is_bigendian").map_err(bad)? != 0;
    let point_step = c.u32("point_step").map_err(bad)?;
    let row_step = c.u32("row_step").map_err(bad)?;
    let data = c.bytes("data").map_err(bad)?;
    let is_dense = c.u8("is_dense").map_err(bad)? != 0;
    Ok(Parsed {
        frame_id,
        fields,
        cloud: CloudRef {
            stamp_sec,
            stamp_nanosec,
            frame_id: "",
            height,
            width,
            fields: &[],
            is_bigendian,
            point_step,
            row_step,
            data,
            is_dense,
        },
    })
}

/// Decodes one CDR-encoded PointCloud2 into a scan. `label` names the message in errors
/// (the file and the message's place in it). Points with a non-finite coordinate are
/// placeholders in a cloud that says `is_dense = false` (left out, mapped back), and an
/// error in one that says it is dense.
pub fn decode(label: &Path, msg: &[u8], max_points: usize) -> Result<Scan, FormatError> {
    decode_cloud(label, &parse(label, msg)?.cloud(), max_points)
}

/// [`decode`] for a message already parsed (by [`parse`] or a DDS subscriber).
pub fn decode_cloud(
    label: &Path,
    cloud: &CloudRef<'_>,
    max_points: usize,
) -> Result<Scan, FormatError> {
    decode_with(label, cloud, max_points, "intensity").map(|(scan, _)| scan)
}

/// The field table as the message definition means it: every field a known datatype, at
/// least one element, inside a record, and named once (a second `x` would make which one
/// is read a matter of search order).
fn check_fields(label: &Path, fields: &[PointField], point_step: usize) -> Result<(), FormatError> {
    let bad = |m: String| FormatError::malformed(label, m);
    let mut seen = std::collections::HashSet::new();
    for f in fields {
        let name = &f.name;
        if !seen.insert(name.as_str()) {
            return Err(bad(format!(
                "field {name:?} appears twice in the field table"
            )));
        }
        let size = datatype_size(f.datatype).ok_or_else(|| {
            bad(format!(
                "field {name:?} has unknown datatype {}",
                f.datatype
            ))
        })?;
        if f.count == 0 {
            return Err(bad(format!("field {name:?} has count 0 (no element)")));
        }
        let end = (f.count as usize)
            .checked_mul(size)
            .and_then(|n| n.checked_add(f.offset as usize));
        if end.is_none_or(|e| e > point_step) {
            return Err(bad(format!(
                "field {name:?} ({} × {size} bytes at offset {}) does not fit in point_step {point_step}",
                f.count, f.offset
            )));
        }
    }
    Ok(())
}

/// The checked geometry of a cloud's records.
#[derive(Debug)]
struct Layout {
    records: usize,
    height: usize,
    width: usize,
    point_step: usize,
    row_step: usize,
}

impl Layout {
    fn of(label: &Path, cloud: &CloudRef<'_>, max_points: usize) -> Result<Self, FormatError> {
        let bad = |m: String| FormatError::malformed(label, m);
        let (height, width) = (cloud.height, cloud.width);
        let n = checked_count(label, u64::from(height) * u64::from(width), max_points)?;
        if n == 0 {
            return Err(FormatError::Empty {
                path: label.to_path_buf(),
            });
        }
        let (w, h) = (width as usize, height as usize);
        let (point_step, row_step) = (cloud.point_step as usize, cloud.row_step as usize);
        if point_step == 0 {
            return Err(bad("point_step is 0".into()));
        }
        if row_step < w * point_step {
            return Err(bad(format!(
                "row_step {row_step} is shorter than width {w} × point_step {point_step}"
            )));
        }
        check_fields(label, cloud.fields, point_step)?;
        let need = (h - 1) * row_step + w * point_step;
        if cloud.data.len() < need {
            return Err(bad(format!(
                "data has {} bytes, {h} rows of {w} points (row_step {row_step}, point_step {point_step}) need {need}",
                cloud.data.len()
            )));
        }
        Ok(Self {
            records: n,
            height: h,
            width: w,
            point_step,
            row_step,
        })
    }

    /// [`Layout::of`] for an output that takes one value per record: `values` of `what`
    /// must be as many.
    fn per_record(
        label: &Path,
        cloud: &CloudRef<'_>,
        max_points: usize,
        values: usize,
        what: &str,
    ) -> Result<Self, FormatError> {
        let layout = Self::of(label, cloud, max_points)?;
        if values != layout.records {
            return Err(FormatError::malformed(
                label,
                format!("{values} {what} for {} records", layout.records),
            ));
        }
        Ok(layout)
    }

    /// Where record `r` starts, bytes.
    #[inline]
    fn record_offset(&self, r: usize) -> usize {
        if self.height == 1 {
            r * self.point_step
        } else {
            (r / self.width) * self.row_step + (r % self.width) * self.point_step
        }
    }

    /// The bytes of record `r`.
    #[inline]
    fn record<'d>(&self, data: &'d [u8], r: usize) -> &'d [u8] {
        let o = self.record_offset(r);
        &data[o..o + self.point_step]
    }

    /// The bytes of every record, in order (rows, then points within a row).
    fn records<'d>(&self, data: &'d [u8]) -> impl Iterator<Item = &'d [u8]> {
        self.records_in(data, 1)
    }

    /// Every record of `data` seen as units of `unit` bytes (which divides the steps).
    fn records_in<'d, T>(&self, data: &'d [T], unit: usize) -> impl Iterator<Item = &'d [T]> {
        let (step, row_step) = (self.point_step / unit, self.row_step / unit);
        let row_len = self.width * step;
        // `of` checked that `data` holds every row (the last without its padding).
        data.chunks(row_step.max(1))
            .take(self.height)
            .flat_map(move |row| row[..row_len].chunks_exact(step))
    }
}

/// The points of a cloud, read in place: its layout checked, x, y and z located, its
/// no-return placeholders found. [`decode_cloud`] collects them into a [`Scan`]; the ROS 2
/// bridge copies them straight into shared memory.
#[derive(Debug)]
pub struct CloudPoints<'a> {
    data: &'a [u8],
    layout: Layout,
    xyz: [(usize, u8); 3],
    /// The field read into `Point::intensity`.
    value: Option<(usize, u8)>,
    big_endian: bool,
    /// Every field read is a little-endian FLOAT32 (most drivers): no per-value dispatch.
    plain: bool,
    /// Moreover 4-byte aligned, in data this machine can read as f32: the records as
    /// runs of floats, the fields' offsets in floats.
    floats: Option<&'a [f32]>,
    /// The record of each point, where placeholders were left out.
    source_index: Option<Vec<u32>>,
    /// The cloud says every record is a point (a non-finite one is then an error).
    dense: bool,
}

impl<'a> CloudPoints<'a> {
    /// The points of `cloud`, intensity from its `intensity` field (0 without one).
    /// Errors as [`decode`]'s.
    pub fn new(label: &Path, cloud: &CloudRef<'a>, max_points: usize) -> Result<Self, FormatError> {
        Self::unsearched(label, cloud, max_points)?.search_placeholders(label)
    }

    /// [`CloudPoints::new`] without the search for placeholders: until
    /// [`CloudPoints::search_placeholders`], every record is a point, finite or not. For a
    /// reader that checks the coordinates as it copies them ([`CloudPoints::copy_into`]),
    /// one pass over the cloud instead of two, and searches only when one is not finite.
    pub fn unsearched(
        label: &Path,
        cloud: &CloudRef<'a>,
        max_points: usize,
    ) -> Result<Self, FormatError> {
        Self::with_value(label, cloud, max_points, "intensity")
    }

    /// Finds the records with a non-finite coordinate: an error for a cloud that says it
    /// is dense, else placeholders, left out of the points and mapped back.
    pub fn search_placeholders(mut self, label: &Path) -> Result<Self, FormatError> {
        self.find_placeholders(label)?;
        Ok(self)
    }

    /// [`CloudPoints::new`], the named field read into `Point::intensity`.
    fn with_value(
        label: &Path,
        cloud: &CloudRef<'a>,
        max_points: usize,
        value_field: &str,
    ) -> Result<Self, FormatError> {
        let bad = |m: String| FormatError::malformed(label, m);
        let layout = Layout::of(label, cloud, max_points)?;
        // `Layout::of` checked every field: a known datatype, inside the record, named once.
        let field = |name: &str| {
            let f = cloud.fields.iter().find(|f| f.name == name)?;
            Some((f.offset as usize, f.datatype))
        };
        let (Some(x), Some(y), Some(z)) = (field("x"), field("y"), field("z")) else {
            return Err(bad("PointCloud2 has no x, y and z fields".into()));
        };
        let value = field(value_field);
        let big_endian = cloud.is_bigendian;
        let f32_le = |f: (usize, u8)| f.1 == FLOAT32 && !big_endian;
        let plain = [x, y, z].into_iter().all(f32_le) && value.is_none_or(f32_le);
        let aligned = |f: (usize, u8)| f.0.is_multiple_of(4);
        let floats = (plain
            && cfg!(target_endian = "little")
            && layout.point_step.is_multiple_of(4)
            && layout.row_step.is_multiple_of(4)
            && [x, y, z].into_iter().all(aligned)
            && value.is_none_or(aligned))
        .then(|| {
            let need = (layout.height - 1) * layout.row_step + layout.width * layout.point_step;
            bytemuck::try_cast_slice::<u8, f32>(&cloud.data[..need]).ok()
        })
        .flatten();
        Ok(Self {
            data: cloud.data,
            layout,
            xyz: [x, y, z],
            value,
            big_endian,
            plain,
            floats,
            source_index: None,
            dense: cloud.is_dense,
        })
    }

    /// Records with a non-finite coordinate: an error in a cloud that says it is dense,
    /// else placeholders, left out and mapped back.
    fn find_placeholders(&mut self, label: &Path) -> Result<(), FormatError> {
        let first = match self.floats {
            Some(f) => {
                let [x, y, z] = self.xyz.map(|(off, _)| off / 4);
                first_placeholder(self.layout.records_in(f, 4).map(|c| [c[x], c[y], c[z]]))
            }
            None => first_placeholder(self.layout.records(self.data).map(|p| self.xyz_of(p))),
        };
        let Some(first) = first else {
            return Ok(());
        };
        if self.dense {
            let p = self.read(first);
            return Err(FormatError::NonFinite {
                path: label.to_path_buf(),
                index: first,
                x: p.x,
                y: p.y,
                z: p.z,
            });
        }
        let n = self.layout.records;
        let finite = |p: Point| p.x.is_finite() && p.y.is_finite() && p.z.is_finite();
        let mut index = Vec::with_capacity(n);
        index.extend(0..first as u32);
        index.extend(
            ((first + 1)..n)
                .filter(|&r| finite(self.read(r)))
                .map(|r| r as u32),
        );
        if index.is_empty() {
            return Err(FormatError::malformed(
                label,
                format!("none of its {n} points has finite coordinates"),
            ));
        }
        self.source_index = Some(index);
        Ok(())
    }

    /// x, y and z of one record.
    #[inline]
    fn xyz_of(&self, p: &[u8]) -> [f32; 3] {
        if self.plain {
            self.xyz.map(|(off, _)| le_f32(p, off))
        } else {
            self.xyz.map(|f| read_value(p, f, self.big_endian))
        }
    }

    /// Points (records with finite coordinates).
    pub fn len(&self) -> usize {
        self.source_index
            .as_ref()
            .map_or(self.layout.records, Vec::len)
    }

    /// Whether there is no point (never: such a cloud is an error).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Point `i`.
    #[inline]
    pub fn point(&self, i: usize) -> Point {
        let r = self.source_index.as_ref().map_or(i, |s| s[i] as usize);
        self.read(r)
    }

    /// Writes every point, in order, into `out` (as `convert` makes it), in one pass over
    /// the records: the copy into shared memory, without [`CloudPoints::point`]'s
    /// per-point record arithmetic. Writes `min(out.len(), self.len())` points; returns
    /// how many, and whether every coordinate written was finite (checked in the same
    /// pass: for [`CloudPoints::unsearched`] points, whose placeholders were not sought).
    pub fn copy_into<T>(&self, out: &mut [T], convert: impl Fn(Point) -> T) -> (usize, bool) {
        let n = out.len().min(self.len());
        let out = &mut out[..n];
        let mut finite = true;
        let mut put = |o: &mut T, p: Point| {
            finite &= p.x.is_finite() & p.y.is_finite() & p.z.is_finite();
            *o = convert(p);
        };
        match (&self.source_index, self.floats) {
            (None, Some(f)) => {
                let [x, y, z] = self.xyz.map(|(off, _)| off / 4);
                let value = self.value.map(|(off, _)| off / 4);
                let point = |c: &[f32]| Point {
                    x: c[x],
                    y: c[y],
                    z: c[z],
                    intensity: value.map_or(0.0, |v| c[v]),
                };
                let l = &self.layout;
                let step = l.point_step / 4;
                if l.height == 1 || l.row_step == l.width * l.point_step {
                    // Records one after the other (rows without padding, as drivers send
                    // them): plain chunks, which the loop walks without a per-row step.
                    for (o, c) in out.iter_mut().zip(f[..n * step].chunks_exact(step)) {
                        put(o, point(c));
                    }
                } else {
                    for (o, c) in out.iter_mut().zip(l.records_in(f, 4)) {
                        put(o, point(c));
                    }
                }
            }
            (None, None) => {
                for (r, o) in out.iter_mut().enumerate() {
                    put(o, self.read(r));
                }
            }
            (Some(index), _) => {
                for (o, &r) in out.iter_mut().zip(index) {
                    put(o, self.read(r as usize));
                }
            }
        }
        (n, finite)
    }

    /// Record `r` as a point.
    #[inline]
    fn read(&self, r: usize) -> Point {
        if let Some(f) = self.floats {
            let o = self.layout.record_offset(r) / 4;
            let c = &f[o..o + self.layout.point_step / 4];
            let [x, y, z] = self.xyz.map(|(off, _)| c[off / 4]);
            let intensity = self.value.map_or(0.0, |(off, _)| c[off / 4]);
            return Point { x, y, z, intensity };
        }
        let p = self.layout.record(self.data, r);
        let [x, y, z] = self.xyz_of(p);
        let intensity = match self.value {
            None => 0.0,
            Some((off, _)) if self.plain => le_f32(p, off),
            Some(f) => read_value(p, f, self.big_endian),
        };
        Point { x, y, z, intensity }
    }

    /// The scan's records and their map, without its points (to map one value per point
    /// back onto the records).
    pub fn records_map(&self) -> Scan {
        Scan {
            points: Vec::new(),
            source_index: self.source_index.clone(),
            records: self.layout.records,
            ..Scan::default()
        }
    }
}

/// The first record with a non-finite coordinate.
fn first_placeholder(mut xyz: impl Iterator<Item = [f32; 3]>) -> Option<usize> {
    xyz.position(|p| !p.iter().all(|v| v.is_finite()))
}

/// A little-endian FLOAT32 at `off` (whose place in the record was checked).
#[inline]
fn le_f32(p: &[u8], off: usize) -> f32 {
    p.get(off..off + 4)
        .and_then(|b| b.try_into().ok())
        .map_or(f32::NAN, f32::from_le_bytes)
}

/// One value of `datatype` at `off` in record `p` (checked to fit), as f32.
fn read_value(p: &[u8], (off, t): (usize, u8), big_endian: bool) -> f32 {
    macro_rules! get {
        ($ty:ty, $n:expr) => {{
            let a: [u8; $n] = p
                .get(off..off + $n)
                .and_then(|b| b.try_into().ok())
                .unwrap_or([0; $n]);
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
}

/// [`decode`], with the named field read into `Point::intensity`; also says whether the
/// message has that field.
fn decode_with(
    label: &Path,
    cloud: &CloudRef<'_>,
    max_points: usize,
    value_field: &str,
) -> Result<(Scan, bool), FormatError> {
    let points = CloudPoints::with_value(label, cloud, max_points, value_field)?
        .search_placeholders(label)?;
    let found = points.value.is_some();
    let mut scan = Scan {
        points: (0..points.len()).map(|i| points.point(i)).collect(),
        source_index: points.source_index,
        records: points.layout.records,
        ..Scan::default()
    };
    if cloud.height > 1 {
        scan.organized = Some((cloud.height, cloud.width));
    }
    scan.stamp_ns = cloud.stamp_ns();
    scan.frame_id = Some(cloud.frame_id.to_string());
    Ok((scan, found))
}

/// The point data and layout of an output cloud built from an input one.
#[derive(Debug, Clone, PartialEq)]
pub struct CloudData {
    /// Rows.
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The point layout.
    pub fields: Vec<PointField>,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    pub data: Vec<u8>,
    /// No point has a non-finite coordinate.
    pub is_dense: bool,
}

/// The input cloud, every record and field as it was, with a FLOAT32 `ground_probability`
/// field appended (in the cloud's byte order, 4-byte aligned): one value per record,
/// `per_record[i]` for record `i`. An organized cloud keeps its rows; rows are packed.
/// A field of that name already in the input is dropped from the layout.
pub fn with_probability(
    label: &Path,
    cloud: &CloudRef<'_>,
    per_record: &[f32],
    max_points: usize,
) -> Result<CloudData, FormatError> {
    let layout = Layout::per_record(label, cloud, max_points, per_record.len(), "probabilities")?;
    let offset = layout.point_step.next_multiple_of(4);
    let step = offset + 4;
    let mut data = vec![0u8; step * layout.records];
    for ((out, &p), record) in data
        .chunks_exact_mut(step)
        .zip(per_record)
        .zip(layout.records(cloud.data))
    {
        out[..layout.point_step].copy_from_slice(record);
        let bytes = if cloud.is_bigendian {
            p.to_be_bytes()
        } else {
            p.to_le_bytes()
        };
        out[offset..].copy_from_slice(&bytes);
    }
    let mut fields: Vec<PointField> = cloud
        .fields
        .iter()
        .filter(|f| f.name != PROBABILITY_FIELD)
        .cloned()
        .collect();
    fields.push(PointField {
        name: PROBABILITY_FIELD.into(),
        offset: offset as u32,
        datatype: FLOAT32,
        count: 1,
    });
    Ok(CloudData {
        height: cloud.height,
        width: cloud.width,
        fields,
        point_step: step as u32,
        row_step: (step * layout.width) as u32,
        data,
        is_dense: cloud.is_dense,
    })
}

/// One `sensor_msgs/PointField` in CDR.
fn put_field(out: &mut Vec<u8>, name: &str, offset: u32, datatype: u8, count: u32) {
    put_string(out, name);
    put_u32(out, offset);
    out.push(datatype);
    put_u32(out, count);
}

/// A cloud of the input's header (its stamp and frame as they were) as a little-endian CDR
/// PointCloud2: what [`with_probability`] or [`select_records`] made of an input cloud,
/// written to a recording.
pub fn encode_data(input: &CloudRef<'_>, cloud: &CloudData) -> Vec<u8> {
    let mut out = cdr::message();
    put_u32(&mut out, input.stamp_sec as u32);
    put_u32(&mut out, input.stamp_nanosec);
    put_string(&mut out, input.frame_id);
    put_u32(&mut out, cloud.height);
    put_u32(&mut out, cloud.width);
    put_u32(&mut out, cloud.fields.len() as u32);
    for f in &cloud.fields {
        put_field(&mut out, &f.name, f.offset, f.datatype, f.count);
    }
    out.push(u8::from(input.is_bigendian));
    put_u32(&mut out, cloud.point_step);
    put_u32(&mut out, cloud.row_step);
    put_u32(&mut out, cloud.data.len() as u32);
    out.extend_from_slice(&cloud.data);
    out.push(u8::from(cloud.is_dense));
    out
}

/// The records `keep` selects (one flag per record), every field as it was, as an
/// unorganized cloud (height 1).
pub fn select_records(
    label: &Path,
    cloud: &CloudRef<'_>,
    keep: &[bool],
    max_points: usize,
) -> Result<CloudData, FormatError> {
    let layout = Layout::per_record(label, cloud, max_points, keep.len(), "flags")?;
    let kept = keep.iter().filter(|&&k| k).count();
    let mut data = Vec::with_capacity(kept * layout.point_step);
    for (record, _) in layout.records(cloud.data).zip(keep).filter(|(_, k)| **k) {
        data.extend_from_slice(record);
    }
    Ok(CloudData {
        height: 1,
        width: kept as u32,
        fields: cloud.fields.to_vec(),
        point_step: layout.point_step as u32,
        row_step: (kept * layout.point_step) as u32,
        data,
        is_dense: cloud.is_dense,
    })
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
        put_field(&mut out, name, 4 * i as u32, FLOAT32, 1);
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
    probabilities(label, &parse(label, msg)?.cloud(), max_points)
}

/// [`decode_probabilities`] for a message already parsed.
pub fn probabilities(
    label: &Path,
    cloud: &CloudRef<'_>,
    max_points: usize,
) -> Result<Vec<f32>, FormatError> {
    let (scan, found) = decode_with(label, cloud, max_points, PROBABILITY_FIELD)?;
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
    use crate::scan::NonFinite;

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

    proptest::proptest! {
        /// The one-pass copy gives what point-by-point reading gives, for any layout: rows
        /// with padding, fields in any order and type, either endianness, placeholders.
        #[test]
        fn copying_all_points_equals_reading_them_one_by_one(
            height in 1u32..4,
            width in 1u32..40,
            pad in 0u32..3,
            row_pad in 0u32..2,
            f64_x in proptest::bool::ANY,
            big in proptest::bool::ANY,
            with_intensity in proptest::bool::ANY,
            holes in proptest::collection::vec(0usize..160, 0..5),
            seed in 0u32..1000,
        ) {
            // x (f32 or f64), y, z, intensity (f32), `pad` 4-byte words of padding.
            let xs = if f64_x { 8 } else { 4 };
            let mut fields = vec![
                PointField { name: "y".into(), offset: 0, datatype: FLOAT32, count: 1 },
                PointField { name: "z".into(), offset: 4, datatype: FLOAT32, count: 1 },
                PointField { name: "x".into(), offset: 8, datatype: if f64_x { 8 } else { FLOAT32 }, count: 1 },
            ];
            if with_intensity {
                fields.push(PointField { name: "intensity".into(), offset: 8 + xs, datatype: FLOAT32, count: 1 });
            }
            let point_step = 8 + xs + 4 + 4 * pad;
            let row_step = width * point_step + 4 * row_pad;
            let records = (height * width) as usize;
            let mut data = vec![0u8; (height * row_step) as usize];
            for r in 0..records {
                let o = (r / width as usize) * row_step as usize + (r % width as usize) * point_step as usize;
                let v = |k: u32| ((r as u32 * 7 + k * 13 + seed) % 101) as f32 * 0.25 - 10.0;
                let hole = holes.contains(&r);
                let x = if hole { f32::NAN } else { v(0) };
                let mut put = |at: usize, b: &[u8]| data[o + at..o + at + b.len()].copy_from_slice(b);
                let f4 = |f: f32| if big { f.to_be_bytes() } else { f.to_le_bytes() };
                put(0, &f4(v(1)));
                put(4, &f4(v(2)));
                if f64_x {
                    let d = f64::from(x);
                    put(8, &if big { d.to_be_bytes() } else { d.to_le_bytes() });
                } else {
                    put(8, &f4(x));
                }
                put(8 + xs as usize, &f4(v(3)));
            }
            let cloud = CloudRef {
                stamp_sec: 0, stamp_nanosec: 0, frame_id: "f", height, width, fields: &fields,
                is_bigendian: big, point_step, row_step, data: &data, is_dense: false,
            };
            let Ok(points) = CloudPoints::new(Path::new("p"), &cloud, 10_000) else {
                // Every record a placeholder: refused either way.
                proptest::prop_assert!((0..records).all(|r| holes.contains(&r)));
                return Ok(());
            };
            let one_by_one: Vec<Point> = (0..points.len()).map(|i| points.point(i)).collect();
            let mut copied = vec![Point::new(0.0, 0.0, 0.0); points.len() + 2];
            proptest::prop_assert_eq!(points.copy_into(&mut copied, |p| p), (points.len(), true));
            proptest::prop_assert_eq!(&copied[..points.len()], &one_by_one[..]);
            proptest::prop_assert!(copied[points.len()..].iter().all(|p| p.x == 0.0));
            // Unsearched, every record is copied, and the copy tells whether one is no
            // point; its finite records are the points.
            let every = CloudPoints::unsearched(Path::new("p"), &cloud, 10_000).expect("layout");
            let mut all = vec![Point::new(0.0, 0.0, 0.0); records];
            let none_missing = !(0..records).any(|r| holes.contains(&r));
            proptest::prop_assert_eq!(every.copy_into(&mut all, |p| p), (records, none_missing));
            let kept: Vec<Point> = all.into_iter().filter(|p| p.x.is_finite()).collect();
            proptest::prop_assert_eq!(&kept[..], &one_by_one[..]);
        }
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

    /// A 2 × 2 organized cloud with a padded row and an extra `ring` field.
    fn organized() -> (Vec<PointField>, Vec<u8>) {
        let fields = vec![
            PointField {
                name: "x".into(),
                offset: 0,
                datatype: FLOAT32,
                count: 1,
            },
            PointField {
                name: "y".into(),
                offset: 4,
                datatype: FLOAT32,
                count: 1,
            },
            PointField {
                name: "z".into(),
                offset: 8,
                datatype: FLOAT32,
                count: 1,
            },
            PointField {
                name: "ring".into(),
                offset: 12,
                datatype: 4,
                count: 1,
            },
        ];
        // point_step 14, row_step 30 (2 bytes of padding per row).
        let mut data = Vec::new();
        for row in 0..2u16 {
            for col in 0..2u16 {
                let k = f32::from(2 * row + col);
                let x = if (row, col) == (1, 0) { f32::NAN } else { k };
                for v in [x, -k, 0.5 * k] {
                    data.extend_from_slice(&v.to_le_bytes());
                }
                data.extend_from_slice(&(10 + row).to_le_bytes());
            }
            data.extend_from_slice(&[0xee, 0xee]);
        }
        (fields, data)
    }

    fn view<'a>(fields: &'a [PointField], data: &'a [u8]) -> CloudRef<'a> {
        CloudRef {
            stamp_sec: 5,
            stamp_nanosec: 6,
            frame_id: "os_lidar",
            height: 2,
            width: 2,
            fields,
            is_bigendian: false,
            point_step: 14,
            row_step: 30,
            data,
            is_dense: false,
        }
    }

    #[test]
    fn the_probability_field_is_appended_to_every_record_keeping_the_others() {
        let (fields, data) = organized();
        let input = view(&fields, &data);
        let out = with_probability(Path::new("c"), &input, &[0.1, 0.2, 0.0, 0.9], 10).unwrap();
        assert_eq!(
            (out.height, out.width, out.point_step, out.row_step),
            (2, 2, 20, 40)
        );
        assert_eq!(out.fields.len(), 5);
        assert_eq!(out.fields[4].offset, 16);
        let back = CloudRef {
            fields: &out.fields,
            point_step: out.point_step,
            row_step: out.row_step,
            data: &out.data,
            ..input
        };
        assert_eq!(
            probabilities(Path::new("c"), &back, 10).unwrap(),
            vec![0.1, 0.2, 0.0, 0.9]
        );
        // Every input byte of every record is where it was; the ring field survives.
        for i in 0..4 {
            let src = &data[(i / 2) * 30 + (i % 2) * 14..][..14];
            assert_eq!(&out.data[i * 20..i * 20 + 14], src, "record {i}");
        }
        let scan = decode_cloud(Path::new("c"), &back, 10).unwrap();
        assert_eq!(scan.source_index, Some(vec![0, 1, 3]));
        // A count that does not match the records is an error, not a short cloud.
        assert!(with_probability(Path::new("c"), &input, &[0.5; 3], 10).is_err());
    }

    #[test]
    fn a_malformed_field_table_is_refused_with_the_field_named() {
        let (fields, data) = organized();
        type Spoil = fn(&mut Vec<PointField>);
        let cases: [(&str, Spoil, &str); 4] = [
            ("count 4e9", |f| f[3].count = 4_000_000_000, "does not fit"),
            ("count 0", |f| f[1].count = 0, "count 0"),
            ("x twice", |f| f[3].name = "x".into(), "appears twice"),
            ("datatype 9", |f| f[3].datatype = 9, "unknown datatype"),
        ];
        for (what, spoil, says) in cases {
            let mut bad = fields.clone();
            spoil(&mut bad);
            let cloud = view(&bad, &data);
            for e in [
                decode_cloud(Path::new("c"), &cloud, 10).unwrap_err(),
                with_probability(Path::new("c"), &cloud, &[0.5; 4], 10).unwrap_err(),
            ] {
                let e = e.to_string();
                assert!(e.contains(says) && e.contains("field \""), "{what}: {e}");
            }
        }
        assert!(decode_cloud(Path::new("c"), &view(&fields, &data), 10).is_ok());
    }

    #[test]
    fn selected_records_keep_their_bytes_in_order() {
        let (fields, data) = organized();
        let input = view(&fields, &data);
        let out = select_records(Path::new("c"), &input, &[true, false, false, true], 10).unwrap();
        assert_eq!(
            (out.height, out.width, out.point_step, out.row_step),
            (1, 2, 14, 28)
        );
        assert_eq!(&out.data[..14], &data[..14]);
        assert_eq!(&out.data[14..], &data[30 + 14..30 + 28]);
        let none = select_records(Path::new("c"), &input, &[false; 4], 10).unwrap();
        assert_eq!((none.width, none.data.len()), (0, 0));
        assert!(select_records(Path::new("c"), &input, &[true; 5], 10).is_err());
    }
}
