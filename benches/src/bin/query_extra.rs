//! The extra query time of N_f frames over one (issue 15, item 5), measured with the two
//! queries alternating: KITTI frame 5 against one frame and against N_f frames of history
//! (see `Frame5WithHistory`), one after the other, `--rounds` times. Each pair runs under
//! the same conditions of a shared VM, so the median of the per-pair differences is robust
//! where two separate criterion runs are not (on the 2-vCPU VMs here, how well the two cores
//! work together changes from minute to minute). Prints JSON.
//!
//! `cargo run --release -p groundwork-benches --bin query-extra -- --frames 16`

use std::time::Instant;

use clap::{Parser, ValueEnum};
use groundwork_benches::Frame5WithHistory;
use groundwork_core::config::PastQuery;
use groundwork_eval::median;

#[derive(Clone, Copy, ValueEnum)]
enum Query {
    Regridded,
    PerFrame,
}

#[derive(Parser)]
struct Args {
    /// History length N_f of the second query.
    #[arg(long, default_value_t = 16)]
    frames: u32,
    /// Which past components answer (`history.query`).
    #[arg(long, value_enum, default_value_t = Query::Regridded)]
    query: Query,
    /// Timed pairs.
    #[arg(long, default_value_t = 400)]
    rounds: usize,
    /// Untimed pairs first.
    #[arg(long, default_value_t = 50)]
    warmup: usize,
}

fn main() -> anyhow::Result<()> {
    // On a CPU below the build's target the first vector instruction would be SIGILL.
    if let Err(e) = groundwork_core::cpu::check() {
        eprintln!("error: {e}");
        std::process::exit(3);
    }
    let args = Args::parse();
    anyhow::ensure!(
        args.frames >= 1 && args.rounds >= 1,
        "--frames and --rounds must be ≥ 1"
    );
    let past = match args.query {
        Query::Regridded => PastQuery::Regridded,
        Query::PerFrame => PastQuery::PerFrame,
    };
    let mut one = Frame5WithHistory::new(1, past)?;
    let mut many = Frame5WithHistory::new(args.frames, past)?;
    let mut out = vec![0.0f32; one.points.len()];
    let (mut t1, mut tn, mut extra) = (Vec::new(), Vec::new(), Vec::new());
    for round in 0..args.warmup + args.rounds {
        let t = Instant::now();
        one.query(&mut out)?;
        let a = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let frames = many.query(&mut out)?;
        let b = t.elapsed().as_secs_f64() * 1e3;
        anyhow::ensure!(frames == args.frames as usize, "queried {frames} frames");
        if round >= args.warmup {
            t1.push(a);
            tn.push(b);
            extra.push(b - a);
        }
    }
    let quartiles = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        [v[v.len() / 4], v[v.len() * 3 / 4]]
    };
    println!(
        "{}",
        serde_json::json!({
            "frames": args.frames,
            "threads": rayon::current_num_threads(),
            "one_frame_median_ms": median(t1),
            "n_frames_median_ms": median(tn),
            "extra_median_ms": median(extra.clone()),
            "extra_quartiles_ms": quartiles(extra),
            "rounds": args.rounds,
        })
    );
    Ok(())
}
