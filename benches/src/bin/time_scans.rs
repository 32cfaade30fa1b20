//! Times groundwork on scan files the way `patchwork_time.py` times Patchwork++: each scan
//! loaded once, segmented `--repeat` times, the median of all runs reported (JSON).

use std::path::PathBuf;
use std::time::Instant;

use clap::Parser;
use groundwork_core::Segmenter;
use groundwork_eval::median;

#[derive(Parser)]
struct Args {
    /// Segmentations per scan.
    #[arg(long, default_value_t = 20)]
    repeat: usize,
    /// Untimed warm-up runs per scan.
    #[arg(long, default_value_t = 3)]
    warmup: usize,
    /// Scan files.
    scans: Vec<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    // On a CPU below the build's target the first vector instruction would be SIGILL.
    if let Err(e) = groundwork_core::cpu::check() {
        eprintln!("error: {e}");
        std::process::exit(3);
    }
    let args = Args::parse();
    let cfg = groundwork_benches::preset()?;
    let max = cfg.sensor.max_points;
    let mut seg = Segmenter::new(cfg)?;
    let mut times = Vec::new();
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
