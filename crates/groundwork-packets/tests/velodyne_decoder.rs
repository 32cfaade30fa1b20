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

use std::path::{Path, PathBuf};
use std::process::Command;

use groundwork_packets::{
    Calibration, Decoder, Model, PacketScans, PcapSource, ScanPackets, SensorDecoder,
};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn peer_python() -> Option<PathBuf> {
    match std::env::var_os("GROUNDWORK_PACKET_PEERS_PYTHON") {
        Some(p) => Some(PathBuf::from(p)),
        None => {
            assert!(
                std::env::var_os("GROUNDWORK_REQUIRE_PACKET_PEERS").is_none(),
                "GROUNDWORK_REQUIRE_PACKET_PEERS is set but GROUNDWORK_PACKET_PEERS_PYTHON is not"
            );
            eprintln!("skipped: GROUNDWORK_PACKET_PEERS_PYTHON is not set");
            None
        }
    }
}

fn run(python: &Path, args: &[&str]) {
    let out = Command::new(python).args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A reference scan: stamp (s) and points (x, y, z, intensity, ring, time).
fn read_reference(path: &Path) -> Vec<(f64, Vec<[f32; 6]>)> {
    let b = std::fs::read(path).unwrap();
    let mut scans = Vec::new();
    let mut at = 0;
    while at < b.len() {
        let n = u32::from_le_bytes(b[at..at + 4].try_into().unwrap()) as usize;
        let stamp = f64::from_le_bytes(b[at + 4..at + 12].try_into().unwrap());
        at += 12;
        let points = (0..n)
            .map(|i| {
                std::array::from_fn(|c| {
                    let o = at + (i * 6 + c) * 4;
                    f32::from_le_bytes(b[o..o + 4].try_into().unwrap())
                })
            })
            .collect();
        at += n * 24;
        scans.push((stamp, points));
    }
    scans
}

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
    let script = |name: &str| root().join("scripts/fixtures").join(name);
    let mut args: Vec<String> = vec![
        script("velodyne_pcap.py").display().to_string(),
        "--model".into(),
        model.into(),
        "--scan".into(),
        scan.display().to_string(),
        "--out".into(),
        pcap.display().to_string(),
        "--calibration-out".into(),
        cal.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    if capture.is_none() {
        run(
            &python,
            &args.iter().map(String::as_str).collect::<Vec<_>>(),
        );
    }
    let mut args = vec![
        script("velodyne_reference.py").display().to_string(),
        pcap.display().to_string(),
        "--out".into(),
        reference.display().to_string(),
    ];
    let (model_id, calibration) = if model == "hdl64e" {
        args.extend([
            "--model".into(),
            "hdl64e".into(),
            "--calibration".into(),
            cal.display().to_string(),
        ]);
        (Model::Hdl64eS3, Some(Calibration::read(&cal).unwrap()))
    } else {
        (Model::from_name(model).unwrap(), None)
    };
    run(
        &python,
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
    );
    let expected = read_reference(&reference);

    let mut scans = PacketScans::new(SensorDecoder::Velodyne(Box::new(
        Decoder::new(model_id, calibration).unwrap(),
    )));
    let mut source = PcapSource::open(&pcap, Some(2368)).unwrap();
    let mut got: Vec<Vec<([f32; 6], u64)>> = Vec::new();
    let mut out = ScanPackets::default();
    let mut take = |scans: &PacketScans, out: &ScanPackets| {
        let mut points = Vec::with_capacity(scans.count(out));
        scans.decode(out, |r| {
            points.push(([r.x, r.y, r.z, r.intensity, r.ring as f32, 0.0], r.time_ns));
        });
        assert_eq!(points.len(), scans.count(out), "count agrees with decode");
        got.push(points);
    };
    while let Some(d) = source.next_datagram() {
        if scans.push(&d.unwrap(), 0, &mut out) {
            take(&scans, &out);
        }
    }
    if scans.flush(0, &mut out) {
        take(&scans, &out);
    }
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
            let want_t = stamp + w[5] as f64;
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
