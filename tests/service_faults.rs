//! Fault tests of the service with real processes: killed and restarted stages, a stalled
//! consumer, malformed scans, stale shared memory. Every test uses its own service names;
//! they run one at a time (a shared lock) because two cores are all there is.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::Mutex;
use std::time::{Duration, Instant};

static SERIAL: Mutex<()> = Mutex::new(());

fn data() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/semantickitti-00")
}

/// A stage process whose output goes to files; killed on drop if still running.
struct Proc {
    child: Child,
    stderr: PathBuf,
}

impl Proc {
    fn start(dir: &Path, name: &str, prefix: &str, args: &[&str]) -> Self {
        let stderr = dir.join(format!("{name}.err"));
        let child = Command::new(env!("CARGO_BIN_EXE_groundwork"))
            .arg(name.split('-').next().unwrap())
            .args(["--prefix", prefix])
            .args(args)
            .env("RUST_LOG", "info")
            .stdout(std::fs::File::create(dir.join(format!("{name}.out"))).unwrap())
            .stderr(std::fs::File::create(&stderr).unwrap())
            .spawn()
            .unwrap();
        Self { child, stderr }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }

    fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    fn kill9(&mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }

    fn term(&mut self) {
        let pid = rustix::process::Pid::from_child(&self.child);
        let _ = rustix::process::kill_process(pid, rustix::process::Signal::TERM);
    }

