//! What the peer tests share: finding the peer's Python, running the fixture scripts, reading
//! the references they write, and decoding a capture scan by scan the way the producer does.

use std::path::{Path, PathBuf};
use std::process::Command;

use groundwork_packets::{PacketScans, PcapSource, ScanPackets};

/// The workspace root.
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A fixture script's path, as an argument.
pub fn script(name: &str) -> String {
    root()
        .join("scripts/fixtures")
        .join(name)
        .display()
        .to_string()
}

/// A path as an argument.
pub fn arg(p: &Path) -> String {
    p.display().to_string()
}

/// The Python that has the peers, or `None` (the test is skipped) unless
/// `GROUNDWORK_REQUIRE_PACKET_PEERS` asks for them.
pub fn peer_python() -> Option<PathBuf> {
    match std::env::var_os("GROUNDWORK_PACKET_PEERS_PYTHON") {
        Some(p) => Some(PathBuf::from(p)),
        None => {
            assert!(
                std::env::var_os("GROUNDWORK_REQUIRE_PACKET_PEERS").is_none(),
                "GROUNDWORK_REQUIRE_PACKET_PEERS is set but GROUNDWORK_PACKET_PEERS_PYTHON is not"
            );
            eprintln!("skipped: GROUNDWORK_PACKET_PEERS_PYTHON is not set");
            None
        }
    }
}

/// Runs a script; its failure fails the test with its stderr.
pub fn run(python: &Path, args: &[String]) {
    let out = Command::new(python).args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A reference file of the fixture scripts: blocks of a u32 count, a `header`-byte header,
/// then that many records of `N` little-endian floats of `width` bytes (4 or 8).
pub fn read_reference<const N: usize>(
    path: &Path,
    header: usize,
    width: usize,
) -> Vec<(Vec<u8>, Vec<[f64; N]>)> {
    let b = std::fs::read(path).unwrap();
    let value = |o: usize| match width {
        4 => f32::from_le_bytes(b[o..o + 4].try_into().unwrap()) as f64,
        _ => f64::from_le_bytes(b[o..o + 8].try_into().unwrap()),
    };
    let mut blocks = Vec::new();
    let mut at = 0;
    while at < b.len() {
        let n = u32::from_le_bytes(b[at..at + 4].try_into().unwrap()) as usize;
        let head = b[at + 4..at + 4 + header].to_vec();
        at += 4 + header;
        let records = (0..n)
            .map(|i| std::array::from_fn(|c| value(at + (i * N + c) * width)))
            .collect();
        at += n * N * width;
        blocks.push((head, records));
    }
    blocks
}

/// Decodes `pcap` (datagrams to `port`) scan by scan, handing each finished scan to `take`;
/// gives back the source for its counters.
pub fn for_each_scan(
    scans: &mut PacketScans,
    pcap: &Path,
    port: u16,
    mut take: impl FnMut(&PacketScans, &ScanPackets),
) -> PcapSource {
    let mut source = PcapSource::open(pcap, Some(port)).unwrap();
    let mut out = ScanPackets::default();
    while let Some(d) = source.next_datagram() {
        if scans.push(&d.unwrap(), 0, &mut out) {
            take(scans, &out);
        }
    }
    if scans.flush(0, &mut out) {
        take(scans, &out);
    }
    source
}
