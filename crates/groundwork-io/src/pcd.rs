//! Point Cloud Library `.pcd` files, v0.5–0.7: ascii, binary and binary_compressed.
//!
//! Only x, y, z and (optionally) intensity are kept; they may come in any order, with any
//! numeric type, among any other fields and `_` padding. Non-finite coordinates are the
//! placeholders PCL writes for missing returns (`is_dense = false` clouds): they are left
//! out and mapped back (see [`Scan`]).
//!
//! Written here rather than with `pcd-rs`: that crate allocates the sizes a
//! binary_compressed header claims before checking them against the file, decodes every
//! point into a vector of dynamically typed fields, and cannot skip placeholders while
//! keeping their indices. The LZF decompression is the `lzf` crate's.

use std::fs;
use std::io::Read;
use std::path::Path;

use groundwork_core::Point;

use crate::error::FormatError;
use crate::scan::{NonFinite, Scan, checked_count};

/// A header longer than this is not a PCD header.
const MAX_HEADER: u64 = 64 * 1024;
/// LZF expands at most about 88:1 (a 3-byte back-reference yields 264 bytes); a claim
/// beyond this is a lie, refused before anything is allocated for it.
const MAX_LZF_RATIO: u64 = 100;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    Ascii,
    Binary,
    BinaryCompressed,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Float,
    Unsigned,
    Signed,
}

#[derive(Debug, Clone)]
struct Field {
    name: String,
    size: usize,
    kind: Kind,
    count: usize,
}

#[derive(Debug)]
struct Header {
    fields: Vec<Field>,
    width: u64,
    height: u64,
    points: u64,
    encoding: Encoding,
    /// Bytes of the header, up to and including the DATA line.
    len: usize,
}

impl Header {
    fn point_size(&self) -> usize {
        self.fields.iter().map(|f| f.size * f.count).sum()
    }

    fn values_per_point(&self) -> usize {
        self.fields.iter().map(|f| f.count).sum()
    }

    /// Index of a field by name, if present.
    fn find(&self, name: &str) -> Option<usize> {
        self.fields.iter().position(|f| f.name == name)
    }
}

