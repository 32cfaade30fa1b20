//! Invariants of the segmenter on arbitrary finite scans.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use groundwork_core::{Point, Pose, SegmentError, Segmenter, SegmenterConfig};
use proptest::prelude::*;

/// A finite coordinate a corrupted packet might carry: huge, tiny, or just either side of
/// the default coordinate bound (4 × 80 m).
fn extreme() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(f32::MAX),
        Just(-f32::MAX),
        Just(1e20f32),
        Just(-1e20f32),
        Just(1e6f32),
        Just(f32::MIN_POSITIVE),
        Just(319.9f32),
        Just(-320.1f32),
        -1e30f32..1e30,
    ]
}

fn point() -> impl Strategy<Value = Point> {
    // Ranges cover the near disc, every zone and beyond max range, and heights from well
    // below the ground to well above the sensor; duplicates are likely with small ranges.
    // Every so often one coordinate is absurd but finite.
    prop_oneof![
        10 => (-100.0f32..100.0, -100.0f32..100.0, -5.0f32..5.0),
        10 => (-6.0f32..6.0, -6.0f32..6.0, -2.0f32..0.5),
        10 => (Just(5.0f32), Just(5.0f32), -1.8f32..-1.6),
        1 => (5.0f32..20.0, -5.0f32..5.0, extreme()),
        1 => (extreme(), -5.0f32..5.0, -1.8f32..-1.6),
        1 => (extreme(), extreme(), extreme()),
    ]
    .prop_map(|(x, y, z)| Point::new(x, y, z))
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// Every input point gets exactly one probability, in [0, 1], and the result does not
    /// depend on where a point sits in the input (order is preserved, not re-sorted).
    #[test]
    fn one_probability_per_point_in_range_and_in_order(pts in prop::collection::vec(point(), 0..3000)) {
        let mut seg = Segmenter::new(SegmenterConfig::default()).unwrap();
        let mut out = vec![f32::NAN; pts.len()];
        let report = seg.segment(&pts, None, &mut out).unwrap();
        prop_assert_eq!(report.points, pts.len());
        for &p in &out {
            prop_assert!((0.0..=1.0).contains(&p), "probability {}", p);
        }
        // No NaN was produced at all (the last-resort guard that writes them as 0 counts).
        prop_assert_eq!(seg.counters().non_finite_outputs, 0);
        let bound = 320.0f32;
        let outside = pts.iter().filter(|p| [p.x, p.y, p.z].iter().any(|v| v.abs() > bound)).count();
        prop_assert_eq!(report.out_of_bounds_points, outside);
        // Reversing the scan reverses the output exactly: each segment is fitted in a
        // canonical order of its points, so not even float rounding depends on input order.
        let rev: Vec<Point> = pts.iter().rev().copied().collect();
        let mut seg2 = Segmenter::new(SegmenterConfig::default()).unwrap();
        let mut out2 = vec![f32::NAN; rev.len()];
        seg2.segment(&rev, None, &mut out2).unwrap();
        let mismatched = out.iter().zip(out2.iter().rev()).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        prop_assert!(mismatched == 0, "{} of {} points changed", mismatched, pts.len());
    }

    /// The same holds with history and arbitrary (finite, rigid) poses.
    #[test]
    fn multi_frame_output_is_well_formed(
        scans in prop::collection::vec(prop::collection::vec(point(), 0..800), 1..5),
        moves in prop::collection::vec((-3.0f64..3.0, -3.0f64..3.0, -0.3f64..0.3), 5),
    ) {
        let mut cfg = SegmenterConfig::default();
        cfg.history.frames = 4;
        let mut seg = Segmenter::new(cfg).unwrap();
        for (i, pts) in scans.iter().enumerate() {
            let (x, y, yaw) = moves[i];
            let pose = Pose::new(nalgebra::Vector3::new(x, y, 0.0), nalgebra::Vector3::new(0.0, 0.0, yaw));
            let mut out = vec![f32::NAN; pts.len()];
            seg.segment(pts, Some(&pose), &mut out).unwrap();
            prop_assert!(out.iter().all(|p| (0.0..=1.0).contains(p)));
            prop_assert!(seg.history_len() <= 3);
            prop_assert_eq!(seg.counters().non_finite_outputs, 0);
        }
    }
}

