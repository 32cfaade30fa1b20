//! Every reader against files written by independent tools (see `fixtures/README.md`):
//! the points must be exactly the KITTI scan's points they were cut from.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::path::{Path, PathBuf};

use groundwork_core::Point;
use groundwork_io::{InputKind, RecordingReader, ScanFormat, read_scan};

const STRIDE: usize = 97;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// The points the fixtures were made from, read by the KITTI reader.
fn source_points() -> Vec<Point> {
    let kitti = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/semantickitti-00/velodyne/000000.bin");
    let scan = read_scan(&kitti, 200_000).unwrap();
    scan.points.into_iter().step_by(STRIDE).collect()
}

#[test]
fn pcd_in_all_three_encodings_matches_the_source() {
    let want = source_points();
    for name in [
        "kitti_ascii.pcd",
        "kitti_binary.pcd",
        "kitti_binary_compressed.pcd",
    ] {
        let scan = read_scan(&fixture(name), 200_000).unwrap();
        assert_eq!(scan.points.len(), want.len(), "{name}");
        for (i, (a, b)) in scan.points.iter().zip(&want).enumerate() {
            if name.contains("ascii") {
                // pypcd4 prints ascii values with 10 decimals: tiny values lose digits.
                let close = |u: f32, v: f32| (u - v).abs() <= 1e-10 + 1e-7 * v.abs();
                assert!(
                    close(a.x, b.x) && close(a.y, b.y) && close(a.z, b.z),
                    "{name} point {i}: {a:?} vs {b:?}"
                );
            } else {
                assert_eq!(a, b, "{name} point {i}");
            }
        }
        assert_eq!(scan.skipped(), 0, "{name}");
        assert_eq!(
            InputKind::detect(&fixture(name)).unwrap(),
            InputKind::Scan(ScanFormat::Pcd)
        );
    }
}

#[test]
fn ply_ascii_and_binary_match_the_source() {
    let want = source_points();
    for name in ["kitti_ascii.ply", "kitti_binary_le.ply"] {
        let scan = read_scan(&fixture(name), 200_000).unwrap();
        for (i, (a, b)) in scan.points.iter().zip(&want).enumerate() {
            // plyfile's ascii writer prints shortest round-trip reprs; binary is exact.
            assert_eq!(a, b, "{name} point {i}");
        }
        assert_eq!(scan.points.len(), want.len(), "{name}");
    }
}

#[test]
fn magic_bytes_find_the_reader_when_the_name_says_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let want = source_points();
    for (name, kind) in [
        (
            "kitti_binary_compressed.pcd",
            InputKind::Scan(ScanFormat::Pcd),
        ),
        ("kitti_binary_le.ply", InputKind::Scan(ScanFormat::Ply)),
        ("kitti_pointcloud2.mcap", InputKind::Recording),
    ] {
        let anon = dir.path().join(name.replace('.', "_"));
        std::fs::copy(fixture(name), &anon).unwrap();
        assert_eq!(InputKind::detect(&anon).unwrap(), kind, "{name}");
        if let InputKind::Scan(_) = kind {
            assert_eq!(read_scan(&anon, 200_000).unwrap().points, want);
        }
    }
    // A folder may mix formats; it lists scans only, recordings and label files not.
    std::fs::copy(fixture("kitti_binary.pcd"), dir.path().join("b.pcd")).unwrap();
    std::fs::write(dir.path().join("000000.label"), [0u8; 8]).unwrap();
    let listed = groundwork_io::list_scans(dir.path()).unwrap();
    let names: Vec<_> = listed
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        names,
        [
            "b.pcd",
            "kitti_binary_compressed_pcd",
            "kitti_binary_le_ply"
        ]
    );
}

#[test]
fn ros2_recording_honours_layout_endianness_and_placeholders() {
    let want = source_points();
    let scans: Vec<_> = RecordingReader::open(&fixture("kitti_pointcloud2.mcap"), None, 200_000)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(scans.len(), 3, "the /chatter messages are not scans");
    assert!(scans.iter().all(|s| s.topic == "/points"));
    let t0 = 1_700_000_000_000_000_000u64;
    for (k, s) in scans.iter().enumerate() {
        assert_eq!(s.index, k);
        assert_eq!(s.log_time_ns, t0 + k as u64 * 100_000_000);
        assert_eq!(s.scan.stamp_ns, Some(s.log_time_ns));
        assert_eq!(s.scan.frame_id.as_deref(), Some("os_lidar"));
    }
    // Little- and big-endian messages carry the same points.
    assert_eq!(scans[0].scan.points, want);
    assert_eq!(scans[2].scan.points, want);
    // The organized, non-dense one: two placeholders left out, mapped back.
    let holes = &scans[1].scan;
    let even = want.len() - want.len() % 2;
    assert_eq!(holes.records, even);
    assert_eq!(holes.organized, Some((2, (even / 2) as u32)));
    assert_eq!(holes.skipped(), 2);
    let index = holes.source_index.as_ref().unwrap();
    assert!(!index.contains(&5) && !index.contains(&17));
    for (p, &i) in holes.points.iter().zip(index) {
        assert_eq!(*p, want[i as usize]);
    }
    // A probability per point expands to one per record, 0 at the placeholders.
    let probs = holes.expand(&vec![1.0; holes.points.len()], 0.0);
    assert_eq!(probs.len(), even);
    assert_eq!((probs[5], probs[17], probs[6]), (0.0, 0.0, 1.0));
}

