//! `Segmenter` (the GMM segmenter with its history) and the offline methods on one scan
//! (`pseudo_label`, `ransac`).

use std::path::PathBuf;

use groundwork_core::height_filter::SegmentHeight;
use groundwork_core::{FrameReport, GroundMethod, SegmentError, Segmenter};
use groundwork_io::Scan;
use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, Ransac};
use numpy::{IntoPyArray, PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{IntoPyDict, PyDict};

use crate::convert::*;

pub(crate) fn segment_error(e: SegmentError) -> PyErr {
    value_error(e)
}

/// The GMM ground segmenter (Gaussian mixture per polar segment, multi-frame history).
///
/// Keeps state between calls: the history of the last `frames` scans (used when poses are
/// given) and the zone-1 height filter. One instance per sensor stream; feed it scans in
/// time order. Not shared between threads (use one per thread).
#[pyclass(module = "groundwork", name = "Segmenter")]
pub(crate) struct PySegmenter {
    /// Boxed: the segmenter holds 32-byte aligned SIMD vectors, and Python allocates its
    /// objects 16-byte aligned (unboxed, an aligned AVX load of them faulted).
    inner: Box<Segmenter>,
    sensor: String,
    last: Option<FrameReport>,
    /// Placeholder rows (NaN or inf coordinates) given probability 0 so far.
    placeholders: u64,
}

#[pymethods]
impl PySegmenter {
    #[new]
    #[pyo3(signature = (sensor=None, config=None, frames=None, **overrides))]
    fn new(
        sensor: Option<&str>,
        config: Option<PathBuf>,
        frames: Option<u32>,
        overrides: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let cfg = load_config(sensor, config, frames, overrides)?;
        Ok(Self {
            inner: Box::new(Segmenter::new(cfg.segmenter).map_err(value_error)?),
            sensor: sensor.unwrap_or(groundwork_io::DEFAULT_SENSOR).to_string(),
            last: None,
            placeholders: 0,
        })
    }

    /// Ground probability per point, in input order. Rows with a NaN or infinite
    /// coordinate are "no return" placeholders: probability 0, in place (counted in
    /// `counters["placeholders"]`).
    #[pyo3(signature = (points, pose=None))]
    fn segment<'py>(
        &mut self,
        points: &Bound<'py, PyAny>,
        pose: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let py = points.py();
        let arr = points_array(points)?;
        let pose = pose.map(pose_arg).transpose()?;
        let pts = Points::of(&arr)?;
        let mut out = vec![0.0f32; pts.len()];
        let seg = &mut self.inner;
        let report = match pts.without_placeholders() {
            None => py.detach(|| match pts {
                Points::Xyz(p) => seg.segment(p, pose.as_ref(), &mut out),
                Points::Xyzi(p) => seg.segment(p, pose.as_ref(), &mut out),
            }),
            Some(scan) if scan.points.is_empty() => {
                return Err(value_error(format!(
                    "none of its {} points has finite coordinates",
                    pts.len()
                )));
            }
            Some(scan) => {
                let mut probs = vec![0.0f32; scan.points.len()];
                let r = py.detach(|| seg.segment(&scan.points, pose.as_ref(), &mut probs));
                if r.is_ok() {
                    out = scan.expand(&probs, 0.0);
                    self.placeholders += scan.skipped() as u64;
                }
                r
            }
        }
        .map_err(segment_error)?;
        self.last = Some(report);
        Ok(out.into_pyarray(py))
    }

    /// Ground mask: probability ≥ `threshold` (default: the configuration's).
    #[pyo3(signature = (points, pose=None, threshold=None))]
    fn ground<'py>(
        &mut self,
        points: &Bound<'py, PyAny>,
        pose: Option<&Bound<'py, PyAny>>,
        threshold: Option<f32>,
    ) -> PyResult<Bound<'py, PyArray1<bool>>> {
        let thr = threshold.unwrap_or(self.inner.config().decision_threshold());
        let probs = self.segment(points, pose)?;
        let mask: Vec<bool> = probs
            .readonly()
            .as_slice()?
            .iter()
            .map(|&p| p >= thr)
            .collect();
        Ok(mask.into_pyarray(points.py()))
    }

    /// Forgets the history and the height filter (a new sequence).
    fn reset(&mut self) -> bool {
        self.inner.reset()
    }

    /// Probability at or above which a point is ground: `ground_threshold` under the map.
    #[getter]
    fn threshold(&self) -> f32 {
        self.inner.config().decision_threshold()
    }

    /// Frames of history queried (1: single frame).
    #[getter]
    fn frames(&self) -> u32 {
        self.inner.config().history.frames
    }

    /// Past frames held for multi-frame queries now.
    #[getter]
    fn history_len(&self) -> usize {
        self.inner.history_len()
    }

    /// The mount observed in the ground fitted so far (height m, roll_deg, pitch_deg,
    /// tilt_from_configured_deg, height_from_configured m, scans) and the mount in use
    /// (applied_height m, applied_roll_deg, applied_pitch_deg: the configured one unless
    /// `mount_check={"mode": "correct"}` moved it; correcting, corrected_scans), or None
    /// before any scan with enough ground or with `mount_check={"mode": "off"}`.
    #[getter]
    fn observed_mount<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(m) = self.inner.observed_mount() else {
            return Ok(None);
        };
        let d = [
            ("height", m.height),
            ("roll_deg", m.roll.to_degrees()),
            ("pitch_deg", m.pitch.to_degrees()),
            (
                "tilt_from_configured_deg",
                m.tilt_from_configured.to_degrees(),
            ),
            ("height_from_configured", m.height_from_configured),
            ("applied_height", m.applied_height),
            ("applied_roll_deg", m.applied_roll.to_degrees()),
            ("applied_pitch_deg", m.applied_pitch.to_degrees()),
        ]
        .into_py_dict(py)?;
        d.set_item("scans", m.scans)?;
        d.set_item("correcting", m.correcting)?;
        d.set_item("corrected_scans", m.corrected_scans)?;
        Ok(Some(d))
    }

    /// The sensor preset it was built from.
    #[getter]
    fn sensor(&self) -> &str {
        &self.sensor
    }

    /// Scans segmented and rejected, history resets by reason, out-of-bounds points.
    #[getter]
    fn counters<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let c = self.inner.counters();
        [
            ("scans", c.scans),
            ("rejected", c.rejected),
            ("without_pose", c.without_pose),
            ("history_resets", c.history_resets),
            ("resets_pose_jump", c.resets_pose_jump),
            ("resets_time_gap", c.resets_time_gap),
            ("resets_requested", c.resets_requested),
            ("out_of_bounds_points", c.out_of_bounds_points),
            ("non_finite_outputs", c.non_finite_outputs),
            ("placeholders", self.placeholders),
        ]
        .into_py_dict(py)
    }

    /// The zone-1 height filter: a summary and, per segment, the running mean height (m,
    /// ground-aligned frame), its variance (m²) and the frames seen.
    #[getter]
    fn height_filter<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let f = self.inner.height_filter();
        let s = f.summary();
        let d = PyDict::new(py);
        d.set_item("active_segments", s.active_segments)?;
        d.set_item("mean_height", s.mean_height)?;
        d.set_item("mean_std", s.mean_std)?;
        let segs = f.segments();
        let column =
            |v: fn(&SegmentHeight) -> f64| segs.iter().map(v).collect::<Vec<_>>().into_pyarray(py);
        d.set_item("mean", column(|x| x.mean))?;
        d.set_item("variance", column(|x| x.variance))?;
        let frames: Vec<u32> = segs.iter().map(|x| x.frames).collect();
        d.set_item("frames", frames.into_pyarray(py))?;
        Ok(d)
    }

    /// The last scan segmented: points, ground_points, frames_queried, posed,
    /// history_cleared, em_iterations, fit_ms and query_ms (the library's own time); None
    /// before the first.
    #[getter]
    fn last_report<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(r) = &self.last else {
            return Ok(None);
        };
        let d = PyDict::new(py);
        d.set_item("points", r.points)?;
        d.set_item("ground_points", r.ground_points)?;
        d.set_item("frames_queried", r.frames_queried)?;
        d.set_item("posed", r.posed)?;
        d.set_item("history_cleared", r.history_cleared)?;
        d.set_item("em_iterations", r.em_iterations)?;
        d.set_item("fit_ms", r.fit_time.as_secs_f64() * 1e3)?;
        d.set_item("query_ms", r.query_time.as_secs_f64() * 1e3)?;
        Ok(Some(d))
    }

    fn __repr__(&self) -> String {
        format!(
            "Segmenter(sensor={:?}, frames={}, threshold={})",
            self.sensor,
            self.frames(),
            self.threshold()
        )
    }
}

