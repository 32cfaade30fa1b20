//! groundwork-io: the file formats around the pure core — KITTI/nuScenes scans,
//! SemanticKITTI labels, KITTI poses and calibration, `.prob`/`.ground` outputs, TOML
//! configuration. Every error names the file and the problem.

pub mod config;
pub mod error;
pub mod kitti;
pub mod output;
pub mod scan;

pub use config::{load_config, parse_config};
pub use error::FormatError;
pub use kitti::{lidar_poses, read_calib_tr, read_labels, read_poses};
pub use output::{read_prob, write_outputs};
pub use scan::{ScanFormat, list_scans, read_scan, scan_stem, write_kitti_bin};
