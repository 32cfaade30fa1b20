//! Multi-frame history: equivalence with single frame, pose handling, bounded memory.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use groundwork_core::{Point, Pose, Segmenter, SegmenterConfig};
use nalgebra::Vector3;

/// A synthetic street: flat road at z = −1.73 (sensor frame) with a box-shaped obstacle,
/// seen from `x0` metres further along x.
fn street(x0: f32) -> Vec<Point> {
    let mut pts = Vec::new();
    for i in 0..240 {
        for j in 0..80 {
            let (x, y) = (-30.0 + i as f32 * 0.25, -10.0 + j as f32 * 0.25);
            let wobble = ((i * 7 + j * 13) % 11) as f32 * 0.002;
            pts.push(Point::new(x - x0, y, -1.73 + wobble));
        }
    }
    for i in 0..40 {
        for k in 0..30 {
            pts.push(Point::new(
                12.0 + i as f32 * 0.05 - x0,
                3.0,
                -1.7 + k as f32 * 0.05,
            ));
        }
    }
    pts
}

fn pose_at(x: f64) -> Pose {
    Pose::new(Vector3::new(x, 0.0, 0.0), Vector3::zeros())
}

#[test]
fn one_frame_history_equals_single_frame_query() {
    let pts = street(0.0);
    let mut cfg = SegmenterConfig::default();
    cfg.history.frames = 1;
    let mut a = Segmenter::new(cfg.clone()).unwrap();
    let mut b = Segmenter::new(cfg).unwrap();
    let (mut pa, mut pb) = (vec![0.0; pts.len()], vec![0.0; pts.len()]);
    for step in 0..3 {
        let pts = street(step as f32 * 0.5);
        a.segment(&pts, None, &mut pa).unwrap();
        b.segment(&pts, Some(&pose_at(step as f64 * 0.5)), &mut pb)
            .unwrap();
        let worst = pa
            .iter()
            .zip(&pb)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(
            worst <= 1e-6,
            "N_f = 1 with a pose must equal single frame, worst {worst}"
        );
    }
    assert_eq!(b.history_len(), 0, "N_f = 1 keeps no past frames");
}

#[test]
fn history_is_used_bounded_and_reset_by_pose_jumps() {
    let mut cfg = SegmenterConfig::default();
    cfg.history.frames = 4;
    let mut seg = Segmenter::new(cfg).unwrap();
    let mut out = Vec::new();
    let mut components_seen = Vec::new();
    for step in 0..600 {
        let x = step as f64 * 0.2;
        // The street repeats every 5 m, so the world is the same after each wrap.
        let pts = street((x % 5.0) as f32);
        out.resize(pts.len(), 0.0);
        let r = seg
            .segment(&pts, Some(&pose_at(x % 5.0)), &mut out)
            .unwrap();
        assert!(r.frames_queried <= 4);
        if step >= 3 {
            assert_eq!(r.frames_queried, 4);
            assert_eq!(seg.history_len(), 3);
        }
        components_seen.push(seg.history_components());
    }
    // Constant memory: the history never holds more than 3 frames' components, and a
    // frame's component count is bounded by segments × K_max.
    let max = *components_seen.iter().max().unwrap();
    assert!(max <= 3 * 504 * 8);
    assert!(components_seen[599] <= max);

    // A relocalisation (jump of 100 m) clears the history and says so.
    let pts = street(0.0);
    out.resize(pts.len(), 0.0);
    let r = seg.segment(&pts, Some(&pose_at(1e5)), &mut out).unwrap();
    assert!(r.history_cleared);
    assert_eq!(r.frames_queried, 1);
    assert_eq!(seg.counters().history_resets, 1);

    // A scan without a pose is segmented single-frame, counted, and leaves history alone.
    let before = seg.history_len();
    let r = seg.segment(&pts, None, &mut out).unwrap();
    assert_eq!(r.frames_queried, 1);
    assert_eq!(seg.counters().without_pose, 1);
    assert_eq!(seg.history_len(), before);
}

#[test]
fn history_answers_for_points_the_current_frame_cannot_model() {
    // Frame 1 sees a dense road patch; frame 2 sees only 5 points of it (too few for a
    // model). Single frame gives them 0, the history knows they are road.
    let dense = street(0.0);
    let sparse: Vec<Point> = dense
        .iter()
        .copied()
        .filter(|p| p.x > 20.0 && p.x < 21.0 && p.y > 0.0 && p.y < 1.0)
        .take(5)
        .collect();
    assert_eq!(sparse.len(), 5);
    let mut cfg = SegmenterConfig::default();
    cfg.history.frames = 2;
    let mut seg = Segmenter::new(cfg).unwrap();
    let mut out = vec![0.0; dense.len()];
    seg.segment(&dense, Some(&pose_at(0.0)), &mut out).unwrap();
    let mut out = vec![0.0; 5];
    seg.segment(&sparse, Some(&pose_at(0.0)), &mut out).unwrap();
    assert!(out.iter().all(|&p| p > 0.5), "{out:?}");
    let mut single = Segmenter::new(SegmenterConfig::default()).unwrap();
    single
        .segment(&sparse, Some(&pose_at(0.0)), &mut out)
        .unwrap();
    assert!(out.iter().all(|&p| p == 0.0), "{out:?}");
}

