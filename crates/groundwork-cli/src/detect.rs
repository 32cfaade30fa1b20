//! `groundwork detect`: ground segmentation, then the fallback detector, over scans offline.
//! Per scan `<stem>.proposals.json` and `<stem>.clusters`; where the scans have instance
//! labels (a SemanticKITTI-layout sequence), the labeled objects found are reported.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Result, anyhow};
use groundwork_detect::Proposal;
use groundwork_detect::{Detections, Detector};
use groundwork_eval::{ObjectScore, median, score_objects};
use groundwork_io::MethodsConfig;
use groundwork_io::Sequence;
use groundwork_io::{OutputTarget, write_atomic};
use tracing::{error, info};

use crate::methods::{self, MethodArg};

/// Labeled objects with fewer points are not scored.
const MIN_OBJECT_POINTS: usize = 20;

/// Options of one run.
#[derive(Debug)]
pub struct DetectJob<'a> {
    /// Configuration (segmenter, methods, `[detector]`).
    pub config: &'a MethodsConfig,
    /// Ground segmentation method.
    pub method: MethodArg,
    /// Output folder.
    pub out: &'a Path,
    /// Scan files or folders.
    pub inputs: &'a [PathBuf],
    /// Poses / calibration files for history (GMM).
    pub poses: Option<&'a Path>,
    /// See `poses`.
    pub calib: Option<&'a Path>,
    /// PointCloud2 topic of recordings.
    pub topic: Option<String>,
}

pub fn run(job: &DetectJob<'_>) -> Result<ExitCode> {
    let mut detector = Detector::new(job.config.detector.clone(), &job.config.segmenter)?;
    let max = job.config.segmenter.sensor.max_points;
    let (sequences, mut failed) =
        crate::common::open_inputs(job.inputs, job.poses, job.calib, job.topic.as_deref())?;
    if !matches!(
        crate::common::create_output(
            job.out,
            job.inputs,
            &sequences,
            &[".proposals.json", ".clusters"],
        )?,
        OutputTarget::Files(_)
    ) {
        anyhow::bail!(
            "{}: detect writes a folder of .proposals.json and .clusters files, not a recording",
            job.out.display()
        );
    }
    let known: Option<usize> = sequences.iter().map(Sequence::len_hint).sum();
    let pb = crate::common::progress(known.unwrap_or(0), "detect");
    let (mut scans, mut proposals) = (0usize, 0usize);
    let (mut seg_ms, mut det_ms) = (Vec::new(), Vec::new());
    let mut score: Option<ObjectScore> = None;
    let mut out = Detections::default();
    let mut probs = Vec::new();
    for seq in &sequences {
        // A fresh method per input: the history of one sequence says nothing of the next.
        let mut method = methods::build(job.method, job.config)?;
        for item in seq.scans(max) {
            if known.is_none() {
                pb.inc_length(1);
            }
            scans += 1;
            let result = (|| -> Result<()> {
                let scan = item.scan.as_ref().map_err(|e| anyhow!("{e}"))?;
                probs.resize(scan.points.len(), 0.0);
                let t = Instant::now();
                method
                    .segment_scan(&scan.points, seq.pose(item.index), &mut probs)
                    .map_err(|e| anyhow!("{}: {e}", item.name))?;
                seg_ms.push(t.elapsed().as_secs_f64() * 1e3);
                let r = detector
                    .detect(&scan.points, &probs, &mut out)
                    .map_err(|e| anyhow!("{}: {e}", item.name))?;
                det_ms.push(r.time.as_secs_f64() * 1e3);
                proposals += out.proposals.len();
                // One id per record of the input: placeholders get 0.
                let clusters = scan.expand(&out.clusters, 0);
                write_detections(job.out, &item.name, &out.proposals, &clusters)?;
                if let Some(l) = seq.label_path(&item) {
                    let labels = seq.label_map.read_raw(&l, scan.records)?;
                    let xy: Vec<[f32; 2]> = scan.points.iter().map(|p| [p.x, p.y]).collect();
                    let expanded_xy = scan.expand(&xy, [0.0, 0.0]);
                    score.get_or_insert_default().merge(score_objects(
                        &item.name,
                        &labels,
                        &clusters,
                        &expanded_xy,
                        &out.proposals,
                        MIN_OBJECT_POINTS,
                    ));
                }
                Ok(())
            })();
            if let Err(e) = result {
                // One bad scan never costs the others.
                failed += 1;
                pb.suspend(|| error!("skipped: {e:#}"));
            }
            pb.inc(1);
        }
    }
    pb.finish_and_clear();
    info!(
        method = job.method.name(),
        scans,
        failed,
        proposals,
        segment_median_ms = median(seg_ms),
        detect_median_ms = median(det_ms),
        out = %job.out.display(),
        "detect done"
    );
    if let Some(s) = score {
        println!(
            "labeled objects (≥ {MIN_OBJECT_POINTS} points) found by a proposal (point IoU > 0.5):"
        );
        print!("{}", s.table());
    }
    Ok(if failed > 0 {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}
/// The frame and units `.proposals.json` states (and docs/detector.md repeats).
pub const PROPOSALS_FRAME: &str = "ground-aligned sensor frame: x forward, y left, z up, origin on the ground below the sensor (the sensor preset's mount); metres, radians";

/// `<stem>.proposals.json`.
#[derive(Debug, serde::Serialize)]
struct ProposalsFile<'a> {
    scan: &'a str,
    frame: &'static str,
    points: usize,
    proposals: &'a [Proposal],
}

/// Writes `<dir>/<stem>.proposals.json` (the proposals, their frame and units) and
/// `<dir>/<stem>.clusters` (one little-endian u32 per point: the proposal id, 0 for ground
/// and unclustered points), each through a temporary name; `.clusters` is renamed last.
pub fn write_detections(
    dir: &Path,
    stem: &str,
    proposals: &[Proposal],
    clusters: &[u32],
) -> Result<()> {
    let file = ProposalsFile {
        scan: stem,
        frame: PROPOSALS_FRAME,
        points: clusters.len(),
        proposals,
    };
    let path = dir.join(format!("{stem}.proposals.json"));
    let json = serde_json::to_vec_pretty(&file)?;
    write_atomic(&path, &json)?;
    let ids: Vec<u8> = clusters.iter().flat_map(|c| c.to_le_bytes()).collect();
    Ok(write_atomic(&dir.join(format!("{stem}.clusters")), &ids)?)
}

/// `groundwork detect`.
pub fn command(a: crate::args::DetectArgs) -> Result<ExitCode> {
    run(&DetectJob {
        config: &crate::common::load_methods(&a.common, None)?,
        method: a.method,
        out: &a.out,
        inputs: &a.inputs,
        poses: a.common.poses.as_deref(),
        calib: a.common.calib.as_deref(),
        topic: a.common.topic.clone(),
    })
}
