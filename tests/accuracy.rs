//! Accuracy on the real labeled KITTI frames 0–2 (SemanticKITTI sequence 00).

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use groundwork_core::Segmenter;
use groundwork_core::probability::ProbabilityMap;
use groundwork_eval::{Protocol, evaluate};
use groundwork_io::Sequence;
use groundwork_io::load_config;
use groundwork_tests::{hdl64e_preset, kitti_sequence};

/// Measured 98.66 pooled ground IoU (gmm protocol) with the HDL-64E preset (terrain
/// following, 4 components, 15 iterations), precision 99.38, scans 98.83 / 98.59 / 98.55
/// (98.33 with ground continuity and the paper's EM, the preset until 2026-12-07; 97.64
/// with neither); the paper reports 95.37 on the whole of sequence 00, Patchwork++ 1.4.1
/// scores 98.04 on these three frames. The floors are the measurement less 0.1.
const MIN_POOLED_IOU_SINGLE_FRAME: f64 = 98.56;

#[test]
fn single_frame_pooled_ground_iou_on_frames_0_to_2() {
    let mut cfg = load_config(&hdl64e_preset()).unwrap();
    cfg.history.frames = 1;
    let mut seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
    // Single frame: no poses needed, and only the labeled frames.
    seq.poses = None;
    seq.limit = Some(3);
    let mut seg = Segmenter::new(cfg).unwrap();
    let r = evaluate(&seq, &mut seg, Protocol::Gmm, |_| {}).unwrap();
    assert_eq!(r.labeled_scans, 3);
    let m = r.pooled_metrics;
    eprintln!("pooled: {m:?}");
    assert!(
        m.iou_ground >= MIN_POOLED_IOU_SINGLE_FRAME,
        "pooled ground IoU {:.2}",
        m.iou_ground
    );
    // Precision is what the GMM paper stresses (modelling objects keeps them out of the
    // ground): it must stay high, not be traded for recall.
    assert!(m.precision >= 99.3, "precision {:.2}", m.precision);
    for s in &r.scans {
        let iou = s.metrics.unwrap().iou_ground;
        assert!(iou >= 98.45, "scan {}: IoU {iou:.2}", s.name);
    }
}

/// The preset's probability map (`[probability] map`, fitted on these frames) makes the
/// probabilities say how often points are ground: expected calibration error 0.125 without
/// it, 0.007 single frame and 0.008 with the default history with it; the decisions, and so
/// every IoU, are the same bits with and without (the threshold moves with the map).
#[test]
fn probabilities_are_calibrated_and_decisions_unchanged() {
    for frames in [1, 2] {
        let mut cfg = load_config(&hdl64e_preset()).unwrap();
        cfg.history.frames = frames;
        let mut raw = cfg.clone();
        raw.probability.map.clear();
        let mut seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
        if frames == 1 {
            seq.poses = None;
            seq.limit = Some(3);
        }
        let mapped = evaluate(
            &seq,
            &mut Segmenter::new(cfg).unwrap(),
            Protocol::Gmm,
            |_| {},
        )
        .unwrap();
        let plain = evaluate(
            &seq,
            &mut Segmenter::new(raw).unwrap(),
            Protocol::Gmm,
            |_| {},
        )
        .unwrap();
        eprintln!(
            "{frames} frame(s): ECE {:.3} (without the map {:.3})",
            mapped.expected_calibration_error, plain.expected_calibration_error
        );
        assert!(mapped.expected_calibration_error <= 0.03);
        assert!(plain.expected_calibration_error > 0.1);
        assert_eq!(mapped.pooled, plain.pooled, "the same decisions");
        // Every bin says what it holds, to within 0.1 where it holds many points.
        for b in mapped.reliability.iter().filter(|b| b.points > 5_000) {
            assert!(
                (b.mean_probability - b.ground_fraction).abs() < 0.1,
                "{b:?}"
            );
        }
    }
}

#[test]
fn terraseg_protocol_counts_vegetation_as_non_ground() {
    let cfg = load_config(&hdl64e_preset()).unwrap();
    let mut seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
    seq.poses = None;
    seq.limit = Some(1);
    let mut seg = Segmenter::new(cfg.clone()).unwrap();
    let gmm = evaluate(&seq, &mut seg, Protocol::Gmm, |_| {}).unwrap();
    let mut seg = Segmenter::new(cfg).unwrap();
    let ts = evaluate(&seq, &mut seg, Protocol::Terraseg, |_| {}).unwrap();
    // Same predictions, vegetation moves from ignored to non-ground.
    assert!(ts.pooled.ignored < gmm.pooled.ignored);
    assert_eq!(ts.pooled.tp, gmm.pooled.tp);
    assert!(ts.pooled.fp >= gmm.pooled.fp);
    assert!(ts.pooled_metrics.miou > 85.0, "{:?}", ts.pooled_metrics);
}

