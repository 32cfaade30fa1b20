//! `calibrate`: `groundwork_calibrate::calibrate` on arrays, its result as keyword
//! arguments and a report, and the CLI's file where asked.

use std::path::PathBuf;

use pyo3::prelude::*;
use pyo3::types::{IntoPyDict, PyDict};

use crate::convert::*;

/// The sensor's mount from raw scans, no labels (`groundwork calibrate`): ground-plane
/// consensus over the scans, starting from the preset's mount. Returns the configuration
/// to lay over the preset (a dict like the keyword arguments: `{"mount": {...}}`, angles in
/// degrees, and `"zones"` where the zone model's near edge moved in to where the scans
/// first see ground or its inner boundaries were scaled with the height found, unless
/// `keep_zones`) and a report (each parameter's median, spread and standard error over the
/// scans; each scan's view or why it showed no usable ground; the near edge; the height
/// scale; `one_sided_ground` when the scans saw the ground on one side of the sensor only,
/// with what the mount then assumes). Then, unless `keep_params`, the likelihood parameters
/// and ground threshold fitted to the PseudoLabeler's labels of up to `param_scans` of the
/// scans, as the CLI does: `"ground"` in the configuration where the fit was kept, the fit in
/// the report's `"parameters"` (or why it could not run, `"parameters_refused"`); with
/// `fit_zones`, the inner zones' layout fitted with them (`"zones"` with rings and sectors
/// where it changed, as `--fit-zones`). Raises ValueError when the scans cannot determine
/// the mount, with the reason.
#[pyfunction]
#[pyo3(signature = (
    scans, sensor=None, config=None, seed=0, keep_zones=false, keep_params=false,
    param_scans=48, param_trust=90.0, param_min_gain=2.5, fit_zones=false, out=None,
    overwrite=false, **overrides
))]
#[allow(clippy::too_many_arguments)] // the keyword arguments of a Python function
pub(crate) fn calibrate<'py>(
    py: Python<'py>,
    scans: Vec<Bound<'py, PyAny>>,
    sensor: Option<&str>,
    config: Option<PathBuf>,
    seed: u64,
    keep_zones: bool,
    keep_params: bool,
    param_scans: usize,
    param_trust: f64,
    param_min_gain: f64,
    fit_zones: bool,
    out: Option<PathBuf>,
    overwrite: bool,
    overrides: Option<&Bound<'py, PyDict>>,
) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
    use groundwork_calibrate::{CalibrateOptions, MountSearchConfig};
    if fit_zones && keep_params {
        return Err(value_error(
            "fit_zones fits the zones with the parameters: not with keep_params",
        ));
    }
    let search = param_search(param_trust, param_min_gain, fit_zones)?;
    let (base, cfg) = load_config_named(sensor, config.clone(), None, overrides)?;
    let options = CalibrateOptions {
        mount: MountSearchConfig {
            seed,
            ..MountSearchConfig::default()
        },
        keep_zones,
        params: (!keep_params).then_some(search),
        param_scans,
        ..CalibrateOptions::new(&base, preset_mount(&base), scans.len())
    };
    options.validate().map_err(value_error)?;
    // The CLI's file: claimed before the work (never an input, an existing one only with
    // overwrite), written through a temporary name.
    let file = match &out {
        Some(path) => Some((claim_file(path, config.as_slice(), overwrite)?, path)),
        None => None,
    };
    let inputs = scan_inputs(&scans)?;
    let cal = py
        .detach(|| {
            groundwork_calibrate::calibrate(
                inputs.into_iter(),
                &cfg.segmenter,
                &cfg.pseudolabeler,
                &options,
                |_| {},
            )
        })
        .map_err(value_error)?;
    let est = cal.estimate().map_err(value_error)?;
    if let Some((files, path)) = file {
        let name = path
            .file_stem()
            .map_or_else(|| "calibrated".into(), |s| s.to_string_lossy().into_owned());
        let text = cal
            .to_toml(&name, &["scans given from Python".to_owned()])
            .map_err(value_error)?;
        files.write(path, text.as_bytes()).map_err(format_error)?;
    }
    Ok((
        calibration_preset(py, &cal, est)?,
        calibration_report(py, &cal, est)?,
    ))
}

/// The parameter search the keywords ask for, refused by the keyword the caller typed.
fn param_search(
    trust: f64,
    min_gain: f64,
    fit_zones: bool,
) -> PyResult<groundwork_calibrate::ParamSearchConfig> {
    let search = groundwork_calibrate::ParamSearchConfig {
        trust_agreement: trust,
        min_held_out_gain: min_gain,
        fit_zones,
        ..Default::default()
    };
    search.check().map_err(|(field, why)| {
        let keyword = match field {
            "trust_agreement" => "param_trust",
            "min_held_out_gain" => "param_min_gain",
            other => other,
        };
        value_error(format!("{keyword}: {why}"))
    })?;
    Ok(search)
}

