//! groundwork-io: the file formats around the pure core — scans (KITTI, nuScenes, PCD,
//! PLY), ROS 2 recordings (MCAP PointCloud2), SemanticKITTI labels, KITTI poses and
//! calibration, `.prob`/`.ground` outputs, TOML configuration. Every error names the file
//! and the problem.

pub mod config;
pub mod error;
pub mod file;
pub mod input;
pub mod kitti;
pub mod labels;
pub mod output;
pub mod pcd;
pub mod ply;
pub mod pointcloud2;
pub mod recording;
pub mod scan;

pub use config::{
    DEFAULT_SENSOR, MethodsConfig, SENSOR_PRESETS, load_config, load_config_over,
    load_methods_config_layers, load_methods_config_over, parse_config, parse_methods_config,
    sensor_preset,
};
pub use error::FormatError;
pub use input::{ScanItem, ScanIter, ScanSource};
pub use kitti::{
    lidar_poses, read_calib_tr, read_labels, read_poses, write_calib_tr, write_labels, write_poses,
};
pub use labels::{LABEL_MAPS, LabelClass, LabelMap};
pub use output::{
    OutputTarget, PROPOSALS_FRAME, check_not_an_input, check_output_names, outputs_complete,
    read_clusters, read_prob, write_atomic, write_detections, write_outputs,
};
pub use recording::{RecordedScan, RecordingReader, RecordingWriter};
pub use scan::{InputKind, Scan, ScanFormat, list_scans, read_scan, scan_stem, write_kitti_bin};
