//! Every reader and config parser fed truncated, random and lying inputs: an error (or a
//! valid result), never a panic, and never an allocation larger than the file.
//!
//! A counting global allocator records the largest single allocation of the reader's
//! thread while a reader runs; the tests share one lock for the shared maximum.

#![allow(unsafe_code)] // the counting allocator below
#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use groundwork_core::Point;
use groundwork_io::{
    FormatError, RecordingReader, parse_config, read_calib_tr, read_labels, read_poses, read_prob,
    read_scan, write_kitti_bin,
};
use proptest::prelude::*;

struct Counting;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    /// Set on the thread running a reader: only its allocations count (tests run in
    /// parallel, and another test's fixture loading must not count as this reader's).
    static MEASURING: Cell<bool> = const { Cell::new(false) };
}

fn record(size: usize) {
    if MEASURING.try_with(Cell::get).unwrap_or(false) {
        LARGEST.fetch_max(size, Ordering::Relaxed);
    }
}

// SAFETY: forwards every call to the system allocator unchanged; only records sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: same layout the caller gave us.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: ptr was allocated by System with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
        // SAFETY: ptr was allocated by System with this layout.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

static SERIAL: Mutex<()> = Mutex::new(());

/// Small allocations anything makes (paths, error messages, proptest's own bookkeeping).
const SLACK: usize = 64 * 1024;

/// Writes `bytes` to `name`, runs `read` on it, and checks: no panic, no allocation larger
/// than the file (+ slack), an error that names the file. Returns whether it was accepted.
fn run<T, E: std::fmt::Display>(
    name: &str,
    bytes: &[u8],
    read: impl Fn(&Path) -> Result<T, E>,
) -> Result<bool, TestCaseError> {
    run_bounded(name, bytes, bytes.len(), read)
}

/// [`run`] for compressed formats, whose reader may legitimately unpack up to `bound`
/// bytes (what it accepts for the configured maximum of points) from a smaller file.
fn run_bounded<T, E: std::fmt::Display>(
    name: &str,
    bytes: &[u8],
    bound: usize,
    read: impl Fn(&Path) -> Result<T, E>,
) -> Result<bool, TestCaseError> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, bytes).unwrap();
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    LARGEST.store(0, Ordering::Relaxed);
    MEASURING.with(|m| m.set(true));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| read(&path)));
    MEASURING.with(|m| m.set(false));
    let largest = LARGEST.load(Ordering::Relaxed);
    let Ok(result) = result else {
        return Err(TestCaseError::fail(format!("{name}: reader panicked")));
    };
    prop_assert!(
        largest <= bound.max(bytes.len()) + SLACK,
        "{name}: allocated {largest} bytes for a {}-byte file",
        bytes.len()
    );
    if let Err(e) = &result {
        prop_assert!(e.to_string().contains(name), "{e}");
    }
    Ok(result.is_ok())
}

fn kitti_bytes(n: usize) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.bin");
    let pts: Vec<Point> = (0..n)
        .map(|i| Point::new(i as f32, -(i as f32), 0.5))
        .collect();
    write_kitti_bin(&p, &pts).unwrap();
    std::fs::read(p).unwrap()
}

/// Fixtures written by independent tools (see `fixtures/README.md`), to be mangled.
const FIXTURES: [&str; 6] = [
    "kitti_ascii.pcd",
    "kitti_binary.pcd",
    "kitti_binary_compressed.pcd",
    "kitti_ascii.ply",
    "kitti_binary_le.ply",
    "kitti_pointcloud2.mcap",
];

fn fixture(name: &str) -> Vec<u8> {
    std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures")
            .join(name),
    )
    .unwrap()
}

/// Reads any scan file or recording to the end; the first error, if any.
fn read_any(path: &Path) -> Result<usize, FormatError> {
    if path.extension().is_some_and(|e| e == "mcap") {
        let mut points = 0;
        for s in RecordingReader::open(path, None, MAX_POINTS)? {
            points += s?.scan.points.len();
        }
        Ok(points)
    } else {
        read_scan(path, MAX_POINTS).map(|s| s.points.len())
    }
}

/// Scans of the fixtures have 1286 points.
const MAX_POINTS: usize = 2000;

/// What reading `name` may allocate at most: a compressed format unpacks up to what the
/// reader accepts for `MAX_POINTS` points, anything else no more than the file.
fn bound(name: &str, bytes: &[u8]) -> usize {
    if name.ends_with(".mcap") {
        RecordingReader::record_limit(MAX_POINTS)
    } else if name.contains("compressed") {
        MAX_POINTS * 64
    } else {
        bytes.len()
    }
}

