//! Latency benchmark of the service with real processes, all methods in one run, per payload size:
//! - `iox-pingpong`: bare iceoryx2 round trip between two processes (scan out, mask back,
//!   event wake-ups), the floor any iceoryx2 pipeline stands on;
//! - `iox-relay`: bare iceoryx2 through three processes like the pipeline (source → relay
//!   answering with a mask → sink), publication of the scan to receipt of the mask;
//! - `uds-copy`: the same round trip over a Unix domain socket (the payload is copied);
//! - `pipeline-echo`: producer → segmenter (`--echo`: answers with a mask of the right size
//!   without computing) → consumer, three processes; transport = scan hop + mask hop, per
//!   message, and scan publication → mask receipt (the path the relay measures);
//! - `pipeline-full`: the same with real segmentation, and the detector stage beside it
//!   (its detect time, and scan production to proposals published);
//! - `pipeline-ros2` (with `--ros2`): a DDS driver process (RustDDS, reliable) publishes
//!   PointCloud2 clouds, the ROS 2 bridge is the pipeline's source, the segmenter echoes:
//!   the bridge's time from DDS's receipt of a cloud to its scan in shared memory, and the
//!   pipeline's end to end from that receipt.
//!
//! The machine is shared and noisy, so every method runs `--rounds` times, interleaved, and
//! each percentile is the median over the rounds. Prints p50/p90/p99/p99.9/max per method
//! and size, the pipeline's transport as a ratio to bare iceoryx2 (ping-pong and relay),
//! and optionally CSV.
//!
//! `cargo build --release -p groundwork-cli -p groundwork-benches && target/release/latency`

use std::io::{Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Parser;
use groundwork_msg::{MaskHeader, ScanHeader, ScanPoint};
use groundwork_service::{ServiceConfig, transport};
use hdrhistogram::Histogram;

#[derive(Parser, Debug)]
struct Args {
    /// Round trips per size for the ping-pongs (paced at --echo-rate).
    #[arg(long, default_value_t = 500)]
    iterations: u64,
    /// Scans per size through the echo pipeline (at --echo-rate Hz).
    #[arg(long, default_value_t = 300)]
    pipeline_scans: u64,
    /// Scans per size through the full pipeline (at 15 Hz).
    #[arg(long, default_value_t = 120)]
    full_scans: u64,
    /// Producer rate of the echo pipeline, and pace of the ping-pongs.
    #[arg(long, default_value_t = 100.0)]
    echo_rate: f64,
    /// Payload sizes in points (16 bytes each): ≈16 KB, 1 MB, 2 MB, 3.2 MB.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1000,65536,131072,200000"
    )]
    points: Vec<usize>,
    /// Also write the table as CSV here.
    #[arg(long)]
    csv: Option<PathBuf>,
    /// Rounds of every method (interleaved); percentiles are medians over rounds.
    #[arg(long, default_value_t = 3)]
    rounds: usize,
    /// Skip the full pipeline (transport only).
    #[arg(long)]
    no_full: bool,
    /// Also the ROS 2 bridge as the pipeline's source (`pipeline-ros2`).
    #[arg(long)]
    ros2: bool,
    /// Internal: run as the answering side of a ping-pong.
    #[arg(long, hide = true)]
    role: Option<String>,
    #[arg(long, hide = true)]
    prefix: Option<String>,
    #[arg(long, hide = true)]
    socket: Option<PathBuf>,
    #[arg(long, hide = true)]
    n: Option<usize>,
    #[arg(long, hide = true)]
    count: Option<u64>,
    #[arg(long, hide = true)]
    domain: Option<u16>,
    #[arg(long, hide = true)]
    rate: Option<f64>,
}

/// Same-run ratios of one payload size, [p50, p99].
#[derive(Debug, Clone)]
struct Ratios {
    bytes: usize,
    vs_pingpong: [f64; 2],
    vs_relay: [f64; 2],
    path_vs_relay: [f64; 2],
    uds: f64,
}

