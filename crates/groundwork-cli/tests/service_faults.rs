//! Fault tests of the service with real processes: killed and restarted stages, a stalled
//! consumer, malformed scans, stale shared memory. Every test uses its own service names;
//! they run one at a time (a shared lock) because two cores are all there is.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::Mutex;
use std::time::{Duration, Instant};

mod support;

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
    logged(log, "producer stopped", "published")
}

/// The number logged as `key=` on the last line of `log` that contains `line`.
fn logged(log: &str, line: &str, key: &str) -> u64 {
    let found = log
        .lines()
        .rev()
        .find(|l| l.contains(line))
        .unwrap_or_else(|| panic!("no {line:?} in:\n{log}"));
    let v = found
        .split(&format!(" {key}="))
        .nth(1)
        .unwrap_or_else(|| panic!("no {key} in {found}"));
    v.split_whitespace().next().unwrap().parse().unwrap()
}

/// Scans in the four buckets of a consumer report's `scan_fate`.
fn scan_fate_total(r: &serde_json::Value) -> u64 {
    ["masked", "rejected", "unanswered", "dropped"]
        .iter()
        .map(|k| r["scan_fate"][k].as_u64().unwrap())
        .sum()
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
    // The consumer's and the producer's periodic sweeps for dead processes would race the
    // new segmenter's sweep at start, which is what this test checks: keep them out of the
    // test's window.
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
    let mut producer = Proc::start(
        tmp.path(),
        "producer",
        &p,
        &["--rate", "20", "--service", quiet.to_str().unwrap()],
    );
    sleep(2.0);
    seg_a.kill9();
    sleep(1.0);
    let mut seg_b = Proc::start(tmp.path(), "segmenter-b", &p, &["--frames", "1"]);
    sleep(2.5);
    assert!(
        producer.alive() && consumer.alive(),
        "nothing else restarted"
    );
    // What the killed segmenter left behind is gone while the pipeline runs on.
    let nodes = groundwork_service::transport::pipeline_nodes(&crate::service(&p));
    assert!(nodes.iter().all(|n| n.1), "stale nodes left: {nodes:?}");
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
    // Removed by the new segmenter at its start, or, if it came first, by the periodic
    // sweep of a stage that outlived the killed one (on a loaded machine either wins).
    let (seg_log, others) = (seg_b.log(), producer.log() + &consumer.log());
    assert!(
        (seg_log.contains("removed stale resources") && seg_log.contains("still_stale=0"))
            || others.contains("removed stale resources of dead processes"),
        "{seg_log}\n{others}"
    );
}

