//! The producer: replays a folder of scans (with poses) or generates scans of a chosen
//! size, writing each straight into loaned shared memory.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use groundwork_core::{Point, Pose};
use groundwork_eval::Sequence;
use groundwork_msg::{SCHEMA_VERSION, ScanHeader, ScanPoint, monotonic_ns, new_epoch};
use tracing::{info, warn};

use crate::config::{ServiceConfig, check_shared_memory};
use crate::transport;

/// Where scans come from.
#[derive(Debug, Clone)]
pub enum Source {
    /// A KITTI-layout folder (velodyne/, optional poses.txt + calib.txt), replayed in a loop.
    Sequence(PathBuf),
    /// Generated scans of this many points (flat ground and a few boxes), no pose.
    Synthetic(usize),
}

/// Kinds of deliberately malformed scans, for fault tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Malformed {
    /// One coordinate NaN.
    NonFinite,
    /// Zero points.
    Empty,
    /// Wrong schema version.
    BadSchema,
    /// Header point count disagrees with the payload.
    CountMismatch,
}

/// Producer options beyond the shared configuration.
#[derive(Debug, Clone)]
pub struct ProducerOptions {
    /// Scan source.
    pub source: Source,
    /// Stop after this many scans (None: until Ctrl-C).
    pub count: Option<u64>,
    /// Overrides `rate_hz` of the configuration.
    pub rate_hz: Option<f64>,
    /// Every n-th scan is replaced by a malformed one (cycling through the kinds).
    pub malformed_every: Option<u64>,
}

/// What the producer did.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProducerReport {
    /// Scans published.
    pub published: u64,
    /// Sends that reached no subscriber.
    pub unreceived: u64,
    /// Malformed scans injected.
    pub malformed: u64,
}

struct Frame {
    points: Vec<Point>,
    pose: Option<Pose>,
    index: u64,
}

fn load(source: &Source, max_points: usize) -> anyhow::Result<Vec<Frame>> {
    match source {
        Source::Synthetic(n) => {
            anyhow::ensure!(
                *n <= max_points,
                "--synthetic {n} exceeds max_points {max_points}"
            );
            Ok(vec![Frame {
                points: crate::synthetic::scan(*n),
                pose: None,
                index: 0,
            }])
        }
        Source::Sequence(dir) => {
            let seq = Sequence::open(dir, None, None)?;
            let mut frames = Vec::new();
            for (i, path) in seq.scans.iter().enumerate() {
                // A bad file is reported and skipped; the replay goes on with the others.
                match groundwork_io::read_scan(path, max_points) {
                    Ok(points) => frames.push(Frame {
                        points,
                        pose: seq.poses.as_ref().and_then(|p| p.get(i).copied()),
                        index: i as u64,
                    }),
                    Err(e) => warn!("skipped: {e}"),
                }
            }
            anyhow::ensure!(!frames.is_empty(), "{}: no readable scans", dir.display());
            Ok(frames)
        }
    }
}

fn pose_matrix(p: &Pose) -> [f64; 16] {
    let m = p.to_homogeneous();
    std::array::from_fn(|i| m[(i / 4, i % 4)])
}

/// Runs the producer until `count` scans are out or a termination signal arrives.
pub fn run(cfg: &ServiceConfig, opts: &ProducerOptions) -> anyhow::Result<ProducerReport> {
    check_shared_memory(cfg)?;
    let frames = load(&opts.source, cfg.max_points)?;
    let node = transport::node(cfg, "producer")?;
    let svc = transport::scan_service(&node, cfg)?;
    let publisher = transport::scan_publisher(&svc, cfg)?;
    let notifier = transport::event_notifier(&node, cfg, "scans")?;
    let epoch = new_epoch();
    let rate = opts.rate_hz.unwrap_or(cfg.rate_hz);
    let period = (rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate));
    info!(
        scans = frames.len(),
        rate_hz = rate,
        prefix = %cfg.prefix,
        "producer started"
    );
    let mut report = ProducerReport::default();
    let mut seq: u64 = 0;
    let kinds = [
        Malformed::NonFinite,
        Malformed::Empty,
        Malformed::BadSchema,
        Malformed::CountMismatch,
    ];
    loop {
        if opts.count.is_some_and(|c| seq >= c) {
            break;
        }
        let t0 = Instant::now();
        let frame = &frames[(seq % frames.len() as u64) as usize];
        let bad = opts
            .malformed_every
            .filter(|&k| k > 0 && seq % k == k - 1)
            .map(|_| kinds[(report.malformed % kinds.len() as u64) as usize]);
        let n = if bad == Some(Malformed::Empty) {
            0
        } else {
            frame.points.len()
        };
        let produced = monotonic_ns();
        let sample = publisher
            .loan_slice_uninit(n)
            .map_err(|e| anyhow::anyhow!("loan of {n} points: {e:?}"))?;
        // The only copy of the scan on the hot path: from the "driver" into shared memory.
        let pts = &frame.points;
        let mut sample = sample.write_from_fn(|i| {
            let p = pts[i];
            ScanPoint {
                x: if bad == Some(Malformed::NonFinite) && i == n / 2 {
                    f32::NAN
                } else {
                    p.x
                },
                y: p.y,
                z: p.z,
                intensity: p.intensity,
            }
        });
        let h = sample.user_header_mut();
        *h = ScanHeader {
            schema_version: if bad == Some(Malformed::BadSchema) {
                SCHEMA_VERSION + 100
            } else {
                SCHEMA_VERSION
            },
            point_count: if bad == Some(Malformed::CountMismatch) {
                n as u32 + 7
            } else {
                n as u32
            },
            sequence: seq,
            producer_epoch: epoch,
            sensor_timestamp_ns: produced,
            source_index: frame.index,
            has_pose: u32::from(frame.pose.is_some()),
            pose: frame
                .pose
                .as_ref()
                .map(pose_matrix)
                .unwrap_or(ScanHeader::default().pose),
            ..ScanHeader::default()
        };
        h.stamps.produced_ns = produced;
        h.stamps.published_ns = monotonic_ns();
        let reached = sample.send().context("send scan")?;
        let _ = notifier.notify();
        if reached == 0 {
            report.unreceived += 1;
        }
        if bad.is_some() {
            report.malformed += 1;
        }
        report.published += 1;
        seq += 1;
        let wait = period.map_or(Duration::ZERO, |p| p.saturating_sub(t0.elapsed()));
        // `Node::wait` sleeps and returns an error on SIGINT/SIGTERM.
        if node.wait(wait).is_err() {
            info!("termination requested");
            break;
        }
    }
    info!(
        published = report.published,
        unreceived = report.unreceived,
        malformed = report.malformed,
        "producer stopped"
    );
    Ok(report)
}
