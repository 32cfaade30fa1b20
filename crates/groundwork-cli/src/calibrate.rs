//! `groundwork calibrate`: the sensor's mount from raw scans, written as a configuration to
//! lay over the preset it started from, with a report.
//!
//! Scans are read in order (every k-th where the inputs' length is known, so that
//! `--max-scans` spreads over the whole drive) and their ground planes found in parallel;
//! each scan's plane depends only on the scan and its place (the seed), so the file written
//! does not depend on the number of cores.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Result, bail};
use groundwork_calibrate::mount::{Estimate, FrameMount};
use groundwork_calibrate::{
    FitProgress, HeightScale, MountEstimate, MountSearchConfig, MountZones, NearEdgeConfig,
    NearGround, NoGround, ParamFit, ParamSearchConfig, combine, combine_near_ground,
    fit_to_pseudo_labels, frame_mount, view_near_ground, zones_for_mount,
};
use groundwork_core::SegmenterConfig;
use groundwork_core::config::{MountConfig, ZoneConfig};
use groundwork_core::mount_transform;
use groundwork_eval::MethodsConfig;
use rayon::prelude::*;
use serde::Serialize;
use tracing::{error, info, warn};

use crate::args::CalibrateArgs;
use crate::common::{open_inputs, progress};

/// One scan's line in the report.
#[derive(Debug, Serialize)]
struct ScanReport {
    /// The scan's name (file stem, or recording and index).
    scan: String,
    /// Its view of the mount, if it showed usable ground.
    #[serde(skip_serializing_if = "Option::is_none")]
    mount: Option<FrameMount>,
    /// Why not, otherwise (no ground, or the scan could not be read).
    #[serde(skip_serializing_if = "Option::is_none")]
    problem: Option<String>,
}

/// One scan looked at: its place, its report line, its view of the mount (None: unreadable),
/// where it first sees ground on that view, and its points if it is in the parameter fit's
/// sample.
struct Looked {
    k: usize,
    line: ScanReport,
    view: Option<Result<FrameMount, NoGround>>,
    near: Option<f64>,
    points: Option<Vec<[f32; 3]>>,
}

/// The zone model's near edge, moved (`--keep-zones` not given).
#[derive(Debug, Serialize)]
struct NearEdge {
    /// Where the scans first see ground.
    ground: NearGround,
    /// `zones.min_range` of the preset, metres.
    was: f64,
    /// And written, if it moved.
    #[serde(skip_serializing_if = "Option::is_none")]
    min_range: Option<f64>,
}

/// The report `--report` writes.
#[derive(Debug, Serialize)]
struct Report {
    /// The preset the calibration started from.
    base_preset: String,
    /// Its mount (the prior).
    prior: MountConfig,
    /// The mount found (absent when refused).
    mount: Option<MountEstimate>,
    /// Why it was refused.
    refused: Option<String>,
    /// Scans looked at.
    scans: usize,
    /// Scans that could not be read.
    unreadable: usize,
    /// Every scan, in input order.
    per_scan: Vec<ScanReport>,
    /// The search's settings.
    settings: MountSearchConfig,
    /// Where the scans first see ground and the zone model's near edge (absent with
    /// `--keep-zones`, or when too few scans show ground near the sensor).
    #[serde(skip_serializing_if = "Option::is_none")]
    near_edge: Option<NearEdge>,
    /// The inner boundaries scaled with the height found (absent with `--keep-zones`, a
    /// refused mount, or a height within 5 % of the preset's).
    #[serde(skip_serializing_if = "Option::is_none")]
    height_scale: Option<HeightScale>,
    /// The parameter fit (unless `--keep-params`), if it ran.
    #[serde(skip_serializing_if = "Option::is_none")]
    parameters: Option<ParamFit>,
    /// Why the parameters were not fitted, if they were asked for and could not be.
    #[serde(skip_serializing_if = "Option::is_none")]
    parameters_refused: Option<String>,
    /// Wall time, s.
    seconds: f64,
}

