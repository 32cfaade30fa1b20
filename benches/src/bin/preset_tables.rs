//! The preset tables of docs/sensors.md, docs/calibration.md and docs/algorithm.md: every
//! preset on every sensor's synthetic scans (the urban, off-road and car-park scenes, seeds
//! 0–2, each on a random mount every preset is told), and the zones as `groundwork
//! calibrate` moves them. A measurement that prints tables, not a test: the floors a change
//! must keep are in `tests/synthetic.rs`.
//!
//! `cargo run --release -p groundwork-benches --bin preset-tables -- across|near-edge|layouts`

#![allow(clippy::unwrap_used)] // a measurement: a preset that does not load is a bug

use clap::{Parser, ValueEnum};
use groundwork_core::SegmenterConfig;
use groundwork_io::{SENSOR_PRESETS, sensor_preset};
use groundwork_synth::SceneKind::{Offroad, Parking, Urban};
use groundwork_tests::presets::{
    best_preset_iou, best_scene_preset, iou_on_mount, near_ground_on, preset_ious, random_mount,
    zones_moved,
};
use groundwork_tests::synthetic_seeded;

/// Which table.
#[derive(Debug, Clone, Copy, ValueEnum)]
enum Table {
    /// Every preset's parameters on every sensor's scans (docs/sensors.md).
    Across,
    /// The near edge moved and the inner boundaries scaled, against every preset
    /// (docs/calibration.md).
    NearEdge,
    /// 1–4 layouts of the zone model against every preset (docs/algorithm.md).
    Layouts,
}

#[derive(Debug, Parser)]
#[command(about = "The preset tables: every preset on every sensor's synthetic scans")]
struct Args {
    /// The table to measure and print.
    table: Table,
}

fn main() {
    match Args::parse().table {
        Table::Across => presets_across_sensors(),
        Table::NearEdge => near_edge_against_every_preset(),
        Table::Layouts => layouts_against_every_preset(),
    }
}

/// Every preset's parameters on every sensor's synthetic scans: the urban, off-road and
/// car-park scenes, seeds 0–2, each on a mount drawn at random (height 0.5–2.5 m, roll ±5°,
/// pitch ±10°) that every preset is told, with the scans' own sensor section (ego radius,
/// most points). Prints the mean pooled IoU per scans × preset (docs/sensors.md). About 10 minutes
/// (`preset-tables across`).
fn presets_across_sensors() {
    let names: Vec<&str> = SENSOR_PRESETS.iter().map(|(n, _)| *n).collect();
    let mut table = Vec::new();
    for (si, &sensor) in names.iter().enumerate() {
        let mut sums = vec![0.0; names.len()];
        let mut runs = 0;
        for scene in [Urban, Offroad, Parking] {
            for seed in 0..3u64 {
                let own = sensor_preset(sensor).unwrap().sensor;
                let truth = random_mount(si, seed, own.mount.yaw);
                let g = synthetic_seeded(sensor, scene, 4, Some(truth.clone()), seed);
                let mut line = format!("{sensor:9} {:8} seed {seed}:", scene.name());
                for (sum, iou) in sums.iter_mut().zip(preset_ious(&g, &own, &truth)) {
                    *sum += iou;
                    line += &format!(" {iou:6.2}");
                }
                eprintln!("{line}");
                runs += 1;
            }
        }
        let means: Vec<f64> = sums.iter().map(|s| s / runs as f64).collect();
        table.push((sensor, means));
    }
    eprintln!("scans \\ preset | {}", names.join(" | "));
    for (sensor, means) in &table {
        let best = means.iter().cloned().fold(f64::MIN, f64::max);
        let cells: Vec<String> = means
            .iter()
            .map(|m| {
                if *m == best {
                    format!("**{m:.2}**")
                } else {
                    format!("{m:.2}")
                }
            })
            .collect();
        eprintln!("TABLE {sensor} | {}", cells.join(" | "));
    }
}

