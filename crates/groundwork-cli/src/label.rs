//! `groundwork label`: a per-scan method over a whole dataset, offline.
//!
//! Parallel across scans on all cores; resumable (a scan whose `.prob` and `.ground` are both
//! complete is skipped, and outputs are written under temporary names and renamed, `.ground`
//! last); shardable with no coordination (`--shard i/n` keeps the scans whose place in the
//! sorted list is i modulo n); a bad scan is reported in the summary and the job goes on.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Result, bail};
use groundwork_core::{Point, SegmentError};
use groundwork_io::MethodsConfig;
use groundwork_io::{InputKind, outputs_complete, read_scan, scan_stem};
use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, Ransac};
use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::Serialize;
use tracing::{error, info};

use crate::args::{LabelMethod, Shard};

/// The per-scan methods `label` runs (shared by all threads: labelling takes `&self`).
enum PerScan {
    PseudoLabeler(PseudoLabeler),
    Ransac(Ransac),
}

impl PerScan {
    fn label(&self, points: &[Point], out: &mut [f32]) -> Result<(), SegmentError> {
        match self {
            Self::PseudoLabeler(m) => m.label(points, out).map(|_| ()),
            Self::Ransac(m) => m.label(points, out).map(|_| ()),
        }
    }
}

/// A scan that could not be labelled.
#[derive(Debug, Clone, Serialize)]
pub struct Failure {
    /// The scan file.
    pub scan: PathBuf,
    /// Why.
    pub reason: String,
}

/// What a `label` run did (written as JSON next to the outputs).
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// Method used.
    pub method: String,
    /// Shard `i/n`.
    pub shard: String,
    /// Scans in the inputs (all shards).
    pub scans_in_inputs: usize,
    /// Scans in this shard.
    pub scans: usize,
    /// Scans labelled by this run.
    pub labelled: usize,
    /// Stems of the scans labelled by this run, sorted.
    pub labelled_scans: Vec<String>,
    /// Scans skipped because their outputs were complete (a resumed run).
    pub skipped_complete: usize,
    /// Scans of this shard whose labels are complete now (labelled + skipped_complete):
    /// the figures below describe all of them, whichever run labelled them.
    pub complete: usize,
    /// Scans that could not be labelled.
    pub failures: Vec<Failure>,
    /// Points of the complete scans (their `.ground` files).
    pub points: u64,
    /// Of which ground.
    pub ground_points: u64,
    /// ground_points / points.
    pub ground_fraction: f64,
    /// Points labelled by this run.
    pub points_labelled_now: u64,
    /// Wall time, s.
    pub seconds: f64,
    /// Scans labelled per second of wall time.
    pub scans_per_second: f64,
    /// Median time to label one scan, ms (several run at once).
    pub median_ms_per_scan: f64,
}

/// The scan files of the inputs (a sequence folder's `velodyne/`, a folder's scans, or a
/// file), sorted, with unique stems (outputs are named after them).
pub fn collect_scans(inputs: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let velodyne = input.join("velodyne");
            let dir = if velodyne.is_dir() { &velodyne } else { input };
            let found = groundwork_io::list_folder(dir)?;
            if let Some(rec) = found.recordings.first() {
                bail!(
                    "{}: label takes scan files; a recording is labelled by \
                     `groundwork segment --method pseudolabeler --out X.mcap`",
                    rec.display()
                );
            }
            files.extend(found.scans);
        } else {
            if matches!(InputKind::detect(input)?, InputKind::Recording) {
                bail!(
                    "{}: label takes scan files and folders; a recording is labelled by \
                     `groundwork segment --method pseudolabeler --out X.mcap`",
                    input.display()
                );
            }
            files.push(input.clone());
        }
    }
    files.sort();
    files.dedup();
    // Outputs are named after the scans: two scans of one name would overwrite each other.
    groundwork_io::check_output_names(&[&groundwork_io::ScanSource::Files(files.clone())])?;
    Ok(files)
}

enum Outcome {
    Labelled {
        stem: String,
        points: u64,
        ground: u64,
        ms: f64,
    },
    /// Complete before this run: its points and ground points, from its `.ground` file.
    Skipped {
        points: u64,
        ground: u64,
    },
    Failed(Failure),
}