pub fn command(a: CalibrateArgs) -> Result<ExitCode> {
    let t = Instant::now();
    let base = a
        .sensor
        .sensor
        .clone()
        .unwrap_or_else(|| groundwork_io::DEFAULT_SENSOR.to_string());
    let methods = crate::common::load_methods(&a.sensor.into(), None)?;
    let cfg = methods.segmenter.clone();
    anyhow::ensure!(a.max_scans > 0, "--max-scans must be at least 1");
    anyhow::ensure!(a.param_scans > 0, "--param-scans must be at least 1");
    let search = ParamSearchConfig {
        trust_agreement: a.param_trust,
        min_held_out_gain: a.param_min_gain,
        fit_zones: a.fit_zones,
        ..ParamSearchConfig::default()
    };
    // Checked before anything is read, by the flag the user typed.
    search.check().map_err(|(field, why)| {
        let flag = match field {
            "trust_agreement" => "--param-trust",
            "min_held_out_gain" => "--param-min-gain",
            other => other,
        };
        anyhow::anyhow!("{flag}: {why}")
    })?;
    let prior_mount = cfg.sensor.mount.clone();
    let prior = mount_transform(&prior_mount)?;
    let settings = MountSearchConfig {
        seed: a.seed,
        ..MountSearchConfig::default()
    };
    settings.validate()?;
    let (sequences, skipped_inputs) = open_inputs(&a.inputs, None, None, a.topic.as_deref())?;
    // The file and the report: never an input, never the same file, never half-written.
    let mut outputs =
        groundwork_io::OutputFiles::new(&crate::common::input_files(&a.inputs, &sequences));
    for out in std::iter::once(&a.out).chain(a.report.as_ref()) {
        outputs.claim(out)?;
    }
    if let (Some(first), false) = (outputs.existing().first(), a.overwrite) {
        bail!(
            "{}: exists; pass --overwrite to replace it",
            first.display()
        );
    }
    outputs.warn_replaced();
    // Spread the scans looked at over the whole inputs, a recording's as a folder's: its
    // scans are counted first (a pass without decoding them).
    let total: Option<usize> = sequences
        .iter()
        .map(|s| match &s.source {
            groundwork_io::ScanSource::Recording { path, topic } => {
                groundwork_io::RecordingReader::count(path, topic.as_deref(), cfg.sensor.max_points)
                    .ok()
            }
            groundwork_io::ScanSource::Files(_) => s.len_hint(),
        })
        .sum();
    let stride = total.map_or(1, |n| n.div_ceil(a.max_scans).max(1));
    let pb = progress(
        total.map_or(a.max_scans, |n| n.div_ceil(stride).min(a.max_scans)),
        "calibrate",
    );
    let max_points = cfg.sensor.max_points;
    let (ego_radius, near_cfg) = (cfg.sensor.ego_radius, NearEdgeConfig::default());
    // Every `keep`-th scan looked at is kept for the parameter fit's sample.
    let looked = total.map_or(a.max_scans, |n| n.div_ceil(stride).min(a.max_scans));
    let keep = (!a.keep_params).then(|| looked.div_ceil(a.param_scans.max(1)).max(1));
    info!(
        base = %base,
        inputs = a.inputs.len(),
        scans = ?total,
        every = stride,
        "finding the mount"
    );
    let mut views: Vec<Looked> = sequences
        .iter()
        .flat_map(|s| s.scans(max_points))
        .enumerate()
        .filter(|(k, _)| k % stride == 0)
        .take(a.max_scans)
        .par_bridge()
        .map(|(k, item)| {
            let (mut points, mut near) = (None, None);
            let result = item.scan.as_ref().map(|scan| {
                let xyz: Vec<[f32; 3]> = scan.points.iter().map(|p| [p.x, p.y, p.z]).collect();
                let m = frame_mount(&xyz, &prior, &settings, k as u64);
                if let (Ok(view), false) = (&m, a.keep_zones) {
                    near = view_near_ground(&xyz, view, ego_radius, &near_cfg);
                }
                if keep.is_some_and(|e| (k / stride).is_multiple_of(e)) {
                    points = Some(xyz);
                }
                m
            });
            pb.inc(1);
            let (mount, problem, view) = match result {
                Ok(Ok(m)) => (Some(m.clone()), None, Some(Ok(m))),
                Ok(Err(no)) => (None, Some(no.to_string()), Some(Err(no))),
                Err(e) => {
                    pb.suspend(|| error!("skipped: {e}"));
                    (None, Some(e.to_string()), None)
                }
            };
            let line = ScanReport {
                scan: item.name,
                mount,
                problem,
            };
            Looked {
                k,
                line,
                view,
                near,
                points,
            }
        })
        .collect();
    pb.finish_and_clear();
    views.sort_by_key(|v| v.k);
    let unreadable = views.iter().filter(|v| v.view.is_none()).count();
    let (frames, names): (Vec<Result<FrameMount, NoGround>>, Vec<&str>) = views
        .iter_mut()
        .filter_map(|v| Some((v.view.take()?, v.line.scan.as_str())))
        .unzip();
    let result = combine(&frames, &prior, &settings);
    if let Ok(est) = &result
        && !est.disagreeing.is_empty()
    {
        let named: Vec<String> = est
            .disagreeing
            .iter()
            .filter_map(|&k| {
                Some(format!(
                    "{} ({:.2} m)",
                    names[k],
                    frames[k].as_ref().ok()?.height
                ))
            })
            .collect();
        warn!(
            "{} of {} scans disagree with the mount found by more than {:.2} m in height, and \
             were outvoted: {}; scans of another sensor or mount among the inputs?",
            named.len(),
            est.frames_used,
            settings.max_height_spread,
            named.join(", ")
        );
    }
    let near = combine_near_ground(views.iter().filter_map(|v| v.near).collect());
    // The zones follow the mount found (not with --keep-zones): the near edge where the
    // scans first see ground, the inner boundaries the height against the preset's.
    let preset_mount = groundwork_io::sensor_preset(&base)
        .ok()
        .map(|p| p.sensor.mount);
    let height = result
        .as_ref()
        .ok()
        .filter(|_| !a.keep_zones)
        .map(|e| e.mount().height);
    let MountZones {
        zones,
        near_edge: min_range,
        height_scale,
    } = zones_for_mount(
        &cfg.zones,
        near.as_ref(),
        height.zip(preset_mount.as_ref()),
        ego_radius,
        &near_cfg,
    );
    let near_edge = near.map(|ground| NearEdge {
        min_range,
        was: cfg.zones.min_range,
        ground,
    });
    let mut methods = methods;
    if let Some(z) = &zones {
        methods.segmenter.zones = z.clone();
    }
    let sample: Vec<Vec<[f32; 3]>> = views
        .iter_mut()
        .filter_map(|v| v.points.take())
        .take(a.param_scans)
        .collect();
    let (parameters, parameters_refused) = match (&result, a.keep_params) {
        (Ok(est), false) => match fit_params(&methods, est, &sample, &search) {
            Ok(fit) => {
                if fit.too_few_trusted_points {
                    warn!(
                        "parameters not fitted, the preset's kept: {}",
                        too_few_words(&fit)
                    );
                }
                (Some(fit), None)
            }
            Err(e) => {
                // The preset's parameters are a valid outcome (as with --keep-params);
                // the file and the report say why.
                warn!("parameters not fitted, the preset's kept: {e:#}");
                (None, Some(format!("{e:#}")))
            }
        },
        _ => (None, None),
    };
    let report = Report {
        base_preset: base.clone(),
        prior: prior_mount.clone(),
        mount: result.as_ref().ok().cloned(),
        refused: result.as_ref().err().map(ToString::to_string),
        scans: views.len(),
        unreadable,
        per_scan: views.into_iter().map(|v| v.line).collect(),
        settings,
        near_edge,
        height_scale,
        parameters,
        parameters_refused,
        seconds: t.elapsed().as_secs_f64(),
    };
    if let Some(path) = &a.report {
        let json = serde_json::to_string_pretty(&report)? + "\n";
        outputs.write(path, json.as_bytes())?;
    }
    let est = match result {
        Ok(e) => e,
        Err(e) => bail!("{e} (nothing written to {})", a.out.display()),
    };
    if let Some(o) = &est.one_sided {
        warn!("{o}");
    }
    let name = a
        .out
        .file_stem()
        .map_or_else(|| "calibrated".into(), |s| s.to_string_lossy().into_owned());
    let mut text = preset_text(&base, &name, &prior_mount, &est, &a.inputs);
    // The zones in use: the parameter fit's (it started from the moved near edge), else
    // the moved near edge's.
    let fitted = report.parameters.as_ref().filter(|f| !f.kept_preset);
    let final_zones = fitted.map(|f| &f.config.zones).or(zones.as_ref());
    if let Some(z) = final_zones.filter(|z| !z.same_layout(&cfg.zones)) {
        let moved = report.near_edge.as_ref().filter(|n| n.min_range.is_some());
        text += &zones_text(&cfg.zones, z, moved, report.height_scale.as_ref());
    }
    if let Some(fit) = &report.parameters {
        text += &params_text(&cfg, fit);
    } else if let Some(why) = &report.parameters_refused {
        let _ = writeln!(
            text,
            "\n# Parameters not fitted (the preset's are kept): {why}"
        );
    }
    outputs.write(&a.out, text.as_bytes())?;
    print!("{}", summary(&base, &prior_mount, &est));
    match &report.near_edge {
        Some(NearEdge {
            ground,
            was,
            min_range: Some(m),
        }) => println!(
            "  near edge of the zones {m:.2} m  was {was:.2} m (ground from {:.2} m)",
            ground.range
        ),
        Some(NearEdge { ground, was, .. }) => println!(
            "  near edge of the zones kept at {was:.2} m (ground from {:.2} m)",
            ground.range
        ),
        None => {}
    }
    if let Some(h) = &report.height_scale {
        println!(
            "  inner zone boundaries scaled by {:.3} with the height: {:?}  was {:?}",
            h.ratio, h.boundaries, h.was
        );
    }
    // After the mount, as in the file.
    if let Some(fit) = &report.parameters {
        print!("{}", params_summary(fit));
    } else if let Some(why) = &report.parameters_refused {
        println!("parameters not fitted, the preset's kept: {why}");
    }
    println!(
        "wrote {} (use: --sensor {base} --config {}) in {:.1} s",
        a.out.display(),
        a.out.display(),
        t.elapsed().as_secs_f64()
    );
    Ok(if unreadable + skipped_inputs > 0 {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}

/// The `[zones]` section: the near edge moved in (`near`), the inner boundaries scaled
/// with the height (`scale`) and the inner zones' layout as the parameter fit left it,
/// each changed value's old one in a comment.
fn zones_text(
    preset: &ZoneConfig,
    z: &ZoneConfig,
    near: Option<&NearEdge>,
    scale: Option<&HeightScale>,
) -> String {
    let list = |v: &[f64]| {
        let v: Vec<String> = v.iter().map(|v| format!("{v:?}")).collect();
        format!("[{}]", v.join(", "))
    };
    let whole = |v: &[u32]| format!("{v:?}");
    let was = |new: &str, old: &str| {
        if new == old {
            String::new()
        } else {
            format!("  # was {old}")
        }
    };
    let mut s = String::from("\n[zones]\n");
    if let Some(n) = near {
        let _ = write!(
            s,
            "# The near edge moved in to where the scans first see ground on the mount found:\n\
             # {:.2} m (the median over {} scans of the 1st percentile of the range of points\n\
             # within 15 cm of the ground), times 0.9.\n",
            n.ground.range, n.ground.scans
        );
    }
    if let Some(h) = scale {
        let _ = write!(
            s,
            "# The inner boundaries scaled by {:.3}, the height found over the preset's (beams\n\
             # meet the ground at ranges in proportion to the height); before: {:?}.\n",
            h.ratio, h.was
        );
    }
    let (old_b, new_b) = (
        preset.resolved_boundaries().unwrap_or_default(),
        z.resolved_boundaries().unwrap_or_default(),
    );
    let scaled_b = scale.map(|h| h.boundaries.as_slice());
    if (new_b[1..] != old_b[1..] && scaled_b.is_none_or(|b| b[1..] != new_b[1..]))
        || z.rings != preset.rings
        || z.sectors != preset.sectors
    {
        s += "# The inner zones' layout fitted to the PseudoLabeler's labels (see the parameters\n\
              # below).\n";
    }
    let (min_new, min_old) = (
        format!("{:?}", z.min_range),
        format!("{}", preset.min_range),
    );
    let _ = writeln!(s, "min_range = {min_new}{}", was(&min_new, &min_old));
    let (b_new, b_old) = (list(&new_b), list(&old_b));
    let _ = writeln!(s, "boundaries = {b_new}{}", was(&b_new, &b_old));
    for (key, new, old) in [
        ("rings", &z.rings, &preset.rings),
        ("sectors", &z.sectors, &preset.sectors),
    ] {
        if new != old {
            let _ = writeln!(s, "{key} = {}{}", whole(new), was(&whole(new), &whole(old)));
        }
    }
    s
}

/// The parameter fit on the mount found, with its progress bars.
fn fit_params(
    methods: &MethodsConfig,
    est: &MountEstimate,
    sample: &[Vec<[f32; 3]>],
    search: &ParamSearchConfig,
) -> Result<ParamFit> {
    let mut cfg = methods.segmenter.clone();
    cfg.sensor.mount = est.mount();
    let labelling = progress(sample.len(), "pseudo-label");
    // The search's bar replaces the labelling's when the search starts.
    let searching = indicatif::ProgressBar::new(0);
    searching.set_style(crate::common::progress_style(
        "fit parameters [{bar:30}] {pos} segmenter runs (at most {len}), {elapsed}",
    ));
    let search_starts = std::sync::Once::new();
    let fit = fit_to_pseudo_labels(&cfg, &methods.pseudolabeler, sample, search, |p| match p {
        FitProgress::Labelled { done, .. } if done > 0 => labelling.inc(1),
        FitProgress::Labelled { .. } => {}
        FitProgress::Searched { done, most } => {
            search_starts.call_once(|| {
                labelling.finish_and_clear();
                info!(
                    scans = sample.len(),
                    "fitting the parameters to the PseudoLabeler's labels"
                );
            });
            searching.set_length(most as u64);
            searching.set_position(done as u64);
        }
    });
    labelling.finish_and_clear();
    searching.finish_and_clear();
    // The mount is calibrated: a refusal here is the parameters' alone.
    fit.map_err(|e| anyhow::anyhow!(e.reason()))
}

/// The fit's figures in one line: the sample, the trusted range and the agreement with the
/// PseudoLabeler's labels (ground IoU, %) before and after.
fn fit_figures(fit: &ParamFit) -> String {
    format!(
        "{} scans ({} held out), within {} m: agreement with the PseudoLabeler, held out, \
         {:.2} -> {:.2} (fitted scans {:.2} -> {:.2})",
        fit.fitted_scans + fit.held_out_scans,
        fit.held_out_scans,
        fit.trusted_range,
        fit.held_out_before.iou(),
        fit.held_out_after.iou(),
        fit.fitted_before.iou(),
        fit.fitted_after.iou(),
    )
}

/// The fitted parameters as TOML, after the mount: what changed, each old value in a comment,
/// and the agreement with the PseudoLabeler before and after.
fn params_text(base: &SegmenterConfig, fit: &ParamFit) -> String {
    let mut s = format!(
        "\n# Parameters fitted to the PseudoLabeler's labels (ground IoU with them, within the\n\
         # range where the preset and the labels agree), from\n# {}.\n",
        fit_figures(fit)
    );
    if fit.kept_preset {
        s += &if fit.too_few_trusted_points {
            format!(
                "# Not fitted: {}.\n# The preset's parameters are kept.\n",
                too_few_words(fit)
            )
        } else if labels_hold_no_ground(fit) {
            "# The PseudoLabeler called nothing ground there: the preset's parameters are kept.\n"
                .to_owned()
        } else {
            "# No change agreed better with the held-out scans: the preset's parameters are kept.\n"
                .to_owned()
        };
        return s;
    }
    let changes = groundwork_calibrate::ground_changes(&base.ground, &fit.config.ground);
    if !changes.is_empty() {
        s += "[ground]\n";
    }
    for c in changes {
        let _ = writeln!(s, "{} = {}  # was {}", c.key, c.new, c.old);
    }
    s
}

/// Why a sample with too few trusted points was not fitted, in a sentence.
fn too_few_words(fit: &ParamFit) -> String {
    format!(
        "only {:.0} points a scan are ground within {} m, where the labels are trusted ({} \
         needed): too few to fit to",
        fit.trusted_points_per_scan, fit.trusted_range, fit.trusted_points_needed
    )
}

/// Whether the PseudoLabeler's labels of the sample hold no ground within the trusted range:
/// agreement with them is then 0 for any parameters.
fn labels_hold_no_ground(fit: &ParamFit) -> bool {
    [&fit.fitted_before, &fit.held_out_before]
        .iter()
        .all(|a| a.both + a.reference_only == 0)
}

/// Below this agreement (ground IoU with the PseudoLabeler, %) the figure is flagged as
/// saying little: on real scans where both are right it is above 90.
const WEAK_AGREEMENT: f64 = 80.0;

/// The parameter fit, for the terminal.
fn params_summary(fit: &ParamFit) -> String {
    let mut s = format!(
        "parameters from {}; {} segmenter runs\n",
        fit_figures(fit),
        fit.evaluations
    );
    // What the agreement is, and when it says little: it is not the accuracy.
    let _ = writeln!(
        s,
        "  (agreement: ground IoU between the segmenter's ground and the PseudoLabeler's within \
         {} m, a check that a change carries over to unseen scans; not accuracy against the \
         truth, which needs labels: groundwork eval)",
        fit.trusted_range
    );
    let agreement = fit.held_out_before.iou().min(fit.fitted_before.iou());
    if agreement < WEAK_AGREEMENT && !labels_hold_no_ground(fit) {
        let _ = writeln!(
            s,
            "  caution: agreement below {WEAK_AGREEMENT:.0}: the PseudoLabeler's labels differ \
             from the segmenter's ground here for reasons of their own (its elevation map, the \
             scene), so this figure says little about either; check the result with labelled \
             scans or `groundwork render --compare`"
        );
    }
    if fit.kept_preset {
        s += &if fit.too_few_trusted_points {
            format!("  kept the preset's: {}\n", too_few_words(fit))
        } else if labels_hold_no_ground(fit) {
            "  kept the preset's: the PseudoLabeler called nothing ground where its labels are \
             trusted, so they cannot teach (it can lose the ground where the terrain falls far \
             below the road: docs/offline-labels.md)\n"
                .to_owned()
        } else {
            "  kept the preset's: no change agreed better with the held-out scans\n".to_owned()
        };
    }
    for c in &fit.changed {
        let _ = writeln!(s, "  {} {}  was {}", c.name, c.new, c.old);
    }
    s
}

/// `value ± error unit`, with the spread over the scans.
fn shown(e: &Estimate, scale: f64, unit: &str, digits: usize) -> String {
    format!(
        "{:.digits$}{unit} ± {:.digits$}{unit} (spread {:.digits$}{unit})",
        e.value * scale,
        e.standard_error * scale,
        e.spread * scale,
    )
}

/// What was found, for the terminal.
fn summary(base: &str, prior: &MountConfig, est: &MountEstimate) -> String {
    let d = 180.0 / std::f64::consts::PI;
    let mut s = format!(
        "mount from {} of {} scans (prior: the {base} preset's)\n",
        est.frames_used, est.frames
    );
    let _ = writeln!(
        s,
        "  height {}  was {:.3} m",
        shown(&est.height, 1.0, " m", 3),
        prior.height
    );
    let _ = writeln!(
        s,
        "  roll   {}  was {:.2}°",
        shown(&est.roll, d, "°", 2),
        prior.roll * d
    );
    let _ = writeln!(
        s,
        "  pitch  {}  was {:.2}°",
        shown(&est.pitch, d, "°", 2),
        prior.pitch * d
    );
    if let Some(o) = &est.one_sided {
        let _ = writeln!(s, "  caveat: {o}");
    }
    if !est.disagreeing.is_empty() {
        let _ = writeln!(
            s,
            "  caveat: {} scan(s) disagree in height and were outvoted (named above)",
            est.disagreeing.len()
        );
    }
    s
}

/// The configuration file: what differs from the base preset, each changed value's old one
/// in a comment, readable and loadable with `--sensor <base> --config <file>`.
fn preset_text(
    base: &str,
    name: &str,
    prior: &MountConfig,
    est: &MountEstimate,
    inputs: &[PathBuf],
) -> String {
    let d = 180.0 / std::f64::consts::PI;
    let shown_inputs: Vec<String> = inputs.iter().map(|p| p.display().to_string()).collect();
    let mut s = format!(
        "# Calibrated by `groundwork calibrate` from {} of {} scans of {}.\n\
         # Use: groundwork segment --sensor {base} --config <this file> ...\n\
         # It holds what differs from the {base} preset; each changed value's old one is in\n\
         # the comment after it, with the estimate's standard error and its spread over the\n\
         # scans.\n\n\
         [sensor]\n\
         name = {name:?}  # was {:?}\n\n\
         [sensor.mount]\n",
        est.frames_used,
        est.frames,
        shown_inputs.join(", "),
        base,
    );
    let m = est.mount();
    if prior.matrix.is_some() {
        // The preset gives a matrix; the file must too (a mount is one or the other).
        let h = mount_transform(&m).map(|t| t.to_homogeneous());
        if let Ok(h) = h {
            let rows: Vec<String> = (0..4)
                .map(|r| {
                    let v: Vec<String> = (0..4).map(|c| format!("{:.6}", h[(r, c)])).collect();
                    format!("[{}]", v.join(", "))
                })
                .collect();
            let _ = writeln!(
                s,
                "matrix = [{}]  # the preset gave a matrix",
                rows.join(", ")
            );
        }
    } else {
        let _ = writeln!(
            s,
            "height = {:.4}  # was {}; ± {:.4} m (spread {:.4} m)",
            m.height, prior.height, est.height.standard_error, est.height.spread
        );
        for (key, new, old, e) in [
            ("roll_deg", m.roll, prior.roll, &est.roll),
            ("pitch_deg", m.pitch, prior.pitch, &est.pitch),
        ] {
            let _ = writeln!(
                s,
                "{key} = {:.3}  # was {:.3}°; ± {:.3}° (spread {:.3}°)",
                new * d,
                old * d,
                e.standard_error * d,
                e.spread * d
            );
        }
        let _ = writeln!(
            s,
            "yaw_deg = {:.3}  # kept: the ground does not show yaw",
            m.yaw * d
        );
    }
    if let Some(o) = &est.one_sided {
        s += &comment_lines(&format!("Caveat: {o}."));
    }
    s
}

/// `text` as TOML comment lines of at most about 90 characters, broken between words.
fn comment_lines(text: &str) -> String {
    let mut out = String::new();
    let mut line = String::from("#");
    for word in text.split_whitespace() {
        if line.len() > 1 && line.len() + 1 + word.len() > 90 {
            out += &line;
            out.push('\n');
            line = String::from("#");
        }
        line.push(' ');
        line += word;
    }
    out + &line + "\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn est(v: [f64; 3]) -> MountEstimate {
        let e = |value| Estimate {
            value,
            spread: 0.01,
            standard_error: 0.004,
        };
        MountEstimate {
            height: e(v[0]),
            roll: e(v[1]),
            pitch: e(v[2]),
            yaw: 0.0,
            frames_used: 5,
            frames: 6,
            one_sided: None,
            disagreeing: Vec::new(),
        }
    }

    #[test]
    fn a_fit_to_labels_without_ground_says_why_the_preset_is_kept() {
        let none = groundwork_calibrate::Agreement {
            both: 0,
            segmenter_only: 900,
            reference_only: 0,
        };
        let fit = ParamFit {
            config: SegmenterConfig::default(),
            changed: Vec::new(),
            fitted_before: none,
            fitted_after: none,
            held_out_before: none,
            held_out_after: none,
            fitted_scans: 18,
            held_out_scans: 6,
            evaluations: 19,
            rounds: 1,
            kept_round: 0,
            kept_preset: true,
            trusted_points_per_scan: 0.0,
            too_few_trusted_points: false,
            trusted_points_needed: 500,
            history: Vec::new(),
            trusted_range: 10.0,
            ring_agreement: vec![0.0],
        };
        let base = SegmenterConfig::default();
        assert!(params_summary(&fit).contains("called nothing ground"));
        assert!(params_text(&base, &fit).contains("called nothing ground"));
        // Labels with ground that no change agreed better with: the usual words.
        let some = groundwork_calibrate::Agreement { both: 50, ..none };
        let fit = ParamFit {
            held_out_before: some,
            fitted_before: some,
            ..fit
        };
        assert!(params_summary(&fit).contains("no change agreed better"));
        assert!(params_text(&base, &fit).contains("No change agreed better"));
        // Too few trusted points: said with the figures.
        let sparse = ParamFit {
            trusted_points_per_scan: 115.4,
            too_few_trusted_points: true,
            ..fit
        };
        let said = params_summary(&sparse);
        assert!(
            said.contains("only 115 points a scan") && said.contains("500 needed"),
            "{said}"
        );
        assert!(params_text(&base, &sparse).contains("# Not fitted: only 115 points a scan"));
    }

    #[test]
    fn the_written_file_loads_over_its_preset_and_gives_the_mount() {
        let dir = tempfile::tempdir().unwrap();
        for base in ["vlp16", "livox", "hdl32e"] {
            let prior = groundwork_io::sensor_preset(base).unwrap().sensor.mount;
            // The estimate keeps the prior's yaw, as `combine` does.
            let e = MountEstimate {
                yaw: prior.yaw,
                ..est([1.9, 0.1, -0.07])
            };
            let text = preset_text(base, "mine", &prior, &e, &[PathBuf::from("a")]);
            let path = dir.path().join(format!("{base}.toml"));
            std::fs::write(&path, &text).unwrap();
            let c = groundwork_io::load_config_over(Some(base), Some(&path)).unwrap();
            let m = &c.sensor.mount;
            assert!((m.height - 1.9).abs() < 1e-4, "{text}");
            assert!(
                (m.roll - 0.1).abs() < 1e-4 && (m.pitch + 0.07).abs() < 1e-4,
                "{text}"
            );
            assert!((m.yaw - prior.yaw).abs() < 1e-4, "{text}");
            assert_eq!(c.sensor.name, "mine");
            assert!(text.contains(&format!("# was {}", prior.height)), "{text}");
        }
    }

    #[test]
    fn ground_seen_on_one_side_is_said_in_comments_and_the_file_still_loads() {
        let prior = groundwork_io::sensor_preset("livox").unwrap().sensor.mount;
        let one_sided = groundwork_calibrate::OneSidedGround {
            leverage: 3.2,
            nearest: 6.3,
        };
        let e = MountEstimate {
            yaw: prior.yaw,
            one_sided: Some(one_sided),
            ..est([1.3, 0.0, 0.04])
        };
        let text = preset_text("livox", "mine", &prior, &e, &[PathBuf::from("a")]);
        let caveat: Vec<&str> = text
            .lines()
            .skip_while(|l| !l.starts_with("# Caveat"))
            .collect();
        assert!(caveat.len() >= 3, "{text}");
        assert!(
            caveat.iter().all(|l| l.starts_with("# ") && l.len() <= 92),
            "{text}"
        );
        let joined: Vec<&str> = caveat.iter().map(|l| &l[2..]).collect();
        assert_eq!(joined.join(" "), format!("Caveat: {one_sided}."));
        assert!(summary("livox", &prior, &e).contains("from 6.3 m, leverage 3.2"));
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mine.toml");
        std::fs::write(&path, &text).unwrap();
        let c = groundwork_io::load_config_over(Some("livox"), Some(&path)).unwrap();
        assert!((c.sensor.mount.height - 1.3).abs() < 1e-4);
        // Told nothing of the kind, the file says nothing of it.
        let plain = preset_text("livox", "mine", &prior, &est([1.3, 0.0, 0.04]), &[]);
        assert!(
            !plain.contains("Caveat")
                && !summary("livox", &prior, &est([1.3, 0.0, 0.04])).contains("caveat")
        );
    }
}
