//! `groundwork calibrate`'s mount on scans whose mount is known only to the test: synthetic
//! sequences of three sensor families on random mounts, and the bundled KITTI frames turned
//! into a tilted mount. Figures in docs/calibration.md.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use groundwork_calibrate::{MountEstimate, MountSearchConfig, estimate_mount};
use groundwork_core::config::MountConfig;
use groundwork_core::config::vertical_in_sensor;
use groundwork_core::mount_transform;
use groundwork_core::{Point, Segmenter};
use groundwork_eval::{Confusion, Protocol};
use groundwork_io::sensor_preset;
use groundwork_io::{LabelMap, read_labels, read_scan};
use groundwork_tests::{SceneKind, synthetic_seeded};
use groundwork_tests::{kitti_sequence, livox_scans};
use nalgebra::Point3;
use rand::{Rng, SeedableRng};

/// The mount calibrated from `scans` (sensor frame) with `prior` as the prior.
fn calibrate(
    scans: &[Vec<[f32; 3]>],
    prior: &MountConfig,
    cfg: &MountSearchConfig,
) -> Result<MountEstimate, groundwork_calibrate::CalibrateError> {
    estimate_mount(scans, &mount_transform(prior).unwrap(), cfg).1
}

/// Angle between the two mounts' verticals (degrees) and their height difference (m).
fn mount_error(e: &MountConfig, truth: &MountConfig) -> (f64, f64) {
    let up = |m: &MountConfig| vertical_in_sensor(&mount_transform(m).unwrap());
    (
        up(e).angle(&up(truth)).to_degrees(),
        (e.height - truth.height).abs(),
    )
}

