//! Scans from a sensor's packets through the service: a pcap replayed, packets sent live
//! over UDP by a test process, bad captures named. Each test has its own service names;
//! they run one at a time (two cores).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::ffi::OsString;
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

/// Arguments of mixed kinds (text, paths) for [`run`].
macro_rules! args {
    ($($a:expr),* $(,)?) => { vec![$(OsString::from(&$a)),*] };
}

/// What a finished `groundwork` said.
struct Ran {
    code: Option<i32>,
    stdout: String,
    stderr: String,
}

/// Runs `groundwork` to its end.
fn run(args: Vec<OsString>) -> Ran {
    let out = groundwork().args(args).output().unwrap();
    Ran {
        code: out.status.code(),
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    }
}

/// Runs `groundwork`, which must succeed.
fn run_ok(args: Vec<OsString>) -> Ran {
    let ran = run(args);
    assert_eq!(ran.code, Some(0), "{}\n{}", ran.stdout, ran.stderr);
    ran
}

/// Runs `groundwork`, which must refuse (exit 2); its stderr.
fn run_refused(args: Vec<OsString>) -> String {
    let ran = run(args);
    assert_eq!(ran.code, Some(2), "{}", ran.stderr);
    ran.stderr
}

/// The producer's packet counters as it logs them at its end: packets, lost, refused.
fn packet_counts(log: &str) -> [u64; 3] {
    ["packets", "lost", "refused"].map(|key| logged(log, "producer: packets ", key))
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
    let Ran { stdout, stderr, .. } = run_ok(args![
        "pipeline",
        "--sensor",
        "vlp16",
        "--packets",
        "velodyne",
        "--pcap",
        capture(),
        "--prefix",
        prefix("replay"),
        "--out",
        tmp.path(),
    ]);
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
    // Packets read, lost (an azimuth or column gap) and refused (a stray datagram).
    assert_eq!(packet_counts(&stderr), [89, 1, 1], "{stderr}");
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
    let ouster = |capture: &str, test: &str| {
        run_ok(args![
            "pipeline",
            "--sensor",
            "os1-64",
            "--packets",
            "ouster",
            "--pcap",
            data.join(format!("{capture}.pcap")),
            "--sensor-config",
            data.join(format!("{capture}.json")),
            "--no-detector",
            "--prefix",
            prefix(test),
        ])
    };
    let Ran { stdout, stderr, .. } = ouster("os1-16-kitti-000002", "ouster");
    assert!(
        stdout.contains("3 masks (3 segmented")
            && stdout.contains("scan fate: 3 masked + 0 rejected + 0 unanswered + 0 dropped = 3"),
        "{stdout}"
    );
    // Packets read, lost (an azimuth or column gap) and refused (a stray datagram).
    assert_eq!(packet_counts(&stderr), [56, 1, 1], "{stderr}");
    // A real sensor's frame (an OS1-32, ouster-sdk's test data): segmented.
    let Ran { stdout, .. } = ouster("OS-1-32-G_v2.1.1_1024x10", "ouster-real");
    assert!(stdout.contains("1 masks (1 segmented"), "{stdout}");

    // Without its metadata an Ouster's packets cannot be read: said so.
    let stderr = run_refused(args![
        "producer",
        "--packets",
        "ouster",
        "--pcap",
        data.join("os1-16-kitti-000002.pcap"),
        "--prefix",
        prefix("ouster-bare"),
    ]);
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
    let Ran { stdout, stderr, .. } = run_ok(args![
        "pipeline",
        "--sensor",
        "vlp16",
        "--packets",
        "velodyne",
        "--pcap",
        cut,
        "--no-detector",
        "--prefix",
        prefix("cut"),
    ]);
    assert!(
        stderr.contains("cut.pcap: record") && stderr.contains("truncated"),
        "{stderr}"
    );
    assert!(stdout.contains("2 masks (2 segmented"), "{stdout}");

    let stderr = run_refused(args![
        "producer",
        "--model",
        "vlp16",
        "--packets",
        "velodyne",
        "--pcap",
        tmp.path().join("none.pcap"),
        "--prefix",
        prefix("missing"),
    ]);
    assert!(stderr.contains("none.pcap"), "{stderr}");

    let stderr = run_refused(args![
        "pipeline",
        "--sensor",
        "hdl64e",
        "--packets",
        "velodyne",
        "--pcap",
        capture(),
        "--prefix",
        prefix("hdl"),
    ]);
    assert!(stderr.contains("--sensor-config"), "{stderr}");

    // Packets set their own pace: a rate other than recorded or 0 is refused.
    let stderr = run_refused(args![
        "producer",
        "--model",
        "vlp16",
        "--packets",
        "velodyne",
        "--rate",
        "20",
        "--pcap",
        capture(),
        "--prefix",
        prefix("paced"),
    ]);
    assert!(
        stderr.contains("--rate 20") && stderr.contains("recorded"),
        "{stderr}"
    );

    // A VLP-32C's decoder refuses every VLP-16 packet by its model byte: counted, named.
    let stderr = run_refused(args![
        "pipeline",
        "--sensor",
        "vlp32c",
        "--packets",
        "velodyne",
        "--pcap",
        capture(),
        "--prefix",
        prefix("wrong"),
    ]);
    assert!(stderr.contains("no scan in the capture"), "{stderr}");
}