/// The mount the preset's own zone layout was made for.
fn preset_mount(base: &str) -> Option<groundwork_core::config::MountConfig> {
    groundwork_io::sensor_preset(base)
        .ok()
        .map(|p| p.sensor.mount)
}

/// `out=` claimed: never an input, an existing file only with `overwrite`.
fn claim_file(
    path: &std::path::Path,
    inputs: &[PathBuf],
    overwrite: bool,
) -> PyResult<groundwork_io::OutputFiles> {
    let mut files = groundwork_io::OutputFiles::new(inputs);
    files.claim(path).map_err(format_error)?;
    if let (Some(first), false) = (files.existing().first(), overwrite) {
        return Err(value_error(format!(
            "{}: exists; pass overwrite=True to replace it",
            first.display()
        )));
    }
    Ok(files)
}

/// The scans as the library takes them, each named by its place in the list.
fn scan_inputs(scans: &[Bound<'_, PyAny>]) -> PyResult<Vec<groundwork_calibrate::ScanInput>> {
    scans
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let arr = points_array(s)?;
            let points = match Points::of(&arr)? {
                Points::Xyz(p) => p.to_vec(),
                Points::Xyzi(p) => p.iter().map(|&[x, y, z, _]| [x, y, z]).collect(),
            };
            Ok(groundwork_calibrate::ScanInput {
                place: k as u64,
                name: format!("scans[{k}]"),
                points: Ok(points),
            })
        })
        .collect()
}

/// The configuration a calibration found, as keyword arguments: the mount, the zones where
/// they moved, the ground parameters where the fit was kept.
pub(crate) fn calibration_preset<'py>(
    py: Python<'py>,
    cal: &groundwork_calibrate::Calibration,
    est: &groundwork_calibrate::MountEstimate,
) -> PyResult<Bound<'py, PyDict>> {
    let d = 180.0 / std::f64::consts::PI;
    let m = est.mount();
    let mount = [
        ("height", m.height),
        ("roll_deg", m.roll * d),
        ("pitch_deg", m.pitch * d),
        ("yaw_deg", m.yaw * d),
    ]
    .into_py_dict(py)?;
    let preset = PyDict::new(py);
    preset.set_item("mount", mount)?;
    let on_mount = cal.mount_zones.as_ref().unwrap_or(&cal.base.zones);
    if let Some(z) = &cal.mount_zones {
        let section = PyDict::new(py);
        section.set_item("min_range", z.min_range)?;
        section.set_item("boundaries", z.boundaries.clone())?;
        preset.set_item("zones", section)?;
    }
    if let Some(fit) = &cal.parameters {
        if let Some(ground) = changed_ground(py, &cal.base.ground, &fit.config.ground)? {
            preset.set_item("ground", ground)?;
        }
        let z = &fit.config.zones;
        if !z.same_layout(on_mount) {
            // The whole layout the fit left (the near edge's move included).
            let section = PyDict::new(py);
            section.set_item("min_range", z.min_range)?;
            section.set_item("boundaries", z.resolved_boundaries().map_err(value_error)?)?;
            section.set_item("rings", z.rings.clone())?;
            section.set_item("sectors", z.sectors.clone())?;
            preset.set_item("zones", section)?;
        }
    }
    Ok(preset)
}

