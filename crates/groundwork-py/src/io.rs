//! The readers: scans, recordings, poses and labels.

use std::path::PathBuf;

use groundwork_core::Point;
use groundwork_io::LabelMap;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayMethods};
use pyo3::prelude::*;

use crate::convert::*;

/// Reads a scan file (KITTI .bin, nuScenes .pcd.bin, PCD, PLY): an (N, 4) float32 array of
/// x, y, z, intensity (metres, sensor frame). Records with non-finite coordinates
/// (placeholders of organised clouds) are left out.
#[pyfunction]
#[pyo3(signature = (path, max_points=10_000_000))]
pub(crate) fn read_scan<'py>(
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
pub(crate) fn read_recording<'py>(
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
pub(crate) fn xyzi_array<'py>(
    py: Python<'py>,
    points: &[Point],
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let flat: Vec<f32> = points
        .iter()
        .flat_map(|p| [p.x, p.y, p.z, p.intensity])
        .collect();
    flat.into_pyarray(py).reshape([points.len(), 4])
}

/// The sensor's world poses of a KITTI sequence (world from sensor, (N, 4, 4) float64),
/// from the camera poses and the calibration's `Tr`, as `groundwork segment` computes them.
#[pyfunction]
pub(crate) fn read_poses<'py>(
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
pub(crate) fn read_labels<'py>(
    py: Python<'py>,
    path: PathBuf,
    points: usize,
    label_format: &str,
) -> PyResult<Bound<'py, PyArray1<u32>>> {
    let map = LabelMap::load(label_format).map_err(format_error)?;
    let raw = map.read_raw(&path, points).map_err(format_error)?;
    Ok(raw.into_pyarray(py))
}