    /// Waits for exit; panics after `limit`.
    fn wait(&mut self, limit: Duration) -> std::process::ExitStatus {
        let t = Instant::now();
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                return s;
            }
            assert!(
                t.elapsed() < limit,
                "process did not exit within {limit:?}:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if self.alive() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// A consumer that writes its final report to `<dir>/<name>.json`.
fn consumer(dir: &Path, name: &str, prefix: &str, args: &[&str]) -> (Proc, PathBuf) {
    let json = dir.join(format!("{name}.json"));
    let mut all: Vec<&str> = args.to_vec();
    all.extend(["--report-json", json.to_str().unwrap()]);
    (Proc::start(dir, name, prefix, &all), json)
}

fn prefix(test: &str) -> String {
    format!("gwtest-{test}-{}", std::process::id())
}

fn report(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// `published=N` from the producer's final log line.
fn published(log: &str) -> u64 {
    let line = log
        .lines()
        .rev()
        .find(|l| l.contains("producer stopped"))
        .unwrap_or_else(|| panic!("{log}"));
    let v = line.split("published=").nth(1).unwrap();
    v.split_whitespace().next().unwrap().parse().unwrap()
}

/// The states ("alive", "dead", "other") of the iceoryx2 nodes called `name`.
fn node_states(name: &str) -> Vec<&'static str> {
    use iceoryx2::node::NodeView;
    use iceoryx2::prelude::*;
    let mut states = Vec::new();
    Node::<ipc::Service>::list(iceoryx2::config::Config::global_config(), |s| {
        let (details, state) = match &s {
            NodeState::Alive(v) => (v.details(), "alive"),
            NodeState::Dead(v) => (v.details(), "dead"),
            _ => (&None, "other"),
        };
        if details.as_ref().is_some_and(|d| d.name().as_str() == name) {
            states.push(state);
        }
        CallbackProgression::Continue
    })
    .unwrap();
    states
}

fn sleep(s: f64) {
    std::thread::sleep(Duration::from_secs_f64(s));
}

#[test]
fn killed_segmenter_is_replaced_without_restarting_anything_else() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("kill-seg");
    // The consumer's periodic sweep for dead processes would race the new segmenter's
    // sweep at start, which is what this test checks: keep it out of the test's window.
    let quiet = tmp.path().join("quiet.toml");
    let service = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../config/service.toml");
    let service = std::fs::read_to_string(service).unwrap();
    assert!(service.contains("report_interval_s = 2.0"), "{service}");
    std::fs::write(
        &quiet,
        service.replace("report_interval_s = 2.0", "report_interval_s = 60.0"),
    )
    .unwrap();
    let (mut consumer, json) = consumer(
        tmp.path(),
        "consumer",
        &p,
        &["--idle-timeout", "3", "--service", quiet.to_str().unwrap()],
    );
    let mut seg_a = Proc::start(tmp.path(), "segmenter-a", &p, &["--frames", "1"]);
    sleep(0.5);
    let started = Instant::now();
    let mut producer = Proc::start(tmp.path(), "producer", &p, &["--rate", "20"]);
    sleep(2.0);
    seg_a.kill9();
    sleep(1.0);
    let mut seg_b = Proc::start(tmp.path(), "segmenter-b", &p, &["--frames", "1"]);
    sleep(2.5);
    assert!(
        producer.alive() && consumer.alive(),
        "nothing else restarted"
    );
    producer.term();
    assert!(producer.wait(Duration::from_secs(5)).success());
    let elapsed = started.elapsed().as_secs_f64();
    consumer.wait(Duration::from_secs(10));
    seg_b.term();
    assert!(seg_b.wait(Duration::from_secs(5)).success());

    let r = report(&json);
    assert_eq!(r["segmenter_runs"], 2, "{r}");
    let segmented = r["segmented"].as_u64().unwrap();
    assert!(segmented >= 40, "masks from both segmenters: {r}");
    // The producer was never blocked: it kept its 20 Hz through the kill (±25 %).
    let n = published(&producer.log());
    assert!(
        n as f64 >= 0.75 * 20.0 * (elapsed - 0.5),
        "published {n} in {elapsed:.1} s"
    );
    // The new segmenter removed what the killed one left behind, at start.
    let log = seg_b.log();
    assert!(
        log.contains("removed stale resources") && log.contains("still_stale=0"),
        "{log}"
    );
}

#[test]
fn killed_producer_leaves_the_others_serving_and_a_new_one_resumes() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("kill-prod");
    let (mut consumer, json) = consumer(tmp.path(), "consumer", &p, &["--idle-timeout", "6"]);
    let mut seg = Proc::start(tmp.path(), "segmenter", &p, &["--frames", "1"]);
    sleep(0.5);
    // 10 Hz leaves the segmenter room on a loaded machine: this test is about the kill,
    // not about keeping up (dropped masks are asserted to be zero below).
    let mut prod_a = Proc::start(tmp.path(), "producer-a", &p, &["--rate", "10"]);
    sleep(1.5);
    let producer = groundwork_service::transport::node_name(
        &groundwork_service::ServiceConfig {
            prefix: p.clone(),
            ..Default::default()
        },
        "producer",
    );
    assert_eq!(node_states(&producer), ["alive"]);
    prod_a.kill9();
    // The survivors' periodic sweep (every 2 s) removes what the killed producer left,
    // before any new process comes to do it at start.
    let t = Instant::now();
    while !node_states(&producer).is_empty() {
        assert!(
            t.elapsed() < Duration::from_secs(6),
            "dead producer not removed"
        );
        sleep(0.1);
    }
    assert!(
        seg.alive() && consumer.alive(),
        "segmenter and consumer survive the producer"
    );
    let mut prod_b = Proc::start(
        tmp.path(),
        "producer-b",
        &p,
        &["--rate", "10", "--count", "20"],
    );
    assert!(prod_b.wait(Duration::from_secs(10)).success());
    assert!(
        node_states(&producer).is_empty(),
        "a clean exit leaves no node"
    );
    consumer.wait(Duration::from_secs(12));
    assert!(seg.alive());
    seg.term();
    assert!(seg.wait(Duration::from_secs(5)).success(), "{}", seg.log());
    assert!(!seg.log().contains("ERROR"), "{}", seg.log());
    let r = report(&json);
    // All 20 scans of the second producer were answered, after those of the first.
    assert!(r["segmented"].as_u64().unwrap() >= 20 + 5, "{r}");
    assert_eq!(r["dropped_masks"], 0, "{r}");
}

#[test]
fn stalled_consumer_costs_only_its_own_messages() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("stall");
    let (mut slow, slow_json) = consumer(
        tmp.path(),
        "consumer-slow",
        &p,
        &[
            "--stall-after",
            "3",
            "--stall-secs",
            "4",
            "--idle-timeout",
            "2",
        ],
    );
    let (mut fast, fast_json) = consumer(
        tmp.path(),
        "consumer-fast",
        &p,
        &["--count", "60", "--idle-timeout", "3"],
    );
    let mut seg = Proc::start(tmp.path(), "segmenter", &p, &["--frames", "1"]);
    sleep(0.5);
    let t = Instant::now();
    let mut prod = Proc::start(
        tmp.path(),
        "producer",
        &p,
        // KITTI's 10 Hz: on a loaded 2-core machine 20 Hz can outrun the segmenter
        // itself, and this test is about the stalled reader.
        &["--rate", "10", "--count", "60"],
    );
    let rss = |pid: u32| -> u64 {
        let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
        s.lines()
            .find(|l| l.starts_with("VmRSS:"))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    sleep(2.0);
    let rss_early = rss(seg.child.id());
    assert!(prod.wait(Duration::from_secs(15)).success());
    let secs = t.elapsed().as_secs_f64();
    let rss_late = rss(seg.child.id());
    fast.wait(Duration::from_secs(10));
    slow.wait(Duration::from_secs(15));
    seg.term();
    seg.wait(Duration::from_secs(5));

    // The producer kept its rate: 60 scans at 10 Hz in about 6 s.
    assert!(secs < 8.0, "producer took {secs:.1} s");
    // The segmenter answered everything (the fast consumer saw all 60 masks).
    let f = report(&fast_json);
    assert_eq!(f["segmented"], 60, "{f}");
    // Bounded memory while a reader stalls: the segmenter did not grow by more than 32 MiB.
    assert!(
        rss_late < rss_early + 32 * 1024,
        "RSS {rss_early} kB → {rss_late} kB"
    );
    // The stalled consumer lost messages (oldest dropped) and counted them.
    let s = report(&slow_json);
    let dropped = s["dropped_scans"].as_u64().unwrap() + s["dropped_masks"].as_u64().unwrap();
    assert!(dropped > 20, "{s}");
    assert!(s["masks"].as_u64().unwrap() < 60, "{s}");
}

