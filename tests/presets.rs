//! Every preset against every sensor's synthetic scans, each on a random mount that every
//! preset is told: the helpers of the preset tables (`cargo run --release -p
//! groundwork-benches --bin preset-tables`) and of the whole-calibration test.

#![allow(clippy::unwrap_used)] // measurement helpers: a preset that does not load is a bug

use groundwork_core::SegmenterConfig;
use groundwork_core::config::{MountConfig, SensorConfig};
use groundwork_io::{SENSOR_PRESETS, sensor_preset};
use groundwork_synth::Generator;

use crate::{Poses, synthetic_run};

/// Turns of the true mount (roll, pitch; degrees) that give the resolution of a comparison
/// with it: a preset's IoU on the same scans moves by that much with angles far finer than
/// any mount is known to.
pub const NUDGES: [(f64, f64); 4] = [(0.02, 0.0), (-0.02, 0.0), (0.0, 0.02), (0.0, -0.02)];

/// Pooled IoU of `cfg` over `g`'s frames (true poses) with the scans' own sensor section
/// `sensor` on the mount `truth` they were taken from.
pub fn iou_on_mount(
    g: &Generator,
    sensor: &SensorConfig,
    truth: &MountConfig,
    cfg: SegmenterConfig,
) -> f64 {
    let sensor = SensorConfig {
        mount: truth.clone(),
        ..sensor.clone()
    };
    synthetic_run(g, SegmenterConfig { sensor, ..cfg }, Poses::True).iou()
}

/// [`iou_on_mount`] of every preset, in the order of `SENSOR_PRESETS`.
pub fn preset_ious(g: &Generator, sensor: &SensorConfig, truth: &MountConfig) -> Vec<f64> {
    SENSOR_PRESETS
        .iter()
        .map(|(p, _)| iou_on_mount(g, sensor, truth, sensor_preset(p).unwrap()))
        .collect()
}

/// The index and mean of the one preset best over a scene's runs, from each preset's mean
/// (the first of equals).
pub fn best_scene_preset(means: &[f64]) -> (usize, f64) {
    means
        .iter()
        .enumerate()
        .fold((0, f64::MIN), |b, (i, &m)| if m > b.1 { (i, m) } else { b })
}

/// The best [`iou_on_mount`] of every preset.
pub fn best_preset_iou(g: &Generator, sensor: &SensorConfig, truth: &MountConfig) -> f64 {
    preset_ious(g, sensor, truth)
        .into_iter()
        .fold(f64::MIN, f64::max)
}

/// `own`'s zones as `calibrate` moves them for a sensor `height` above the ground that first
/// sees ground where `near` says (the preset's zones where nothing moves).
pub fn zones_moved(
    own: &SegmenterConfig,
    near: Option<&groundwork_calibrate::NearGround>,
    height: f64,
) -> groundwork_core::config::ZoneConfig {
    let cfg = groundwork_calibrate::NearEdgeConfig::default();
    let mount = Some((height, &own.sensor.mount));
    groundwork_calibrate::zones_for_mount(&own.zones, near, mount, own.sensor.ego_radius, &cfg)
        .zones
        .unwrap_or_else(|| own.zones.clone())
}

/// Where `g`'s scans first see ground on the mount `truth`, as `calibrate` finds it.
pub fn near_ground_on(
    g: &Generator,
    truth: &MountConfig,
    ego_radius: f64,
    cfg: &groundwork_calibrate::NearEdgeConfig,
) -> Option<groundwork_calibrate::NearGround> {
    let scans: Vec<Vec<[f32; 3]>> = (0..g.frames())
        .map(|i| g.scan(i).points.iter().map(|p| [p.x, p.y, p.z]).collect())
        .collect();
    let pose = groundwork_core::mount_transform(truth).unwrap();
    groundwork_calibrate::near_ground(&scans, &pose, ego_radius, cfg)
}

/// The random mount of the preset tables (`benches/src/bin/preset_tables.rs`) for sensor `si`'s scans, seed `seed`.
pub fn random_mount(si: usize, seed: u64, yaw: f64) -> MountConfig {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(1000 * si as u64 + seed);
    MountConfig {
        height: rng.random_range(0.5..2.5),
        roll: rng.random_range(-5f64..5.0).to_radians(),
        pitch: rng.random_range(-10f64..10.0).to_radians(),
        yaw,
        matrix: None,
    }
}
