//! The consumer stage: reads scans and masks in place, pairs them by sequence number, and
//! reports latency per stage and end to end, live accuracy when labels are available, and
//! where every scan it saw ended.
//!
//! [`ConsumerStage`] does the pairing, accounting, scoring and output with no IPC;
//! [`Consumer`] is the stage the service runs ([`run`]): that, plus when to stop, the CPU
//! time per scan of every stage, and the report.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use groundwork_io::{Confusion, Metrics, Protocol};
use groundwork_io::{LabelClass, LabelMap, OutputTarget, Scan};
use groundwork_msg::{MaskHeader, MaskStatus, ProposalsHeader, ScanHeader, ScanPoint, ScanSource};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::ServiceConfig;
use crate::cpu::CpuSnapshot;
use crate::segmenter::sequence_gap;
use crate::signals;
use crate::stage::{Input, Inputs, Outbox, Stage, Topic, Wiring};
use crate::stats::{LatencyStats, Percentiles};
use crate::window::ScanWindow;

/// Consumer options beyond the shared configuration.
#[derive(Debug, Clone, Default)]
pub struct ConsumerOptions {
    /// Stop after this many masks.
    pub count: Option<u64>,
    /// Stop when no mask arrived for this long (after the first one).
    pub idle_timeout: Option<Duration>,
    /// Sequence folder with `labels/<index>.label` for live accuracy (gmm protocol).
    pub labels: Option<PathBuf>,
    /// Write `<index>.prob` / `<index>.ground` into this folder, or, for a path ending in
    /// `.mcap`, every segmented scan into one recording (PointCloud2 with a
    /// `ground_probability` field, topic [`RECORDING_TOPIC`]).
    pub out: Option<PathBuf>,
    /// Write the final report as JSON here.
    pub report_json: Option<PathBuf>,
    /// Fault test: after this many masks, stop reading for `stall`.
    pub stall_after: Option<u64>,
    /// How long to stall.
    pub stall: Duration,
    /// Segmented masks left out of the latency figures at the start.
    pub warmup: u64,
    /// The sensor's mount: a recording places the scan frame on the ground frame by it.
    pub mount: Option<groundwork_core::config::MountConfig>,
}

/// Where each scan the producer published to this consumer ended: exactly one bucket per
/// scan, so the four add up to what the producer published while the consumer listened.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct ScanFate {
    /// Read, and its mask (segmented) arrived.
    pub masked: u64,
    /// Read, and its mask arrived saying the segmenter rejected it.
    pub rejected: u64,
    /// Read, but no mask arrived for it: no segmenter was running, it died with the scan
    /// in its queue, its queue overflowed, or the mask was lost in this consumer's queue
    /// (`dropped_masks` counts those). Decided at exit, or when the scan falls out of the
    /// pairing window.
    pub unanswered: u64,
    /// Never read: lost in this consumer's full scan queue (a gap in sequence numbers).
    pub dropped: u64,
}

impl ScanFate {
    /// Scans accounted for.
    pub fn total(&self) -> u64 {
        self.masked + self.rejected + self.unanswered + self.dropped
    }
}

/// Proposals messages read from the detector stage.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct DetectionsSeen {
    /// Messages (one per detected scan).
    pub messages: u64,
    /// Proposals in them.
    pub proposals: u64,
    /// Proposals the detector left out for the message's capacity.
    pub dropped_proposals: u64,
    /// Distinct detector runs seen (a restarted detector is a new run).
    pub detector_runs: u64,
}

/// The consumer's final report.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ConsumerReport {
    /// Scans read.
    pub scans: u64,
    /// Masks read (any status).
    pub masks: u64,
    /// Masks of segmented scans.
    pub segmented: u64,
    /// Masks that reported a rejected scan, by reason.
    pub rejected: BTreeMap<String, u64>,
    /// Where every scan ended (the four buckets add up).
    pub scan_fate: ScanFate,
    /// Scans lost before this consumer read them (sequence gaps) = `scan_fate.dropped`.
    pub dropped_scans: u64,
    /// Masks lost before this consumer read them: gaps in one segmenter run's mask
    /// sequence. (Scans the segmenter itself never received have no mask to lose: they are
    /// `scan_fate.unanswered`, and the segmenter's own `dropped`.)
    pub dropped_masks: u64,
    /// Masks whose scan this consumer never saw (dropped, or outside the pairing window).
    pub unmatched_masks: u64,
    /// Distinct segmenter runs seen (a restarted segmenter is a new run).
    pub segmenter_runs: u64,
    /// Points the segmenter found beyond its coordinate bound (corrupted returns).
    pub out_of_bounds_points: u64,
    /// What the detector stage published (zero without one).
    pub detections: DetectionsSeen,
    /// Latency percentiles per stage, µs.
    pub latency_us: Vec<Percentiles>,
    /// Pooled live accuracy over labeled scans.
    pub accuracy: Option<Metrics>,
    /// Scans written to the output (`--out`).
    pub writes: u64,
    /// Scans that could not be written to the output (a full disk, a scan no longer
    /// held), and a recording that could not be closed: any makes the consumer exit 1.
    pub write_failures: u64,
    /// Wall time from first to last mask, s.
    pub seconds: f64,
    /// CPU time (user + system) per segmented scan of each stage's process, ms, from the
    /// first mask to the end (a restarted stage is left out).
    pub cpu_ms_per_scan: BTreeMap<String, f64>,
}