fn parse_header(path: &Path, head: &[u8]) -> Result<Header, FormatError> {
    let bad = |line: usize, m: String| FormatError::parse(path, line, m);
    let (mut names, mut sizes, mut types, mut counts) = (None, None, None, None);
    let (mut width, mut height, mut points) = (None, None, None);
    let mut pos = 0usize;
    let mut line_no = 0usize;
    loop {
        line_no += 1;
        let Some(end) = head[pos..].iter().position(|&b| b == b'\n') else {
            return Err(FormatError::malformed(
                path,
                "PCD header has no DATA line (truncated, or not a PCD file)",
            ));
        };
        let raw = &head[pos..pos + end];
        pos += end + 1;
        let line = std::str::from_utf8(raw)
            .map_err(|_| bad(line_no, "PCD header line is not text".into()))?
            .trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut words = line.split_whitespace();
        let key = words.next().unwrap_or_default().to_ascii_uppercase();
        let rest: Vec<&str> = words.collect();
        let number = |w: &str| {
            w.parse::<u64>()
                .map_err(|_| bad(line_no, format!("{key}: not a whole number: {w:?}")))
        };
        let one = |rest: &[&str]| match rest {
            [w] => number(w),
            _ => Err(bad(line_no, format!("{key}: expected one number"))),
        };
        match key.as_str() {
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" | "COLUMNS" => {
                names = Some(rest.iter().map(|s| s.to_string()).collect::<Vec<_>>())
            }
            "SIZE" => {
                sizes = Some(
                    rest.iter()
                        .map(|w| number(w))
                        .collect::<Result<Vec<_>, _>>()?,
                )
            }
            "COUNT" => {
                counts = Some(
                    rest.iter()
                        .map(|w| number(w))
                        .collect::<Result<Vec<_>, _>>()?,
                )
            }
            "TYPE" => {
                types = Some(
                    rest.iter()
                        .map(|w| match *w {
                            "F" => Ok(Kind::Float),
                            "U" => Ok(Kind::Unsigned),
                            "I" => Ok(Kind::Signed),
                            _ => Err(bad(line_no, format!("TYPE: unknown type {w:?}"))),
                        })
                        .collect::<Result<Vec<_>, _>>()?,
                )
            }
            "WIDTH" => width = Some(one(&rest)?),
            "HEIGHT" => height = Some(one(&rest)?),
            "POINTS" => points = Some(one(&rest)?),
            "DATA" => {
                let encoding = match rest.first().map(|w| w.to_ascii_lowercase()).as_deref() {
                    Some("ascii") => Encoding::Ascii,
                    Some("binary") => Encoding::Binary,
                    Some("binary_compressed") => Encoding::BinaryCompressed,
                    other => {
                        return Err(bad(
                            line_no,
                            format!("DATA: unknown encoding {:?}", other.unwrap_or("")),
                        ));
                    }
                };
                let names = names.ok_or_else(|| bad(line_no, "no FIELDS line".into()))?;
                let sizes = sizes.ok_or_else(|| bad(line_no, "no SIZE line".into()))?;
                let types = types.ok_or_else(|| bad(line_no, "no TYPE line".into()))?;
                let counts = counts.unwrap_or_else(|| vec![1; names.len()]);
                if sizes.len() != names.len()
                    || types.len() != names.len()
                    || counts.len() != names.len()
                {
                    return Err(bad(
                        line_no,
                        format!(
                            "{} FIELDS but {} SIZE, {} TYPE and {} COUNT entries",
                            names.len(),
                            sizes.len(),
                            types.len(),
                            counts.len()
                        ),
                    ));
                }
                let mut fields = Vec::with_capacity(names.len());
                for (((name, size), kind), count) in
                    names.into_iter().zip(sizes).zip(types).zip(counts)
                {
                    let ok_size = match kind {
                        Kind::Float => size == 4 || size == 8,
                        _ => matches!(size, 1 | 2 | 4 | 8),
                    };
                    if !ok_size || !(1..=1 << 16).contains(&count) {
                        return Err(bad(
                            line_no,
                            format!("field {name:?}: size {size} / count {count} not supported"),
                        ));
                    }
                    fields.push(Field {
                        name,
                        size: size as usize,
                        kind,
                        count: count as usize,
                    });
                }
                let width = width.ok_or_else(|| bad(line_no, "no WIDTH line".into()))?;
                let height = height.unwrap_or(1);
                let total = width
                    .checked_mul(height)
                    .ok_or_else(|| bad(line_no, "WIDTH × HEIGHT overflows".into()))?;
                let points = points.unwrap_or(total);
                if points != total {
                    return Err(bad(
                        line_no,
                        format!("POINTS {points} but WIDTH × HEIGHT = {width} × {height}"),
                    ));
                }
                return Ok(Header {
                    fields,
                    width,
                    height,
                    points,
                    encoding,
                    len: pos,
                });
            }
            _ => return Err(bad(line_no, format!("unknown PCD header key {key:?}"))),
        }
    }
}

/// Byte offset of each field within a point.
fn offsets(h: &Header) -> Vec<usize> {
    let mut o = 0;
    h.fields
        .iter()
        .map(|f| {
            let this = o;
            o += f.size * f.count;
            this
        })
        .collect()
}

/// One little-endian value of a field as f32.
fn value(b: &[u8], f: &Field) -> f32 {
    let a = |n: usize| -> [u8; 8] {
        let mut x = [0u8; 8];
        x[..n].copy_from_slice(&b[..n]);
        x
    };
    match (f.kind, f.size) {
        (Kind::Float, 4) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        (Kind::Float, _) => f64::from_le_bytes(a(8)) as f32,
        (Kind::Unsigned, n) => u64::from_le_bytes(a(n)) as f32,
        (Kind::Signed, n) => {
            // Sign-extend from n bytes.
            let shift = 64 - 8 * n as u32;
            ((i64::from_le_bytes(a(n)) << shift) >> shift) as f32
        }
    }
}

