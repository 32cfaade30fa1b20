//! Helpers shared by the end-to-end tests: where the vendored data lives.

use std::path::PathBuf;

/// The vendored SemanticKITTI sequence 00, frames 0–5 (labels for 0–2).
pub fn kitti_sequence() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/semantickitti-00")
}

/// The HDL-64E preset.
pub fn hdl64e_preset() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config/sensors/hdl64e.toml")
}
