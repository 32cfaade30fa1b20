//! Where packets come from: a pcap capture's UDP datagrams, or a UDP socket.

use std::fs::File;
use std::io::BufReader;
use std::net::{SocketAddr, UdpSocket};
use std::path::Path;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use etherparse::{SlicedPacket, TransportSlice};
use pcap_file::DataLink;
use pcap_file::pcap::PcapReader;
use serde::Serialize;

use crate::PacketError;

/// A UDP datagram: when it was received, to which port, its payload.
#[derive(Debug, Clone, Copy)]
pub struct Datagram<'a> {
    /// Receive time (the capture's clock, or the wall clock for a socket), ns since 1970.
    pub time_ns: u64,
    /// Destination port.
    pub port: u16,
    /// The UDP payload.
    pub payload: &'a [u8],
}

/// What a capture held besides the datagrams handed on.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct CaptureCounters {
    /// Records read.
    pub records: u64,
    /// Records that are not UDP over IP (ARP, TCP, ...), or whose headers do not parse.
    pub not_udp: u64,
    /// IP fragments read (an Ouster packet of 12 kB travels in nine on a 1500-byte MTU);
    /// they are reassembled into their datagrams.
    pub fragments: u64,
    /// Fragments that could not be reassembled (inconsistent, or never completed within
    /// a second of capture time).
    pub bad_fragments: u64,
    /// UDP datagrams to other ports.
    pub other_port: u64,
}

/// A pcap capture's UDP datagrams, in capture order.
#[derive(Debug)]
pub struct PcapSource {
    path: String,
    reader: PcapReader<BufReader<File>>,
    link: DataLink,
    port: Option<u16>,
    counters: CaptureCounters,
    payload: Vec<u8>,
    ended: bool,
    /// Datagrams being reassembled from their fragments, by capture time.
    defrag: etherparse::defrag::IpDefragPool<u64, ()>,
}

/// A datagram whose fragments have not all come within this much capture time is given up.
const DEFRAG_WINDOW_NS: u64 = 1_000_000_000;

impl PcapSource {
    /// Opens a capture; only datagrams to `port` are handed on (None: all).
    pub fn open(path: &Path, port: Option<u16>) -> Result<Self, PacketError> {
        let name = path.display().to_string();
        let bad = |reason: String| PacketError::Capture {
            path: name.clone(),
            reason,
        };
        let file = File::open(path).map_err(|e| bad(e.to_string()))?;
        let reader = PcapReader::new(BufReader::new(file)).map_err(|e| {
            bad(format!(
                "not a pcap capture ({e}); pcapng: convert with `editcap -F pcap`"
            ))
        })?;
        let link = reader.header().datalink;
        if !matches!(
            link,
            DataLink::ETHERNET
                | DataLink::LINUX_SLL
                | DataLink::RAW
                | DataLink::IPV4
                | DataLink::IPV6
        ) {
            return Err(bad(format!(
                "link type {link:?}: Ethernet, Linux cooked or raw IP captures are read"
            )));
        }
        Ok(Self {
            path: name,
            reader,
            link,
            port,
            counters: CaptureCounters::default(),
            payload: Vec::with_capacity(2048),
            ended: false,
            defrag: etherparse::defrag::IpDefragPool::new(),
        })
    }

    /// The counters so far.
    pub fn counters(&self) -> &CaptureCounters {
        &self.counters
    }

