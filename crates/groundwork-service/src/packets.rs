//! The producer's packet source: a sensor's UDP packets (live, or replayed from a pcap
//! capture) gathered into scans by a receiving thread, and decoded by the producer
//! straight into the loaned scan sample.
//!
//! The receiving thread only copies each datagram's payload into the scan it belongs to
//! (1.2 kB a packet); at the scan's last packet it hands the scan's packets over. The
//! producer then counts the scan's returns, loans a sample of exactly that many points and
//! decodes the packets into it: no point is written twice.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, SyncSender, channel, sync_channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use groundwork_msg::{ScanPoint, monotonic_ns};
use groundwork_packets::capture::CaptureCounters;
use groundwork_packets::{
    Calibration, Decoder, Model, PacketReport, PacketScans, PcapSource, ScanPackets, SensorDecoder,
    UdpSource, ouster,
};
use serde::Serialize;
use tracing::{info, warn};

/// Where packets come from.
#[derive(Debug, Clone)]
pub enum PacketInput {
    /// A pcap capture, replayed once.
    Pcap(PathBuf),
    /// A UDP address to listen on (e.g. `0.0.0.0:2368`).
    Udp(SocketAddr),
}

/// Which sensor sends the packets, and what decoding them needs.
#[derive(Debug, Clone)]
pub enum PacketSensor {
    /// A Velodyne: its model, and its calibration file (None: the manual's table).
    Velodyne(Model, Option<PathBuf>),
    /// An Ouster: its metadata JSON.
    Ouster(PathBuf),
}

impl PacketSensor {
    /// The decoder for these packets (reads the calibration or metadata file).
    pub fn decoder(&self) -> anyhow::Result<SensorDecoder> {
        Ok(match self {
            Self::Velodyne(model, calibration) => {
                let calibration = calibration.as_deref().map(Calibration::read).transpose()?;
                SensorDecoder::Velodyne(Box::new(Decoder::new(*model, calibration)?))
            }
            Self::Ouster(metadata) => SensorDecoder::Ouster(Box::new(ouster::Decoder::new(
                ouster::Metadata::read(metadata)?,
            ))),
        })
    }

    /// The coordinate frame its scans are in: the ROS drivers' default names.
    pub fn frame_id(&self) -> &'static str {
        match self {
            Self::Velodyne(..) => "velodyne",
            Self::Ouster(_) => "os_sensor",
        }
    }

    /// A short name for logs and reports.
    pub fn name(&self) -> String {
        match self {
            Self::Velodyne(model, _) => model.name().to_string(),
            Self::Ouster(metadata) => format!("ouster ({})", metadata.display()),
        }
    }
}

/// A sensor's packets, as the producer is asked to read them.
#[derive(Debug, Clone)]
pub struct PacketSource {
    /// The sensor.
    pub sensor: PacketSensor,
    /// Live or a capture.
    pub input: PacketInput,
    /// A capture's datagrams to this port only (None: every port).
    pub port: Option<u16>,
    /// Replay a capture at its recorded rate (else as fast as the scans are taken).
    pub recorded_rate: bool,
}

/// What the packet source saw: packets, losses, refusals, the capture's other records.
#[derive(Debug, Clone, Default, Serialize)]
pub struct PacketSourceReport {
    /// Packets decoded into scans, lost, late, refused (by fault).
    #[serde(flatten)]
    pub packets: PacketReport,
    /// A capture's records that were not the sensor's datagrams.
    pub capture: CaptureCounters,
    /// Scans left out: more points than `max_points`, or none at all.
    pub scans_skipped: u64,
    /// An error that ended the input early (a truncated capture, a socket error).
    pub input_error: Option<String>,
}

/// Scans arriving from the receiving thread.
#[derive(Debug)]
pub struct PacketStream {
    decoder: SensorDecoder,
    scans: Receiver<ScanPackets>,
    /// Emptied scans go back to the receiving thread (no allocation per scan).
    recycle: Sender<ScanPackets>,
    report: Arc<Mutex<PacketSourceReport>>,
    /// The receiving thread has stopped (end of capture) and every scan was taken.
    ended: bool,
    scans_taken: u64,
    /// Tells the receiving thread to stop (a socket has no end of its own).
    stop: Arc<AtomicBool>,
}