/// Runs an offline method on one scan with the GIL released.
pub(crate) fn run_method<'py>(
    py: Python<'py>,
    method: &mut (dyn GroundMethod + Send),
    points: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyArray1<f32>>> {
    let arr = points_array(points)?;
    let all = Points::of(&arr)?;
    // Placeholder rows (NaN, inf): probability 0 in place, as in `Segmenter.segment`.
    let scan = all
        .without_placeholders()
        .unwrap_or_else(|| Scan::dense(all.to_vec()));
    let mut probs = vec![0.0f32; scan.points.len()];
    py.detach(|| method.segment_scan(&scan.points, None, &mut probs))
        .map_err(segment_error)?;
    Ok(scan.expand(&probs, 0.0).into_pyarray(py))
}

/// TerraSeg's PseudoLabeler on one scan: ground probability per point.
#[pyfunction]
#[pyo3(signature = (points, seed=0, sensor=None, config=None, **overrides))]
pub(crate) fn pseudo_label<'py>(
    points: &Bound<'py, PyAny>,
    seed: u64,
    sensor: Option<&str>,
    config: Option<PathBuf>,
    overrides: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyArray1<f32>>> {
    let cfg = load_config(sensor, config, None, overrides)?;
    let frame = GroundFrame::from_config(&cfg.segmenter).map_err(value_error)?;
    let mut pl_cfg = cfg.pseudolabeler.clone();
    pl_cfg.seed = seed;
    let mut m = PseudoLabeler::new(pl_cfg, frame).map_err(value_error)?;
    run_method(points.py(), &mut m, points)
}

/// The RANSAC plane baseline on one scan: ground probability per point.
#[pyfunction]
#[pyo3(signature = (points, sensor=None, config=None, **overrides))]
pub(crate) fn ransac<'py>(
    points: &Bound<'py, PyAny>,
    sensor: Option<&str>,
    config: Option<PathBuf>,
    overrides: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyArray1<f32>>> {
    let cfg = load_config(sensor, config, None, overrides)?;
    let frame = GroundFrame::from_config(&cfg.segmenter).map_err(value_error)?;
    let mut m = Ransac::new(cfg.ransac.clone(), frame).map_err(value_error)?;
    run_method(points.py(), &mut m, points)
}