#[test]
fn empty_and_single_point_scans() {
    let mut seg = Segmenter::new(SegmenterConfig::default()).unwrap();
    let mut out: Vec<f32> = vec![];
    seg.segment::<Point>(&[], None, &mut out).unwrap();
    let mut one = [f32::NAN];
    seg.segment(&[Point::new(10.0, 0.0, -1.7)], None, &mut one)
        .unwrap();
    // A lone point cannot support a component (τ_N = 10): no model, probability 0.
    assert_eq!(one[0], 0.0);
}

#[test]
fn bad_input_is_rejected_without_touching_state() {
    let mut cfg = SegmenterConfig::default();
    cfg.sensor.max_points = 10;
    cfg.history.frames = 2;
    let mut seg = Segmenter::new(cfg).unwrap();
    let good: Vec<Point> = (0..10)
        .map(|i| Point::new(5.0 + i as f32, 0.0, -1.7))
        .collect();
    let mut out = vec![0.0; 10];
    seg.segment(&good, Some(&Pose::identity()), &mut out)
        .unwrap();
    assert_eq!(seg.history_len(), 1);

    let mut bad = good.clone();
    bad[3].y = f32::NAN;
    match seg.segment(&bad, Some(&Pose::identity()), &mut out) {
        Err(SegmentError::NonFinitePoint { index: 3, .. }) => {}
        other => panic!("{other:?}"),
    }
    bad[3].y = f32::INFINITY;
    assert!(seg.segment(&bad, None, &mut out).is_err());
    let many = vec![Point::new(5.0, 0.0, -1.7); 11];
    let mut out11 = vec![0.0; 11];
    assert!(matches!(
        seg.segment(&many, None, &mut out11),
        Err(SegmentError::TooManyPoints {
            points: 11,
            max: 10
        })
    ));
    assert!(matches!(
        seg.segment(&good, None, &mut out11),
        Err(SegmentError::OutputSize { .. })
    ));
    assert_eq!(seg.counters().rejected, 4);
    assert_eq!(seg.counters().scans, 1);
    assert_eq!(
        seg.history_len(),
        1,
        "rejected scans leave the history alone"
    );
}

#[test]
fn points_inside_min_range_are_never_ground() {
    // A dense flat floor everywhere, including right next to the sensor.
    let mut pts = Vec::new();
    for i in -60..60 {
        for j in -60..60 {
            pts.push(Point::new(i as f32 * 0.1, j as f32 * 0.1, -1.73));
        }
    }
    let mut seg = Segmenter::new(SegmenterConfig::default()).unwrap();
    let mut out = vec![0.0; pts.len()];
    seg.segment(&pts, None, &mut out).unwrap();
    let mut near = 0;
    let mut far_ground = 0;
    for (p, &g) in pts.iter().zip(&out) {
        let r = (p.x * p.x + p.y * p.y).sqrt();
        // The ground-aligned frame is 1.73 m up, so horizontal range is unchanged.
        if r < 2.7 {
            near += 1;
            assert_eq!(g, 0.0, "point at {r} m inside min range");
        } else if r < 5.5 && g >= 0.5 {
            far_ground += 1;
        }
    }
    assert!(near > 1000);
    // The same floor just outside min range is ground.
    assert!(far_ground > 1000, "{far_ground}");
}

#[test]
fn beyond_max_range_policy_is_honoured() {
    use groundwork_core::config::BeyondRangePolicy;
    // A flat floor from 70 to 90 m straight ahead.
    let mut pts = Vec::new();
    for i in 0..400 {
        for j in 0..20 {
            pts.push(Point::new(70.0 + i as f32 * 0.05, j as f32 * 0.2, -1.73));
        }
    }
    let beyond: Vec<usize> = (0..pts.len())
        .filter(|&i| f64::from(pts[i].x).hypot(f64::from(pts[i].y)) >= 80.0)
        .collect();
    for (policy, expect_ground) in [
        (BeyondRangePolicy::OuterRing, true),
        (BeyondRangePolicy::NonGround, false),
    ] {
        let mut cfg = SegmenterConfig::default();
        cfg.zones.beyond_max_range = policy;
        let mut seg = Segmenter::new(cfg).unwrap();
        let mut out = vec![0.0; pts.len()];
        let r = seg.segment(&pts, None, &mut out).unwrap();
        assert_eq!(r.beyond_points, beyond.len());
        let ground = beyond.iter().filter(|&&i| out[i] >= 0.5).count();
        if expect_ground {
            assert!(
                ground * 10 >= beyond.len() * 9,
                "{policy:?}: {ground}/{}",
                beyond.len()
            );
        } else {
            assert_eq!(ground, 0, "{policy:?}");
        }
    }
}
