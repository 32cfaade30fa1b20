//! Every parameter of the segmenter, with the GMM paper's values as defaults.
//!
//! The structs deserialize from TOML (see `config/sensors/*.toml`); unknown keys are
//! rejected so that a typo never silently falls back to a default.

use serde::{Deserialize, Serialize};

use crate::error::ConfigError;
use crate::point::{Pose, pose_from_matrix};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// Upper bound on the zone model's segment count.
pub const MAX_SEGMENTS: u64 = 1 << 20;

/// Complete configuration of one segmenter instance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct SegmenterConfig {
    /// Sensor mount and input limits.
    pub sensor: SensorConfig,
    /// Concentric zone model (Patchwork++'s CZM).
    pub zones: ZoneConfig,
    /// Per-segment GMM fit.
    pub gmm: GmmConfig,
    /// Ground likelihoods of the fitted components, outlier rule and decision threshold.
    pub ground: GroundConfig,
    /// Zone-1 adaptive sensor-height filter (paper §III-D).
    pub height_filter: HeightFilterConfig,
    /// Multi-frame history (paper §III-F).
    pub history: HistoryConfig,
    /// The mount observed in the fitted ground, checked against `sensor.mount`.
    pub mount_check: MountCheckConfig,
    /// Uncertain points at the height of confident ground next to them become ground.
    pub continuity: ContinuityConfig,
    /// Points at the height of the terrain the confident ground traces are raised, ground
    /// standing above it lowered.
    pub terrain: TerrainConfig,
    /// The map from the equation's value to a calibrated probability.
    pub probability: ProbabilityConfig,
}

/// Terrain following, a step after continuity (docs/algorithm.md, "Terrain following"):
/// the confident ground's height in narrow sectors, walked outward from the sensor's foot
/// with a bounded grade, raises the points at its height and lowers ground standing above
/// it (the lower parts of cars).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TerrainConfig {
    /// Off (the default, and every preset's but `pandar64`'s and `vlp16`'s for now): the probabilities
    /// as continuity left them.
    pub enabled: bool,
    /// Sectors around the sensor.
    pub sectors: u32,
    /// Depth of a cell along its sector (m).
    pub cell: f64,
    /// A point's weight in a cell's height ramps from 0 at the first probability to 1 at
    /// the second (as continuity's `confident`).
    pub confident: [f64; 2],
    /// Confident weight a cell needs to be trusted fully (half of it to count at all).
    pub support: f64,
    /// Steepest grade the terrain follows (rise over run).
    pub grade: f64,
    /// A cell's height continues the terrain if within this (m) plus `grade` times the run
    /// of the height predicted from the cells nearer the sensor.
    pub step: f64,
    /// Past the last cell of confident ground the terrain carries on at its grade, trusted
    /// less and less, for this far (m).
    pub gap: f64,
    /// A point within the first height of the terrain (m) is raised fully, none beyond
    /// the second.
    pub tolerance: [f64; 2],
    /// Ground standing above the terrain is lowered: not at all below the first height
    /// (m), fully to 0 from the second. Past the last cell of confident ground both
    /// heights grow by `step` and by what a change from the steepest fall to the steepest
    /// climb (twice `grade`) rises over the gap, so that a slope starting to rise is not
    /// lowered while a car's hood over hidden road is.
    pub veto: [f64; 2],
    /// Lower ground standing above the terrain (`veto`); off, the terrain only raises. Off
    /// in the `livox` preset: a forward sensor's curving ground rises above the terrain
    /// predicted for it more often than a car's skirt stands there (docs/algorithm.md).
    pub lower: bool,
    /// What a point at the terrain's height, fully trusted, rises to.
    pub probability: f64,
}

impl Default for TerrainConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            sectors: 180,
            cell: 1.0,
            confident: [0.6, 0.75],
            support: 3.0,
            grade: 0.15,
            step: 0.1,
            gap: 10.0,
            tolerance: [0.05, 0.1],
            veto: [0.15, 0.25],
            lower: true,
            probability: 0.8,
        }
    }
}

/// Calibrated output (`crate::probability`): a monotone map from the equation's value to
/// the fraction of points that are ground, fitted on labelled scans of the sensor. The
/// decision threshold moves with it, so no point changes side.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct ProbabilityConfig {
    /// The calibrated probability at the equation values 0, 1/(n−1), …, 1, linear between;
    /// strictly increasing, in [0, 1]. Empty: the equation's value as it is.
    pub map: Vec<f32>,
}

/// Knots of a probability map at most.
pub const MAX_PROBABILITY_KNOTS: usize = 1025;

impl ProbabilityConfig {
    /// Checks the map: none, or 2 to [`MAX_PROBABILITY_KNOTS`] strictly increasing values in
    /// [0, 1].
    pub fn validate(&self) -> Result<(), ConfigError> {
        let m = &self.map;
        if m.is_empty() {
            return Ok(());
        }
        if m.len() < 2 || m.len() > MAX_PROBABILITY_KNOTS {
            return Err(ConfigError::invalid(
                "probability.map",
                "must hold 2 to 1025 values (or none: no map)",
            ));
        }
        if !m.iter().all(|v| (0.0..=1.0).contains(v)) || !m.windows(2).all(|w| w[0] < w[1]) {
            return Err(ConfigError::invalid(
                "probability.map",
                "must be strictly increasing values in [0, 1] (a map that keeps every \
                 point on its side of the threshold)",
            ));
        }
        Ok(())
    }
}

/// Ground continuity, a step after the query (docs/algorithm.md, "Ground continuity"): a
/// point the mixtures leave uncertain is raised towards ground where it lies at the height
/// of the confident ground within `reach` of it. Every rule is a ramp, not a cut, so the
/// output stays a continuous function of the coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ContinuityConfig {
    /// Off: the paper's probabilities, untouched.
    pub enabled: bool,
    /// Spacing of the horizontal grid whose nodes hold the confident ground's height (m).
    pub cell: f64,
    /// Nodes within this horizontal distance of a point count: fully within half of it,
    /// fading to nothing at it (m).
    pub reach: f64,
    /// A point within this height of a node's ground counts fully (m)...
    pub height_tolerance: f64,
    /// ...fading to nothing at this height (m).
    pub height_cutoff: f64,
    /// A point's weight in the ground height ramps from 0 at the first probability to 1
    /// at the second.
    pub confident: [f64; 2],
    /// Which points may be raised: none below the first probability, fully from the
    /// second (a point the mixtures call surely non-ground stays so).
    pub uncertain: [f64; 2],
    /// Sum of confident weights a node needs to be trusted fully (fewer: in proportion).
    pub support: f64,
    /// The probability a fully supported point is raised to (never lowered).
    pub probability: f64,
}

/// Nodes a side of the continuity grid at most (a million nodes, 24 MB of scratch per
/// worker thread at worst).
pub const MAX_CONTINUITY_SIDE: u32 = 1024;

impl Default for ContinuityConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            cell: 1.0,
            reach: 1.0,
            height_tolerance: 0.03,
            height_cutoff: 0.06,
            confident: [0.6, 0.75],
            uncertain: [0.02, 0.05],
            support: 1.0,
            probability: 0.8,
        }
    }
}

