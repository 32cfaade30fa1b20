//! A driver's side: publishes your own scans to a running segmenter and reads its answers.
//! Each scan is written straight into loaned shared memory (no copy after that), announced
//! on the scans event, and answered by a mask of one ground probability per point.
//!
//! ```sh
//! groundwork segmenter &                                  # or a pipeline without producer
//! cargo run -p groundwork-examples --bin publish-scans -- [PREFIX] [COUNT] [SCAN.bin]
//! ```

use std::time::{Duration, Instant};

use groundwork_msg::{MaskStatus, ScanHeader, ScanPoint, monotonic_ns, new_epoch};
use groundwork_service::{ServiceConfig, signals, transport};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let prefix = args.next().unwrap_or_else(|| "groundwork".into());
    let count: u64 = args.next().map_or(Ok(10), |c| c.parse())?;
    let file = args.next().unwrap_or_else(|| {
        concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../tests/data/semantickitti-00/velodyne/000000.bin"
        )
        .into()
    });
    // Your driver's points: here a KITTI scan, x, y, z, intensity as little-endian f32.
    let bytes = std::fs::read(&file)?;
    let points: Vec<ScanPoint> = bytes
        .chunks_exact(16)
        .map(|r| {
            let f =
                |k: usize| f32::from_le_bytes([r[4 * k], r[4 * k + 1], r[4 * k + 2], r[4 * k + 3]]);
            ScanPoint {
                x: f(0),
                y: f(1),
                z: f(2),
                intensity: f(3),
            }
        })
        .collect();
    let cfg = ServiceConfig {
        prefix,
        ..ServiceConfig::default()
    };
    // The producer's node name: the pipeline refuses a second producer.
    let node = transport::unique_node(&cfg, "producer")?;
    signals::install(&node)?;
    let scans = transport::scan_publisher(&transport::scan_service(&node, &cfg)?, &cfg)?;
    let announce = transport::event_notifier(&node, &cfg, "scans")?;
    let masks = transport::mask_subscriber(&transport::mask_service(&node, &cfg)?, &cfg)?;
    let answered = transport::event_listener(&node, &cfg, "masks")?;
    // A run of this producer: the segmenter starts a fresh history for a new epoch.
    let epoch = new_epoch();
    for sequence in 0..count {
        let sample = scans.loan_slice_uninit(points.len())?;
        let mut sample = sample.write_from_slice(&points);
        let now = monotonic_ns();
        let mut header = ScanHeader {
            point_count: points.len() as u32,
            sequence,
            producer_epoch: epoch,
            sensor_timestamp_ns: now,
            source_index: sequence,
            ..ScanHeader::default()
        };
        header.stamps.produced_ns = now;
        header.stamps.published_ns = monotonic_ns();
        *sample.user_header_mut() = header;
        sample.send()?;
        announce.notify()?;
        // Wait for the answer (a second at most), 10 Hz like a spinning LiDAR.
        let sent = Instant::now();
        'answer: while sent.elapsed() < Duration::from_secs(1) {
            if !transport::wait_or_stop(&answered, Duration::from_millis(100))? {
                return Ok(());
            }
            while let Some(mask) = masks.receive()? {
                let h = mask.user_header();
                if h.scan_sequence != sequence || h.producer_epoch != epoch {
                    continue;
                }
                if h.status != MaskStatus::OK {
                    println!("scan {sequence}: rejected ({})", h.status.name());
                } else {
                    let ground = mask.payload().iter().filter(|&&p| p >= 0.5).count();
                    println!(
                        "scan {sequence}: {} points, {ground} ground, answered in {:.1} ms",
                        mask.payload().len(),
                        sent.elapsed().as_secs_f64() * 1e3
                    );
                }
                break 'answer;
            }
        }
        std::thread::sleep(Duration::from_millis(100).saturating_sub(sent.elapsed()));
    }
    Ok(())
}