/// Runs the job; exit code 1 when some scan failed (all others are labelled).
pub fn run(
    cfg: &MethodsConfig,
    method: LabelMethod,
    out: &Path,
    shard: Shard,
    overwrite: bool,
    inputs: &[PathBuf],
) -> Result<ExitCode> {
    let frame = GroundFrame::from_config(&cfg.segmenter)?;
    let labeler = match method {
        LabelMethod::Pseudolabeler => {
            PerScan::PseudoLabeler(PseudoLabeler::new(cfg.pseudolabeler.clone(), frame)?)
        }
        LabelMethod::Ransac => PerScan::Ransac(Ransac::new(cfg.ransac.clone(), frame)?),
    };
    let all = collect_scans(inputs)?;
    let mine: Vec<&PathBuf> = all
        .iter()
        .enumerate()
        .filter(|&(k, _)| shard.contains(k))
        .map(|(_, f)| f)
        .collect();
    // The folder as every offline command takes it (never an input, writable), and the
    // summary through the one output path.
    groundwork_io::OutputTarget::create(out, &all)?;
    let summary_path = out.join(if shard.count == 1 {
        "label-summary.json".to_string()
    } else {
        format!("label-summary-{}-of-{}.json", shard.index, shard.count)
    });
    let mut outputs = groundwork_io::OutputFiles::new(&all);
    outputs.claim(&summary_path)?;
    info!(
        method = %format!("{method:?}").to_lowercase(),
        shard = %shard,
        scans = mine.len(),
        of = all.len(),
        out = %out.display(),
        "labelling"
    );
    let pb = ProgressBar::new(mine.len() as u64);
    pb.set_style(crate::common::progress_style(
        "label [{bar:30}] {pos}/{len} scans, {rate}, elapsed {elapsed}, eta {eta}",
    ));
    let max = cfg.segmenter.sensor.max_points;
    let t = Instant::now();
    // Scans in parallel; each scan's own fit is deterministic whatever the thread count.
    let outcomes: Vec<Outcome> = mine
        .par_iter()
        .map(|&path| {
            let stem = scan_stem(path);
            let done = (!overwrite && outputs_complete(out, &stem))
                .then(|| std::fs::read(out.join(format!("{stem}.ground"))).ok())
                .flatten();
            let outcome = if let Some(mask) = done {
                Outcome::Skipped {
                    points: mask.len() as u64,
                    ground: mask.iter().filter(|&&g| g == 1).count() as u64,
                }
            } else {
                let t = Instant::now();
                let result = (|| -> Result<(u64, u64), String> {
                    let scan = read_scan(path, max).map_err(|e| e.to_string())?;
                    let mut probs = vec![0.0f32; scan.points.len()];
                    labeler
                        .label(&scan.points, &mut probs)
                        .map_err(|e| format!("{}: {e}", path.display()))?;
                    // One value per record of the input (placeholders: 0).
                    let all = scan.expand(&probs, 0.0);
                    groundwork_io::write_outputs(out, &stem, &all, 0.5)
                        .map_err(|e| e.to_string())?;
                    let ground = all.iter().filter(|&&p| p >= 0.5).count() as u64;
                    Ok((all.len() as u64, ground))
                })();
                match result {
                    Ok((points, ground)) => Outcome::Labelled {
                        stem,
                        points,
                        ground,
                        ms: t.elapsed().as_secs_f64() * 1e3,
                    },
                    Err(reason) => {
                        pb.suspend(|| error!("skipped: {reason}"));
                        Outcome::Failed(Failure {
                            scan: path.to_path_buf(),
                            reason,
                        })
                    }
                }
            };
            pb.inc(1);
            outcome
        })
        .collect();
    pb.finish_and_clear();
    let seconds = t.elapsed().as_secs_f64();

    let mut s = Summary {
        method: format!("{method:?}").to_lowercase(),
        shard: shard.to_string(),
        scans_in_inputs: all.len(),
        scans: mine.len(),
        labelled: 0,
        labelled_scans: Vec::new(),
        skipped_complete: 0,
        complete: 0,
        failures: Vec::new(),
        points: 0,
        ground_points: 0,
        ground_fraction: 0.0,
        points_labelled_now: 0,
        seconds,
        scans_per_second: 0.0,
        median_ms_per_scan: 0.0,
    };
    let mut times = Vec::new();
    for o in outcomes {
        match o {
            Outcome::Labelled {
                stem,
                points,
                ground,
                ms,
            } => {
                s.labelled += 1;
                s.labelled_scans.push(stem);
                s.points += points;
                s.points_labelled_now += points;
                s.ground_points += ground;
                times.push(ms);
            }
            Outcome::Skipped { points, ground } => {
                s.skipped_complete += 1;
                s.points += points;
                s.ground_points += ground;
            }
            Outcome::Failed(f) => s.failures.push(f),
        }
    }
    s.labelled_scans.sort();
    s.complete = s.labelled + s.skipped_complete;
    s.ground_fraction = if s.points > 0 {
        s.ground_points as f64 / s.points as f64
    } else {
        0.0
    };
    s.scans_per_second = if seconds > 0.0 {
        s.labelled as f64 / seconds
    } else {
        0.0
    };
    s.median_ms_per_scan = groundwork_eval::median(times);
    let path = summary_path;
    outputs.write(&path, serde_json::to_string_pretty(&s)?.as_bytes())?;
    println!(
        "label ({}, shard {}): {} scans labelled, {} already complete, {} failed; {} points in the complete scans, {:.1} % ground; {:.1} s, {:.2} scans/s; summary {}",
        s.method,
        s.shard,
        s.labelled,
        s.skipped_complete,
        s.failures.len(),
        s.points,
        100.0 * s.ground_fraction,
        s.seconds,
        s.scans_per_second,
        path.display()
    );
    Ok(if s.failures.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// `groundwork label`.
pub fn command(a: crate::args::LabelArgs) -> Result<ExitCode> {
    run(
        &crate::common::load_methods(&a.sensor.into(), None)?,
        a.method,
        &a.out,
        a.shard.unwrap_or_default(),
        a.overwrite,
        &a.inputs,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::args::parse_shard;

    #[test]
    fn shards_partition_any_list_exactly() {
        for n in 1..=7u64 {
            let shards: Vec<Shard> = (0..n).map(|index| Shard { index, count: n }).collect();
            for k in 0..100 {
                assert_eq!(shards.iter().filter(|s| s.contains(k)).count(), 1);
            }
        }
        assert_eq!(parse_shard("2/8"), Ok(Shard { index: 2, count: 8 }));
        for bad in ["8/8", "1/0", "x/2", "3", "-1/2"] {
            assert!(parse_shard(bad).is_err(), "{bad}");
        }
    }
}
