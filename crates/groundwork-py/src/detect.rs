//! `detect`: the fallback detector's proposals and cluster ids.

use std::path::PathBuf;

use groundwork_detect::{Detections, Detector};
use numpy::{IntoPyArray, PyArray1};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::*;

/// One object proposal of [`detect`]: lengths in metres, angles in radians, in the
/// sensor's ground-aligned frame (x forward, y left, z up, origin on the ground below the
/// sensor).
#[pyclass(module = "groundwork", name = "Proposal", frozen, get_all)]
pub(crate) struct PyProposal {
    id: u32,
    centroid: (f32, f32, f32),
    center: (f32, f32),
    yaw: f32,
    length: f32,
    width: f32,
    ground_z: f32,
    bottom: f32,
    height: f32,
    points: u32,
    flags: Vec<&'static str>,
}

#[pymethods]
impl PyProposal {
    fn __repr__(&self) -> String {
        format!(
            "Proposal(id={}, center=({:.2}, {:.2}), yaw={:.3}, length={:.2}, width={:.2}, height={:.2}, points={}, flags={:?})",
            self.id,
            self.center.0,
            self.center.1,
            self.yaw,
            self.length,
            self.width,
            self.height,
            self.points,
            self.flags
        )
    }
}

/// The fallback detector: proposals (nearest first) and a cluster id per point (0: none).
#[pyfunction]
#[pyo3(signature = (points, probabilities, sensor=None, config=None, **overrides))]
pub(crate) fn detect<'py>(
    points: &Bound<'py, PyAny>,
    probabilities: &Bound<'py, PyAny>,
    sensor: Option<&str>,
    config: Option<PathBuf>,
    overrides: Option<&Bound<'py, PyDict>>,
) -> PyResult<(Vec<PyProposal>, Bound<'py, PyArray1<u32>>)> {
    let py = points.py();
    let cfg = load_config(sensor, config, None, overrides)?;
    let mut det = Detector::new(cfg.detector, &cfg.segmenter).map_err(value_error)?;
    let arr = points_array(points)?;
    let probs = vector::<f32>(probabilities, "float32", "probabilities")?;
    let probs = probs.as_slice().map_err(value_error)?;
    let pts = Points::of(&arr)?;
    let mut out = Detections::default();
    py.detach(|| match pts {
        Points::Xyz(p) => det.detect(p, probs, &mut out),
        Points::Xyzi(p) => det.detect(p, probs, &mut out),
    })
    .map_err(value_error)?;
    let proposals = out
        .proposals
        .iter()
        .map(|p| PyProposal {
            id: p.id,
            centroid: p.centroid.into(),
            center: p.center.into(),
            yaw: p.yaw,
            length: p.length,
            width: p.width,
            ground_z: p.ground_z,
            bottom: p.bottom,
            height: p.height,
            points: p.points,
            flags: p.flags.names().collect(),
        })
        .collect();
    Ok((proposals, out.clusters.into_pyarray(py)))
}