#[test]
fn killed_detector_is_replaced_and_rejected_masks_are_skipped_and_counted() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("kill-det");
    let (mut consumer, json) = consumer(tmp.path(), "consumer", &p, &["--idle-timeout", "3"]);
    let mut seg = Proc::start(tmp.path(), "segmenter", &p, &["--frames", "1"]);
    let mut det_a = Proc::start(tmp.path(), "detector-a", &p, &[]);
    sleep(0.5);
    // Every 4th scan is malformed: the segmenter rejects it, the detector skips its mask.
    let mut producer = Proc::start(
        tmp.path(),
        "producer",
        &p,
        &["--rate", "10", "--malformed-every", "4"],
    );
    sleep(3.0);
    det_a.kill9();
    sleep(1.0);
    let mut det_b = Proc::start(tmp.path(), "detector-b", &p, &[]);
    sleep(3.0);
    assert!(
        producer.alive() && consumer.alive() && seg.alive(),
        "nothing else restarted"
    );
    producer.term();
    assert!(producer.wait(Duration::from_secs(5)).success());
    consumer.wait(Duration::from_secs(10));
    for s in [&mut seg, &mut det_b] {
        s.term();
        assert!(s.wait(Duration::from_secs(5)).success());
    }
    let r = report(&json);
    let d = &r["detections"];
    assert_eq!(d["detector_runs"], 2, "{r}");
    assert!(
        d["messages"].as_u64().unwrap() >= 25 && d["proposals"].as_u64().unwrap() > 1000,
        "proposals from both detectors: {r}"
    );
    // The segmenter was not disturbed: every scan got its mask.
    assert_eq!(r["unmatched_masks"], 0, "{r}");
    // (What the killed detector left is swept by whichever stage looks first: the others'
    // periodic sweep, or the new detector at start.)
    let log = det_b.log();
    assert!(
        log.contains("detector stopped") && log.contains("mask_rejected"),
        "{log}"
    );
    assert!(
        log.contains("no proposals: the segmenter rejected scan"),
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
    let producer = groundwork_service::transport::node_name(&service(&p), "producer");
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
    // What ran and whether it was healthy, first, in words.
    assert!(
        stdout.starts_with("pipeline: 6 scans of")
            && stdout.contains("replayed 2 time(s) (12 scans), through 4 processes"),
        "{stdout}"
    );
    assert!(
        stdout.contains("verdict: healthy: every scan masked (12 of 12), nothing dropped"),
        "{stdout}"
    );
    // A clean start and stop logs no warning (iceoryx2's config is set in code).
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains(" WARN "), "{stderr}");
    assert!(
        stdout.contains("end to end") && stdout.contains("live accuracy"),
        "{stdout}"
    );
    // The detector stage ran beside them: its proposals and its latency rows.
    assert!(
        stdout.contains("detector: ") && stdout.contains("\ndetect "),
        "{stdout}"
    );
    // Each stage's CPU time per scan, beside the latency it buys.
    let cpu = stdout
        .lines()
        .find_map(|l| l.strip_prefix("CPU per scan, ms: "))
        .unwrap_or_else(|| panic!("no CPU line: {stdout}"));
    let ms = |stage: &str| -> f64 {
        cpu.split(", ")
            .find_map(|e| e.strip_prefix(&format!("{stage} ")))
            .unwrap_or_else(|| panic!("no {stage} in {cpu}"))
            .parse()
            .unwrap()
    };
    // Segmenting 124k points takes milliseconds of CPU; publishing them far less.
    assert!(ms("segmenter") > 1.0 && ms("detector") > 0.5, "{cpu}");
    assert!(ms("producer") < ms("segmenter"), "{cpu}");
    // The consumer counted every proposal the detector published (its last ones come
    // after the last mask).
    let published = logged(&stderr, "detector stopped", "proposals");
    assert!(
        stdout.contains(&format!(" proposals messages, {published} proposals")),
        "detector published {published}: {stdout}"
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

/// The consumer's optional recording: every segmented scan as a PointCloud2 with its
/// ground probabilities, readable by the same reader `segment` and `eval` use.
#[test]
fn the_consumer_records_the_pipeline_to_mcap() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("run/ground.mcap");
    let p = prefix("record");
    let out = Command::new(env!("CARGO_BIN_EXE_groundwork"))
        .args([
            "pipeline", "--count", "6", "--rate", "10", "--prefix", &p, "--out",
        ])
        .arg(&rec)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("6 masks (6 segmented"), "{stdout}");
    let scans: Vec<_> = groundwork_io::RecordingReader::open(&rec, None, 200_000)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(scans.len(), 6);
    let bytes = std::fs::read(&rec).unwrap();
    // The clouds, after the mount's one static transform of their frame.
    let all: Vec<_> = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(Result::unwrap)
        .collect();
    assert_eq!(all[0].channel.topic, "/tf_static");
    let messages: Vec<_> = all[1..]
        .iter()
        .filter(|m| m.channel.topic == "/points")
        .collect();
    // The detector's boxes beside them (foxglove.SceneUpdate), each at its scan's stamp;
    // the last one may miss the consumer's stop.
    let boxes: Vec<_> = all
        .iter()
        .filter(|m| m.channel.topic == "/proposals")
        .collect();
    assert!((5..=6).contains(&boxes.len()), "{} proposals", boxes.len());
    for b in &boxes {
        assert_eq!(b.channel.message_encoding, "protobuf");
        assert!(messages.iter().any(|m| m.log_time == b.log_time));
    }
    let bundled: Vec<_> = groundwork_io::list_scans(&data().join("velodyne"))
        .unwrap()
        .iter()
        .map(|f| groundwork_io::read_scan(f, 200_000).unwrap())
        .collect();
    for (i, (s, m)) in scans.iter().zip(messages).enumerate() {
        // Points exactly as the producer published one of the bundled frames.
        let want = bundled
            .iter()
            .find(|b| b.points == s.scan.points)
            .unwrap_or_else(|| panic!("scan {i} is none of the bundled frames"));
        assert_eq!(s.topic, "/points");
        if i > 0 {
            assert!(s.log_time_ns > scans[i - 1].log_time_ns);
        }
        let probs =
            groundwork_io::pointcloud2::decode_probabilities(&rec, &m.data, 200_000).unwrap();
        assert_eq!(probs.len(), want.points.len());
        assert!(probs.iter().all(|p| (0.0..=1.0).contains(p)));
        let ground = probs.iter().filter(|&&p| p >= 0.5).count();
        assert!(ground > probs.len() / 4, "scan {i}: {ground} ground");
    }
}

