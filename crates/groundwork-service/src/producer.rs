//! The producer stage: replays a folder of scans (with poses) or generates scans of a
//! chosen size, writing each straight into loaned shared memory.
//!
//! [`ProducerStage`] holds the frames and builds each message's header (sequence, run,
//! pose, stamps, injected faults) with no IPC; as a [`Stage`] (a source) it publishes one
//! scan per tick at the configured or recorded rate, and [`run`] runs it.

use std::path::PathBuf;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::time::Duration;

use anyhow::Context;
use groundwork_core::{Point, Pose};
use groundwork_io::Sequence;
use groundwork_msg::{
    FrameId, SCHEMA_VERSION, ScanHeader, ScanPoint, ScanSource, new_epoch, wall_clock_ns,
};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::ServiceConfig;
use crate::signals;
use crate::stage::{Input, Inputs, Outbox, Stage, Topic, Wiring};

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
    /// A sensor's packets, live or from a capture, decoded into the loaned samples.
    Packets(crate::packets::PacketSource),
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
    /// After `count` scans, stay this long (`Duration::MAX`: until stopped) before
    /// leaving: iceoryx2 takes a leaving publisher's samples with it, so a subscriber that
    /// has not read the last scans yet would lose them without a trace.
    pub linger: Duration,
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
    /// The packet source's counters (packets, losses, refusals), when scans came from
    /// packets.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub packets: Option<crate::packets::PacketSourceReport>,
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
    /// Recorded time (a recording's log, a folder's times.txt), ns: replays of recordings
    /// keep the recorded spacing.
    pub log_time_ns: Option<u64>,
    /// The scan's own time (its header stamp, else its recorded time), ns.
    pub stamp_ns: Option<u64>,
    /// Its coordinate frame, where the source names one.
    pub frame_id: Option<String>,
}

/// The frames a producer replays: one generated frame (synthetic), or a folder or
/// recording streamed from disk in a loop, a few frames ahead: memory stays flat whatever
/// the size of the source (a KITTI sequence is 9 GB of scans).
#[derive(Debug)]
pub enum Frames {
    /// All frames in memory, replayed in a loop.
    Loaded(Vec<Frame>),
    /// A folder or recording read ahead by a thread of its own.
    Streamed(Box<Stream>),
    /// A sensor's packets, gathered into scans by a receiving thread.
    Packets(Box<crate::packets::PacketStream>),
}

/// Frames read ahead of the one being published: enough to keep a 10 Hz (or a flat-out)
/// replay fed while the disk hiccups, little memory (2 MB per KITTI scan).
pub const READ_AHEAD: usize = 4;

/// What the reading thread hands over.
#[derive(Debug)]
enum Ahead {
    Frame(Frame),
    /// A scan that could not be read (first pass only: a loop does not count it again).
    Skipped(String),
    /// The end of one pass over the source; the next pass follows.
    EndOfPass,
}

/// A folder or recording being replayed.
#[derive(Debug)]
pub struct Stream {
    /// Frames from the reading thread (which ends when this is dropped).
    ahead: Receiver<Ahead>,
    /// The frame being published.
    current: Frame,
    /// The one after it (to know the recorded gap), if the pass has one.
    next: Option<Frame>,
}

/// Reads the source in a loop into `tx` until the receiver is gone. A pass without a
/// single readable scan ends the loop (the producer then has nothing to replay).
fn read_ahead(seq: &Sequence, max_points: usize, tx: &SyncSender<Ahead>) {
    let mut first_pass = true;
    loop {
        let mut any = false;
        for item in seq.scans(max_points) {
            let sent = match item.scan {
                Ok(scan) => {
                    any = true;
                    if scan.skipped() > 0 {
                        tracing::debug!(
                            placeholders = scan.skipped(),
                            "{}: NaN placeholders left out",
                            item.name
                        );
                    }
                    tx.send(Ahead::Frame(Frame {
                        stamp_ns: scan.stamp_ns.or(item.log_time_ns),
                        frame_id: scan.frame_id,
                        points: scan.points,
                        pose: seq.pose(item.index).copied(),
                        index: item.index as u64,
                        log_time_ns: item.log_time_ns,
                    }))
                }
                Err(e) if first_pass => {
                    warn!("skipped: {e}");
                    tx.send(Ahead::Skipped(e.to_string()))
                }
                Err(_) => Ok(()),
            };
            if sent.is_err() {
                return;
            }
        }
        if !any || tx.send(Ahead::EndOfPass).is_err() {
            return;
        }
        first_pass = false;
    }
}