/// The last character boundary of `s` at or before byte `i` (the presets hold `°`).
fn boundary(s: &str, i: usize) -> usize {
    let mut i = i.min(s.len());
    while !s.is_char_boundary(i) {
        i -= 1;
    }
    i
}

/// A PLY whose header declares an element before `vertex` with `count` records and no
/// properties, followed by one vertex.
fn ply_with_junk_element(count: u64) -> Vec<u8> {
    let mut b = format!("ply\nformat binary_little_endian 1.0\nelement junk {count}\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n").into_bytes();
    b.extend_from_slice(&[0; 12]);
    b
}

/// An MCAP file holding one zstd chunk that unpacks to `zeros` zero bytes (9-byte records
/// of opcode 0: a reader that walks them finds nothing) and declares `declared` of them.
fn zstd_bomb(zeros: usize, declared: u64) -> Vec<u8> {
    use std::io::Write;
    let mut enc = zstd::stream::Encoder::new(Vec::new(), 3).unwrap();
    let block = vec![0u8; 1 << 16];
    let mut left = zeros;
    while left > 0 {
        let n = left.min(block.len());
        enc.write_all(&block[..n]).unwrap();
        left -= n;
    }
    let compressed = enc.finish().unwrap();
    let record = |out: &mut Vec<u8>, op: u8, body: &[u8]| {
        out.push(op);
        out.extend_from_slice(&(body.len() as u64).to_le_bytes());
        out.extend_from_slice(body);
    };
    let string = |b: &mut Vec<u8>, s: &str| {
        b.extend_from_slice(&(s.len() as u32).to_le_bytes());
        b.extend_from_slice(s.as_bytes());
    };
    let mut out = b"\x89MCAP0\r\n".to_vec();
    let mut header = Vec::new();
    string(&mut header, "ros2");
    string(&mut header, "bomb");
    record(&mut out, 0x01, &header);
    let mut chunk = Vec::new();
    chunk.extend_from_slice(&0u64.to_le_bytes()); // start time
    chunk.extend_from_slice(&0u64.to_le_bytes()); // end time
    chunk.extend_from_slice(&declared.to_le_bytes());
    chunk.extend_from_slice(&0u32.to_le_bytes()); // no CRC
    string(&mut chunk, "zstd");
    chunk.extend_from_slice(&(compressed.len() as u64).to_le_bytes());
    chunk.extend_from_slice(&compressed);
    record(&mut out, 0x06, &chunk);
    record(&mut out, 0x0F, &0u32.to_le_bytes());
    record(&mut out, 0x02, &[0; 20]);
    out.extend_from_slice(b"\x89MCAP0\r\n");
    out
}

