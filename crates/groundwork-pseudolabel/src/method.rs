//! The PseudoLabeler and RANSAC behind the interface every method shares.

use groundwork_core::{FrameReport, GroundMethod, Point, Pose, SegmentError};

use crate::labeler::PseudoLabeler;
use crate::ransac::Ransac;

/// Both label at 0.5 by construction.
const THRESHOLD: f32 = 0.5;

fn report(
    points: usize,
    pose: Option<&Pose>,
    out: &[f32],
    fit: std::time::Duration,
    label: std::time::Duration,
) -> FrameReport {
    FrameReport {
        points,
        frames_queried: 1,
        posed: pose.is_some(),
        ground_points: out.iter().filter(|&&p| p >= THRESHOLD).count(),
        fit_time: fit,
        query_time: label,
        ..FrameReport::default()
    }
}

impl GroundMethod for PseudoLabeler {
    fn name(&self) -> &'static str {
        "pseudolabeler"
    }

    fn threshold(&self) -> f32 {
        THRESHOLD
    }

    fn max_points(&self) -> usize {
        self.frame().max_points()
    }

    fn segment_scan(
        &mut self,
        points: &[Point],
        pose: Option<&Pose>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError> {
        let r = self.label(points, out)?;
        let mut rep = report(points.len(), pose, out, r.fit_time, r.label_time);
        rep.em_iterations = u64::from(r.iterations);
        Ok(rep)
    }
}

impl GroundMethod for Ransac {
    fn name(&self) -> &'static str {
        "ransac"
    }

    fn threshold(&self) -> f32 {
        THRESHOLD
    }

    fn max_points(&self) -> usize {
        self.frame().max_points()
    }

    fn segment_scan(
        &mut self,
        points: &[Point],
        pose: Option<&Pose>,
        out: &mut [f32],
    ) -> Result<FrameReport, SegmentError> {
        let r = self.label(points, out)?;
        Ok(report(
            points.len(),
            pose,
            out,
            r.time,
            std::time::Duration::ZERO,
        ))
    }
}
