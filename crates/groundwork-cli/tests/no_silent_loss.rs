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

/// Every command that writes a file takes the one output path: an output that is an input
/// (by name, or through a link) or named twice is refused before anything is read (exit 2),
/// and the input is left as it was.
#[test]
fn every_command_refuses_an_output_that_is_an_input() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let scans = d.join("c");
    for n in 0..3 {
        copy_scan(n, &scans);
    }
    let scan = scans.join("000000.bin");
    let before = fs::read(&scan).unwrap();
    std::os::unix::fs::symlink(&scan, d.join("link.bin")).unwrap();
    let calibrate = || {
        let mut c = bin();
        c.args(["calibrate", "--keep-params", "--overwrite"]);
        c
    };
    let cases: Vec<(&str, Command, &str)> = vec![
        (
            "calibrate --out",
            {
                let mut c = calibrate();
                c.arg("--out").arg(&scan).arg(&scans);
                c
            },
            "destroy",
        ),
        (
            "calibrate --out link",
            {
                let mut c = calibrate();
                c.arg("--out").arg(d.join("link.bin")).arg(&scans);
                c
            },
            "destroy",
        ),
        (
            "calibrate --report",
            {
                let mut c = calibrate();
                c.arg("--out")
                    .arg(d.join("x.toml"))
                    .arg("--report")
                    .arg(&scan)
                    .arg(&scans);
                c
            },
            "destroy",
        ),
        (
            "calibrate --out X --report X",
            {
                let mut c = calibrate();
                c.arg("--out")
                    .arg(d.join("x.toml"))
                    .arg("--report")
                    .arg(d.join("x.toml"))
                    .arg(&scans);
                c
            },
            "named twice",
        ),
        (
            "render",
            {
                let mut c = bin();
                c.args(["render", "--out"]).arg(&scan).arg(&scan);
                c
            },
            "destroy",
        ),
        (
            "label",
            {
                let mut c = bin();
                c.args(["label", "--out"]).arg(&scan).arg(&scans);
                c
            },
            "destroy",
        ),
    ];
    for (what, mut cmd, says) in cases {
        let o = run(&mut cmd, Duration::from_secs(60));
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{what}: {err}");
        assert!(err.contains(says), "{what}: {err}");
        assert_eq!(
            fs::read(&scan).unwrap(),
            before,
            "{what}: the input is untouched"
        );
    }
    assert!(!d.join("x.toml").exists());
    // The consumer's report and its recording are one file: refused before it starts.
    let o = run(
        bin()
            .args([
                "consumer",
                "--prefix",
                "gw-test-outputs-twice",
                "--count",
                "1",
            ])
            .arg("--out")
            .arg(d.join("r.mcap"))
            .arg("--report-json")
            .arg(d.join("r.mcap")),
        Duration::from_secs(30),
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("named twice"), "{}", stderr(&o));
}

/// A full disk under the newer commands: `calibrate` leaves neither an empty configuration
/// nor a cut report, and a re-run elsewhere is not blocked; `synth` leaves no cut scan that
/// would read as a shorter one. And an empty configuration is refused wherever it is met.
#[test]
fn a_full_disk_leaves_no_empty_configuration_and_no_cut_scan() {
    let tmp = tempfile::tempdir().unwrap();
    let empty = tmp.path().join("empty.toml");
    fs::write(&empty, "").unwrap();
    let scan = copy_scan(0, &tmp.path().join("in"));
    let o = run(
        bin()
            .args(["segment", "--config"])
            .arg(&empty)
            .arg("--out")
            .arg(tmp.path().join("o"))
            .arg(&scan),
        Duration::from_secs(60),
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("empty.toml: sets nothing"),
        "{}",
        stderr(&o)
    );

    let syn = tmp.path().join("syn");
    let o = run(
        bin()
            .args(["synth", "--sensor", "vlp16", "--frames", "3", "--out"])
            .arg(&syn),
        Duration::from_secs(60),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let Some(disk) = Tmpfs::mount(&tmp.path().join("disk"), 16) else {
        return;
    };
    // Every page taken (a byte into the fourth of four).
    fs::write(disk.0.join("fill"), vec![7u8; 12_289]).unwrap();
    let calibrate = |out: &Path, report: &Path| {
        run(
            bin()
                .args(["calibrate", "--sensor", "vlp16", "--keep-params", "--out"])
                .arg(out)
                .arg("--report")
                .arg(report)
                .arg(&syn),
            Duration::from_secs(60),
        )
    };
    let o = calibrate(&disk.0.join("x.toml"), &disk.0.join("r.json"));
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("No space left"), "{err}");
    assert_eq!(
        files_in(&disk.0),
        ["fill"],
        "no empty x.toml, no cut r.json"
    );
    // The same command with room: nothing left in the way ("exists").
    fs::remove_file(disk.0.join("fill")).unwrap();
    let o = calibrate(&disk.0.join("x.toml"), &tmp.path().join("r.json"));
    assert!(o.status.success(), "{}", stderr(&o));
    let text = fs::read_to_string(disk.0.join("x.toml")).unwrap();
    assert!(text.contains("height"), "{text}");

    // synth: the first scan (about 400 KB) does not fit in 16 KB; nothing cut is left.
    fs::remove_file(disk.0.join("x.toml")).unwrap();
    let o = run(
        bin()
            .args(["synth", "--sensor", "vlp16", "--frames", "2", "--out"])
            .arg(disk.0.join("s")),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("No space left"), "{err}");
    assert!(files_in(&disk.0.join("s/velodyne")).is_empty());
}

