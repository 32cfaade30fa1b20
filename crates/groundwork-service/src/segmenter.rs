//! The segmenter process: scans in, masks out, multi-frame history kept between frames.
//! Blocks on the scan topic's iceoryx2 event while idle; a malformed scan is rejected with a counted,
//! logged reason (and an empty mask naming it), and the next scan is served as usual.

use std::collections::BTreeMap;
use std::time::Duration;

use anyhow::Context;
use groundwork_core::{SegmentError, Segmenter, SegmenterConfig, pose_from_matrix};
use groundwork_msg::{
    MaskHeader, MaskStatus, SCHEMA_VERSION, ScanHeader, ScanPoint, monotonic_ns, new_epoch,
};
use tracing::{info, warn};

use crate::config::{ServiceConfig, check_shared_memory};
use crate::transport;

/// Segmenter options beyond the shared configuration.
#[derive(Debug, Clone)]
pub struct SegmenterOptions {
    /// The algorithm's configuration.
    pub segmenter: SegmenterConfig,
    /// Stop after this many scans (None: until Ctrl-C).
    pub count: Option<u64>,
    /// Transport benchmark: answer every scan with a mask of the right size without
    /// segmenting (the values are 0).
    pub echo: bool,
}

/// What the segmenter did.
#[derive(Debug, Clone, Default)]
pub struct SegmenterReport {
    /// Scans received.
    pub received: u64,
    /// Masks published for segmented scans.
    pub segmented: u64,
    /// Rejected scans by reason.
    pub rejected: BTreeMap<&'static str, u64>,
    /// Scans lost between producer and segmenter (gaps in sequence numbers).
    pub dropped: u64,
}

/// Validates one received scan; `Err` carries the rejection status and a reason.
fn validate(
    h: &ScanHeader,
    points: &[ScanPoint],
    max_points: usize,
) -> Result<(), (MaskStatus, String)> {
    if h.schema_version != SCHEMA_VERSION {
        return Err((
            MaskStatus::BAD_SCHEMA,
            format!(
                "schema version {} (expected {SCHEMA_VERSION})",
                h.schema_version
            ),
        ));
    }
    if h.point_count as usize != points.len() {
        return Err((
            MaskStatus::COUNT_MISMATCH,
            format!(
                "header says {} points, payload has {}",
                h.point_count,
                points.len()
            ),
        ));
    }
    if points.is_empty() {
        return Err((MaskStatus::EMPTY, "scan has no points".into()));
    }
    if points.len() > max_points {
        return Err((
            MaskStatus::TOO_MANY_POINTS,
            format!(
                "{} points, more than the configured maximum of {max_points}",
                points.len()
            ),
        ));
    }
    Ok(())
}

fn status_of(e: &SegmentError) -> MaskStatus {
    match e {
        SegmentError::NonFinitePoint { .. } => MaskStatus::NON_FINITE,
        SegmentError::TooManyPoints { .. } => MaskStatus::TOO_MANY_POINTS,
        _ => MaskStatus::OTHER,
    }
}