#[derive(Debug, Clone)]
struct Row {
    method: String,
    bytes: usize,
    p: [f64; 5],
}

/// Messages sent first and left out of every figure (first touches of shared memory, cold
/// caches), by every method alike.
const WARMUP: u64 = 50;

fn hist() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 60_000_000_000, 3).expect("static bounds are valid")
}

fn row(method: &str, bytes: usize, h: &Histogram<u64>) -> Row {
    let us = |q: f64| h.value_at_quantile(q) as f64 / 1e3;
    Row {
        method: method.into(),
        bytes,
        p: [us(0.5), us(0.9), us(0.99), us(0.999), h.max() as f64 / 1e3],
    }
}

fn service_cfg(prefix: &str, n: usize) -> ServiceConfig {
    ServiceConfig {
        prefix: prefix.into(),
        max_points: n.max(1),
        ..ServiceConfig::default()
    }
}

/// The answering side of the iceoryx2 ping-pong: every scan gets a mask of n f32 back.
fn pong_iox(prefix: &str, n: usize) -> Result<()> {
    let cfg = service_cfg(prefix, n);
    let node = transport::node(&cfg, "pong")?;
    let sub = transport::scan_subscriber(&transport::scan_service(&node, &cfg)?, &cfg)?;
    let publ = transport::mask_publisher(&transport::mask_service(&node, &cfg)?, &cfg)?;
    let scan_listener = transport::event_listener(&node, &cfg, "scans")?;
    let mask_notifier = transport::event_notifier(&node, &cfg, "masks")?;
    loop {
        if scan_listener
            .timed_wait(|_| {}, Duration::from_secs(10))
            .map_err(|e| anyhow::anyhow!("{e:?}"))?
            == 0
        {
            return Ok(()); // the ping side is gone
        }
        while let Some(scan) = sub.receive().map_err(|e| anyhow::anyhow!("{e:?}"))? {
            let h = *scan.user_header();
            let mut mask = publ
                .loan_slice(scan.payload().len())
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            mask.user_header_mut().scan_sequence = h.sequence;
            mask.user_header_mut().stamps = h.stamps;
            drop(scan);
            mask.send().map_err(|e| anyhow::anyhow!("{e:?}"))?;
            mask_notifier
                .notify()
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        }
    }
}

/// The last process of the bare iceoryx2 relay: receives masks and prints the latency
/// from the scan's publication (its stamp) to receipt, as JSON [p50, p90, p99, p99.9, max] µs.
fn sink_iox(prefix: &str, n: usize, count: u64) -> Result<()> {
    let cfg = service_cfg(prefix, n);
    let node = transport::node(&cfg, "sink")?;
    let sub = transport::mask_subscriber(&transport::mask_service(&node, &cfg)?, &cfg)?;
    let mask_listener = transport::event_listener(&node, &cfg, "masks")?;
    let mut h = hist();
    let mut seen = 0;
    while seen < count {
        if mask_listener
            .timed_wait(|_| {}, Duration::from_secs(5))
            .map_err(|e| anyhow::anyhow!("{e:?}"))?
            == 0
        {
            break;
        }
        while let Some(m) = sub.receive().map_err(|e| anyhow::anyhow!("{e:?}"))? {
            let now = groundwork_msg::monotonic_ns();
            let sent = m.user_header().stamps.published_ns;
            seen += 1;
            if seen > WARMUP {
                h.saturating_record(now.saturating_sub(sent).max(1));
            }
        }
    }
    let r = row("", 0, &h);
    println!("{}", serde_json::json!(r.p));
    Ok(())
}

