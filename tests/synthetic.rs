//! Accuracy on synthetic sequences with exact labels (`groundwork-synth`): every sensor
//! preset on every scene, tilted and low mounts, no-return placeholders, and multi-frame
//! history through a tilted mount and turning poses.
//!
//! Generator and segmenter are deterministic, so each figure is a measurement (seed 1,
//! frames 0–3 unless said otherwise); thresholds sit 1.5 IoU points below it. The figures
//! are in docs/synthetic.md.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use groundwork_core::SegmenterConfig;
use groundwork_core::config::MountConfig;
use groundwork_core::{Point, Segmenter};
use groundwork_io::{SENSOR_PRESETS, sensor_preset};
use groundwork_synth::{Generator, SceneKind, SynthConfig};
use groundwork_tests::presets::{
    NUDGES, best_scene_preset, iou_on_mount, random_mount, zones_moved,
};
use groundwork_tests::{
    Poses, SyntheticRun, method_run, synthetic, synthetic_run, synthetic_seeded,
};

use SceneKind::{Hill, Offroad, Parking, Urban};

/// Pooled ground IoU (gmm protocol, default history, true poses) measured per preset and
/// scene (summary cells). The presets from `os0-64` on are synthetic-only (no labelled real
/// scans of those sensors were at hand), measured when they were added. Re-measured on
/// 2026-12-07 when the scenes' cars came to stand tilted on the ground under their wheels
/// (most entries within ±0.3; the car parks up to +4.0 for the Pandar64, −2.1 for the
/// Mid-360, whose cars' lower points it takes for ground) and terrain following held the
/// grade at the sensor's foot; the `livox` rows again when its preset came to follow the
/// terrain, raising only.
const MEASURED: &[(&str, SceneKind, f64)] = &[
    ("hdl64e", Urban, 99.02),
    ("hdl64e", Offroad, 96.49),
    ("hdl64e", Parking, 98.10),
    ("hdl64e", Hill, 98.03),
    ("hdl32e", Urban, 94.16),
    ("hdl32e", Offroad, 93.35),
    ("hdl32e", Parking, 93.31),
    ("hdl32e", Hill, 93.77),
    ("vlp16", Urban, 93.81),
    ("vlp16", Offroad, 94.54),
    ("vlp16", Parking, 95.37),
    ("vlp16", Hill, 96.73),
    ("vlp32c", Urban, 91.64),
    ("vlp32c", Offroad, 86.54),
    ("vlp32c", Parking, 84.62),
    ("vlp32c", Hill, 94.87),
    ("os1-64", Urban, 98.50),
    ("os1-64", Offroad, 95.59),
    ("os1-64", Parking, 97.81),
    ("os1-64", Hill, 98.09),
    ("os1-128", Urban, 99.07),
    ("os1-128", Offroad, 97.46),
    ("os1-128", Parking, 99.11),
    ("os1-128", Hill, 98.58),
    ("pandar64", Urban, 93.96),
    ("pandar64", Offroad, 89.48),
    ("pandar64", Parking, 92.01),
    ("pandar64", Hill, 95.43),
    ("livox", Urban, 98.06),
    ("livox", Offroad, 91.07),
    ("livox", Parking, 99.22),
    ("livox", Hill, 99.42),
    ("os0-64", Urban, 99.05),
    ("os0-64", Offroad, 99.17),
    ("os0-64", Parking, 98.57),
    ("os0-64", Hill, 99.09),
    ("os2-64", Urban, 91.22),
    ("os2-64", Offroad, 89.76),
    ("os2-64", Parking, 88.20),
    ("os2-64", Hill, 97.29),
    ("xt32", Urban, 93.24),
    ("xt32", Offroad, 92.31),
    ("xt32", Parking, 94.40),
    ("xt32", Hill, 96.98),
    ("qt128", Urban, 99.27),
    ("qt128", Offroad, 99.35),
    ("qt128", Parking, 99.28),
    ("qt128", Hill, 99.52),
    ("helios", Urban, 93.97),
    ("helios", Offroad, 90.29),
    ("helios", Parking, 90.91),
    ("helios", Hill, 96.46),
    ("mid360", Urban, 78.00),
    ("mid360", Offroad, 80.03),
    ("mid360", Parking, 73.68),
    ("mid360", Hill, 92.86),
    ("m1", Urban, 99.34),
    ("m1", Offroad, 91.23),
    ("m1", Parking, 97.47),
    ("m1", Hill, 99.46),
];

