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
    let (poses_path, calib_path, times_path) = (
        out.join("poses.txt"),
        out.join("calib.txt"),
        out.join("times.txt"),
    );
    // Every file claimed before the first is written: none is the configuration read, and
    // a sequence written over an earlier one says so first.
    let mut outputs = groundwork_io::OutputFiles::new(
        &config
            .map(Path::to_path_buf)
            .into_iter()
            .collect::<Vec<_>>(),
    );
    let stems: Vec<String> = (0..frames).map(|i| format!("{i:06}")).collect();
    for stem in &stems {
        outputs.claim(&velodyne.join(format!("{stem}.bin")))?;
        outputs.claim(&labels.join(format!("{stem}.label")))?;
    }
    for p in [&poses_path, &calib_path, &times_path] {
        outputs.claim(p)?;
    }
    outputs.warn_replaced();
    info!(sensor, scene, frames, seed, out = %out.display(), "generating a synthetic sequence");
    let pb = progress(frames, "synth");
    let mut poses = Vec::with_capacity(frames);
    let mut points = 0;
    for (i, stem) in stems.iter().enumerate() {
        let scan = generator.scan(i);
        let bin = groundwork_io::kitti_bin_bytes(&scan.points);
        outputs.write(&velodyne.join(format!("{stem}.bin")), &bin)?;
        let label = groundwork_io::labels_bytes(&scan.labels);
        outputs.write(&labels.join(format!("{stem}.label")), &label)?;
        poses.push(scan.pose_matrix());
        points += scan.points.len();
        pb.inc(1);
    }
    pb.finish_and_clear();
    outputs.write(&poses_path, groundwork_io::poses_text(&poses).as_bytes())?;
    // The poses are the LiDAR's own: Tr is the identity.
    let identity = std::array::from_fn(|r| std::array::from_fn(|c| f64::from(u8::from(r == c))));
    outputs.write(
        &calib_path,
        groundwork_io::calib_tr_text(&identity).as_bytes(),
    )?;
    // Scan times from 0 at the pattern's rate, as KITTI's times.txt.
    let times: Vec<u64> = (0..frames as u64).map(|i| i * period_ns).collect();
    outputs.write(&times_path, groundwork_io::times_text(&times).as_bytes())?;
    info!(frames, points, "synthetic sequence written");
    Ok(())
}