/// How the sensor sits on the vehicle, and what the segmenter accepts from it.
///
/// The segmenter works in a ground-aligned frame: x forward, y left, z up, origin on the
/// ground below the sensor. `mount` maps sensor coordinates into that frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorConfig {
    /// Human-readable preset name (only used in logs and reports).
    pub name: String,
    /// Sensor to ground-aligned frame.
    pub mount: MountConfig,
    /// Points closer than this horizontal radius belong to the ego vehicle (TerraSeg's
    /// OmniLiDAR standardisation). They get ground probability 0, like every point closer
    /// than `zones.min_range`.
    pub ego_radius: f64,
    /// Scans with more points are rejected (protects the service's fixed-size buffers).
    pub max_points: usize,
    /// Largest plausible coordinate, metres, on any axis of the sensor frame. A finite but
    /// absurd return beyond it (a corrupted packet: (10, 0, 1e20)) would overflow the f32
    /// moments of its segment's EM and poison the whole segment with NaN; such points get
    /// probability 0, are never fitted, and are counted (`out_of_bounds_points`). Default
    /// (absent): 4 × `zones.max_range`.
    pub max_coordinate: Option<f64>,
}

impl Default for SensorConfig {
    fn default() -> Self {
        Self {
            name: "generic".into(),
            mount: MountConfig::default(),
            ego_radius: 0.0,
            max_points: 200_000,
            max_coordinate: None,
        }
    }
}

/// Sensor pose relative to the ground-aligned frame: either height + roll/pitch/yaw, or a
/// full 4×4 row-major matrix (which then wins; giving both is an error). In TOML each angle
/// may be given in degrees instead (`roll_deg`, `pitch_deg`, `yaw_deg`); they are held in
/// radians.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(try_from = "MountToml")]
pub struct MountConfig {
    /// Height of the sensor origin above the ground, metres.
    pub height: f64,
    /// Rotation of the sensor about the ground frame's x axis, radians.
    pub roll: f64,
    /// Rotation about y, radians.
    pub pitch: f64,
    /// Rotation about z, radians.
    pub yaw: f64,
    /// Optional 4×4 row-major homogeneous matrix, ground-aligned from sensor.
    pub matrix: Option<[[f64; 4]; 4]>,
}

/// The mount as written in TOML: each angle in radians or in degrees, not both.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MountToml {
    #[serde(default)]
    height: f64,
    roll: Option<f64>,
    roll_deg: Option<f64>,
    pitch: Option<f64>,
    pitch_deg: Option<f64>,
    yaw: Option<f64>,
    yaw_deg: Option<f64>,
    #[serde(default)]
    matrix: Option<[[f64; 4]; 4]>,
}

/// An angle given in radians or in degrees (zero if neither), or why not.
fn radians(name: &str, rad: Option<f64>, deg: Option<f64>) -> Result<f64, String> {
    match (rad, deg) {
        (Some(_), Some(_)) => Err(format!(
            "give {name} (radians) or {name}_deg (degrees), not both"
        )),
        (Some(r), None) => Ok(r),
        (None, Some(d)) => Ok(d.to_radians()),
        (None, None) => Ok(0.0),
    }
}

impl TryFrom<MountToml> for MountConfig {
    type Error = String;

    fn try_from(m: MountToml) -> Result<Self, String> {
        Ok(Self {
            height: m.height,
            roll: radians("roll", m.roll, m.roll_deg)?,
            pitch: radians("pitch", m.pitch, m.pitch_deg)?,
            yaw: radians("yaw", m.yaw, m.yaw_deg)?,
            matrix: m.matrix,
        })
    }
}

/// What the segmenter does when the ground it fits disagrees with the configured mount.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MountCheckMode {
    /// Nothing is observed.
    Off,
    /// The observed mount is kept (`Segmenter::observed_mount`) and a warning is logged,
    /// once, when it disagrees beyond the tolerances.
    Warn,
    /// As `warn`, and the mount in use follows the observation: once it disagrees beyond
    /// the tolerances, the mount in use moves towards it by at most `correct_rate_deg` and
    /// `correct_rate_m` per scan, never further than `correct_max_deg` / `correct_max_m`
    /// from `sensor.mount`, and locks where it reaches it until the two disagree beyond
    /// the tolerances again. Outputs change while it moves.
    Correct,
}

/// Settings of the mount check (`[mount_check]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MountCheckConfig {
    /// `off`; `warn`: log once when the observed mount disagrees beyond the tolerances;
    /// `correct`: also move the mount in use towards the observed one.
    pub mode: MountCheckMode,
    /// Tolerated angle between configured and observed vertical, degrees.
    pub max_tilt_deg: f64,
    /// Tolerated height difference, metres.
    pub max_height: f64,
    /// Weight of the newest scan in the moving average (0 < w ≤ 1).
    pub smoothing: f64,
    /// Scans observed before any verdict.
    pub warmup_scans: u32,
    /// Ground components whose mean lies within this horizontal range are used, metres.
    pub range: f64,
    /// `correct`: largest turn of the mount in use per scan, degrees.
    pub correct_rate_deg: f64,
    /// `correct`: largest change of the mount's height per scan, metres.
    pub correct_rate_m: f64,
    /// `correct`: the mount in use stays within this angle of `sensor.mount`, degrees.
    pub correct_max_deg: f64,
    /// `correct`: and within this height of it, metres.
    pub correct_max_m: f64,
}

impl Default for MountCheckConfig {
    fn default() -> Self {
        Self {
            mode: MountCheckMode::Warn,
            max_tilt_deg: 3.0,
            max_height: 0.2,
            smoothing: 0.05,
            warmup_scans: 20,
            range: 20.0,
            correct_rate_deg: 0.1,
            correct_rate_m: 0.01,
            correct_max_deg: 10.0,
            correct_max_m: 1.0,
        }
    }
}

/// What a point beyond `zones.max_range` gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BeyondRangePolicy {
    /// Query the GMM of the outermost ring of the point's sector (the nearest model).
    OuterRing,
    /// Probability 0: treated as non-ground.
    NonGround,
}

/// The concentric zone model. Zone boundaries default to Patchwork++'s
/// min, (7·min+max)/8, (3·min+max)/4, (min+max)/2, max.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZoneConfig {
    /// Inner edge of the model, metres (horizontal range). Closer points get probability 0.
    pub min_range: f64,
    /// Outer edge of the model, metres (horizontal range).
    pub max_range: f64,
    /// Explicit zone boundaries (len = zones + 1, increasing); derived from the ranges if
    /// absent.
    pub boundaries: Option<Vec<f64>>,
    /// Rings per zone.
    pub rings: Vec<u32>,
    /// Sectors per zone.
    pub sectors: Vec<u32>,
    /// Treatment of points beyond `max_range`.
    pub beyond_max_range: BeyondRangePolicy,
    /// How many times the zone model is laid over each scan (1–8), each layout fitted and
    /// queried on its own and the probabilities averaged: a point whose segment border
    /// falls badly in one layout is outvoted by the others. Costs the fit and the query
    /// once per layout. See [`SegmenterConfig::layout`].
    pub layouts: u32,
    /// The inner boundaries follow the beams' rings on the preset's mount: `calibrate`
    /// scales them with the height it finds. Not read by the segmenter.
    pub scale_with_height: bool,
}