/// Scans remembered for pairing; older ones count as unanswered.
pub const PAIRING_WINDOW: usize = 256;
/// Label files kept in memory (a replay loops over a few; a long drive never repeats).
const LABEL_CACHE: usize = 32;
/// Scans whose points are held for a recording until their mask comes.
pub const RECORDING_WINDOW: usize = crate::window::SCAN_WINDOW;
/// The topic of the consumer's recording.
pub const RECORDING_TOPIC: &str = "/points";
/// The topic of the proposals' boxes in the consumer's recording (`foxglove.SceneUpdate`).
pub const PROPOSALS_RECORDING_TOPIC: &str = "/proposals";

/// The consumer stage: pairing, accounting, latency, accuracy, outputs. No IPC.
#[derive(Debug, Default)]
pub struct ConsumerStage {
    labels_dir: Option<PathBuf>,
    out: Option<OutputTarget>,
    /// Recording only: (producer epoch, sequence) → the points of a scan waiting for its
    /// mask, at most [`RECORDING_WINDOW`].
    held: ScanWindow,
    warmup: u64,
    /// Scans seen and not yet answered: (producer epoch, sequence) → source index.
    pending: BTreeMap<(u64, u64), (u64, ScanSource)>,
    last_scan: Option<(u64, u64)>,
    /// (segmenter epoch, mask sequence) of the last mask.
    last_mask: Option<(u64, u64)>,
    /// Wall-clock ns since which this consumer's subscriber exists: a producer run that
    /// began later published every one of its scans to it, from sequence 0.
    listening_since: u64,
    segmenter_epochs: HashSet<u64>,
    detector_epochs: HashSet<u64>,
    labels: HashMap<u64, Option<Vec<LabelClass>>>,
    label_map: LabelMap,
    label_order: VecDeque<u64>,
    confusion: Option<Confusion>,
    stats: LatencyStats,
    report: ConsumerReport,
}

impl ConsumerStage {
    /// A stage scoring against `labels` (a sequence folder: its labels are found where
    /// every command finds them, [`groundwork_io::label_folder`]) and writing to `out`.
    pub fn new(labels: Option<PathBuf>, out: Option<OutputTarget>, warmup: u64) -> Self {
        Self {
            labels_dir: labels.and_then(|d| groundwork_io::label_folder(&d)),
            out,
            warmup,
            listening_since: u64::MAX,
            ..Default::default()
        }
    }

    /// Tells the stage when its subscriber started listening (wall-clock ns, as producer
    /// epochs are): scans of a later producer run lost before the first one read count as
    /// dropped too. (Unset: a run's scans count from the first one read.)
    pub fn listening_since(&mut self, wall_ns: u64) {
        self.listening_since = wall_ns;
    }

    /// A scan was read (its points are copied only when writing a recording).
    pub fn on_scan(&mut self, h: &ScanHeader, points: &[ScanPoint]) {
        if let Some(OutputTarget::Recording(_)) = &self.out {
            self.held.hold(h.producer_epoch, h.sequence, points);
        }
        let r = &mut self.report;
        r.scans += 1;
        match self.last_scan {
            Some((e, s)) if e == h.producer_epoch => {
                r.scan_fate.dropped += sequence_gap(s, h.sequence);
            }
            // The first scan read of a run that started while we listened: the scans
            // before it (sequence 0 on) were published to us and lost in our queue.
            _ if h.producer_epoch >= self.listening_since => r.scan_fate.dropped += h.sequence,
            _ => {}
        }
        self.last_scan = Some((h.producer_epoch, h.sequence));
        let key = (h.producer_epoch, h.sequence);
        if self
            .pending
            .insert(key, (h.source_index, h.source))
            .is_some()
        {
            // The same scan twice (a misbehaving producer): the earlier copy is unanswered.
            r.scan_fate.unanswered += 1;
        }
        if self.pending.len() > PAIRING_WINDOW {
            self.pending.pop_first();
            r.scan_fate.unanswered += 1;
        }
    }