/// Bare iceoryx2 through three processes, the pipeline's topology: this process publishes
/// scans, a relay answers each with a mask, a third process receives the masks.
fn relay_iox(exe: &Path, n: usize, iterations: u64, rate: f64) -> Result<Row> {
    let prefix = format!("latency-relay-{}-{n}", std::process::id());
    let cfg = service_cfg(&prefix, n);
    let node = transport::node(&cfg, "source")?;
    let publ = transport::scan_publisher(&transport::scan_service(&node, &cfg)?, &cfg)?;
    let scan_notifier = transport::event_notifier(&node, &cfg, "scans")?;
    let total = iterations + WARMUP;
    let mut relay = role(exe, "pong-iox", &prefix, n).spawn()?;
    let sink = role(exe, "sink-iox", &prefix, n)
        .args(["--count", &total.to_string()])
        .stdout(Stdio::piped())
        .spawn()?;
    std::thread::sleep(Duration::from_millis(500));
    let t0 = Instant::now();
    for i in 0..total {
        pace(t0, i, rate);
        send_scan(&publ, &scan_notifier, n, i)?;
    }
    let out = sink.wait_with_output()?;
    drop(publ);
    let _ = relay.wait();
    let p: [f64; 5] = serde_json::from_slice(&out.stdout).context("relay sink output")?;
    Ok(Row {
        method: "iox-relay (3 processes)".into(),
        bytes: n * 16,
        p,
    })
}

/// Fills a scan of `n` points in loaned memory, stamps its publication, sends it and wakes
/// the readers. Returns the instant of the send: the fill is the producer's own work and
/// is not part of any measured latency.
fn send_scan(
    publ: &transport::ScanPublisher,
    notifier: &transport::EventNotifier,
    n: usize,
    sequence: u64,
) -> Result<Instant> {
    let sample = publ
        .loan_slice_uninit(n)
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let mut sample = sample.write_from_fn(|k| ScanPoint {
        x: k as f32,
        ..ScanPoint::default()
    });
    let mut h = ScanHeader {
        sequence,
        point_count: n as u32,
        ..ScanHeader::default()
    };
    h.stamps.published_ns = groundwork_msg::monotonic_ns();
    *sample.user_header_mut() = h;
    let t = Instant::now();
    sample.send().map_err(|e| anyhow::anyhow!("{e:?}"))?;
    notifier.notify().map_err(|e| anyhow::anyhow!("{e:?}"))?;
    Ok(t)
}

/// This executable in one of its answering roles, for `n`-point payloads.
fn role(exe: &Path, role: &str, prefix: &str, n: usize) -> Command {
    let mut c = Command::new(exe);
    c.args(["--role", role, "--prefix", prefix, "--n", &n.to_string()])
        .stderr(Stdio::null());
    c
}

