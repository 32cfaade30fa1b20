//! The consumer: reads scans and masks in place, pairs them by sequence number, and
//! reports latency per stage and end to end, live accuracy when labels are available, and
//! counters of dropped, unmatched and rejected messages.

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use groundwork_eval::{Confusion, Metrics, Protocol};
use groundwork_msg::{MaskStatus, monotonic_ns};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::{ServiceConfig, check_shared_memory};
use crate::stats::{LatencyStats, Percentiles};
use crate::transport;

/// Consumer options beyond the shared configuration.
#[derive(Debug, Clone, Default)]
pub struct ConsumerOptions {
    /// Stop after this many masks.
    pub count: Option<u64>,
    /// Stop when no mask arrived for this long (after the first one).
    pub idle_timeout: Option<Duration>,
    /// Sequence folder with `labels/<index>.label` for live accuracy (gmm protocol).
    pub labels: Option<PathBuf>,
    /// Write `<index>.prob` / `<index>.ground` here.
    pub out: Option<PathBuf>,
    /// Write the final report as JSON here.
    pub report_json: Option<PathBuf>,
    /// Fault test: after this many masks, stop reading for `stall`.
    pub stall_after: Option<u64>,
    /// How long to stall.
    pub stall: Duration,
    /// Segmented masks left out of the latency figures at the start.
    pub warmup: u64,
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
    /// Scans lost before this consumer read them (sequence gaps).
    pub dropped_scans: u64,
    /// Masks lost before this consumer read them (sequence gaps).
    pub dropped_masks: u64,
    /// Masks whose scan this consumer never saw.
    pub unmatched_masks: u64,
    /// Scans for which no mask arrived while they were remembered.
    pub unmatched_scans: u64,
    /// Distinct segmenter runs seen (a restarted segmenter is a new run).
    pub segmenter_runs: u64,
    /// Latency percentiles per stage, µs.
    pub latency_us: Vec<Percentiles>,
    /// Pooled live accuracy over labeled scans.
    pub accuracy: Option<Metrics>,
    /// Wall time from first to last mask, s.
    pub seconds: f64,
}

/// Scans remembered for pairing; older ones count as unmatched.
const PAIRING_WINDOW: usize = 256;