fn signal(pid: i32, sig: rustix::process::Signal) {
    let pid = rustix::process::Pid::from_raw(pid).unwrap();
    rustix::process::kill_process(pid, sig).unwrap();
}

fn service(p: &str) -> groundwork_service::ServiceConfig {
    groundwork_service::ServiceConfig {
        prefix: p.to_string(),
        ..Default::default()
    }
}

/// Pid of the live process holding `stage` in pipeline `p`, waiting up to 10 s for it.
fn stage_pid(p: &str, stage: &str) -> i32 {
    let t = Instant::now();
    loop {
        let nodes = groundwork_service::transport::pipeline_nodes(&service(p));
        if let Some(n) = nodes.iter().find(|n| n.0 == stage && n.1) {
            return n.2;
        }
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "no {stage}: {nodes:?}"
        );
        sleep(0.1);
    }
}

fn shm_files() -> Vec<std::ffi::OsString> {
    std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name())
        .collect()
}

/// iceoryx2's domain-wide node counter (`iox2_<hash>_node.<version>.global_mgmt`): the first
/// node on the machine creates it, world-writable by iceoryx2's design, and it outlives every
/// pipeline. It holds a node counter and no pipeline data, so it is not the pipeline's.
fn is_iceoryx2_global(f: &std::ffi::OsStr) -> bool {
    f.to_string_lossy().ends_with(".global_mgmt")
}

/// Asserts that pipeline `p` left no node (alive or dead) and no shared memory beyond
/// iceoryx2's management file, waiting up to `limit` for its processes to leave.
fn assert_nothing_left(p: &str, shm_before: &[std::ffi::OsString], limit: Duration) {
    let t = Instant::now();
    loop {
        let nodes = groundwork_service::transport::pipeline_nodes(&service(p));
        let new: Vec<_> = shm_files()
            .into_iter()
            .filter(|f| !shm_before.contains(f) && !is_iceoryx2_global(f))
            .collect();
        if nodes.is_empty() && new.is_empty() {
            return;
        }
        assert!(t.elapsed() < limit, "left behind: {nodes:?} {new:?}");
        sleep(0.1);
    }
}

/// `groundwork pipeline` as a child with its output in files.
fn pipeline(dir: &Path, p: &str, args: &[&str], own_group: bool) -> Proc {
    use std::os::unix::process::CommandExt;
    let stderr = dir.join("pipeline.err");
    let mut c = Command::new(env!("CARGO_BIN_EXE_groundwork"));
    c.args(["pipeline", "--prefix", p, "--rate", "10"])
        .args(args)
        .env("RUST_LOG", "info")
        .stdout(std::fs::File::create(dir.join("pipeline.out")).unwrap())
        .stderr(std::fs::File::create(&stderr).unwrap());
    if own_group {
        c.process_group(0);
    }
    Proc {
        child: c.spawn().unwrap(),
        stderr,
    }
}

