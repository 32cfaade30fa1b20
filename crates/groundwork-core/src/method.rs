//! One interface for every ground segmentation method (the GMM segmenter here, the
//! PseudoLabeler and RANSAC beside it), so that commands and the evaluator treat them alike.

use crate::error::SegmentError;
use crate::point::{Point, Pose};
use crate::segmenter::{FrameReport, Segmenter};

/// A ground segmentation method: one probability in [0, 1] per point, in input order.
pub trait GroundMethod: Send {
    /// Short name, as `--method` spells it.
    fn name(&self) -> &'static str;
    /// Probability at or above which a point counts as ground.
    fn threshold(&self) -> f32;
    /// Largest scan accepted (readers stop earlier).
    fn max_points(&self) -> usize;
    /// Frames of history it queries (1: single-frame).
    fn history_frames(&self) -> u32 {
        1
    }
    /// Segments one scan (sensor frame) with its world pose if known; a rejected scan is an
    /// error and leaves the method's state untouched.
    fn segment_scan(
        &mut self,
        points: &[Point],
        pose: Option<&Pose>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError>;
}

impl GroundMethod for Segmenter {
    fn name(&self) -> &'static str {
        "gmm"
    }

    fn threshold(&self) -> f32 {
        self.config().decision_threshold()
    }

    fn max_points(&self) -> usize {
        self.config().sensor.max_points
    }

    fn history_frames(&self) -> u32 {
        self.config().history.frames
    }

    fn segment_scan(
        &mut self,
        points: &[Point],
        pose: Option<&Pose>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError> {
        self.segment(points, pose, out)
    }
}