impl Default for ZoneConfig {
    fn default() -> Self {
        Self {
            min_range: 2.7,
            max_range: 80.0,
            boundaries: None,
            rings: vec![2, 4, 4, 4],
            sectors: vec![16, 32, 54, 32],
            beyond_max_range: BeyondRangePolicy::OuterRing,
            layouts: 1,
            scale_with_height: false,
        }
    }
}

impl ZoneConfig {
    /// Whether `other` lays out the zones the same way: the boundaries in use, the rings
    /// and the sectors (what a calibration writes into `[zones]` when they differ).
    pub fn same_layout(&self, other: &ZoneConfig) -> bool {
        (self.resolved_boundaries().ok(), &self.rings, &self.sectors)
            == (
                other.resolved_boundaries().ok(),
                &other.rings,
                &other.sectors,
            )
    }

    /// The zone boundaries in use: explicit ones, or Patchwork++'s derived from the ranges
    /// (only defined for four zones; other zone counts must give `boundaries`).
    pub fn resolved_boundaries(&self) -> Result<Vec<f64>, ConfigError> {
        if let Some(b) = &self.boundaries {
            return Ok(b.clone());
        }
        let (lo, hi) = (self.min_range, self.max_range);
        if self.rings.len() != 4 {
            return Err(ConfigError::invalid(
                "zones.boundaries",
                "must be given when the model does not have exactly 4 zones",
            ));
        }
        Ok(vec![
            lo,
            (7.0 * lo + hi) / 8.0,
            (3.0 * lo + hi) / 4.0,
            (lo + hi) / 2.0,
            hi,
        ])
    }
}

/// Per-segment GMM and its EM fit.
///
/// The paper gives no stopping rule; EM stops after `max_iterations` or when the mean
/// log-likelihood per point improves by less than `tolerance` (nats), whichever comes first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GmmConfig {
    /// One component per `n_min` points (N_min).
    pub n_min: u32,
    /// Upper bound on components per segment (K_max).
    pub k_max: u32,
    /// Components that are the most likely one for fewer points are removed (τ_N).
    pub tau_n: u32,
    /// Hard cap on EM iterations per segment.
    pub max_iterations: u32,
    /// Per-segment convergence test: stop when the mean log-likelihood per point changes
    /// by less than this between iterations.
    pub tolerance: f64,
    /// Added to the covariance diagonal after every M-step (m²) so that no component can
    /// become singular (e.g. on a perfectly planar patch or a segment of repeated points).
    pub covariance_regularization: f64,
    /// EM of a denser segment runs on an even subsample of this many points (0 = all).
    /// Every point is still queried and still counts for the outlier rule.
    pub max_fit_points: u32,
    /// Edges (m) of the cells a denser segment's points are summarised in, horizontal and
    /// vertical (default 0.6 × 0.12); `[0, 0]`: EM runs on the subsample instead. With
    /// cells, EM runs on every point through each cell's count, mean and scatter, so a small
    /// turn of the scan (a mount a hundredth of a degree off) cannot draw another subsample.
    pub summary_cell: [f64; 2],
}

impl Default for GmmConfig {
    fn default() -> Self {
        Self {
            n_min: 20,
            k_max: 8,
            tau_n: 10,
            max_iterations: 30,
            tolerance: 1e-3,
            covariance_regularization: 1e-4,
            max_fit_points: 256,
            summary_cell: [0.6, 0.12],
        }
    }
}

/// Slope and offset of an inverted sigmoid p(x) = 1 − 1/(1 + e^{−α(x−β)}).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sigmoid {
    /// Slope α.
    pub alpha: f64,
    /// Offset β: the input at which the likelihood is 0.5.
    pub beta: f64,
}

/// Ground likelihoods, outlier rule and the decision threshold.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GroundConfig {
    /// Flatness: on the smallest covariance eigenvalue (m²).
    pub flatness: Sigmoid,
    /// Orientation: on the angle between the smallest eigenvector and the vertical (rad).
    pub orientation: Sigmoid,
    /// Elevation: on the component mean's height above the segment's lowest inlier (m).
    pub elevation: Sigmoid,
    /// Terrain-following elevation reference (metres): a component's height is measured
    /// above the lowest inlier whose horizontal range lies within this distance of the
    /// component mean's range, not above the whole segment's lowest inlier. On a slope a
    /// long segment's lowest point is at its far (downhill) or near (uphill) end, and the
    /// rest of the slope then looks raised; a band follows the terrain. 0: the paper's
    /// segment-wide reference.
    pub elevation_window: f64,
    /// Points more than this far below the lowest retained component mean are outliers
    /// and do not define the segment's lowest point (τ_o, metres).
    pub outlier_threshold: f64,
    /// Points with ground probability ≥ this are ground (τ_g).
    pub ground_threshold: f32,
}

impl Default for GroundConfig {
    fn default() -> Self {
        Self {
            flatness: Sigmoid {
                alpha: 40.0,
                beta: 0.06,
            },
            orientation: Sigmoid {
                alpha: 4.0,
                beta: 0.8,
            },
            elevation: Sigmoid {
                alpha: 4.0,
                beta: 0.8,
            },
            elevation_window: 2.0,
            outlier_threshold: 0.5,
            ground_threshold: 0.5,
        }
    }
}

/// The zone-1 sensor-height filter: per zone-1 segment an exponentially weighted mean and
/// standard deviation of the height of high-ground-likelihood components over frames.
/// Components below mean − `sigmas`·std are ignored when finding the lowest component
/// (they are multipath reflections below the road).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HeightFilterConfig {
    /// Switch the filter off entirely.
    pub enabled: bool,
    /// Weight of the newest frame in the moving average (0 < w ≤ 1). 0.1 ≈ a 10-frame
    /// memory: bounded, and it follows a real change of ground height within a second.
    pub smoothing: f64,
    /// Components below mean − sigmas·std are excluded (the paper uses 3).
    pub sigmas: f64,
    /// Floor on the standard deviation (m), so that a perfectly steady history does not
    /// exclude ground components a few centimetres low.
    pub min_std: f64,
    /// Frames a segment must have observed before it filters anything.
    pub warmup_frames: u32,
    /// A component counts as "high ground likelihood" at or above this probability.
    pub min_ground_likelihood: f64,
}

impl Default for HeightFilterConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            smoothing: 0.1,
            sigmas: 3.0,
            min_std: 0.05,
            warmup_frames: 3,
            min_ground_likelihood: 0.5,
        }
    }
}