#[test]
fn stop_and_continue_does_not_end_any_stage() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("stopcont");
    let (mut consumer, json) = consumer(tmp.path(), "consumer", &p, &["--idle-timeout", "4"]);
    let mut seg = Proc::start(tmp.path(), "segmenter", &p, &["--frames", "1"]);
    sleep(0.5);
    let mut prod = Proc::start(
        tmp.path(),
        "producer",
        &p,
        &["--rate", "10", "--count", "50"],
    );
    sleep(1.0);
    use rustix::process::Signal;
    // A debugger, `kill -STOP` while profiling, Ctrl-Z: each stage in turn.
    for pid in [seg.child.id(), consumer.child.id(), prod.child.id()] {
        signal(pid as i32, Signal::STOP);
        sleep(0.7);
        signal(pid as i32, Signal::CONT);
        sleep(0.3);
    }
    assert!(seg.alive(), "segmenter ended:\n{}", seg.log());
    assert!(
        prod.wait(Duration::from_secs(15)).success(),
        "{}",
        prod.log()
    );
    assert!(
        !prod.log().contains("termination requested"),
        "{}",
        prod.log()
    );
    assert!(
        consumer.wait(Duration::from_secs(15)).success(),
        "{}",
        consumer.log()
    );
    assert!(seg.alive(), "segmenter ended:\n{}", seg.log());
    seg.term();
    assert!(seg.wait(Duration::from_secs(5)).success(), "{}", seg.log());
    // The consumer's report was written and every scan is accounted for.
    let r = report(&json);
    assert_eq!(scan_fate_total(&r), 50, "{r}");
    assert!(r["scan_fate"]["masked"].as_u64().unwrap() >= 40, "{r}");
}

#[test]
fn every_scan_is_accounted_for_across_a_segmenter_restart() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("fate");
    let (mut consumer, json) = consumer(tmp.path(), "consumer", &p, &["--idle-timeout", "3"]);
    sleep(0.3);
    // The consumer and the producer run before any segmenter exists.
    let mut prod = Proc::start(
        tmp.path(),
        "producer",
        &p,
        &["--rate", "10", "--count", "60"],
    );
    sleep(1.0);
    let mut seg_a = Proc::start(tmp.path(), "segmenter-a", &p, &["--frames", "1"]);
    sleep(2.0);
    seg_a.kill9();
    sleep(1.0);
    let mut seg_b = Proc::start(tmp.path(), "segmenter-b", &p, &["--frames", "1"]);
    assert!(prod.wait(Duration::from_secs(15)).success());
    let published = published(&prod.log());
    assert!(consumer.wait(Duration::from_secs(10)).success());
    seg_b.term();
    seg_b.wait(Duration::from_secs(5));
    let r = report(&json);
    let f = &r["scan_fate"];
    let get = |k: &str| f[k].as_u64().unwrap();
    // Exactly one bucket per published scan.
    assert_eq!(scan_fate_total(&r), published, "{r}");
    // The first second (no segmenter) and the second after the kill got no mask.
    assert!(get("unanswered") >= 12, "{r}");
    assert!(get("masked") >= 30, "{r}");
    assert_eq!(r["segmenter_runs"], 2, "{r}");
}

