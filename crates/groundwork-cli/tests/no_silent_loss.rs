//! Nothing lost in silence: inputs that are not files, outputs that would overwrite inputs
//! or each other, writes that fail, files of another layout. Each test drives the release
//! binary as a user would and checks the exit code, what it says, and what is on disk.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_groundwork"))
}

fn data() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/semantickitti-00")
}

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../groundwork-io/tests/fixtures")
        .join(name)
}

fn copy_scan(n: u32, dir: &Path) -> PathBuf {
    fs::create_dir_all(dir).unwrap();
    let dst = dir.join(format!("{n:06}.bin"));
    fs::copy(data().join(format!("velodyne/{n:06}.bin")), &dst).unwrap();
    dst
}

/// Runs a command with a deadline: a command that blocks (on a FIFO, say) fails the test
/// instead of hanging it.
fn run(cmd: &mut Command, deadline: Duration) -> Output {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > deadline {
            child.kill().unwrap();
            let o = child.wait_with_output().unwrap();
            panic!(
                "still running after {deadline:?}: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

mod support;
use support::Tmpfs;

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = fs::read_dir(dir)
        .map(|r| {
            r.map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

#[test]
fn a_device_or_a_fifo_named_as_a_scan_is_refused_not_read() {
    let tmp = tempfile::tempdir().unwrap();
    let zero = tmp.path().join("zero.bin");
    std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
    let fifo = tmp.path().join("pipe.bin");
    assert!(
        Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    let good = copy_scan(0, &tmp.path().join("in"));
    let out = tmp.path().join("out");
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(&out)
            .arg(&zero)
            .arg(&fifo)
            .arg(&good),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("zero.bin") && err.contains("character device"),
        "{err}"
    );
    assert!(err.contains("pipe.bin") && err.contains("FIFO"), "{err}");
    assert!(out.join("000000.prob").is_file(), "the good scan is served");
}

#[test]
fn odd_entries_of_a_folder_are_reported_not_skipped() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    copy_scan(0, &input);
    std::os::unix::fs::symlink(input.join("gone.bin"), input.join("000001.bin")).unwrap();
    let out = tmp.path().join("out");
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(&out)
            .arg(&input),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("000001.bin") && err.contains("failed=1"),
        "{err}"
    );
}

#[test]
fn inputs_whose_outputs_collide_are_refused_before_anything_is_written() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    copy_scan(0, &a);
    copy_scan(0, &b);
    for command in ["segment", "detect"] {
        let out = tmp.path().join(format!("out-{command}"));
        let o = run(
            bin()
                .args([command, "--frames", "1", "--out"])
                .arg(&out)
                .arg(&a)
                .arg(&b),
            Duration::from_secs(60),
        );
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{command}: {err}");
        assert!(
            err.contains("000000") && err.contains("separate --out"),
            "{command}: {err}"
        );
        assert!(files_in(&out).is_empty(), "{command}: {:?}", files_in(&out));
    }
    // Two formats of one scan name.
    let out = tmp.path().join("out-formats");
    let o = run(
        bin()
            .args(["segment", "--out"])
            .arg(&out)
            .arg(fixture("kitti_ascii.pcd"))
            .arg(fixture("kitti_ascii.ply")),
        Duration::from_secs(60),
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(files_in(&out).is_empty());
}

#[test]
fn a_rerun_into_the_same_place_says_what_it_replaces() {
    let tmp = tempfile::tempdir().unwrap();
    let scans = tmp.path().join("scans");
    copy_scan(0, &scans);
    copy_scan(1, &scans);
    let replaced = |o: &Output| {
        let err = stderr(o);
        assert_eq!(o.status.code(), Some(0), "{err}");
        err.lines()
            .find(|l| l.contains("earlier run") || l.contains("exists, and is replaced"))
            .map(str::to_owned)
    };
    for (command, first) in [("segment", "000000.ground"), ("detect", "000000.clusters")] {
        let out = tmp.path().join(format!("out-{command}"));
        let mut cmd = bin();
        cmd.args([command, "--frames", "1", "--out"]).arg(&out);
        // One scan, then both: the second run replaces the first one's files and says so.
        let o = run(cmd.arg(scans.join("000000.bin")), Duration::from_secs(60));
        assert_eq!(
            replaced(&o),
            None,
            "{command}: a first run replaces nothing"
        );
        let o = run(
            bin()
                .args([command, "--frames", "1", "--out"])
                .arg(&out)
                .arg(&scans),
            Duration::from_secs(60),
        );
        let line = replaced(&o).unwrap_or_else(|| panic!("{command}: {}", stderr(&o)));
        assert!(
            line.contains("2 file(s)") && line.contains(first),
            "{command}: {line}"
        );
    }
    // Another command's files in the folder are not this run's: nothing said.
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(tmp.path().join("out-detect"))
            .arg(&scans),
        Duration::from_secs(60),
    );
    assert_eq!(replaced(&o), None);
    // A recording output that exists.
    let rec = tmp.path().join("out.mcap");
    for (k, expect) in [(0, false), (1, true)] {
        let o = run(
            bin()
                .args(["segment", "--out"])
                .arg(&rec)
                .arg(fixture("kitti_pointcloud2.mcap")),
            Duration::from_secs(60),
        );
        assert_eq!(replaced(&o).is_some(), expect, "run {k}: {}", stderr(&o));
    }
}

#[test]
fn an_output_that_is_an_input_is_refused_and_the_input_kept() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec.mcap");
    fs::copy(fixture("kitti_pointcloud2.mcap"), &rec).unwrap();
    let before = fs::read(&rec).unwrap();
    // The same file, and the same file through a link.
    let link = tmp.path().join("link.mcap");
    std::os::unix::fs::symlink(&rec, &link).unwrap();
    for out in [&rec, &link] {
        let o = run(
            bin().args(["segment", "--out"]).arg(out).arg(&rec),
            Duration::from_secs(60),
        );
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(err.contains("destroy"), "{err}");
        assert_eq!(fs::read(&rec).unwrap(), before, "the input is untouched");
    }
}

#[test]
fn a_headerless_file_of_another_layout_is_flagged() {
    let tmp = tempfile::tempdir().unwrap();
    // Scan 0 as x, y, z only (3 floats per point), cut to a multiple of 4 points so that
    // its size divides by 16 and it reads as a KITTI .bin.
    let bytes = fs::read(data().join("velodyne/000000.bin")).unwrap();
    let n = bytes.len() / 16 / 4 * 4;
    let xyz: Vec<u8> = bytes
        .chunks_exact(16)
        .take(n)
        .flat_map(|r| r[..12].to_vec())
        .collect();
    assert_eq!(xyz.len() % 16, 0);
    let p = tmp.path().join("xyz.bin");
    fs::write(&p, xyz).unwrap();
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(tmp.path().join("out"))
            .arg(&p),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert!(
        err.contains("xyz.bin") && err.contains("another layout"),
        "{err}"
    );
    // The real scan is not flagged.
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(tmp.path().join("out2"))
            .arg(data().join("velodyne/000000.bin")),
        Duration::from_secs(60),
    );
    assert!(o.status.success());
    assert!(!stderr(&o).contains("another layout"), "{}", stderr(&o));
}

