//! Every parameter of the detector: the `[detector]` section of a configuration file.

use groundwork_core::ConfigError;
use serde::{Deserialize, Serialize};

/// Detector parameters. Distances in metres, in the ground-aligned frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DetectorConfig {
    /// A point whose ground probability is at least this is ground (the segmenter's
    /// threshold unless set).
    pub ground_threshold: Option<f32>,
    /// Ground points less sure than this (probability in [threshold, join_probability))
    /// that sit at least `min_height` above the local ground and touch a cluster join it:
    /// the low parts of objects (bumpers, wheels, feet) the segmenter half-believes are
    /// ground. Set it to the threshold to turn joining off.
    pub join_probability: f32,
    /// Points nearer than this horizontally are not clustered (the segmenter's
    /// `zones.min_range`, where it decides nothing, unless set).
    pub min_range: Option<f32>,
    /// Points farther than this horizontally are not clustered.
    pub max_range: f32,
    /// Non-ground points lower than this above the local ground are not clustered (curb
    /// edges, grass, the segmenter's noise at the ground's surface).
    pub min_height: f32,
    /// Points higher than this above the local ground are not clustered (tree crowns,
    /// upper storeys): they would join whatever stands beneath them.
    pub max_height: f32,
    /// Side of the bird's-eye clustering grid's cells. Two point groups join when the
    /// lower bound of their distance that the grid gives is within the cluster distance:
    /// points up to one cell diagonal farther apart than that may join.
    pub cell_size: f32,
    /// Cluster distance near the sensor.
    pub cluster_distance: f32,
    /// Growth of the horizontal cluster distance with horizontal range r:
    /// d_h(r) = max(cluster_distance, distance_per_metre · r). A spinning sensor's points
    /// along a ring are close (0.1–0.4° apart), so this grows slowly: cars parked a metre
    /// apart stay apart.
    pub distance_per_metre: f32,
    /// Growth of the vertical cluster distance: d_v(r) = max(cluster_distance,
    /// vertical_distance_per_metre · r). Rings are far apart in height at range (the beam
    /// spacing times r): set it to about 1.5 × tan(beam spacing) of the sensor, so one
    /// object's rings stay one cluster (the sensor presets do). Two point groups join when
    /// (horizontal gap / d_h)² + (vertical gap / d_v)² ≤ 1.
    pub vertical_distance_per_metre: f32,
    /// Clusters with fewer points are dropped (their points get id 0).
    pub min_points: u32,
    /// Clusters with more points are kept but flagged `many_points`.
    pub max_points: u32,
    /// Side of the local ground height map's cells.
    pub ground_cell: f32,
    /// Cells searched around a cell with no ground point (rings). Beyond, the ground is
    /// unknown: non-ground points there are clustered whatever their height.
    pub ground_search: u32,
    /// Longest box side of an object-like proposal; longer ones are flagged `large`.
    pub max_length: f32,
    /// Tallest object-like proposal (top above the local ground); taller: `tall`.
    pub max_object_height: f32,
    /// Boxes at least this long and at most `wall_width` wide are flagged `wall`.
    pub wall_length: f32,
    /// See `wall_length`.
    pub wall_width: f32,
    /// Clusters whose lowest point is more than this above the local ground are flagged
    /// `floating` (a crown, a sign or a bridge without its support in view).
    pub floating_height: f32,
}

impl Default for DetectorConfig {
    fn default() -> Self {
        Self {
            ground_threshold: None,
            join_probability: 0.8,
            min_range: None,
            max_range: 80.0,
            min_height: 0.15,
            max_height: 4.0,
            cell_size: 0.15,
            cluster_distance: 0.5,
            distance_per_metre: 0.01,
            vertical_distance_per_metre: 0.02,
            min_points: 8,
            max_points: 20_000,
            ground_cell: 1.0,
            ground_search: 4,
            max_length: 15.0,
            max_object_height: 4.5,
            wall_length: 6.0,
            wall_width: 1.0,
            floating_height: 1.2,
        }
    }
}

impl DetectorConfig {
    /// The horizontal cluster distance at horizontal range `r`.
    #[inline]
    pub fn distance_at(&self, r: f32) -> f32 {
        self.cluster_distance.max(self.distance_per_metre * r)
    }

    /// The vertical cluster distance at horizontal range `r`.
    #[inline]
    pub fn vertical_distance_at(&self, r: f32) -> f32 {
        self.cluster_distance
            .max(self.vertical_distance_per_metre * r)
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, reason: &str| {
            Err(ConfigError {
                field: format!("detector.{field}"),
                reason: reason.into(),
            })
        };
        let positive = [
            ("max_range", self.max_range),
            ("cell_size", self.cell_size),
            ("cluster_distance", self.cluster_distance),
            ("ground_cell", self.ground_cell),
            ("max_length", self.max_length),
            ("max_object_height", self.max_object_height),
            ("wall_length", self.wall_length),
            ("wall_width", self.wall_width),
            ("floating_height", self.floating_height),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, "must be a positive number");
            }
        }
        for (field, v) in [
            ("distance_per_metre", self.distance_per_metre),
            (
                "vertical_distance_per_metre",
                self.vertical_distance_per_metre,
            ),
            ("min_height", self.min_height),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, "must be a number ≥ 0");
            }
        }
        if !(self.max_height.is_finite() && self.max_height > self.min_height) {
            return bad("max_height", "must be a number above min_height");
        }
        for (field, v) in [
            ("ground_threshold", self.ground_threshold),
            ("join_probability", Some(self.join_probability)),
        ] {
            if v.is_some_and(|p| !(0.0..=1.0).contains(&p)) {
                return bad(field, "must be a probability in [0, 1]");
            }
        }
        if let Some(r) = self.min_range
            && !(r.is_finite() && r >= 0.0 && r < self.max_range)
        {
            return bad("min_range", "must be ≥ 0 and below max_range");
        }
        // The grid spans ±max_range; a cell far smaller than the scene would make it huge.
        if self.max_range / self.cell_size > 4096.0 {
            return bad(
                "cell_size",
                "gives more than 8192 × 8192 grid cells over ±max_range",
            );
        }
        if self.distance_at(self.max_range + 2.0) > 30.0 * self.cell_size {
            return bad(
                "cell_size",
                "the cluster distance at max_range must stay under 30 cells",
            );
        }
        if self.max_range / self.ground_cell > 4096.0 {
            return bad(
                "ground_cell",
                "gives more than 8192 × 8192 cells over ±max_range",
            );
        }
        if self.min_points == 0 || self.max_points < self.min_points {
            return bad("min_points", "must be ≥ 1 and at most max_points");
        }
        if self.ground_search > 64 {
            return bad("ground_search", "must be at most 64 cells");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_fields_are_named() {
        DetectorConfig::default().validate().unwrap();
        let c = DetectorConfig {
            max_height: 0.1,
            ..Default::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("detector.max_height")
        );
        let c = DetectorConfig {
            join_probability: 1.5,
            ..Default::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("detector.join_probability")
        );
        let c = DetectorConfig {
            cell_size: 0.001,
            ..Default::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("detector.cell_size")
        );
    }

    #[test]
    fn the_cluster_distance_grows_with_range() {
        let c = DetectorConfig::default();
        assert_eq!(c.distance_at(5.0), 0.5);
        assert!((c.distance_at(100.0) - 1.0).abs() < 1e-6);
        assert!((c.vertical_distance_at(50.0) - 1.0).abs() < 1e-6);
    }
}