/// Reads a `.pcd` file; see the module documentation.
pub fn read(path: &Path, max_points: usize) -> Result<Scan, FormatError> {
    let (mut file, size) = crate::file::open_regular(path)?;
    let mut head = Vec::new();
    (&mut file)
        .take(MAX_HEADER.min(size))
        .read_to_end(&mut head)
        .map_err(|e| FormatError::io(path, e))?;
    let h = parse_header(path, &head)?;
    let n = checked_count(path, h.points, max_points)?;
    if n == 0 {
        return Err(FormatError::Empty {
            path: path.to_path_buf(),
        });
    }
    let [x, y, z] = ["x", "y", "z"].map(|name| h.find(name));
    let (Some(x), Some(y), Some(z)) = (x, y, z) else {
        return Err(FormatError::malformed(path, "PCD has no x, y and z fields"));
    };
    let intensity = h.find("intensity").or_else(|| h.find("i"));
    let body_len = size - h.len as u64;
    let point_size = h.point_size();
    let want = n as u64 * point_size as u64;
    let mut rest = Vec::new();
    let records = match h.encoding {
        Encoding::Ascii => {
            file.read_to_end(&mut rest)
                .map_err(|e| FormatError::io(path, e))?;
            let mut all = head[h.len..].to_vec();
            all.extend_from_slice(&rest);
            ascii_records(path, &h, &all, [x, y, z], intensity, n)?
        }
        Encoding::Binary => {
            if body_len < want {
                return Err(FormatError::malformed(
                    path,
                    format!(
                        "binary body has {body_len} bytes, {n} points of {point_size} bytes need {want} (truncated, or a lying header)"
                    ),
                ));
            }
            let body = read_body(path, &mut file, &head[h.len..], want)?;
            let off = offsets(&h);
            // Row-major: point i's field k at i × point_size + its offset.
            assemble(n, [x, y, z], intensity, |i, k| {
                value(&body[i * point_size + off[k]..], &h.fields[k])
            })
        }
        Encoding::BinaryCompressed => {
            if body_len < 8 {
                return Err(FormatError::malformed(
                    path,
                    "binary_compressed body is truncated",
                ));
            }
            let sizes = read_body(path, &mut file, &head[h.len..], 8)?;
            let compressed =
                u64::from(u32::from_le_bytes([sizes[0], sizes[1], sizes[2], sizes[3]]));
            let uncompressed =
                u64::from(u32::from_le_bytes([sizes[4], sizes[5], sizes[6], sizes[7]]));
            if uncompressed != want {
                return Err(FormatError::malformed(
                    path,
                    format!(
                        "binary_compressed body unpacks to {uncompressed} bytes, {n} points of {point_size} bytes are {want}"
                    ),
                ));
            }
            if compressed > body_len - 8 {
                return Err(FormatError::malformed(
                    path,
                    format!(
                        "binary_compressed body claims {compressed} compressed bytes, the file holds {} (truncated, or a lying header)",
                        body_len - 8
                    ),
                ));
            }
            if uncompressed > compressed.saturating_mul(MAX_LZF_RATIO) {
                return Err(FormatError::malformed(
                    path,
                    format!(
                        "binary_compressed body claims {compressed} compressed bytes unpack to {uncompressed}, more than LZF's {MAX_LZF_RATIO}:1 can (a lying header)"
                    ),
                ));
            }
            let already = head.len() - h.len;
            let skip = already.min(8);
            let data = read_body(path, &mut file, &head[h.len + skip..], compressed)?;
            let raw = lzf::decompress(&data, want as usize).map_err(|e| {
                FormatError::malformed(
                    path,
                    format!("binary_compressed body does not unpack: {e:?}"),
                )
            })?;
            if raw.len() != want as usize {
                return Err(FormatError::malformed(
                    path,
                    "binary_compressed body unpacks short",
                ));
            }
            // Column-major: every point's value of field 0, then of field 1, ...
            let mut start = 0usize;
            let starts: Vec<usize> = h
                .fields
                .iter()
                .map(|f| {
                    let s = start;
                    start += n * f.size * f.count;
                    s
                })
                .collect();
            assemble(n, [x, y, z], intensity, |i, k| {
                let f = &h.fields[k];
                value(&raw[starts[k] + i * f.size * f.count..], f)
            })
        }
    };
    let mut scan = Scan::from_records(path, records, NonFinite::Skip)?;
    if h.height > 1 {
        scan.organized = Some((h.height as u32, h.width as u32));
    }
    Ok(scan)
}

