//! The offline methods per scan on KITTI frames 0–2: the PseudoLabeler (fit on fresh
//! 4096-point mini-batches, then labels and pillars) and RANSAC, each with all threads.
//! Throughput with several scans at once is `groundwork label`'s summary (docs/offline-labels.md).
//!
//! `cargo bench -p groundwork-benches --bench pseudolabel`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use groundwork_benches::{kitti_frame, preset};
use groundwork_pseudolabel::{GroundFrame, PseudoLabeler, Ransac};

fn per_scan(c: &mut Criterion) {
    let cfg = preset().expect("preset");
    let frame = GroundFrame::from_config(&cfg).expect("mount");
    let pl = PseudoLabeler::new(Default::default(), frame).expect("defaults");
    let ransac = Ransac::new(Default::default(), frame).expect("defaults");
    let mut g = c.benchmark_group("offline_per_scan");
    g.sample_size(10);
    for n in 0..3 {
        let points = kitti_frame(n).expect("vendored frame");
        let mut out = vec![0.0f32; points.len()];
        g.bench_with_input(BenchmarkId::new("pseudolabeler", n), &points, |b, p| {
            b.iter(|| pl.label(p, &mut out).expect("label"))
        });
        g.bench_with_input(BenchmarkId::new("ransac", n), &points, |b, p| {
            b.iter(|| ransac.label(p, &mut out).expect("label"))
        });
    }
    g.finish();
}

criterion_group!(benches, per_scan);
criterion_main!(benches);