    /// A mask was read at `received_ns` (monotonic).
    pub fn on_mask(&mut self, h: &MaskHeader, probs: &[f32], received_ns: u64) {
        let r = &mut self.report;
        r.masks += 1;
        if let Some((g, s)) = self.last_mask
            && g == h.segmenter_epoch
        {
            r.dropped_masks += sequence_gap(s, h.mask_sequence);
        }
        self.last_mask = Some((h.segmenter_epoch, h.mask_sequence));
        if self.segmenter_epochs.insert(h.segmenter_epoch) {
            r.segmenter_runs += 1;
        }
        let ok = h.status == MaskStatus::OK;
        let held = self.held.take(h.producer_epoch, h.scan_sequence);
        let paired = self.pending.remove(&(h.producer_epoch, h.scan_sequence));
        match paired {
            Some(_) if ok => r.scan_fate.masked += 1,
            Some(_) => r.scan_fate.rejected += 1,
            None => r.unmatched_masks += 1,
        }
        if !ok {
            *r.rejected.entry(h.status.name().to_string()).or_default() += 1;
            return;
        }
        r.segmented += 1;
        r.out_of_bounds_points += u64::from(h.out_of_bounds_points);
        if r.segmented > self.warmup {
            let s = h.stamps;
            let source = paired.map_or(ScanSource::PRODUCER, |(_, source)| source);
            self.stats.record(
                source,
                s.produced_ns,
                s.published_ns,
                s.segmenter_received_ns,
                s.segmenter_published_ns,
                received_ns,
            );
        }
        if probs.len() != h.point_count as usize {
            warn!(
                sequence = h.scan_sequence,
                "mask header says {} points, payload has {}",
                h.point_count,
                probs.len()
            );
            return;
        }
        if self.labels_dir.is_some() {
            self.score(h.source_index, probs);
        }
        let written = match &mut self.out {
            None => Ok(()),
            Some(OutputTarget::Files(dir)) => {
                let stem = format!("{:06}", h.source_index);
                groundwork_io::write_outputs(dir, &stem, probs, 0.5).map_err(|e| e.to_string())
            }
            Some(OutputTarget::Recording(writer)) => match held {
                Some(points) if points.len() == probs.len() => {
                    let mut scan = Scan::dense(points);
                    scan.stamp_ns = Some(h.sensor_timestamp_ns);
                    scan.frame_id = h.frame_id.get().map(str::to_string);
                    writer
                        .write(RECORDING_TOPIC, &scan, probs, h.sensor_timestamp_ns)
                        .map_err(|e| e.to_string())
                }
                Some(points) => Err(format!(
                    "scan {} has {} points, its mask {}: not recorded",
                    h.scan_sequence,
                    points.len(),
                    probs.len()
                )),
                None => Err(format!(
                    "scan {} is no longer held (unseen, or more than {RECORDING_WINDOW} scans \
                     ago): not recorded",
                    h.scan_sequence
                )),
            },
        };
        match written {
            Ok(()) if self.out.is_some() => self.report.writes += 1,
            Ok(()) => {}
            Err(e) => {
                self.report.write_failures += 1;
                warn!("{e}");
            }
        }
    }

    /// A proposals message was read: counted, its stamps give the detector's latency, and
    /// a recording gets its boxes beside the scan's points, at the scan's stamp.
    pub fn on_proposals(&mut self, h: &ProposalsHeader) {
        if let Some(OutputTarget::Recording(writer)) = &mut self.out {
            let stamp = h.sensor_timestamp_ns;
            let boxes = crate::scene::proposals(h, stamp);
            if let Err(e) = writer.write_foxglove(PROPOSALS_RECORDING_TOPIC, &boxes, stamp) {
                self.report.write_failures += 1;
                warn!("{e}");
            }
        }
        let d = &mut self.report.detections;
        d.messages += 1;
        d.proposals += u64::from(h.proposal_count);
        d.dropped_proposals += u64::from(h.dropped_proposals);
        if self.detector_epochs.insert(h.detector_epoch) {
            d.detector_runs += 1;
        }
        if d.messages > self.warmup {
            let s = h.stamps;
            self.stats.record_proposals(
                s.produced_ns,
                s.segmenter_published_ns,
                h.detector_received_ns,
                h.detector_published_ns,
            );
        }
    }

