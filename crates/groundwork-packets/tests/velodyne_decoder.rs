//! groundwork's decoding of Velodyne captures against velodyne_decoder's (PyPI
//! `velodyne-decoder` 3.1, C++ with Python bindings, which we did not write).
//!
//! The captures are written at test time from a real KITTI scan by the sensors' packet
//! layout (`scripts/fixtures/velodyne_pcap.py`); the peer decodes them
//! (`scripts/fixtures/velodyne_reference.py`). Scan by scan, the same packets, the same
//! returns in the same order, positions within 1e-4 m, ring and intensity equal, the
//! sensor time within 2 µs.
//!
//! Needs a Python with velodyne-decoder and numpy: `GROUNDWORK_PACKET_PEERS_PYTHON`.
//! `crates/groundwork-py/test.sh` (the second half of the README's test command) installs
//! them and runs these tests with it set (and `GROUNDWORK_REQUIRE_PACKET_PEERS`, which turns
//! a missing peer into a failure instead of a skip).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

mod peers;

use std::path::Path;

use groundwork_packets::{Calibration, Decoder, Model, PacketScans, SensorDecoder};
use peers::{arg, for_each_scan, peer_python, read_reference, root, run, script};

/// Writes a capture of `model` from KITTI frame 0, decodes it both ways, compares.
fn compare(model: &str, extra: &[&str]) -> groundwork_packets::PacketReport {
    compare_capture(model, extra, None)
}

/// As [`compare`], on `capture` if given (else written from KITTI frame 0).
fn compare_capture(
    model: &str,
    extra: &[&str],
    capture: Option<&Path>,
) -> groundwork_packets::PacketReport {
    let Some(python) = peer_python() else {
        return Default::default();
    };
    let dir = tempfile::tempdir().unwrap();
    let pcap = capture.map_or_else(
        || dir.path().join(format!("{model}.pcap")),
        Path::to_path_buf,
    );
    let cal = dir.path().join("calibration.yaml");
    let reference = dir.path().join("reference.bin");
    let scan = root().join("tests/data/semantickitti-00/velodyne/000000.bin");
    if capture.is_none() {
        let mut args = vec![
            script("velodyne_pcap.py"),
            "--model".into(),
            model.into(),
            "--scan".into(),
            arg(&scan),
            "--out".into(),
            arg(&pcap),
            "--calibration-out".into(),
            arg(&cal),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        run(&python, &args);
    }
    let mut args = vec![
        script("velodyne_reference.py"),
        arg(&pcap),
        "--out".into(),
        arg(&reference),
    ];
    let (model_id, calibration) = if model == "hdl64e" {
        args.extend([
            "--model".into(),
            "hdl64e".into(),
            "--calibration".into(),
            arg(&cal),
        ]);
        (Model::Hdl64eS3, Some(Calibration::read(&cal).unwrap()))
    } else {
        (Model::from_name(model).unwrap(), None)
    };
    run(&python, &args);
    // A scan: stamp (s, the header's f64) and points (x, y, z, intensity, ring, time).
    let expected: Vec<(f64, Vec<[f64; 6]>)> = read_reference::<6>(&reference, 8, 4)
        .into_iter()
        .map(|(h, p)| (f64::from_le_bytes(h.try_into().unwrap()), p))
        .collect();

    let mut scans = PacketScans::new(SensorDecoder::Velodyne(Box::new(
        Decoder::new(model_id, calibration).unwrap(),
    )));
    let mut got: Vec<Vec<([f64; 6], u64)>> = Vec::new();
    for_each_scan(&mut scans, &pcap, 2368, |scans, out| {
        let mut points = Vec::with_capacity(scans.count(out));
        scans.decode(out, |r| {
            let p = [r.x, r.y, r.z, r.intensity, r.ring as f32, 0.0];
            points.push((p.map(f64::from), r.time_ns));
        });
        assert_eq!(points.len(), scans.count(out), "count agrees with decode");
        got.push(points);
    });
    assert_eq!(got.len(), expected.len(), "{model}: scans");
    assert!(got.len() >= 2, "{model}: at least two scans");
    for (k, ((stamp, want), have)) in expected.iter().zip(&got).enumerate() {
        assert_eq!(have.len(), want.len(), "{model} scan {k}: points");
        assert!(want.len() > 1000, "{model} scan {k}: a real scan");
        for (i, (w, (h, t))) in want.iter().zip(have).enumerate() {
            for c in 0..3 {
                assert!(
                    (w[c] - h[c]).abs() <= 1e-4,
                    "{model} scan {k} point {i}: {w:?} against {h:?}"
                );
            }
            assert_eq!(w[4], h[4], "{model} scan {k} point {i}: ring");
            assert!(
                (w[3] - h[3]).abs() <= 1e-3,
                "{model} scan {k} point {i}: intensity {w:?} against {h:?}"
            );
            let want_t = stamp + w[5];
            let have_t = *t as f64 * 1e-9;
            assert!(
                (want_t - have_t).abs() < 2e-6,
                "{model} scan {k} point {i}: time {want_t} against {have_t}"
            );
        }
    }
    scans.report()
}

#[test]
fn vlp16_with_a_lost_packet_and_stray_records_matches_velodyne_decoder() {
    let report = compare("vlp16", &["--faults", "--drop", "40"]);
    if report.counters.packets > 0 {
        assert_eq!(report.counters.lost, 1);
        // The 100-byte datagram to the data port; the position packet (port 8308) and the
        // ARP frame never reach the decoder.
        assert_eq!(report.refused.get("wrong size"), Some(&1));
    }
}

#[test]
fn vlp16_dual_return_matches_velodyne_decoder() {
    compare("vlp16", &["--dual", "--turns", "1.6"]);
}

#[test]
fn vlp32c_matches_velodyne_decoder() {
    compare("vlp32c", &["--turns", "1.6", "--hz", "20"]);
}

#[test]
fn hdl32e_matches_velodyne_decoder() {
    compare("hdl32e", &["--turns", "1.6"]);
}

#[test]
fn hdl64e_with_its_calibration_file_matches_velodyne_decoder() {
    compare("hdl64e", &["--turns", "1.4"]);
}

/// The capture the replay tests use (tests/data/packets).
#[test]
fn the_bundled_vlp16_capture_matches_velodyne_decoder() {
    let capture = root().join("tests/data/packets/vlp16-kitti-000001.pcap");
    let report = compare_capture("vlp16", &[], Some(&capture));
    if report.counters.packets > 0 {
        assert_eq!((report.counters.packets, report.counters.lost), (89, 1));
    }
}