    /// The next datagram; None at the end. A damaged or truncated capture ends with one
    /// error naming the file and the record, then None.
    pub fn next_datagram(&mut self) -> Option<Result<Datagram<'_>, PacketError>> {
        loop {
            if self.ended {
                return None;
            }
            let record = match self.reader.next_packet()? {
                Ok(r) => r,
                Err(e) => {
                    self.ended = true;
                    return Some(Err(PacketError::Capture {
                        path: self.path.clone(),
                        reason: format!(
                            "record {} cannot be read ({e}): the capture is truncated or damaged",
                            self.counters.records + 1
                        ),
                    }));
                }
            };
            self.counters.records += 1;
            let time_ns = u64::try_from(record.timestamp.as_nanos()).unwrap_or(u64::MAX);
            let data: &[u8] = &record.data;
            let sliced = match self.link {
                DataLink::ETHERNET => SlicedPacket::from_ethernet(data),
                DataLink::LINUX_SLL => SlicedPacket::from_linux_sll(data),
                _ => SlicedPacket::from_ip(data),
            };
            let Ok(sliced) = sliced else {
                self.counters.not_udp += 1;
                continue;
            };
            if sliced.is_ip_payload_fragmented() {
                self.counters.fragments += 1;
                let done = match self.defrag.process_sliced_packet(&sliced, time_ns, ()) {
                    Ok(done) => done,
                    Err(_) => {
                        self.counters.bad_fragments += 1;
                        None
                    }
                };
                // Give up on datagrams whose fragments stopped coming (bounded memory).
                let stale = std::cell::Cell::new(0u64);
                self.defrag.retain(|&t| {
                    let keep = time_ns.saturating_sub(t) <= DEFRAG_WINDOW_NS;
                    stale.set(stale.get() + u64::from(!keep));
                    keep
                });
                self.counters.bad_fragments += stale.get();
                let Some(done) = done else {
                    continue;
                };
                let udp = (done.ip_number == etherparse::IpNumber::UDP)
                    .then(|| etherparse::UdpSlice::from_slice(&done.payload).ok())
                    .flatten();
                let port = udp.as_ref().map(|u| u.destination_port());
                if let Some(u) = &udp {
                    self.payload.clear();
                    self.payload.extend_from_slice(u.payload());
                }
                self.defrag.return_buf(done);
                let Some(port) = port else {
                    self.counters.not_udp += 1;
                    continue;
                };
                if self.port.is_some_and(|p| p != port) {
                    self.counters.other_port += 1;
                    continue;
                }
                return Some(Ok(Datagram {
                    time_ns,
                    port,
                    payload: &self.payload,
                }));
            }
            let Some(TransportSlice::Udp(udp)) = &sliced.transport else {
                self.counters.not_udp += 1;
                continue;
            };
            let port = udp.destination_port();
            if self.port.is_some_and(|p| p != port) {
                self.counters.other_port += 1;
                continue;
            }
            self.payload.clear();
            self.payload.extend_from_slice(udp.payload());
            return Some(Ok(Datagram {
                time_ns,
                port,
                payload: &self.payload,
            }));
        }
    }
}

/// Live packets: a UDP socket with a bounded receive buffer.
#[derive(Debug)]
pub struct UdpSource {
    socket: UdpSocket,
    port: u16,
    buffer: Vec<u8>,
}

/// The kernel's receive buffer asked for: about 0.3 s of a 64-beam sensor's packets (a
/// scan and a half); beyond it the kernel drops packets, and the gaps count them.
pub const SOCKET_BUFFER_BYTES: usize = 4 << 20;

impl UdpSource {
    /// Binds `addr` (e.g. `0.0.0.0:2368`); receives wait at most `timeout`.
    pub fn bind(addr: SocketAddr, timeout: Duration) -> Result<Self, PacketError> {
        let bad = |e: std::io::Error| PacketError::Capture {
            path: addr.to_string(),
            reason: e.to_string(),
        };
        let socket = socket2::Socket::new(
            socket2::Domain::for_address(addr),
            socket2::Type::DGRAM,
            Some(socket2::Protocol::UDP),
        )
        .map_err(bad)?;
        socket.set_reuse_address(true).map_err(bad)?;
        socket
            .set_recv_buffer_size(SOCKET_BUFFER_BYTES)
            .map_err(bad)?;
        socket.bind(&addr.into()).map_err(bad)?;
        let socket: UdpSocket = socket.into();
        socket.set_read_timeout(Some(timeout)).map_err(bad)?;
        let port = socket.local_addr().map_err(bad)?.port();
        Ok(Self {
            socket,
            port,
            buffer: vec![0; 65_536],
        })
    }

    /// The port bound (the one asked for, or the one the system chose for port 0).
    pub fn port(&self) -> u16 {
        self.port
    }