impl Stream {
    /// Starts the reading thread over `seq`.
    fn start(seq: Sequence, max_points: usize, skipped: &mut Vec<String>) -> Option<Self> {
        let (tx, rx) = sync_channel(READ_AHEAD);
        std::thread::Builder::new()
            .name("read-ahead".into())
            .spawn(move || read_ahead(&seq, max_points, &tx))
            .ok()?;
        let mut stream = Self {
            ahead: rx,
            current: NO_FRAME.clone(),
            next: None,
        };
        stream.current = stream.pull(skipped)?;
        stream.next = stream.pull(skipped);
        Some(stream)
    }

    /// The next frame of this pass, counting unreadable scans; None at the end of the pass
    /// (or if the reader has stopped).
    fn pull(&mut self, skipped: &mut Vec<String>) -> Option<Frame> {
        loop {
            match self.ahead.recv().ok()? {
                Ahead::Frame(f) => return Some(f),
                Ahead::Skipped(e) => skipped.push(e),
                Ahead::EndOfPass => return None,
            }
        }
    }

    /// Moves to the next frame (the first of the next pass after the last).
    fn advance(&mut self, skipped: &mut Vec<String>) {
        let upcoming = match self.next.take() {
            Some(n) => Some(n),
            None => self.pull(skipped),
        };
        if let Some(n) = upcoming {
            self.current = n;
        }
        self.next = self.pull(skipped);
    }
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
                    stamp_ns: None,
                    frame_id: None,
                };
                Ok((Self::Loaded(vec![frame]), skipped))
            }
            Source::Sequence(path) | Source::Recording(path, _) => {
                let topic = match source {
                    Source::Recording(_, t) => t.clone(),
                    _ => None,
                };
                let seq = Sequence::open(path, None, None)?.with_topic(topic);
                // A bad file is reported and skipped; the replay goes on with the others.
                let stream = Stream::start(seq, max_points, &mut skipped).with_context(|| {
                    format!(
                        "{}: no readable scans ({} skipped)",
                        path.display(),
                        skipped.len()
                    )
                })?;
                Ok((Self::Streamed(Box::new(stream)), skipped))
            }
            Source::Packets(p) => Ok((
                Self::Packets(Box::new(crate::packets::PacketStream::start(p)?)),
                skipped,
            )),
        }
    }

    /// Frames in memory besides those read ahead ([`READ_AHEAD`] at most).
    pub fn loaded(&self) -> usize {
        match self {
            Self::Loaded(f) => f.len(),
            Self::Streamed(s) => 1 + usize::from(s.next.is_some()),
            Self::Packets(_) => 0,
        }
    }
}

/// The frame of a packet source, which has none (its scans are decoded in place).
static NO_FRAME: Frame = Frame {
    points: Vec::new(),
    pose: None,
    index: 0,
    log_time_ns: None,
    stamp_ns: None,
    frame_id: None,
};

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
    /// How it runs: count, linger, rate.
    pace: Pace,
    /// The sensor time of each message.
    clock: SensorClock,
    report: ProducerReport,
    /// The most points a scan from packets may have.
    max_points: usize,
    /// The coordinate frame of scans from packets.
    frame_id: Option<String>,
}

/// The sensor time a message carries: a scan's own stamp where its source has one (the
/// first pass over a recording keeps every stamp exactly; a looped replay shifts later
/// passes so that time never runs back), else the wall clock at publication, as a live
/// driver stamps.
#[derive(Debug, Clone, Default)]
struct SensorClock {
    /// Added to recorded stamps (0 on the first pass).
    offset: u64,
    /// The last stamp sent and the recorded gap before it.
    last: Option<(u64, u64)>,
}

impl SensorClock {
    /// A gap assumed where a loop restarts and no gap was seen yet: 10 Hz.
    const DEFAULT_GAP: u64 = 100_000_000;

