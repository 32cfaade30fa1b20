//! Packets gathered into scans.
//!
//! A scan is whole packets, cut after the packet with which the rotation has covered a
//! full turn from where the scan began (the rule of the ROS driver and of
//! `velodyne_decoder`, so that frames match theirs one for one): its coverage, the last
//! block's azimuth measured from the scan's start, passes half a turn and then falls back.
//! The next scan starts where the last packet ended. A scan that has lasted longer than
//! [`MAX_SCAN_S`] (a sensor stopped, a pause in a capture) is cut before the late packet.
//!
//! Lost packets are counted from the azimuth: a packet that starts further on than the
//! previous one's span predicts stands for the packets missing in between; one that starts
//! behind its predecessor (other than at the wrap) arrived out of order.

use crate::velodyne::PacketView;

/// A scan lasting longer than this is cut (a turn takes 0.05–0.2 s), seconds.
pub const MAX_SCAN_S: f64 = 0.3;
/// A scan of this many packets is cut whatever its azimuth and times say (an HDL-64E's
/// dual-return turn at 5 Hz is about 2 900): memory stays bounded on any input.
pub const MAX_SCAN_PACKETS: usize = 8_192;
const TURN: i32 = 36_000;

/// One scan's packets, as received.
#[derive(Debug, Clone, Default)]
pub struct ScanPackets {
    /// The packets' bytes, one after another.
    bytes: Vec<u8>,
    /// Each packet's length in `bytes`.
    sizes: Vec<usize>,
    /// Each packet's receive time (the capture's or the socket's clock), ns.
    pub host_ns: Vec<u64>,
    /// Each packet's sensor time, ns (the sensor's top-of-hour µs placed in the hour of its
    /// receive time).
    pub sensor_ns: Vec<u64>,
    /// When the last packet arrived (this process's monotonic clock), for latency.
    pub completed_at_ns: u64,
}

impl ScanPackets {
    /// The packets.
    pub fn packets(&self) -> impl Iterator<Item = &[u8]> {
        let mut at = 0;
        self.sizes.iter().map(move |&n| {
            let p = &self.bytes[at..at + n];
            at += n;
            p
        })
    }

    /// How many.
    pub fn len(&self) -> usize {
        self.sizes.len()
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.sizes.is_empty()
    }

    /// The scan's time: its first packet's sensor time (the first firing's), ns.
    pub fn stamp_ns(&self) -> Option<u64> {
        self.sensor_ns.first().copied()
    }

    /// Hands this finished scan to `out` and starts the next one empty in `out`'s buffers.
    pub(crate) fn hand_over(&mut self, now_ns: u64, out: &mut ScanPackets) {
        out.clear();
        std::mem::swap(self, out);
        out.completed_at_ns = now_ns;
    }

    pub(crate) fn push(&mut self, bytes: &[u8], host_ns: u64, sensor_ns: u64) {
        self.bytes.extend_from_slice(bytes);
        self.sizes.push(bytes.len());
        self.host_ns.push(host_ns);
        self.sensor_ns.push(sensor_ns);
    }

    /// Empties it, keeping its memory (scans are recycled, not reallocated).
    pub fn clear(&mut self) {
        self.bytes.clear();
        self.sizes.clear();
        self.host_ns.clear();
        self.sensor_ns.clear();
        self.completed_at_ns = 0;
    }
}

/// Packets seen, lost and refused: the report's counters.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct PacketCounters {
    /// Packets decoded into scans.
    pub packets: u64,
    /// Packets missing, judged from azimuth gaps.
    pub lost: u64,
    /// Packets that arrived behind their predecessor.
    pub out_of_order: u64,
}

/// Gathers checked packets into scans.
#[derive(Debug, Default)]
pub struct ScanAssembler {
    current: ScanPackets,
    /// Azimuth where the scan began (the previous scan's last packet's end).
    start: Option<i32>,
    coverage: i32,
    /// The previous packet's first and last azimuth and its block step, for loss counting.
    previous: Option<(i32, i32, i32)>,
    counters: PacketCounters,
}