    fn score(&mut self, index: u64, probs: &[f32]) {
        let Some(dir) = &self.labels_dir else {
            return;
        };
        if let std::collections::hash_map::Entry::Vacant(slot) = self.labels.entry(index) {
            let p = dir.join(format!("{index:06}.label"));
            let l = p
                .is_file()
                .then(|| self.label_map.read(&p, probs.len()))
                .transpose()
                .unwrap_or_else(|e| {
                    warn!("{e}");
                    None
                });
            slot.insert(l);
            self.label_order.push_back(index);
            if self.label_order.len() > LABEL_CACHE
                && let Some(old) = self.label_order.pop_front()
            {
                self.labels.remove(&old);
            }
        }
        if let Some(Some(l)) = self.labels.get(&index)
            && l.len() == probs.len()
        {
            let c = Confusion::from_predictions(probs, l, Protocol::Gmm, 0.5);
            self.confusion
                .get_or_insert_with(Confusion::default)
                .merge(&c);
        }
    }

    /// Label files held in memory (bounded).
    pub fn cached_labels(&self) -> usize {
        self.labels.len()
    }

    /// The counters so far (scans still pending are not yet in a bucket).
    pub fn report(&self) -> &ConsumerReport {
        &self.report
    }

    /// Latency percentiles so far.
    pub fn stats(&self) -> &LatencyStats {
        &self.stats
    }

    /// Ends the run: scans still waiting for a mask are unanswered; a recording is closed.
    pub fn finish(mut self, seconds: f64) -> ConsumerReport {
        if let Some(OutputTarget::Recording(writer)) = self.out.take() {
            match writer.finish_unless_empty() {
                Ok(true) => {}
                // An earlier recording at the path is worth more than an empty one.
                Ok(false) => warn!("no scan was recorded: no recording written"),
                Err(e) => {
                    self.report.write_failures += 1;
                    warn!("{e}");
                }
            }
        }
        self.report.scan_fate.unanswered += self.pending.len() as u64;
        self.report.dropped_scans = self.report.scan_fate.dropped;
        self.report.latency_us = self.stats.percentiles();
        self.report.accuracy = self.confusion.map(|c| c.metrics());
        self.report.seconds = seconds;
        self.report
    }

    fn log_state(&self) {
        let r = &self.report;
        let p = self.stats.percentiles();
        info!(
            masks = r.masks,
            segmented = r.segmented,
            dropped_scans = r.scan_fate.dropped,
            dropped_masks = r.dropped_masks,
            rejected = r.rejected.values().sum::<u64>(),
            pending = self.pending.len(),
            e2e_p50_us = p
                .iter()
                .find(|p| p.stage == "end to end")
                .map_or(0.0, |p| p.p50),
            iou = self.confusion.map(|c| c.metrics().iou_ground),
            "consumer state"
        );
    }
}

/// One line a newcomer can read: healthy or not, and why; the headline latencies in ms.
pub fn verdict(r: &ConsumerReport) -> String {
    let f = r.scan_fate;
    let mut problems = Vec::new();
    for (n, what) in [
        (f.rejected, "rejected"),
        (f.unanswered, "unanswered"),
        (f.dropped, "dropped on the way"),
        (r.dropped_masks, "masks lost"),
        (r.write_failures, "writes failed"),
    ] {
        if n > 0 {
            problems.push(format!("{n} {what}"));
        }
    }
    let ms = |stage: &str| {
        r.latency_us
            .iter()
            .find(|p| p.stage == stage && p.count > 0)
            .map(|p| (p.p50 / 1e3, p.p99 / 1e3))
    };
    let mut s = if f.total() == 0 {
        "verdict: NOT healthy: no scan arrived".to_string()
    } else if problems.is_empty() {
        format!(
            "verdict: healthy: every scan masked ({} of {}), nothing dropped",
            f.masked,
            f.total()
        )
    } else {
        format!(
            "verdict: NOT healthy: {} of {} scans masked; {}",
            f.masked,
            f.total(),
            problems.join(", ")
        )
    };
    if let Some((p50, p99)) = ms("end to end") {
        s.push_str(&format!("; end to end {p50:.1} ms median, {p99:.1} ms p99"));
    }
    if let Some((p50, _)) = ms("segment") {
        s.push_str(&format!(", segmenting {p50:.1} ms median"));
    }
    if let Some(m) = r.accuracy {
        s.push_str(&format!(
            "; ground IoU {:.2} on the labeled scans",
            m.iou_ground
        ));
    }
    s.push('\n');
    s
}

