//! groundwork-core: LiDAR ground segmentation with per-segment Gaussian mixture models
//! (Neumann et al., "LiDAR Ground Segmentation with Gaussian Mixture Models").
//!
//! Pure algorithm: no file I/O, no IPC, no CLI. The pipeline per scan:
//! 1. mount transform into the ground-aligned frame (x forward, y left, z up);
//! 2. concentric zone model binning ([`zones`]);
//! 3. per-segment GMM fitted by EM, in parallel ([`gmm`], [`model`]);
//! 4. ground likelihoods per component with outlier removal and the zone-1 height filter
//!    ([`likelihood`], [`height_filter`]);
//! 5. query: a ground probability per input point, in input order, optionally over the
//!    last N_f fitted frames ([`query`], [`Segmenter`]).

pub mod config;
pub mod cpu;
pub mod error;
mod fastmath;
pub mod frame;
pub mod gmm;
mod grouping;
pub mod height_filter;
mod history;
pub mod likelihood;
pub mod method;
pub mod model;
pub mod point;
pub mod query;
pub mod segmenter;
mod simd;
pub mod workers;
pub mod zones;

pub use config::SegmenterConfig;
pub use error::{ConfigError, SegmentError};
pub use frame::GroundFrame;
pub use method::GroundMethod;
pub use point::{Point, PointXyz, Pose, check_finite, mount_transform, pose_from_matrix};
pub use segmenter::{FrameReport, HistoryReset, Segmenter, SegmenterCounters};
