//! The fallback detector on the real labeled KITTI frames and on synthetic scenes with
//! known objects.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use glam::DVec3;
use groundwork_core::{Segmenter, SegmenterConfig, pose_from_matrix};
use groundwork_detect::{Detections, Detector, DetectorConfig};
use groundwork_eval::{ObjectScore, score_objects};
use groundwork_io::LabelMap;
use groundwork_io::Sequence;
use groundwork_io::load_methods_config_over;
use groundwork_synth::Shape;
use groundwork_synth::classes::is_ground;
use groundwork_tests::{SceneKind, kitti_sequence, synthetic};

/// Segments the labeled frames 0–2 in order with the default history and poses, detects,
/// and scores every labeled object.
fn kitti_objects(seg_cfg: &SegmenterConfig, det_cfg: DetectorConfig) -> ObjectScore {
    let seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
    let mut seg = Segmenter::new(seg_cfg.clone()).unwrap();
    let mut det = Detector::new(det_cfg, seg_cfg).unwrap();
    let labels_dir = kitti_sequence().join("labels");
    let map = LabelMap::semantickitti();
    let mut score = ObjectScore::default();
    let mut out = Detections::default();
    for item in seq.scans(200_000).take(3) {
        let scan = item.scan.unwrap();
        let mut probs = vec![0.0; scan.points.len()];
        seg.segment(&scan.points, seq.pose(item.index), &mut probs)
            .unwrap();
        let r = det.detect(&scan.points, &probs, &mut out).unwrap();
        eprintln!("{}: {r:?}", item.name);
        let labels = map
            .read_raw(&map.file_for(&labels_dir, &item.name), scan.points.len())
            .unwrap();
        let xy: Vec<[f32; 2]> = scan.points.iter().map(|p| [p.x, p.y]).collect();
        score.merge(score_objects(
            &item.name,
            &labels,
            &out.clusters,
            &xy,
            &out.proposals,
            20,
        ));
    }
    score
}

/// SemanticKITTI frames 0–2 hold 35 labeled cars with ≥ 20 points within 40 m (and 3
/// cyclists). Measured: all 35 cars and 3 cyclists found, segmented by the GMM with the
/// preset's 2 frames of history.
#[test]
fn cars_on_the_real_frames_are_found() {
    let methods = load_methods_config_over(Some("hdl64e"), None).unwrap();
    let score = kitti_objects(&methods.segmenter, methods.detector);
    eprintln!("{}", score.table());
    for o in score.objects.iter().filter(|o| o.proposal == 0) {
        eprintln!("missed: {o:?}");
    }
    let (found, cars) = score.recall("car", 40.0);
    assert_eq!(cars, 35, "labeled cars with ≥ 20 points within 40 m");
    assert!(found * 100 >= cars * 90, "{found}/{cars} cars found");
    assert_eq!(score.recall("cyclist", 40.0).1, 3);
}

/// Box errors of matched cars against their true boxes (the body's, in the vehicle's
/// ground-aligned frame).
#[derive(Debug, Default)]
struct BoxErrors {
    centre: Vec<f64>,
    heading_deg: Vec<f64>,
    length: Vec<f64>,
    width: Vec<f64>,
}

/// Where the ground probabilities come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Ground {
    /// The GMM segmenter (preset, history with true poses).
    Segmenter,
    /// The true labels: what is left to lose is the clustering's.
    Labels,
}

/// A synthetic sequence segmented by the GMM (preset, history with true poses), detected,
/// scored against the generator's instances.
fn synthetic_objects(
    sensor: &str,
    scene: SceneKind,
    frames: usize,
    ground: Ground,
) -> (ObjectScore, BoxErrors) {
    let generator = synthetic(sensor, scene, frames, None);
    let methods = load_methods_config_over(Some(sensor), None).unwrap();
    let cfg = methods.segmenter;
    let mut seg = Segmenter::new(cfg.clone()).unwrap();
    let mut det = Detector::new(methods.detector, &cfg).unwrap();
    let mut score = ObjectScore::default();
    let mut errors = BoxErrors::default();
    let mut out = Detections::default();
    for i in 0..frames {
        let scan = generator.scan(i);
        let pose = pose_from_matrix(&scan.pose_matrix()).unwrap();
        let mut probs = vec![0.0; scan.points.len()];
        seg.segment(&scan.points, Some(&pose), &mut probs).unwrap();
        if ground == Ground::Labels {
            for (p, &l) in probs.iter_mut().zip(&scan.labels) {
                *p = if is_ground(l as u16) { 1.0 } else { 0.0 };
            }
        }
        det.detect(&scan.points, &probs, &mut out).unwrap();
        let xy: Vec<[f32; 2]> = scan.points.iter().map(|p| [p.x, p.y]).collect();
        let s = score_objects(
            &format!("{i}"),
            &scan.labels,
            &out.clusters,
            &xy,
            &out.proposals,
            20,
        );
        let world_to_vehicle = generator.vehicle_pose(i).inverse();
        for o in s
            .objects
            .iter()
            .filter(|o| o.class == "car" && o.proposal > 0)
        {
            let instance = (o.label >> 16) as u16;
            // A car's first part is its body, a box tilted with the ground under it.
            let Some(Shape::TiltedBox {
                center,
                half,
                rotation,
            }) = generator
                .scene()
                .objects()
                .iter()
                .find(|b| b.instance == instance)
                .map(|b| b.shape)
            else {
                continue;
            };
            let c = world_to_vehicle.transform_point3(center);
            let axis = world_to_vehicle.transform_vector3(rotation * DVec3::X);
            let p = &out.proposals[o.proposal as usize - 1];
            errors
                .centre
                .push((f64::from(p.center[0]) - c.x).hypot(f64::from(p.center[1]) - c.y));
            // Boxes are symmetric: headings compare modulo 180°.
            let d = (f64::from(p.yaw) - axis.y.atan2(axis.x)).rem_euclid(std::f64::consts::PI);
            errors
                .heading_deg
                .push(d.min(std::f64::consts::PI - d).to_degrees());
            errors.length.push(f64::from(p.length) - 2.0 * half.x);
            errors.width.push(f64::from(p.width) - 2.0 * half.y);
        }
        score.merge(s);
    }
    (score, errors)
}

