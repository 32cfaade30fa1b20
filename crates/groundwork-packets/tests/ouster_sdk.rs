//! groundwork's decoding of Ouster captures against ouster-sdk's (PyPI `ouster-sdk` 1.0,
//! Ouster's own SDK, which we did not write).
//!
//! The captures and their metadata are written at test time from a real KITTI scan by the
//! packet layout of Ouster's documentation (`scripts/fixtures/ouster_pcap.py`: an OS1-64,
//! 12.5 kB packets fragmented at a 1500-byte MTU); ouster-sdk decodes them
//! (`scripts/fixtures/ouster_reference.py`). Frame by frame: the same frames, the same
//! pixels with a range (matched by beam and column), positions within 1e-4 m, the column
//! times equal.
//!
//! Needs a Python with ouster-sdk: `GROUNDWORK_PACKET_PEERS_PYTHON`, set by
//! `crates/groundwork-py/test.sh` (see tests/velodyne_decoder.rs).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

mod peers;

use std::collections::HashMap;
use std::path::Path;

use groundwork_packets::{PacketReport, PacketScans, SensorDecoder, ouster};
use peers::{arg, for_each_scan, peer_python, read_reference, root, run, script};

fn compare(extra: &[&str]) -> PacketReport {
    compare_capture(extra, None)
}

/// As [`compare`], on a capture and its metadata if given (else written from KITTI).
fn compare_capture(extra: &[&str], capture: Option<(&Path, &Path)>) -> PacketReport {
    let Some(python) = peer_python() else {
        return Default::default();
    };
    let dir = tempfile::tempdir().unwrap();
    let (pcap, meta) = capture.map_or_else(
        || (dir.path().join("os.pcap"), dir.path().join("os.json")),
        |(p, m)| (p.to_path_buf(), m.to_path_buf()),
    );
    let reference = dir.path().join("reference.bin");
    if capture.is_none() {
        let mut args = vec![
            script("ouster_pcap.py"),
            "--scan".into(),
            arg(&root().join("tests/data/semantickitti-00/velodyne/000002.bin")),
            "--out".into(),
            arg(&pcap),
            "--metadata-out".into(),
            arg(&meta),
        ];
        args.extend(extra.iter().map(|a| a.to_string()));
        run(&python, &args);
    }
    run(
        &python,
        &[
            script("ouster_reference.py"),
            arg(&pcap),
            "--metadata".into(),
            arg(&meta),
            "--out".into(),
            arg(&reference),
        ],
    );
    // A frame: its id (the header) and pixels (row, column, x, y, z, time).
    let expected = read_reference::<6>(&reference, 4, 8);

    let decoder = ouster::Decoder::new(ouster::Metadata::read(&meta).unwrap());
    let mut scans = PacketScans::new(SensorDecoder::Ouster(Box::new(decoder.clone())));
    let mut got: Vec<Vec<ouster::Return>> = Vec::new();
    let source = for_each_scan(&mut scans, &pcap, ouster::LIDAR_PORT, |scans, out| {
        let mut px = Vec::new();
        decoder.decode_scan(out, |r| px.push(r));
        assert_eq!(px.len(), scans.count(out));
        got.push(px);
    });
    // The captures written here travel in fragments (a 1500-byte MTU).
    assert!(
        capture.is_some() || source.counters().fragments > 0,
        "fragmented datagrams"
    );
    assert_eq!(got.len(), expected.len(), "frames");
    for (k, ((_, want), have)) in expected.iter().zip(&got).enumerate() {
        assert_eq!(have.len(), want.len(), "frame {k}: pixels with a range");
        assert!(want.len() > 200, "frame {k}: a real scan");
        let by_pixel: HashMap<(u16, u16), &ouster::Return> =
            have.iter().map(|r| ((r.row, r.column), r)).collect();
        for w in want {
            let h = by_pixel
                .get(&(w[0] as u16, w[1] as u16))
                .unwrap_or_else(|| panic!("frame {k}: no pixel {w:?}"));
            for (c, v) in [h.x, h.y, h.z].into_iter().enumerate() {
                assert!(
                    (w[2 + c] - v as f64).abs() <= 1e-4,
                    "frame {k} pixel {w:?}: {h:?}"
                );
            }
            assert_eq!(w[5] as u64, h.time_ns, "frame {k} pixel {w:?}: time");
        }
    }
    scans.report()
}

#[test]
fn os1_64_rng19_with_a_lost_packet_and_stray_datagrams_matches_ouster_sdk() {
    let report = compare(&["--faults", "--drop", "70"]);
    if report.counters.packets > 0 {
        assert_eq!(report.counters.lost, 1);
        assert_eq!(report.refused.get("wrong size"), Some(&1));
    }
}

#[test]
fn os1_64_legacy_2048_matches_ouster_sdk() {
    compare(&["--profile", "LEGACY", "--width", "2048", "--frames", "1.6"]);
}

/// A capture bundled in tests/data/packets (`<stem>.pcap` with its metadata `<stem>.json`).
fn compare_bundled(stem: &str) -> PacketReport {
    let data = root().join("tests/data/packets");
    compare_capture(
        &[],
        Some((
            &data.join(format!("{stem}.pcap")),
            &data.join(format!("{stem}.json")),
        )),
    )
}

/// The capture the replay tests use (tests/data/packets): an OS1-16 in 512x10.
#[test]
fn the_bundled_os1_16_capture_matches_ouster_sdk() {
    let report = compare_bundled("os1-16-kitti-000002");
    if report.counters.packets > 0 {
        assert_eq!((report.counters.packets, report.counters.lost), (56, 1));
    }
}

/// A real sensor's capture: an OS1-32 (firmware 2.1.1, 1024x10, LEGACY profile, the flat
/// metadata of firmware 1.x/2.0), from ouster-sdk's own test data (tests/data/packets).
#[test]
fn a_real_os1_32_capture_matches_ouster_sdk() {
    let report = compare_bundled("OS-1-32-G_v2.1.1_1024x10");
    if report.counters.packets > 0 {
        assert_eq!((report.counters.packets, report.counters.lost), (64, 0));
        assert!(report.refused.is_empty(), "{report:?}");
    }
}
