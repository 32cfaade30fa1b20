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
use groundwork_io::{ScanIter, ScanSource};
use groundwork_msg::{SCHEMA_VERSION, ScanHeader, ScanPoint, monotonic_ns, new_epoch};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::{ServiceConfig, check_shared_memory};
use crate::{signals, transport};

/// Where scans come from.
#[derive(Debug, Clone)]
pub enum Source {
    /// A folder of scans (KITTI layout with velodyne/ and optional poses.txt + calib.txt,
    /// or any mix of scan formats), replayed in a loop.
    Sequence(PathBuf),
    /// An MCAP recording's PointCloud2 messages (of this topic, or the first point cloud
    /// topic), streamed and replayed in a loop at the recorded rate.
    Recording(PathBuf, Option<String>),
    /// Generated scans of this many points (flat ground and a few boxes), no pose.
    Synthetic(usize),
}

impl Source {
    /// A folder or a recording, told apart by the path.
    pub fn from_path(path: PathBuf, topic: Option<String>) -> Self {
        if path.is_file() {
            Self::Recording(path, topic)
        } else {
            Self::Sequence(path)
        }
    }
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
    /// Index in its source (file or message index), for label lookup.
    pub index: u64,
    /// Recorded time (recordings), ns: replays keep the recorded spacing.
    pub log_time_ns: Option<u64>,
}

/// The frames a producer replays: loaded once (folders, synthetic), or streamed from a
/// recording, which may be far larger than memory and is reopened at its end.
#[derive(Debug)]
pub enum Frames {
    /// All frames in memory, replayed in a loop.
    Loaded(Vec<Frame>),
    /// A recording read one message at a time.
    Streamed(Box<Stream>),
}

/// A recording being replayed.
#[derive(Debug)]
pub struct Stream {
    /// The recording.
    source: ScanSource,
    /// Point limit.
    max_points: usize,
    /// The reader of the current pass.
    reader: ScanIter,
    /// The frame being published.
    current: Frame,
    /// The one after it (to know the recorded gap), if the pass has one.
    next: Option<Frame>,
}

/// Reads the next good frame of a stream, reporting and counting bad ones; None at the end
/// of the pass.
fn next_streamed(reader: &mut ScanIter, skipped: &mut Vec<String>) -> Option<Frame> {
    for item in reader.by_ref() {
        match item.scan {
            Ok(scan) => {
                if scan.skipped() > 0 {
                    tracing::debug!(
                        placeholders = scan.skipped(),
                        "{}: NaN placeholders left out",
                        item.name
                    );
                }
                return Some(Frame {
                    points: scan.points,
                    pose: None,
                    index: item.index as u64,
                    log_time_ns: item.log_time_ns,
                });
            }
            Err(e) => {
                warn!("skipped: {e}");
                skipped.push(e.to_string());
            }
        }
    }
    None
}

