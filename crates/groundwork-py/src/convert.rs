//! Python values to the library's and back: errors as exceptions, keyword arguments as
//! a configuration layer, point arrays read without a copy where they allow it, poses.

use std::path::PathBuf;

use groundwork_core::{Point, Pose, pose_from_matrix};
use groundwork_io::MethodsConfig;
use groundwork_io::{FormatError, Scan};
use numpy::{PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};

pub(crate) fn value_error(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// A file that cannot be read is an `OSError`; a file that reads but is wrong, a
/// `ValueError` (both with the library's message, which names the file).
pub(crate) fn format_error(e: FormatError) -> PyErr {
    match e {
        FormatError::Io { .. } => PyOSError::new_err(e.to_string()),
        e => value_error(e),
    }
}

/// A keyword argument's value as TOML (bool, int, float, str, dict, list).
pub(crate) fn to_toml(v: &Bound<'_, PyAny>) -> PyResult<toml::Value> {
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

pub(crate) fn to_table(d: &Bound<'_, PyDict>) -> PyResult<toml::Table> {
    d.iter()
        .map(|(k, v)| Ok((k.extract::<String>()?, to_toml(&v)?)))
        .collect()
}

/// The configuration: the sensor preset (default hdl64e), the TOML file over it, then the
/// keyword arguments (sections as dicts, e.g. `history={"frames": 3}`), then `frames`.
pub(crate) fn load_config(
    sensor: Option<&str>,
    config: Option<PathBuf>,
    frames: Option<u32>,
    overrides: Option<&Bound<'_, PyDict>>,
) -> PyResult<MethodsConfig> {
    Ok(load_config_named(sensor, config, frames, overrides)?.1)
}

/// [`load_config`], and the preset it was laid over: `sensor`, else the one the file names,
/// else the default.
pub(crate) fn load_config_named(
    sensor: Option<&str>,
    config: Option<PathBuf>,
    frames: Option<u32>,
    overrides: Option<&Bound<'_, PyDict>>,
) -> PyResult<(String, MethodsConfig)> {
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
    let (preset, mut cfg) = groundwork_io::load_methods_config_named(
        sensor,
        groundwork_io::DEFAULT_SENSOR,
        config.as_deref(),
        overlay,
    )
    .map_err(format_error)?;
    if let Some(n) = frames {
        cfg.segmenter.history.frames = n;
        cfg.segmenter
            .validate()
            .map_err(|e| value_error(format!("frames: {e}")))?;
    }
    Ok((preset, cfg))
}

/// `v` as a C-contiguous numpy array of `dtype` (float32, uint32, …): `v` itself when it
/// already is one, else converted by numpy.
pub(crate) fn contiguous<'py>(v: &Bound<'py, PyAny>, dtype: &str) -> PyResult<Bound<'py, PyAny>> {
    let np = v.py().import("numpy")?;
    let kwargs = PyDict::new(v.py());
    kwargs.set_item("dtype", np.getattr(dtype)?)?;
    np.call_method("ascontiguousarray", (v,), Some(&kwargs))
}

/// Points as float32, C-contiguous, (N, 3) or (N, 4): the caller's array itself when it
/// already is one. Columns after the fourth (a nuScenes ring index, a time offset) are
/// ignored, as the CLI ignores them in files.
pub(crate) fn points_array<'py>(
    points: &Bound<'py, PyAny>,
) -> PyResult<PyReadonlyArray2<'py, f32>> {
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
pub(crate) fn vector<'py, T: numpy::Element>(
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
pub(crate) enum Points<'a> {
    Xyz(&'a [[f32; 3]]),
    Xyzi(&'a [[f32; 4]]),
}

impl<'a> Points<'a> {
    pub(crate) fn of(arr: &'a PyReadonlyArray2<'_, f32>) -> PyResult<Self> {
        let flat = arr.as_slice().map_err(value_error)?;
        Ok(if arr.shape()[1] == 3 {
            Self::Xyz(flat.as_chunks().0)
        } else {
            Self::Xyzi(flat.as_chunks().0)
        })
    }

    pub(crate) fn len(self) -> usize {
        match self {
            Self::Xyz(p) => p.len(),
            Self::Xyzi(p) => p.len(),
        }
    }

    pub(crate) fn get(self, i: usize) -> Point {
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
    pub(crate) fn without_placeholders(self) -> Option<Scan> {
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
    pub(crate) fn to_vec(self) -> Vec<Point> {
        let point = |x, y, z, intensity| Point { x, y, z, intensity };
        match self {
            Self::Xyz(p) => p.iter().map(|&[x, y, z]| point(x, y, z, 0.0)).collect(),
            Self::Xyzi(p) => p.iter().map(|&[x, y, z, i]| point(x, y, z, i)).collect(),
        }
    }
}

/// A 4 × 4 pose (world from sensor) from anything numpy reads as one.
pub(crate) fn pose_arg(pose: &Bound<'_, PyAny>) -> PyResult<Pose> {
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