/// Multi-frame history.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HistoryConfig {
    /// Number of fitted models queried per scan, the current one included (N_f, 1…16).
    /// Default 2: on the vendored KITTI frames one past frame gains 0.5 IoU points and more
    /// gain nothing further, while each costs about 0.4 ms of query time here.
    pub frames: u32,
    /// A pose jump larger than this (metres of translation between consecutive frames)
    /// clears the history: the old models describe another place.
    pub max_translation_jump: f64,
    /// Same for rotation (radians).
    pub max_rotation_jump: f64,
    /// A sensor-time gap between consecutive stamped scans larger than this (seconds), or
    /// time running backwards, clears the history: the stored models are of a world that
    /// may have changed (a paused recording, a restarted driver). Scans without a sensor
    /// time are not checked.
    pub max_time_gap: f64,
    /// How a point finds the past frames' components it is normalised against.
    pub query: PastQuery,
    /// `regridded` only: how far a past component reaches beyond its mean, in standard
    /// deviations along x and y, when it is given to the query scan's segments (0: the
    /// segment of its mean alone). 0.6 matches the per-frame query's accuracy on the
    /// vendored frames; less is faster and loses a few hundredths of IoU.
    pub spread: f64,
}

/// How the multi-frame query finds a point's past components.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PastQuery {
    /// The past frames' components are moved into the query scan once per query and given to
    /// every segment their footprint (mean ± `spread` σ) reaches; a point is normalised
    /// against its own segment's lists. About half the work of `per_frame` at 16 frames.
    Regridded,
    /// The paper's §III-F literally: every point is moved into every past frame, binned
    /// there, and normalised against the components of the segment it falls into.
    PerFrame,
}

impl Default for HistoryConfig {
    fn default() -> Self {
        Self {
            frames: 2,
            max_translation_jump: 5.0,
            max_rotation_jump: 0.5,
            max_time_gap: 0.5,
            query: PastQuery::Regridded,
            spread: 0.6,
        }
    }
}

/// Largest supported history length.
pub const MAX_HISTORY_FRAMES: u32 = 16;

impl SegmenterConfig {
    /// The decision threshold on the output probabilities: a point is ground when its
    /// probability is at least this. `ground.ground_threshold` under the probability map
    /// (itself when there is none).
    pub fn decision_threshold(&self) -> f32 {
        crate::probability::ProbabilityMap::new(&self.probability, self.ground.ground_threshold)
            .threshold()
    }

    /// The coordinate bound in use (metres): `sensor.max_coordinate`, or 4 × max range.
    pub fn max_coordinate(&self) -> f64 {
        self.sensor
            .max_coordinate
            .unwrap_or(4.0 * self.zones.max_range)
    }

    /// Checks every value for consistency; the error names the offending field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let z = &self.zones;
        if !(z.min_range.is_finite() && z.min_range >= 0.0) {
            return Err(ConfigError::invalid(
                "zones.min_range",
                "must be finite and ≥ 0",
            ));
        }
        if !(z.max_range.is_finite() && z.max_range > z.min_range) {
            return Err(ConfigError::invalid(
                "zones.max_range",
                "must be finite and greater than zones.min_range",
            ));
        }
        if z.rings.is_empty() || z.rings.len() != z.sectors.len() {
            return Err(ConfigError::invalid(
                "zones.rings / zones.sectors",
                "must be non-empty and of equal length (one entry per zone)",
            ));
        }
        if z.rings
            .iter()
            .chain(&z.sectors)
            .any(|&n| n == 0 || n > 4096)
        {
            return Err(ConfigError::invalid(
                "zones.rings / zones.sectors",
                "every entry must be in 1..=4096",
            ));
        }
        let segments: u64 = z
            .rings
            .iter()
            .zip(&z.sectors)
            .map(|(&r, &s)| u64::from(r) * u64::from(s))
            .sum();
        // The vectorised binning carries segment indices exactly in f32 (below 2^23).
        if segments > MAX_SEGMENTS {
            return Err(ConfigError::invalid(
                "zones.rings / zones.sectors",
                &format!("{segments} segments in all; at most {MAX_SEGMENTS} are supported"),
            ));
        }
        let b = z.resolved_boundaries()?;
        if b.len() != z.rings.len() + 1 {
            return Err(ConfigError::invalid(
                "zones.boundaries",
                "must have one more entry than there are zones",
            ));
        }
        if b.iter().any(|v| !v.is_finite()) || b.windows(2).any(|w| w[1] <= w[0]) {
            return Err(ConfigError::invalid(
                "zones.boundaries",
                "must be finite and strictly increasing",
            ));
        }
        let g = &self.gmm;
        if g.n_min == 0 || g.k_max == 0 || g.k_max > 64 {
            return Err(ConfigError::invalid(
                "gmm.n_min / gmm.k_max",
                "n_min must be ≥ 1 and k_max in 1..=64",
            ));
        }
        if g.max_iterations == 0 {
            return Err(ConfigError::invalid("gmm.max_iterations", "must be ≥ 1"));
        }
        if !(g.tolerance.is_finite() && g.tolerance >= 0.0) {
            return Err(ConfigError::invalid(
                "gmm.tolerance",
                "must be finite and ≥ 0",
            ));
        }
        if !(g.covariance_regularization.is_finite() && g.covariance_regularization > 0.0) {
            return Err(ConfigError::invalid(
                "gmm.covariance_regularization",
                "must be finite and > 0 (a zero regulariser lets covariances become singular)",
            ));
        }
        let gr = &self.ground;
        for (name, s) in [
            ("ground.flatness", gr.flatness),
            ("ground.orientation", gr.orientation),
            ("ground.elevation", gr.elevation),
        ] {
            if !(s.alpha.is_finite() && s.beta.is_finite()) {
                return Err(ConfigError::invalid(name, "alpha and beta must be finite"));
            }
        }
        if !(gr.outlier_threshold.is_finite() && gr.outlier_threshold >= 0.0) {
            return Err(ConfigError::invalid(
                "ground.outlier_threshold",
                "must be finite and ≥ 0",
            ));
        }
        if !(0.0..=1.0).contains(&gr.ground_threshold) {
            return Err(ConfigError::invalid(
                "ground.ground_threshold",
                "must be in [0, 1]",
            ));
        }
        self.probability.validate()?;
        let t = &self.terrain;
        let cells = self.zones.max_range / t.cell * f64::from(t.sectors);
        let fits = (4..=4096).contains(&t.sectors)
            && (0.1..=10.0).contains(&t.cell)
            && cells <= (1u64 << 22) as f64;
        if !fits {
            return Err(ConfigError::invalid(
                "terrain.sectors / terrain.cell",
                "sectors in 4..=4096, cell in [0.1, 10] m, at most 2^22 cells out to \
                 zones.max_range",
            ));
        }
        for (name, [a, b]) in [
            ("terrain.confident", t.confident),
            ("terrain.tolerance", t.tolerance),
            ("terrain.veto", t.veto),
        ] {
            if !(a.is_finite() && b.is_finite() && a >= 0.0 && a < b) {
                return Err(ConfigError::invalid(
                    name,
                    "must be [from, to] with 0 ≤ from < to",
                ));
            }
        }
        if t.tolerance[1] > t.veto[0] {
            return Err(ConfigError::invalid(
                "terrain.tolerance / terrain.veto",
                "the raised band must end at or below where the lowered one begins",
            ));
        }
        for (name, v, hi) in [
            ("terrain.support", t.support, 1e6),
            ("terrain.grade", t.grade, 1.0),
            ("terrain.step", t.step, 10.0),
            ("terrain.gap", t.gap, 1000.0),
            ("terrain.probability", t.probability, 1.0),
        ] {
            if !(v.is_finite() && v >= 0.0 && v <= hi) {
                return Err(ConfigError::invalid(name, &format!("must be in [0, {hi}]")));
            }
        }
        let h = &self.height_filter;
        if !(h.smoothing > 0.0 && h.smoothing <= 1.0) {
            return Err(ConfigError::invalid(
                "height_filter.smoothing",
                "must be in (0, 1]",
            ));
        }
        if !(h.sigmas.is_finite() && h.sigmas > 0.0 && h.min_std.is_finite() && h.min_std >= 0.0) {
            return Err(ConfigError::invalid(
                "height_filter.sigmas / min_std",
                "sigmas must be > 0 and min_std ≥ 0",
            ));
        }
        if !(1..=MAX_HISTORY_FRAMES).contains(&self.history.frames) {
            return Err(ConfigError::invalid("history.frames", "must be in 1..=16"));
        }
        if !(self.history.max_translation_jump > 0.0 && self.history.max_rotation_jump > 0.0) {
            return Err(ConfigError::invalid(
                "history.max_translation_jump / max_rotation_jump",
                "must be > 0",
            ));
        }
        if !(self.history.spread.is_finite() && (0.0..=5.0).contains(&self.history.spread)) {
            return Err(ConfigError::invalid("history.spread", "must be in 0..=5"));
        }
        if !(self.history.max_time_gap.is_finite() && self.history.max_time_gap > 0.0) {
            return Err(ConfigError::invalid(
                "history.max_time_gap",
                "must be finite and > 0",
            ));
        }
        let s = &self.sensor;
        if let Some(c) = s.max_coordinate
            && !(c.is_finite() && c > z.max_range.max(z.min_range))
        {
            return Err(ConfigError::invalid(
                "sensor.max_coordinate",
                "must be finite and larger than zones.max_range",
            ));
        }
        if !(s.ego_radius.is_finite() && s.ego_radius >= 0.0) {
            return Err(ConfigError::invalid(
                "sensor.ego_radius",
                "must be finite and ≥ 0",
            ));
        }
        if s.max_points == 0 || s.max_points > u32::MAX as usize {
            return Err(ConfigError::invalid(
                "sensor.max_points",
                "must be in 1..=4294967295",
            ));
        }
        let m = &s.mount;
        let angles = [m.height, m.roll, m.pitch, m.yaw];
        if angles.iter().any(|v| !v.is_finite()) {
            return Err(ConfigError::invalid(
                "sensor.mount",
                "height, roll, pitch and yaw must be finite",
            ));
        }
        self.validate_ranges()?;
        if let Some(mat) = &m.matrix {
            if angles.iter().any(|&v| v != 0.0) {
                return Err(ConfigError::invalid(
                    "sensor.mount",
                    "give either matrix or height/roll/pitch/yaw, not both",
                ));
            }
            if mat.iter().flatten().any(|v| !v.is_finite()) || mat[3] != [0.0, 0.0, 0.0, 1.0] {
                return Err(ConfigError::invalid(
                    "sensor.mount.matrix",
                    "must be finite with last row [0, 0, 0, 1]",
                ));
            }
        }
        Ok(())
    }
}