/// Runs the segmenter until `count` scans were handled or a termination signal arrives.
pub fn run(cfg: &ServiceConfig, opts: &SegmenterOptions) -> anyhow::Result<SegmenterReport> {
    check_shared_memory(cfg)?;
    let max_points = cfg.max_points.min(opts.segmenter.sensor.max_points);
    let mut seg = Segmenter::new(opts.segmenter.clone())?;
    let node = transport::node(cfg, "segmenter")?;
    let scans = transport::scan_service(&node, cfg)?;
    let masks = transport::mask_service(&node, cfg)?;
    let subscriber = transport::scan_subscriber(&scans, cfg)?;
    let publisher = transport::mask_publisher(&masks, cfg)?;
    let scan_listener = transport::event_listener(&node, cfg, "scans")?;
    let mask_notifier = transport::event_notifier(&node, cfg, "masks")?;
    let epoch = new_epoch();
    info!(prefix = %cfg.prefix, frames = opts.segmenter.history.frames, echo = opts.echo, "segmenter started");

    let mut report = SegmenterReport::default();
    let mut last: Option<(u64, u64)> = None; // (producer epoch, sequence)

    let mut handle_scans = |report: &mut SegmenterReport,
                            seg: &mut Segmenter|
     -> anyhow::Result<()> {
        while let Some(scan) = subscriber.receive().context("receive scan")? {
            let received_ns = monotonic_ns();
            report.received += 1;
            let h = *scan.user_header();
            if let Some((e, s)) = last {
                if e == h.producer_epoch && h.sequence > s + 1 {
                    report.dropped += h.sequence - s - 1;
                }
            }
            last = Some((h.producer_epoch, h.sequence));
            let points: &[ScanPoint] = scan.payload();
            let mut header = MaskHeader {
                scan_sequence: h.sequence,
                producer_epoch: h.producer_epoch,
                sensor_timestamp_ns: h.sensor_timestamp_ns,
                source_index: h.source_index,
                stamps: h.stamps,
                segmenter_epoch: epoch,
                ..MaskHeader::default()
            };
            header.stamps.segmenter_received_ns = received_ns;
            let verdict = validate(&h, points, max_points);
            let n = if verdict.is_ok() { points.len() } else { 0 };
            let mut mask = publisher
                .loan_slice(n)
                .map_err(|e| anyhow::anyhow!("loan mask of {n}: {e:?}"))?;
            let outcome = match verdict {
                Err(e) => Err(e),
                Ok(()) if opts.echo => Ok(None),
                Ok(()) => {
                    let pose = (h.has_pose == 1)
                        .then(|| {
                            pose_from_matrix(&std::array::from_fn(|r| {
                                std::array::from_fn(|c| h.pose[4 * r + c])
                            }))
                        })
                        .transpose();
                    match pose {
                        Err(e) => Err((MaskStatus::OTHER, e.to_string())),
                        // The segmenter reads the scan in shared memory and writes the
                        // probabilities straight into the loaned mask: no copies.
                        Ok(pose) => match seg.segment(points, pose.as_ref(), mask.payload_mut()) {
                            Ok(r) => Ok(Some(r)),
                            Err(e) => Err((status_of(&e), e.to_string())),
                        },
                    }
                }
            };
            match outcome {
                Ok(r) => {
                    report.segmented += 1;
                    header.point_count = n as u32;
                    if let Some(r) = r {
                        header.ground_points = r.ground_points as u32;
                        header.frames_queried = r.frames_queried as u32;
                        header.fit_us = r.fit_time.as_micros() as u32;
                        header.query_us = r.query_time.as_micros() as u32;
                    }
                }
                Err((status, reason)) => {
                    *report.rejected.entry(status.name()).or_default() += 1;
                    warn!(
                        sequence = h.sequence,
                        reason = status.name(),
                        "rejected scan: {reason}"
                    );
                    header.status = status;
                    header.point_count = 0;
                }
            }
            drop(scan);
            header.stamps.segmenter_published_ns = monotonic_ns();
            *mask.user_header_mut() = header;
            mask.send().context("send mask")?;
            let _ = mask_notifier.notify();
            if opts.count.is_some_and(|c| report.received >= c) {
                break;
            }
        }
        Ok(())
    };

    // Scans published before our listener existed wake nobody: look once at start.
    handle_scans(&mut report, &mut seg)?;
    let interval = Duration::from_secs_f64(cfg.report_interval_s);
    let mut last_report = std::time::Instant::now();
    loop {
        if opts.count.is_some_and(|c| report.received >= c) {
            break;
        }
        // The bounded wait also lets the periodic work run while idle.
        if !transport::wait_or_stop(&node, &scan_listener, Duration::from_millis(250))? {
            break;
        }
        // Also serves scans whose wake-up was missed (e.g. a producer restarted between
        // our listener's cleanups): nothing strands in the queue.
        handle_scans(&mut report, &mut seg)?;
        if last_report.elapsed() >= interval {
            last_report = std::time::Instant::now();
            let rejected: u64 = report.rejected.values().sum();
            info!(
                received = report.received,
                segmented = report.segmented,
                rejected,
                dropped = report.dropped,
                history = seg.history_len(),
                "segmenter state"
            );
            seg.log_state();
            transport::cleanup_dead(&node);
        }
    }
    info!(
        received = report.received,
        segmented = report.segmented,
        rejected = ?report.rejected,
        dropped = report.dropped,
        "segmenter stopped"
    );
    Ok(report)
}
