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
    /// Fragments of IP datagrams (not reassembled: no Velodyne packet is fragmented).
    pub fragments: u64,
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
}

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
            let fragmented = match &sliced.net {
                Some(etherparse::NetSlice::Ipv4(ip)) => ip.is_payload_fragmented(),
                Some(etherparse::NetSlice::Ipv6(ip)) => ip.is_payload_fragmented(),
                _ => false,
            };
            if fragmented {
                self.counters.fragments += 1;
                continue;
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
