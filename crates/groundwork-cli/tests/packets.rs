//! Scans from a sensor's packets through the service: a pcap replayed, packets sent live
//! over UDP by a test process, bad captures named. Each test has its own service names;
//! they run one at a time (two cores).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::net::UdpSocket;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

static SERIAL: Mutex<()> = Mutex::new(());

fn capture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/data/packets/vlp16-kitti-000001.pcap")
}

fn prefix(test: &str) -> String {
    format!("gwtest-pk-{test}-{}", std::process::id())
}

fn groundwork() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_groundwork"));
    c.env("RUST_LOG", "info");
    c
}

/// A number in a log line: `key=N` after `marker`.
fn logged(log: &str, marker: &str, key: &str) -> u64 {
    let line = log
        .lines()
        .rev()
        .find(|l| l.contains(marker))
        .unwrap_or_else(|| panic!("no {marker:?} in:\n{log}"));
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(&format!("{key}=")))
        .unwrap_or_else(|| panic!("no {key} in {line}"))
        .parse()
        .unwrap()
}

/// The bundled capture (two whole VLP-16 turns and a part, one packet lost, three stray
/// records) through producer, segmenter, detector and consumer: every scan masked, the
/// fate adding up, the loss and the refused datagram counted, the latency from the last
/// packet to the published scan in the consumer's table.
#[test]
fn a_capture_replays_through_the_pipeline_with_every_scan_masked() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let out = groundwork()
        .args([
            "pipeline",
            "--sensor",
            "vlp16",
            "--packets",
            "velodyne",
            "--pcap",
        ])
        .arg(capture())
        .args(["--prefix", &prefix("replay"), "--out"])
        .arg(tmp.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.starts_with("pipeline: 3 scans of vlp16 packets from"),
        "{stdout}"
    );
    assert!(
        stdout.contains("3 masks (3 segmented")
            && stdout.contains("scan fate: 3 masked + 0 rejected + 0 unanswered + 0 dropped = 3"),
        "{stdout}"
    );
    assert!(stdout.contains("last packet to scan published"), "{stdout}");
    assert!(!stdout.contains("producer fill"), "{stdout}");
    assert_eq!(
        logged(&stderr, "producer: packets ", "packets"),
        89,
        "{stderr}"
    );
    assert_eq!(logged(&stderr, "producer: packets ", "lost"), 1);
    assert_eq!(logged(&stderr, "producer: packets ", "refused"), 1);
    // One probability per decoded point, written per scan.
    let written: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.path().extension().is_some_and(|x| x == "prob"))
        .collect();
    assert_eq!(written.len(), 3, "{written:?}");
    for f in written {
        let prob = groundwork_io::read_prob(&f.path()).unwrap();
        assert!(prob.len() > 1000 && prob.iter().all(|p| (0.0..=1.0).contains(p)));
    }
}

/// An Ouster capture (an OS1-16, 3.3 kB packets in IP fragments) with its metadata: every
/// frame masked.
#[test]
fn an_ouster_capture_replays_through_the_pipeline() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let data = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/packets");
    let out = groundwork()
        .args([
            "pipeline",
            "--sensor",
            "os1-64",
            "--packets",
            "ouster",
            "--pcap",
        ])
        .arg(data.join("os1-16-kitti-000002.pcap"))
        .arg("--sensor-config")
        .arg(data.join("os1-16-kitti-000002.json"))
        .args(["--no-detector", "--prefix", &prefix("ouster")])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("3 masks (3 segmented")
            && stdout.contains("scan fate: 3 masked + 0 rejected + 0 unanswered + 0 dropped = 3"),
        "{stdout}"
    );
    assert_eq!(
        logged(&stderr, "producer: packets ", "packets"),
        56,
        "{stderr}"
    );
    assert_eq!(logged(&stderr, "producer: packets ", "lost"), 1);
    assert_eq!(logged(&stderr, "producer: packets ", "refused"), 1);
    // A real sensor's frame (an OS1-32, ouster-sdk's test data): segmented.
    let real = groundwork()
        .args([
            "pipeline",
            "--sensor",
            "os1-64",
            "--packets",
            "ouster",
            "--pcap",
        ])
        .arg(data.join("OS-1-32-G_v2.1.1_1024x10.pcap"))
        .arg("--sensor-config")
        .arg(data.join("OS-1-32-G_v2.1.1_1024x10.json"))
        .args(["--no-detector", "--prefix", &prefix("ouster-real")])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&real.stdout);
    assert!(
        real.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&real.stderr)
    );
    assert!(stdout.contains("1 masks (1 segmented"), "{stdout}");

    // Without its metadata an Ouster's packets cannot be read: said so.
    let bare = groundwork()
        .args(["producer", "--packets", "ouster", "--pcap"])
        .arg(data.join("os1-16-kitti-000002.pcap"))
        .args(["--prefix", &prefix("ouster-bare")])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&bare.stderr);
    assert_eq!(bare.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("metadata JSON"), "{stderr}");
}

