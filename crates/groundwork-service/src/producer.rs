//! The producer stage: replays a folder of scans (with poses) or generates scans of a
//! chosen size, writing each straight into loaned shared memory.
//!
//! [`ProducerStage`] holds the frames and builds each message's header (sequence, run,
//! pose, stamps, injected faults) with no IPC; [`run`] is the thin iceoryx2 loop around it.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use groundwork_core::{Point, Pose};
use groundwork_eval::Sequence;
use groundwork_msg::{SCHEMA_VERSION, ScanHeader, ScanPoint, monotonic_ns, new_epoch};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::{ServiceConfig, check_shared_memory};
use crate::{signals, transport};

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

const MALFORMED_KINDS: [Malformed; 4] = [
    Malformed::NonFinite,
    Malformed::Empty,
    Malformed::BadSchema,
    Malformed::CountMismatch,
];

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
#[derive(Debug, Clone, Default, Serialize)]
pub struct ProducerReport {
    /// Scans published.
    pub published: u64,
    /// Sends that reached no subscriber.
    pub unreceived: u64,
    /// Malformed scans injected.
    pub malformed: u64,
    /// Input files that could not be read (skipped), with the reason.
    pub skipped_files: Vec<String>,
}

/// One scan ready to publish.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Its points (sensor frame).
    pub points: Vec<Point>,
    /// World from sensor, if known.
    pub pose: Option<Pose>,
    /// Index in its source (file index), for label lookup.
    pub index: u64,
}

/// Reads the source's frames; a file that cannot be read is skipped and reported (the
/// second value), never fatal unless nothing is left.
pub fn load(source: &Source, max_points: usize) -> anyhow::Result<(Vec<Frame>, Vec<String>)> {
    match source {
        Source::Synthetic(n) => {
            anyhow::ensure!(
                *n <= max_points,
                "--synthetic {n} exceeds max_points {max_points}"
            );
            let frame = Frame {
                points: crate::synthetic::scan(*n),
                pose: None,
                index: 0,
            };
            Ok((vec![frame], Vec::new()))
        }
        Source::Sequence(dir) => {
            let seq = Sequence::open(dir, None, None)?;
            let (mut frames, mut skipped) = (Vec::new(), Vec::new());
            for (i, path) in seq.scans.iter().enumerate() {
                // A bad file is reported and skipped; the replay goes on with the others.
                match groundwork_io::read_scan(path, max_points) {
                    Ok(points) => frames.push(Frame {
                        points,
                        pose: seq.poses.as_ref().and_then(|p| p.get(i).copied()),
                        index: i as u64,
                    }),
                    Err(e) => {
                        warn!("skipped: {e}");
                        skipped.push(e.to_string());
                    }
                }
            }
            anyhow::ensure!(
                !frames.is_empty(),
                "{}: no readable scans ({} skipped)",
                dir.display(),
                skipped.len()
            );
            Ok((frames, skipped))
        }
    }
}

/// A pose as a scan header carries it: 4×4 row-major (the inverse of
/// [`crate::segmenter::decode_pose`]).
pub fn pose_matrix(p: &Pose) -> [f64; 16] {
    let m = p.to_homogeneous();
    std::array::from_fn(|i| m[(i / 4, i % 4)])
}

/// The producer stage: frames, run identity, sequence, counters. No IPC.
#[derive(Debug)]
pub struct ProducerStage {
    frames: Vec<Frame>,
    epoch: u64,
    sequence: u64,
    malformed_every: Option<u64>,
    report: ProducerReport,
}

/// The next message: which frame, its header, and the fault to inject (if any).
#[derive(Debug, Clone)]
pub struct Outgoing {
    /// Index into the stage's frames.
    pub frame: usize,
    /// Points the payload carries.
    pub len: usize,
    /// The header (stamps `produced_ns` set; `published_ns` is set just before sending).
    pub header: ScanHeader,
    /// A fault to inject into the payload.
    pub malformed: Option<Malformed>,
}

impl ProducerStage {
    /// A stage over loaded frames (at least one), a new producer run.
    pub fn new(frames: Vec<Frame>, skipped: Vec<String>, malformed_every: Option<u64>) -> Self {
        Self {
            frames,
            epoch: new_epoch(),
            sequence: 0,
            malformed_every,
            report: ProducerReport {
                skipped_files: skipped,
                ..Default::default()
            },
        }
    }

    /// The frames replayed.
    pub fn frames(&self) -> &[Frame] {
        &self.frames
    }