/// Measured: pooled IoU 98.66 single-frame → 98.81 with 2 frames, 98.86 with 3, 4 and 16
/// (frames 1 and 2 gain 0.33 and 0.13 IoU points) on the vendored frames; precision
/// 99.39. The floor is the 2-frame measurement less 0.1.
#[test]
fn multi_frame_is_never_worse_than_single_frame_on_frames_1_and_2() {
    let single = {
        let mut seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
        seq.limit = Some(3);
        let mut cfg = load_config(&hdl64e_preset()).unwrap();
        cfg.history.frames = 1;
        let mut seg = Segmenter::new(cfg).unwrap();
        evaluate(&seq, &mut seg, Protocol::Gmm, |_| {}).unwrap()
    };
    for frames in [2, 4, 16] {
        let mut cfg = load_config(&hdl64e_preset()).unwrap();
        cfg.history.frames = frames;
        let mut seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
        assert!(seq.poses.is_some(), "poses.txt + calib.txt are vendored");
        seq.limit = Some(3);
        let mut seg = Segmenter::new(cfg).unwrap();
        let multi = evaluate(&seq, &mut seg, Protocol::Gmm, |_| {}).unwrap();
        assert_eq!(multi.scans[2].frames_queried, 3.min(frames as usize));
        for i in [1, 2] {
            let (s, m) = (
                single.scans[i].metrics.unwrap(),
                multi.scans[i].metrics.unwrap(),
            );
            eprintln!(
                "N_f {frames}, frame {i}: IoU {:.2} → {:.2}",
                s.iou_ground, m.iou_ground
            );
            assert!(
                m.iou_ground >= s.iou_ground,
                "N_f {frames}, frame {i}: {:.2} < {:.2}",
                m.iou_ground,
                s.iou_ground
            );
            assert!(m.f1 >= s.f1);
        }
        eprintln!(
            "N_f {frames}: pooled IoU {:.2}, precision {:.2}",
            multi.pooled_metrics.iou_ground, multi.pooled_metrics.precision
        );
        assert!(
            multi.pooled_metrics.iou_ground >= 98.71 && multi.pooled_metrics.precision >= 99.3,
            "{:?}",
            multi.pooled_metrics
        );
    }
}

/// Three layouts of the zone model (`zones.layouts = 3`), their probabilities averaged.
/// Measured on frames 0–2: single frame 98.99 pooled ground IoU, precision 99.48 (one
/// layout: 98.66, 99.38); three frames of history 99.04 (98.86), precision 99.46. The floors
/// are these less 0.1. The output is exactly the mean, in layout order, of the three layouts segmented
/// apart (`SegmenterConfig::layout`), and a reversed scan gets the same bits reversed.
#[test]
fn three_layouts_outvote_badly_placed_segment_borders() {
    let mut cfg = load_config(&hdl64e_preset()).unwrap();
    cfg.zones.layouts = 3;
    for (frames, floor, min_precision) in [(1, 98.89, 99.38), (3, 98.94, 99.36)] {
        cfg.history.frames = frames;
        let mut seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
        seq.limit = Some(3);
        let mut seg = Segmenter::new(cfg.clone()).unwrap();
        let m = evaluate(&seq, &mut seg, Protocol::Gmm, |_| {})
            .unwrap()
            .pooled_metrics;
        eprintln!("3 layouts, {frames} frame(s): {m:?}");
        assert!(
            m.iou_ground >= floor,
            "{frames} frame(s): IoU {:.2}",
            m.iou_ground
        );
        assert!(m.precision >= min_precision, "precision {:.2}", m.precision);
    }

    cfg.history.frames = 1;
    let points =
        groundwork_io::read_scan(&kitti_sequence().join("velodyne/000000.bin"), usize::MAX)
            .unwrap()
            .points;
    let mut together = vec![0.0f32; points.len()];
    let mut whole = Segmenter::new(cfg.clone()).unwrap();
    whole.segment(&points, None, &mut together).unwrap();
    let judged: Vec<bool> = whole.judged_points(points.len()).collect();
    let mut mean = vec![0.0f32; points.len()];
    for k in 0..3 {
        let mut p = vec![0.0f32; points.len()];
        // Each layout's equation values: the preset's map comes after their mean.
        let mut layout = cfg.layout(k).unwrap();
        layout.probability.map.clear();
        Segmenter::new(layout)
            .unwrap()
            .segment(&points, None, &mut p)
            .unwrap();
        for (m, v) in mean.iter_mut().zip(&p) {
            *m += v;
        }
    }
    mean.iter_mut().for_each(|m| *m /= 3.0);
    ProbabilityMap::new(&cfg.probability, cfg.ground.ground_threshold).apply(
        &mut mean,
        &judged,
        |&j| j,
    );
    assert_eq!(together, mean, "the layouts' mean, in layout order");
    assert!(together.iter().all(|p| (0.0..=1.0).contains(p)));
    // The layouts disagree somewhere: otherwise they would be one layout three times.
    assert!(
        together
            .iter()
            .any(|&p| p > 0.0 && p < 1.0 && (p * 3.0 - (p * 3.0).round()).abs() > 1e-3)
    );

    let reversed: Vec<_> = points.iter().rev().copied().collect();
    let mut back = vec![0.0f32; points.len()];
    Segmenter::new(cfg)
        .unwrap()
        .segment(&reversed, None, &mut back)
        .unwrap();
    back.reverse();
    assert_eq!(
        back, together,
        "a reversed scan gets the same probabilities, reversed"
    );
}

