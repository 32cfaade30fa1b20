//! groundwork from Python (`import groundwork`): the GMM segmenter with its multi-frame
//! history, the offline methods (PseudoLabeler, RANSAC), the scan readers, evaluation and
//! the fallback detector, on numpy arrays. A thin layer: arrays in, the library's calls,
//! arrays out; every error of the library is a Python exception with its message.
//!
//! Points are read without a copy when they are a C-contiguous float32 (N, 3) or (N, 4)
//! array (x, y, z[, intensity], metres, sensor frame); anything else numpy can convert is
//! converted once. The GIL is released while a scan is processed, so Python threads with
//! one `Segmenter` each run in parallel. The typed interface is `python/groundwork/__init__.pyi`.

mod calibrate;
mod convert;
mod detect;
mod evaluate;
mod io;
mod segmenter;

use groundwork_io::SENSOR_PRESETS;
use pyo3::prelude::*;

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
    m.add_class::<segmenter::PySegmenter>()?;
    m.add_class::<detect::PyProposal>()?;
    m.add_function(wrap_pyfunction!(segmenter::pseudo_label, m)?)?;
    m.add_function(wrap_pyfunction!(segmenter::ransac, m)?)?;
    m.add_function(wrap_pyfunction!(detect::detect, m)?)?;
    m.add_function(wrap_pyfunction!(io::read_scan, m)?)?;
    m.add_function(wrap_pyfunction!(io::read_recording, m)?)?;
    m.add_function(wrap_pyfunction!(io::read_poses, m)?)?;
    m.add_function(wrap_pyfunction!(io::read_labels, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate::evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(sensors, m)?)?;
    m.add_function(wrap_pyfunction!(calibrate::calibrate, m)?)?;
    Ok(())
}
