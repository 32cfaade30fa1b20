//! `groundwork synth`: a labeled synthetic sequence in the KITTI layout.

use std::path::Path;
use std::process::ExitCode;

use anyhow::{Context, Result};
use groundwork_io::load_config_over;
use tracing::info;

use crate::args::SynthArgs;
use crate::common::progress;

/// `groundwork synth`.
pub fn command(a: SynthArgs) -> Result<ExitCode> {
    synth(
        &a.sensor,
        a.config.as_deref(),
        &a.scene,
        a.frames,
        a.seed,
        &a.out,
    )?;
    Ok(ExitCode::SUCCESS)
}

/// Writes a synthetic sequence in the KITTI layout.
fn synth(
    sensor: &str,
    config: Option<&Path>,
    scene: &str,
    frames: usize,
    seed: u64,
    out: &Path,
) -> Result<()> {
    use groundwork_synth::{Generator, SceneKind, SynthConfig};
    let kind = SceneKind::from_name(scene).with_context(|| {
        let known: Vec<_> = SceneKind::ALL.iter().map(|k| k.name()).collect();
        format!("unknown scene {scene:?} (known: {})", known.join(", "))
    })?;
    let cfg = load_config_over(Some(sensor), config)?;
    let synth = SynthConfig::new(sensor, cfg.sensor.mount, kind, seed)?;
    let period_ns = (synth.pattern.period * 1e9).round() as u64;
    let generator = Generator::new(synth, frames)?;
    let (velodyne, labels) = (out.join("velodyne"), out.join("labels"));
    for dir in [&velodyne, &labels] {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    info!(sensor, scene, frames, seed, out = %out.display(), "generating a synthetic sequence");
    let pb = progress(frames, "synth");
    let mut poses = Vec::with_capacity(frames);
    let mut points = 0;
    for i in 0..frames {
        let scan = generator.scan(i);
        let stem = format!("{i:06}");
        groundwork_io::write_kitti_bin(&velodyne.join(format!("{stem}.bin")), &scan.points)?;
        groundwork_io::write_labels(&labels.join(format!("{stem}.label")), &scan.labels)?;
        poses.push(scan.pose_matrix());
        points += scan.points.len();
        pb.inc(1);
    }
    pb.finish_and_clear();
    groundwork_io::write_poses(&out.join("poses.txt"), &poses)?;
    // The poses are the LiDAR's own: Tr is the identity.
    let identity = std::array::from_fn(|r| std::array::from_fn(|c| f64::from(u8::from(r == c))));
    groundwork_io::write_calib_tr(&out.join("calib.txt"), &identity)?;
    // Scan times from 0 at the pattern's rate, as KITTI's times.txt.
    let times: Vec<u64> = (0..frames as u64).map(|i| i * period_ns).collect();
    groundwork_io::write_times(&out.join("times.txt"), &times)?;
    info!(frames, points, "synthetic sequence written");
    Ok(())
}