    /// The next datagram, or None if none came within the timeout.
    pub fn next_datagram(&mut self) -> Result<Option<Datagram<'_>>, PacketError> {
        match self.socket.recv(&mut self.buffer) {
            Ok(n) => Ok(Some(Datagram {
                time_ns: SystemTime::now()
                    .duration_since(UNIX_EPOCH)
                    .map(|d| d.as_nanos() as u64)
                    .unwrap_or(0),
                port: self.port,
                payload: &self.buffer[..n],
            })),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                Ok(None)
            }
            Err(e) => Err(PacketError::Capture {
                path: format!("udp port {}", self.port),
                reason: e.to_string(),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    /// A little-endian pcap of Ethernet frames with µs stamps.
    fn pcap(records: &[Vec<u8>]) -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(&0xA1B2_C3D4u32.to_le_bytes());
        b.extend_from_slice(&2u16.to_le_bytes());
        b.extend_from_slice(&4u16.to_le_bytes());
        for v in [0u32, 0, 65_535, 1] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        for (k, r) in records.iter().enumerate() {
            for v in [1_000 + k as u32, 0, r.len() as u32, r.len() as u32] {
                b.extend_from_slice(&v.to_le_bytes());
            }
            b.extend_from_slice(r);
        }
        b
    }

    fn udp_frame(port: u16, payload: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        etherparse::PacketBuilder::ethernet2([1; 6], [2; 6])
            .ipv4([192, 168, 1, 201], [192, 168, 1, 100], 64)
            .udp(2368, port)
            .write(&mut out, payload)
            .unwrap();
        out
    }

    /// Datagrams read (time, payload), the error that ended the capture, the counters.
    type Read = (Vec<(u64, Vec<u8>)>, Option<String>, CaptureCounters);

    fn read_all(bytes: &[u8], port: Option<u16>) -> Read {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.pcap");
        std::fs::write(&path, bytes).unwrap();
        let mut src = match PcapSource::open(&path, port) {
            Ok(s) => s,
            Err(e) => return (Vec::new(), Some(e.to_string()), CaptureCounters::default()),
        };
        let mut got = Vec::new();
        let mut error = None;
        while let Some(d) = src.next_datagram() {
            match d {
                Ok(d) => got.push((d.time_ns, d.payload.to_vec())),
                Err(e) => error = Some(e.to_string()),
            }
        }
        (got, error, src.counters().clone())
    }

    #[test]
    fn datagrams_to_the_port_are_handed_on_the_rest_counted() {
        let arp = [vec![0xFF; 12], vec![0x08, 0x06], vec![0; 28]].concat();
        let bytes = pcap(&[
            udp_frame(2368, b"first"),
            udp_frame(8308, b"position"),
            arp,
            udp_frame(2368, b"second"),
        ]);
        let (got, error, c) = read_all(&bytes, Some(2368));
        assert!(error.is_none());
        assert_eq!(
            got,
            [
                (1_000_000_000_000, b"first".to_vec()),
                (1_003_000_000_000, b"second".to_vec())
            ]
        );
        assert_eq!((c.records, c.other_port, c.not_udp), (4, 1, 1));
        let (all, _, _) = read_all(&bytes, None);
        assert_eq!(all.len(), 3);
        // Truncated in the last record: the records before it, then the file named.
        let (got, error, _) = read_all(&bytes[..bytes.len() - 3], Some(2368));
        assert_eq!(got.len(), 1);
        let e = error.unwrap();
        assert!(
            e.contains("c.pcap") && e.contains("record 4") && e.contains("truncated"),
            "{e}"
        );
        // Not a capture at all.
        let (_, error, _) = read_all(b"hello, this is not a capture", None);
        assert!(error.unwrap().contains("not a pcap capture"));
    }

    /// A record that claims 4 GB: refused as damaged, not allocated.
    #[test]
    fn a_record_claiming_gigabytes_is_refused() {
        let mut bytes = pcap(&[udp_frame(2368, b"ok")]);
        for v in [2_000u32, 0, 0xFFFF_FFF0, 0xFFFF_FFF0] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        bytes.extend_from_slice(&[0; 64]);
        let (got, error, _) = read_all(&bytes, None);
        assert_eq!(got.len(), 1);
        assert!(error.unwrap().contains("record 2"));
    }

    proptest! {
        /// Any bytes after a valid header, or a valid capture with damaged bytes: records
        /// or a named error, never a panic, never a datagram larger than its record.
        #[test]
        fn damaged_captures_end_with_a_named_error(
            payloads in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..300), 1..6),
            damage in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..12),
            cut in any::<prop::sample::Index>(),
        ) {
            let mut bytes = pcap(&payloads.iter().map(|p| udp_frame(2368, p)).collect::<Vec<_>>());
            for (at, b) in damage {
                let i = at.index(bytes.len());
                bytes[i] = b;
            }
            bytes.truncate(cut.index(bytes.len() + 1));
            let (got, _, c) = read_all(&bytes, None);
            prop_assert!(got.len() as u64 <= c.records);
            prop_assert!(got.iter().all(|(_, p)| p.len() <= 65_535));
        }
    }
}