/// A calibration's report as a dict (angles in degrees).
pub(crate) fn calibration_report<'py>(
    py: Python<'py>,
    cal: &groundwork_calibrate::Calibration,
    est: &groundwork_calibrate::MountEstimate,
) -> PyResult<Bound<'py, PyDict>> {
    let deg =
        |e: &groundwork_calibrate::mount::Estimate, scale: f64| -> PyResult<Bound<'py, PyDict>> {
            [
                ("value", e.value * scale),
                ("spread", e.spread * scale),
                ("standard_error", e.standard_error * scale),
            ]
            .into_py_dict(py)
        };
    let d = 180.0 / std::f64::consts::PI;
    let report = PyDict::new(py);
    report.set_item("height", deg(&est.height, 1.0)?)?;
    report.set_item("roll_deg", deg(&est.roll, d)?)?;
    report.set_item("pitch_deg", deg(&est.pitch, d)?)?;
    report.set_item("frames_used", est.frames_used)?;
    report.set_item("frames", est.frames)?;
    if let Some(o) = &est.one_sided {
        let item = PyDict::new(py);
        item.set_item("leverage", o.leverage)?;
        item.set_item("nearest_m", o.nearest)?;
        item.set_item("caveat", o.to_string())?;
        report.set_item("one_sided_ground", item)?;
    }
    let per_scan = pyo3::types::PyList::empty(py);
    for line in &cal.per_scan {
        let item = PyDict::new(py);
        match (&line.mount, &line.problem) {
            (Some(f), _) => {
                item.set_item("height", f.height)?;
                item.set_item("roll_deg", f.roll * d)?;
                item.set_item("pitch_deg", f.pitch * d)?;
                item.set_item("inliers", f.plane.inliers)?;
            }
            (None, problem) => item.set_item("problem", problem.clone().unwrap_or_default())?,
        }
        per_scan.append(item)?;
    }
    report.set_item("per_scan", per_scan)?;
    if let Some(n) = &cal.near_edge {
        let item = PyDict::new(py);
        item.set_item("ground_from", n.ground.range)?;
        item.set_item("scans", n.ground.scans)?;
        item.set_item("was", n.was)?;
        item.set_item("min_range", n.min_range)?;
        report.set_item("near_edge", item)?;
    }
    if let Some(h) = &cal.height_scale {
        let item = PyDict::new(py);
        item.set_item("ratio", h.ratio)?;
        item.set_item("was", h.was.clone())?;
        item.set_item("boundaries", h.boundaries.clone())?;
        report.set_item("height_scale", item)?;
    }
    if let Some(fit) = &cal.parameters {
        report.set_item("parameters", param_fit_dict(py, fit)?)?;
    } else if let Some(why) = &cal.parameters_refused {
        report.set_item("parameters_refused", why)?;
    }
    report.set_item("summary", cal.summary())?;
    Ok(report)
}

/// The `[ground]` settings `new` changed from `old`, as keyword arguments (None if none).
pub(crate) fn changed_ground<'py>(
    py: Python<'py>,
    old: &groundwork_core::config::GroundConfig,
    new: &groundwork_core::config::GroundConfig,
) -> PyResult<Option<Bound<'py, PyDict>>> {
    use groundwork_calibrate::GroundValue;
    let d = PyDict::new(py);
    for c in groundwork_calibrate::ground_changes(old, new) {
        match c.new {
            GroundValue::Sigmoid(s) => d.set_item(
                c.key,
                [("alpha", s.alpha), ("beta", s.beta)].into_py_dict(py)?,
            )?,
            GroundValue::Number(v) => d.set_item(c.key, v)?,
            // The f32 as the f64 it is exactly: read back, the same bits.
            GroundValue::Threshold(v) => d.set_item(c.key, f64::from(v))?,
        }
    }
    Ok((!d.is_empty()).then_some(d))
}

/// A parameter fit's report as the CLI's `--report` holds it ("parameters"), each agreement
/// with its ground IoU (%) added.
pub(crate) fn param_fit_dict<'py>(
    py: Python<'py>,
    fit: &groundwork_calibrate::ParamFit,
) -> PyResult<Bound<'py, PyDict>> {
    let agreement = |a: &groundwork_calibrate::Agreement| -> PyResult<Bound<'py, PyDict>> {
        let d = [
            ("both", a.both),
            ("segmenter_only", a.segmenter_only),
            ("reference_only", a.reference_only),
        ]
        .into_py_dict(py)?;
        d.set_item("iou", a.iou())?;
        Ok(d)
    };
    let d = PyDict::new(py);
    d.set_item("kept_preset", fit.kept_preset)?;
    d.set_item("trusted_points_per_scan", fit.trusted_points_per_scan)?;
    d.set_item("too_few_trusted_points", fit.too_few_trusted_points)?;
    let changed = pyo3::types::PyList::empty(py);
    for c in &fit.changed {
        let item = [("old", c.old), ("new", c.new)].into_py_dict(py)?;
        item.set_item("name", c.name)?;
        changed.append(item)?;
    }
    d.set_item("changed", changed)?;
    d.set_item("fitted_before", agreement(&fit.fitted_before)?)?;
    d.set_item("fitted_after", agreement(&fit.fitted_after)?)?;
    d.set_item("held_out_before", agreement(&fit.held_out_before)?)?;
    d.set_item("held_out_after", agreement(&fit.held_out_after)?)?;
    d.set_item("fitted_scans", fit.fitted_scans)?;
    d.set_item("held_out_scans", fit.held_out_scans)?;
    d.set_item("evaluations", fit.evaluations)?;
    d.set_item("trusted_range", fit.trusted_range)?;
    d.set_item("ring_agreement", fit.ring_agreement.clone())?;
    Ok(d)
}