#[test]
fn a_second_producer_or_segmenter_of_a_pipeline_is_refused() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("dup");
    let mut seg_a = Proc::start(tmp.path(), "segmenter-a", &p, &["--frames", "1"]);
    let mut prod_a = Proc::start(tmp.path(), "producer-a", &p, &["--rate", "5"]);
    stage_pid(&p, "segmenter");
    stage_pid(&p, "producer");
    for (name, args) in [
        ("segmenter-b", &["--frames", "1"][..]),
        ("producer-b", &["--rate", "5"][..]),
    ] {
        let mut b = Proc::start(tmp.path(), name, &p, args);
        let st = b.wait(Duration::from_secs(10));
        assert_eq!(st.code(), Some(2), "{}", b.log());
        let role = name.split('-').next().unwrap();
        assert!(
            b.log().contains(&format!("another {role} of pipeline")),
            "{}",
            b.log()
        );
    }
    assert!(
        seg_a.alive() && prod_a.alive(),
        "the first ones keep running"
    );
    // Let a few scans flow (5 Hz) before stopping, for the count below.
    sleep(2.0);
    prod_a.term();
    seg_a.term();
    assert!(prod_a.wait(Duration::from_secs(5)).success());
    assert!(seg_a.wait(Duration::from_secs(5)).success());
    // No consumer was attached: every mask reached nobody, and that is counted.
    let log = seg_a.log();
    let field = |k: &str| logged(&log, "segmenter stopped", k);
    assert!(field("received") > 0, "{log}");
    assert_eq!(field("unreceived_masks"), field("received"), "{log}");
}

#[test]
fn skipped_input_files_are_counted_and_the_producer_exits_non_zero() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("skip");
    let dir = tmp.path().join("seq");
    std::fs::create_dir(&dir).unwrap();
    for i in 0..2 {
        let name = format!("{i:06}.bin");
        std::fs::copy(data().join("velodyne").join(&name), dir.join(&name)).unwrap();
    }
    std::fs::write(dir.join("000002.bin"), [0u8; 7]).unwrap();
    let mut prod = Proc::start(
        tmp.path(),
        "producer",
        &p,
        &["--rate", "50", "--count", "6", dir.to_str().unwrap()],
    );
    let st = prod.wait(Duration::from_secs(10));
    let log = prod.log();
    assert_eq!(st.code(), Some(1), "{log}");
    assert!(log.contains("000002.bin"), "{log}");
    assert_eq!(published(&log), 6, "{log}");
    assert_eq!(
        logged(&log, "producer stopped", "skipped_files"),
        1,
        "{log}"
    );
}

#[test]
fn the_pipeline_fails_when_a_stage_dies_and_restarts_it_when_asked() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    use rustix::process::Signal;
    // Without --restart: a supervisor sees a failure.
    for stage in ["segmenter", "detector", "producer", "consumer"] {
        let p = prefix(&format!("die-{stage}"));
        let mut pl = pipeline(tmp.path(), &p, &[], false);
        let pid = stage_pid(&p, stage);
        sleep(1.0);
        signal(pid, Signal::KILL);
        let st = pl.wait(Duration::from_secs(15));
        assert_eq!(st.code(), Some(1), "{stage}:\n{}", pl.log());
        assert!(pl.log().contains("killed by signal 9"), "{}", pl.log());
    }
    // With --restart 1: the dead segmenter is started again and the run completes.
    let p = prefix("restart");
    let mut pl = pipeline(tmp.path(), &p, &["--count", "40", "--restart", "1"], false);
    let pid = stage_pid(&p, "segmenter");
    sleep(1.5);
    signal(pid, Signal::KILL);
    let st = pl.wait(Duration::from_secs(30));
    let log = pl.log();
    assert!(st.success(), "{log}");
    assert!(log.contains("restarting"), "{log}");
    let out = std::fs::read_to_string(tmp.path().join("pipeline.out")).unwrap();
    assert!(out.contains("2 segmenter run(s)"), "{out}");
}