#[test]
fn malformed_scans_are_rejected_counted_and_the_next_served() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("malformed");
    // Too many points: a segmenter configured for at most 124,200 points rejects KITTI
    // frames 0–2 (124,668 / 124,605 / 124,478 points) and accepts 3–5.
    let cfg = tmp.path().join("small.toml");
    std::fs::write(&cfg, "[sensor]\nmax_points = 124200\n").unwrap();
    let (mut consumer, json) = consumer(
        tmp.path(),
        "consumer",
        &p,
        &["--count", "24", "--idle-timeout", "3"],
    );
    let mut seg = Proc::start(
        tmp.path(),
        "segmenter",
        &p,
        &["--config", cfg.to_str().unwrap()],
    );
    sleep(0.5);
    // Every 4th scan is malformed, cycling NaN, empty, bad schema, bad count.
    let mut prod = Proc::start(
        tmp.path(),
        "producer",
        &p,
        &[
            "--rate",
            "20",
            "--count",
            "24",
            "--malformed-every",
            "4",
            data().to_str().unwrap(),
        ],
    );
    assert!(prod.wait(Duration::from_secs(10)).success());
    consumer.wait(Duration::from_secs(10));
    assert!(seg.alive(), "the segmenter keeps serving");
    seg.term();
    assert!(seg.wait(Duration::from_secs(5)).success());
    let r = report(&json);
    assert_eq!(
        (r["dropped_scans"].as_u64(), r["masks"].as_u64()),
        (Some(0), Some(24)),
        "{r}"
    );
    // Sequence s replays frame s mod 6; s = 3, 7, 11, … are malformed, kinds cycling
    // NaN, empty, bad schema, bad count. The first failing check names the reason, so the
    // NaN scan at s = 19 (frame 1, too large) counts as too many points.
    let rej = &r["rejected"];
    let count = |k: &str| rej[k].as_u64().unwrap_or(0);
    assert_eq!(
        [
            count("non_finite"),
            count("empty"),
            count("bad_schema"),
            count("count_mismatch")
        ],
        [1, 2, 1, 1],
        "{r}"
    );
    assert_eq!(count("too_many_points"), 11, "{r}");
    assert_eq!(r["segmented"], 8, "{r}");
    let log = seg.log();
    assert!(
        log.contains("rejected scan") && log.contains("non_finite"),
        "{log}"
    );
}

#[test]
fn pipeline_runs_end_to_end_and_leaves_no_shared_memory() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("pipeline");
    let shm_before: Vec<_> = std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name())
        .collect();
    let out = Command::new(env!("CARGO_BIN_EXE_groundwork"))
        .args([
            "pipeline", "--count", "12", "--rate", "10", "--prefix", &p, "--out",
        ])
        .arg(tmp.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("12 masks (12 segmented"), "{stdout}");
    assert!(
        stdout.contains("end to end") && stdout.contains("live accuracy"),
        "{stdout}"
    );
    // Outputs written by the consumer, one value per point.
    let prob = groundwork_io::read_prob(&tmp.path().join("000000.prob")).unwrap();
    assert_eq!(prob.len(), 124_668);
    // A clean exit removes the shared memory (only iceoryx2's tiny management file may
    // remain, and it is shared by all pipelines).
    let shm_after: Vec<_> = std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name())
        .collect();
    let new: Vec<_> = shm_after
        .iter()
        .filter(|f| !shm_before.contains(f))
        .collect();
    assert!(
        new.iter()
            .all(|f| f.to_string_lossy().ends_with("global_mgmt")),
        "left behind: {new:?}"
    );
}
