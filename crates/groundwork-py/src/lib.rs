//! groundwork from Python (`import groundwork`): the GMM segmenter with its multi-frame
//! history, the offline methods (PseudoLabeler, RANSAC), the scan readers, evaluation and
//! the fallback detector, on numpy arrays. A thin layer: arrays in, the library's calls,
//! arrays out; every error of the library is a Python exception with its message.
//!
//! Points are read without a copy when they are a C-contiguous float32 (N, 3) or (N, 4)
//! array (x, y, z[, intensity], metres, sensor frame); anything else numpy can convert is
//! converted once. The GIL is released while a scan is processed, so Python threads with
//! one `Segmenter` each run in parallel. The typed interface is `python/groundwork/__init__.pyi`.

use std::path::PathBuf;

use groundwork_core::height_filter::SegmentHeight;
use groundwork_core::{
    FrameReport, GroundMethod, Point, Pose, SegmentError, Segmenter, pose_from_matrix,
};
use groundwork_detect::{Detections, Detector};
use groundwork_eval::MethodsConfig;
use groundwork_eval::{Confusion, Protocol};
use groundwork_io::{FormatError, LabelMap, SENSOR_PRESETS, Scan};
use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, Ransac};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray2,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{IntoPyDict, PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};

fn value_error(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// A file that cannot be read is an `OSError`; a file that reads but is wrong, a
/// `ValueError` (both with the library's message, which names the file).
fn format_error(e: FormatError) -> PyErr {
    match e {
        FormatError::Io { .. } => PyOSError::new_err(e.to_string()),
        e => value_error(e),
    }
}

/// A keyword argument's value as TOML (bool, int, float, str, dict, list).
fn to_toml(v: &Bound<'_, PyAny>) -> PyResult<toml::Value> {
    // bool before int: Python's bool is an int.
    Ok(if v.is_instance_of::<PyBool>() {
        toml::Value::Boolean(v.extract()?)
    } else if v.is_instance_of::<PyInt>() {
        toml::Value::Integer(v.extract()?)
    } else if v.is_instance_of::<PyFloat>() {
        toml::Value::Float(v.extract()?)
    } else if v.is_instance_of::<PyString>() {
        toml::Value::String(v.extract()?)
    } else if let Ok(d) = v.cast::<PyDict>() {
        toml::Value::Table(to_table(d)?)
    } else if v.is_instance_of::<PyList>() || v.is_instance_of::<PyTuple>() {
        toml::Value::Array(
            v.try_iter()?
                .map(|x| to_toml(&x?))
                .collect::<PyResult<_>>()?,
        )
    } else {
        return Err(value_error(format!(
            "configuration values are bool, int, float, str, dict or list, not {}",
            v.get_type().name()?
        )));
    })
}

fn to_table(d: &Bound<'_, PyDict>) -> PyResult<toml::Table> {
    d.iter()
        .map(|(k, v)| Ok((k.extract::<String>()?, to_toml(&v)?)))
        .collect()
}

/// The configuration: the sensor preset (default hdl64e), the TOML file over it, then the
/// keyword arguments (sections as dicts, e.g. `history={"frames": 3}`), then `frames`.
fn load_config(
    sensor: Option<&str>,
    config: Option<PathBuf>,
    frames: Option<u32>,
    overrides: Option<&Bound<'_, PyDict>>,
) -> PyResult<MethodsConfig> {
    let overlay = match overrides {
        Some(d) if !d.is_empty() => {
            let mut t = to_table(d)?;
            // `mount=dict(height=…, pitch_deg=…)` is short for `sensor={"mount": …}`.
            if let Some(m) = t.remove("mount") {
                let sensor = t
                    .entry("sensor")
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                match sensor.as_table_mut() {
                    Some(s) => {
                        s.insert("mount".into(), m);
                    }
                    None => return Err(value_error("sensor= must be a dict")),
                }
            }
            Some(("keyword arguments", t))
        }
        _ => None,
    };
    let mut cfg = groundwork_eval::load_methods_config_layers(sensor, config.as_deref(), overlay)
        .map_err(format_error)?;
    if let Some(n) = frames {
        cfg.segmenter.history.frames = n;
        cfg.segmenter
            .validate()
            .map_err(|e| value_error(format!("frames: {e}")))?;
    }
    Ok(cfg)
}

/// `v` as a C-contiguous numpy array of `dtype` (float32, uint32, …): `v` itself when it
/// already is one, else converted by numpy.
fn contiguous<'py>(v: &Bound<'py, PyAny>, dtype: &str) -> PyResult<Bound<'py, PyAny>> {
    let np = v.py().import("numpy")?;
    let kwargs = PyDict::new(v.py());
    kwargs.set_item("dtype", np.getattr(dtype)?)?;
    np.call_method("ascontiguousarray", (v,), Some(&kwargs))
}

