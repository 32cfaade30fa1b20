//! `groundwork calibrate`: the sensor's mount from raw scans, written as a configuration to
//! lay over the preset it started from, with a report.
//!
//! This reads the scans (every k-th where the inputs' length is known, so that
//! `--max-scans` spreads over the whole drive), shows progress and writes the files; the
//! calibration itself is `groundwork_calibrate::calibrate`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Result, bail};
use groundwork_calibrate::{
    CalibrateOptions, CalibrateProgress, FitProgress, MountSearchConfig, ParamSearchConfig,
    ScanInput, calibrate,
};
use groundwork_io::Sequence;
use tracing::{error, info, warn};

use crate::args::CalibrateArgs;
use crate::common::{open_inputs, progress};

pub fn command(a: CalibrateArgs) -> Result<ExitCode> {
    let t = Instant::now();
    let (base, methods) = crate::common::load_named(&a.sensor.into(), None)?;
    anyhow::ensure!(a.max_scans > 0, "--max-scans must be at least 1");
    anyhow::ensure!(a.param_scans > 0, "--param-scans must be at least 1");
    let search = param_search(a.param_trust, a.param_min_gain, a.fit_zones)?;
    let (sequences, skipped_inputs) = open_inputs(&a.inputs, None, None, a.topic.as_deref())?;
    // The file and the report: never an input, never the same file, never half-written.
    let outputs = claim_outputs(
        &a.inputs,
        &sequences,
        &a.out,
        a.report.as_ref(),
        a.overwrite,
    )?;
    let max_points = methods.segmenter.sensor.max_points;
    let spread = Spread::over(&sequences, a.max_scans, max_points);
    let options = CalibrateOptions {
        mount: MountSearchConfig {
            seed: a.seed,
            ..MountSearchConfig::default()
        },
        keep_zones: a.keep_zones,
        params: (!a.keep_params).then_some(search),
        param_scans: a.param_scans,
        ..CalibrateOptions::new(&base, preset_mount(&base), spread.looked)
    };
    options.validate()?;
    info!(base = %base, inputs = a.inputs.len(), scans = ?spread.total, every = spread.every,
        "finding the mount");
    let bars = Bars::new(spread.looked);
    let calibration = calibrate(
        spread.scans(&sequences, max_points),
        &methods.segmenter,
        &methods.pseudolabeler,
        &options,
        |p| bars.show(p),
    )?;
    bars.finish();
    warn_about(&calibration, &options);
    if let Some(path) = &a.report {
        let json = serde_json::to_string_pretty(&calibration)? + "\n";
        outputs.write(path, json.as_bytes())?;
    }
    if let Err(e) = calibration.estimate() {
        bail!("{e} (nothing written to {})", a.out.display());
    }
    let name = a
        .out
        .file_stem()
        .map_or_else(|| "calibrated".into(), |s| s.to_string_lossy().into_owned());
    let inputs: Vec<String> = a.inputs.iter().map(|p| p.display().to_string()).collect();
    outputs.write(&a.out, calibration.to_toml(&name, &inputs)?.as_bytes())?;
    print!("{}", calibration.summary());
    let (out, seconds) = (a.out.display(), t.elapsed().as_secs_f64());
    println!("wrote {out} (use: --sensor {base} --config {out}) in {seconds:.1} s");
    let failed = calibration.unreadable + skipped_inputs > 0;
    Ok(if failed {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}

/// The parameter search the flags ask for, checked before anything is read and refused by
/// the flag the user typed.
fn param_search(trust: f64, min_gain: f64, fit_zones: bool) -> Result<ParamSearchConfig> {
    let search = ParamSearchConfig {
        trust_agreement: trust,
        min_held_out_gain: min_gain,
        fit_zones,
        ..ParamSearchConfig::default()
    };
    search.check().map_err(|(field, why)| {
        let flag = match field {
            "trust_agreement" => "--param-trust",
            "min_held_out_gain" => "--param-min-gain",
            other => other,
        };
        anyhow::anyhow!("{flag}: {why}")
    })?;
    Ok(search)
}

/// `--out` and `--report` claimed before anything is read: never an input, never the same
/// file; an existing one only with `--overwrite`.
fn claim_outputs(
    inputs: &[PathBuf],
    sequences: &[Sequence],
    out: &PathBuf,
    report: Option<&PathBuf>,
    overwrite: bool,
) -> Result<groundwork_io::OutputFiles> {
    let mut outputs =
        groundwork_io::OutputFiles::new(&crate::common::input_files(inputs, sequences));
    for path in std::iter::once(out).chain(report) {
        outputs.claim(path)?;
    }
    if let (Some(first), false) = (outputs.existing().first(), overwrite) {
        bail!(
            "{}: exists; pass --overwrite to replace it",
            first.display()
        );
    }
    outputs.warn_replaced();
    Ok(outputs)
}

/// Which scans are looked at: every `every`-th, at most `looked` of them, spread over the
/// whole inputs where their length is known (a recording's scans are counted first, a
/// pass without decoding them).
struct Spread {
    total: Option<usize>,
    every: usize,
    looked: usize,
    max_scans: usize,
}

impl Spread {
    fn over(sequences: &[Sequence], max_scans: usize, max_points: usize) -> Self {
        let total: Option<usize> = sequences
            .iter()
            .map(|s| match &s.source {
                groundwork_io::ScanSource::Recording { path, topic } => {
                    groundwork_io::RecordingReader::count(path, topic.as_deref(), max_points).ok()
                }
                groundwork_io::ScanSource::Files(_) => s.len_hint(),
            })
            .sum();
        let every = total.map_or(1, |n| n.div_ceil(max_scans).max(1));
        let looked = total.map_or(max_scans, |n| n.div_ceil(every).min(max_scans));
        Self {
            total,
            every,
            looked,
            max_scans,
        }
    }

    /// The scans looked at, each with its place among all the inputs' scans (its seed).
    fn scans<'a>(
        &self,
        sequences: &'a [Sequence],
        max_points: usize,
    ) -> impl Iterator<Item = ScanInput> + Send + 'a {
        let every = self.every;
        sequences
            .iter()
            .flat_map(move |s| s.scans(max_points))
            .enumerate()
            .filter(move |(k, _)| k % every == 0)
            .take(self.max_scans)
            .map(|(k, item)| ScanInput {
                place: k as u64,
                name: item.name,
                points: item
                    .scan
                    .map(|scan| scan.points.iter().map(|p| [p.x, p.y, p.z]).collect())
                    .map_err(|e| e.to_string()),
            })
    }
}

