//! `evaluate`: a mask against labels, as `groundwork eval` scores it.

use groundwork_eval::{Confusion, Protocol};
use groundwork_io::LabelMap;
use pyo3::prelude::*;
use pyo3::types::{IntoPyDict, PyDict};

use crate::convert::*;

/// Scores ground probabilities against labels as `groundwork eval` does: a point is ground
/// when its probability is at least `threshold` (default: the default preset's, as
/// `Segmenter().threshold`; pass `seg.threshold` for another); `protocol` "gmm" ignores
/// vegetation, "terraseg" counts it as non-ground. Metrics in percent, and the counts.
#[pyfunction]
#[pyo3(signature = (probabilities, labels, protocol="gmm", threshold=None, label_format="semantickitti"))]
pub(crate) fn evaluate<'py>(
    py: Python<'py>,
    probabilities: &Bound<'py, PyAny>,
    labels: &Bound<'py, PyAny>,
    protocol: &str,
    threshold: Option<f32>,
    label_format: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let threshold = match threshold {
        Some(t) => t,
        None => groundwork_io::sensor_preset(groundwork_io::DEFAULT_SENSOR)
            .map_err(format_error)?
            .decision_threshold(),
    };
    let protocol = match protocol {
        "gmm" => Protocol::Gmm,
        "terraseg" => Protocol::Terraseg,
        p => {
            return Err(value_error(format!(
                "protocol must be \"gmm\" or \"terraseg\", not {p:?}"
            )));
        }
    };
    let probs = vector::<f32>(probabilities, "float32", "probabilities")?;
    let probs = probs.as_slice().map_err(value_error)?;
    let labels = vector::<u32>(labels, "uint32", "labels")?;
    let labels = labels.as_slice().map_err(value_error)?;
    if labels.len() != probs.len() {
        return Err(value_error(format!(
            "{} labels for {} probabilities",
            labels.len(),
            probs.len()
        )));
    }
    let map = LabelMap::load(label_format).map_err(format_error)?;
    let classes: Vec<_> = labels.iter().map(|&l| map.class(l as u16)).collect();
    let c = Confusion::from_predictions(probs, &classes, protocol, threshold);
    let m = c.metrics();
    let d = [
        ("precision", m.precision),
        ("recall", m.recall),
        ("f1", m.f1),
        ("accuracy", m.accuracy),
        ("iou_ground", m.iou_ground),
        ("iou_nonground", m.iou_nonground),
        ("miou", m.miou),
    ]
    .into_py_dict(py)?;
    let counts = [
        ("tp", c.tp),
        ("fp", c.fp),
        ("fn", c.fn_),
        ("tn", c.tn),
        ("ignored", c.ignored),
    ]
    .into_py_dict(py)?;
    d.update(counts.as_mapping())?;
    Ok(d)
}
