//! A planner's view of a running pipeline: subscribes to its masks and proposals and prints,
//! per scan, the share of ground and the nearest object-like proposal.
//!
//! ```sh
//! groundwork pipeline &                                   # or any pipeline, --prefix P
//! cargo run -p groundwork-examples --bin nearest-obstacle -- [PREFIX] [COUNT]
//! ```
//!
//! The messages are read in place in shared memory; this process never blocks the pipeline
//! (a slow reader loses its oldest messages, counted by nobody but itself).

use std::time::Duration;

use groundwork_msg::{MaskStatus, ProposalRecord};
use groundwork_service::{ServiceConfig, signals, transport};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let prefix = args.next().unwrap_or_else(|| "groundwork".into());
    let count: u64 = args.next().map_or(Ok(u64::MAX), |c| c.parse())?;
    let cfg = ServiceConfig {
        prefix,
        ..ServiceConfig::default()
    };
    let node = transport::node(&cfg, "nearest-obstacle")?;
    signals::install(&node)?;
    let masks = transport::mask_subscriber(&transport::mask_service(&node, &cfg)?, &cfg)?;
    let proposals =
        transport::proposals_subscriber(&transport::proposals_service(&node, &cfg)?, &cfg)?;
    // The detector announces each proposals message; its masks arrived just before.
    let woken = transport::event_listener(&node, &cfg, "proposals")?;
    let mut seen = 0;
    while seen < count && transport::wait_or_stop(&woken, Duration::from_secs(1))? {
        while let Some(mask) = masks.receive()? {
            let h = mask.user_header();
            if h.status == MaskStatus::OK {
                let ground = mask.payload().iter().filter(|&&p| p >= 0.5).count();
                let share = 100.0 * ground as f64 / mask.payload().len().max(1) as f64;
                println!("scan {}: {share:.1} % ground", h.scan_sequence);
            }
        }
        while let Some(p) = proposals.receive()? {
            let h = p.user_header();
            let records = &h.records[..h.proposal_count as usize];
            // Object-like proposals (no flag: not a wall, not too large), by ground distance.
            let range = |r: &ProposalRecord| r.center[0].hypot(r.center[1]);
            match records
                .iter()
                .filter(|r| r.flags == 0)
                .min_by(|a, b| range(a).total_cmp(&range(b)))
            {
                Some(r) => println!(
                    "scan {}: nearest obstacle {} at {:.1} m ({:.1} × {:.1} m, {:.1} m high)",
                    h.scan_sequence,
                    r.id,
                    range(r),
                    r.length,
                    r.width,
                    r.height
                ),
                None => println!("scan {}: no obstacle", h.scan_sequence),
            }
            seen += 1;
        }
    }
    Ok(())
}
