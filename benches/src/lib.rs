//! Shared bits of the benchmarks: the vendored data and the preset.

use std::path::PathBuf;

use groundwork_core::{Point, SegmenterConfig};

/// The vendored SemanticKITTI sequence.
pub fn kitti_sequence() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/semantickitti-00")
}

/// The HDL-64E preset.
pub fn preset() -> anyhow::Result<SegmenterConfig> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config/sensors/hdl64e.toml");
    Ok(groundwork_io::load_config(&p)?)
}

/// KITTI frame `n` (0..=5) of the vendored sequence.
pub fn kitti_frame(n: usize) -> anyhow::Result<Vec<Point>> {
    let p = kitti_sequence().join(format!("velodyne/{n:06}.bin"));
    Ok(groundwork_io::read_scan(&p, 1_000_000)?.points)
}
