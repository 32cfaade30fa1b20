//! `groundwork eval`: score methods against labels, per scan and pooled.

use std::path::Path;
use std::process::ExitCode;

use anyhow::Result;
use groundwork_eval::{Protocol, evaluate};
use groundwork_io::Sequence;
use tracing::info;

use crate::args::{Common, EvalArgs, ProtocolArg};
use crate::common::{load_methods, progress};
use crate::methods::{self, MethodArg};

/// `groundwork eval`.
pub fn command(a: EvalArgs) -> Result<ExitCode> {
    eval(
        &a.common,
        &a.method,
        &a.sequence,
        a.labels.as_deref(),
        &a.labels_format,
        a.protocol,
        a.json,
    )
}

fn eval(
    common: &Common,
    methods: &[MethodArg],
    dir: &Path,
    labels: Option<&Path>,
    labels_format: &str,
    protocol: ProtocolArg,
    json: bool,
) -> Result<ExitCode> {
    let all = load_methods(common, None)?;
    let cfg = &all.segmenter;
    let mut seq = Sequence::open(dir, common.poses.as_deref(), common.calib.as_deref())?
        .with_topic(common.topic.clone())
        .with_label_map(groundwork_io::LabelMap::load(labels_format)?);
    if let Some(l) = labels {
        anyhow::ensure!(l.is_dir(), "{}: no such folder", l.display());
        seq = seq.with_labels(l.to_path_buf());
    }
    if cfg.history.frames > 1 && seq.poses.is_none() {
        info!("no poses.txt + calib.txt: multi-frame history is not used");
    }
    let protocol = match protocol {
        ProtocolArg::Gmm => Protocol::Gmm,
        ProtocolArg::Terraseg => Protocol::Terraseg,
    };
    // Every method on the same scans, through the same evaluator.
    let mut reports = Vec::new();
    for &m in methods {
        let mut method = methods::build(m, &all)?;
        let known = seq.len_hint();
        let pb = progress(known.unwrap_or(0), method.name());
        let report = evaluate(&seq, method.as_mut(), protocol, |_| {
            if known.is_none() {
                pb.inc_length(1);
            }
            pb.inc(1)
        })?;
        pb.finish_and_clear();
        reports.push(report);
    }
    match (json, reports.as_slice()) {
        (true, [one]) => println!("{}", serde_json::to_string_pretty(one)?),
        (true, _) => println!("{}", serde_json::to_string_pretty(&reports)?),
        (false, [one]) => print!("{}", one.to_table()),
        (false, _) => print!("{}", groundwork_eval::side_by_side(&reports)),
    }
    // Scores of the readable scans are printed; a run that skipped any is incomplete.
    Ok(if reports.iter().any(|r| !r.skipped.is_empty()) {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}