const MARGIN: f64 = 1.5;

#[test]
fn every_preset_segments_every_synthetic_scene() {
    // Every preset is in the table.
    for (name, _) in SENSOR_PRESETS {
        assert!(MEASURED.iter().any(|(n, ..)| n == name), "{name} untested");
    }
    let mut failures = Vec::new();
    for &(sensor, scene, measured) in MEASURED {
        let run = synthetic_run(
            &synthetic(sensor, scene, 4, None),
            sensor_preset(sensor).unwrap(),
            Poses::True,
        );
        let m = run.pooled.metrics();
        eprintln!(
            "{sensor:9} {:8} IoU {:6.2} (measured {measured:.2}) precision {:6.2} recall {:6.2}",
            scene.name(),
            m.iou_ground,
            m.precision,
            m.recall
        );
        if m.iou_ground < measured - MARGIN {
            failures.push(format!("{sensor} {}: {:.2}", scene.name(), m.iou_ground));
        }
    }
    assert!(failures.is_empty(), "below threshold: {failures:?}");
}

/// The terrain-following elevation reference (`ground.elevation_window`, the presets')
/// against the paper's segment-wide one (0) on slopes: the hill road (grades to 11 %,
/// crests and dips) and the rolling off-road terrain. Mean pooled IoU over HDL-64E,
/// VLP-32C and OS1-128, seeds 0–1, 4 frames. Measured (segment-wide → following):
/// hill 93.00 → 93.82, off-road 85.77 → 89.33.
#[test]
fn the_elevation_reference_follows_slopes() {
    for (scene, gain) in [(Hill, 0.4), (Offroad, 1.5)] {
        let (mut follows, mut wide) = (0.0, 0.0);
        for sensor in ["hdl64e", "vlp32c", "os1-128"] {
            for seed in 0..2 {
                let g = synthetic_seeded(sensor, scene, 4, None, seed);
                let cfg = sensor_preset(sensor).unwrap();
                let mut paper = cfg.clone();
                paper.ground.elevation_window = 0.0;
                follows += synthetic_run(&g, cfg, Poses::True).iou() / 6.0;
                wide += synthetic_run(&g, paper, Poses::True).iou() / 6.0;
            }
        }
        eprintln!(
            "{}: terrain-following {follows:.2}, segment-wide {wide:.2}",
            scene.name()
        );
        assert!(
            follows >= wide + gain,
            "{}: {follows:.2} against {wide:.2}",
            scene.name()
        );
    }
}

fn mount(height: f64, roll: f64, pitch: f64, yaw: f64) -> MountConfig {
    MountConfig {
        height,
        roll: roll.to_radians(),
        pitch: pitch.to_radians(),
        yaw: yaw.to_radians(),
        matrix: None,
    }
}

/// Mean pooled IoU over seeds 0–5 (4 frames each): one seed's layout moves the IoU of a
/// 4-frame run by several points, the mean by much less.
fn mean_iou(sensor: &str, scene: SceneKind, taken: &MountConfig, given: &MountConfig) -> f64 {
    let mut cfg = sensor_preset(sensor).unwrap();
    cfg.sensor.mount = given.clone();
    let sum: f64 = (0..6)
        .map(|seed| {
            let synth = SynthConfig::new(sensor, taken.clone(), scene, seed).unwrap();
            let g = Generator::new(synth, 4).unwrap();
            synthetic_run(&g, cfg.clone(), Poses::True).iou()
        })
        .sum();
    sum / 6.0
}

