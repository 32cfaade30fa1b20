//! `groundwork render`: a bird's-eye PNG of one scan, its ground and its proposals.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use groundwork_core::GroundFrame;
use groundwork_detect::{Detections, Detector, Proposal};
use groundwork_io::MethodsConfig;
use groundwork_io::{LabelMap, read_prob, read_scan, scan_stem};
use groundwork_viz::{Colouring, Scene, View, render};

use crate::args::ColourArg;
use crate::methods::{self, MethodArg};

/// Options of one picture.
#[derive(Debug)]
pub struct RenderJob<'a> {
    /// Configuration (sensor mount, methods, detector).
    pub config: &'a MethodsConfig,
    /// The scan.
    pub scan: &'a Path,
    /// A `.prob` file for it (else `method` segments it).
    pub mask: Option<&'a Path>,
    /// Method when no mask is given.
    pub method: MethodArg,
    /// A `.proposals.json` (else the detector runs when `detect` is set).
    pub proposals: Option<&'a Path>,
    /// Run the detector for the boxes.
    pub detect: bool,
    /// Colour errors against labels instead.
    pub compare: bool,
    /// Label file (default: `<sequence>/labels/<stem>.label` beside `velodyne/`).
    pub labels: Option<&'a Path>,
    /// Ground colouring.
    pub colour: ColourArg,
    /// Window.
    pub view: View,
    /// The PNG.
    pub out: &'a Path,
}

/// Where a scan's label file may be: its name in each of the folders every command looks
/// in ([`groundwork_io::label_folders`]).
fn label_candidates(scan: &Path) -> Vec<PathBuf> {
    let name = format!("{}.label", scan_stem(scan));
    groundwork_io::label_folders(scan)
        .into_iter()
        .map(|d| d.join(&name))
        .collect()
}

pub fn run(job: &RenderJob<'_>) -> Result<()> {
    let cfg = &job.config.segmenter;
    // The picture is never one of the files it is drawn from.
    let read: Vec<PathBuf> = [Some(job.scan), job.mask, job.proposals, job.labels]
        .into_iter()
        .flatten()
        .map(Path::to_path_buf)
        .chain(label_candidates(job.scan))
        .collect();
    let mut outputs = groundwork_io::OutputFiles::new(&read);
    outputs.claim(job.out)?;
    outputs.warn_replaced();
    let scan = read_scan(job.scan, cfg.sensor.max_points)?;
    let n = scan.points.len();
    let probs: Vec<f32> = match job.mask {
        Some(m) => {
            let all = read_prob(m)?;
            if all.len() != scan.records {
                bail!(
                    "{}: {} probabilities for a scan of {} records ({})",
                    m.display(),
                    all.len(),
                    scan.records,
                    job.scan.display()
                );
            }
            scan.select(all)
        }
        None => {
            let mut method = methods::build(job.method, job.config)?;
            let mut p = vec![0.0; n];
            method
                .segment_scan(&scan.points, None, &mut p)
                .map_err(|e| anyhow!("{}: {e}", job.scan.display()))?;
            p
        }
    };
    let proposals: Vec<Proposal> = match job.proposals {
        Some(p) => {
            #[derive(serde::Deserialize)]
            struct File {
                proposals: Vec<Proposal>,
            }
            let text = std::fs::read(p).with_context(|| format!("{}", p.display()))?;
            serde_json::from_slice::<File>(&text)
                .with_context(|| format!("{}: not a proposals file", p.display()))?
                .proposals
        }
        None if job.detect => {
            let mut d = Detector::new(job.config.detector.clone(), cfg)?;
            let mut out = Detections::default();
            d.detect(&scan.points, &probs, &mut out)
                .map_err(|e| anyhow!("{}: {e}", job.scan.display()))?;
            out.proposals
        }
        None => Vec::new(),
    };
    let frame = GroundFrame::from_config(cfg)?;
    let xyz = frame
        .prepare(&scan.points, &probs)
        .map_err(|e| anyhow!("{}: {e}", job.scan.display()))?
        .xyz;
    let truth: Vec<Option<bool>>;
    let colouring = if job.compare {
        let tried = label_candidates(job.scan);
        let path = job
            .labels
            .map(Path::to_path_buf)
            .or_else(|| tried.iter().find(|l| l.is_file()).cloned())
            .ok_or_else(|| {
                let tried: Vec<String> = tried.iter().map(|p| p.display().to_string()).collect();
                anyhow!(
                    "{}: --compare needs its label file: none at {} (give --labels F)",
                    job.scan.display(),
                    tried.join(" or ")
                )
            })?;
        let map = LabelMap::semantickitti();
        let classes = map.read(&path, scan.records)?;
        let protocol = groundwork_eval::Protocol::Gmm;
        truth = scan.select(classes.iter().map(|&c| protocol.truth(c)).collect());
        Colouring::Errors(&truth)
    } else {
        match job.colour {
            ColourArg::Height => Colouring::Height,
            ColourArg::Probability => Colouring::Probability,
        }
    };
    let scene = Scene {
        points: &xyz,
        probabilities: &probs,
        threshold: cfg.decision_threshold(),
        proposals: &proposals,
    };
    let png = render(&scene, colouring, job.view)?.to_png()?;
    outputs.write(job.out, &png)?;
    tracing::info!(
        out = %job.out.display(),
        points = n,
        proposals = proposals.len(),
        "picture written"
    );
    Ok(())
}
/// `groundwork render`.
pub fn command(a: crate::args::RenderArgs) -> Result<std::process::ExitCode> {
    run(&RenderJob {
        config: &crate::common::load_methods(&a.sensor.into(), None)?,
        scan: &a.scan,
        mask: a.mask.as_deref(),
        method: a.method,
        proposals: a.proposals.as_deref(),
        detect: a.detect,
        compare: a.compare,
        labels: a.labels.as_deref(),
        colour: a.colour,
        view: groundwork_viz::View {
            range: a.range,
            resolution: a.resolution,
        },
        out: &a.out,
    })?;
    Ok(std::process::ExitCode::SUCCESS)
}