impl Drop for PacketStream {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// Complete scans waiting for the producer: a few, so that a slow publication does not
/// make the socket's buffer overflow, and no more (each is its packets, about 0.5 MB).
const SCANS_AHEAD: usize = 4;

/// A capture replayed at its recorded rate is released in steps of about this much.
const PACE_GRANULARITY: Duration = Duration::from_millis(1);

/// How long the producer waits for a scan before it looks at signals again.
const SCAN_WAIT: Duration = Duration::from_millis(100);

impl PacketStream {
    /// Opens the input and starts the receiving thread.
    pub fn start(source: &PacketSource) -> anyhow::Result<Self> {
        let decoder = source.sensor.decoder()?;
        let input = match &source.input {
            PacketInput::Pcap(path) => Input::Pcap(Box::new(PcapSource::open(path, source.port)?)),
            PacketInput::Udp(addr) => Input::Udp(UdpSource::bind(*addr, SCAN_WAIT)?),
        };
        let (tx, scans) = sync_channel(SCANS_AHEAD);
        let (recycle, returned) = channel();
        let report = Arc::new(Mutex::new(PacketSourceReport::default()));
        let stop = Arc::new(AtomicBool::new(false));
        let receiver = Receiving {
            stop: Arc::clone(&stop),
            scans: PacketScans::new(decoder.clone()),
            tx,
            returned,
            report: Arc::clone(&report),
            recorded_rate: source.recorded_rate,
        };
        std::thread::Builder::new()
            .name("packets".into())
            .spawn(move || receiver.run(input))
            .context("start the packet receiving thread")?;
        info!(
            sensor = source.sensor.name(),
            input = ?source.input,
            "packets: receiving"
        );
        Ok(Self {
            decoder,
            scans,
            recycle,
            report,
            ended: false,
            scans_taken: 0,
            stop,
        })
    }

    /// The next complete scan (None: none within a short wait, or the input has ended).
    pub fn next_scan(&mut self) -> Option<ScanPackets> {
        match self.scans.recv_timeout(SCAN_WAIT) {
            Ok(s) => {
                self.scans_taken += 1;
                Some(s)
            }
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => {
                self.ended = true;
                None
            }
        }
    }

    /// Hands an emptied scan back for reuse.
    pub fn recycle(&self, scan: ScanPackets) {
        let _ = self.recycle.send(scan);
    }

    /// Whether the input has ended and every scan was taken.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// The returns a scan decodes to.
    pub fn count(&self, scan: &ScanPackets) -> usize {
        self.decoder.count_scan(scan)
    }

    /// Decodes a scan into `points` (exactly [`PacketStream::count`] long).
    pub fn decode_into(&self, scan: &ScanPackets, points: &mut [ScanPoint]) -> bool {
        let mut k = 0;
        self.decoder.decode_scan(scan, |r| {
            if let Some(p) = points.get_mut(k) {
                *p = ScanPoint {
                    x: r.x,
                    y: r.y,
                    z: r.z,
                    intensity: r.intensity,
                };
            }
            k += 1;
        });
        k == points.len()
    }

    /// Counts a scan left out.
    pub fn count_skipped(&self) {
        if let Ok(mut r) = self.report.lock() {
            r.scans_skipped += 1;
        }
    }

