//! groundwork-io: the file formats around the pure core — scans (KITTI, nuScenes, PCD,
//! PLY), ROS 2 recordings (MCAP PointCloud2), SemanticKITTI labels, KITTI poses and
//! calibration, `.prob`/`.ground` outputs, TOML configuration. Every error names the file
//! and the problem.
//!
//! ```
//! use std::path::Path;
//!
//! // Any scan file: the reader is chosen from the file (here a KITTI .bin).
//! let bin = Path::new("../../tests/data/semantickitti-00/velodyne/000000.bin");
//! let scan = groundwork_io::read_scan(bin, 200_000)?;
//! assert_eq!(scan.points.len(), 124_668);
//! // One probability per point out, in input order.
//! let dir = tempfile::tempdir()?;
//! let probabilities = vec![0.75f32; scan.points.len()];
//! groundwork_io::write_outputs(dir.path(), "000000", &probabilities, 0.5)?;
//! assert_eq!(groundwork_io::read_prob(&dir.path().join("000000.prob"))?, probabilities);
//! // A file that is not what it claims is an error naming it.
//! let e = groundwork_io::read_scan(Path::new("Cargo.toml"), 10).unwrap_err();
//! assert!(e.to_string().contains("Cargo.toml"));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

/// The ros2msg definitions of `std_msgs/Header` and its `builtin_interfaces/Time`, which
/// every MCAP schema of a stamped message must carry (a schema holds its dependencies).
macro_rules! header_definitions {
    () => {
        "================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"
    };
}

pub mod bin;
mod cdr;
pub mod config;
pub mod error;
pub mod file;
pub mod input;
pub mod kitti;
pub mod labels;
pub mod metrics;
pub mod output;
pub mod pcd;
pub mod ply;
pub mod pointcloud2;
pub mod recording;
mod rosbag2;
pub mod scan;
pub mod sequence;
pub mod transform;

pub use bin::{kitti_bin_bytes, write_kitti_bin};
pub use config::methods::{
    MethodsConfig, load_methods_config_layers, load_methods_config_named, load_methods_config_over,
    parse_methods_config,
};
pub use config::{
    DEFAULT_SENSOR, Layers, METHOD_SECTIONS, PRESET_KEY, SENSOR_PRESETS, config_error, load_config,
    load_config_over, load_layers, parse_config, parse_table, read_table, segmenter_config,
    sensor_preset,
};
pub use error::FormatError;
pub use input::{
    FolderContents, InputKind, ScanFormat, ScanItem, ScanIter, ScanSource, list_folder, list_scans,
    read_scan, scan_stem,
};
pub use kitti::{
    calib_tr_text, labels_bytes, lidar_poses, poses_text, read_calib_tr, read_labels, read_poses,
    read_times, times_text, write_calib_tr, write_labels, write_poses, write_times,
};
pub use labels::{LABEL_MAPS, LabelClass, LabelMap, label_folder, label_folders};
pub use metrics::{Confusion, Metrics, Protocol, Reliability, ReliabilityBin};
pub use output::{
    OutputFiles, OutputTarget, check_not_an_input, check_output_names, earlier_outputs,
    outputs_complete, read_clusters, read_prob, warn_replaced, write_atomic, write_outputs,
};
pub use recording::{
    OtherMessage, OtherMessages, RecordedScan, RecordingReader, RecordingWriter, SchemaRecord,
};
pub use scan::Scan;
pub use sequence::Sequence;