/// Runs the consumer until `count` masks, the idle timeout, or a termination signal.
pub fn run(cfg: &ServiceConfig, opts: &ConsumerOptions) -> anyhow::Result<ConsumerReport> {
    check_shared_memory(cfg)?;
    let node = transport::node(cfg, "consumer")?;
    let scans = transport::scan_service(&node, cfg)?;
    let masks = transport::mask_service(&node, cfg)?;
    let scan_sub = transport::scan_subscriber(&scans, cfg)?;
    let mask_sub = transport::mask_subscriber(&masks, cfg)?;
    let mask_listener = transport::event_listener(&node, cfg, "masks")?;
    // Only masks wake the consumer: it reads the scans it pairs them with from its queue at
    // that moment. Waking on scans as well would put a third process on the CPU exactly
    // when the segmenter needs it, and cost the pipeline latency. It blocks on the mask
    // listener itself (in one comparison here a WaitSet with an interval timer made the
    // mask hop some 10 µs slower at the median and 50 µs at p99).
    let interval = Duration::from_secs_f64(cfg.report_interval_s);
    let mut last_report = Instant::now();
    if let Some(out) = &opts.out {
        std::fs::create_dir_all(out)
            .with_context(|| format!("{}: cannot create", out.display()))?;
    }
    info!(prefix = %cfg.prefix, "consumer started");

    let mut st = State::default();
    let mut stats = LatencyStats::default();
    let mut report = ConsumerReport::default();
    let mut first: Option<Instant> = None;
    let mut last_mask = Instant::now();
    let mut stalled = false;

    let drain_all = |report: &mut ConsumerReport,
                     stats: &mut LatencyStats,
                     st: &mut State|
     -> anyhow::Result<()> {
        let drain_scans = |report: &mut ConsumerReport, st: &mut State| -> anyhow::Result<()> {
            while let Some(scan) = scan_sub.receive().context("receive scan")? {
                let h = *scan.user_header();
                report.scans += 1;
                report.dropped_scans += st.scan_gap(h.producer_epoch, h.sequence);
                st.pending
                    .insert((h.producer_epoch, h.sequence), h.source_index);
                if st.pending.len() > PAIRING_WINDOW {
                    st.pending.pop_first();
                    report.unmatched_scans += 1;
                }
            }
            Ok(())
        };
        // A mask is stamped the moment it is taken, before the scans it answers are read
        // (they are published earlier, so they are queued by now).
        loop {
            let next = mask_sub.receive().context("receive mask")?;
            let now = monotonic_ns();
            drain_scans(report, st)?;
            let Some(mask) = next else {
                break;
            };
            let h = *mask.user_header();
            report.masks += 1;
            report.dropped_masks +=
                st.mask_gap(h.segmenter_epoch, h.producer_epoch, h.scan_sequence);
            if st.segmenter_epochs.insert(h.segmenter_epoch, ()).is_none() {
                report.segmenter_runs += 1;
            }
            if st
                .pending
                .remove(&(h.producer_epoch, h.scan_sequence))
                .is_none()
            {
                report.unmatched_masks += 1;
            }
            if h.status != MaskStatus::OK {
                *report
                    .rejected
                    .entry(h.status.name().to_string())
                    .or_default() += 1;
                continue;
            }
            report.segmented += 1;
            if report.segmented > opts.warmup {
                let s = h.stamps;
                stats.record(
                    s.produced_ns,
                    s.published_ns,
                    s.segmenter_received_ns,
                    s.segmenter_published_ns,
                    now,
                );
            }
            let probs: &[f32] = mask.payload();
            if let Some(dir) = &opts.labels {
                st.score(dir, h.source_index, probs);
            }
            if let Some(out) = &opts.out {
                let stem = format!("{:06}", h.source_index);
                if let Err(e) = groundwork_io::write_outputs(out, &stem, probs, 0.5) {
                    warn!("{e}");
                }
            }
        }
        Ok(())
    };

    loop {
        if opts.count.is_some_and(|c| report.masks >= c) {
            break;
        }
        if let (Some(t), Some(_)) = (opts.idle_timeout, first) {
            if last_mask.elapsed() > t {
                info!("no mask for {t:?}: stopping");
                break;
            }
        }
        if let Some(after) = opts.stall_after {
            if !stalled && report.masks >= after {
                stalled = true;
                info!(seconds = opts.stall.as_secs_f64(), "stalling: not reading");
                // A sleep that still honours Ctrl-C.
                if node.wait(opts.stall).is_err() {
                    break;
                }
                info!("resuming");
            }
        }
        let before = report.masks;
        if !transport::wait_or_stop(&node, &mask_listener, Duration::from_millis(200))? {
            break;
        }
        drain_all(&mut report, &mut stats, &mut st)?;
        if report.masks > before {
            last_mask = Instant::now();
            first.get_or_insert_with(Instant::now);
        }
        if last_report.elapsed() >= interval {
            last_report = Instant::now();
            let p = stats.percentiles();
            let e2e = p.last().map(|p| p.p50).unwrap_or(0.0);
            info!(
                masks = report.masks,
                segmented = report.segmented,
                dropped_scans = report.dropped_scans,
                dropped_masks = report.dropped_masks,
                rejected = report.rejected.values().sum::<u64>(),
                e2e_p50_us = e2e,
                iou = st.confusion.map(|c| c.metrics().iou_ground),
                "consumer state"
            );
            transport::cleanup_dead(&node);
        }
    }
    report.latency_us = stats.percentiles();
    report.accuracy = st.confusion.map(|c| c.metrics());
    report.seconds = first.map_or(0.0, |f| f.elapsed().as_secs_f64());
    let rejected: u64 = report.rejected.values().sum();
    println!(
        "consumer: {} masks ({} segmented, {rejected} rejected {:?}), {} scans; dropped {} scans / {} masks; unmatched {} masks / {} scans; {} segmenter run(s)",
        report.masks,
        report.segmented,
        report.rejected,
        report.scans,
        report.dropped_scans,
        report.dropped_masks,
        report.unmatched_masks,
        report.unmatched_scans,
        report.segmenter_runs
    );
    print!("{}", stats.table());
    if let Some(m) = report.accuracy {
        println!(
            "live accuracy (gmm protocol, labeled scans): precision {:.2} recall {:.2} F1 {:.2} ground IoU {:.2}",
            m.precision, m.recall, m.f1, m.iou_ground
        );
    }
    if let Some(p) = &opts.report_json {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("{}: cannot write report", p.display()))?;
    }
    Ok(report)
}

#[derive(Default)]
struct State {
    /// Scans seen and not yet answered: (producer epoch, sequence) → source index.
    pending: BTreeMap<(u64, u64), u64>,
    last_scan: Option<(u64, u64)>,
    last_mask: Option<(u64, u64, u64)>,
    segmenter_epochs: HashMap<u64, ()>,
    labels: HashMap<u64, Option<Vec<u16>>>,
    confusion: Option<Confusion>,
}

impl State {
    fn scan_gap(&mut self, epoch: u64, seq: u64) -> u64 {
        let gap = match self.last_scan {
            Some((e, s)) if e == epoch && seq > s + 1 => seq - s - 1,
            _ => 0,
        };
        self.last_scan = Some((epoch, seq));
        gap
    }

    fn mask_gap(&mut self, seg_epoch: u64, epoch: u64, seq: u64) -> u64 {
        let gap = match self.last_mask {
            Some((g, e, s)) if g == seg_epoch && e == epoch && seq > s + 1 => seq - s - 1,
            _ => 0,
        };
        self.last_mask = Some((seg_epoch, epoch, seq));
        gap
    }

    fn score(&mut self, dir: &std::path::Path, index: u64, probs: &[f32]) {
        let labels = self.labels.entry(index).or_insert_with(|| {
            let p = dir.join(format!("labels/{index:06}.label"));
            p.is_file()
                .then(|| groundwork_io::read_labels(&p, probs.len()))
                .transpose()
                .unwrap_or_else(|e| {
                    warn!("{e}");
                    None
                })
        });
        if let Some(l) = labels {
            if l.len() == probs.len() {
                let c = Confusion::from_predictions(probs, l, Protocol::Gmm, 0.5);
                self.confusion
                    .get_or_insert_with(Confusion::default)
                    .merge(&c);
            }
        }
    }
}