/// Measured: upright 92.41, tilted (roll 4°, pitch −5°) with its mount 94.03, without
/// 90.27.
#[test]
fn a_tilted_sensor_needs_only_its_mount_transform() {
    let upright = mount(1.73, 0.0, 0.0, 0.0);
    let tilted = mount(1.73, 4.0, -5.0, 0.0);
    let reference = mean_iou("hdl64e", Urban, &upright, &upright);
    let with = mean_iou("hdl64e", Urban, &tilted, &tilted);
    let without = mean_iou("hdl64e", Urban, &tilted, &upright);
    eprintln!("upright {reference:.2}, tilted with mount {with:.2}, without {without:.2}");
    assert!(
        with >= reference - 1.0,
        "{with:.2} vs upright {reference:.2}"
    );
    assert!(
        without <= with - 1.0,
        "without the mount {without:.2}, with {with:.2}"
    );
}

/// Measured (VLP-16 at 0.6 m, its preset otherwise; seed 1): urban 95.55, offroad 95.48,
/// parking 95.29.
#[test]
fn a_sensor_mounted_at_0_6_m() {
    let low = mount(0.6, 0.0, 0.0, 0.0);
    let mut cfg = sensor_preset("vlp16").unwrap();
    cfg.sensor.mount = low.clone();
    for (scene, measured) in [(Urban, 95.55), (Offroad, 95.48), (Parking, 95.29)] {
        let run = synthetic_run(
            &synthetic("vlp16", scene, 4, Some(low.clone())),
            cfg.clone(),
            Poses::True,
        );
        eprintln!("vlp16 at 0.6 m, {}: {:.2}", scene.name(), run.iou());
        assert!(
            run.iou() >= measured - MARGIN,
            "{}: {:.2}",
            scene.name(),
            run.iou()
        );
    }
}

#[test]
fn origin_placeholders_get_zero_and_do_not_disturb_the_fit() {
    let scan = synthetic("os1-64", Offroad, 1, None).scan(0);
    let is_placeholder = |p: &Point| p.x == 0.0 && p.y == 0.0 && p.z == 0.0;
    let placeholders = scan.points.iter().filter(|p| is_placeholder(p)).count();
    // Sky and dropouts: an organized OS1-64 image has thousands.
    assert!(placeholders > 1000, "{placeholders}");
    let cfg = sensor_preset("os1-64").unwrap();
    let mut with = vec![0.0; scan.points.len()];
    Segmenter::new(cfg.clone())
        .unwrap()
        .segment(&scan.points, None, &mut with)
        .unwrap();
    let real: Vec<Point> = scan
        .points
        .iter()
        .copied()
        .filter(|p| !is_placeholder(p))
        .collect();
    let mut without = vec![0.0; real.len()];
    Segmenter::new(cfg)
        .unwrap()
        .segment(&real, None, &mut without)
        .unwrap();
    let mut rest = without.iter();
    for (p, &prob) in scan.points.iter().zip(&with) {
        if is_placeholder(p) {
            assert_eq!(prob, 0.0);
        } else {
            // Bit for bit: the placeholders took no part in any fit.
            assert_eq!(prob.to_bits(), rest.next().unwrap().to_bits());
        }
    }
}

/// Measured on 12 frames of an Ouster on hills (sensor rolled 3°, pitched 4°, turned 30°
/// on its mount; the vehicle turns and pitches along the track), with the `os1-64` preset:
/// single frame 95.30, 3 frames with the true poses 95.79, with the poses run backwards
/// 94.92.
#[test]
fn history_maps_points_through_mount_and_turning_poses() {
    let m = mount(1.6, 3.0, 4.0, 30.0);
    let g = synthetic("os1-64", Offroad, 12, Some(m.clone()));
    let mut cfg = sensor_preset("os1-64").unwrap();
    cfg.sensor.mount = m;
    cfg.history.frames = 1;
    let single = synthetic_run(&g, cfg.clone(), Poses::True).iou();
    cfg.history.frames = 3;
    let multi = synthetic_run(&g, cfg.clone(), Poses::True);
    let wrong = synthetic_run(&g, cfg, Poses::Reversed).iou();
    eprintln!(
        "single {single:.2}, 3 frames {:.2}, wrong poses {wrong:.2}",
        multi.iou()
    );
    assert!(
        multi.iou() >= single + 0.4,
        "{:.2} vs single {single:.2}",
        multi.iou()
    );
    assert!(
        multi.iou() >= wrong + 0.5,
        "{:.2} vs wrong poses {wrong:.2}",
        multi.iou()
    );
}