/// Points as float32, C-contiguous, (N, 3) or (N, 4): the caller's array itself when it
/// already is one. Columns after the fourth (a nuScenes ring index, a time offset) are
/// ignored, as the CLI ignores them in files.
fn points_array<'py>(points: &Bound<'py, PyAny>) -> PyResult<PyReadonlyArray2<'py, f32>> {
    let mut arr = contiguous(points, "float32")?;
    let shape: Vec<usize> = arr.getattr("shape")?.extract()?;
    if shape.len() != 2 || shape[1] < 3 {
        return Err(value_error(format!(
            "points must be an (N, 3) or (N, 4+) array (x, y, z[, intensity, ...]), got shape {shape:?}"
        )));
    }
    if shape[1] > 4 {
        let py = points.py();
        let builtins = py.import("builtins")?;
        let all = builtins.getattr("slice")?.call1((py.None(),))?;
        let first4 = builtins.getattr("slice")?.call1((4,))?;
        let view = arr.get_item((all, first4))?;
        arr = contiguous(&view, "float32")?;
    }
    arr.extract()
}

/// A 1-D C-contiguous array of `dtype` (converted if need be); `what` names it in errors.
fn vector<'py, T: numpy::Element>(
    v: &Bound<'py, PyAny>,
    dtype: &str,
    what: &str,
) -> PyResult<numpy::PyReadonlyArray1<'py, T>> {
    let arr = contiguous(v, dtype)?;
    let ndim: usize = arr.getattr("ndim")?.extract()?;
    if ndim != 1 {
        return Err(value_error(format!(
            "{what} must be a 1-D array, got {ndim} dimensions"
        )));
    }
    arr.extract()
}