/// A number as a person writes it: 1e30, not thirty-one digits.
fn shown(v: f64) -> String {
    if v != 0.0 && !(1e-3..1e6).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// A value in [lo, hi]; NaN and infinities are outside every range.
fn within(field: &str, v: f64, lo: f64, hi: f64, unit: &str) -> Result<(), ConfigError> {
    if v.is_finite() && (lo..=hi).contains(&v) {
        return Ok(());
    }
    Err(ConfigError::invalid(
        field,
        &format!(
            "{} is outside its range [{}, {}]{unit}",
            shown(v),
            shown(lo),
            shown(hi)
        ),
    ))
}

/// A value in (0, hi].
fn positive(field: &str, v: f64, hi: f64, unit: &str) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 && v <= hi {
        return Ok(());
    }
    Err(ConfigError::invalid(
        field,
        &format!("{} is outside its range (0, {}]{unit}", shown(v), shown(hi)),
    ))
}

/// A mount angle in radians, with a hint where the value looks like degrees.
fn angle(field: &str, v: f64, limit: f64, name: &str) -> Result<(), ConfigError> {
    if v.abs() <= limit {
        return Ok(());
    }
    Err(ConfigError::invalid(
        field,
        &format!(
            "{v} is outside ±{limit:.4} rad ({name}): angles are in radians; if you meant {v}°, \
             write {:.4} or {}_deg = {v}",
            v.to_radians(),
            field.rsplit('.').next().unwrap_or(field),
        ),
    ))
}