/// The report as a person reads it: the verdict, then the details.
pub fn summary(r: &ConsumerReport, stats: &str) -> String {
    let f = r.scan_fate;
    let reasons: Vec<String> = r.rejected.iter().map(|(k, n)| format!("{k} {n}")).collect();
    let reasons = if reasons.is_empty() {
        String::new()
    } else {
        format!(": {}", reasons.join(", "))
    };
    let mut s = verdict(r);
    s += &format!(
        "consumer: {} masks ({} segmented, {} rejected{}), {} scans; scan fate: {} masked + {} rejected + {} unanswered + {} dropped = {}; dropped masks {}, unmatched masks {}; {} segmenter run(s)\n",
        r.masks,
        r.segmented,
        r.rejected.values().sum::<u64>(),
        reasons,
        r.scans,
        f.masked,
        f.rejected,
        f.unanswered,
        f.dropped,
        f.total(),
        r.dropped_masks,
        r.unmatched_masks,
        r.segmenter_runs
    );
    if r.writes + r.write_failures > 0 {
        s.push_str(&format!(
            "outputs: {} scans written, {} writes failed\n",
            r.writes, r.write_failures
        ));
    }
    let d = r.detections;
    if d.messages > 0 {
        s.push_str(&format!(
            "detector: {} proposals messages, {} proposals ({} left out for capacity), {} detector run(s)\n",
            d.messages, d.proposals, d.dropped_proposals, d.detector_runs
        ));
    }
    s.push_str(stats);
    if !r.cpu_ms_per_scan.is_empty() {
        let per: Vec<String> = r
            .cpu_ms_per_scan
            .iter()
            .map(|(stage, ms)| format!("{stage} {ms:.2}"))
            .collect();
        s.push_str(&format!("CPU per scan, ms: {}\n", per.join(", ")));
    }
    if let Some(m) = r.accuracy {
        s.push_str(&format!(
            "live accuracy (gmm protocol, labeled scans): precision {:.2} recall {:.2} F1 {:.2} ground IoU {:.2}\n",
            m.precision, m.recall, m.f1, m.iou_ground
        ));
    }
    s
}

/// How long a consumer with an idle timeout waits for its first mask.
const FIRST_MASK_WAIT: Duration = Duration::from_secs(30);

/// The consumer as the service runs it: the stage, when to stop, and what each stage's
/// process costs.
#[derive(Debug)]
pub struct Consumer {
    /// The report's file, claimed at the start.
    files: groundwork_io::OutputFiles,
    stage: ConsumerStage,
    opts: ConsumerOptions,
    cfg: ServiceConfig,
    /// When the first mask came.
    first: Option<Instant>,
    /// When the last mask came.
    last_mask: Instant,
    /// Each stage's CPU time at the first mask, and the scans segmented by then.
    cpu_start: Option<(CpuSnapshot, u64)>,
    stalled: bool,
}

impl Consumer {
    /// A consumer of `cfg`'s pipeline; its output (if any) is created here, so that a bad
    /// `--out` fails before anything runs.
    pub fn new(cfg: &ServiceConfig, opts: &ConsumerOptions) -> anyhow::Result<Self> {
        // The report through the one output path: never the labels read, never the
        // recording written, never half-written.
        let mut files =
            groundwork_io::OutputFiles::new(&opts.labels.iter().cloned().collect::<Vec<_>>());
        if let Some(out) = opts.out.as_deref().filter(|o| !o.is_dir()) {
            files.claim(out)?;
        }
        if let Some(report) = &opts.report_json {
            files.claim(report)?;
        }
        let mut output = opts
            .out
            .as_deref()
            .map(|o| OutputTarget::create(o, &[]))
            .transpose()?;
        if let (Some(OutputTarget::Recording(w)), Some(mount)) = (&mut output, &opts.mount) {
            w.set_mount(groundwork_io::transform::StaticTransform::of_mount(mount)?);
        }
        Ok(Self {
            files,
            stage: ConsumerStage::new(opts.labels.clone(), output, opts.warmup),
            opts: opts.clone(),
            cfg: cfg.clone(),
            first: None,
            last_mask: Instant::now(),
            cpu_start: None,
            stalled: false,
        })
    }

    /// One message read: one that woke the consumer, one read beside it, or one still
    /// queued at the end.
    fn see(&mut self, input: Input<'_>, received_ns: u64) {
        match input {
            Input::Scan(h, points) => self.stage.on_scan(h, points),
            Input::Proposals(h, _) => self.stage.on_proposals(h),
            Input::Mask(h, probabilities) => {
                self.stage.on_mask(h, probabilities, received_ns);
                self.last_mask = Instant::now();
                self.first.get_or_insert(self.last_mask);
                if self.cpu_start.is_none() {
                    self.cpu_start =
                        Some((CpuSnapshot::take(&self.cfg), self.stage.report().segmented));
                }
            }
            Input::Tick => {}
        }
    }
}