#[test]
fn posed_query_matches_segment_and_leaves_the_history_alone() {
    let mut cfg = SegmenterConfig::default();
    cfg.history.frames = 4;
    let mut seg = Segmenter::new(cfg).unwrap();
    for step in 0..3 {
        let pts = street(step as f32 * 0.8);
        let mut out = vec![0.0; pts.len()];
        seg.segment(&pts, Some(&pose_at(step as f64 * 0.8)), &mut out)
            .unwrap();
    }
    assert_eq!(seg.history_len(), 3);
    let pts = street(2.4);
    let pose = pose_at(2.4);
    let model = seg.fit(&pts).unwrap();
    let mut queried = vec![0.0; pts.len()];
    for _ in 0..2 {
        let frames = seg
            .query_model_posed(&model, &pts, &pose, &mut queried)
            .unwrap();
        assert_eq!(frames, 4, "the model and three past frames");
        assert_eq!(seg.history_len(), 3, "querying must not push a frame");
    }
    // `segment` fits the same model (the height filter has not moved in between) and
    // queries the same history.
    let mut segmented = vec![0.0; pts.len()];
    let report = seg.segment(&pts, Some(&pose), &mut segmented).unwrap();
    assert_eq!(report.frames_queried, 4);
    let worst = queried
        .iter()
        .zip(&segmented)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 1e-6, "posed query vs segment: worst {worst}");
    // A pose beyond the jump limit queries the model alone.
    let far = pose_at(100.0);
    let frames = seg
        .query_model_posed(&model, &pts, &far, &mut queried)
        .unwrap();
    assert_eq!(frames, 1);
}

#[test]
fn sensor_time_gaps_and_requests_reset_the_history_and_are_counted() {
    let mut cfg = SegmenterConfig::default();
    cfg.history.frames = 3;
    cfg.history.max_time_gap = 0.5;
    let mut seg = Segmenter::new(cfg).unwrap();
    let pts = street(0.0);
    let mut out = vec![0.0; pts.len()];
    let mut frame = |seg: &mut Segmenter, x: f64, t_ms: u64| {
        seg.segment_stamped(&pts, Some(&pose_at(x)), Some(t_ms * 1_000_000), &mut out)
            .unwrap()
    };
    // 10 Hz: the history fills up.
    for i in 0..4u64 {
        frame(&mut seg, i as f64 * 0.1, i * 100);
    }
    assert_eq!(seg.history_len(), 2);
    // A 2 s pause of the sensor: the stored models are stale, the history is cleared
    // before this scan is queried (continuous pose or not).
    let r = frame(&mut seg, 0.4, 2300);
    assert!(r.history_cleared);
    assert_eq!(r.frames_queried, 1);
    assert_eq!(seg.counters().resets_time_gap, 1);
    frame(&mut seg, 0.5, 2400);
    assert_eq!(seg.history_len(), 2);
    // Time running backwards (a replay restarted, a clock reset) clears it too.
    let r = frame(&mut seg, 0.6, 100);
    assert!(r.history_cleared && r.frames_queried == 1);
    assert_eq!(seg.counters().resets_time_gap, 2);
    // Within the gap: kept.
    let r = frame(&mut seg, 0.7, 550);
    assert!(!r.history_cleared && r.frames_queried == 2);
    // A requested reset (a new sequence, a new producer run) is counted apart.
    assert!(seg.continues_history(&pose_at(0.8)));
    assert!(!seg.continues_history(&pose_at(80.0)));
    assert!(seg.reset_history());
    assert!(!seg.reset_history(), "nothing left to clear");
    let c = seg.counters();
    assert_eq!(
        (c.resets_requested, c.resets_pose_jump, c.history_resets),
        (1, 0, 3)
    );
    assert_eq!(seg.history_len(), 0);
}

#[test]
fn absurd_finite_points_never_reach_the_fit_or_the_history() {
    let mut cfg = SegmenterConfig::default();
    cfg.history.frames = 3;
    let mut seg = Segmenter::new(cfg).unwrap();
    let clean = street(0.0);
    let mut poisoned = clean.clone();
    // A corrupted return right inside a well-populated road segment.
    let i = poisoned
        .iter()
        .position(|p| (p.x - 10.0).abs() < 0.2 && p.y.abs() < 0.2)
        .unwrap();
    poisoned[i] = Point::new(10.0, 0.0, 1e20);
    let mut out = vec![0.0; clean.len()];
    let mut reference = vec![0.0; clean.len()];
    // The reference: the same scan with that return replaced by one in the near disc.
    let mut near = clean.clone();
    near[i] = Point::new(0.0, 0.0, 0.0);
    let mut ref_seg = Segmenter::new(seg.config().clone()).unwrap();
    for step in 0..3 {
        let r = seg
            .segment(&poisoned, Some(&pose_at(step as f64 * 0.1)), &mut out)
            .unwrap();
        ref_seg
            .segment(&near, Some(&pose_at(step as f64 * 0.1)), &mut reference)
            .unwrap();
        assert_eq!(r.out_of_bounds_points, 1);
        assert_eq!(out[i], 0.0);
        assert!(out.iter().all(|p| p.is_finite()));
        assert_eq!(
            out.iter().map(|p| p.to_bits()).collect::<Vec<_>>(),
            reference.iter().map(|p| p.to_bits()).collect::<Vec<_>>(),
            "one absurd return changes nothing but its own probability"
        );
    }
    assert_eq!(seg.counters().out_of_bounds_points, 3);
    assert_eq!(seg.counters().non_finite_outputs, 0);
}