impl SegmenterConfig {
    /// Every number's documented range (the field docs and `docs/configuration.md` state
    /// them): values that parse but make the output meaningless (`flatness.beta = 0`: no
    /// ground; `mount.height = 1e30`; a pitch in degrees) are refused by name.
    fn validate_ranges(&self) -> Result<(), ConfigError> {
        use std::f64::consts::{FRAC_PI_2, PI};
        let s = &self.sensor;
        let m = &s.mount;
        within("sensor.mount.height", m.height, 0.0, 100.0, " m")?;
        angle("sensor.mount.roll", m.roll, FRAC_PI_2, "π/2")?;
        angle("sensor.mount.pitch", m.pitch, FRAC_PI_2, "π/2")?;
        angle("sensor.mount.yaw", m.yaw, PI, "π")?;
        if let Some(mat) = &m.matrix {
            for row in mat.iter().take(3) {
                within(
                    "sensor.mount.matrix (translation)",
                    row[3],
                    -100.0,
                    100.0,
                    " m",
                )?;
            }
            pose_from_matrix(mat)
                .map_err(|e| ConfigError::invalid("sensor.mount.matrix", &e.to_string()))?;
        }
        within("sensor.ego_radius", s.ego_radius, 0.0, 50.0, " m")?;
        if let Some(c) = s.max_coordinate {
            within("sensor.max_coordinate", c, 0.0, 1e5, " m")?;
        }
        let z = &self.zones;
        within("zones.min_range", z.min_range, 0.0, 1000.0, " m")?;
        within("zones.max_range", z.max_range, 0.0, 10_000.0, " m")?;
        let g = &self.gmm;
        within("gmm.n_min", f64::from(g.n_min), 1.0, 10_000.0, "")?;
        within("gmm.tau_n", f64::from(g.tau_n), 0.0, 10_000.0, "")?;
        within(
            "gmm.max_iterations",
            f64::from(g.max_iterations),
            1.0,
            1000.0,
            "",
        )?;
        within("gmm.tolerance", g.tolerance, 0.0, 1.0, " nats")?;
        positive(
            "gmm.covariance_regularization",
            g.covariance_regularization,
            1.0,
            " m²",
        )?;
        if g.max_fit_points != 0 {
            within(
                "gmm.max_fit_points",
                f64::from(g.max_fit_points),
                16.0,
                1e6,
                " (0: every point)",
            )?;
        }
        if g.summary_cell != [0.0, 0.0] {
            within("gmm.summary_cell[0]", g.summary_cell[0], 0.005, 2.0, " m")?;
            within("gmm.summary_cell[1]", g.summary_cell[1], 0.005, 2.0, " m")?;
        }
        let gr = &self.ground;
        positive("ground.flatness.alpha", gr.flatness.alpha, 1e4, " per m²")?;
        positive("ground.flatness.beta", gr.flatness.beta, 10.0, " m²")?;
        positive(
            "ground.orientation.alpha",
            gr.orientation.alpha,
            1e3,
            " per rad",
        )?;
        positive(
            "ground.orientation.beta",
            gr.orientation.beta,
            FRAC_PI_2,
            " rad",
        )?;
        positive("ground.elevation.alpha", gr.elevation.alpha, 1e3, " per m")?;
        positive("ground.elevation.beta", gr.elevation.beta, 10.0, " m")?;
        within(
            "ground.elevation_window",
            gr.elevation_window,
            0.0,
            100.0,
            " m",
        )?;
        within(
            "ground.outlier_threshold",
            gr.outlier_threshold,
            0.0,
            10.0,
            " m",
        )?;
        let c = &self.continuity;
        within("continuity.cell", c.cell, 0.05, 10.0, " m")?;
        // A point is scored against the (2 · reach / cell)² nodes around it: bounded.
        within(
            "continuity.reach",
            c.reach,
            c.cell,
            (8.0 * c.cell).min(20.0),
            " m (from continuity.cell to 8 cells, at most 20 m)",
        )?;
        within(
            "continuity.height_tolerance",
            c.height_tolerance,
            0.0,
            1.0,
            " m",
        )?;
        within(
            "continuity.height_cutoff",
            c.height_cutoff,
            c.height_tolerance + 1e-3,
            2.0,
            " m (above continuity.height_tolerance)",
        )?;
        for (name, [a, b]) in [
            ("continuity.confident", c.confident),
            ("continuity.uncertain", c.uncertain),
        ] {
            if !(0.0 <= a && a < b && b <= 1.0) {
                return Err(ConfigError::invalid(
                    name,
                    "must be two probabilities [from, to] with 0 ≤ from < to ≤ 1",
                ));
            }
        }
        // The grid spans ±zones.max_range: bounded, so that no setting allocates gigabytes.
        let side = 2.0 * self.zones.max_range / c.cell + 2.0;
        if c.enabled && side > f64::from(MAX_CONTINUITY_SIDE) {
            return Err(ConfigError::invalid(
                "continuity.cell",
                &format!(
                    "the grid over ±zones.max_range ({} m) would have {:.0} nodes a side (at \
                     most {MAX_CONTINUITY_SIDE}): raise cell to at least {:.2} m",
                    shown(self.zones.max_range),
                    side,
                    2.0 * self.zones.max_range / f64::from(MAX_CONTINUITY_SIDE - 2)
                ),
            ));
        }
        positive("continuity.support", c.support, 1e6, "")?;
        within("continuity.probability", c.probability, 0.0, 1.0, "")?;
        let h = &self.height_filter;
        positive("height_filter.sigmas", h.sigmas, 100.0, "")?;
        within("height_filter.min_std", h.min_std, 0.0, 10.0, " m")?;
        within(
            "height_filter.warmup_frames",
            f64::from(h.warmup_frames),
            0.0,
            10_000.0,
            "",
        )?;
        within(
            "height_filter.min_ground_likelihood",
            h.min_ground_likelihood,
            0.0,
            1.0,
            "",
        )?;
        let hi = &self.history;
        positive(
            "history.max_translation_jump",
            hi.max_translation_jump,
            1000.0,
            " m",
        )?;
        positive(
            "history.max_rotation_jump",
            hi.max_rotation_jump,
            PI,
            " rad",
        )?;
        positive("history.max_time_gap", hi.max_time_gap, 3600.0, " s")?;
        let mc = &self.mount_check;
        positive("mount_check.max_tilt_deg", mc.max_tilt_deg, 90.0, "°")?;
        positive("mount_check.max_height", mc.max_height, 100.0, " m")?;
        positive("mount_check.smoothing", mc.smoothing, 1.0, "")?;
        positive("mount_check.range", mc.range, 10_000.0, " m")?;
        positive(
            "mount_check.correct_rate_deg",
            mc.correct_rate_deg,
            90.0,
            "°",
        )?;
        positive("mount_check.correct_rate_m", mc.correct_rate_m, 100.0, " m")?;
        positive("mount_check.correct_max_deg", mc.correct_max_deg, 90.0, "°")?;
        positive("mount_check.correct_max_m", mc.correct_max_m, 100.0, " m")?;
        within(
            "zones.layouts",
            f64::from(z.layouts),
            1.0,
            f64::from(MAX_LAYOUTS),
            "",
        )?;
        if z.layouts > 1 && mc.mode == MountCheckMode::Correct {
            return Err(ConfigError::invalid(
                "zones.layouts",
                "more than one layout needs mount_check.mode = \"off\" or \"warn\": the \
                 layouts are laid on the configured mount, which \"correct\" would move",
            ));
        }
        within(
            "mount_check.warmup_scans",
            f64::from(mc.warmup_scans),
            1.0,
            1e6,
            "",
        )?;
        Ok(())
    }
}

/// The ground-aligned-from-sensor transform described by a mount configuration.
pub fn mount_transform(mount: &MountConfig) -> Result<Pose, ConfigError> {
    if let Some(m) = &mount.matrix {
        return pose_from_matrix(m).map_err(|e| ConfigError {
            field: "sensor.mount.matrix".into(),
            reason: e.to_string(),
        });
    }
    let rotation = UnitQuaternion::from_euler_angles(mount.roll, mount.pitch, mount.yaw);
    Ok(Isometry3::from_parts(
        Translation3::from(Vector3::new(0.0, 0.0, mount.height)),
        rotation,
    ))
}

/// The most layouts of the zone model (`zones.layouts`).
pub const MAX_LAYOUTS: u32 = 8;

/// How far the layouts' inner boundaries spread: layout k's are scaled by
/// 1 + LAYOUT_SPREAD · (frac(k · φ⁻¹) − ½), φ the golden ratio (an even spread for any count).
const LAYOUT_SPREAD: f64 = 0.15;