    /// The report so far.
    pub fn report(&self) -> PacketSourceReport {
        self.report.lock().map(|r| r.clone()).unwrap_or_default()
    }
}

enum Input {
    Pcap(Box<PcapSource>),
    Udp(UdpSource),
}

/// The receiving thread's state.
struct Receiving {
    scans: PacketScans,
    tx: SyncSender<ScanPackets>,
    returned: Receiver<ScanPackets>,
    report: Arc<Mutex<PacketSourceReport>>,
    recorded_rate: bool,
    stop: Arc<AtomicBool>,
}

impl Receiving {
    fn run(mut self, input: Input) {
        let mut out = self.returned.try_recv().unwrap_or_default();
        match input {
            Input::Pcap(mut pcap) => {
                // Replay pace: the capture's clock against ours, from the first record.
                let mut origin: Option<(u64, Instant)> = None;
                while let Some(d) = pcap.next_datagram() {
                    let d = match d {
                        Ok(d) => d,
                        Err(e) => {
                            warn!("{e}");
                            self.update(|r| r.input_error = Some(e.to_string()));
                            break;
                        }
                    };
                    if self.recorded_rate {
                        let (t0, w0) = *origin.get_or_insert((d.time_ns, Instant::now()));
                        let due = w0 + Duration::from_nanos(d.time_ns.saturating_sub(t0));
                        // Sleep only when a millisecond or more ahead: a wake-up per packet
                        // (3 500 a second from a 64-beam sensor) would cost more CPU than
                        // the decoding.
                        let ahead = due.saturating_duration_since(Instant::now());
                        if ahead >= PACE_GRANULARITY {
                            std::thread::sleep(ahead);
                        }
                    }
                    if self.scans.push(&d, monotonic_ns(), &mut out) && !self.hand_over(&mut out) {
                        return;
                    }
                }
                let capture = pcap.counters().clone();
                self.update(|r| r.capture = capture);
                // The capture's last, partial turn is a scan too (as other decoders do).
                if self.scans.flush(monotonic_ns(), &mut out) {
                    self.hand_over(&mut out);
                }
                self.publish_counters();
            }
            Input::Udp(mut udp) => loop {
                match udp.next_datagram() {
                    Ok(Some(d)) => {
                        if self.scans.push(&d, monotonic_ns(), &mut out)
                            && !self.hand_over(&mut out)
                        {
                            return;
                        }
                    }
                    // Nothing for a while: is anyone still taking scans?
                    Ok(None) => {
                        if self.stop.load(Ordering::Relaxed) {
                            return;
                        }
                    }
                    Err(e) => {
                        warn!("{e}");
                        self.update(|r| r.input_error = Some(e.to_string()));
                        return;
                    }
                }
            },
        }
    }

    /// Sends the scan in `out` to the producer and takes an emptied one back (or a new
    /// one); false once the producer is gone.
    fn hand_over(&mut self, out: &mut ScanPackets) -> bool {
        self.publish_counters();
        let next = self.returned.try_recv().unwrap_or_default();
        let full = std::mem::replace(out, next);
        self.tx.send(full).is_ok()
    }

    fn publish_counters(&self) {
        let packets = self.scans.report();
        self.update(|r| r.packets = packets);
    }

    fn update(&self, f: impl FnOnce(&mut PacketSourceReport)) {
        if let Ok(mut r) = self.report.lock() {
            f(&mut r);
        }
    }
}

impl PacketSource {
    /// The scans a capture gives the producer (with returns, within `max_points`): read
    /// once ahead, so that a pipeline knows when every scan has been segmented. None for a
    /// live source.
    pub fn count_scans(&self, max_points: usize) -> anyhow::Result<Option<u64>> {
        let PacketInput::Pcap(path) = &self.input else {
            return Ok(None);
        };
        let mut scans = PacketScans::new(self.sensor.decoder()?).quiet();
        let mut pcap = PcapSource::open(path, self.port)?;
        let mut out = ScanPackets::default();
        let mut n = 0;
        let mut take = |scans: &PacketScans, out: &ScanPackets| {
            let len = scans.count(out);
            n += u64::from(len > 0 && len <= max_points);
        };
        // A damaged capture's error is reported when it is replayed; its scans up to the
        // damage count.
        while let Some(Ok(d)) = pcap.next_datagram() {
            if scans.push(&d, 0, &mut out) {
                take(&scans, &out);
            }
        }
        if scans.flush(0, &mut out) {
            take(&scans, &out);
        }
        Ok(Some(n))
    }
}