    /// Builds the next message's header; `now_ns` is its production stamp (and, for
    /// replays, its sensor time).
    pub fn process(&mut self, now_ns: u64) -> Outgoing {
        let seq = self.sequence;
        let fi = (seq % self.frames.len() as u64) as usize;
        let frame = &self.frames[fi];
        let bad = self
            .malformed_every
            .filter(|&k| k > 0 && seq % k == k - 1)
            .map(|_| MALFORMED_KINDS[(self.report.malformed % 4) as usize]);
        let len = if bad == Some(Malformed::Empty) {
            0
        } else {
            frame.points.len()
        };
        let mut header = ScanHeader {
            schema_version: if bad == Some(Malformed::BadSchema) {
                SCHEMA_VERSION + 100
            } else {
                SCHEMA_VERSION
            },
            point_count: if bad == Some(Malformed::CountMismatch) {
                len as u32 + 7
            } else {
                len as u32
            },
            sequence: seq,
            producer_epoch: self.epoch,
            sensor_timestamp_ns: now_ns,
            source_index: frame.index,
            has_pose: u32::from(frame.pose.is_some()),
            pose: frame
                .pose
                .as_ref()
                .map(pose_matrix)
                .unwrap_or(ScanHeader::default().pose),
            ..ScanHeader::default()
        };
        header.stamps.produced_ns = now_ns;
        self.sequence += 1;
        self.report.published += 1;
        if bad.is_some() {
            self.report.malformed += 1;
        }
        Outgoing {
            frame: fi,
            len,
            header,
            malformed: bad,
        }
    }

    /// The payload's i-th point of a message.
    pub fn point(&self, out: &Outgoing, i: usize) -> ScanPoint {
        let p = self.frames[out.frame].points[i];
        let nan = out.malformed == Some(Malformed::NonFinite) && i == out.len / 2;
        ScanPoint {
            x: if nan { f32::NAN } else { p.x },
            y: p.y,
            z: p.z,
            intensity: p.intensity,
        }
    }

    /// Counts a send that reached no subscriber.
    pub fn count_unreceived(&mut self) {
        self.report.unreceived += 1;
    }

    /// The counters so far.
    pub fn report(&self) -> &ProducerReport {
        &self.report
    }
}

/// Runs the producer until `count` scans are out or a termination signal arrives.
pub fn run(cfg: &ServiceConfig, opts: &ProducerOptions) -> anyhow::Result<ProducerReport> {
    signals::die_with_launcher()?;
    check_shared_memory(cfg)?;
    let (frames, skipped) = load(&opts.source, cfg.max_points)?;
    let mut stage = ProducerStage::new(frames, skipped, opts.malformed_every);
    let node = transport::node(cfg, "producer")?;
    signals::install(&node)?;
    let svc = transport::scan_service(&node, cfg)?;
    let publisher = transport::scan_publisher(&svc, cfg)?;
    let notifier = transport::event_notifier(&node, cfg, "scans")?;
    let rate = opts.rate_hz.unwrap_or(cfg.rate_hz);
    let period = (rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate));
    info!(
        scans = stage.frames().len(),
        skipped_files = stage.report().skipped_files.len(),
        rate_hz = rate,
        prefix = %cfg.prefix,
        "producer started"
    );
    while opts.count.is_none_or(|c| stage.report().published < c) {
        let t0 = Instant::now();
        let out = stage.process(monotonic_ns());
        let sample = publisher
            .loan_slice_uninit(out.len)
            .map_err(|e| anyhow::anyhow!("loan of {} points: {e:?}", out.len))?;
        // The only copy of the scan on the hot path: from the "driver" into shared memory.
        let mut sample = sample.write_from_fn(|i| stage.point(&out, i));
        *sample.user_header_mut() = out.header;
        sample.user_header_mut().stamps.published_ns = monotonic_ns();
        let reached = sample.send().context("send scan")?;
        let _ = notifier.notify();
        if reached == 0 {
            stage.count_unreceived();
        }
        let wait = period.map_or(Duration::ZERO, |p| p.saturating_sub(t0.elapsed()));
        if !signals::sleep(wait) {
            info!("termination requested");
            break;
        }
    }
    // A launcher killed with -9 (whose death is why we stop) leaves its node: sweep it.
    transport::cleanup_dead(&node);
    let r = stage.report().clone();
    info!(
        published = r.published,
        unreceived = r.unreceived,
        malformed = r.malformed,
        skipped_files = r.skipped_files.len(),
        "producer stopped"
    );
    Ok(r)
}