#[test]
fn a_topic_that_is_not_a_point_cloud_is_an_error_per_message() {
    let errors: Vec<String> =
        RecordingReader::open(&fixture("kitti_pointcloud2.mcap"), Some("/chatter"), 1000)
            .unwrap()
            .map(|r| r.unwrap_err().to_string())
            .collect();
    assert_eq!(errors.len(), 3);
    assert!(
        errors[1].contains("kitti_pointcloud2.mcap (message 1 on /chatter)")
            && errors[1].contains("std_msgs/msg/String"),
        "{}",
        errors[1]
    );
}

#[test]
fn a_rosbag2_sqlite_bag_reads_like_a_recording() {
    let want = source_points();
    let half = want.len() / 2;
    let db3 = fixture("kitti_rosbag2/kitti_rosbag2.db3");
    assert_eq!(
        InputKind::detect(&db3).ok(),
        Some(InputKind::Recording),
        "by name"
    );
    let scans: Vec<_> = RecordingReader::open(&db3, None, 200_000)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(scans.len(), 2, "the /chatter message is not a scan");
    let t0 = 1_700_000_000_000_000_000u64;
    for (k, s) in scans.iter().enumerate() {
        assert_eq!((s.index, s.topic.as_str()), (k, "/points"));
        assert_eq!(s.log_time_ns, t0 + k as u64 * 100_000_000);
        assert_eq!(s.scan.stamp_ns, Some(s.log_time_ns));
        assert_eq!(s.scan.frame_id.as_deref(), Some("velodyne"));
    }
    // Plain x, y, z, intensity, then the same with a ring field and padding.
    assert_eq!(scans[0].scan.points, want[..half]);
    assert_eq!(scans[1].scan.points, want[half..]);
    assert_eq!(
        RecordingReader::count(&db3, None, 200_000).unwrap(),
        2,
        "counted as read"
    );
    // The other topic passes through with its type and the bag's message definition.
    let others: Vec<_> = RecordingReader::others(&db3, "/points", 200_000)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(others.len(), 1);
    let schema = others[0].schema.as_ref().unwrap();
    assert_eq!(
        (others[0].topic.as_str(), schema.name.as_str()),
        ("/chatter", "std_msgs/msg/String")
    );
    assert_eq!(others[0].encoding, "cdr");
    // CDR of the string "hello": encapsulation, length 6, the bytes and the NUL.
    assert_eq!(&others[0].data[4..8], &6u32.to_le_bytes());
    assert_eq!(&others[0].data[8..13], b"hello");

    // A message larger than max_points allows is a bad scan, named; the rest reads on.
    let small: Vec<_> = RecordingReader::open(&db3, None, 10).unwrap().collect();
    assert_eq!(small.len(), 2);
    for r in &small {
        let e = r.as_ref().unwrap_err().to_string();
        assert!(e.contains("kitti_rosbag2.db3"), "{e}");
    }
    // The bag's folder (metadata.yaml beside the .db3) is read as that recording.
    let folder = groundwork_io::ScanSource::open(&fixture("kitti_rosbag2"), None).unwrap();
    let names: Vec<_> = folder
        .scans(200_000)
        .filter(|s| s.scan.is_ok())
        .map(|s| s.name)
        .collect();
    assert_eq!(names, ["kitti_rosbag2_000000", "kitti_rosbag2_000001"]);
}

#[test]
fn a_file_that_is_not_a_rosbag2_bag_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let fake = dir.path().join("broken.db3");
    // SQLite's magic, then nothing a database needs.
    let mut bytes = b"SQLite format 3\0".to_vec();
    bytes.resize(4096, 0xAB);
    std::fs::write(&fake, &bytes).unwrap();
    let e = RecordingReader::open(&fake, None, 1000)
        .map(|r| r.collect::<Vec<_>>())
        .map_err(|e| e.to_string());
    let text = match e {
        Err(e) => e,
        Ok(items) => items
            .into_iter()
            .find_map(Result::err)
            .map(|e| e.to_string())
            .unwrap_or_default(),
    };
    assert!(
        text.contains("broken.db3") && text.contains("rosbag2 SQLite"),
        "{text}"
    );
}