/// The zones as `groundwork calibrate` moves them (`groundwork_calibrate::zones`), on the
/// scans and mounts of [`presets_across_sensors`]: each sensor's preset told the true
/// mount, the same with the near edge found in the four scans, then with the inner
/// boundaries scaled by the true height over the preset's too, and the best of every preset
/// told the true mount (docs/calibration.md), per run and per scene: the zones moved against
/// the one preset with the best mean over the scene's three runs (`SCENE` lines). About 5
/// minutes (`preset-tables near-edge`).
fn near_edge_against_every_preset() {
    use groundwork_calibrate::{NearEdgeConfig, zones_for_mount};
    let names: Vec<&str> = SENSOR_PRESETS.iter().map(|(n, _)| *n).collect();
    let near_cfg = NearEdgeConfig::default();
    for (si, &sensor) in names.iter().enumerate() {
        let own = sensor_preset(sensor).unwrap();
        let (mut own_sum, mut near_sum, mut scaled_sum, mut best_sum) = (0.0, 0.0, 0.0, 0.0);
        let (mut near_wins, mut scaled_wins) = (0, 0);
        for scene in [Urban, Offroad, Parking] {
            let (mut scene_presets, mut scene_scaled) = (vec![0.0; names.len()], 0.0);
            for seed in 0..3u64 {
                let truth = random_mount(si, seed, own.sensor.mount.yaw);
                let g = synthetic_seeded(sensor, scene, 4, Some(truth.clone()), seed);
                let run = |cfg| iou_on_mount(&g, &own.sensor, &truth, cfg);
                let presets = preset_ious(&g, &own.sensor, &truth);
                for (sum, iou) in scene_presets.iter_mut().zip(&presets) {
                    *sum += iou / 3.0;
                }
                let best = presets.iter().copied().fold(f64::MIN, f64::max);
                let ego = own.sensor.ego_radius;
                let ground = near_ground_on(&g, &truth, ego, &near_cfg);
                let fit = |height| {
                    zones_for_mount(&own.zones, ground.as_ref(), height, ego, &near_cfg).zones
                };
                let zones = fit(None);
                let scaled = fit(Some((truth.height, &own.sensor.mount)));
                let with = |z: &Option<groundwork_core::config::ZoneConfig>, plain: f64| match z {
                    Some(z) => run(SegmenterConfig {
                        zones: z.clone(),
                        ..own.clone()
                    }),
                    None => plain,
                };
                let plain = run(own.clone());
                let near = with(&zones, plain);
                let both = with(&scaled, plain);
                eprintln!(
                    "{sensor:9} {:8} seed {seed} h {:.2} pitch {:5.1}°: preset {plain:6.2}, \
                     near edge {near:6.2} (at {:?}), inner scaled {both:6.2}, best preset \
                     {best:6.2}",
                    scene.name(),
                    truth.height,
                    truth.pitch.to_degrees(),
                    zones.map(|z| z.min_range)
                );
                own_sum += plain;
                near_sum += near;
                scaled_sum += both;
                best_sum += best;
                near_wins += usize::from(near >= best);
                scaled_wins += usize::from(both >= best);
                scene_scaled += both / 3.0;
            }
            // The one preset best over the scene's three runs (not the best per run).
            let (best, best_mean) = best_scene_preset(&scene_presets);
            eprintln!(
                "SCENE {sensor} | {} | {:.2} | {scene_scaled:.2} | `{}` {best_mean:.2} | {:+.2}",
                scene.name(),
                scene_presets[si],
                names[best],
                scene_scaled - best_mean
            );
        }
        eprintln!(
            "NEAR {sensor} | {:.2} | {:.2} | {:.2} | {:.2} | {near_wins} of 9 | {scaled_wins} of 9",
            own_sum / 9.0,
            near_sum / 9.0,
            scaled_sum / 9.0,
            best_sum / 9.0
        );
    }
}

/// Layouts of the zone model (`zones.layouts`) on the scans and mounts of
/// [`presets_across_sensors`]: each sensor's preset with its zones moved for the true mount
/// as `groundwork calibrate` moves them, with 1, 2, 3 and 4 layouts, against the best of
/// every preset told the true mount (docs/algorithm.md, "Layouts"). About 8 minutes
/// (`preset-tables layouts`).
fn layouts_against_every_preset() {
    use groundwork_calibrate::NearEdgeConfig;
    let names: Vec<&str> = SENSOR_PRESETS.iter().map(|(n, _)| *n).collect();
    let near_cfg = NearEdgeConfig::default();
    let counts = [1u32, 2, 3, 4];
    let (mut sums, mut wins, mut runs) = ([0.0; 4], [0usize; 4], 0);
    for (si, &sensor) in names.iter().enumerate() {
        let own = sensor_preset(sensor).unwrap();
        for scene in [Urban, Offroad, Parking] {
            for seed in 0..3u64 {
                let truth = random_mount(si, seed, own.sensor.mount.yaw);
                let g = synthetic_seeded(sensor, scene, 4, Some(truth.clone()), seed);
                let best = best_preset_iou(&g, &own.sensor, &truth);
                let ego = own.sensor.ego_radius;
                let ground = near_ground_on(&g, &truth, ego, &near_cfg);
                let moved = zones_moved(&own, ground.as_ref(), truth.height);
                let mut line = format!("{sensor:9} {:8} seed {seed}:", scene.name());
                for (j, &n) in counts.iter().enumerate() {
                    let mut cfg = own.clone();
                    cfg.zones = moved.clone();
                    cfg.zones.layouts = n;
                    let iou = iou_on_mount(&g, &own.sensor, &truth, cfg);
                    sums[j] += iou;
                    wins[j] += usize::from(iou >= best);
                    line += &format!(" {n} layout(s) {iou:6.2}");
                }
                eprintln!("{line}, best preset {best:6.2}");
                runs += 1;
            }
        }
    }
    for (j, n) in counts.iter().enumerate() {
        eprintln!(
            "LAYOUTS {n}: mean {:.2}, {} of {runs} runs at least the best preset",
            sums[j] / f64::from(runs),
            wins[j]
        );
    }
}