/// Frame 0 with one return set to (10, 0, 1e20), as a corrupted packet might carry: that
/// point alone gets probability 0 and is counted, no value is NaN, and through the
/// history the next frames are unaffected (they equal a run with that return removed).
#[test]
fn one_absurd_return_poisons_nothing() {
    let cfg = load_config(&hdl64e_preset()).unwrap();
    let seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
    let poses = seq.poses.clone().unwrap();
    let mut poisoned = Segmenter::new(cfg.clone()).unwrap();
    let mut clean = Segmenter::new(cfg).unwrap();
    for (f, (item, pose)) in seq.scans(200_000).zip(&poses).take(3).enumerate() {
        let mut pts = item.scan.unwrap().points;
        let mut removed = pts.clone();
        if f == 0 {
            pts[500] = groundwork_core::Point::new(10.0, 0.0, 1e20);
            // Removed: a point in the near disc, which is never fitted either.
            removed[500] = groundwork_core::Point::new(0.0, 0.0, 0.0);
        }
        let (mut a, mut b) = (vec![0.0; pts.len()], vec![0.0; pts.len()]);
        let r = poisoned.segment(&pts, Some(pose), &mut a).unwrap();
        clean.segment(&removed, Some(pose), &mut b).unwrap();
        assert!(a.iter().all(|p| p.is_finite()), "frame {f}");
        assert_eq!(r.out_of_bounds_points, usize::from(f == 0));
        let differ = a
            .iter()
            .zip(&b)
            .filter(|(x, y)| x.to_bits() != y.to_bits())
            .count();
        assert_eq!(differ, 0, "frame {f}: {differ} probabilities moved");
    }
    assert_eq!(poisoned.counters().out_of_bounds_points, 1);
}

/// The PseudoLabeler and RANSAC on the labeled frames, terraseg protocol (vegetation is
/// non-ground). Measured: PseudoLabeler pooled mIoU 94.13 (98.62 ground IoU in the gmm
/// protocol), RANSAC 90.49; for reference Patchwork++ 91.33 and an independent faithful
/// PseudoLabeler 93.85 on these frames. The floor is 92.5.
#[test]
fn pseudolabeler_pooled_miou_on_frames_0_to_2() {
    use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, Ransac};
    let cfg = load_config(&hdl64e_preset()).unwrap();
    let mut seq = Sequence::open(&kitti_sequence(), None, None).unwrap();
    seq.poses = None;
    seq.limit = Some(3);
    let frame = GroundFrame::from_config(&cfg).unwrap();
    let mut pl = PseudoLabeler::new(Default::default(), frame).unwrap();
    let ts = evaluate(&seq, &mut pl, Protocol::Terraseg, |_| {}).unwrap();
    let mut r = Ransac::new(Default::default(), frame).unwrap();
    let rs = evaluate(&seq, &mut r, Protocol::Terraseg, |_| {}).unwrap();
    let (p, rm) = (ts.pooled_metrics.miou, rs.pooled_metrics.miou);
    eprintln!("terraseg mIoU: pseudolabeler {p:.2}, ransac {rm:.2}");
    assert_eq!(ts.labeled_scans, 3);
    assert!(p >= 92.5, "pooled mIoU {p:.2}");
    assert!(p > rm, "PseudoLabeler {p:.2} vs RANSAC {rm:.2}");
    // Every frame, not only the pool.
    for s in &ts.scans {
        let m = s.metrics.unwrap().miou;
        assert!(m >= 92.0, "scan {}: mIoU {m:.2}", s.name);
    }
}
