//! Times groundwork on scan files the way `patchwork_time.py` times Patchwork++: each scan
//! loaded once, segmented `--repeat` times, the median of all runs reported (JSON).
//!
//! `--sequence DIR` times the service's case instead: the sequence (with its poses) replayed
//! in order `--repeat` times, each replay by a fresh segmenter with the preset's history, and
//! every scan but a replay's first (which has no predecessor) timed. `--period-ms 100` paces
//! the replay as the service's producer paces a 10 Hz sensor: the cores idle between scans.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use groundwork_core::{Pose, Segmenter};
use groundwork_eval::median;
use groundwork_io::Sequence;

#[derive(Parser)]
struct Args {
    /// Segmentations per scan (with --sequence: replays of the sequence).
    #[arg(long, default_value_t = 20)]
    repeat: usize,
    /// Untimed warm-up runs per scan (with --sequence: replays).
    #[arg(long, default_value_t = 3)]
    warmup: usize,
    /// A sequence folder with poses.txt and calib.txt, streamed in order with history.
    #[arg(long, conflicts_with = "scans")]
    sequence: Option<PathBuf>,
    /// With --sequence: start a scan every this many milliseconds, idle in between, as the
    /// service's producer paces the sensor (0: back to back).
    #[arg(long, default_value_t = 0.0, requires = "sequence")]
    period_ms: f64,
    /// A configuration file (TOML) laid over the HDL-64E preset, as `groundwork --config`
    /// takes it: times a setting against the preset with the same binary.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Scan files, each segmented single-frame (no previous frame).
    #[arg(required_unless_present = "sequence")]
    scans: Vec<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    // On a CPU below the build's target the first vector instruction would be SIGILL.
    if let Err(e) = groundwork_core::cpu::check() {
        eprintln!("error: {e}");
        std::process::exit(3);
    }
    let args = Args::parse();
    let cfg = match &args.config {
        Some(path) => groundwork_io::load_config_over(Some("hdl64e"), Some(path))?,
        None => groundwork_benches::preset()?,
    };
    let max = cfg.sensor.max_points;
    let mut times = Vec::new();
    if let Some(dir) = &args.sequence {
        let seq = Sequence::open(dir, None, None)?;
        let mut scans: Vec<(Vec<groundwork_core::Point>, Pose)> = Vec::new();
        for item in seq.scans(max) {
            let pose = *seq
                .pose(item.index)
                .with_context(|| format!("{}: no poses.txt + calib.txt", dir.display()))?;
            scans.push((item.scan?.points, pose));
        }
        let frames = cfg.history.frames;
        let (mut fits, mut queries) = (Vec::new(), Vec::new());
        let period = std::time::Duration::from_secs_f64(args.period_ms.max(0.0) / 1e3);
        let mut last_start = Instant::now();
        for replay in 0..args.warmup + args.repeat {
            let mut seg = Segmenter::new(cfg.clone())?;
            for (i, (points, pose)) in scans.iter().enumerate() {
                let mut out = vec![0.0f32; points.len()];
                if let Some(wait) = period.checked_sub(last_start.elapsed()) {
                    std::thread::sleep(wait);
                }
                last_start = Instant::now();
                let t = Instant::now();
                let r = seg.segment(points, Some(pose), &mut out)?;
                if replay >= args.warmup && i > 0 {
                    times.push(t.elapsed().as_secs_f64() * 1e3);
                    fits.push(r.fit_time.as_secs_f64() * 1e3);
                    queries.push(r.query_time.as_secs_f64() * 1e3);
                }
            }
        }
        println!(
            "{}",
            serde_json::json!({ "median_ms": median(times.clone()), "fit_median_ms": median(fits), "query_median_ms": median(queries), "runs": times.len(), "history_frames": frames, "period_ms": args.period_ms })
        );
        return Ok(());
    }
    let mut seg = Segmenter::new(cfg)?;
    for path in &args.scans {
        let points = groundwork_io::read_scan(path, max)?.points;
        let mut out = vec![0.0f32; points.len()];
        for _ in 0..args.warmup {
            seg.segment(&points, None, &mut out)?;
        }
        for _ in 0..args.repeat {
            let t = Instant::now();
            seg.segment(&points, None, &mut out)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    println!(
        "{}",
        serde_json::json!({ "median_ms": median(times.clone()), "runs": times.len() })
    );
    Ok(())
}
