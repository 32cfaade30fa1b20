//! Single-frame segmentation of KITTI frame 0 (124,668 points), split into fit and query.
//!
//! `cargo bench -p groundwork-benches --bench segment`

use criterion::{Criterion, criterion_group, criterion_main};
use groundwork_benches::{kitti_frame, preset};
use groundwork_core::Segmenter;

fn single_frame(c: &mut Criterion) {
    let points = kitti_frame(0).expect("vendored frame 0");
    let cfg = preset().expect("preset");
    let mut seg = Segmenter::new(cfg).expect("valid preset");
    let mut out = vec![0.0f32; points.len()];
    let mut g = c.benchmark_group("kitti_frame0_124668pts");
    g.sample_size(50);
    g.bench_function("fit", |b| b.iter(|| seg.fit(&points).expect("fit")));
    // The paper's segment-wide elevation reference, for the cost of the terrain-following
    // one (`ground.elevation_window`) in the same run.
    let mut wide = preset().expect("preset");
    wide.ground.elevation_window = 0.0;
    let mut seg_wide = Segmenter::new(wide).expect("valid preset");
    g.bench_function("fit_segment_wide_reference", |b| {
        b.iter(|| seg_wide.fit(&points).expect("fit"))
    });
    let model = seg.fit(&points).expect("fit");
    g.bench_function("query", |b| {
        b.iter(|| seg.query_model(&model, &points, &mut out).expect("query"))
    });
    g.bench_function("fit+query", |b| {
        b.iter(|| seg.segment(&points, None, &mut out).expect("segment"))
    });
    g.finish();
}

criterion_group!(benches, single_frame);
criterion_main!(benches);
