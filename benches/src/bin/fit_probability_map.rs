//! Fits a preset's probability map (`[probability] map`, docs/accuracy.md "Reliability") on
//! labelled scans of its sensor: segments every scan with the preset's map removed, pools
//! each scored point's equation value with its label (gmm protocol; the points the map
//! applies to, those binned into a segment) and prints the map to
//! paste into `config/sensors/<preset>.toml`, with the reliability before and after.
//!
//! `cargo run --release -p groundwork-benches --bin fit-probability-map -- --sensor hdl64e
//!  --frames 1 tests/data/semantickitti-00`

#![allow(clippy::unwrap_used)] // a measurement tool: a preset that does not load is a bug

use std::path::PathBuf;

use clap::Parser;
use groundwork_core::Segmenter;
use groundwork_core::probability::{ProbabilityMap, fit_map};
use groundwork_io::{LabelMap, Protocol, Reliability, Sequence, sensor_preset};

#[derive(Debug, Parser)]
#[command(about = "Fit a preset's probability map on labelled scans")]
struct Args {
    /// The preset whose map to fit.
    #[arg(long)]
    sensor: String,
    /// History length (default: the preset's); with poses beside the scans, as segment runs.
    #[arg(long)]
    frames: Option<u32>,
    /// Values of the map (equation values 0, 1/(n−1), …, 1).
    #[arg(long, default_value_t = 21)]
    knots: usize,
    /// Sequence folders (velodyne/ and labels/, SemanticKITTI ids).
    #[arg(required = true)]
    sequences: Vec<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let mut cfg = sensor_preset(&a.sensor)?;
    cfg.probability.map.clear();
    if let Some(f) = a.frames {
        cfg.history.frames = f;
    }
    let labels = LabelMap::load("semantickitti")?;
    let mut samples: Vec<(f32, bool)> = Vec::new();
    for dir in &a.sequences {
        let seq = Sequence::open(dir, None, None)?.with_label_map(labels.clone());
        let mut seg = Segmenter::new(cfg.clone())?;
        for item in seq.scans(cfg.sensor.max_points) {
            let scan = item.scan.as_ref().map_err(|e| anyhow::anyhow!("{e}"))?;
            let mut probs = vec![0.0f32; scan.points.len()];
            seg.segment(&scan.points, seq.pose(item.index), &mut probs)?;
            let Some(path) = seq.label_path(&item) else {
                continue;
            };
            let classes = seq.label_map.read(&path, scan.records)?;
            // Only the points the map applies to (the others stay 0).
            let judged: Vec<bool> = seg.judged_points(probs.len()).collect();
            let all = scan.expand(&probs, 0.0);
            let judged = scan.expand(&judged, false);
            samples.extend(
                all.iter()
                    .zip(&classes)
                    .zip(&judged)
                    .filter(|(_, j)| **j)
                    .filter_map(|((&p, &c), _)| Protocol::Gmm.truth(c).map(|t| (p, t))),
            );
        }
    }
    let map = fit_map(&samples, a.knots);
    let before = reliability(&samples);
    let fitted = ProbabilityMap::new(
        &groundwork_core::config::ProbabilityConfig { map: map.clone() },
        cfg.ground.ground_threshold,
    );
    let mapped: Vec<(f32, bool)> = samples
        .iter()
        .map(|&(p, t)| {
            let mut o = [p];
            fitted.apply(&mut o, &[true], |&j| j);
            (o[0], t)
        })
        .collect();
    let after = reliability(&mapped);
    println!(
        "# {} scored points; ECE {:.3} -> {:.3}; threshold {} -> {:.4}",
        samples.len(),
        before.expected_calibration_error(),
        after.expected_calibration_error(),
        cfg.ground.ground_threshold,
        fitted.threshold()
    );
    for (name, r) in [("before", before), ("after", after)] {
        println!("# {name}: bin, points, mean probability, ground fraction");
        for b in r.bins() {
            println!(
                "#   {:.1}  {:>8}  {:.3}  {:.3}",
                b.from, b.points, b.mean_probability, b.ground_fraction
            );
        }
    }
    let values: Vec<String> = map.iter().map(|v| format!("{v}")).collect();
    println!("[probability]\nmap = [{}]", values.join(", "));
    Ok(())
}

fn reliability(samples: &[(f32, bool)]) -> Reliability {
    let (p, c): (Vec<f32>, Vec<groundwork_io::LabelClass>) = samples
        .iter()
        .map(|&(p, t)| {
            (
                p,
                if t {
                    groundwork_io::LabelClass::Ground
                } else {
                    groundwork_io::LabelClass::NonGround
                },
            )
        })
        .unzip();
    Reliability::from_predictions(&p, &c, Protocol::Gmm)
}
