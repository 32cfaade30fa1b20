//! Errors of the pure core. Callers that know the file a scan came from wrap these with it.

use thiserror::Error;

/// An inconsistent configuration value.
#[derive(Debug, Clone, Error, PartialEq)]
#[error("invalid configuration: {field}: {reason}")]
pub struct ConfigError {
    /// Dotted path of the offending field.
    pub field: String,
    /// What is wrong with it.
    pub reason: String,
}

impl ConfigError {
    pub(crate) fn invalid(field: &str, reason: &str) -> Self {
        Self {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

/// Why a scan could not be segmented. The scan is rejected whole; the segmenter's state
/// (history, height filter) is left untouched.
#[derive(Debug, Clone, Error, PartialEq)]
pub enum SegmentError {
    /// A coordinate is NaN or infinite.
    #[error("point {index} has a non-finite coordinate ({x}, {y}, {z})")]
    NonFinitePoint {
        /// Index of the first offending point, in input order.
        index: usize,
        /// Its coordinates.
        x: f32,
        /// Its coordinates.
        y: f32,
        /// Its coordinates.
        z: f32,
    },
    /// More points than `sensor.max_points`.
    #[error("scan has {points} points, more than the configured maximum of {max}")]
    TooManyPoints {
        /// Points in the scan.
        points: usize,
        /// Configured maximum.
        max: usize,
    },
    /// The output buffer does not have one slot per input point.
    #[error("output buffer holds {got} values but the scan has {expected} points")]
    OutputSize {
        /// Points in the scan.
        expected: usize,
        /// Length of the output buffer.
        got: usize,
    },
    /// A pose with a non-finite entry or a non-rigid rotation.
    #[error("invalid pose: {0}")]
    InvalidPose(String),
}