    fn stamp(&mut self, recorded: Option<u64>, wall_ns: u64) -> u64 {
        let t = match recorded {
            None => wall_ns,
            Some(r) => {
                let mut t = r.saturating_add(self.offset);
                if let Some((last, gap)) = self.last
                    && t <= last
                {
                    // Back to the start of the recording: continue one gap later.
                    self.offset = (last + gap).saturating_sub(r);
                    t = r.saturating_add(self.offset);
                }
                t
            }
        };
        let gap = match self.last {
            Some((last, _)) if t > last && recorded.is_some() => t - last,
            Some((_, gap)) => gap,
            None => Self::DEFAULT_GAP,
        };
        self.last = Some((t, gap.min(1_000_000_000)));
        t
    }
}

/// When the producer publishes, and when it stops.
#[derive(Debug, Clone, Default)]
struct Pace {
    count: Option<u64>,
    linger: Duration,
    /// Time between scans (None: flat out).
    period: Option<Duration>,
    /// Replay a recording at its recorded rate.
    recorded: bool,
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
            pace: Pace::default(),
            clock: SensorClock::default(),
            report: ProducerReport {
                skipped_files: skipped,
                ..Default::default()
            },
            max_points: usize::MAX,
            frame_id: None,
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
            Frames::Packets(_) => &NO_FRAME,
        }
    }

    /// Moves to the frame of the next message (the first call stays on the first frame).
    fn advance(&mut self) {
        if self.sequence == 0 {
            return;
        }
        match &mut self.frames {
            Frames::Loaded(f) => self.last = (self.last + 1) % f.len(),
            Frames::Streamed(stream) => stream.advance(&mut self.report.skipped_files),
            Frames::Packets(_) => {}
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

    /// Builds the next message's header; `now_ns` is its production stamp (monotonic),
    /// the sensor time is the scan's own (see `SensorClock`).
    pub fn next_scan(&mut self, now_ns: u64) -> Outgoing {
        self.advance();
        let seq = self.sequence;
        let recorded = self.frame().stamp_ns;
        let sensor_time = self.clock.stamp(recorded, wall_clock_ns());
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
            sensor_timestamp_ns: sensor_time,
            source_index: frame.index,
            frame_id: FrameId::new(frame.frame_id.as_deref().unwrap_or("")),
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

    /// Publishes the next scan of a packet source, if one is complete: its returns counted,
    /// a sample of exactly that size loaned and the packets decoded straight into it. The
    /// header's production stamp is the receipt of the scan's last packet, so the
    /// consumer's "last packet to scan published" row is the decoding's latency.
    fn publish_packets(&mut self, out: &mut Outbox) -> anyhow::Result<()> {
        let Frames::Packets(stream) = &mut self.frames else {
            return Ok(());
        };
        let Some(scan) = stream.next_scan() else {
            return Ok(());
        };
        let len = stream.count(&scan);
        if len == 0 || len > self.max_points {
            if len > 0 {
                warn!(
                    points = len,
                    max_points = self.max_points,
                    "scan from packets skipped: more points than max_points"
                );
            }
            stream.count_skipped();
            stream.recycle(scan);
            return Ok(());
        }
        let seq = self.sequence;
        let sensor_time = self.clock.stamp(scan.stamp_ns(), wall_clock_ns());
        let mut header = ScanHeader {
            point_count: len as u32,
            sequence: seq,
            producer_epoch: self.epoch,
            sensor_timestamp_ns: sensor_time,
            source_index: seq,
            source: ScanSource::PACKETS,
            frame_id: FrameId::new(self.frame_id.as_deref().unwrap_or("")),
            ..ScanHeader::default()
        };
        header.stamps.produced_ns = scan.completed_at_ns;
        let Frames::Packets(stream) = &self.frames else {
            return Ok(());
        };
        let reached =
            out.send_scan_filled(len, |points| stream.decode_into(&scan, points), header)?;
        if let Frames::Packets(stream) = &self.frames {
            stream.recycle(scan);
        }
        match reached {
            Some(0) => self.count_unreceived(),
            Some(_) => {}
            None => anyhow::bail!("a scan decoded to another number of points than counted"),
        }
        self.sequence += 1;
        self.report.published += 1;
        Ok(())
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

impl Stage for ProducerStage {
    const NAME: &'static str = "producer";
    const WIRING: Wiring = Wiring {
        wakes_on: None,
        reads: &[],
        publishes: Some(Topic::Scans),
        parallel: false,
        unique: true,
    };
    type Report = ProducerReport;

    fn process(&mut self, _: Input<'_>, now_ns: u64, out: &mut Outbox) -> anyhow::Result<()> {
        if matches!(self.frames, Frames::Packets(_)) {
            return self.publish_packets(out);
        }
        let next = self.next_scan(now_ns);
        // The only copy of the scan on the hot path: from the "driver" into shared memory.
        let reached = out.send_scan(next.len, |i| self.point(&next, i), next.header)?;
        if reached == 0 {
            self.count_unreceived();
        }
        Ok(())
    }

    fn done(&self) -> bool {
        let ended = matches!(&self.frames, Frames::Packets(p) if p.ended());
        ended || self.pace.count.is_some_and(|c| self.report.published >= c)
    }

    /// A recording replays at its recorded rate unless a rate is asked for.
    fn period(&self) -> Duration {
        let gap = if self.pace.recorded {
            self.recorded_gap().or(self.pace.period)
        } else {
            self.pace.period
        };
        gap.unwrap_or_default()
    }

    fn log_state(&self) {
        let r = &self.report;
        if let Frames::Packets(p) = &self.frames {
            // A live sensor's health: packets lost (azimuth or column gaps), late, refused.
            let k = p.report();
            info!(
                published = r.published,
                unreceived = r.unreceived,
                packets = k.packets.counters.packets,
                lost = k.packets.counters.lost,
                out_of_order = k.packets.counters.out_of_order,
                refused = k.packets.refused.values().sum::<u64>(),
                scans_skipped = k.scans_skipped,
                "producer state"
            );
            return;
        }
        info!(
            published = r.published,
            unreceived = r.unreceived,
            "producer state"
        );
    }

    fn stop(mut self, _: &Inputs) -> anyhow::Result<ProducerReport> {
        if let Frames::Packets(p) = &self.frames {
            let r = p.report();
            info!(
                packets = r.packets.counters.packets,
                lost = r.packets.counters.lost,
                out_of_order = r.packets.counters.out_of_order,
                refused = r.packets.refused.values().sum::<u64>(),
                scans_skipped = r.scans_skipped,
                "packets"
            );
            self.report.packets = Some(r);
        }
        if self.done() && !self.pace.linger.is_zero() {
            info!(
                published = self.report.published,
                "all scans out: staying until the subscribers have read them (or stopped)"
            );
            signals::sleep(self.pace.linger);
        }
        let r = self.report;
        info!(
            published = r.published,
            unreceived = r.unreceived,
            malformed = r.malformed,
            skipped_files = r.skipped_files.len(),
            "producer stopped"
        );
        Ok(r)
    }
}

/// Runs the producer until `count` scans are out or a termination signal arrives.
pub fn run(cfg: &ServiceConfig, opts: &ProducerOptions) -> anyhow::Result<ProducerReport> {
    if let Some(r) = opts.rate_hz {
        crate::config::check_rate("--rate", r)?;
    }
    crate::stage::run(cfg, || {
        let (frames, skipped) = Frames::load(&opts.source, cfg.max_points)?;
        let mut stage = ProducerStage::new(frames, skipped, opts.malformed_every);
        stage.max_points = cfg.max_points;
        if let Source::Packets(p) = &opts.source {
            // The packets set the pace; scans are taken as they complete.
            stage.frame_id = Some(p.sensor.frame_id().into());
            stage.pace = Pace {
                count: opts.count,
                linger: opts.linger,
                period: None,
                recorded: false,
            };
            info!("producer ready: scans from packets");
            return Ok(stage);
        }
        let rate = opts.rate_hz.unwrap_or(cfg.rate_hz);
        stage.pace = Pace {
            count: opts.count,
            linger: opts.linger,
            period: (rate > 0.0).then(|| Duration::from_secs_f64(1.0 / rate)),
            recorded: opts.rate_hz.is_none() && matches!(opts.source, Source::Recording(..)),
        };
        info!(
            frames_in_memory = stage.frames().loaded(),
            recorded_rate = stage.pace.recorded,
            skipped_files = stage.report().skipped_files.len(),
            rate_hz = rate,
            "producer ready"
        );
        Ok(stage)
    })
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
        assert_eq!(frames.loaded(), 2, "the frame published and the next");
        let mut stage = ProducerStage::new(frames, skipped, None);
        let mut order = Vec::new();
        let t0 = 1_700_000_000_000_000_000u64;
        for k in 0..7 {
            let out = stage.next_scan(k);
            order.push(out.header.source_index);
            // The recorded stamps and frame, kept exactly on the first pass; the loop
            // carries on 100 ms after the last (time never runs back).
            assert_eq!(out.header.sensor_timestamp_ns, t0 + k * 100_000_000);
            assert_eq!(out.header.frame_id.get(), Some("os_lidar"));
            assert_eq!(out.len, out.header.point_count as usize);
            if out.header.source_index < 2 {
                assert_eq!(stage.recorded_gap(), Some(Duration::from_millis(100)));
            }
        }
        assert_eq!(order, [0, 1, 2, 0, 1, 2, 0]);
        // Message 1 holds two NaN placeholders: left out of the published points.
        let (frames, _) = Frames::load(&Source::Recording(recording(), None), 10_000).unwrap();
        let mut stage = ProducerStage::new(frames, Vec::new(), None);
        let lens: Vec<usize> = (0..3).map(|k| stage.next_scan(k).len).collect();
        assert_eq!(lens, [1286, 1284, 1286]);
        let out = stage.next_scan(3);
        let p = stage.point(&out, 0);
        assert!(p.x.is_finite());
    }

    /// A folder streams too: frames in order, looped, poses kept, a bad file counted once
    /// however often the loop passes it, never more than a few frames in memory.
    #[test]
    fn a_folder_is_streamed_in_a_loop_a_few_frames_ahead() {
        let dir = tempfile::tempdir().unwrap();
        for k in 0..20 {
            let pts = vec![Point::new(k as f32 + 3.0, 0.0, -1.7); 10];
            groundwork_io::write_kitti_bin(&dir.path().join(format!("{k:06}.bin")), &pts).unwrap();
        }
        std::fs::write(dir.path().join("000007.bin"), [0u8; 5]).unwrap();
        let (frames, skipped) =
            Frames::load(&Source::Sequence(dir.path().to_path_buf()), 100).unwrap();
        let mut stage = ProducerStage::new(frames, skipped, None);
        let mut order = Vec::new();
        for k in 0..45 {
            let out = stage.next_scan(k);
            order.push(out.header.source_index);
            assert_eq!(stage.point(&out, 0).x, out.header.source_index as f32 + 3.0);
            assert!(stage.frames().loaded() <= 2);
        }
        let pass: Vec<u64> = (0..20).filter(|&k| k != 7).collect();
        let expected: Vec<u64> = pass
            .iter()
            .chain(&pass)
            .chain(&pass)
            .copied()
            .take(45)
            .collect();
        assert_eq!(order, expected);
        assert_eq!(
            stage.report().skipped_files.len(),
            1,
            "counted on the first pass only"
        );
    }

    #[test]
    fn scans_without_a_time_get_the_wall_clock_and_loops_never_run_back() {
        let mut c = SensorClock::default();
        assert_eq!(c.stamp(None, 5), 5);
        let mut c = SensorClock::default();
        // A recording at 20 Hz with a pause of 3 s, looped twice.
        let rec = [1_000, 1_050, 1_100, 4_100].map(|ms| ms * 1_000_000);
        let got: Vec<u64> = (0..8)
            .map(|k| c.stamp(Some(rec[k % 4]), 0) / 1_000_000)
            .collect();
        // The pause is kept; the loop restarts one (capped, 1 s) gap after the end.
        assert_eq!(
            got,
            [1_000, 1_050, 1_100, 4_100, 5_100, 5_150, 5_200, 8_200]
        );
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