/// A sensor time from the top-of-hour µs a packet carries and its receive time: the hour
/// of the receive time, or the one before or after if that is nearer (a packet sent just
/// before the hour turns, received just after).
pub fn sensor_time_ns(toh_us: u32, host_ns: u64) -> u64 {
    const HOUR: i128 = 3_600_000_000_000;
    let host = host_ns as i128;
    let t = host - host.rem_euclid(HOUR) + toh_us as i128 * 1_000;
    let t = if t > host + HOUR / 2 {
        t - HOUR
    } else if t < host - HOUR / 2 {
        t + HOUR
    } else {
        t
    };
    t.clamp(0, u64::MAX as i128) as u64
}

impl ScanAssembler {
    /// An assembler whose first scan starts at the first packet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The counters so far.
    pub fn counters(&self) -> &PacketCounters {
        &self.counters
    }

    /// Adds a checked packet received at `host_ns`; a complete scan is moved into `out`
    /// (which is cleared first) and `true` returned. `now_ns` is stamped on a completed scan.
    pub fn push(
        &mut self,
        packet: &PacketView,
        bytes: &[u8],
        host_ns: u64,
        now_ns: u64,
        out: &mut ScanPackets,
    ) -> bool {
        let previous_end = self.previous.map(|(_, end, _)| end);
        self.count_gaps(packet);
        let sensor_ns = sensor_time_ns(packet.toh_us(), host_ns);
        let last = packet.last_azimuth() as i32;
        // A scan that lasts too long ends before this packet, which starts the next.
        let too_long = self.current.len() >= MAX_SCAN_PACKETS
            || self
                .current
                .host_ns
                .first()
                .is_some_and(|&t0| host_ns.saturating_sub(t0) as f64 > MAX_SCAN_S * 1e9);
        if too_long {
            self.current.hand_over(now_ns, out);
            let start = previous_end.unwrap_or(last);
            self.start = Some(start);
            self.current.push(bytes, host_ns, sensor_ns);
            self.counters.packets += 1;
            self.coverage = (last - start).rem_euclid(TURN);
            return true;
        }
        let start = *self.start.get_or_insert(last);
        self.current.push(bytes, host_ns, sensor_ns);
        self.counters.packets += 1;
        let coverage = (last - start).rem_euclid(TURN);
        let complete = self.coverage > TURN / 2 && self.coverage > coverage;
        self.coverage = coverage;
        if complete {
            self.start = Some(last);
            self.coverage = 0;
            self.current.hand_over(now_ns, out);
        }
        complete
    }

    /// The packets gathered since the last scan, as a last (partial) scan; false if none.
    pub fn flush(&mut self, now_ns: u64, out: &mut ScanPackets) -> bool {
        if self.current.is_empty() {
            return false;
        }
        self.current.hand_over(now_ns, out);
        self.start = None;
        self.coverage = 0;
        true
    }

