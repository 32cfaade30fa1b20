//! The zone-1 adaptive sensor-height filter (paper §III-D), as explicit state.
//!
//! Close to the sensor, multipath returns below the road can gather enough points to own a
//! component, which would then pass for the lowest ("ground") component and wreck the
//! elevation likelihood. Per zone-1 segment we keep an exponentially weighted mean and
//! standard deviation of the height of the components judged ground in past frames, and
//! ignore components below mean − k·std when finding the segment's lowest component.
//!
//! The state is bounded (one small record per zone-1 segment, exponential forgetting),
//! inspectable (`segments`, `summary`) and resettable (`reset`): it never drifts silently.

use crate::config::HeightFilterConfig;

/// Moving statistics of one zone-1 segment.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SegmentHeight {
    /// Exponentially weighted mean height of ground components (m, ground-aligned frame).
    pub mean: f64,
    /// Exponentially weighted variance (m²).
    pub variance: f64,
    /// Frames that contributed (saturating).
    pub frames: u32,
}

/// Aggregate of the filter state, for logs and reports.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct HeightFilterSummary {
    /// Segments past their warm-up, i.e. actively filtering.
    pub active_segments: usize,
    /// Mean of their mean heights (m).
    pub mean_height: f64,
    /// Mean of their standard deviations (m).
    pub mean_std: f64,
}

/// Per-segment state of the zone-1 height filter.
#[derive(Debug, Clone)]
pub struct HeightFilter {
    cfg: HeightFilterConfig,
    segments: Vec<SegmentHeight>,
}

impl HeightFilter {
    /// A fresh filter for `segments` zone-1 segments.
    pub fn new(cfg: HeightFilterConfig, segments: usize) -> Self {
        Self {
            cfg,
            segments: vec![SegmentHeight::default(); segments],
        }
    }

    /// Components of zone-1 segment `seg` whose mean lies below this are ignored when
    /// finding the lowest component; `None` while the filter is off or warming up.
    pub fn lower_bound(&self, seg: usize) -> Option<f64> {
        let s = self.segments.get(seg)?;
        if !self.cfg.enabled || s.frames < self.cfg.warmup_frames.max(1) {
            return None;
        }
        let std = s.variance.sqrt().max(self.cfg.min_std);
        Some(s.mean - self.cfg.sigmas * std)
    }

    /// Feeds one frame's ground-component height of segment `seg`.
    pub fn observe(&mut self, seg: usize, height: f64) {
        let w = self.cfg.smoothing;
        let Some(s) = self.segments.get_mut(seg) else {
            return;
        };
        if !height.is_finite() {
            return;
        }
        if s.frames == 0 {
            *s = SegmentHeight {
                mean: height,
                variance: 0.0,
                frames: 1,
            };
            return;
        }
        // Exponentially weighted mean and variance (West's incremental form).
        let d = height - s.mean;
        s.mean += w * d;
        s.variance = (1.0 - w) * (s.variance + w * d * d);
        s.frames = s.frames.saturating_add(1);
    }

    /// The minimum ground likelihood for a component to feed the filter.
    pub fn min_ground_likelihood(&self) -> f64 {
        self.cfg.min_ground_likelihood
    }

    /// Forgets everything (e.g. after a relocalisation or a sensor remount).
    pub fn reset(&mut self) {
        self.segments.fill(SegmentHeight::default());
    }

    /// Per-segment state, indexed like zone 1's segments.
    pub fn segments(&self) -> &[SegmentHeight] {
        &self.segments
    }

    /// Aggregate view for logs.
    pub fn summary(&self) -> HeightFilterSummary {
        let active: Vec<&SegmentHeight> = (0..self.segments.len())
            .filter(|&i| self.lower_bound(i).is_some())
            .map(|i| &self.segments[i])
            .collect();
        let n = active.len();
        if n == 0 {
            return HeightFilterSummary::default();
        }
        HeightFilterSummary {
            active_segments: n,
            mean_height: active.iter().map(|s| s.mean).sum::<f64>() / n as f64,
            mean_std: active.iter().map(|s| s.variance.sqrt()).sum::<f64>() / n as f64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warms_up_filters_and_resets() {
        let cfg = HeightFilterConfig {
            warmup_frames: 3,
            ..Default::default()
        };
        let mut f = HeightFilter::new(cfg, 4);
        f.observe(1, 0.02);
        f.observe(1, -0.02);
        assert_eq!(f.lower_bound(1), None, "still warming up");
        f.observe(1, 0.0);
        let lb = f.lower_bound(1).unwrap();
        // EWMA mean 0.02 → 0.016 → 0.0144; the std (≈ 1.3 cm) is below the 5 cm floor, so
        // the bound is mean − 3 · 0.05.
        let s = f.segments()[1];
        assert!((s.mean - 0.0144).abs() < 1e-12, "{s:?}");
        assert!(s.variance.sqrt() < 0.05);
        assert!((lb - (0.0144 - 0.15)).abs() < 1e-12, "{lb}");
        assert_eq!(f.summary().active_segments, 1);
        f.reset();
        assert_eq!(f.lower_bound(1), None);
        assert_eq!(f.segments()[1], SegmentHeight::default());
    }

    #[test]
    fn state_is_bounded_and_follows_a_real_change() {
        let mut f = HeightFilter::new(HeightFilterConfig::default(), 1);
        for _ in 0..10_000 {
            f.observe(0, 0.0);
        }
        // The ground really moves 0.3 m (e.g. a load changes the pitch): the filter follows
        // within a few tens of frames instead of excluding the ground for ever.
        for _ in 0..60 {
            f.observe(0, -0.3);
        }
        assert!((f.segments()[0].mean + 0.3).abs() < 0.01);
        assert!(f.lower_bound(0).unwrap() < -0.3);
        // Non-finite inputs are ignored, not absorbed.
        f.observe(0, f64::NAN);
        assert!(f.segments()[0].mean.is_finite());
    }

    #[test]
    fn disabled_filter_never_filters() {
        let cfg = HeightFilterConfig {
            enabled: false,
            ..Default::default()
        };
        let mut f = HeightFilter::new(cfg, 1);
        for _ in 0..10 {
            f.observe(0, 0.0);
        }
        assert_eq!(f.lower_bound(0), None);
    }
}
