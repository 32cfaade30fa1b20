//! Helpers shared by the end-to-end tests: where the vendored data lives.

use std::path::PathBuf;

pub mod presets;

use groundwork_core::config::MountConfig;
use groundwork_core::{GroundMethod, Segmenter, SegmenterConfig, pose_from_matrix};
use groundwork_eval::{Confusion, Protocol};
use groundwork_io::{LabelClass, LabelMap, sensor_preset};
pub use groundwork_synth::{Generator, SceneKind, SynthConfig};

/// The vendored SemanticKITTI sequence 00, frames 0–5 (labels for 0–2).
pub fn kitti_sequence() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/semantickitti-00")
}

/// The vendored real solid-state scans (no labels): tests/data/livox-g3reg/README.md.
pub fn livox_scans() -> Vec<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/livox-g3reg");
    ["source.pcd", "target.pcd"]
        .iter()
        .map(|f| dir.join(f))
        .collect()
}

/// The HDL-64E preset.
pub fn hdl64e_preset() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config/sensors/hdl64e.toml")
}

/// A synthetic sequence segmented in memory, scored like `groundwork eval` (gmm protocol).
#[derive(Debug)]
pub struct SyntheticRun {
    /// Counts over all frames.
    pub pooled: Confusion,
    /// Counts per frame.
    pub frames: Vec<Confusion>,
    /// Probabilities per frame.
    pub probabilities: Vec<Vec<f32>>,
}

impl SyntheticRun {
    /// Pooled ground IoU, percent.
    pub fn iou(&self) -> f64 {
        self.pooled.metrics().iou_ground
    }
}

/// Which poses a synthetic run gives the segmenter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Poses {
    /// None: single-frame segmentation of every scan.
    Without,
    /// The frames' true sensor poses.
    True,
    /// Frame i gets the pose of frame n − 1 − i: a history that runs backwards (wrong).
    Reversed,
}

/// A synthetic sequence: `frames` frames of `scene` seen by `sensor`'s pattern on `mount`
/// (the preset's if `None`), seed 1.
pub fn synthetic(
    sensor: &str,
    scene: SceneKind,
    frames: usize,
    mount: Option<MountConfig>,
) -> Generator {
    synthetic_seeded(sensor, scene, frames, mount, 1)
}

/// [`synthetic`] with the generator's seed.
pub fn synthetic_seeded(
    sensor: &str,
    scene: SceneKind,
    frames: usize,
    mount: Option<MountConfig>,
    seed: u64,
) -> Generator {
    let preset = sensor_preset(sensor).expect("preset");
    let mount = mount.unwrap_or(preset.sensor.mount);
    let synth = SynthConfig::new(sensor, mount, scene, seed).expect("pattern");
    Generator::new(synth, frames).expect("generator")
}

/// Segments every frame of `generator` in order with `cfg`, given `poses`.
pub fn synthetic_run(generator: &Generator, cfg: SegmenterConfig, poses: Poses) -> SyntheticRun {
    let mut seg = Segmenter::new(cfg).expect("config");
    method_run(generator, &mut seg, poses, Protocol::Gmm)
}

/// Segments every frame of `generator` in order with any method, scored in `protocol`.
pub fn method_run(
    generator: &Generator,
    seg: &mut dyn GroundMethod,
    poses: Poses,
    protocol: Protocol,
) -> SyntheticRun {
    let map = LabelMap::semantickitti();
    let thr = seg.threshold();
    let mut run = SyntheticRun {
        pooled: Confusion::default(),
        frames: Vec::new(),
        probabilities: Vec::new(),
    };
    let n = generator.frames();
    for i in 0..n {
        let scan = generator.scan(i);
        let pose = match poses {
            Poses::Without => None,
            Poses::True => Some(scan.pose_matrix()),
            Poses::Reversed => Some(generator.scan_pose_matrix(n - 1 - i)),
        }
        .map(|m| pose_from_matrix(&m).expect("rigid pose"));
        let mut probs = vec![0.0; scan.points.len()];
        seg.segment_scan(&scan.points, pose.as_ref(), &mut probs)
            .expect("segment");
        let classes: Vec<LabelClass> = scan
            .labels
            .iter()
            .map(|l| map.class((l & 0xffff) as u16))
            .collect();
        let c = Confusion::from_predictions(&probs, &classes, protocol, thr);
        run.pooled.merge(&c);
        run.frames.push(c);
        run.probabilities.push(probs);
    }
    run
}