const POSES: &str = "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0.8 0 1 0 0 0 0 1 0.1\n";
const CALIB: &str = "P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 0 1 0 0 0\n";

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn binary_readers_survive_random_bytes(bytes in prop::collection::vec(any::<u8>(), 0..2048)) {
        run("r.bin", &bytes, |p| read_scan(p, 400_000))?;
        run("r.pcd.bin", &bytes, |p| read_scan(p, 400_000))?;
        run("r.label", &bytes, |p| read_labels(p, 100))?;
        run("r.pcd", &bytes, read_any)?;
        run("r.ply", &bytes, read_any)?;
        run_bounded("r.mcap", &bytes, bound("r.mcap", &bytes), read_any)?;
        run("r.prob", &bytes, read_prob)?;
    }

    #[test]
    fn truncated_binary_files_are_errors(n in 1usize..300, cut in 1usize..16) {
        let full = kitti_bytes(n);
        prop_assert!(!run("t.bin", &full[..full.len() - cut], |p| read_scan(p, 400_000))?);
        // A label file short of a record, or with a torn one.
        let labels = vec![0u8; 4 * n - cut.min(4 * n - 1)];
        prop_assert!(!run("t.label", &labels, |p| read_labels(p, n))?);
    }

    /// The caller's expectation lies (labels for a scan of a billion points; a maximum of
    /// a few points): an error from the file size, no allocation for what was claimed.
    #[test]
    fn lying_sizes_allocate_nothing_they_claim(n in 1usize..200, claim in 1_000_000usize..2_000_000_000) {
        prop_assert!(!run("l.label", &vec![0u8; 4 * n], |p| read_labels(p, claim))?);
        prop_assert!(!run("s.bin", &kitti_bytes(n + 5), |p| read_scan(p, n))?);
    }

    /// Files other tools wrote, truncated, with bytes overwritten and junk inserted: a
    /// header that now lies about counts, sizes or lengths is an error, never a panic or
    /// an allocation of what it claims.
    #[test]
    fn format_readers_survive_mangled_fixtures(
        which in 0usize..FIXTURES.len(),
        cut in 0.0f64..1.0,
        flips in prop::collection::vec((0.0f64..1.0, any::<u8>()), 0..6),
        junk in prop::collection::vec(any::<u8>(), 0..16),
        insert_at in 0.0f64..1.0,
    ) {
        let name = FIXTURES[which];
        let mut bytes = fixture(name);
        // Mostly keep the whole file, so that flips land in headers and bodies too.
        let keep = if cut < 0.5 { bytes.len() } else { (bytes.len() as f64 * (cut - 0.5) * 2.0) as usize };
        bytes.truncate(keep);
        for (at, value) in flips {
            if !bytes.is_empty() {
                let i = (at * bytes.len() as f64) as usize % bytes.len();
                bytes[i] = value;
            }
        }
        let at = (insert_at * bytes.len() as f64) as usize;
        bytes.splice(at..at, junk);
        run_bounded(name, &bytes, bound(name, &bytes), read_any)?;
    }

    #[test]
    fn text_readers_survive_mangled_text(
        cut in 0usize..120,
        junk in "[ -~\n]{0,40}",
        insert_at in 0usize..120,
    ) {
        for (name, text) in [("poses.txt", POSES), ("calib.txt", CALIB)] {
            let mut s = text[..boundary(text, cut)].to_string();
            s.insert_str(boundary(&s, insert_at), &junk);
            run(name, s.as_bytes(), read_poses)?;
            run(name, s.as_bytes(), read_calib_tr)?;
        }
    }

    #[test]
    fn config_parser_survives_mangled_presets(
        cut in 0usize..2000,
        junk in "[ -~\n]{0,40}",
        insert_at in 0usize..2000,
    ) {
        let preset = include_str!("../../../config/sensors/hdl64e.toml");
        let mut s = preset[..boundary(preset, cut)].to_string();
        s.insert_str(boundary(&s, insert_at), &junk);
        run("sensor.toml", s.as_bytes(), |p| {
            parse_config(p, &std::fs::read_to_string(p).unwrap())
        })?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Elements before the vertices must fit in the file, whatever their count.
    #[test]
    fn ply_elements_before_the_vertices_must_fit(count in 0u64..u64::from(u32::MAX)) {
        let bytes = ply_with_junk_element(count);
        let accepted = run("junk.ply", &bytes, |p| read_scan(p, MAX_POINTS))?;
        // 12 bytes of vertex: at most that many header-declared junk records fit beside it.
        prop_assert_eq!(accepted, count == 0);
    }

    /// A zstd chunk unpacks to at most what it declares, and never far more than its size.
    #[test]
    fn zstd_chunks_cost_what_they_declare(zeros in 0usize..(4 << 20), declared in 0u64..(1 << 40)) {
        let bytes = zstd_bomb(zeros, declared);
        let bound = RecordingReader::record_limit(MAX_POINTS);
        prop_assert!(!run_bounded("bomb.mcap", &bytes, bound, read_any)?);
    }
}

#[test]
fn a_zstd_bomb_is_refused_as_one() {
    // 256 MiB of zeros in about 10 KB: refused at the ratio bound after a MiB or two of
    // output, not walked record by record (which took 115 s of CPU per MB of file).
    let bytes = zstd_bomb(256 << 20, 256 << 20);
    assert!(bytes.len() < 64 << 10, "{}", bytes.len());
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bomb.mcap");
    std::fs::write(&p, &bytes).unwrap();
    let e = read_any(&p).unwrap_err().to_string();
    assert!(
        e.contains("bomb.mcap") && e.contains("decompression bomb"),
        "{e}"
    );
    // A chunk may not unpack to more than it declares, either.
    std::fs::write(&p, zstd_bomb(1 << 16, 1 << 10)).unwrap();
    let e = read_any(&p).unwrap_err().to_string();
    assert!(e.contains("bomb.mcap") && e.contains("decompress"), "{e}");
}

#[test]
fn the_fixtures_the_strategies_start_from_are_valid() {
    assert!(run("v.bin", &kitti_bytes(10), |p| read_scan(p, 100)).unwrap());
    for name in FIXTURES {
        let bytes = fixture(name);
        assert!(
            run_bounded(name, &bytes, bound(name, &bytes), read_any).unwrap(),
            "{name}"
        );
    }
    assert!(run("poses.txt", POSES.as_bytes(), read_poses).unwrap());
    assert!(run("calib.txt", CALIB.as_bytes(), read_calib_tr).unwrap());
    let preset = include_str!("../../../config/sensors/hdl64e.toml");
    assert!(
        run("sensor.toml", preset.as_bytes(), |p| parse_config(
            p, preset
        ))
        .unwrap()
    );
}