#[test]
fn stages_die_with_a_killed_launcher_and_sighup_stops_the_pipeline_cleanly() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    use rustix::process::Signal;
    let before = shm_files();
    // kill -9 of the launcher: its stages get SIGTERM from the kernel and leave cleanly.
    let p = prefix("orphan");
    let mut pl = pipeline(tmp.path(), &p, &[], false);
    stage_pid(&p, "producer");
    sleep(1.5);
    pl.kill9();
    assert_nothing_left(&p, &before, Duration::from_secs(10));

    // SIGHUP to the whole group (an ssh session closing): a clean stop with a report.
    let p = prefix("hangup");
    let mut pl = pipeline(tmp.path(), &p, &[], true);
    stage_pid(&p, "producer");
    sleep(2.0);
    let pgid = rustix::process::Pid::from_child(&pl.child);
    rustix::process::kill_process_group(pgid, Signal::HUP).unwrap();
    let st = pl.wait(Duration::from_secs(15));
    assert!(st.success(), "{}", pl.log());
    let out = std::fs::read_to_string(tmp.path().join("pipeline.out")).unwrap();
    assert!(
        out.contains("scan fate") && out.contains("end to end"),
        "{out}"
    );
    assert_nothing_left(&p, &before, Duration::from_secs(5));
}

#[test]
fn another_user_cannot_attach_to_a_pipeline() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    if !rustix::process::geteuid().is_root() {
        // CI runs as root and says so (GROUNDWORK_REQUIRE_ROOT=1): there it must run.
        assert!(
            std::env::var_os("GROUNDWORK_REQUIRE_ROOT").is_none(),
            "GROUNDWORK_REQUIRE_ROOT is set: this test needs root to run a stage as another user"
        );
        eprintln!("skipped: needs root to run a stage as another user");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("perm");
    let before = shm_files();
    let mut seg = Proc::start(tmp.path(), "segmenter", &p, &["--frames", "1"]);
    stage_pid(&p, "segmenter");
    // The pipeline's shared memory is this user's alone.
    use std::os::unix::fs::MetadataExt;
    // (On a fresh machine this segmenter may be the first node and create iceoryx2's global
    // counter, which is not the pipeline's.)
    for f in shm_files()
        .iter()
        .filter(|f| !before.contains(f) && !is_iceoryx2_global(f))
    {
        let m = std::fs::metadata(Path::new("/dev/shm").join(f)).unwrap();
        assert_eq!(
            m.mode() & 0o077,
            0,
            "{f:?} is open to others: {:o}",
            m.mode()
        );
    }
    // A consumer and a producer run as `nobody` are refused with a clear message. The
    // binary is copied where `nobody` may run it (the checkout may be private to root).
    use std::os::unix::fs::PermissionsExt;
    let open = PathBuf::from(format!("/tmp/gwtest-perm-{}", std::process::id()));
    std::fs::create_dir_all(&open).unwrap();
    std::fs::set_permissions(&open, std::fs::Permissions::from_mode(0o755)).unwrap();
    let exe = open.join("groundwork");
    std::fs::copy(env!("CARGO_BIN_EXE_groundwork"), &exe).unwrap();
    std::fs::set_permissions(&exe, std::fs::Permissions::from_mode(0o755)).unwrap();
    for args in [
        &["consumer", "--count", "1"][..],
        &["producer", "--synthetic", "1000"],
    ] {
        let o = Command::new("setpriv")
            .args(["--reuid=65534", "--regid=65534", "--clear-groups"])
            .arg(&exe)
            .args(args)
            .args(["--prefix", &p])
            .current_dir(&open)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(
            err.contains("permission denied") && err.contains("run every stage as that user"),
            "{err}"
        );
    }
    let _ = std::fs::remove_dir_all(&open);
    assert!(seg.alive());
    seg.term();
    assert!(seg.wait(Duration::from_secs(5)).success());
}

#[test]
fn stale_counts_name_only_this_pipelines_dead_processes() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let other = prefix("stale-other");
    let mine = prefix("stale-mine");
    // Another pipeline's segmenter dies with -9 and leaves its node behind.
    let mut dead = Proc::start(tmp.path(), "segmenter-other", &other, &["--frames", "1"]);
    stage_pid(&other, "segmenter");
    dead.kill9();
    // This pipeline's segmenter cleans it up (iceoryx2 cleans every dead node) but does
    // not report it as one of its own.
    let mut seg = Proc::start(tmp.path(), "segmenter-mine", &mine, &["--frames", "1"]);
    stage_pid(&mine, "segmenter");
    seg.term();
    assert!(seg.wait(Duration::from_secs(5)).success());
    let log = seg.log();
    assert!(!log.contains("removed stale resources"), "{log}");
    assert!(
        groundwork_service::transport::pipeline_nodes(&service(&other)).is_empty(),
        "the dead node was removed all the same"
    );
}