/// Live: the pipeline listens on a UDP port; a test process sends the capture's packets
/// to it at the sensor's pace until two scans are masked.
#[test]
fn packets_sent_over_udp_are_segmented_live() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let port = UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut pipeline = groundwork()
        .args([
            "pipeline",
            "--sensor",
            "vlp16",
            "--packets",
            "velodyne",
            "--udp",
        ])
        .arg(format!("127.0.0.1:{port}"))
        .args(["--count", "2", "--no-detector", "--prefix", &prefix("udp")])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The capture's data packets, as the sensor sends them.
    let mut payloads = Vec::new();
    let mut pcap = groundwork_packets::PcapSource::open(&capture(), Some(2368)).unwrap();
    while let Some(d) = pcap.next_datagram() {
        payloads.push(d.unwrap().payload.to_vec());
    }
    let sender = UdpSocket::bind("127.0.0.1:0").unwrap();
    let start = Instant::now();
    // Sent in a loop (the sensor's azimuth wraps, as a spinning sensor's does) until the
    // pipeline has what it asked for.
    'send: while start.elapsed() < Duration::from_secs(60) {
        for p in &payloads {
            if pipeline.try_wait().unwrap().is_some() {
                break 'send;
            }
            sender.send_to(p, ("127.0.0.1", port)).unwrap();
            std::thread::sleep(Duration::from_micros(600));
        }
    }
    let out = pipeline.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("2 masks (2 segmented"),
        "{stdout}\n{stderr}"
    );
    assert!(stdout.contains("last packet to scan published"), "{stdout}");
}

/// A truncated capture, a missing one, an HDL-64E without its calibration file: named,
/// never a panic; the scans before the damage are still segmented.
#[test]
fn bad_captures_and_missing_calibration_are_named() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(capture()).unwrap();
    let cut = tmp.path().join("cut.pcap");
    // Cut in the middle of the 70th record: one whole scan before it.
    std::fs::write(&cut, &bytes[..bytes.len() * 3 / 4 + 7]).unwrap();
    let out = groundwork()
        .args([
            "pipeline",
            "--sensor",
            "vlp16",
            "--packets",
            "velodyne",
            "--pcap",
        ])
        .arg(&cut)
        .args(["--no-detector", "--prefix", &prefix("cut")])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("cut.pcap: record") && stderr.contains("truncated"),
        "{stderr}"
    );
    assert!(stdout.contains("2 masks (2 segmented"), "{stdout}");

    let missing = groundwork()
        .args([
            "producer",
            "--model",
            "vlp16",
            "--packets",
            "velodyne",
            "--pcap",
        ])
        .arg(tmp.path().join("none.pcap"))
        .args(["--prefix", &prefix("missing")])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&missing.stderr);
    assert_eq!(missing.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("none.pcap"), "{stderr}");

    let hdl = groundwork()
        .args([
            "pipeline",
            "--sensor",
            "hdl64e",
            "--packets",
            "velodyne",
            "--pcap",
        ])
        .arg(capture())
        .args(["--prefix", &prefix("hdl")])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&hdl.stderr);
    assert_eq!(hdl.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("--sensor-config"), "{stderr}");

    // Packets set their own pace: a rate other than recorded or 0 is refused.
    let paced = groundwork()
        .args([
            "producer",
            "--model",
            "vlp16",
            "--packets",
            "velodyne",
            "--rate",
            "20",
            "--pcap",
        ])
        .arg(capture())
        .args(["--prefix", &prefix("paced")])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&paced.stderr);
    assert_eq!(paced.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("--rate 20") && stderr.contains("recorded"),
        "{stderr}"
    );

    // A VLP-32C's decoder refuses every VLP-16 packet by its model byte: counted, named.
    let wrong = groundwork()
        .args([
            "pipeline",
            "--sensor",
            "vlp32c",
            "--packets",
            "velodyne",
            "--pcap",
        ])
        .arg(capture())
        .args(["--prefix", &prefix("wrong")])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&wrong.stderr);
    assert_eq!(wrong.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("no scan in the capture"), "{stderr}");
}