    fn count_gaps(&mut self, packet: &PacketView) {
        let first = packet.azimuth(0) as i32;
        let last = packet.last_azimuth() as i32;
        if let Some((p_first, p_last, p_step)) = self.previous {
            // The next packet starts one block step after this one's end (blocks on the
            // same azimuth, dual returns or the HDL-64E's banks, do not step).
            let per_packet = (p_last - p_first).rem_euclid(TURN) + p_step;
            let advance = (first - p_first).rem_euclid(TURN);
            if per_packet > p_step {
                if advance > TURN / 2 {
                    // Late: its gap was counted as a loss; the furthest packet stays the
                    // reference for the next gap.
                    self.counters.out_of_order += 1;
                    self.counters.lost = self.counters.lost.saturating_sub(1);
                    return;
                } else if advance * 2 > per_packet * 3 {
                    // Rounded: the packets that fit in the gap, less the one that arrived.
                    let missing = (advance + per_packet / 2) / per_packet - 1;
                    self.counters.lost += missing.max(0) as u64;
                }
            }
        }
        let step = (1..12)
            .map(|i| (packet.azimuth(i) as i32 - packet.azimuth(i - 1) as i32).rem_euclid(TURN))
            .find(|&d| d > 0)
            .unwrap_or(0);
        self.previous = Some((first, last, step));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::velodyne::{Decoder, Model};

    fn packet(az0: u16, toh_us: u32) -> Vec<u8> {
        let mut p = crate::velodyne::tests::packet(Model::Vlp16, az0, 20, 5_000);
        p[1200..1204].copy_from_slice(&toh_us.to_le_bytes());
        p
    }

    /// A VLP-16 at 10 Hz: 0.2° a block, 2.4° a packet, 150 packets a turn.
    fn feed(azimuths: impl Iterator<Item = u32>) -> (Vec<usize>, PacketCounters) {
        let d = Decoder::new(Model::Vlp16, None).unwrap();
        let mut a = ScanAssembler::new();
        let mut out = ScanPackets::default();
        let mut sizes = Vec::new();
        for (k, az) in azimuths.enumerate() {
            let bytes = packet((az % 36_000) as u16, 1_000 + k as u32 * 1_327);
            let p = d.check(&bytes).unwrap();
            if a.push(
                &p,
                &bytes,
                5_000_000_000 + k as u64 * 1_327_000,
                0,
                &mut out,
            ) {
                sizes.push(out.len());
                assert_eq!(
                    out.stamp_ns().unwrap() % 1_000_000_000,
                    out.sensor_ns[0] % 1_000_000_000
                );
            }
        }
        if a.flush(0, &mut out) {
            sizes.push(out.len());
        }
        (sizes, a.counters().clone())
    }

    #[test]
    fn scans_are_cut_once_a_turn_and_lost_packets_counted() {
        // Three turns and a bit, from 100°.
        let (sizes, c) = feed((0..460).map(|k| 10_000 + k * 240));
        assert_eq!(sizes.iter().sum::<usize>(), 460);
        // The first scan ends with the packet that completes the turn (151 packets: the
        // 151st passes the start); then a packet's end is the next scan's start.
        assert_eq!(&sizes[..3], &[151, 150, 150]);
        assert_eq!((c.lost, c.out_of_order, c.packets), (0, 0, 460));
        // Every fifth packet lost: the gaps say so.
        let (sizes, c) = feed((0..460).filter(|k| k % 5 != 4).map(|k| k * 240));
        // 92 dropped; the last one has no packet after it to show the gap.
        assert_eq!(c.lost, 91);
        assert!(sizes[0] >= 120 && sizes[0] <= 121, "{sizes:?}");
        // Two packets swapped.
        let mut order: Vec<u32> = (0..40).collect();
        order.swap(10, 11);
        let (_, c) = feed(order.into_iter().map(|k| k * 240));
        assert_eq!((c.out_of_order, c.lost), (1, 0));
    }

    #[test]
    fn a_pause_cuts_the_scan_before_the_late_packet() {
        let d = Decoder::new(Model::Vlp16, None).unwrap();
        let mut a = ScanAssembler::new();
        let mut out = ScanPackets::default();
        let bytes = packet(0, 0);
        let p = d.check(&bytes).unwrap();
        assert!(!a.push(&p, &bytes, 0, 0, &mut out));
        assert!(!a.push(&p, &bytes, 100_000_000, 0, &mut out));
        assert!(a.push(&p, &bytes, 500_000_000, 7, &mut out));
        assert_eq!((out.len(), out.completed_at_ns), (2, 7));
        assert!(a.flush(0, &mut out));
        assert_eq!(out.len(), 1);
        assert!(!a.flush(0, &mut out));
    }

    /// Packets that never complete a turn (a stuck azimuth, one capture time): scans are
    /// still cut, at [`MAX_SCAN_PACKETS`].
    #[test]
    fn a_turn_that_never_ends_is_cut_at_the_packet_limit() {
        let d = Decoder::new(Model::Vlp16, None).unwrap();
        let mut a = ScanAssembler::new();
        let mut out = ScanPackets::default();
        let bytes = packet(500, 0);
        let p = d.check(&bytes).unwrap();
        let cuts: Vec<usize> = (0..2 * MAX_SCAN_PACKETS + 5)
            .filter(|_| a.push(&p, &bytes, 7, 0, &mut out))
            .collect();
        assert_eq!(cuts, [MAX_SCAN_PACKETS, 2 * MAX_SCAN_PACKETS]);
        assert_eq!(out.len(), MAX_SCAN_PACKETS);
    }

    #[test]
    fn the_sensor_time_takes_the_nearest_hour() {
        let hour = 3_600_000_000_000u64;
        let host = 10 * hour + 5_000_000;
        assert_eq!(sensor_time_ns(4_000, host), 10 * hour + 4_000_000);
        // Sent at 59:59.9, received just after the hour.
        assert_eq!(sensor_time_ns(3_599_900_000, host), 10 * hour - 100_000_000);
        assert_eq!(sensor_time_ns(0, 0), 0);
    }
}
