//! Latency histograms per stage and end to end, and their report.

use std::fmt::Write;

use groundwork_msg::ScanSource;
use hdrhistogram::Histogram;
use serde::Serialize;

/// Stages a message passes, in order; the last three are the detector's, from the stamps of
/// its proposals (rows without samples are left out of the table).
pub const STAGES: [&str; 12] = [
    "producer fill",
    // A scan from the ROS 2 bridge: from DDS's receipt of the cloud's last fragment to the
    // scan published in shared memory (DDS queue, deserialization, checks, one copy).
    "ros2 receipt to scan published",
    // A scan decoded from the sensor's packets: from the receipt of its last packet to the
    // scan published (hand-over from the receiving thread, decoding into shared memory).
    "last packet to scan published",
    "scan transport",
    "segment",
    "mask transport",
    // Per message, not a sum of percentiles (which overstates the tail).
    "transport",
    "scan published to mask received",
    "end to end",
    "mask to detector",
    "detect",
    "produced to proposals published",
];

/// Index of the first detector row of [`STAGES`].
const DETECTOR_ROWS: usize = 9;

/// Index of the "segment" row, which every segmented message has.
const SEGMENT_ROW: usize = 4;

/// Percentiles of one stage, µs.
#[derive(Debug, Clone, Serialize)]
pub struct Percentiles {
    /// Stage name.
    pub stage: String,
    /// Samples.
    pub count: u64,
    /// Median.
    pub p50: f64,
    /// 90th percentile.
    pub p90: f64,
    /// 99th percentile.
    pub p99: f64,
    /// 99.9th percentile.
    pub p999: f64,
    /// Maximum.
    pub max: f64,
}

/// One histogram per stage (ns, 3 significant digits, up to 100 s).
#[derive(Debug)]
pub struct LatencyStats {
    hist: Vec<Histogram<u64>>,
}

impl Default for LatencyStats {
    fn default() -> Self {
        Self {
            hist: STAGES
                .iter()
                .map(|_| {
                    Histogram::new_with_bounds(1, 100_000_000_000, 3)
                        .expect("static bounds are valid")
                })
                .collect(),
        }
    }
}

impl LatencyStats {
    /// Records one message from its stamps (ns) and the consumer's receive time; `source`:
    /// the stage that published the scan (its fill is that stage's row).
    pub fn record(
        &mut self,
        source: ScanSource,
        produced: u64,
        published: u64,
        seg_in: u64,
        seg_out: u64,
        consumed: u64,
    ) {
        let scan_hop = seg_in.saturating_sub(published);
        let mask_hop = consumed.saturating_sub(seg_out);
        let fill = published.saturating_sub(produced);
        let d = [
            (source == ScanSource::PRODUCER).then_some(fill),
            (source == ScanSource::ROS2).then_some(fill),
            (source == ScanSource::PACKETS).then_some(fill),
            Some(scan_hop),
            Some(seg_out.saturating_sub(seg_in)),
            Some(mask_hop),
            Some(scan_hop + mask_hop),
            Some(consumed.saturating_sub(published)),
            Some(consumed.saturating_sub(produced)),
        ];
        for (h, v) in self.hist.iter_mut().zip(d) {
            if let Some(v) = v {
                h.saturating_record(v.max(1));
            }
        }
    }

    /// Records one proposals message from its stamps (ns): the segmenter's publication, the
    /// detector's receipt and publication, and the producer's fill.
    pub fn record_proposals(&mut self, produced: u64, seg_out: u64, det_in: u64, det_out: u64) {
        let d = [
            det_in.saturating_sub(seg_out),
            det_out.saturating_sub(det_in),
            det_out.saturating_sub(produced),
        ];
        for (h, v) in self.hist[DETECTOR_ROWS..].iter_mut().zip(d) {
            h.saturating_record(v.max(1));
        }
    }

    /// The percentiles of one stage by name.
    pub fn stage(&self, name: &str) -> Option<Percentiles> {
        self.percentiles().into_iter().find(|p| p.stage == name)
    }