/// The warnings a calibration carries: scans outvoted in height, a mount seen from one
/// side, parameters not fitted.
fn warn_about(calibration: &groundwork_calibrate::Calibration, options: &CalibrateOptions) {
    if let (Some(est), false) = (&calibration.mount, calibration.disagreeing.is_empty()) {
        let named: Vec<String> = calibration
            .disagreeing
            .iter()
            .map(|(name, height)| format!("{name} ({height:.2} m)"))
            .collect();
        warn!(
            "{} of {} scans disagree with the mount found by more than {:.2} m in height, and \
             were outvoted: {}; scans of another sensor or mount among the inputs?",
            named.len(),
            est.frames_used,
            options.mount.max_height_spread,
            named.join(", ")
        );
    }
    if let Some(why) = calibration.too_few_trusted_points() {
        warn!("parameters not fitted, the preset's kept: {why}");
    } else if let Some(why) = &calibration.parameters_refused {
        warn!("parameters not fitted, the preset's kept: {why}");
    }
    if let Some(o) = calibration
        .mount
        .as_ref()
        .and_then(|m| m.one_sided.as_ref())
    {
        warn!("{o}");
    }
}

/// The mount the preset's own zone layout was made for.
fn preset_mount(base: &str) -> Option<groundwork_core::config::MountConfig> {
    groundwork_io::sensor_preset(base)
        .ok()
        .map(|p| p.sensor.mount)
}

/// The progress bars: the scans looked at, then the PseudoLabeler's labelling of the sample,
/// then the parameter search (its bar replaces the labelling's when it starts).
struct Bars {
    looking: indicatif::ProgressBar,
    labelling: indicatif::ProgressBar,
    searching: indicatif::ProgressBar,
    search_starts: std::sync::Once,
}

impl Bars {
    fn new(scans: usize) -> Self {
        let labelling = progress(0, "pseudo-label");
        labelling.set_draw_target(indicatif::ProgressDrawTarget::hidden());
        let searching = indicatif::ProgressBar::hidden();
        searching.set_style(crate::common::progress_style(
            "fit parameters [{bar:30}] {pos} segmenter runs (at most {len}), {elapsed}",
        ));
        Self {
            looking: progress(scans, "calibrate"),
            labelling,
            searching,
            search_starts: std::sync::Once::new(),
        }
    }

    fn show(&self, p: CalibrateProgress<'_>) {
        match p {
            CalibrateProgress::Looked => self.looking.inc(1),
            CalibrateProgress::Skipped { problem } => {
                self.looking.suspend(|| error!("skipped: {problem}"));
            }
            CalibrateProgress::Fit(FitProgress::Labelled { done: 0, of }) => {
                self.looking.finish_and_clear();
                self.labelling.set_length(of as u64);
                self.labelling
                    .set_draw_target(indicatif::ProgressDrawTarget::stderr());
            }
            CalibrateProgress::Fit(FitProgress::Labelled { .. }) => self.labelling.inc(1),
            CalibrateProgress::Fit(FitProgress::Searched { done, most }) => {
                self.search_starts.call_once(|| {
                    self.labelling.finish_and_clear();
                    self.searching
                        .set_draw_target(indicatif::ProgressDrawTarget::stderr());
                    info!("fitting the parameters to the PseudoLabeler's labels");
                });
                self.searching.set_length(most as u64);
                self.searching.set_position(done as u64);
            }
        }
    }

    fn finish(&self) {
        for bar in [&self.looking, &self.labelling, &self.searching] {
            bar.finish_and_clear();
        }
    }
}
