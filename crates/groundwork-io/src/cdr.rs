//! Little-endian CDR (the ROS 2 wire format) for the messages recordings carry: the
//! encapsulation header, aligned primitives, strings and `std_msgs/Header`.

/// A message: its 4-byte encapsulation header (CDR, little-endian) and nothing yet.
pub(crate) fn message() -> Vec<u8> {
    vec![0, 1, 0, 0]
}

/// Pads `out` to `align` bytes after the encapsulation header (CDR aligns each primitive
/// to its size, counted from there).
fn align(out: &mut Vec<u8>, align: usize) {
    while !(out.len() - 4).is_multiple_of(align) {
        out.push(0);
    }
}

pub(crate) fn put_u32(out: &mut Vec<u8>, v: u32) {
    align(out, 4);
    out.extend_from_slice(&v.to_le_bytes());
}

pub(crate) fn put_f64(out: &mut Vec<u8>, v: f64) {
    align(out, 8);
    out.extend_from_slice(&v.to_le_bytes());
}

/// A string: its length with the NUL, its bytes, the NUL.
pub(crate) fn put_string(out: &mut Vec<u8>, s: &str) {
    put_u32(out, s.len() as u32 + 1);
    out.extend_from_slice(s.as_bytes());
    out.push(0);
}

/// A `std_msgs/Header`: the stamp (seconds, nanoseconds) and the frame.
pub(crate) fn put_header(out: &mut Vec<u8>, stamp_ns: u64, frame_id: &str) {
    put_u32(out, (stamp_ns / 1_000_000_000) as u32);
    put_u32(out, (stamp_ns % 1_000_000_000) as u32);
    put_string(out, frame_id);
}