/// The PseudoLabeler's defaults, unchanged, on sensors other than the HDL-64E: the tilted
/// (3° pitch) forward-facing Livox-like sensor in the street, an Ouster off-road, a VLP-16
/// in a car park (terraseg protocol, frames 0–3, seed 1). Measured mIoU (pseudolabeler /
/// ransac / gmm): livox urban 96.27 / 91.73 / 97.24; os1-64 offroad 73.52 / 48.96 / 78.62;
/// vlp16 parking 91.93 / 97.55 / 92.20 (a flat car park is RANSAC's best case). The gmm
/// figures, for comparison only, are `groundwork synth --frames 4 --seed 1` then `groundwork
/// eval --protocol terraseg` with an earlier set of presets (default history). Thresholds are
/// 1.5 below; where the ground is not a plane the PseudoLabeler must beat RANSAC.
#[test]
fn the_pseudolabeler_defaults_serve_other_sensors() {
    use groundwork_eval::Protocol;
    use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, Ransac};
    for (sensor, scene, min, beats_ransac) in [
        ("livox", Urban, 94.7, true),
        ("os1-64", Offroad, 72.0, true),
        ("vlp16", Parking, 90.4, false),
    ] {
        let generator = synthetic(sensor, scene, 4, None);
        let cfg = sensor_preset(sensor).unwrap();
        let frame = GroundFrame::from_config(&cfg).unwrap();
        let mut pl = PseudoLabeler::new(Default::default(), frame).unwrap();
        let p = method_run(&generator, &mut pl, Poses::Without, Protocol::Terraseg);
        let mut r = Ransac::new(Default::default(), frame).unwrap();
        let rs = method_run(&generator, &mut r, Poses::Without, Protocol::Terraseg);
        let miou = |r: &SyntheticRun| r.pooled.metrics().miou;
        let (p, rs) = (miou(&p), miou(&rs));
        eprintln!("{sensor} {scene:?}: pseudolabeler {p:.2} ransac {rs:.2}");
        assert!(p >= min, "{sensor} {scene:?}: mIoU {p:.2} < {min}");
        if beats_ransac {
            assert!(p > rs, "{sensor} {scene:?}: {p:.2} vs RANSAC {rs:.2}");
        }
    }
}

/// A Livox-like sensor's missing returns arrive as points at (0, 0, 0), and the `livox`
/// preset has no ego radius to hold them out: the PseudoLabeler must leave them out all the
/// same, or it fits its map to a stack of points at the sensor's height and calls them
/// ground, and the map rises around them (docs/offline-labels.md, "Placeholders at the
/// origin"). A car-park sequence from a mount 1.37 m up, pitched 5.3° down (about 14,000
/// placeholders in a scan of 24,000), labelled on the true mount: ground IoU (gmm protocol,
/// frames 0–3) measured 89.92 with the placeholders left out, 77.02 when they were fitted.
#[test]
fn the_pseudolabeler_leaves_out_placeholders_at_the_origin() {
    use groundwork_eval::Protocol;
    use groundwork_pseudolabel::{GroundFrame, PseudoLabeler};
    let mount = MountConfig {
        height: 1.373,
        roll: 0.034684,
        pitch: -0.092171,
        yaw: 0.0,
        matrix: None,
    };
    let generator = synthetic_seeded("livox", Parking, 4, Some(mount.clone()), 2);
    let scan = generator.scan(0);
    let placeholders = scan
        .points
        .iter()
        .filter(|p| [p.x, p.y, p.z] == [0.0; 3])
        .count();
    assert!(placeholders > 10_000, "{placeholders}");
    let mut cfg = sensor_preset("livox").unwrap();
    cfg.sensor.mount = mount;
    let frame = GroundFrame::from_config(&cfg).unwrap();
    let mut pl = PseudoLabeler::new(Default::default(), frame).unwrap();
    let run = method_run(&generator, &mut pl, Poses::Without, Protocol::Gmm);
    let iou = run.pooled.metrics().iou_ground;
    eprintln!("{placeholders} placeholders in scan 0; ground IoU {iou:.2}");
    assert!(iou >= 84.0, "ground IoU {iou:.2}");
    // No placeholder is called ground.
    for (k, p) in run.probabilities.iter().enumerate() {
        let scan = generator.scan(k);
        for (q, &prob) in scan.points.iter().zip(p) {
            if [q.x, q.y, q.z] == [0.0; 3] {
                assert_eq!(prob, 0.0);
            }
        }
    }
}