#[test]
fn a_full_disk_leaves_no_partial_files_and_no_broken_recording() {
    let tmp = tempfile::tempdir().unwrap();
    let scan = copy_scan(0, &tmp.path().join("in"));
    // 64 KiB: the scan's .prob (480 KB) cannot fit.
    let Some(disk) = Tmpfs::mount(&tmp.path().join("disk"), 64) else {
        return;
    };
    let out = disk.0.join("out");
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(&out)
            .arg(&scan),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("No space left"), "{err}");
    assert!(files_in(&out).is_empty(), "{:?}", files_in(&out));

    let rec = disk.0.join("x.mcap");
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(&rec)
            .arg(&scan),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_ne!(o.status.code(), Some(0), "{err}");
    assert!(err.contains("No space left"), "{err}");
    assert_eq!(files_in(&disk.0), ["out"], "no x.mcap, no x.mcap.partial");

    // A read-only output folder is an error before anything is read: exit 2.
    disk.read_only();
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(&out)
            .arg(&scan),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("Read-only"), "{err}");
}

/// A sequence folder with scans 0–2 and their labels, and whichever of poses.txt and
/// calib.txt are asked for.
fn sequence(dir: &Path, poses: bool, calib: bool) -> PathBuf {
    for n in 0..3 {
        copy_scan(n, &dir.join("velodyne"));
        fs::create_dir_all(dir.join("labels")).unwrap();
        let l = format!("labels/{n:06}.label");
        fs::copy(data().join(&l), dir.join(&l)).unwrap();
    }
    for (want, f) in [(poses, "poses.txt"), (calib, "calib.txt")] {
        if want {
            fs::copy(data().join(f), dir.join(f)).unwrap();
        }
    }
    dir.to_path_buf()
}

fn eval_json(args: &[&std::ffi::OsStr]) -> (Output, Option<serde_json::Value>) {
    let o = run(
        bin().args(["eval", "--json", "--frames", "3"]).args(args),
        Duration::from_secs(120),
    );
    let v = serde_json::from_slice(&o.stdout).ok();
    (o, v)
}

