//! groundwork-ros2: the ROS 2 bridge stage. It subscribes to a `sensor_msgs/PointCloud2`
//! topic over DDS, publishes each cloud into the pipeline's `scans` topic (stamp and frame
//! kept), and answers each mask on ROS 2 topics, stamped with the input's stamp and frame:
//! the cloud with a `ground_probability` field (`~/points`), the non-ground points
//! (`~/nonground`) and, if asked, the ground points (`~/ground`). With an odometry topic or
//! the TF tree (`/tf`, `/tf_static`), each scan carries its pose, and the segmenter its
//! multi-frame history.
//!
//! DDS is RustDDS through `ros2-client` (pure Rust, no ROS installation, ROS 2's topic
//! naming `rt/<name>` and type naming `pkg::msg::dds_::Type_`). The layout of clouds is
//! read and written by `groundwork-io::pointcloud2`, the same code that reads recordings:
//! a cloud gives the same scan whether it came from a recording or from DDS.

pub mod bridge;
pub mod msg;
pub mod odom;
pub mod pose;
pub mod tf;

pub use bridge::{BridgeOptions, BridgeReport, Qos, cloud_type, profile, ros_name, run};