/// The PseudoLabeler's schedule for hills (docs/offline-labels.md, "Hills"): a plateau of
/// 30 iterations at 0.3 % instead of 10 at 1 % before the rate drops. Measured (terraseg
/// mIoU, frames 0–1, default / hills): hdl64e hill seed 0 25.54 / 86.31, os1-64 hill seed
/// 0 27.15 / 66.38 (the default stops while the map is still climbing the hill), os1-64
/// car park seed 0 97.38 / 97.35 (flat ground: the same). Thresholds 1.5 below. (With the
/// scenes' cars upright, sunk into the uphill road: 25.58 / 75.31 and 27.12 / 73.79; where
/// the map stops on a hill moves with what stands on the road.)
#[test]
fn the_pseudolabeler_hill_schedule_follows_hills() {
    use groundwork_eval::Protocol;
    use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, PseudoLabelerConfig};
    let hills = PseudoLabelerConfig {
        plateau_patience: 30,
        plateau_min_improvement: 0.003,
        ..Default::default()
    };
    for (sensor, scene, seed, min, gain) in [
        ("hdl64e", Hill, 0, 84.8, 30.0),
        ("os1-64", Hill, 0, 64.8, 30.0),
        ("os1-64", Parking, 0, 95.8, -0.5),
    ] {
        let generator = synthetic_seeded(sensor, scene, 2, None, seed);
        let frame = GroundFrame::from_config(&sensor_preset(sensor).unwrap()).unwrap();
        let miou = |cfg: PseudoLabelerConfig| {
            let mut pl = PseudoLabeler::new(cfg, frame).unwrap();
            method_run(&generator, &mut pl, Poses::Without, Protocol::Terraseg)
                .pooled
                .metrics()
                .miou
        };
        let (default, hill) = (miou(Default::default()), miou(hills.clone()));
        eprintln!("{sensor} {scene:?} seed {seed}: default {default:.2}, hill schedule {hill:.2}");
        assert!(hill >= min, "{sensor} {scene:?}: {hill:.2} < {min}");
        assert!(
            hill - default >= gain,
            "{sensor} {scene:?}: {hill:.2} against the default's {default:.2}"
        );
    }
}