fn quantile(mut v: Vec<f64>, q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(((v.len() as f64 - 1.0) * q).round() as usize)
        .copied()
        .unwrap_or(f64::NAN)
}

/// Found / scored objects (cars and people with ≥ 20 points, any range).
fn recall(score: &ObjectScore) -> (usize, usize) {
    let (c, cn) = score.recall("car", f32::INFINITY);
    let (p, pn) = score.recall("person", f32::INFINITY);
    (c + p, cn + pn)
}

/// Measured (4 frames each, cars and people with ≥ 20 points; cell 0.15 m, d 0.5 m):
///
/// | scene | GMM's probabilities | true ground |
/// | --- | --- | --- |
/// | HDL-64E street | 107/107 | 107/107 |
/// | OS1-64 street | 45/48 | 48/48 |
/// | Livox street | 24/27 | 27/27 |
/// | VLP-16 car park | 87/131 | 120/131 |
///
/// With true ground the clustering finds ≥ 95 % except in the VLP-16 car park, where cars
/// stand 0.7–1.0 m apart in their stalls and 16 rings 2° apart leave the cars' sides
/// sparse; with the GMM, the 16-beam sensor's lowest ring on a car is often called ground.
#[test]
fn synthetic_objects_are_found_and_boxed() {
    let cases = [
        ("hdl64e", SceneKind::Urban, Ground::Segmenter, 0.95),
        // 45/48: one car 21–22 m away, at the boundary of two zones, split into two
        // proposals in two frames, and one of 20 points 43 m away. Other zone layouts trade
        // these few marginal objects for worse ground (docs/sensors.md).
        ("os1-64", SceneKind::Urban, Ground::Segmenter, 0.93),
        ("hdl64e", SceneKind::Urban, Ground::Labels, 0.95),
        ("os1-64", SceneKind::Urban, Ground::Labels, 0.95),
        ("livox", SceneKind::Urban, Ground::Labels, 0.95),
        // 24/27: one car 56–57 m ahead, 22–29 points, is missed in three of the frames.
        ("livox", SceneKind::Urban, Ground::Segmenter, 0.85),
        ("vlp16", SceneKind::Parking, Ground::Labels, 0.88),
    ];
    for (sensor, scene, ground, floor) in cases {
        let (score, e) = synthetic_objects(sensor, scene, 4, ground);
        let (found, total) = recall(&score);
        eprintln!(
            "{sensor} {scene:?} {ground:?}: {found}/{total}\n{}",
            score.table()
        );
        for o in score.objects.iter().filter(|o| o.proposal == 0) {
            eprintln!("  missed: {o:?}");
        }
        assert!(total >= 25, "{sensor}: only {total} objects");
        assert!(
            found as f64 >= floor * total as f64,
            "{sensor} {scene:?} {ground:?}: {found}/{total} objects found"
        );
        if sensor == "hdl64e" {
            // Cars seen by a 64-beam sensor from the street: boxes close to the truth.
            // Measured medians: centre 0.27 m, heading 0.3°, length −0.20 m, width −0.07 m.
            let (c, h) = (
                quantile(e.centre.clone(), 0.5),
                quantile(e.heading_deg.clone(), 0.5),
            );
            let (l, w) = (
                quantile(e.length.clone(), 0.5),
                quantile(e.width.clone(), 0.5),
            );
            eprintln!(
                "  {} car boxes: median |centre| {c:.2} m (p90 {:.2}), heading {h:.1}° (p90 {:.1}°), length {l:+.2} m, width {w:+.2} m",
                e.centre.len(),
                quantile(e.centre.clone(), 0.9),
                quantile(e.heading_deg.clone(), 0.9),
            );
            assert!(c < 0.4 && h < 2.0 && l.abs() < 0.5 && w.abs() < 0.3);
            // The tail: a car seen only end-on is a line across it, and its box turns by
            // 90° (p90 heading 39°, centre 1.3 m measured; 23° with the fit points chosen
            // by the coordinates' bits: which end-on cars turn follows which low points
            // the ground takes, one draw of the fit points or another).
            assert!(quantile(e.heading_deg.clone(), 0.9) < 45.0);
            assert!(quantile(e.centre.clone(), 0.9) < 2.0);
        }
    }
}