impl Frames {
    /// Frames of a source; a scan that cannot be read is skipped and reported (the second
    /// value), never fatal unless nothing is left.
    pub fn load(source: &Source, max_points: usize) -> anyhow::Result<(Self, Vec<String>)> {
        let mut skipped = Vec::new();
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
                    log_time_ns: None,
                };
                Ok((Self::Loaded(vec![frame]), skipped))
            }
            Source::Sequence(dir) => {
                let seq = Sequence::open(dir, None, None)?;
                let mut frames = Vec::new();
                for item in seq.scans(max_points) {
                    // A bad file is reported and skipped; the replay goes on with the others.
                    match item.scan {
                        Ok(scan) => frames.push(Frame {
                            points: scan.points,
                            pose: seq.pose(item.index).copied(),
                            index: item.index as u64,
                            log_time_ns: None,
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
                Ok((Self::Loaded(frames), skipped))
            }
            Source::Recording(path, topic) => {
                let source = ScanSource::Recording {
                    path: path.clone(),
                    topic: topic.clone(),
                };
                let mut reader = source.scans(max_points);
                let current = next_streamed(&mut reader, &mut skipped).with_context(|| {
                    format!(
                        "{}: no readable scans ({} skipped)",
                        path.display(),
                        skipped.len()
                    )
                })?;
                let next = next_streamed(&mut reader, &mut skipped);
                let stream = Stream {
                    source,
                    max_points,
                    reader,
                    current,
                    next,
                };
                Ok((Self::Streamed(Box::new(stream)), skipped))
            }
        }
    }

    /// Frames in memory (a streamed recording holds one).
    pub fn loaded(&self) -> usize {
        match self {
            Self::Loaded(f) => f.len(),
            Self::Streamed(_) => 1,
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
    frames: Frames,
    /// Index of the frame of the last message (loaded frames).
    last: usize,
    epoch: u64,
    sequence: u64,
    malformed_every: Option<u64>,
    report: ProducerReport,
}

/// The next message: which frame, its header, and the fault to inject (if any).
#[derive(Debug, Clone)]
pub struct Outgoing {
    /// Points the payload carries.
    pub len: usize,
    /// The header (stamps `produced_ns` set; `published_ns` is set just before sending).
    pub header: ScanHeader,
    /// A fault to inject into the payload.
    pub malformed: Option<Malformed>,
}

impl ProducerStage {
    /// A stage over frames (at least one), a new producer run.
    pub fn new(frames: Frames, skipped: Vec<String>, malformed_every: Option<u64>) -> Self {
        Self {
            frames,
            last: 0,
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
    pub fn frames(&self) -> &Frames {
        &self.frames
    }

    /// The frame of the last message built.
    fn frame(&self) -> &Frame {
        match &self.frames {
            Frames::Loaded(f) => &f[self.last],
            Frames::Streamed(s) => &s.current,
        }
    }

    /// Moves to the frame of the next message (the first call stays on the first frame).
    fn advance(&mut self) {
        if self.sequence == 0 {
            return;
        }
        match &mut self.frames {
            Frames::Loaded(f) => self.last = (self.last + 1) % f.len(),
            Frames::Streamed(stream) => {
                let Stream {
                    source,
                    max_points,
                    reader,
                    current,
                    next,
                } = &mut **stream;
                let skipped = &mut self.report.skipped_files;
                let upcoming = match next.take() {
                    Some(n) => Some(n),
                    None => {
                        // End of the recording: replay it from the start.
                        *reader = source.scans(*max_points);
                        next_streamed(reader, skipped)
                    }
                };
                if let Some(n) = upcoming {
                    *current = n;
                }
                *next = next_streamed(reader, skipped);
            }
        }
    }

    /// The recorded gap between the frame of the last message and the one after it, for
    /// replays at the recorded rate (None: not a recording, or unknown).
    pub fn recorded_gap(&self) -> Option<Duration> {
        let Frames::Streamed(s) = &self.frames else {
            return None;
        };
        let (a, b) = (s.current.log_time_ns?, s.next.as_ref()?.log_time_ns?);
        // A gap beyond a second is a pause in the recording, not the sensor's rate.
        Some(Duration::from_nanos(b.saturating_sub(a)).min(Duration::from_secs(1)))
    }

    /// Builds the next message's header; `now_ns` is its production stamp (and, for
    /// replays, its sensor time).
    pub fn process(&mut self, now_ns: u64) -> Outgoing {
        self.advance();
        let seq = self.sequence;
        let frame = self.frame();
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
            len,
            header,
            malformed: bad,
        }
    }

    /// The payload's i-th point of a message.
    pub fn point(&self, out: &Outgoing, i: usize) -> ScanPoint {
        let p = self.frame().points[i];
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
    if let Some(r) = opts.rate_hz {
        crate::config::check_rate("--rate", r)?;
    }
    signals::die_with_launcher()?;
    check_shared_memory(cfg)?;
    let (frames, skipped) = Frames::load(&opts.source, cfg.max_points)?;
    let mut stage = ProducerStage::new(frames, skipped, opts.malformed_every);
    let node = transport::node(cfg, "producer")?;
    signals::install(&node)?;
    let svc = transport::scan_service(&node, cfg)?;
    let publisher = transport::scan_publisher(&svc, cfg)?;
    let notifier = transport::event_notifier(&node, cfg, "scans")?;
    // A recording replays at its recorded rate unless a rate is asked for.
    let recorded = opts.rate_hz.is_none() && matches!(opts.source, Source::Recording(..));
    let rate = opts.rate_hz.unwrap_or(cfg.rate_hz);
    let period = (rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate));
    info!(
        frames_in_memory = stage.frames().loaded(),
        recorded_rate = recorded,
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
        let gap = if recorded {
            stage.recorded_gap().or(period)
        } else {
            period
        };
        let wait = gap.map_or(Duration::ZERO, |p| p.saturating_sub(t0.elapsed()));
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

#[cfg(test)]
mod tests {
    use super::*;

    fn recording() -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../groundwork-io/tests/fixtures/kitti_pointcloud2.mcap")
    }

    /// A recording streams one message at a time, loops at its end, and tells the
    /// recorded spacing (10 Hz) for replays at the recorded rate.
    #[test]
    fn a_recording_is_streamed_in_a_loop_at_its_recorded_rate() {
        let (frames, skipped) =
            Frames::load(&Source::Recording(recording(), None), 10_000).unwrap();
        assert!(skipped.is_empty());
        assert_eq!(frames.loaded(), 1);
        let mut stage = ProducerStage::new(frames, skipped, None);
        let mut order = Vec::new();
        for k in 0..7 {
            let out = stage.process(k);
            order.push(out.header.source_index);
            assert_eq!(out.len, out.header.point_count as usize);
            if out.header.source_index < 2 {
                assert_eq!(stage.recorded_gap(), Some(Duration::from_millis(100)));
            }
        }
        assert_eq!(order, [0, 1, 2, 0, 1, 2, 0]);
        // Message 1 holds two NaN placeholders: left out of the published points.
        let (frames, _) = Frames::load(&Source::Recording(recording(), None), 10_000).unwrap();
        let mut stage = ProducerStage::new(frames, Vec::new(), None);
        let lens: Vec<usize> = (0..3).map(|k| stage.process(k).len).collect();
        assert_eq!(lens, [1286, 1284, 1286]);
        let out = stage.process(3);
        let p = stage.point(&out, 0);
        assert!(p.x.is_finite());
    }

    #[test]
    fn a_recording_without_point_clouds_is_an_error() {
        let e = Frames::load(
            &Source::Recording(recording(), Some("/chatter".into())),
            10_000,
        )
        .unwrap_err();
        assert!(format!("{e:#}").contains("no readable scans"), "{e:#}");
    }
}