#[test]
fn eval_skips_an_unreadable_scan_scores_the_rest_and_exits_1() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = sequence(&tmp.path().join("seq"), true, true);
    let bin1 = seq.join("velodyne/000001.bin");
    let bytes = fs::read(&bin1).unwrap();
    fs::write(&bin1, &bytes[..bytes.len() - 3]).unwrap();
    let (o, v) = eval_json(&[seq.as_os_str()]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let v = v.unwrap_or_else(|| panic!("no JSON report: {err}"));
    assert_eq!(v["scans"].as_array().unwrap().len(), 2);
    assert_eq!(v["labeled_scans"], 2);
    assert!(v["pooled_metrics"]["iou_ground"].as_f64().unwrap() > 90.0);
    let skipped = &v["skipped"][0];
    assert_eq!(skipped["name"], "000001");
    assert!(
        skipped["reason"]
            .as_str()
            .unwrap()
            .contains("not a whole number"),
        "{skipped}"
    );
}

#[test]
fn poses_without_a_calibration_are_the_lidars_own_and_said_so() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = sequence(&tmp.path().join("seq"), true, false);
    let (o, v) = eval_json(&[seq.as_os_str()]);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("taken as the LiDAR's own"), "{err}");
    let v = v.unwrap();
    assert_eq!(v["scans"][2]["frames_queried"], 3, "history is used");
    // --poses without --calib, likewise.
    let bare = sequence(&tmp.path().join("bare"), false, false);
    let poses = seq.join("poses.txt");
    let (o, v) = eval_json(&["--poses".as_ref(), poses.as_os_str(), bare.as_os_str()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(v.unwrap()["scans"][2]["frames_queried"], 3);
    // A calibration alone is refused.
    let calib = data().join("calib.txt");
    let (o, _) = eval_json(&["--calib".as_ref(), calib.as_os_str(), bare.as_os_str()]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("without poses"), "{}", stderr(&o));
}

#[test]
fn nonsense_numbers_are_refused_by_name_before_anything_runs() {
    let tmp = tempfile::tempdir().unwrap();
    // A rate that would overflow the clock, and one that is not a number.
    for rate in ["1e-19", "nan", "inf"] {
        let o = run(
            bin().args([
                "producer",
                "--prefix",
                "gwtest-rate",
                "--count",
                "1",
                "--rate",
                rate,
            ]),
            Duration::from_secs(30),
        );
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{rate}: {err}");
        assert!(
            err.contains("--rate") && err.contains("scans per second"),
            "{rate}: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
        // Said once, not as a log line and again as the error.
        assert_eq!(err.matches("--rate").count(), 1, "{err}");
    }
    let service = tmp.path().join("service.toml");
    fs::write(&service, "rate_hz = 1e-300\n").unwrap();
    let o = run(
        bin()
            .args(["pipeline", "--count", "1", "--service"])
            .arg(&service),
        Duration::from_secs(30),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("service.toml") && err.contains("rate_hz"),
        "{err}"
    );
    // A segmenter value in degrees, through a config file.
    let cfg = tmp.path().join("tilted.toml");
    fs::write(&cfg, "[sensor]\nmount = { height = 2.2, pitch = -6 }\n").unwrap();
    let o = run(
        bin()
            .args(["segment", "--out"])
            .arg(tmp.path().join("out"))
            .arg("--config")
            .arg(&cfg)
            .arg(data().join("velodyne/000000.bin")),
        Duration::from_secs(30),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("tilted.toml")
            && err.contains("sensor.mount.pitch")
            && err.contains("radians"),
        "{err}"
    );
}

#[test]
fn errors_are_said_once_in_words() {
    let tmp = tempfile::tempdir().unwrap();
    let o = run(
        bin()
            .args(["segment", "--config"])
            .arg(tmp.path().join("missing.toml"))
            .arg("--out")
            .arg(tmp.path().join("out"))
            .arg(data().join("velodyne/000000.bin")),
        Duration::from_secs(30),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert_eq!(err.matches("No such file").count(), 1, "{err}");
    assert_eq!(
        err.lines().filter(|l| l.contains("missing.toml")).count(),
        1,
        "{err}"
    );
    // An --out that is a file is named for what it is.
    let file = tmp.path().join("taken");
    fs::write(&file, "x").unwrap();
    let o = run(
        bin()
            .args(["segment", "--out"])
            .arg(&file)
            .arg(data().join("velodyne/000000.bin")),
        Duration::from_secs(30),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("is not a folder") && !err.contains("os error"),
        "{err}"
    );
}