impl Stage for Consumer {
    const NAME: &'static str = "consumer";
    // Only masks wake the consumer: it reads the scans it pairs them with from its queue at
    // that moment. Waking on scans as well would put a third process on the CPU exactly
    // when the segmenter needs it, and cost the pipeline latency. Proposals (if a detector
    // runs) are read then too; their latency comes from their own stamps.
    const WIRING: Wiring = Wiring {
        wakes_on: Some(Topic::Masks),
        reads: &[Topic::Scans, Topic::Proposals],
        publishes: None,
        parallel: false,
        unique: false,
    };
    type Report = ConsumerReport;

    fn start(&mut self) -> anyhow::Result<()> {
        // The subscribers exist from here on.
        self.stage.listening_since(groundwork_msg::new_epoch());
        Ok(())
    }

    /// A mask is stamped the moment it is taken, before the scans it answers are read
    /// (they were published earlier, so they are queued by now).
    fn process(
        &mut self,
        input: Input<'_>,
        received_ns: u64,
        _: &mut Outbox,
    ) -> anyhow::Result<()> {
        self.see(input, received_ns);
        Ok(())
    }

    fn done(&self) -> bool {
        self.opts
            .count
            .is_some_and(|c| self.stage.report().masks >= c)
    }

    fn before_wait(&mut self) -> bool {
        if let (Some(t), Some(_)) = (self.opts.idle_timeout, self.first)
            && self.last_mask.elapsed() > t
        {
            info!("no mask for {t:?}: stopping");
            return false;
        }
        // Before the first mask the stages may still be starting: a longer wait, but not
        // forever (a consumer restarted after the producer's last scan would wait for ever).
        if let (Some(t), None) = (self.opts.idle_timeout, self.first)
            && self.last_mask.elapsed() > t.max(FIRST_MASK_WAIT)
        {
            warn!(
                "no mask in the first {:?}: stopping",
                t.max(FIRST_MASK_WAIT)
            );
            return false;
        }
        if let Some(after) = self.opts.stall_after
            && !self.stalled
            && self.stage.report().masks >= after
        {
            self.stalled = true;
            info!(
                seconds = self.opts.stall.as_secs_f64(),
                "stalling: not reading"
            );
            if !signals::sleep(self.opts.stall) {
                return false;
            }
            info!("resuming");
        }
        true
    }

    fn log_state(&self) {
        self.stage.log_state();
    }

    fn stop(mut self, rest: &Inputs) -> anyhow::Result<ConsumerReport> {
        // Scans already queued are seen, so that they count (as unanswered if no mask came).
        rest.read(Topic::Scans, |input, at| {
            self.see(input, at);
            Ok(())
        })?;
        // The detector answers a mask after we have read it: with a detector running, its
        // last proposals get a moment (until 200 ms pass without one, 1 s at most), so that
        // the report counts what it published.
        let (since, mut last) = (Instant::now(), Instant::now());
        while self.stage.report().detections.messages > 0
            && since.elapsed() < Duration::from_secs(1)
            && last.elapsed() < Duration::from_millis(200)
        {
            let read = rest.read(Topic::Proposals, |input, at| {
                self.see(input, at);
                Ok(())
            })?;
            if read > 0 {
                last = Instant::now();
            }
            if !signals::sleep(Duration::from_millis(10)) {
                break;
            }
        }
        let table = self.stage.stats().table();
        let cpu_end = CpuSnapshot::take(&self.cfg);
        let segmented = self.stage.report().segmented;
        let seconds = self.first.map_or(0.0, |f| f.elapsed().as_secs_f64());
        let mut report = self.stage.finish(seconds);
        if let Some((start, at)) = self.cpu_start {
            report.cpu_ms_per_scan = start.per_scan(&cpu_end, segmented.saturating_sub(at));
        }
        // The machine-readable report first: stdout may be a terminal that is gone (SIGHUP).
        if let Some(p) = &self.opts.report_json {
            let json = serde_json::to_string_pretty(&report)? + "\n";
            self.files.write(p, json.as_bytes())?;
        }
        let _ = std::io::stdout().write_all(summary(&report, &table).as_bytes());
        info!(
            masks = report.masks,
            masked = report.scan_fate.masked,
            rejected = report.scan_fate.rejected,
            unanswered = report.scan_fate.unanswered,
            dropped = report.scan_fate.dropped,
            "consumer stopped"
        );
        Ok(report)
    }
}

