//! LiDAR packets from the wire: the first process that touches a sensor's UDP packets
//! decodes them, cuts them into scans at the sensor's frame boundary and stamps each scan
//! with the sensor's own time.
//!
//! - [`velodyne`]: the packet layout, the laser tables (built in or read from the
//!   sensor's calibration file) and the decoder.
//! - [`ouster`]: Ouster lidar packets with the sensor's metadata JSON.
//! - [`scan`]: packets gathered into scans (cut where the rotation wraps), with lost
//!   packets counted from azimuth gaps.
//! - [`capture`]: UDP datagrams from a pcap capture (Ethernet, VLAN, Linux cooked or raw
//!   IP), or from a socket.
//!
//! No shared memory and no threads here: the producer (`groundwork-service`) owns those.

pub mod capture;
pub mod ouster;
pub mod scan;
pub mod velodyne;

pub use capture::{Datagram, PcapSource, UdpSource};
pub use scan::{ScanAssembler, ScanPackets};
pub use velodyne::{Calibration, Decoder, Model};

/// Why a packet, a capture or a calibration file was refused.
#[derive(Debug, thiserror::Error)]
pub enum PacketError {
    /// A payload of the wrong size for the family.
    #[error("packet of {got} bytes where {expected} were expected")]
    Size {
        /// Its size.
        got: usize,
        /// The family's.
        expected: usize,
    },
    /// The packet's model byte names another sensor.
    #[error("model byte {got:#04x} is not a {expected}'s")]
    Model {
        /// The byte.
        got: u8,
        /// The model decoded.
        expected: &'static str,
    },
    /// A return-mode byte the formats do not define.
    #[error("unknown return mode byte {0:#04x}")]
    ReturnMode(u8),
    /// A block whose flag is not a laser bank's.
    #[error("block {block} has flag {flag:#06x}, not a laser bank's")]
    BlockFlag {
        /// Which block.
        block: usize,
        /// Its flag.
        flag: u16,
    },
    /// An azimuth of a full turn or more.
    #[error("block {block} has azimuth {azimuth} (0.01°), beyond a turn")]
    Azimuth {
        /// Which block.
        block: usize,
        /// Its azimuth.
        azimuth: u16,
    },
    /// A model whose every unit has its own laser table.
    #[error(
        "{model} packets need the sensor's calibration file (--sensor-config FILE.yaml, the ROS velodyne driver's format)"
    )]
    NeedsCalibration {
        /// The model.
        model: &'static str,
    },
    /// A calibration file for another number of lasers.
    #[error("the calibration has {lasers} lasers; a {model} has {expected}")]
    CalibrationMismatch {
        /// The model.
        model: &'static str,
        /// The file's lasers.
        lasers: usize,
        /// The model's.
        expected: usize,
    },
    /// A calibration file that cannot be read.
    #[error("{path}: {reason}")]
    Calibration {
        /// The file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// A capture that cannot be opened or read.
    #[error("{path}: {reason}")]
    Capture {
        /// The file or address.
        path: String,
        /// What is wrong.
        reason: String,
    },
}

impl PacketError {
    /// A short name of the kind of fault, for the report's counters.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Size { .. } => "wrong size",
            Self::Model { .. } => "other model",
            Self::ReturnMode(_) => "unknown return mode",
            Self::BlockFlag { .. } => "bad block flag",
            Self::Azimuth { .. } => "bad azimuth",
            Self::NeedsCalibration { .. }
            | Self::CalibrationMismatch { .. }
            | Self::Calibration { .. } => "calibration",
            Self::Capture { .. } => "capture",
        }
    }
}

impl Decoder {
    /// The returns a scan's packets decode to (to size the scan before decoding it).
    pub fn count_scan(&self, scan: &ScanPackets) -> usize {
        scan.packets()
            .filter_map(|p| self.check(p).ok())
            .map(|p| self.count(&p))
            .sum()
    }

    /// Decodes a scan's returns in firing order, each with its sensor time (ns).
    pub fn decode_scan(&self, scan: &ScanPackets, mut sink: impl FnMut(velodyne::Return, u64)) {
        for (bytes, &t) in scan.packets().zip(&scan.sensor_ns) {
            if let Ok(p) = self.check(bytes) {
                self.decode(&p, |r| sink(r, t + (r.time as f64 * 1e9).round() as u64));
            }
        }
    }
}

/// Packets seen, lost, refused: what a report shows.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct PacketReport {
    /// Packets decoded into scans, lost (azimuth gaps) and late.
    #[serde(flatten)]
    pub counters: scan::PacketCounters,
    /// Datagrams refused, by fault.
    pub refused: std::collections::BTreeMap<&'static str, u64>,
}

/// A sensor's decoder, of either family.
#[derive(Debug, Clone)]
pub enum SensorDecoder {
    /// Velodyne (boxed, as the Ouster's: their tables are hundreds of bytes to kB).
    Velodyne(Box<Decoder>),
    /// Ouster.
    Ouster(Box<ouster::Decoder>),
}