/// `groundwork pipeline <args>` to the end: (exit status, stdout, stderr).
fn pipeline_run(p: &str, args: &[&str]) -> (std::process::ExitStatus, String, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_groundwork"))
        .args(["pipeline", "--prefix", p])
        .args(args)
        .output()
        .unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (o.status, text(&o.stdout), text(&o.stderr))
}

/// The consumer summary's "scan fate: … = N" and "dropped masks M".
fn fate_and_dropped_masks(stdout: &str) -> (u64, u64) {
    let after = |key: &str| -> u64 {
        let rest = stdout
            .split(key)
            .nth(1)
            .unwrap_or_else(|| panic!("no {key:?} in {stdout}"));
        rest.trim_start()
            .split(|c: char| !c.is_ascii_digit())
            .next()
            .unwrap()
            .parse()
            .unwrap()
    };
    (after(" dropped = "), after("dropped masks "))
}

#[test]
fn the_scan_fate_adds_up_when_the_producer_outruns_everything() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // --rate 0: 150 scans in a fraction of a second; the segmenter and the consumer lose
    // most of them in their queues, and the producer is done long before they are.
    let p = prefix("rate0");
    let (st, out, err) = pipeline_run(&p, &["--count", "150", "--rate", "0", "--no-detector"]);
    assert!(st.success(), "{out}\n{err}");
    let (fate, dropped_masks) = fate_and_dropped_masks(&out);
    assert_eq!(fate, 150, "{out}");
    // Masks for scans the segmenter never received were never published: none was lost.
    assert_eq!(dropped_masks, 0, "{out}");
}

#[test]
fn a_stopped_segmenter_loses_scans_not_masks() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let p = prefix("segstop");
    let mut pl = pipeline(tmp.path(), &p, &["--count", "80", "--no-detector"], false);
    let pid = stage_pid(&p, "segmenter");
    sleep(1.5);
    use rustix::process::Signal;
    signal(pid, Signal::STOP);
    sleep(3.0);
    signal(pid, Signal::CONT);
    assert!(pl.wait(Duration::from_secs(60)).success(), "{}", pl.log());
    let out = std::fs::read_to_string(tmp.path().join("pipeline.out")).unwrap();
    let (fate, dropped_masks) = fate_and_dropped_masks(&out);
    assert_eq!(fate, 80, "{out}");
    assert_eq!(dropped_masks, 0, "{out}");
    // The scans the stopped segmenter missed are unanswered, not masks lost.
    let unanswered: u64 = out
        .split(" unanswered")
        .next()
        .and_then(|s| s.rsplit(' ').next())
        .unwrap()
        .parse()
        .unwrap();
    assert!(unanswered >= 20, "{out}");
}

