//! Shared bits of the benchmarks: the vendored data and the preset.

use std::path::PathBuf;

use groundwork_core::config::PastQuery;
use groundwork_core::model::FrameModel;
use groundwork_core::{Point, Pose, Segmenter, SegmenterConfig};
use nalgebra::{Translation3, Vector3};

/// The vendored SemanticKITTI sequence.
pub fn kitti_sequence() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/semantickitti-00")
}

/// The HDL-64E preset.
pub fn preset() -> anyhow::Result<SegmenterConfig> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config/sensors/hdl64e.toml");
    Ok(groundwork_io::load_config(&p)?)
}

/// KITTI frame `n` (0..=5) of the vendored sequence.
pub fn kitti_frame(n: usize) -> anyhow::Result<Vec<Point>> {
    let p = kitti_sequence().join(format!("velodyne/{n:06}.bin"));
    Ok(groundwork_io::read_scan(&p, 1_000_000)?.points)
}

/// KITTI frame 5 fitted once, and a segmenter whose history holds `frames − 1` past frames
/// behind it: the six vendored scans, then copies of them placed 0.8 m apart behind the
/// vehicle (KITTI's speed at 10 Hz), each segmented with its pose so that the history
/// stores them as the service would. Query it with [`Segmenter::query_model_posed`], which
/// leaves the history alone: every query sees the same realistic spread of past poses.
#[derive(Debug)]
pub struct Frame5WithHistory {
    pub segmenter: Segmenter,
    pub model: FrameModel,
    pub points: Vec<Point>,
    pub pose: Pose,
}

impl Frame5WithHistory {
    pub fn new(frames: u32, query: PastQuery) -> anyhow::Result<Self> {
        let seq = kitti_sequence();
        let cam = groundwork_io::read_poses(&seq.join("poses.txt"))?;
        let tr = groundwork_io::read_calib_tr(&seq.join("calib.txt"))?;
        let poses = groundwork_io::lidar_poses(&cam, &tr);
        let scans = (0..6)
            .map(kitti_frame)
            .collect::<anyhow::Result<Vec<_>>>()?;
        let pose = poses[5];
        let mut cfg = preset()?;
        cfg.history.frames = frames;
        cfg.history.query = query;
        let mut segmenter = Segmenter::new(cfg)?;
        // Oldest first: frame k steps behind the query pose.
        for k in (1..frames as usize).rev() {
            let back = Translation3::from(pose.rotation * Vector3::new(-0.8 * k as f64, 0.0, 0.0));
            let pts = &scans[(6 - (k % 6)) % 6];
            let mut out = vec![0.0; pts.len()];
            segmenter.segment(pts, Some(&(back * pose)), &mut out)?;
        }
        let points = scans[5].clone();
        let model = segmenter.fit(&points)?;
        Ok(Self {
            segmenter,
            model,
            points,
            pose,
        })
    }

    /// One query of frame 5 against its model and the history; returns the frames queried.
    pub fn query(&mut self, out: &mut [f32]) -> anyhow::Result<usize> {
        Ok(self
            .segmenter
            .query_model_posed(&self.model, &self.points, &self.pose, out)?)
    }
}
