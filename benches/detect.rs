//! The fallback detector per KITTI scan (frames 0–2, ~124k points): ground removal,
//! clustering and boxes from the GMM's probabilities, with the GMM segmenter's own time
//! (fit + query, single frame) beside it.
//!
//! `cargo bench -p groundwork-benches --bench detect`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use groundwork_benches::{kitti_frame, preset};
use groundwork_core::Segmenter;
use groundwork_detect::{Detections, Detector};

fn per_scan(c: &mut Criterion) {
    let cfg = preset().expect("preset");
    let mut seg = Segmenter::new(cfg.clone()).expect("valid preset");
    let mut det = Detector::new(Default::default(), &cfg).expect("defaults");
    let mut g = c.benchmark_group("detect_per_scan");
    g.sample_size(30);
    for n in 0..3 {
        let points = kitti_frame(n).expect("vendored frame");
        let mut probs = vec![0.0f32; points.len()];
        seg.segment(&points, None, &mut probs).expect("segment");
        let mut out = Detections::default();
        g.bench_with_input(BenchmarkId::new("detector", n), &points, |b, p| {
            b.iter(|| det.detect(p, &probs, &mut out).expect("detect"))
        });
        let mut scratch = vec![0.0f32; points.len()];
        g.bench_with_input(BenchmarkId::new("segmenter", n), &points, |b, p| {
            b.iter(|| seg.segment(p, None, &mut scratch).expect("segment"))
        });
    }
    g.finish();
}

criterion_group!(benches, per_scan);
criterion_main!(benches);
