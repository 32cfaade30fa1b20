//! Decoding a scan's packets into the points a scan sample holds (`count_scan`, then
//! `decode_scan` into a buffer the size of the scan, as the producer does into the loaned
//! sample): an HDL-64E scan built from KITTI frame 0 (about 120k returns, the factory
//! calibration's corrections), and the bundled VLP-16 and OS1-16 captures' scans. Beside it
//! stands the ROS 2 bridge's copy of a 124,668-point cloud (`benches/ros2.rs`, cloud_in).
//!
//! `cargo bench -p groundwork-benches --bench packets`

use std::path::PathBuf;

use criterion::{Criterion, criterion_group, criterion_main};
use groundwork_benches::kitti_frame;
use groundwork_msg::ScanPoint;
use groundwork_packets::velodyne::{Calibration, LaserCorrection, PACKET_SIZE};
use groundwork_packets::{
    Datagram, Decoder, Model, PacketScans, PcapSource, ScanPackets, SensorDecoder, ouster,
};

/// An HDL-64E S3's laser table, KITTI-like: elevations −24.9° to +2°, factory-style
/// corrections.
fn hdl64e_calibration() -> Calibration {
    let lasers = (0..64)
        .map(|k| LaserCorrection {
            laser_id: k,
            rot_correction: ((k % 8) as f32 - 4.0) * 0.005,
            vert_correction: (-24.9 + 26.9 * k as f32 / 63.0).to_radians(),
            dist_correction: 1.3,
            dist_correction_x: 1.35,
            dist_correction_y: 1.32,
            vert_offset_correction: 0.2,
            horiz_offset_correction: 0.026,
            max_intensity: 255.0,
            min_intensity: 0.0,
            focal_distance: 10.0,
            focal_slope: 1.0,
        })
        .collect();
    Calibration::new(0.002, lasers).expect("a valid table")
}

/// KITTI frame 0 as one turn of HDL-64E packets: each laser's nearest point per column.
fn hdl64e_scan() -> ScanPackets {
    let points = kitti_frame(0).expect("vendored frame");
    const COLUMNS: usize = 2_088;
    let mut grid = vec![0u16; COLUMNS * 64];
    for p in &points {
        let r = (p.x * p.x + p.y * p.y + p.z * p.z).sqrt();
        let az = (-p.y).atan2(p.x).to_degrees().rem_euclid(360.0);
        let el = (p.z / r).asin().to_degrees();
        let laser = ((el + 24.9) / 26.9 * 63.0).round();
        if !(0.0..64.0).contains(&laser) || r < 2.0 {
            continue;
        }
        let col = ((az / 360.0 * COLUMNS as f32) as usize).min(COLUMNS - 1);
        grid[col * 64 + laser as usize] = ((r - 1.3) / 0.002) as u16;
    }
    let mut scan = ScanPackets::default();
    let mut scans = PacketScans::new(SensorDecoder::Velodyne(Box::new(
        Decoder::new(Model::Hdl64eS3, Some(hdl64e_calibration())).expect("decoder"),
    )));
    // Six columns a packet (upper and lower banks), one turn and a packet to close it.
    for k in 0..=COLUMNS / 6 {
        let mut p = vec![0u8; PACKET_SIZE];
        for b in 0..12 {
            let col = (k * 6 + b / 2) % COLUMNS;
            let at = b * 100;
            let flag: u16 = if b % 2 == 0 { 0xEEFF } else { 0xDDFF };
            p[at..at + 2].copy_from_slice(&flag.to_le_bytes());
            let az = (col * 36_000 / COLUMNS) as u16;
            p[at + 2..at + 4].copy_from_slice(&az.to_le_bytes());
            for j in 0..32 {
                let d = grid[col * 64 + (b % 2) * 32 + j];
                p[at + 4 + j * 3..at + 6 + j * 3].copy_from_slice(&d.to_le_bytes());
                p[at + 6 + j * 3] = 40;
            }
        }
        let d = Datagram {
            time_ns: 1_000_000_000 + k as u64 * 288_000,
            port: 2368,
            payload: &p,
        };
        if scans.push(&d, 0, &mut scan) {
            break;
        }
    }
    scan
}

fn capture_scans(file: &str, decoder: SensorDecoder) -> (SensorDecoder, ScanPackets) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data/packets")
        .join(file);
    let mut src = PcapSource::open(&path, None).expect("bundled capture");
    let mut scans = PacketScans::new(decoder.clone()).quiet();
    let mut out = ScanPackets::default();
    let mut largest = ScanPackets::default();
    while let Some(Ok(d)) = src.next_datagram() {
        if scans.push(&d, 0, &mut out) && out.len() > largest.len() {
            largest = out.clone();
        }
    }
    (decoder, largest)
}

fn decode_into(decoder: &SensorDecoder, scan: &ScanPackets, sample: &mut Vec<ScanPoint>) -> usize {
    let n = decoder.count_scan(scan);
    sample.resize(n, ScanPoint::default());
    let mut k = 0;
    decoder.decode_scan(scan, |r| {
        sample[k] = ScanPoint {
            x: r.x,
            y: r.y,
            z: r.z,
            intensity: r.intensity,
        };
        k += 1;
    });
    k
}

fn per_scan(c: &mut Criterion) {
    let hdl = SensorDecoder::Velodyne(Box::new(
        Decoder::new(Model::Hdl64eS3, Some(hdl64e_calibration())).expect("decoder"),
    ));
    let hdl_scan = hdl64e_scan();
    let vlp = capture_scans(
        "vlp16-kitti-000001.pcap",
        SensorDecoder::Velodyne(Box::new(Decoder::new(Model::Vlp16, None).expect("decoder"))),
    );
    let meta = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data/packets/os1-16-kitti-000002.json");
    let os = capture_scans(
        "os1-16-kitti-000002.pcap",
        SensorDecoder::Ouster(Box::new(ouster::Decoder::new(
            ouster::Metadata::read(&meta).expect("bundled metadata"),
        ))),
    );
    let mut sample = Vec::new();
    let mut g = c.benchmark_group("packets_per_scan");
    g.sample_size(30);
    let n = decode_into(&hdl, &hdl_scan, &mut sample);
    eprintln!("hdl64e scan: {} packets, {n} returns", hdl_scan.len());
    g.bench_function("hdl64e_kitti_decode", |b| {
        b.iter(|| decode_into(&hdl, &hdl_scan, &mut sample))
    });
    for (name, (d, s)) in [
        ("vlp16_capture_decode", &vlp),
        ("os1_16_capture_decode", &os),
    ] {
        eprintln!("{name}: {} packets, {} returns", s.len(), d.count_scan(s));
        g.bench_function(name, |b| b.iter(|| decode_into(d, s, &mut sample)));
    }
    g.finish();
}

criterion_group!(benches, per_scan);
criterion_main!(benches);