/// Seeds 0–5 of every preset and scene (4 frames, true poses): one seed moves a 4-frame
/// figure by points, so a change of the method is judged on these means (the table in
/// docs/synthetic.md). About 3 minutes in release:
/// `cargo test --release -p groundwork-tests --test synthetic -- --ignored --nocapture`.
#[test]
#[ignore = "slow: the mean over six seeds of every preset and scene, for docs/synthetic.md"]
fn mean_iou_over_seeds_of_every_preset_and_scene() {
    let mut failures = Vec::new();
    for &(sensor, scene, _) in MEASURED {
        let ious: Vec<f64> = (0..6)
            .map(|seed| {
                let run = synthetic_run(
                    &groundwork_tests::synthetic_seeded(sensor, scene, 4, None, seed),
                    sensor_preset(sensor).unwrap(),
                    Poses::True,
                );
                run.iou()
            })
            .collect();
        let mean = ious.iter().sum::<f64>() / ious.len() as f64;
        let floor = MEAN_OVER_SEEDS
            .iter()
            .find(|(n, s, _)| *n == sensor && *s == scene)
            .map(|t| t.2);
        eprintln!(
            "MEAN {sensor:9} {:8} {mean:6.2}  seeds {:?}",
            scene.name(),
            ious.iter()
                .map(|v| (v * 100.0).round() / 100.0)
                .collect::<Vec<_>>()
        );
        if let Some(f) = floor {
            // A change of the method may cost at most 0.3 on any of these means.
            if mean < f - 0.3 {
                failures.push(format!(
                    "{sensor} {}: {mean:.2} < {f:.2} − 0.3",
                    scene.name()
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

/// Mean IoU over seeds 0–5 of each preset and scene, the floor a change of the method may
/// lower by at most 0.3 (how each preset's entries moved as its zones were tuned:
/// docs/sensors.md and docs/synthetic.md).
const MEAN_OVER_SEEDS: &[(&str, SceneKind, f64)] = &[
    ("hdl64e", Urban, 97.75),
    ("hdl64e", Offroad, 96.48),
    ("hdl64e", Parking, 98.48),
    ("hdl64e", Hill, 98.36),
    ("hdl32e", Urban, 93.00),
    ("hdl32e", Offroad, 92.09),
    ("hdl32e", Parking, 92.61),
    ("hdl32e", Hill, 93.55),
    ("vlp16", Urban, 93.49),
    ("vlp16", Offroad, 94.11),
    ("vlp16", Parking, 94.20),
    ("vlp16", Hill, 96.26),
    ("vlp32c", Urban, 89.56),
    ("vlp32c", Offroad, 86.15),
    ("vlp32c", Parking, 84.19),
    ("vlp32c", Hill, 93.23),
    ("os1-64", Urban, 96.74),
    ("os1-64", Offroad, 95.63),
    ("os1-64", Parking, 98.00),
    ("os1-64", Hill, 97.91),
    ("os1-128", Urban, 97.08),
    ("os1-128", Offroad, 97.73),
    ("os1-128", Parking, 99.23),
    ("os1-128", Hill, 99.02),
    ("pandar64", Urban, 93.18),
    ("pandar64", Offroad, 90.47),
    ("pandar64", Parking, 89.88),
    ("pandar64", Hill, 96.61),
    ("livox", Urban, 98.82),
    ("livox", Offroad, 91.87),
    ("livox", Parking, 99.20),
    ("livox", Hill, 98.95),
];

/// The whole of `groundwork calibrate` with its defaults on the scans and mounts of
/// the preset tables (`preset-tables`), 24 consecutive scans each: the mount found from the scans
/// alone, the zones moved for it, the parameters fitted to the PseudoLabeler's labels of the
/// scans, then single-frame pooled IoU on the same scans against every preset told the true
/// mount, per run and per scene (the one preset best over the scene's three runs), beside
/// the sensor's own preset and the comparison's resolution: how far that preset's scene mean
/// moves when the true mount is turned by 0.02° ([`NUDGES`]). `SENSORS` (comma-separated)
/// picks the scans' sensors; VLP-16, OS1-64 and Livox by default, the three of issue 42's
/// acceptance. `FRAMES` scores with that many frames of history (`preset`: the preset's
/// own), single frame by default; `FIT=mount` leaves the parameters out (`--keep-params`).
/// Each fit's held-out agreement and the mount alone's IoU are printed. About 14 minutes
/// (half that with `FIT=mount`):
/// `cargo test -p groundwork-tests --test synthetic -- --ignored whole_calibration
/// --nocapture` (docs/dev/calibration-notes.md, "The whole command per scene").
#[test]
#[ignore = "slow: calibrate and every preset on 24 scans of every scene, for docs/dev/calibration-notes.md"]
fn whole_calibration_per_scene_against_every_preset() {
    use groundwork_calibrate::{
        MountSearchConfig, NearEdgeConfig, combine_near_ground, estimate_mount, view_near_ground,
    };
    let names: Vec<&str> = SENSOR_PRESETS.iter().map(|(n, _)| *n).collect();
    let sensors = std::env::var("SENSORS").unwrap_or_else(|_| "vlp16,os1-64,livox".into());
    let near_cfg = NearEdgeConfig::default();
    let frames: Option<u32> = match std::env::var("FRAMES") {
        Ok(f) if f == "preset" => None,
        Ok(f) => Some(f.parse().expect("FRAMES: a number or `preset`")),
        Err(_) => Some(1),
    };
    let scoring = |mut cfg: SegmenterConfig| {
        if let Some(f) = frames {
            cfg.history.frames = f;
        }
        cfg
    };
    // `FIT=mount`: `calibrate --keep-params` (no fit to the PseudoLabeler's labels).
    let fit_params = !std::env::var("FIT").is_ok_and(|f| f == "mount");
    let (mut scenes, mut scene_wins, mut within, mut runs, mut run_wins) = (0, 0, 0, 0, 0);
    let mut far_behind = Vec::new();
    for sensor in sensors.split(',') {
        let si = names.iter().position(|n| *n == sensor).expect("a preset");
        let own = sensor_preset(sensor).unwrap();
        let ego = own.sensor.ego_radius;
        for scene in [Urban, Offroad, Parking] {
            let (mut presets, mut calibrated) = (vec![0.0; names.len()], 0.0);
            let mut nudged = [0.0; NUDGES.len()];
            for seed in 0..3u64 {
                let truth = random_mount(si, seed, own.sensor.mount.yaw);
                let g = synthetic_seeded(sensor, scene, 24, Some(truth.clone()), seed);
                let xyz: Vec<Vec<[f32; 3]>> = (0..g.frames())
                    .map(|i| g.scan(i).points.iter().map(|p| [p.x, p.y, p.z]).collect())
                    .collect();
                let prior = groundwork_core::mount_transform(&own.sensor.mount).unwrap();
                let (views, est) = estimate_mount(&xyz, &prior, &MountSearchConfig::default());
                let ious: Vec<f64> = SENSOR_PRESETS
                    .iter()
                    .map(|(p, _)| {
                        iou_on_mount(&g, &own.sensor, &truth, scoring(sensor_preset(p).unwrap()))
                    })
                    .collect();
                let best = ious.iter().copied().fold(f64::MIN, f64::max);
                // The comparison's resolution: the sensor's own preset told the true mount
                // turned by 0.02° in roll or pitch, either way.
                for (sum, nudge) in nudged.iter_mut().zip(NUDGES) {
                    let m = MountConfig {
                        roll: truth.roll + nudge.0.to_radians(),
                        pitch: truth.pitch + nudge.1.to_radians(),
                        ..truth.clone()
                    };
                    *sum += iou_on_mount(&g, &own.sensor, &m, scoring(own.clone())) / 3.0;
                }
                for (sum, iou) in presets.iter_mut().zip(&ious) {
                    *sum += iou / 3.0;
                }
                let mut found = String::from("refused");
                let iou = match est {
                    Ok(est) => {
                        let near = combine_near_ground(
                            xyz.iter()
                                .zip(&views)
                                .filter_map(|(p, v)| {
                                    view_near_ground(p, v.as_ref().ok()?, ego, &near_cfg)
                                })
                                .collect(),
                        );
                        let mount = est.mount();
                        found = format!(
                            "found {:+.1} cm, roll {:+.2}°, pitch {:+.2}°",
                            100.0 * (mount.height - truth.height),
                            (mount.roll - truth.roll).to_degrees(),
                            (mount.pitch - truth.pitch).to_degrees()
                        );
                        let zones = zones_moved(&own, near.as_ref(), mount.height);
                        let moved = SegmenterConfig {
                            zones,
                            ..own.clone()
                        };
                        if fit_params {
                            let fitted = fitted_to_pseudolabels(&moved, &mount, &xyz);
                            let alone = iou_on_mount(&g, &own.sensor, &mount, scoring(moved));
                            found += &format!("; the mount alone {alone:.2}");
                            iou_on_mount(&g, &own.sensor, &mount, scoring(fitted))
                        } else {
                            iou_on_mount(&g, &own.sensor, &mount, scoring(moved))
                        }
                    }
                    // A refusal leaves the user with the preset on its own mount.
                    Err(_) => {
                        iou_on_mount(&g, &own.sensor, &own.sensor.mount, scoring(own.clone()))
                    }
                };
                eprintln!(
                    "{sensor:9} {:8} seed {seed}: calibrated {iou:6.2}, own preset {:6.2}, best \
                     preset {best:6.2}; {found}",
                    scene.name(),
                    ious[si]
                );
                calibrated += iou / 3.0;
                runs += 1;
                run_wins += usize::from(iou >= best);
            }
            let (bi, best) = best_scene_preset(&presets);
            let resolution = nudged
                .iter()
                .map(|n| (n - presets[si]).abs())
                .fold(0.0, f64::max);
            eprintln!(
                "WHOLE {sensor} | {} | {calibrated:.2} (`{}` {best:.2}, {:+.2}) | own preset \
                 {:.2} | ±{resolution:.2}",
                scene.name(),
                names[bi],
                calibrated - best,
                presets[si]
            );
            scenes += 1;
            scene_wins += usize::from(calibrated >= best);
            within += usize::from(calibrated >= best - resolution);
            if calibrated < best - 0.25 {
                far_behind.push(format!("{sensor} {}", scene.name()));
            }
        }
    }
    eprintln!(
        "WHOLE {scene_wins} of {scenes} scenes ({within} within the resolution), {run_wins} of \
         {runs} runs at least the best preset"
    );
    // Measured with summary cells and the `os1-64` sectors re-tuned for them
    // (docs/dev/calibration-notes.md, "The whole command per scene"): 4 of 9 scenes at least the best
    // preset, 5 within the resolution; this guard fails on the VLP-16 car park (−0.69) and
    // the Livox street (−0.30), where another sensor's preset beats the sensor's own (the
    // calibrated figures are within 0.02 of the own preset's or above). With the `vlp16`
    // preset taking the `os1-64` parameters: 7 of 9, 8 within the resolution.
    // The goal is every scene; this guards what holds.
    assert!(
        far_behind.is_empty(),
        "more than 0.25 points behind: {far_behind:?}"
    );
}

/// `calibrate`'s parameter fit after the mount: `scans` pseudo-labelled on the mount found,
/// the parameters of `cfg` fitted to the labels (the defaults of the command).
fn fitted_to_pseudolabels(
    cfg: &SegmenterConfig,
    mount: &MountConfig,
    scans: &[Vec<[f32; 3]>],
) -> SegmenterConfig {
    use groundwork_calibrate::{ParamSearchConfig, fit_to_pseudo_labels};
    let mut cfg = cfg.clone();
    cfg.sensor.mount = mount.clone();
    let labeler = Default::default();
    let fit =
        fit_to_pseudo_labels(&cfg, &labeler, scans, &ParamSearchConfig::default(), |_| {}).unwrap();
    eprintln!(
        "  fit: held out {:.2} -> {:.2} (best round), {}",
        fit.held_out_before.iou(),
        fit.history
            .iter()
            .skip(1)
            .map(|r| r.held_out_iou)
            .fold(fit.held_out_before.iou(), f64::max),
        if fit.too_few_trusted_points {
            format!(
                "kept the preset: too few trusted points ({:.0} a scan)",
                fit.trusted_points_per_scan
            )
        } else if fit.kept_preset {
            "kept the preset".to_owned()
        } else {
            fit.changed
                .iter()
                .map(|c| format!("{} {} → {}", c.name, c.old, c.new))
                .collect::<Vec<_>>()
                .join(", ")
        }
    );
    fit.config
}