/// Runs the consumer until `count` masks, the idle timeout, or a termination signal.
pub fn run(cfg: &ServiceConfig, opts: &ConsumerOptions) -> anyhow::Result<ConsumerReport> {
    crate::stage::run(cfg, || Consumer::new(cfg, opts))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan(epoch: u64, seq: u64) -> ScanHeader {
        ScanHeader {
            producer_epoch: epoch,
            sequence: seq,
            source_index: seq,
            ..ScanHeader::default()
        }
    }

    /// The `m`-th mask of segmenter run `seg`, answering scan `seq` of producer run `epoch`.
    fn mask(seg: u64, m: u64, epoch: u64, seq: u64, status: MaskStatus) -> MaskHeader {
        MaskHeader {
            mask_sequence: m,
            segmenter_epoch: seg,
            producer_epoch: epoch,
            scan_sequence: seq,
            status,
            point_count: 0,
            ..MaskHeader::default()
        }
    }

    #[test]
    fn every_scan_ends_in_exactly_one_bucket() {
        let mut c = ConsumerStage::new(None, None, 0);
        // Producer run 1: scans 0..10; scans 3 and 4 never reach us (queue overflow).
        for s in (0..10).filter(|s| ![3, 4].contains(s)) {
            c.on_scan(&scan(1, s), &[]);
        }
        // Segmenter A answers 0..=5 (5 rejected), then dies with 6 and 7 in its queue; B
        // answers 8, and a mask for the dropped scan 3 arrives (unmatched).
        for (m, s) in [0, 1, 2, 5].into_iter().enumerate() {
            let st = if s == 5 {
                MaskStatus::EMPTY
            } else {
                MaskStatus::OK
            };
            c.on_mask(&mask(100, m as u64, 1, s, st), &[], 1);
        }
        c.on_mask(&mask(100, 4, 1, 3, MaskStatus::OK), &[], 1);
        c.on_mask(&mask(200, 0, 1, 8, MaskStatus::OK), &[], 1);
        // Producer run 2 starts over at sequence 0: not a gap.
        c.on_scan(&scan(2, 0), &[]);
        c.on_mask(&mask(200, 1, 2, 0, MaskStatus::OK), &[], 1);
        let r = c.finish(1.0);
        let f = r.scan_fate;
        assert_eq!((f.masked, f.rejected, f.dropped), (5, 1, 2), "{r:?}");
        // 6, 7 and 9 got no mask.
        assert_eq!(f.unanswered, 3, "{r:?}");
        assert_eq!(f.total(), 11, "10 + 1 scans published");
        assert_eq!(f.total() - f.dropped, r.scans);
        assert_eq!((r.unmatched_masks, r.segmenter_runs), (1, 2));
        assert_eq!(r.dropped_masks, 0);
    }

    #[test]
    fn masks_lost_are_told_from_scans_the_segmenter_never_got() {
        let mut c = ConsumerStage::new(None, None, 0);
        c.listening_since(1_000);
        // A producer run that began after we listened: its scans 0..3 were lost in our
        // queue before the first one we read (4); we read 4..10.
        for s in 4..10 {
            c.on_scan(&scan(2_000, s), &[]);
        }
        // The segmenter got only scans 4, 7 and 9 (it dropped the rest from its own
        // queue): three masks in a row, none lost, although their scans are not
        // consecutive. Then mask 3 (for no scan we hold) is lost and mask 4 arrives.
        for (m, s) in [(0, 4), (1, 7), (2, 9)] {
            c.on_mask(&mask(7, m, 2_000, s, MaskStatus::OK), &[], 1);
        }
        let r = c.report();
        assert_eq!(r.dropped_masks, 0, "{r:?}");
        c.on_mask(&mask(7, 4, 2_000, 11, MaskStatus::OK), &[], 1);
        let r = c.finish(1.0);
        assert_eq!(r.dropped_masks, 1);
        let f = r.scan_fate;
        assert_eq!((f.masked, f.dropped, f.unanswered), (3, 4, 3), "{r:?}");
        // Everything published up to the last scan read (0..10) is in one bucket.
        assert_eq!(f.total(), 10);
        // A run that began before we listened counts from its first scan read.
        let mut c = ConsumerStage::new(None, None, 0);
        c.listening_since(5_000);
        c.on_scan(&scan(2_000, 40), &[]);
        assert_eq!(c.finish(1.0).scan_fate.total(), 1);
    }

    #[test]
    fn sequence_arithmetic_never_overflows() {
        assert_eq!(sequence_gap(u64::MAX, 0), 0);
        assert_eq!(sequence_gap(0, u64::MAX), u64::MAX - 1);
        assert_eq!(sequence_gap(u64::MAX - 1, u64::MAX), 0);
        let mut c = ConsumerStage::new(None, None, 0);
        c.on_scan(&scan(1, u64::MAX), &[]);
        c.on_scan(&scan(1, 0), &[]);
        c.on_mask(&mask(1, u64::MAX, 1, u64::MAX, MaskStatus::OK), &[], 1);
        c.on_mask(&mask(1, 0, 1, 0, MaskStatus::OK), &[], 1);
        let r = c.finish(0.0);
        assert_eq!(
            (r.scan_fate.masked, r.dropped_scans, r.dropped_masks),
            (2, 0, 0)
        );
    }

    #[test]
    fn a_recording_holds_each_segmented_scan_with_its_probabilities() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("sub/out.mcap");
        let out = OutputTarget::create(&path, &[]).unwrap();
        let mut c = ConsumerStage::new(None, Some(out), 0);
        let points = |s: u64| {
            (0..3)
                .map(|i| ScanPoint {
                    x: s as f32,
                    y: i as f32,
                    z: -1.5,
                    intensity: 7.0,
                })
                .collect::<Vec<_>>()
        };
        let answer = |c: &mut ConsumerStage, s: u64, status: MaskStatus| {
            let mut m = mask(1, s, 1, s, status);
            m.point_count = 3;
            m.sensor_timestamp_ns = 1_000 + s;
            c.on_mask(&m, &[s as f32 / 8.0, 0.5, 1.0], 1);
        };
        // More scans than the window: the oldest ones are no longer held.
        for s in 0..(RECORDING_WINDOW as u64 + 4) {
            let mut h = scan(1, s);
            h.point_count = 3;
            c.on_scan(&h, &points(s));
        }
        answer(&mut c, 0, MaskStatus::OK); // not held any more: a write failure
        answer(&mut c, 5, MaskStatus::OK);
        answer(&mut c, 6, MaskStatus::EMPTY); // rejected: nothing to record
        answer(&mut c, 7, MaskStatus::OK);
        let r = c.finish(1.0);
        assert_eq!((r.segmented, r.write_failures), (3, 1), "{r:?}");

        let back: Vec<_> = groundwork_io::RecordingReader::open(&path, None, 100)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(back.len(), 2);
        for (b, s) in back.iter().zip([5u64, 7]) {
            assert_eq!(b.topic, RECORDING_TOPIC);
            assert_eq!(b.log_time_ns, 1_000 + s);
            assert_eq!(b.scan.stamp_ns, Some(1_000 + s));
            let want: Vec<_> = points(s).iter().map(groundwork_core::Point::from).collect();
            assert_eq!(b.scan.points, want);
        }
        let data = std::fs::read(&path).unwrap();
        let msg = mcap::MessageStream::new(&data)
            .unwrap()
            .nth(1)
            .unwrap()
            .unwrap();
        let probs =
            groundwork_io::pointcloud2::decode_probabilities(&path, &msg.data, 100).unwrap();
        assert_eq!(probs, [0.875, 0.5, 1.0]);
    }

    #[test]
    fn the_verdict_says_healthy_only_when_every_scan_was_masked() {
        let mut r = ConsumerReport::default();
        assert!(verdict(&r).contains("NOT healthy: no scan arrived"));
        r.scan_fate.masked = 60;
        r.latency_us = vec![crate::stats::Percentiles {
            stage: "end to end".into(),
            count: 60,
            p50: 12_340.0,
            p90: 0.0,
            p99: 15_900.0,
            p999: 0.0,
            max: 0.0,
        }];
        let v = verdict(&r);
        assert!(
            v.starts_with("verdict: healthy: every scan masked (60 of 60)"),
            "{v}"
        );
        assert!(v.contains("end to end 12.3 ms median, 15.9 ms p99"), "{v}");
        r.scan_fate.dropped = 2;
        r.write_failures = 1;
        let v = verdict(&r);
        assert!(
            v.contains("NOT healthy: 60 of 62 scans masked; 2 dropped on the way, 1 writes failed"),
            "{v}"
        );
    }

    #[test]
    fn the_pairing_window_and_the_label_cache_are_bounded() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::create_dir(tmp.path().join("labels")).unwrap();
        let mut c = ConsumerStage::new(Some(tmp.path().to_path_buf()), None, 0);
        for s in 0..(PAIRING_WINDOW as u64 + 50) {
            c.on_scan(&scan(1, s), &[]);
        }
        assert_eq!(c.report().scan_fate.unanswered, 50);
        for s in 0..1000u64 {
            let mut m = mask(1, s, 1, s, MaskStatus::OK);
            m.point_count = 1;
            m.source_index = s;
            c.on_mask(&m, &[0.5], 1);
        }
        assert!(c.cached_labels() <= LABEL_CACHE, "{}", c.cached_labels());
    }
}