    /// Percentiles per stage.
    pub fn percentiles(&self) -> Vec<Percentiles> {
        STAGES
            .iter()
            .zip(&self.hist)
            .map(|(name, h)| {
                let us = |q: f64| h.value_at_quantile(q) as f64 / 1e3;
                Percentiles {
                    stage: (*name).to_string(),
                    count: h.len(),
                    p50: us(0.5),
                    p90: us(0.9),
                    p99: us(0.99),
                    p999: us(0.999),
                    max: h.max() as f64 / 1e3,
                }
            })
            .collect()
    }

    /// Samples recorded.
    pub fn len(&self) -> u64 {
        self.hist[SEGMENT_ROW].len()
    }

    /// Whether nothing was recorded.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A table a person reads at a glance.
    pub fn table(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{:<32} {:>7} {:>10} {:>10} {:>10} {:>10} {:>10}",
            "stage (µs)", "n", "p50", "p90", "p99", "p99.9", "max"
        );
        for p in self.percentiles().into_iter().filter(|p| p.count > 0) {
            let _ = writeln!(
                s,
                "{:<32} {:>7} {:>10.1} {:>10.1} {:>10.1} {:>10.1} {:>10.1}",
                p.stage, p.count, p.p50, p.p90, p.p99, p.p999, p.max
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_are_differences_of_stamps() {
        let mut s = LatencyStats::default();
        for i in 0..100u64 {
            s.record(
                ScanSource::PRODUCER,
                1000,
                2000,
                3000 + i,
                10_000 + i,
                11_000 + i,
            );
        }
        let p = s.percentiles();
        assert_eq!(p[0].count, 100);
        assert!((p[0].p50 - 1.0).abs() < 0.01, "{:?}", p[0]);
        assert_eq!(p[1].count, 0, "no bridged scan");
        assert_eq!(p[2].count, 0, "no scan from packets");
        assert!((p[4].p50 - 7.0).abs() < 0.01, "{:?}", p[4]);
        // Transport: 1.0 + i ns scan hop + 1.0 µs mask hop, per message.
        assert!((p[6].p50 - 2.05).abs() < 0.01, "{:?}", p[6]);
        assert!((p[7].max - 9.099).abs() < 0.02, "{:?}", p[7]);
        assert!((p[8].max - 10.099).abs() < 0.02, "{:?}", p[8]);
        assert!(!s.table().contains("ros2"));
        // A bridged scan's fill is the bridge's row, not the producer's.
        s.record(ScanSource::ROS2, 1000, 3000, 3500, 10_000, 11_000);
        assert_eq!(s.stage("producer fill").unwrap().count, 100);
        let b = s.stage("ros2 receipt to scan published").unwrap();
        assert!(b.count == 1 && (b.p50 - 2.0).abs() < 0.01, "{b:?}");
        // A scan from packets: its fill starts at its last packet's receipt.
        s.record(ScanSource::PACKETS, 1000, 1500, 3500, 10_000, 11_000);
        let k = s.stage("last packet to scan published").unwrap();
        assert!(k.count == 1 && (k.p50 - 0.5).abs() < 0.01, "{k:?}");
        assert_eq!(s.stage("producer fill").unwrap().count, 100);
        assert_eq!(s.len(), 102);
        assert!(s.table().contains("end to end"));
        assert!(
            !s.table().contains("detect"),
            "no detector, no detector rows"
        );
        s.record_proposals(1000, 10_000, 10_500, 14_500);
        let d = s.stage("detect").unwrap();
        assert!((d.p50 - 4.0).abs() < 0.01 && d.count == 1, "{d:?}");
        assert!((s.stage("mask to detector").unwrap().p50 - 0.5).abs() < 0.01);
        assert!((s.stage("produced to proposals published").unwrap().p50 - 13.5).abs() < 0.02);
        assert!(s.table().contains("detect"));
    }
}