/// Sleeps until the next tick of a `rate` Hz clock that started at `t0`: the ping-pongs run
/// at the pipeline's pace, so both pay the same wake-up-from-idle costs.
fn pace(t0: Instant, i: u64, rate: f64) {
    if rate > 0.0 {
        let next = t0 + Duration::from_secs_f64((i + 1) as f64 / rate);
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
}

fn ping_iox(exe: &Path, n: usize, iterations: u64, rate: f64) -> Result<Histogram<u64>> {
    let prefix = format!("latency-iox-{}-{n}", std::process::id());
    let cfg = service_cfg(&prefix, n);
    let node = transport::node(&cfg, "ping")?;
    let publ = transport::scan_publisher(&transport::scan_service(&node, &cfg)?, &cfg)?;
    let sub = transport::mask_subscriber(&transport::mask_service(&node, &cfg)?, &cfg)?;
    let scan_notifier = transport::event_notifier(&node, &cfg, "scans")?;
    let mask_listener = transport::event_listener(&node, &cfg, "masks")?;
    let mut child = role(exe, "pong-iox", &prefix, n).spawn()?;
    std::thread::sleep(Duration::from_millis(500));
    let mut h = hist();
    let t0 = Instant::now();
    for i in 0..iterations + WARMUP {
        pace(t0, i, rate);
        let t = send_scan(&publ, &scan_notifier, n, i)?;
        loop {
            mask_listener
                .timed_wait(|_| {}, Duration::from_secs(5))
                .map_err(|e| anyhow::anyhow!("{e:?}"))?;
            if let Some(m) = sub.receive().map_err(|e| anyhow::anyhow!("{e:?}"))? {
                let m: &MaskHeader = m.user_header();
                anyhow::ensure!(m.scan_sequence == i, "out of order answer");
                break;
            }
        }
        if i >= WARMUP {
            h.saturating_record(t.elapsed().as_nanos() as u64);
        }
    }
    drop((publ, sub));
    let _ = child.wait();
    Ok(h)
}

/// The answering side over a Unix socket: read a whole scan, write a whole mask.
fn pong_uds(path: &Path, n: usize) -> Result<()> {
    let listener = UnixListener::bind(path)?;
    let (mut s, _) = listener.accept()?;
    let mut scan = vec![0u8; n * 16];
    let mask = vec![0u8; n * 4];
    while s.read_exact(&mut scan).is_ok() {
        s.write_all(&mask)?;
    }
    Ok(())
}

fn ping_uds(exe: &Path, n: usize, iterations: u64, rate: f64) -> Result<Histogram<u64>> {
    let path = std::env::temp_dir().join(format!(
        "groundwork-latency-{}-{n}.sock",
        std::process::id()
    ));
    let _ = std::fs::remove_file(&path);
    let mut child = Command::new(exe)
        .args(["--role", "pong-uds", "--n", &n.to_string(), "--socket"])
        .arg(&path)
        .spawn()?;
    let t0 = Instant::now();
    let mut s = loop {
        match UnixStream::connect(&path) {
            Ok(s) => break s,
            Err(_) if t0.elapsed() < Duration::from_secs(5) => {
                std::thread::sleep(Duration::from_millis(20));
            }
            Err(e) => return Err(e).context("connect to the UDS pong"),
        }
    };
    let scan: Vec<u8> = (0..n * 16).map(|i| i as u8).collect();
    let mut mask = vec![0u8; n * 4];
    let mut h = hist();
    let t0 = Instant::now();
    for i in 0..iterations + WARMUP {
        pace(t0, i, rate);
        let t = Instant::now();
        s.write_all(&scan)?;
        s.read_exact(&mut mask)?;
        if i >= WARMUP {
            h.saturating_record(t.elapsed().as_nanos() as u64);
        }
    }
    drop(s);
    let _ = child.wait();
    let _ = std::fs::remove_file(&path);
    Ok(h)
}

/// Where the pipeline's scans come from.
#[derive(Debug, Clone, Copy)]
enum Source<'a> {
    /// `groundwork producer --synthetic`.
    Producer,
    /// The ROS 2 bridge, fed by this tool's DDS driver role (`exe`).
    Ros2 { exe: &'a Path },
}

/// The DDS driver: publishes `count` synthetic clouds of `n` points (x, y, z, intensity
/// float32, as drivers do) at `rate` Hz on `topic`, reliably, after a moment for discovery.
fn ros2_driver(topic: &str, domain: u16, n: usize, count: u64, rate: f64) -> Result<()> {
    use groundwork_io::pointcloud2::PointField;
    use groundwork_ros2::msg::{Header, PointCloud2, Time};
    use ros2_client::{Context, NodeName, NodeOptions};
    let context = Context::from_domain_participant(
        ros2_client::dds::rustdds::DomainParticipant::new(domain)?,
    )?;
    let mut node = context.new_node(
        NodeName::new("/", "latency_driver").map_err(|e| anyhow::anyhow!("{e:?}"))?,
        NodeOptions::new().enable_rosout(false),
    )?;
    let qos = groundwork_ros2::profile(groundwork_ros2::Qos::Reliable);
    let t = node.create_topic(
        &groundwork_ros2::ros_name(topic)?,
        groundwork_ros2::cloud_type(),
        &qos,
    )?;
    let publisher = node.create_publisher::<PointCloud2>(&t, Some(qos))?;
    let mut data = Vec::with_capacity(16 * n);
    for p in groundwork_service::synthetic::scan(n) {
        for v in [p.x, p.y, p.z, p.intensity] {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    let fields = ["x", "y", "z", "intensity"]
        .iter()
        .enumerate()
        .map(|(i, name)| PointField {
            name: (*name).into(),
            offset: 4 * i as u32,
            datatype: 7,
            count: 1,
        })
        .collect();
    let mut cloud = PointCloud2 {
        header: Header {
            stamp: Time::default(),
            frame_id: "lidar".into(),
        },
        height: 1,
        width: n as u32,
        fields,
        is_bigendian: false,
        point_step: 16,
        row_step: 16 * n as u32,
        data,
        is_dense: true,
    };
    std::thread::sleep(Duration::from_secs(2));
    let t0 = Instant::now();
    for i in 0..count {
        pace(t0, i, rate);
        cloud.header.stamp.sec = i as i32;
        publisher
            .publish(cloud.clone())
            .map_err(|e| anyhow::anyhow!("publish: {e}"))?;
    }
    // A leaving reliable writer may take unacknowledged samples with it.
    std::thread::sleep(Duration::from_secs(2));
    Ok(())
}

/// Runs the real pipeline (three processes; four with the detector) on synthetic scans
/// and returns the consumer's report (per-stage percentiles, µs).
fn pipeline(
    groundwork: &Path,
    n: usize,
    scans: u64,
    rate: f64,
    echo: bool,
    source: Source<'_>,
) -> Result<serde_json::Value> {
    let dir = tempfile::tempdir()?;
    let prefix = format!("latency-pipe-{}-{n}-{echo}", std::process::id());
    let svc = dir.path().join("service.toml");
    std::fs::write(
        &svc,
        format!(
            "prefix = \"{prefix}\"\nmax_points = {}\nreport_interval_s = 60.0\n",
            n.max(1)
        ),
    )?;
    let json = dir.path().join("consumer.json");
    // As the bare baselines, leave the first WARMUP messages out.
    let scans = scans + WARMUP;
    let stage = |name: &str| {
        let mut c = Command::new(groundwork);
        c.arg(name)
            .arg("--service")
            .arg(&svc)
            .stderr(Stdio::null())
            .stdout(Stdio::null());
        c
    };
    let mut seg = stage("segmenter");
    seg.args(["--frames", "1"]);
    if echo {
        seg.arg("--echo");
    }
    let mut seg = seg.spawn()?;
    // The full pipeline has its detector beside it, as `groundwork pipeline` does.
    let mut det = if echo {
        None
    } else {
        Some(stage("detector").spawn()?)
    };
    let mut con = stage("consumer")
        .args([
            "--count",
            &scans.to_string(),
            "--idle-timeout",
            "5",
            "--warmup",
            &WARMUP.to_string(),
            "--report-json",
        ])
        .arg(&json)
        .spawn()?;
    std::thread::sleep(Duration::from_millis(500));
    let (mut bridge, mut prod) = match source {
        Source::Producer => {
            let prod = stage("producer")
                .args([
                    "--synthetic",
                    &n.to_string(),
                    "--count",
                    &scans.to_string(),
                    "--rate",
                    &rate.to_string(),
                ])
                .spawn()?;
            (None, prod)
        }
        Source::Ros2 { exe } => {
            // A domain and topic of this run's own: side-by-side runs do not meet.
            let domain = 100 + (std::process::id() % 100) as u16;
            let topic = format!("/latency_{}_{n}", std::process::id());
            let bridge = stage("ros2")
                .args([
                    "--reliable",
                    "--domain-id",
                    &domain.to_string(),
                    "--input-topic",
                ])
                .arg(&topic)
                .spawn()?;
            let driver = role(exe, "ros2-driver", &topic, n)
                .args(["--count", &scans.to_string(), "--rate", &rate.to_string()])
                .args(["--domain", &domain.to_string()])
                .spawn()?;
            (Some(bridge), driver)
        }
    };
    con.wait()?;
    prod.wait()?;
    for child in std::iter::once(&mut seg)
        .chain(det.as_mut())
        .chain(bridge.as_mut())
    {
        let _ = rustix::process::kill_process(
            rustix::process::Pid::from_child(child),
            rustix::process::Signal::TERM,
        );
        child.wait()?;
    }
    let text = std::fs::read_to_string(&json).context("consumer report")?;
    Ok(serde_json::from_str(&text)?)
}

fn stage_row(method: &str, bytes: usize, report: &serde_json::Value, stage: &str) -> Row {
    let s = report["latency_us"]
        .as_array()
        .and_then(|a| a.iter().find(|s| s["stage"] == stage))
        .cloned()
        .unwrap_or_default();
    let g = |k: &str| s[k].as_f64().unwrap_or(f64::NAN);
    Row {
        method: method.into(),
        bytes,
        p: [g("p50"), g("p90"), g("p99"), g("p999"), g("max")],
    }
}

/// Per method, the median over rounds of each percentile.
fn median_rows(rounds: &[Vec<Row>]) -> Vec<Row> {
    let Some(first) = rounds.first() else {
        return Vec::new();
    };
    (0..first.len())
        .map(|m| {
            let p = std::array::from_fn(|i| {
                let mut v: Vec<f64> = rounds.iter().map(|r| r[m].p[i]).collect();
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            });
            Row {
                method: first[m].method.clone(),
                bytes: first[m].bytes,
                p,
            }
        })
        .collect()
}

/// One round of every method for one payload size; the bare baselines first.
fn round(args: &Args, exe: &Path, groundwork: &Path, n: usize) -> Result<Vec<Row>> {
    let bytes = n * 16;
    let (iters, rate) = (args.iterations, args.echo_rate);
    let mut rows = vec![
        row("iox-pingpong", bytes, &ping_iox(exe, n, iters, rate)?),
        relay_iox(exe, n, iters, rate)?,
        row("uds-copy", bytes, &ping_uds(exe, n, iters, rate)?),
    ];
    let echo = pipeline(
        groundwork,
        n,
        args.pipeline_scans,
        rate,
        true,
        Source::Producer,
    )?;
    rows.extend([
        stage_row("pipeline-echo transport", bytes, &echo, "transport"),
        stage_row(
            "pipeline-echo scan→mask",
            bytes,
            &echo,
            "scan published to mask received",
        ),
        stage_row("pipeline-echo end-to-end", bytes, &echo, "end to end"),
    ]);
    if !args.no_full {
        let full = pipeline(
            groundwork,
            n,
            args.full_scans,
            15.0,
            false,
            Source::Producer,
        )?;
        rows.extend([
            stage_row("pipeline-full transport", bytes, &full, "transport"),
            stage_row("pipeline-full segment", bytes, &full, "segment"),
            stage_row("pipeline-full end-to-end", bytes, &full, "end to end"),
            stage_row("pipeline-full detect", bytes, &full, "detect"),
            stage_row(
                "pipeline-full proposals",
                bytes,
                &full,
                "produced to proposals published",
            ),
        ]);
    }
    if args.ros2 {
        let ros2 = pipeline(
            groundwork,
            n,
            args.full_scans,
            15.0,
            true,
            Source::Ros2 { exe },
        )?;
        rows.extend([
            stage_row(
                "pipeline-ros2 bridge",
                bytes,
                &ros2,
                "ros2 receipt to scan published",
            ),
            stage_row("pipeline-ros2 transport", bytes, &ros2, "transport"),
            stage_row("pipeline-ros2 end-to-end", bytes, &ros2, "end to end"),
        ]);
    }
    Ok(rows)
}

fn main() -> Result<()> {
    // On a CPU below the build's target the first vector instruction would be SIGILL.
    if let Err(e) = groundwork_core::cpu::check() {
        eprintln!("error: {e}");
        std::process::exit(3);
    }
    let args = Args::parse();
    match args.role.as_deref() {
        Some("pong-iox") => {
            return pong_iox(args.prefix.as_deref().unwrap_or("x"), args.n.unwrap_or(1));
        }
        Some("sink-iox") => {
            return sink_iox(
                args.prefix.as_deref().unwrap_or("x"),
                args.n.unwrap_or(1),
                args.count.unwrap_or(1),
            );
        }
        Some("pong-uds") => {
            return pong_uds(
                args.socket.as_deref().context("--socket")?,
                args.n.unwrap_or(1),
            );
        }
        Some("ros2-driver") => {
            return ros2_driver(
                args.prefix.as_deref().unwrap_or("/points"),
                args.domain.unwrap_or(0),
                args.n.unwrap_or(1),
                args.count.unwrap_or(1),
                args.rate.unwrap_or(10.0),
            );
        }
        Some(r) => anyhow::bail!("unknown role {r}"),
        None => {}
    }
    let exe = std::env::current_exe()?;
    let groundwork = exe.with_file_name("groundwork");
    anyhow::ensure!(
        groundwork.is_file(),
        "{}: build it first (cargo build --release -p groundwork-cli)",
        groundwork.display()
    );
    let mut rows = Vec::new();
    let mut ratios = Vec::new();
    for &n in &args.points {
        let bytes = n * 16;
        let mut rounds = Vec::new();
        for r in 0..args.rounds.max(1) {
            eprintln!(
                "payload {n} points ({:.1} KB), round {} of {} …",
                bytes as f64 / 1024.0,
                r + 1,
                args.rounds.max(1)
            );
            rounds.push(round(&args, &exe, &groundwork, n)?);
        }
        let med = median_rows(&rounds);
        let p = |name: &str| {
            med.iter()
                .find(|r| r.method == name)
                .map_or([f64::NAN; 5], |r| r.p)
        };
        let (iox, relay, uds) = (
            p("iox-pingpong"),
            p("iox-relay (3 processes)"),
            p("uds-copy"),
        );
        let (transport, path) = (p("pipeline-echo transport"), p("pipeline-echo scan→mask"));
        ratios.push(Ratios {
            bytes,
            vs_pingpong: [transport[0] / iox[0], transport[2] / iox[2]],
            vs_relay: [transport[0] / relay[0], transport[2] / relay[2]],
            path_vs_relay: [path[0] / relay[0], path[2] / relay[2]],
            uds: uds[0] / iox[0],
        });
        rows.extend(med);
    }
    println!(
        "{:<28} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "method (µs)", "payload", "p50", "p90", "p99", "p99.9", "max"
    );
    for r in &rows {
        println!(
            "{:<28} {:>9.0}K {:>10.1} {:>10.1} {:>10.1} {:>10.1} {:>10.1}",
            r.method,
            r.bytes as f64 / 1024.0,
            r.p[0],
            r.p[1],
            r.p[2],
            r.p[3],
            r.p[4]
        );
    }
    println!(
        "\nmedians of {} rounds, same run. Pipeline transport is the scan hop plus the mask hop \
         of each message (the segmenter's own work excluded); the bare 3-process relay does the \
         same two hops with a trivial middle stage; the ping-pong is a round trip between two \
         processes:",
        args.rounds.max(1)
    );
    for r in &ratios {
        let [a, b] = r.vs_relay;
        let [c, d] = r.vs_pingpong;
        let [e, f] = r.path_vs_relay;
        println!(
            "  {:>7.0} KB: transport / bare relay p50 {a:.2}x p99 {b:.2}x (budget <= 1.5x); \
             transport / ping-pong p50 {c:.2}x p99 {d:.2}x; scan→mask / bare relay p50 {e:.2}x \
             p99 {f:.2}x; UDS copy / ping-pong p50 {:.1}x",
            r.bytes as f64 / 1024.0,
            r.uds
        );
    }
    if let Some(path) = &args.csv {
        let mut f = std::fs::File::create(path).with_context(|| path.display().to_string())?;
        writeln!(
            f,
            "method,payload_bytes,p50_us,p90_us,p99_us,p999_us,max_us"
        )?;
        for r in &rows {
            writeln!(
                f,
                "{},{},{},{},{},{},{}",
                r.method, r.bytes, r.p[0], r.p[1], r.p[2], r.p[3], r.p[4]
            )?;
        }
    }
    Ok(())
}
