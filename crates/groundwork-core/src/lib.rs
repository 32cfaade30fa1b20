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
//!    last N_f fitted frames ([`query`], [`Segmenter`]);
//! 6. ground continuity: uncertain points at the height of confident ground next to them
//!    are raised towards ground (docs/algorithm.md);
//! 7. the preset's monotone map to calibrated probabilities ([`probability`]).
//!
//! ```
//! use groundwork_core::{Point, Segmenter, SegmenterConfig};
//!
//! // A flat road 1.73 m below the sensor (the KITTI mount) and a wall 10 m ahead.
//! let mut cfg = SegmenterConfig::default();
//! cfg.sensor.mount.height = 1.73;
//! let mut points = Vec::new();
//! for i in 0..200 {
//!     for j in 0..60 {
//!         points.push(Point::new(3.0 + i as f32 * 0.2, -6.0 + j as f32 * 0.2, -1.73));
//!     }
//! }
//! for k in 0..400 {
//!     points.push(Point::new(10.0, -2.0 + (k % 20) as f32 * 0.2, -1.5 + (k / 20) as f32 * 0.1));
//! }
//! let mut segmenter = Segmenter::new(cfg)?;
//! let mut probabilities = vec![0.0f32; points.len()];
//! segmenter.segment(&points, None, &mut probabilities)?;
//! let threshold = segmenter.config().decision_threshold();
//! // The road is ground, the wall's upper part is not.
//! assert!(probabilities[..12_000].iter().filter(|&&p| p >= threshold).count() > 11_000);
//! assert!(probabilities[12_000 + 200..].iter().all(|&p| p < threshold));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]

pub mod config;
mod continuity;
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
pub mod mount_watch;
pub mod point;
pub mod probability;
pub mod query;
pub mod segmenter;
mod simd;
mod terrain;
pub mod zones;

pub use config::{SegmenterConfig, mount_transform};
pub use error::{ConfigError, SegmentError};
pub use frame::GroundFrame;
pub use method::GroundMethod;
pub use point::{Point, PointXyz, Pose, check_finite, pose_from_matrix};
pub use segmenter::{FrameReport, HistoryReset, Segmenter, SegmenterCounters};