/// The points of a binary body, `at(i, k)` being point i's value of field k.
fn assemble(
    n: usize,
    [x, y, z]: [usize; 3],
    intensity: Option<usize>,
    at: impl Fn(usize, usize) -> f32,
) -> Vec<Point> {
    (0..n)
        .map(|i| Point {
            x: at(i, x),
            y: at(i, y),
            z: at(i, z),
            intensity: intensity.map_or(0.0, |k| at(i, k)),
        })
        .collect()
}

/// `len` body bytes: those already read with the header, then the rest from the file.
fn read_body(
    path: &Path,
    file: &mut fs::File,
    already: &[u8],
    len: u64,
) -> Result<Vec<u8>, FormatError> {
    let len = len as usize;
    let mut body = Vec::with_capacity(len);
    body.extend_from_slice(&already[..already.len().min(len)]);
    let missing = (len - body.len()) as u64;
    file.take(missing)
        .read_to_end(&mut body)
        .map_err(|e| FormatError::io(path, e))?;
    if body.len() != len {
        return Err(FormatError::malformed(path, "body is truncated"));
    }
    Ok(body)
}

fn ascii_records(
    path: &Path,
    h: &Header,
    body: &[u8],
    [x, y, z]: [usize; 3],
    intensity: Option<usize>,
    n: usize,
) -> Result<Vec<Point>, FormatError> {
    let text = std::str::from_utf8(body)
        .map_err(|_| FormatError::malformed(path, "ascii body is not text"))?;
    // Token index of each field's first value.
    let mut first = Vec::with_capacity(h.fields.len());
    let mut t = 0;
    for f in &h.fields {
        first.push(t);
        t += f.count;
    }
    let per_point = h.values_per_point();
    let mut records = Vec::with_capacity(n);
    let mut tokens: Vec<&str> = Vec::with_capacity(per_point);
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        if records.len() == n {
            return Err(FormatError::malformed(
                path,
                format!("ascii body has more than the {n} points its header declares"),
            ));
        }
        tokens.clear();
        tokens.extend(line.split_whitespace());
        if tokens.len() != per_point {
            return Err(FormatError::malformed(
                path,
                format!(
                    "ascii point {} (body line {}) has {} values, the header declares {per_point}",
                    records.len(),
                    i + 1,
                    tokens.len()
                ),
            ));
        }
        let get = |k: usize| -> Result<f32, FormatError> {
            let tok = tokens[first[k]];
            tok.parse::<f32>().map_err(|_| {
                FormatError::malformed(
                    path,
                    format!("ascii point {}: {:?} is not a number", records.len(), tok),
                )
            })
        };
        records.push(Point {
            x: get(x)?,
            y: get(y)?,
            z: get(z)?,
            intensity: intensity.map(get).transpose()?.unwrap_or(0.0),
        });
    }
    if records.len() != n {
        return Err(FormatError::malformed(
            path,
            format!(
                "ascii body has {} points, the header declares {n} (truncated?)",
                records.len()
            ),
        ));
    }
    Ok(records)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, bytes: &[u8]) -> std::path::PathBuf {
        let p = dir.join(name);
        fs::write(&p, bytes).unwrap();
        p
    }

    const HEAD: &str = "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n";

    #[test]
    fn padding_counts_and_integer_fields_are_honoured() {
        let dir = tempfile::tempdir().unwrap();
        // PCL-style padding field `_` with count 3, a u16 ring, f64 x.
        let mut bytes = format!(
            "{HEAD}FIELDS x _ y z ring intensity\nSIZE 8 1 4 4 2 1\nTYPE F U F F U U\nCOUNT 1 3 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA binary\n"
        )
        .into_bytes();
        for (x, y, z, ring, i) in [
            (1.5f64, 2.0f32, -1.0f32, 7u16, 200u8),
            (-3.0, 0.5, 0.25, 8, 9),
        ] {
            bytes.extend_from_slice(&x.to_le_bytes());
            bytes.extend_from_slice(&[0xAA; 3]);
            bytes.extend_from_slice(&y.to_le_bytes());
            bytes.extend_from_slice(&z.to_le_bytes());
            bytes.extend_from_slice(&ring.to_le_bytes());
            bytes.push(i);
        }
        let p = write(dir.path(), "pad.pcd", &bytes);
        let s = read(&p, 10).unwrap();
        assert_eq!(
            s.points,
            vec![
                Point {
                    x: 1.5,
                    y: 2.0,
                    z: -1.0,
                    intensity: 200.0
                },
                Point {
                    x: -3.0,
                    y: 0.5,
                    z: 0.25,
                    intensity: 9.0
                }
            ]
        );
        // One byte short.
        let p = write(dir.path(), "short.pcd", &bytes[..bytes.len() - 1]);
        let e = read(&p, 10).unwrap_err().to_string();
        assert!(e.contains("short.pcd") && e.contains("truncated"), "{e}");
    }

    #[test]
    fn organized_ascii_with_nan_placeholders_maps_back() {
        let dir = tempfile::tempdir().unwrap();
        let text = format!(
            "{HEAD}FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA ascii\n1 2 3\nnan nan nan\n4 5 6\n7 8 -9\n"
        );
        let p = write(dir.path(), "org.pcd", text.as_bytes());
        let s = read(&p, 10).unwrap();
        assert_eq!(s.points.len(), 3);
        assert_eq!(s.records, 4);
        assert_eq!(s.organized, Some((2, 2)));
        assert_eq!(s.source_index.as_deref(), Some(&[0u32, 2, 3][..]));
    }

    #[test]
    fn lying_headers_are_refused_before_allocating() {
        let dir = tempfile::tempdir().unwrap();
        let huge = format!(
            "{HEAD}FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 100000\nHEIGHT 1\nPOINTS 100000\nDATA binary_compressed\n"
        );
        let mut b = huge.clone().into_bytes();
        b.extend_from_slice(&4_000_000_000u32.to_le_bytes());
        b.extend_from_slice(&1_200_000u32.to_le_bytes());
        let p = write(dir.path(), "lie.pcd", &b);
        let e = read(&p, 200_000).unwrap_err().to_string();
        assert!(
            e.contains("lie.pcd") && e.contains("compressed bytes"),
            "{e}"
        );
        let p = write(dir.path(), "many.pcd", huge.as_bytes());
        let e = read(&p, 1000).unwrap_err().to_string();
        assert!(e.contains("maximum of 1000"), "{e}");
        let p = write(
            dir.path(),
            "nofields.pcd",
            b"VERSION 0.7\nWIDTH 1\nDATA ascii\n",
        );
        let e = read(&p, 10).unwrap_err().to_string();
        assert!(e.contains("nofields.pcd:3") && e.contains("FIELDS"), "{e}");
        let p = write(
            dir.path(),
            "noxyz.pcd",
            b"FIELDS a b\nSIZE 4 4\nTYPE F F\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2\n",
        );
        assert!(
            read(&p, 10)
                .unwrap_err()
                .to_string()
                .contains("no x, y and z")
        );
    }
}