impl SegmenterConfig {
    /// The configuration of layout `k` (0 ≤ k < `zones.layouts`) of the zone model: layout
    /// 0 is this one; layout k is turned about the ground vertical by k / layouts of the
    /// narrowest sector, and its inner zone boundaries (all but the first and the last) are
    /// scaled by a factor in [0.925, 1.075) (`LAYOUT_SPREAD`), so that segment borders fall
    /// elsewhere in azimuth and in range. Each is a whole configuration of one layout
    /// (`layouts = 1`); the mount check runs on layout 0 only (`mount_check.mode = "off"`).
    pub fn layout(&self, k: u32) -> Result<Self, ConfigError> {
        let mut c = self.clone();
        c.zones.layouts = 1;
        if k == 0 {
            return Ok(c);
        }
        c.mount_check.mode = MountCheckMode::Off;
        let n = f64::from(self.zones.layouts.max(1));
        let narrowest = self.zones.sectors.iter().copied().max().unwrap_or(1).max(1);
        let turn = f64::from(k) / n * std::f64::consts::TAU / f64::from(narrowest);
        let m = &mut c.sensor.mount;
        match &mut m.matrix {
            // Rz(turn) after the mount: the same ground, turned about its vertical.
            Some(mat) => {
                let pose = pose_from_matrix(mat)
                    .map_err(|e| ConfigError::invalid("sensor.mount.matrix", &e.to_string()))?;
                let turned = UnitQuaternion::from_euler_angles(0.0, 0.0, turn) * pose;
                let h = turned.to_homogeneous();
                for (r, row) in mat.iter_mut().enumerate() {
                    for (col, v) in row.iter_mut().enumerate() {
                        *v = h[(r, col)];
                    }
                }
            }
            // Rz(yaw)·Ry(pitch)·Rx(roll): a turn about the ground vertical adds to the yaw.
            None => {
                let yaw = m.yaw + turn;
                m.yaw = if yaw > std::f64::consts::PI {
                    yaw - std::f64::consts::TAU
                } else {
                    yaw
                };
            }
        }
        let b = self.zones.resolved_boundaries()?;
        let scale = 1.0 + LAYOUT_SPREAD * ((f64::from(k) * 0.618_033_988_749_895).fract() - 0.5);
        let last = b.len().saturating_sub(1);
        let scaled: Vec<f64> = b
            .iter()
            .enumerate()
            .map(|(i, &v)| if i == 0 || i == last { v } else { v * scale })
            .collect();
        // A layout whose scaled boundaries would cross the fixed ones keeps them unscaled.
        if scaled.windows(2).all(|w| w[0] < w[1]) {
            c.zones.boundaries = Some(scaled);
        } else {
            c.zones.boundaries = Some(b);
        }
        Ok(c)
    }
}

/// The roll and pitch of a mount whose ground vertical, seen from the sensor, is the unit
/// vector `up` (any yaw): the inverse of [`mount_transform`]'s rotation
/// Rz(yaw)·Ry(pitch)·Rx(roll), which carries up = (−sin p, sin r cos p, cos r cos p) to z.
pub fn roll_pitch_of(up: &Vector3<f64>) -> (f64, f64) {
    (up.y.atan2(up.z), (-up.x).clamp(-1.0, 1.0).asin())
}