/// One return of either family, as a scan carries it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    /// Position (metres, the sensor's frame: x forward, y left, z up).
    pub x: f32,
    /// See `x`.
    pub y: f32,
    /// See `x`.
    pub z: f32,
    /// Velodyne: calibrated reflectivity (0–255); Ouster: signal photons.
    pub intensity: f32,
    /// The ring (Velodyne: rank by elevation, lowest 0; Ouster: beam row, top 0).
    pub ring: u16,
    /// The firing's sensor time, ns.
    pub time_ns: u64,
}

impl SensorDecoder {
    /// The returns a scan's packets decode to (to size the scan before decoding it).
    pub fn count_scan(&self, scan: &ScanPackets) -> usize {
        match self {
            Self::Velodyne(d) => d.count_scan(scan),
            Self::Ouster(d) => d.count_scan(scan),
        }
    }

    /// Decodes a scan's returns in the order the packets hold them.
    pub fn decode_scan(&self, scan: &ScanPackets, mut sink: impl FnMut(Point)) {
        match self {
            Self::Velodyne(d) => d.decode_scan(scan, |r, t| {
                sink(Point {
                    x: r.x,
                    y: r.y,
                    z: r.z,
                    intensity: r.intensity,
                    ring: r.ring,
                    time_ns: t,
                })
            }),
            Self::Ouster(d) => d.decode_scan(scan, |r| {
                sink(Point {
                    x: r.x,
                    y: r.y,
                    z: r.z,
                    intensity: r.intensity,
                    ring: r.row,
                    time_ns: r.time_ns,
                })
            }),
        }
    }
}

#[derive(Debug)]
enum Assembling {
    Velodyne(ScanAssembler),
    Ouster(ouster::Assembler),
}

/// A sensor's datagrams turned into scans: checked, gathered at the sensor's frame
/// boundary, decoded.
#[derive(Debug)]
pub struct PacketScans {
    decoder: SensorDecoder,
    assembler: Assembling,
    refused: std::collections::BTreeMap<&'static str, u64>,
    /// Log the first refused packet of each kind.
    warn: bool,
}

impl PacketScans {
    /// Scans of the sensor `decoder` decodes.
    pub fn new(decoder: SensorDecoder) -> Self {
        let assembler = match &decoder {
            SensorDecoder::Velodyne(_) => Assembling::Velodyne(ScanAssembler::new()),
            SensorDecoder::Ouster(d) => Assembling::Ouster(ouster::Assembler::new(d.metadata())),
        };
        Self {
            decoder,
            assembler,
            refused: Default::default(),
            warn: true,
        }
    }

    /// The same, counting refused packets without logging them (a pass that only counts
    /// scans).
    pub fn quiet(mut self) -> Self {
        self.warn = false;
        self
    }

    /// The decoder.
    pub fn decoder(&self) -> &SensorDecoder {
        &self.decoder
    }

    /// Feeds one datagram; true when `out` holds a complete scan. A datagram that is not a
    /// good packet is counted by fault (the first of each kind logged) and skipped.
    pub fn push(&mut self, d: &Datagram, now_ns: u64, out: &mut ScanPackets) -> bool {
        let pushed = match (&self.decoder, &mut self.assembler) {
            (SensorDecoder::Velodyne(dec), Assembling::Velodyne(a)) => dec
                .check(d.payload)
                .map(|p| a.push(&p, d.payload, d.time_ns, now_ns, out)),
            (SensorDecoder::Ouster(dec), Assembling::Ouster(a)) => dec
                .check(d.payload)
                .map(|p| a.push(dec, &p, d.payload, d.time_ns, now_ns, out)),
            _ => Ok(false),
        };
        match pushed {
            Ok(done) => done,
            Err(e) => {
                let n = self.refused.entry(e.kind()).or_default();
                if *n == 0 && self.warn {
                    tracing::warn!("packet skipped (counted from now on): {e}");
                }
                *n += 1;
                false
            }
        }
    }

    /// The packets gathered since the last scan as a last, partial scan (false: none).
    pub fn flush(&mut self, now_ns: u64, out: &mut ScanPackets) -> bool {
        match &mut self.assembler {
            Assembling::Velodyne(a) => a.flush(now_ns, out),
            Assembling::Ouster(a) => a.flush(now_ns, out),
        }
    }

    /// The returns a scan decodes to.
    pub fn count(&self, scan: &ScanPackets) -> usize {
        self.decoder.count_scan(scan)
    }

    /// Decodes a scan's returns in the order the packets hold them.
    pub fn decode(&self, scan: &ScanPackets, sink: impl FnMut(Point)) {
        self.decoder.decode_scan(scan, sink)
    }

    /// The counters so far.
    pub fn report(&self) -> PacketReport {
        let counters = match &self.assembler {
            Assembling::Velodyne(a) => a.counters().clone(),
            Assembling::Ouster(a) => a.counters().clone(),
        };
        PacketReport {
            counters,
            refused: self.refused.clone(),
        }
    }
}