/// Mounts drawn at random (height 0.5–2.5 m, roll ±5°, pitch ±10°, two draws per sensor and
/// scene) are found within 1° and 10 cm from 16 scans spread over 80–130 m of driving,
/// starting from the sensor's preset. The one way out is a refusal with the reason, and only
/// a solid-state sensor pitched up may take it: it sees the ground 14 m ahead at the
/// nearest, and on rolling terrain the scans then disagree (measured: livox offroad at
/// −8.8° pitch, spread 2.7°). Only the solid-state sensor's mounts are flagged as seen
/// from ground on one side.
#[test]
fn synthetic_mounts_drawn_at_random_are_recovered() {
    let mut failures = Vec::new();
    let mut refused = 0;
    for seed in [42, 1] {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        for sensor in ["vlp16", "os1-64", "livox"] {
            let preset = sensor_preset(sensor).unwrap();
            for scene in [SceneKind::Urban, SceneKind::Offroad, SceneKind::Parking] {
                let truth = MountConfig {
                    height: rng.random_range(0.5..2.5),
                    roll: rng.random_range(-5f64..5.0).to_radians(),
                    pitch: rng.random_range(-10f64..10.0).to_radians(),
                    yaw: preset.sensor.mount.yaw,
                    matrix: None,
                };
                let g = synthetic_seeded(sensor, scene, 160, Some(truth.clone()), 3);
                let scans: Vec<Vec<[f32; 3]>> = (0..g.frames())
                    .step_by(10)
                    .map(|i| g.scan(i).points.iter().map(|p| [p.x, p.y, p.z]).collect())
                    .collect();
                let case = format!(
                    "{sensor:7} {:8} truth h {:.2} roll {:5.2}° pitch {:6.2}°",
                    scene.name(),
                    truth.height,
                    truth.roll.to_degrees(),
                    truth.pitch.to_degrees()
                );
                let cfg = MountSearchConfig::default();
                match calibrate(&scans, &preset.sensor.mount, &cfg) {
                    Ok(e) => {
                        let (angle, dh) = mount_error(&e.mount(), &truth);
                        eprintln!(
                            "{case} | found h {:.3} roll {:5.2}° pitch {:6.2}° ({}/{} scans, \
                             spread {:.2}° {:.2}° {:.3} m) | error {angle:.2}° {dh:.3} m",
                            e.height.value,
                            e.roll.value.to_degrees(),
                            e.pitch.value.to_degrees(),
                            e.frames_used,
                            e.frames,
                            e.roll.spread.to_degrees(),
                            e.pitch.spread.to_degrees(),
                            e.height.spread,
                        );
                        if angle > 1.0 || dh > 0.1 {
                            failures.push(format!("{case}: {angle:.2}° {dh:.3} m"));
                        }
                        // The spinning sensors see ground all around, the solid-state one
                        // ahead only, and its mount says so.
                        if e.one_sided.is_some() != (sensor == "livox") {
                            failures.push(format!("{case}: one-sided {:?}", e.one_sided));
                        }
                    }
                    Err(e) => {
                        eprintln!("{case} | {e}");
                        refused += 1;
                        if !(sensor == "livox" && truth.pitch < -3f64.to_radians()) {
                            failures.push(format!("{case}: {e}"));
                        }
                    }
                }
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
    assert!(refused <= 1, "{refused} refusals");
}

/// The bundled KITTI frames 0–5 as a sensor on `mount` would see them: KITTI's own mount is
/// taken to be the hdl64e preset's (1.73 m, level).
fn kitti_seen_from(mount: &MountConfig) -> Vec<Vec<Point>> {
    let kitti = mount_transform(&sensor_preset("hdl64e").unwrap().sensor.mount).unwrap();
    let to = mount_transform(mount).unwrap().inverse() * kitti;
    (0..6)
        .map(|i| {
            let path = kitti_sequence().join(format!("velodyne/{i:06}.bin"));
            read_scan(&path, usize::MAX)
                .unwrap()
                .points
                .iter()
                .map(|p| {
                    let q = to * Point3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                    Point::new(q.x as f32, q.y as f32, q.z as f32)
                })
                .collect()
        })
        .collect()
}

fn xyz(scans: &[Vec<Point>]) -> Vec<Vec<[f32; 3]>> {
    scans
        .iter()
        .map(|s| s.iter().map(|p| [p.x, p.y, p.z]).collect())
        .collect()
}

/// Single-frame pooled ground IoU and precision over the labeled frames 0–2, with the preset's
/// parameters on `mount`.
fn kitti_iou(scans: &[Vec<Point>], mount: &MountConfig) -> (f64, f64) {
    let mut cfg = sensor_preset("hdl64e").unwrap();
    cfg.history.frames = 1;
    cfg.sensor.mount = mount.clone();
    kitti_config_iou(scans, &cfg)
}

/// The same with the whole configuration given.
fn kitti_config_iou(scans: &[Vec<Point>], cfg: &groundwork_core::SegmenterConfig) -> (f64, f64) {
    let map = LabelMap::semantickitti();
    let mut pooled = Confusion::default();
    for (i, points) in scans.iter().enumerate().take(3) {
        let mut seg = Segmenter::new(cfg.clone()).unwrap();
        let mut probs = vec![0.0; points.len()];
        groundwork_core::GroundMethod::segment_scan(&mut seg, points, None, &mut probs).unwrap();
        let labels = read_labels(
            &kitti_sequence().join(format!("labels/{i:06}.label")),
            points.len(),
        )
        .unwrap();
        let classes: Vec<_> = labels.iter().map(|&l| map.class(l)).collect();
        pooled.merge(&Confusion::from_predictions(
            &probs,
            &classes,
            Protocol::Gmm,
            cfg.decision_threshold(),
        ));
    }
    let m = pooled.metrics();
    (m.iou_ground, m.precision)
}

/// The KITTI frames re-expressed in a tilted mount known only to this test (roll 6°,
/// pitch −4°, 1.9 m): calibrate finds the tilted mount as it finds KITTI's own, composed
/// with the tilt (within 0.5° and 5 cm), and segments as well as the true mount (within
/// 0.3 IoU). KITTI's own ground, as calibrate finds it, lies within 2.5° and 6 cm of the
/// preset's level 1.73 m (it is rolled about 2°: the labeled road alone gives 1.5–1.7°).
#[test]
fn kitti_in_a_tilted_mount_is_calibrated() {
    let hdl64e = sensor_preset("hdl64e").unwrap().sensor.mount;
    let cfg = MountSearchConfig::default();
    let level = kitti_seen_from(&hdl64e);
    let own = calibrate(&xyz(&level), &hdl64e, &cfg).unwrap();
    let (angle, dh) = mount_error(&own.mount(), &hdl64e);
    eprintln!("KITTI's own mount: {own:?} ({angle:.2}°, {dh:.3} m from the preset)");
    assert!(angle < 2.5 && dh < 0.06, "{own:?}");
    assert_eq!(own.frames_used, 6);

    let tilt = MountConfig {
        height: 1.9,
        roll: 6f64.to_radians(),
        pitch: -4f64.to_radians(),
        yaw: 0.0,
        matrix: None,
    };
    let tilted = kitti_seen_from(&tilt);
    let found = calibrate(&xyz(&tilted), &hdl64e, &cfg).unwrap();
    // What it should find: the tilt composed with the ground KITTI's frames show.
    let kitti = mount_transform(&hdl64e).unwrap();
    // Tilted sensor coordinates p' = T⁻¹·K·p, so ground-from-tilted-sensor = E·K⁻¹·T.
    let expected_pose =
        mount_transform(&own.mount()).unwrap() * kitti.inverse() * mount_transform(&tilt).unwrap();
    let angle = vertical_in_sensor(&mount_transform(&found.mount()).unwrap())
        .angle(&vertical_in_sensor(&expected_pose))
        .to_degrees();
    let (_, dh_true) = mount_error(&found.mount(), &tilt);
    let dh = (found.height.value - expected_pose.translation.z).abs();
    eprintln!(
        "tilted: found h {:.3} roll {:.2}° pitch {:.2}° | {angle:.2}° and {dh:.3} m from the \
         composition, {dh_true:.3} m from the tilt's height",
        found.height.value,
        found.roll.value.to_degrees(),
        found.pitch.value.to_degrees()
    );
    assert!(angle < 0.5 && dh < 0.05, "{found:?}");

    let (iou_true, _) = kitti_iou(&tilted, &tilt);
    let (iou_found, precision) = kitti_iou(&tilted, &found.mount());
    eprintln!(
        "single-frame IoU, frames 0–2: true mount {iou_true:.2}, calibrated {iou_found:.2} (precision {precision:.2})"
    );
    assert!(
        iou_found >= iou_true - 0.3,
        "{iou_found:.2} against {iou_true:.2}"
    );
    assert!(precision >= 99.3, "{precision:.2}");
}

/// Scans of two mounts in one calibration (KITTI's, and the same frames 0.6 m higher): a
/// few are outvoted and named by their place; a quarter or more is a refusal that says the
/// inputs are of more than one mount.
#[test]
fn scans_of_another_mount_are_named_or_refused() {
    let hdl64e = sensor_preset("hdl64e").unwrap().sensor.mount;
    let cfg = MountSearchConfig::default();
    let higher = MountConfig {
        height: hdl64e.height + 0.6,
        ..hdl64e.clone()
    };
    let (own, high) = (
        xyz(&kitti_seen_from(&hdl64e)),
        xyz(&kitti_seen_from(&higher)),
    );
    // Twelve scans of KITTI's mount, one of the higher one at place 5.
    let mut mixed: Vec<Vec<[f32; 3]>> = own.iter().chain(&own).cloned().collect();
    mixed.insert(5, high[0].clone());
    let found = calibrate(&mixed, &hdl64e, &cfg).unwrap();
    assert_eq!(found.disagreeing, [5], "{found:?}");
    assert!(
        (found.height.value - hdl64e.height).abs() < 0.06,
        "{found:?}"
    );
    // Twelve and four: refused, with the heights.
    mixed.extend(high[1..4].iter().cloned());
    let e = calibrate(&mixed, &hdl64e, &cfg).unwrap_err().to_string();
    assert!(
        e.contains("4 of 16 scans") && e.contains("more than one"),
        "{e}"
    );
    // One mount: nobody is named.
    assert!(
        calibrate(&own, &hdl64e, &cfg)
            .unwrap()
            .disagreeing
            .is_empty()
    );
}

/// Terrain is not the mount: on a synthetic OS1-64 drive over a hill (the road climbs, crests
/// and falls away) and off-road (rolling ground, ruts), told the true mount, the observed
/// mount stays well within the tolerances, so the check stays silent and `correct` has
/// nothing to chase. With the plane through every ground component within 20 m it saw the
/// sensor 1.82 m up on the hill and 2.02 m off-road, for a true 1.5 m.
#[test]
fn terrain_that_falls_away_is_not_taken_for_the_mount() {
    for (scene, seed) in [
        (SceneKind::Hill, 0),
        (SceneKind::Hill, 1),
        (SceneKind::Offroad, 0),
        (SceneKind::Offroad, 1),
    ] {
        let g = synthetic_seeded("os1-64", scene, 30, None, seed);
        let cfg = sensor_preset("os1-64").unwrap();
        let mut seg = Segmenter::new(cfg).unwrap();
        for i in 0..g.frames() {
            let s = g.scan(i).points;
            let mut p = vec![0.0; s.len()];
            seg.segment(&s, None, &mut p).unwrap();
        }
        let seen = seg.observed_mount().unwrap();
        eprintln!(
            "{scene:?} seed {seed}: observed h {:.3} roll {:.2}° pitch {:.2}° ({:.2}°, {:+.3} m \
             from the true mount)",
            seen.height,
            seen.roll.to_degrees(),
            seen.pitch.to_degrees(),
            seen.tilt_from_configured.to_degrees(),
            seen.height_from_configured,
        );
        // Half the tolerances (3°, 20 cm): silent with a margin.
        assert!(
            seen.tilt_from_configured.to_degrees() < 1.5 && seen.height_from_configured.abs() < 0.1,
            "{scene:?} seed {seed}: {seen:?}"
        );
    }
}

/// The segmenter observes the mount in the ground it fits: told a mount 4° off in pitch and
/// 20 cm off in height, it sees the true one (within 1° and 10 cm: it is a check, not a
/// calibration; in this urban scene the crown and the lawns tilt its plane by 0.8°; the
/// sidewalks lifted it by 6 cm until it leant to the lowest ground) and says how far the
/// configured one is beyond the tolerances (3°, 20 cm); told the true one, it stays within
/// them. With the check off it observes nothing.
#[test]
fn the_segmenter_observes_the_mount_it_was_not_told() {
    let truth = MountConfig {
        height: 1.6,
        roll: 2f64.to_radians(),
        pitch: -3f64.to_radians(),
        yaw: 0.0,
        matrix: None,
    };
    let g = synthetic_seeded("os1-64", SceneKind::Urban, 300, Some(truth.clone()), 5);
    let scans: Vec<Vec<Point>> = (0..g.frames())
        .step_by(12)
        .map(|i| g.scan(i).points)
        .collect();
    let wrong = MountConfig {
        height: 1.4,
        pitch: 1f64.to_radians(),
        ..truth.clone()
    };
    for (told, off) in [(&truth, false), (&wrong, true)] {
        let mut cfg = sensor_preset("os1-64").unwrap();
        cfg.sensor.mount = told.clone();
        let mut seg = Segmenter::new(cfg).unwrap();
        for s in &scans {
            let mut p = vec![0.0; s.len()];
            seg.segment(s, None, &mut p).unwrap();
        }
        let seen = seg.observed_mount().unwrap();
        let found = MountConfig {
            height: seen.height,
            roll: seen.roll,
            pitch: seen.pitch,
            yaw: 0.0,
            matrix: None,
        };
        let (angle, dh) = mount_error(&found, &truth);
        eprintln!(
            "told h {:.2} pitch {:.1}°: observed h {:.3} roll {:.2}° pitch {:.2}° over {} scans \
             ({angle:.2}°, {dh:.3} m from the truth; {:.2}°, {:.3} m from what it was told)",
            told.height,
            told.pitch.to_degrees(),
            seen.height,
            seen.roll.to_degrees(),
            seen.pitch.to_degrees(),
            seen.scans,
            seen.tilt_from_configured.to_degrees(),
            seen.height_from_configured,
        );
        assert!(angle < 1.0 && dh < 0.1, "{seen:?}");
        assert_eq!(seen.scans, scans.len() as u64);
        let tolerance = groundwork_core::config::MountCheckConfig::default();
        let disagrees = seen.tilt_from_configured.to_degrees() > tolerance.max_tilt_deg
            || seen.height_from_configured.abs() > tolerance.max_height;
        assert_eq!(disagrees, off, "{seen:?}");
    }
    let mut cfg = sensor_preset("os1-64").unwrap();
    cfg.mount_check.mode = groundwork_core::config::MountCheckMode::Off;
    let mut seg = Segmenter::new(cfg).unwrap();
    let mut p = vec![0.0; scans[0].len()];
    seg.segment(&scans[0], None, &mut p).unwrap();
    assert!(seg.observed_mount().is_none());
}

/// Eight scans of a synthetic VLP-16 street with their exact labels as the reference.
fn synthetic_street() -> (Vec<Vec<[f32; 3]>>, Vec<Vec<bool>>) {
    let g = groundwork_tests::synthetic("vlp16", SceneKind::Urban, 40, None);
    (0..g.frames())
        .step_by(5)
        .map(|i| {
            let scan = g.scan(i);
            let ground = (0..scan.points.len())
                .map(|k| groundwork_synth::classes::is_ground(scan.class(k)))
                .collect();
            (
                scan.points.iter().map(|p| [p.x, p.y, p.z]).collect(),
                ground,
            )
        })
        .unzip()
}

/// The VLP-16 preset spoiled where a new sensor's guesses go wrong: objects up to 3 m
/// tall pass the elevation test, and the decision threshold is high. (2 m would cost only
/// 1.6 points on the held-out scans.)
fn spoiled_vlp16_following_the_terrain() -> groundwork_core::SegmenterConfig {
    let mut cfg = sensor_preset("vlp16").unwrap();
    cfg.history.frames = 1;
    cfg.ground.elevation.beta = 3.0;
    cfg.ground.ground_threshold = 0.8;
    cfg
}

fn spoiled_vlp16() -> groundwork_core::SegmenterConfig {
    let mut cfg = spoiled_vlp16_following_the_terrain();
    // The search is under test, not terrain following, which makes up for much of the spoil
    // on its own (held-out 93.09 before any fit with it on).
    cfg.terrain.enabled = false;
    cfg
}

/// The search with the labels trusted everywhere: these tests give it exact labels (or labels
/// wrong on purpose on whole scans) to test the search itself.
///
/// The bar for keeping a fit is lowered to one point: it guards against fitting the
/// PseudoLabeler's own mistakes, which exact labels do not have.
fn exact_labels() -> groundwork_calibrate::ParamSearchConfig {
    groundwork_calibrate::ParamSearchConfig {
        trust_agreement: 0.0,
        min_held_out_gain: 1.0,
        ..Default::default()
    }
}

/// The scans `fit_parameters` holds out of the fit (one in `held_out_every`, the last of
/// each run).
fn held_out<'a>(
    sample: &[groundwork_calibrate::LabeledScan<'a>],
    search: &groundwork_calibrate::ParamSearchConfig,
) -> Vec<groundwork_calibrate::LabeledScan<'a>> {
    let every = search.held_out_every;
    sample
        .iter()
        .skip(every - 1)
        .step_by(every)
        .copied()
        .collect()
}

/// Pooled ground IoU (%) of `cfg`'s single-frame decisions against `ground`, every point.
fn iou_against(
    cfg: &groundwork_core::SegmenterConfig,
    scans: &[Vec<[f32; 3]>],
    ground: &[Vec<bool>],
) -> f64 {
    groundwork_calibrate::params::agreement(
        cfg,
        &groundwork_calibrate::LabeledScan::pair(scans, ground),
        f64::INFINITY,
    )
    .unwrap()
    .iou()
}

/// A labeler that loses the ground far from the sensor (here: exact within 20 m, nothing
/// called ground beyond, as the PseudoLabeler does on hills) is trusted only where the
/// preset agrees with it (within 20 m at most), and the fit does not follow its far
/// mistakes: against the exact labels, the fitted parameters lose no more than 0.3 points.
#[test]
fn labels_are_trusted_only_where_the_preset_agrees_with_them() {
    let (scans, truth) = synthetic_street();
    let near_only: Vec<Vec<bool>> = scans
        .iter()
        .zip(&truth)
        .map(|(s, t)| {
            s.iter()
                .zip(t)
                .map(|(p, &g)| g && f64::from(p[0]).hypot(f64::from(p[1])) < 20.0)
                .collect()
        })
        .collect();
    let sample = groundwork_calibrate::LabeledScan::pair(&scans, &near_only);
    let mut base = sensor_preset("vlp16").unwrap();
    base.history.frames = 1;
    let preset_iou = iou_against(&base, &scans, &truth);
    let search = groundwork_calibrate::ParamSearchConfig::default();
    let fit = groundwork_calibrate::fit_parameters(&base, &sample, &search, |_, _| {}).unwrap();
    let fitted_iou = iou_against(&fit.config, &scans, &truth);
    eprintln!(
        "trusted within {} m (rings {:?}): {preset_iou:.2} -> {fitted_iou:.2} against the \
         exact labels ({:?})",
        fit.trusted_range, fit.ring_agreement, fit.changed
    );
    assert!(fit.trusted_range <= 20.0, "{:?}", fit.ring_agreement);
    assert!(
        fitted_iou >= preset_iou - 0.3,
        "{fitted_iou:.2} {preset_iou:.2}"
    );
}

/// Fitted to labels, a spoiled preset's parameters come back: the held-out scans' agreement
/// rises by 1.5 points and more, to within 1.5 of the unspoiled preset's, and the
/// elevation offset (spoiled to 3 m) comes back below 1.8 m (the preset's: 0.8 m).
/// Measured: 90.30 → 92.28 against 93.50, offset 1.55 m, since the synthetic cars stand
/// tilted on the street (2026-12-07); with cars sunk into the uphill road, 90.82 → 93.03
/// against 92.95 and the offset within 0.4 m of the preset's. The same scans give the
/// same fit on one thread as on the default pool.
#[test]
fn parameters_fitted_to_labels_undo_a_spoiled_preset_on_any_number_of_threads() {
    let (scans, ground) = synthetic_street();
    let sample = groundwork_calibrate::LabeledScan::pair(&scans, &ground);
    let base = spoiled_vlp16();
    let search = exact_labels();
    let fit = groundwork_calibrate::fit_parameters(&base, &sample, &search, |_, _| {}).unwrap();
    eprintln!(
        "held-out {:.2} -> {:.2}, fitted {:.2} -> {:.2}, {} evaluations, kept round {}: {:#?}",
        fit.held_out_before.iou(),
        fit.held_out_after.iou(),
        fit.fitted_before.iou(),
        fit.fitted_after.iou(),
        fit.evaluations,
        fit.kept_round,
        fit.changed
    );
    assert!(!fit.kept_preset, "{:?}", fit.history);
    assert!(
        fit.held_out_after.iou() > fit.held_out_before.iou() + 1.5,
        "{:?}",
        fit.history
    );
    let mut preset = sensor_preset("vlp16").unwrap();
    preset.history.frames = 1;
    preset.terrain.enabled = false;
    let held = held_out(&sample, &search);
    let unspoiled =
        groundwork_calibrate::params::agreement(&preset, &held, fit.trusted_range).unwrap();
    eprintln!(
        "the unspoiled preset's held-out agreement: {:.2}",
        unspoiled.iou()
    );
    assert!(
        fit.held_out_after.iou() > unspoiled.iou() - 1.5,
        "{:.2} against {:.2}",
        fit.held_out_after.iou(),
        unspoiled.iou()
    );
    assert!(fit.config.ground.elevation.beta <= 1.8, "{:?}", fit.changed);
    assert_eq!((fit.fitted_scans, fit.held_out_scans), (6, 2));

    // With the trust rule (the default) the fit counts only the rings where the spoiled
    // preset and the labels agree, the first always: there (within 10 m) the spoiled
    // preset already agrees on more than 97.5 %, so the default bar for keeping a fit (a
    // held-out gain above 2.5 points) cannot be met and the preset stays. With no bar the
    // held-out part still decides: the search gains on the fitted scans' near rings, and a
    // round is kept only if it also gains on the held-out scans' (measured:
    // fitted 93.58 → 98.18, held-out 98.89 → 98.58–98.66, so the preset stays).
    let default = groundwork_calibrate::ParamSearchConfig::default();
    let kept = groundwork_calibrate::fit_parameters(&base, &sample, &default, |_, _| {}).unwrap();
    assert!(kept.held_out_before.iou() > 100.0 - default.min_held_out_gain);
    assert!(
        kept.kept_preset && kept.config == base,
        "{:?}",
        kept.changed
    );
    let low_bar = groundwork_calibrate::ParamSearchConfig {
        min_held_out_gain: 0.0,
        ..default
    };
    let trusted =
        groundwork_calibrate::fit_parameters(&base, &sample, &low_bar, |_, _| {}).unwrap();
    eprintln!(
        "trusted within {} m: held-out {:.2} -> {:.2} ({:?}; {:?})",
        trusted.trusted_range,
        trusted.held_out_before.iou(),
        trusted.held_out_after.iou(),
        trusted.ring_agreement,
        trusted.history
    );
    let (first, rounds) = trusted.history.split_first().unwrap();
    let last = rounds.last().unwrap();
    assert!(
        last.fitted_iou > first.fitted_iou + 1.0,
        "{:?}",
        trusted.history
    );
    let carried_over = rounds.iter().any(|r| r.held_out_iou > first.held_out_iou);
    assert_eq!(trusted.kept_preset, !carried_over, "{:?}", trusted.history);
    assert!(trusted.trusted_range >= 10.0);

    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| groundwork_calibrate::fit_parameters(&base, &sample, &search, |_, _| {}))
        .unwrap();
    assert_eq!(one.changed, fit.changed);
    assert_eq!(one.history, fit.history);
    assert_eq!(one.held_out_after, fit.held_out_after);
}

/// A sample with hardly any trusted ground (a sensor that first sees ground beyond the
/// first trusted ring: here the street's points within 9.5 m dropped, so the first ring holds
/// what falls between 9.5 and 10 m) is not fitted: the preset stays, no search runs, and the
/// report says how few points there were. Without the minimum the search runs on them.
#[test]
fn a_sample_with_too_few_trusted_points_keeps_the_preset_unsearched() {
    let (scans, ground) = synthetic_street();
    let (far, far_ground): (Vec<Vec<[f32; 3]>>, Vec<Vec<bool>>) = scans
        .iter()
        .zip(&ground)
        .map(|(s, g)| {
            s.iter()
                .zip(g)
                .filter(|(p, _)| f64::from(p[0]).hypot(f64::from(p[1])) >= 9.5)
                .map(|(p, &g)| (*p, g))
                .unzip()
        })
        .unzip();
    let sample = groundwork_calibrate::LabeledScan::pair(&far, &far_ground);
    let base = spoiled_vlp16();
    let default = groundwork_calibrate::ParamSearchConfig::default();
    let fit = groundwork_calibrate::fit_parameters(&base, &sample, &default, |_, _| {}).unwrap();
    eprintln!(
        "{:.0} trusted points a scan within {} m ({:?})",
        fit.trusted_points_per_scan, fit.trusted_range, fit.ring_agreement
    );
    assert!(fit.too_few_trusted_points, "{:?}", fit.history);
    assert!(fit.trusted_points_per_scan < default.min_trusted_points as f64);
    assert!(fit.kept_preset && fit.config == base && fit.changed.is_empty());
    assert_eq!((fit.evaluations, fit.history.len()), (1, 1));
    // The same sample with no minimum: the search runs.
    let no_minimum = groundwork_calibrate::ParamSearchConfig {
        min_trusted_points: 0,
        ..default
    };
    let searched =
        groundwork_calibrate::fit_parameters(&base, &sample, &no_minimum, |_, _| {}).unwrap();
    assert!(!searched.too_few_trusted_points);
    assert!(searched.evaluations > 1, "{:?}", searched.history);
    // The whole street holds thousands a scan there: fitted as before.
    let whole = groundwork_calibrate::LabeledScan::pair(&scans, &ground);
    let fit = groundwork_calibrate::fit_parameters(&base, &whole, &default, |_, _| {}).unwrap();
    assert!(
        !fit.too_few_trusted_points && fit.trusted_points_per_scan > 1000.0,
        "{}",
        fit.trusted_points_per_scan
    );
}

/// The parameters are fitted to the mixtures' labels, without terrain following (which
/// would hide a fit's gain from the held-out guard); the fitted configuration carries the
/// preset's terrain following again. The VLP-16 preset follows the terrain.
#[test]
fn parameters_are_fitted_without_terrain_following_and_keep_it() {
    let (scans, ground) = synthetic_street();
    let sample = groundwork_calibrate::LabeledScan::pair(&scans, &ground);
    let with = spoiled_vlp16_following_the_terrain();
    assert!(with.terrain.enabled);
    let mut without = with.clone();
    without.terrain.enabled = false;
    let search = exact_labels();
    let a = groundwork_calibrate::fit_parameters(&with, &sample, &search, |_, _| {}).unwrap();
    let b = groundwork_calibrate::fit_parameters(&without, &sample, &search, |_, _| {}).unwrap();
    assert_eq!(a.history, b.history);
    assert_eq!(a.changed, b.changed);
    assert!(a.config.terrain.enabled && !b.config.terrain.enabled);
    // Terrain following does change what the preset decides here: the guard would have
    // seen other numbers.
    let held = held_out(&sample, &search);
    let following = groundwork_calibrate::params::agreement(&with, &held, a.trusted_range).unwrap();
    assert!(
        (following.iou() - a.held_out_before.iou()).abs() > 0.5,
        "{:.2} {:.2}",
        following.iou(),
        a.held_out_before.iou()
    );
}

/// The held-out part decides: where its labels contradict the fitted part's (here, every
/// held-out label inverted, a labeler wrong on those scans), what the search gains on the
/// fitted part is not kept, and the preset's parameters come back unchanged.
#[test]
fn the_held_out_part_keeps_the_preset_when_the_fit_does_not_carry_over() {
    let (scans, mut ground) = synthetic_street();
    let every = groundwork_calibrate::ParamSearchConfig::default().held_out_every;
    for labels in ground.iter_mut().skip(every - 1).step_by(every) {
        labels.iter_mut().for_each(|g| *g = !*g);
    }
    let sample = groundwork_calibrate::LabeledScan::pair(&scans, &ground);
    let base = spoiled_vlp16();
    let search = exact_labels();
    let fit = groundwork_calibrate::fit_parameters(&base, &sample, &search, |_, _| {}).unwrap();
    eprintln!("{:?}", fit.history);
    // The search did gain on the fitted part...
    let last = fit.history.last().unwrap();
    assert!(
        last.fitted_iou > fit.history[0].fitted_iou + 1.5,
        "{:?}",
        fit.history
    );
    // ...and it is not kept.
    assert!(
        fit.kept_preset && fit.changed.is_empty(),
        "{:?}",
        fit.changed
    );
    assert_eq!(fit.config, base);
}

/// On the bundled KITTI frames, parameters fitted to the PseudoLabeler's labels of frames
/// 0–5 (no true label used) lose nothing against the floors the issue sets: single-frame
/// pooled IoU ≥ 97.6 and precision ≥ 99.3 on frames 0–2, measured with the true labels.
#[test]
fn kitti_parameters_fitted_to_pseudo_labels_keep_the_accuracy() {
    let methods = groundwork_io::load_methods_config_over(Some("hdl64e"), None).unwrap();
    let mut base = methods.segmenter.clone();
    base.history.frames = 1;
    let hdl64e = sensor_preset("hdl64e").unwrap().sensor.mount;
    let kitti = kitti_seen_from(&hdl64e);
    let scans = xyz(&kitti);
    let search = groundwork_calibrate::ParamSearchConfig::default();
    let fit = groundwork_calibrate::fit_to_pseudo_labels(
        &base,
        &methods.pseudolabeler,
        &scans,
        &search,
        |_| {},
    )
    .unwrap();
    let (iou_preset, precision_preset) = kitti_config_iou(&kitti, &base);
    let (iou, precision) = kitti_config_iou(&kitti, &fit.config);
    eprintln!(
        "agreement with the PseudoLabeler held-out {:.2} -> {:.2}, fitted {:.2} -> {:.2}; \
         true labels, frames 0–2: preset {iou_preset:.2} ({precision_preset:.2}), fitted \
         {iou:.2} ({precision:.2}); {:#?}",
        fit.held_out_before.iou(),
        fit.held_out_after.iou(),
        fit.fitted_before.iou(),
        fit.fitted_after.iou(),
        fit.changed
    );
    assert!(iou >= 97.6 && precision >= 99.3, "{iou:.2} {precision:.2}");
}

/// Two real scans of a solid-state LiDAR (tests/data/livox-g3reg, PCD files written by PCL,
/// no labels). Read as their writer wrote them (counts and the first and last points as
/// parsed apart from groundwork); each scan's ground plane gives the same mount (measured:
/// 0.834 and 0.843 m, roll 0.27° and −0.75°, pitch −0.04° and 1.01°); on that mount the
/// `livox` preset agrees with the PseudoLabeler's labels as well as any preset does
/// (measured pooled ground IoU: docs/sensors.md, "Real solid-state scans"). Agreement with
/// the labeler is not accuracy: the labeler is the reference only because nothing better
/// exists for these scans; the threshold guards against the preset drifting from it.
#[test]
fn real_solid_state_scans_give_one_mount_and_the_livox_preset_agrees_with_the_labeler() {
    use groundwork_calibrate::frame_mount;
    use groundwork_calibrate::params::agreement;
    use groundwork_core::config::SensorConfig;
    use groundwork_io::SENSOR_PRESETS;
    let scans: Vec<Vec<[f32; 3]>> = livox_scans()
        .iter()
        .map(|f| {
            let s = read_scan(f, 200_000).unwrap();
            assert_eq!(
                s.records,
                s.points.len(),
                "{}: every record a point",
                f.display()
            );
            s.points.iter().map(|p| [p.x, p.y, p.z]).collect()
        })
        .collect();
    // Counts and end points as Python's `struct` reads the files' records.
    assert_eq!(scans[0].len(), 41_657);
    assert_eq!(scans[1].len(), 39_783);
    assert_eq!(scans[0][0], [4.444_587, 4.999_737_7, -0.883_785_7]);
    assert_eq!(scans[1][39_782], [19.163_956, 13.929_987, 1.389_021_8]);
    let livox = sensor_preset("livox").unwrap();
    let prior = mount_transform(&livox.sensor.mount).unwrap();
    let cfg = MountSearchConfig::default();
    let views: Vec<_> = scans
        .iter()
        .enumerate()
        .map(|(k, s)| frame_mount(s, &prior, &cfg, k as u64).unwrap())
        .collect();
    for v in &views {
        eprintln!(
            "plane: height {:.3} m, roll {:.2}°, pitch {:.2}°",
            v.height,
            v.roll.to_degrees(),
            v.pitch.to_degrees()
        );
        assert!((0.80..0.88).contains(&v.height), "{}", v.height);
        assert!(v.roll.to_degrees().abs() < 1.5 && v.pitch.to_degrees().abs() < 1.5);
        // Ground ahead only (measured leverage 2.32 and 2.13): a mount from such scans
        // carries the one-sided caveat.
        assert!(
            v.plane.leverage > cfg.one_sided_leverage,
            "{}",
            v.plane.leverage
        );
    }
    assert!((views[0].height - views[1].height).abs() < 0.03);
    let mean = |f: fn(&groundwork_calibrate::mount::FrameMount) -> f64| {
        views.iter().map(f).sum::<f64>() / views.len() as f64
    };
    let mount = MountConfig {
        height: mean(|v| v.height),
        roll: mean(|v| v.roll),
        pitch: mean(|v| v.pitch),
        yaw: 0.0,
        matrix: None,
    };
    let sensor = SensorConfig {
        mount,
        ..livox.sensor.clone()
    };
    let mut labeling = livox.clone();
    labeling.sensor = sensor.clone();
    let labeler = groundwork_pseudolabel::PseudoLabeler::new(
        Default::default(),
        groundwork_pseudolabel::GroundFrame::from_config(&labeling).unwrap(),
    )
    .unwrap();
    let ground = groundwork_calibrate::pseudo::pseudo_ground(&labeler, &scans, || {}).unwrap();
    let sample = groundwork_calibrate::LabeledScan::pair(&scans, &ground);
    let mut table = Vec::new();
    for (name, _) in SENSOR_PRESETS {
        let mut cfg = sensor_preset(name).unwrap();
        cfg.sensor = sensor.clone();
        cfg.history.frames = 1;
        table.push((
            *name,
            agreement(&cfg, &sample, f64::INFINITY).unwrap().iou(),
        ));
    }
    eprintln!("agreement with the PseudoLabeler (ground IoU, %): {table:?}");
    let best = table.iter().map(|t| t.1).fold(f64::MIN, f64::max);
    let own = table.iter().find(|t| t.0 == "livox").unwrap().1;
    assert!(
        own >= 90.5 && own >= best - 1.0,
        "livox {own:.2}, best {best:.2}"
    );
}

/// `mount_check.mode = "correct"`: a sensor mounted 2.2 m high and pitched 6° nose down,
/// segmented on its preset's mount, with the true poses (history on). The
/// mount in use turns towards the observed one at its rate and locks there; from then on
/// the segmentation is as good as with the true mount and better than `warn`'s, which keeps
/// the configured mount, wherever that mount costs accuracy. Told the true mount, `correct`
/// never moves it: the output is `warn`'s, bit for bit. Figures in docs/calibration.md.
#[test]
fn correct_mode_moves_a_wrong_mount_to_the_observed_one() {
    use groundwork_core::config::MountCheckMode;
    use groundwork_tests::{Poses, SyntheticRun, method_run};
    let truth = MountConfig {
        height: 2.2,
        roll: 0.0,
        pitch: 6f64.to_radians(),
        yaw: 0.0,
        matrix: None,
    };
    // IoU over the scans from `from` on.
    let tail = |r: &SyntheticRun, from: usize| {
        let mut c = Confusion::default();
        for f in &r.frames[from..] {
            c.merge(f);
        }
        c.metrics().iou_ground
    };
    for (sensor, scene) in [("vlp16", SceneKind::Urban), ("os1-64", SceneKind::Parking)] {
        let g = synthetic_seeded(sensor, scene, 200, Some(truth.clone()), 2);
        let run = |mount: &MountConfig, mode: MountCheckMode| {
            let mut cfg = sensor_preset(sensor).unwrap();
            cfg.sensor.mount = mount.clone();
            cfg.mount_check.mode = mode;
            let mut seg = Segmenter::new(cfg).unwrap();
            let r = method_run(&g, &mut seg, Poses::True, Protocol::Gmm);
            (r, seg.observed_mount().unwrap())
        };
        let preset = sensor_preset(sensor).unwrap().sensor.mount;
        let (warn, _) = run(&preset, MountCheckMode::Warn);
        let (correct, seen) = run(&preset, MountCheckMode::Correct);
        let (exact, _) = run(&truth, MountCheckMode::Warn);
        let (exact_correct, still) = run(&truth, MountCheckMode::Correct);
        let applied = MountConfig {
            height: seen.applied_height,
            roll: seen.applied_roll,
            pitch: seen.applied_pitch,
            yaw: 0.0,
            matrix: None,
        };
        let (angle, dh) = mount_error(&applied, &truth);
        let (w, c, t) = (tail(&warn, 150), tail(&correct, 150), tail(&exact, 150));
        eprintln!(
            "{sensor} {scene:?}: applied h {:.3} pitch {:.2}° roll {:.2}° after {} corrected \
             scans ({angle:.2}°, {dh:.3} m from the truth; observed h {:.3} in {} of {} \
             scans); IoU over scans 150–199: warn {w:.2}, correct {c:.2}, true mount {t:.2}; \
             all scans: {:.2} {:.2} {:.2}",
            seen.applied_height,
            seen.applied_pitch.to_degrees(),
            seen.applied_roll.to_degrees(),
            seen.corrected_scans,
            seen.height,
            seen.scans,
            g.frames(),
            tail(&warn, 0),
            tail(&correct, 0),
            tail(&exact, 0),
        );
        // The tilt is the truth's, to the observer's own bias in these scenes (up to 1.2°
        // on the VLP-16's urban scans told the true mount); the height the observed one,
        // held within `correct_max_m` of the configured one (the VLP-16's preset says 1 m:
        // 2 m at most), to the quarter tolerance it locks within.
        let cap = groundwork_core::config::MountCheckConfig::default();
        let allowed = seen.height.clamp(
            preset.height - cap.correct_max_m,
            preset.height + cap.correct_max_m,
        );
        assert!(
            angle < 1.5 && (seen.applied_height - allowed).abs() < 0.1,
            "{seen:?}"
        );
        assert!(!seen.correcting, "{seen:?}");
        // At 0.1° and 1 cm per scan, about 5° or 0.7–1 m takes 50 scans or more; it then
        // follows the observation until that settles (at most the 200 scans seen).
        assert!((50..=200).contains(&seen.corrected_scans), "{seen:?}");
        // As good as the true mount; better than the wrong one wherever that costs (on the
        // OS1-64's car park its zones score 97.67 on the wrong mount, 97.35 on the true).
        assert!(
            c >= t - 0.3 && (c > w || w >= t - 0.3),
            "{c:.2} against {w:.2} and {t:.2}"
        );
        assert_eq!(still.corrected_scans, 0, "{still:?}");
        assert_eq!(exact_correct.probabilities, exact.probabilities);
    }
}