/// A scan's points viewed in place.
#[derive(Clone, Copy)]
enum Points<'a> {
    Xyz(&'a [[f32; 3]]),
    Xyzi(&'a [[f32; 4]]),
}

impl<'a> Points<'a> {
    fn of(arr: &'a PyReadonlyArray2<'_, f32>) -> PyResult<Self> {
        let flat = arr.as_slice().map_err(value_error)?;
        Ok(if arr.shape()[1] == 3 {
            Self::Xyz(flat.as_chunks().0)
        } else {
            Self::Xyzi(flat.as_chunks().0)
        })
    }

    fn len(self) -> usize {
        match self {
            Self::Xyz(p) => p.len(),
            Self::Xyzi(p) => p.len(),
        }
    }

    fn get(self, i: usize) -> Point {
        match self {
            Self::Xyz(p) => Point::new(p[i][0], p[i][1], p[i][2]),
            Self::Xyzi(p) => Point {
                x: p[i][0],
                y: p[i][1],
                z: p[i][2],
                intensity: p[i][3],
            },
        }
    }

    /// The rows whose x, y and z are finite, as the readers leave out "no return"
    /// placeholders (an organized PCD or PointCloud2): a [`Scan`] whose `expand` puts one
    /// value per kept row back in place, 0 for the placeholders, as the CLI does. None:
    /// every row is finite.
    fn without_placeholders(self) -> Option<Scan> {
        let finite = |i: usize| {
            let p = self.get(i);
            p.x.is_finite() && p.y.is_finite() && p.z.is_finite()
        };
        let n = self.len();
        if (0..n).all(finite) {
            return None;
        }
        let rows: Vec<u32> = (0..n).filter(|&i| finite(i)).map(|i| i as u32).collect();
        Some(Scan {
            points: rows.iter().map(|&i| self.get(i as usize)).collect(),
            source_index: Some(rows),
            records: n,
            ..Scan::default()
        })
    }

    /// As the library's point records (a copy: the offline methods take `Point`s).
    fn to_vec(self) -> Vec<Point> {
        let point = |x, y, z, intensity| Point { x, y, z, intensity };
        match self {
            Self::Xyz(p) => p.iter().map(|&[x, y, z]| point(x, y, z, 0.0)).collect(),
            Self::Xyzi(p) => p.iter().map(|&[x, y, z, i]| point(x, y, z, i)).collect(),
        }
    }
}

/// A 4 × 4 pose (world from sensor) from anything numpy reads as one.
fn pose_arg(pose: &Bound<'_, PyAny>) -> PyResult<Pose> {
    let np = pose.py().import("numpy")?;
    let m = np.call_method1("asarray", (pose, np.getattr("float64")?))?;
    let shape: Vec<usize> = m.getattr("shape")?.extract()?;
    if shape != [4, 4] {
        return Err(value_error(format!(
            "pose must be a 4 × 4 matrix (world from sensor), got shape {shape:?}"
        )));
    }
    let rows: [[f64; 4]; 4] = m.call_method0("tolist")?.extract()?;
    pose_from_matrix(&rows).map_err(value_error)
}

fn segment_error(e: SegmentError) -> PyErr {
    value_error(e)
}

/// The GMM ground segmenter (Gaussian mixture per polar segment, multi-frame history).
///
/// Keeps state between calls: the history of the last `frames` scans (used when poses are
/// given) and the zone-1 height filter. One instance per sensor stream; feed it scans in
/// time order. Not shared between threads (use one per thread).
#[pyclass(module = "groundwork", name = "Segmenter")]
struct PySegmenter {
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
        let thr = threshold.unwrap_or(self.inner.config().ground.ground_threshold);
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

    /// Probability at or above which a point is ground.
    #[getter]
    fn threshold(&self) -> f32 {
        self.inner.config().ground.ground_threshold
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
fn run_method<'py>(
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
fn pseudo_label<'py>(
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
fn ransac<'py>(
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

/// One object proposal of [`detect`]: lengths in metres, angles in radians, in the
/// sensor's ground-aligned frame (x forward, y left, z up, origin on the ground below the
/// sensor).
#[pyclass(module = "groundwork", name = "Proposal", frozen, get_all)]
struct PyProposal {
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
fn detect<'py>(
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

/// Reads a scan file (KITTI .bin, nuScenes .pcd.bin, PCD, PLY): an (N, 4) float32 array of
/// x, y, z, intensity (metres, sensor frame). Records with non-finite coordinates
/// (placeholders of organised clouds) are left out.
#[pyfunction]
#[pyo3(signature = (path, max_points=10_000_000))]
fn read_scan<'py>(
    py: Python<'py>,
    path: PathBuf,
    max_points: usize,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let scan = py
        .detach(|| groundwork_io::read_scan(&path, max_points))
        .map_err(format_error)?;
    xyzi_array(py, &scan.points)
}

/// The point clouds of a ROS 2 recording (MCAP, `sensor_msgs/msg/PointCloud2`) on `topic`
/// (default: the first point cloud topic), in log order: a list of (log time in ns, (N, 4)
/// float32 array of x, y, z, intensity). A message that cannot be decoded is an error naming
/// it.
#[pyfunction]
#[pyo3(signature = (path, topic=None, max_points=10_000_000))]
fn read_recording<'py>(
    py: Python<'py>,
    path: PathBuf,
    topic: Option<&str>,
    max_points: usize,
) -> PyResult<Vec<(u64, Bound<'py, PyArray2<f32>>)>> {
    let scans = py
        .detach(|| {
            groundwork_io::RecordingReader::open(&path, topic, max_points)?
                .collect::<Result<Vec<_>, _>>()
        })
        .map_err(format_error)?;
    scans
        .into_iter()
        .map(|s| Ok((s.log_time_ns, xyzi_array(py, &s.scan.points)?)))
        .collect()
}

/// Points as an (N, 4) float32 array: x, y, z, intensity.
fn xyzi_array<'py>(py: Python<'py>, points: &[Point]) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let flat: Vec<f32> = points
        .iter()
        .flat_map(|p| [p.x, p.y, p.z, p.intensity])
        .collect();
    flat.into_pyarray(py).reshape([points.len(), 4])
}

/// The sensor's world poses of a KITTI sequence (world from sensor, (N, 4, 4) float64),
/// from the camera poses and the calibration's `Tr`, as `groundwork segment` computes them.
#[pyfunction]
fn read_poses<'py>(
    py: Python<'py>,
    poses: PathBuf,
    calib: PathBuf,
) -> PyResult<Bound<'py, PyArray3<f64>>> {
    let cam = groundwork_io::read_poses(&poses).map_err(format_error)?;
    let tr = groundwork_io::read_calib_tr(&calib).map_err(format_error)?;
    let lidar = groundwork_io::lidar_poses(&cam, &tr);
    let flat: Vec<f64> = lidar
        .iter()
        .flat_map(|p| {
            let m = p.to_homogeneous();
            (0..16).map(move |k| m[(k / 4, k % 4)])
        })
        .collect();
    flat.into_pyarray(py).reshape([lidar.len(), 4, 4])
}

