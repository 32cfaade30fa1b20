//! Stanford `.ply` files: the `vertex` element's x, y, z and (optionally) intensity, ascii
//! or binary, parsed by `ply-rs-bw` straight into our point type (no per-vertex maps).

use std::io::BufReader;
use std::path::Path;

use groundwork_core::Point;
use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{Encoding, PropertyAccess, PropertyAccessResult, PropertyType, ScalarType};

use crate::error::FormatError;
use crate::scan::{NonFinite, Scan, checked_count};

/// A vertex as the parser fills it; unknown properties are ignored.
#[derive(Debug, Default)]
struct Vertex(Point);

/// Intensity goes by several names in the tools that write PLY point clouds.
fn is_intensity(name: &str) -> bool {
    matches!(
        name.to_ascii_lowercase().as_str(),
        "intensity" | "scalar_intensity" | "reflectance"
    )
}

impl Vertex {
    fn set(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        match name {
            "x" => self.0.x = v,
            "y" => self.0.y = v,
            "z" => self.0.z = v,
            n if is_intensity(n) => self.0.intensity = v,
            _ => return PropertyAccessResult::Ignored,
        }
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for Vertex {
    fn new() -> Self {
        Self::default()
    }
    fn set_char(&mut self, name: &str, v: i8) -> PropertyAccessResult {
        self.set(name, f32::from(v))
    }
    fn set_uchar(&mut self, name: &str, v: u8) -> PropertyAccessResult {
        self.set(name, f32::from(v))
    }
    fn set_short(&mut self, name: &str, v: i16) -> PropertyAccessResult {
        self.set(name, f32::from(v))
    }
    fn set_ushort(&mut self, name: &str, v: u16) -> PropertyAccessResult {
        self.set(name, f32::from(v))
    }
    fn set_int(&mut self, name: &str, v: i32) -> PropertyAccessResult {
        self.set(name, v as f32)
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        self.set(name, v as f32)
    }
    fn set_float(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        self.set(name, v)
    }
    fn set_double(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        self.set(name, v as f32)
    }
}

fn scalar_size(t: &ScalarType) -> u64 {
    match t {
        ScalarType::Char | ScalarType::UChar => 1,
        ScalarType::Short | ScalarType::UShort => 2,
        ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
        ScalarType::Double => 8,
    }
}

/// Reads the vertices of a `.ply` file. Elements before `vertex` (rare) are read and
/// dropped; elements after it (faces of a mesh) are not read at all.
pub fn read(path: &Path, max_points: usize) -> Result<Scan, FormatError> {
    let (file, size) = crate::file::open_regular(path)?;
    let mut reader = Reader::new(BufReader::new(file));
    let parser = Parser::<Vertex>::new();
    let ply_err =
        |e: ply_rs_bw::parser::ParseError| FormatError::malformed(path, format!("PLY: {e}"));
    let header = parser.read_header(&mut reader).map_err(ply_err)?;
    let Some(vertex) = header.elements.get("vertex") else {
        return Err(FormatError::malformed(path, "PLY has no vertex element"));
    };
    for axis in ["x", "y", "z"] {
        match vertex.properties.get(axis).map(|p| &p.data_type) {
            Some(PropertyType::Scalar(_)) => {}
            _ => {
                return Err(FormatError::malformed(
                    path,
                    format!("PLY vertex has no scalar property {axis:?}"),
                ));
            }
        }
    }
    let n = checked_count(path, vertex.count as u64, max_points)?;
    if n == 0 {
        return Err(FormatError::Empty {
            path: path.to_path_buf(),
        });
    }
    // Every element up to the vertices is read, so each must fit in the file: a binary
    // record holds at least its scalars and list lengths (lists make it longer, never
    // shorter), an ascii record at least two bytes per value and a line end; a record
    // without properties still counts one byte, or `element junk 4000000000` would cost
    // the parser 4e9 records for nothing. Checked before the parser reserves anything for
    // a claimed count.
    let mut declared = 0u64;
    for element in header.elements.values() {
        let min_record: u64 = element
            .properties
            .values()
            .map(|p| match (&p.data_type, &header.encoding) {
                (_, Encoding::Ascii) => 2,
                (PropertyType::Scalar(t), _) => scalar_size(t),
                (PropertyType::List(len, _), _) => scalar_size(len),
            })
            .sum();
        declared =
            declared.saturating_add((element.count as u64).saturating_mul(min_record.max(1)));
        if declared > size {
            return Err(FormatError::malformed(
                path,
                format!(
                    "PLY header declares {} {:?} elements, more than its {size} bytes can hold (truncated, or a lying header)",
                    element.count, element.name
                ),
            ));
        }
        if element.name == "vertex" {
            break;
        }
    }
    let mut vertices = Vec::new();
    for element in header.elements.values() {
        let read = parser
            .read_payload_for_element(&mut reader, element, &header)
            .map_err(ply_err)?;
        if element.name == "vertex" {
            vertices = read;
            break;
        }
    }
    let points = vertices.into_iter().map(|v| v.0).collect();
    Scan::from_records(path, points, NonFinite::Reject)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;

    #[test]
    fn ascii_vertices_with_double_coordinates() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.ply");
        fs::write(
            &p,
            "ply\nformat ascii 1.0\ncomment by hand\nelement vertex 2\nproperty double x\nproperty double y\nproperty double z\nproperty uchar scalar_Intensity\nend_header\n1 2 3 4\n-1.5 0 2.25 255\n",
        )
        .unwrap();
        let s = read(&p, 10).unwrap();
        assert_eq!(
            s.points,
            vec![
                Point {
                    x: 1.0,
                    y: 2.0,
                    z: 3.0,
                    intensity: 4.0
                },
                Point {
                    x: -1.5,
                    y: 0.0,
                    z: 2.25,
                    intensity: 255.0
                }
            ]
        );
    }

    #[test]
    fn lying_counts_and_missing_axes_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.ply");
        fs::write(
            &p,
            "ply\nformat binary_little_endian 1.0\nelement vertex 1000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0",
        )
        .unwrap();
        let e = read(&p, 2_000_000).unwrap_err().to_string();
        assert!(e.contains("b.ply") && e.contains("lying header"), "{e}");
        fs::write(
            &p,
            "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
        )
        .unwrap();
        let e = read(&p, 10).unwrap_err().to_string();
        assert!(e.contains("\"z\""), "{e}");
        fs::write(&p, "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n").unwrap();
        let e = read(&p, 10).unwrap_err().to_string();
        assert!(e.contains("b.ply"), "{e}");
    }

    #[test]
    fn a_huge_element_before_the_vertices_is_refused_before_allocating() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bomb.ply");
        let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement junk 4000000000\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n".to_vec();
        bytes.extend_from_slice(&[0; 12]);
        fs::write(&p, &bytes).unwrap();
        let e = read(&p, 10).unwrap_err().to_string();
        assert!(
            e.contains("bomb.ply") && e.contains("\"junk\"") && e.contains("lying header"),
            "{e}"
        );
        // The same element with a count the file can hold is read and dropped.
        let mut ok = b"ply\nformat binary_little_endian 1.0\nelement junk 2\nproperty uchar a\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n".to_vec();
        ok.extend_from_slice(&[7, 8]);
        ok.extend([1.0f32, 2.0, 3.0].iter().flat_map(|v| v.to_le_bytes()));
        fs::write(&p, &ok).unwrap();
        assert_eq!(read(&p, 10).unwrap().points[0], Point::new(1.0, 2.0, 3.0));
    }
}