#[test]
fn a_stage_that_exits_while_the_pipeline_runs_is_restarted_or_fails_it() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    use rustix::process::Signal;
    // SIGTERM makes a stage leave cleanly with exit code 0; the pipeline still lost it.
    let p = prefix("term-seg");
    let mut pl = pipeline(tmp.path(), &p, &[], false);
    let pid = stage_pid(&p, "segmenter");
    sleep(1.0);
    signal(pid, Signal::TERM);
    let st = pl.wait(Duration::from_secs(15));
    assert_eq!(st.code(), Some(1), "{}", pl.log());
    assert!(
        pl.log()
            .contains("exited with code 0 while the pipeline ran"),
        "{}",
        pl.log()
    );
    // With --restart it is started again, and the run completes with every scan answered
    // but those of the gap.
    let p = prefix("term-restart");
    let mut pl = pipeline(tmp.path(), &p, &["--count", "40", "--restart", "3"], false);
    let pid = stage_pid(&p, "segmenter");
    sleep(1.5);
    signal(pid, Signal::TERM);
    let st = pl.wait(Duration::from_secs(40));
    assert!(st.success(), "{}", pl.log());
    assert!(pl.log().contains("restarting"), "{}", pl.log());
    let out = std::fs::read_to_string(tmp.path().join("pipeline.out")).unwrap();
    assert!(out.contains("2 segmenter run(s)"), "{out}");

    // The consumer is the stage whose end ends the pipeline: stopped by a signal before its
    // count, it did not finish (exit 4), so the pipeline fails or restarts it.
    for (sig, restart) in [(Signal::TERM, false), (Signal::INT, true)] {
        let p = prefix(&format!("term-consumer-{restart}"));
        let args: &[&str] = if restart {
            &["--count", "60", "--restart", "3"]
        } else {
            &["--count", "60"]
        };
        let mut pl = pipeline(tmp.path(), &p, args, false);
        let pid = stage_pid(&p, "consumer");
        sleep(2.0);
        signal(pid, sig);
        let st = pl.wait(Duration::from_secs(60));
        let log = pl.log();
        assert!(
            log.contains("stopped by a signal before it finished"),
            "{log}"
        );
        if restart {
            assert!(st.success(), "{log}");
            assert!(
                log.contains("restarting") && log.contains("stage=\"consumer\""),
                "{log}"
            );
        } else {
            assert_eq!(st.code(), Some(1), "{log}");
        }
    }
}

#[test]
fn a_pipeline_that_cannot_write_its_outputs_fails() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let Some(tmpfs) = support::Tmpfs::mount(&tmp.path().join("disk"), 64) else {
        return;
    };
    let disk = &tmpfs.0;
    let p = prefix("fulldisk");
    let rec = disk.join("rec.mcap");
    let (st, out, err) = pipeline_run(
        &p,
        &[
            "--count",
            "6",
            "--no-detector",
            "--out",
            rec.to_str().unwrap(),
        ],
    );
    assert_eq!(st.code(), Some(1), "{out}\n{err}");
    assert!(out.contains("writes failed"), "{out}");
    assert!(!out.contains(" 0 writes failed"), "{out}");
    assert!(!rec.exists(), "no broken recording under the final name");
}

#[test]
fn the_producer_streams_a_folder_in_flat_memory() {
    let _g = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    // 120 scans of 2 MB (links to one file: no disk cost): 240 MB if loaded at once.
    let dir = tmp.path().join("seq");
    std::fs::create_dir(&dir).unwrap();
    for k in 0..120 {
        std::fs::hard_link(
            data().join("velodyne/000000.bin"),
            dir.join(format!("{k:06}.bin")),
        )
        .unwrap();
    }
    let p = prefix("stream");
    let mut prod = Proc::start(
        tmp.path(),
        "producer",
        &p,
        &[
            "--count",
            "120",
            "--rate",
            "0",
            "--linger",
            "inf",
            dir.to_str().unwrap(),
        ],
    );
    // Wait for all 120 to be out (the linger line), then read the peak resident size.
    let t = Instant::now();
    while !prod.log().contains("all scans out") {
        assert!(t.elapsed() < Duration::from_secs(30), "{}", prod.log());
        sleep(0.1);
    }
    let status = std::fs::read_to_string(format!("/proc/{}/status", prod.child.id())).unwrap();
    let peak_kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.split_whitespace().next())
        .unwrap()
        .parse()
        .unwrap();
    prod.term();
    assert!(
        prod.wait(Duration::from_secs(5)).success(),
        "{}",
        prod.log()
    );
    assert_eq!(published(&prod.log()), 120);
    // Measured 25 MB streaming; loading the folder took over 240 MB.
    assert!(peak_kb < 100_000, "peak resident {peak_kb} kB");
}