/// The ground vertical of a mount (ground-from-sensor pose), in the sensor frame.
pub fn vertical_in_sensor(mount: &Pose) -> Vector3<f64> {
    mount.rotation.inverse() * Vector3::z()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_layout_is_its_boundaries_in_use_rings_and_sectors() {
        let derived = ZoneConfig::default();
        // The same boundaries written out are the same layout.
        let written = ZoneConfig {
            boundaries: Some(derived.resolved_boundaries().unwrap()),
            ..derived.clone()
        };
        assert!(written.same_layout(&derived) && derived.same_layout(&written));
        let mut sectors = derived.sectors.clone();
        sectors[1] += 1;
        assert!(!derived.same_layout(&ZoneConfig {
            sectors,
            ..derived.clone()
        }));
        let mut b = derived.resolved_boundaries().unwrap();
        b[1] += 0.5;
        assert!(!derived.same_layout(&ZoneConfig {
            boundaries: Some(b),
            ..derived.clone()
        }));
    }

    /// Every layout lies on the same ground (same vertical and height), turned about it by
    /// less than one narrowest sector, with its inner boundaries moved by at most 7.5 %;
    /// the same for a mount given as a matrix.
    #[test]
    fn layouts_are_the_zone_model_turned_and_stretched_on_the_same_ground() {
        let mut cfg = SegmenterConfig::default();
        cfg.sensor.mount = MountConfig {
            height: 1.3,
            roll: 0.05,
            pitch: -0.12,
            yaw: 3.1,
            matrix: None,
        };
        cfg.zones.layouts = 4;
        let base = mount_transform(&cfg.sensor.mount).unwrap();
        let bounds = cfg.zones.resolved_boundaries().unwrap();
        let narrowest = std::f64::consts::TAU / 54.0;
        let as_matrix = {
            let mut c = cfg.clone();
            let h = base.to_homogeneous();
            c.sensor.mount = MountConfig {
                height: 0.0,
                roll: 0.0,
                pitch: 0.0,
                yaw: 0.0,
                matrix: Some(std::array::from_fn(|r| std::array::from_fn(|k| h[(r, k)]))),
            };
            c
        };
        for k in 0..4 {
            for c in [&cfg, &as_matrix] {
                let l = c.layout(k).unwrap();
                assert_eq!(l.zones.layouts, 1);
                l.validate().unwrap();
                let m = mount_transform(&l.sensor.mount).unwrap();
                let up = (vertical_in_sensor(&m) - vertical_in_sensor(&base)).norm();
                assert!(up < 1e-12, "layout {k}: the vertical moved by {up}");
                assert!((m.translation.z - 1.3).abs() < 1e-12);
                let turn = (m.rotation * base.rotation.inverse()).angle();
                let want = f64::from(k) / 4.0 * narrowest;
                assert!(
                    (turn - want).abs() < 1e-9,
                    "layout {k}: turned {turn}, not {want}"
                );
                let b = l.zones.resolved_boundaries().unwrap();
                assert_eq!((b[0], b[4]), (bounds[0], bounds[4]));
                for i in 1..4 {
                    let r = b[i] / bounds[i];
                    assert!(
                        (0.925..1.075).contains(&r),
                        "layout {k}, boundary {i}: ×{r}"
                    );
                    assert_eq!(r == 1.0, k == 0);
                }
                assert_eq!(
                    l.mount_check.mode == MountCheckMode::Off,
                    k > 0 || c.mount_check.mode == MountCheckMode::Off
                );
            }
        }
        for bad in [0, MAX_LAYOUTS + 1] {
            let mut c = cfg.clone();
            c.zones.layouts = bad;
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains("zones.layouts"), "{e}");
        }
        let mut c = cfg.clone();
        c.mount_check.mode = MountCheckMode::Correct;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("zones.layouts") && e.contains("correct"), "{e}");
    }

    #[test]
    fn roll_and_pitch_invert_the_mount_rotation() {
        let m = MountConfig {
            height: 1.0,
            roll: 0.1,
            pitch: -0.2,
            yaw: 0.7,
            matrix: None,
        };
        let (r, p) = roll_pitch_of(&vertical_in_sensor(&mount_transform(&m).unwrap()));
        assert!((r - 0.1).abs() < 1e-12 && (p + 0.2).abs() < 1e-12);
    }

    #[test]
    fn mount_lifts_points_by_the_sensor_height() {
        let m = MountConfig {
            height: 1.73,
            ..Default::default()
        };
        let t = mount_transform(&m).unwrap();
        let p = t * nalgebra::Point3::new(1.0, 2.0, -1.73);
        assert!((p.z).abs() < 1e-12 && (p.x - 1.0).abs() < 1e-12);
    }

    #[test]
    fn defaults_are_the_papers_values_and_valid() {
        let c = SegmenterConfig::default();
        c.validate().unwrap();
        assert_eq!(c.gmm.n_min, 20);
        assert_eq!(c.gmm.k_max, 8);
        assert_eq!(c.gmm.tau_n, 10);
        assert_eq!(c.ground.flatness.alpha, 40.0);
        assert_eq!(c.ground.flatness.beta, 0.06);
        assert_eq!(c.ground.outlier_threshold, 0.5);
        let b = c.zones.resolved_boundaries().unwrap();
        assert_eq!(b.len(), 5);
        assert!((b[1] - (7.0 * 2.7 + 80.0) / 8.0).abs() < 1e-12);
        assert!((b[3] - (2.7 + 80.0) / 2.0).abs() < 1e-12);
    }

    #[test]
    fn rejects_inconsistent_values_naming_the_field() {
        let mut c = SegmenterConfig::default();
        c.zones.max_range = 1.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("zones.max_range"), "{e}");

        let mut c = SegmenterConfig::default();
        c.history.frames = 17;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("history.frames")
        );

        let mut c = SegmenterConfig::default();
        c.gmm.covariance_regularization = 0.0;
        assert!(c.validate().is_err());

        for spread in [-0.1, f64::NAN, 6.0] {
            let mut c = SegmenterConfig::default();
            c.history.spread = spread;
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains("history.spread"), "{spread}: {e}");
        }

        let mut c = SegmenterConfig::default();
        c.zones.rings = vec![2, 4, 4];
        assert!(c.validate().is_err());

        // A continuity grid that would take gigabytes is refused, naming the fix; off, it
        // is not built and the cell does not matter.
        let mut c = SegmenterConfig::default();
        c.zones.max_range = 1000.0;
        c.continuity.cell = 0.05;
        c.continuity.reach = 0.1;
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("continuity.cell") && e.contains("raise cell"),
            "{e}"
        );
        c.continuity.enabled = false;
        c.validate().unwrap();
        // Reach: from one cell to eight.
        for (reach, ok) in [(0.5, false), (1.0, true), (8.0, true), (8.5, false)] {
            let mut c = SegmenterConfig::default();
            c.continuity.reach = reach;
            let r = c.validate();
            assert_eq!(r.is_ok(), ok, "{reach}: {r:?}");
            if let Err(e) = r {
                assert!(e.to_string().contains("continuity.reach"), "{e}");
            }
        }
        for (confident, ok) in [
            ([0.6, 0.75], true),
            ([0.75, 0.6], false),
            ([0.5, 1.5], false),
        ] {
            let mut c = SegmenterConfig::default();
            c.continuity.confident = confident;
            assert_eq!(c.validate().is_ok(), ok, "{confident:?}");
        }
        let mut c = SegmenterConfig::default();
        c.continuity.height_cutoff = c.continuity.height_tolerance;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("continuity.height_cutoff"), "{e}");
    }

    #[test]
    fn a_terrain_whose_bands_meet_or_that_would_take_gigabytes_is_refused() {
        let mut c = SegmenterConfig::default();
        c.terrain.tolerance = [0.05, 0.2];
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("terrain.tolerance / terrain.veto"), "{e}");
        let mut c = SegmenterConfig::default();
        c.terrain.sectors = 4096;
        c.terrain.cell = 0.1;
        c.zones.max_range = 200.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("terrain.sectors"), "{e}");
        let mut c = SegmenterConfig::default();
        c.terrain.grade = f64::NAN;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("terrain.grade")
        );
    }

    #[test]
    fn a_probability_map_that_could_move_a_decision_is_refused() {
        // Flat somewhere, not a number, or a single value: refused by name.
        for map in [
            vec![0.2, 0.5, 0.5],
            vec![0.0, f32::NAN],
            vec![0.5],
            vec![0.5, 1.5],
        ] {
            let mut c = SegmenterConfig::default();
            c.probability.map = map.clone();
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains("probability.map"), "{map:?}: {e}");
        }
        let mut c = SegmenterConfig::default();
        c.probability.map = vec![0.1, 0.3, 0.9];
        c.validate().unwrap();
        // The threshold moves with the map: 0.5 is the middle knot, 0.75 halfway up to 1.
        assert!((c.decision_threshold() - 0.3).abs() < 1e-6);
        c.ground.ground_threshold = 0.75;
        assert!((c.decision_threshold() - 0.6).abs() < 1e-6);
    }

    #[test]
    fn values_that_parse_but_mean_nothing_are_refused_by_name() {
        type Edit = fn(&mut SegmenterConfig);
        let cases: [(&str, Edit); 11] = [
            ("ground.flatness.beta", |c| c.ground.flatness.beta = 0.0),
            ("gmm.covariance_regularization", |c| {
                c.gmm.covariance_regularization = 1e300
            }),
            ("sensor.mount.height", |c| c.sensor.mount.height = 1e30),
            ("height_filter.min_ground_likelihood", |c| {
                c.height_filter.min_ground_likelihood = f64::NAN
            }),
            ("gmm.max_iterations", |c| {
                c.gmm.max_iterations = 4_000_000_000
            }),
            ("gmm.max_fit_points", |c| c.gmm.max_fit_points = 3),
            ("gmm.summary_cell[0]", |c| c.gmm.summary_cell = [5.0, 0.1]),
            ("ground.orientation.beta", |c| {
                c.ground.orientation.beta = 3.0
            }),
            ("ground.elevation.alpha", |c| {
                c.ground.elevation.alpha = -4.0
            }),
            ("history.max_time_gap", |c| c.history.max_time_gap = 1e9),
            ("sensor.ego_radius", |c| c.sensor.ego_radius = 1e6),
        ];
        for (field, edit) in cases {
            let mut c = SegmenterConfig::default();
            edit(&mut c);
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains(field) && e.contains("range"), "{field}: {e}");
        }
        // Degrees for radians: refused with the conversion.
        let mut c = SegmenterConfig::default();
        c.sensor.mount.pitch = -6.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("sensor.mount.pitch")
                && e.contains("radians")
                && e.contains("-0.1047")
                && e.contains("pitch_deg = -6"),
            "{e}"
        );
        // A yaw of π (a sensor facing backwards) is a mount, not a mistake.
        let mut c = SegmenterConfig::default();
        c.sensor.mount.yaw = std::f64::consts::PI;
        c.validate().unwrap();
        // A scaled matrix is not a mount.
        let mut c = SegmenterConfig::default();
        c.sensor.mount.matrix = Some([
            [2.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 1.7],
            [0.0, 0.0, 0.0, 1.0],
        ]);
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("rotation"), "{e}");
    }
}