/// Ground-truth labels of a scan (SemanticKITTI `.label`: u32 per point, class in the low
/// 16 bits, instance in the high 16), checked against the scan's point count.
#[pyfunction]
#[pyo3(signature = (path, points, label_format="semantickitti"))]
fn read_labels<'py>(
    py: Python<'py>,
    path: PathBuf,
    points: usize,
    label_format: &str,
) -> PyResult<Bound<'py, PyArray1<u32>>> {
    let map = LabelMap::load(label_format).map_err(format_error)?;
    let raw = map.read_raw(&path, points).map_err(format_error)?;
    Ok(raw.into_pyarray(py))
}

/// Scores ground probabilities against labels as `groundwork eval` does: a point is ground
/// when its probability is at least `threshold`; `protocol` "gmm" ignores vegetation,
/// "terraseg" counts it as non-ground. Metrics in percent, and the counts.
#[pyfunction]
#[pyo3(signature = (probabilities, labels, protocol="gmm", threshold=0.5, label_format="semantickitti"))]
fn evaluate<'py>(
    py: Python<'py>,
    probabilities: &Bound<'py, PyAny>,
    labels: &Bound<'py, PyAny>,
    protocol: &str,
    threshold: f32,
    label_format: &str,
) -> PyResult<Bound<'py, PyDict>> {
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
    param_scans=48, param_trust=90.0, param_min_gain=2.5, fit_zones=false, **overrides
))]
#[allow(clippy::too_many_arguments)] // the keyword arguments of a Python function
fn calibrate<'py>(
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
    overrides: Option<&Bound<'py, PyDict>>,
) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
    use groundwork_calibrate::{
        MountSearchConfig, NearEdgeConfig, ParamSearchConfig, combine_near_ground, estimate_mount,
        fit_to_pseudo_labels, view_near_ground, zones_for_mount,
    };
    if param_scans == 0 {
        return Err(value_error("param_scans must be at least 1"));
    }
    if fit_zones && keep_params {
        return Err(value_error(
            "fit_zones fits the zones with the parameters: not with keep_params",
        ));
    }
    let search = ParamSearchConfig {
        trust_agreement: param_trust,
        min_held_out_gain: param_min_gain,
        fit_zones,
        ..ParamSearchConfig::default()
    };
    search.check().map_err(|(field, why)| {
        let keyword = match field {
            "trust_agreement" => "param_trust",
            "min_held_out_gain" => "param_min_gain",
            other => other,
        };
        value_error(format!("{keyword}: {why}"))
    })?;
    let cfg = load_config(sensor, config, None, overrides)?;
    let prior =
        groundwork_core::mount_transform(&cfg.segmenter.sensor.mount).map_err(value_error)?;
    let settings = MountSearchConfig {
        seed,
        ..MountSearchConfig::default()
    };
    settings.validate().map_err(value_error)?;
    let xyz: Vec<Vec<[f32; 3]>> = scans
        .iter()
        .map(|s| {
            let arr = points_array(s)?;
            Ok(match Points::of(&arr)? {
                Points::Xyz(p) => p.to_vec(),
                Points::Xyzi(p) => p.iter().map(|&[x, y, z, _]| [x, y, z]).collect(),
            })
        })
        .collect::<PyResult<_>>()?;
    let (views, est) = py.detach(|| estimate_mount(&xyz, &prior, &settings));
    let est = est.map_err(value_error)?;
    let (zones, ego) = (&cfg.segmenter.zones, cfg.segmenter.sensor.ego_radius);
    let near_cfg = NearEdgeConfig::default();
    let near = (!keep_zones)
        .then(|| {
            combine_near_ground(
                xyz.iter()
                    .zip(&views)
                    .filter_map(|(p, v)| view_near_ground(p, v.as_ref().ok()?, ego, &near_cfg))
                    .collect(),
            )
        })
        .flatten();
    // The zones follow the mount found: the near edge, and the inner boundaries the height
    // against the preset's (`near` is None with keep_zones).
    let preset_mount = (!keep_zones)
        .then(|| groundwork_io::sensor_preset(sensor.unwrap_or(groundwork_io::DEFAULT_SENSOR)))
        .and_then(Result::ok)
        .map(|p| p.sensor.mount);
    let fitted = zones_for_mount(
        zones,
        near.as_ref(),
        preset_mount.as_ref().map(|m| (est.mount().height, m)),
        ego,
        &near_cfg,
    );
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
    if let Some(z) = &fitted.zones {
        let section = PyDict::new(py);
        section.set_item("min_range", z.min_range)?;
        section.set_item("boundaries", z.boundaries.clone())?;
        preset.set_item("zones", section)?;
    }
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
    for v in &views {
        let item = PyDict::new(py);
        match v {
            Ok(f) => {
                item.set_item("height", f.height)?;
                item.set_item("roll_deg", f.roll * d)?;
                item.set_item("pitch_deg", f.pitch * d)?;
                item.set_item("inliers", f.plane.inliers)?;
            }
            Err(e) => item.set_item("problem", e.to_string())?,
        }
        per_scan.append(item)?;
    }
    report.set_item("per_scan", per_scan)?;
    if let Some(n) = &near {
        let item = PyDict::new(py);
        item.set_item("ground_from", n.range)?;
        item.set_item("scans", n.scans)?;
        item.set_item("was", zones.min_range)?;
        item.set_item("min_range", fitted.near_edge)?;
        report.set_item("near_edge", item)?;
    }
    if let Some(h) = &fitted.height_scale {
        let item = PyDict::new(py);
        item.set_item("ratio", h.ratio)?;
        item.set_item("was", h.was.clone())?;
        item.set_item("boundaries", h.boundaries.clone())?;
        report.set_item("height_scale", item)?;
    }
    if !keep_params {
        // As the CLI: the mount found and the zones moved for it, a sample spread evenly
        // over the scans.
        let mut base = cfg.segmenter.clone();
        base.sensor.mount = est.mount();
        if let Some(z) = &fitted.zones {
            base.zones = z.clone();
        }
        let every = xyz.len().div_ceil(param_scans).max(1);
        let sample: Vec<Vec<[f32; 3]>> = xyz
            .iter()
            .step_by(every)
            .take(param_scans)
            .cloned()
            .collect();
        let fit =
            py.detach(|| fit_to_pseudo_labels(&base, &cfg.pseudolabeler, &sample, &search, |_| {}));
        match fit {
            Ok(fit) => {
                if let Some(ground) = changed_ground(py, &base.ground, &fit.config.ground)? {
                    preset.set_item("ground", ground)?;
                }
                let z = &fit.config.zones;
                if !z.same_layout(&base.zones) {
                    // The whole layout the fit left (the near edge's move included).
                    let section = PyDict::new(py);
                    section.set_item("min_range", z.min_range)?;
                    section
                        .set_item("boundaries", z.resolved_boundaries().map_err(value_error)?)?;
                    section.set_item("rings", z.rings.clone())?;
                    section.set_item("sectors", z.sectors.clone())?;
                    preset.set_item("zones", section)?;
                }
                report.set_item("parameters", param_fit_dict(py, &fit)?)?;
            }
            // The mount is calibrated: a refusal here is the parameters' alone.
            Err(e) => report.set_item("parameters_refused", e.reason())?,
        }
    }
    Ok((preset, report))
}