/// A recording in a folder is never passed over: beside scan files it is refused by name
/// (the folder is one sequence); alone it is the folder's sequence.
#[test]
fn a_recording_in_a_folder_is_read_or_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let mixed = tmp.path().join("mixed");
    fs::create_dir_all(&mixed).unwrap();
    fs::copy(fixture("kitti_pointcloud2.mcap"), mixed.join("rec.mcap")).unwrap();
    fs::copy(fixture("kitti_binary.pcd"), mixed.join("000000_pcdbin.pcd")).unwrap();
    for command in ["segment", "detect"] {
        let o = run(
            bin()
                .args([command, "--frames", "1", "--out"])
                .arg(tmp.path().join(format!("out-{command}")))
                .arg(&mixed),
            Duration::from_secs(60),
        );
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{command}: {err}");
        assert!(
            err.contains("rec.mcap") && err.contains("input of its own"),
            "{command}: {err}"
        );
    }
    let o = run(bin().args(["eval"]).arg(&mixed), Duration::from_secs(60));
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("rec.mcap"), "{}", stderr(&o));
    let o = run(
        bin()
            .args(["label", "--out"])
            .arg(tmp.path().join("l"))
            .arg(&mixed),
        Duration::from_secs(60),
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("rec.mcap"), "{}", stderr(&o));
    // Alone in its folder, the recording is read.
    fs::remove_file(mixed.join("000000_pcdbin.pcd")).unwrap();
    let out = tmp.path().join("alone");
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(&out)
            .arg(&mixed),
        Duration::from_secs(60),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        files_in(&out).contains(&"rec_000000.prob".to_string()),
        "{:?}",
        files_in(&out)
    );
}

/// Nothing to run is an error before any output exists (exit 2, not "some input was bad");
/// a run whose every scan failed leaves an earlier recording as it was.
#[test]
fn nothing_segmented_replaces_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("e1");
    let o = run(
        bin()
            .args(["segment", "--out"])
            .arg(&out)
            .arg(tmp.path().join("does/not/exist")),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("no readable input"), "{err}");
    assert!(!out.exists());

    let prev = tmp.path().join("prev.mcap");
    let scan = copy_scan(0, &tmp.path().join("in"));
    let o = run(
        bin()
            .args(["segment", "--frames", "1", "--out"])
            .arg(&prev)
            .arg(&scan),
        Duration::from_secs(60),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let before = fs::read(&prev).unwrap();
    let bad = tmp.path().join("bad");
    fs::create_dir_all(&bad).unwrap();
    fs::write(bad.join("000000.bin"), [1u8, 2, 3]).unwrap();
    fs::write(bad.join("000001.bin"), []).unwrap();
    let o = run(
        bin().args(["segment", "--out"]).arg(&prev).arg(&bad),
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("no recording was written"), "{err}");
    assert_eq!(
        fs::read(&prev).unwrap(),
        before,
        "the earlier recording is kept"
    );
    assert_eq!(
        files_in(tmp.path())
            .iter()
            .filter(|f| f.ends_with(".partial"))
            .count(),
        0
    );
}

/// Scans of two sensors in one calibration (the HDL-64E preset, whose point limit takes
/// both): the few of the other mount are named, in the log and in the summary.
#[test]
fn calibrate_names_scans_of_another_mount() {
    let tmp = tempfile::tempdir().unwrap();
    let mix = tmp.path().join("mix");
    fs::create_dir_all(&mix).unwrap();
    for (sensor, frames, prefix) in [("vlp16", "8", "a"), ("hdl64e", "2", "b")] {
        let syn = tmp.path().join(sensor);
        let o = run(
            bin()
                .args(["synth", "--sensor", sensor, "--frames", frames, "--out"])
                .arg(&syn),
            Duration::from_secs(60),
        );
        assert!(o.status.success(), "{}", stderr(&o));
        for f in fs::read_dir(syn.join("velodyne")).unwrap() {
            let f = f.unwrap();
            let name = format!("{prefix}{}", f.file_name().to_string_lossy());
            fs::copy(f.path(), mix.join(name)).unwrap();
        }
    }
    let o = run(
        bin()
            .args(["calibrate", "--keep-params", "--out"])
            .arg(tmp.path().join("cal.toml"))
            .arg(&mix),
        Duration::from_secs(120),
    );
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("2 of 10 scans disagree"), "{err}");
    assert!(err.contains("b000000") && err.contains("b000001"), "{err}");
    assert!(!err.contains("a000003 ("), "{err}");
    assert!(String::from_utf8_lossy(&o.stdout).contains("2 scan(s) disagree"));
}