/// The `[ground]` settings `new` changed from `old`, as keyword arguments (None if none).
fn changed_ground<'py>(
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
fn param_fit_dict<'py>(
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

/// The sensor presets (`sensor=` of every call).
#[pyfunction]
fn sensors() -> Vec<&'static str> {
    SENSOR_PRESETS.iter().map(|(n, _)| *n).collect()
}

#[pymodule(name = "_native")]
fn groundwork(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // python/groundwork/__init__.py checks x86-64's level before this module loads (pyo3's
    // own set-up already runs vectorised code). This is the check of an aarch64 build for a
    // newer core, whose features only the native side knows.
    groundwork_core::cpu::check()
        .map_err(|e| pyo3::exceptions::PyImportError::new_err(format!("groundwork: {e}")))?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<PySegmenter>()?;
    m.add_class::<PyProposal>()?;
    m.add_function(wrap_pyfunction!(pseudo_label, m)?)?;
    m.add_function(wrap_pyfunction!(ransac, m)?)?;
    m.add_function(wrap_pyfunction!(detect, m)?)?;
    m.add_function(wrap_pyfunction!(read_scan, m)?)?;
    m.add_function(wrap_pyfunction!(read_recording, m)?)?;
    m.add_function(wrap_pyfunction!(read_poses, m)?)?;
    m.add_function(wrap_pyfunction!(read_labels, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(sensors, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate, m)?)?;
    Ok(())
}
