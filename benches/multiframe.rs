//! Query time against N_f = 1, 2, 4, 8, 16 fitted frames for KITTI frame 5 (124k points),
//! with the default (regridded) past query, and with the per-frame one at 16 frames
//! (`per_frame/16`).
//!
//! History: see [`Frame5WithHistory`] (the vendored scans placed 0.8 m apart behind frame
//! 5, queried against that fixed history); fit time does not depend on N_f. On a noisy VM
//! the extra time of N_f frames over one is better measured with the two queries
//! alternating: `query-extra` (`benches/src/bin/query_extra.rs`).
//!
//! `cargo bench -p groundwork-benches --bench multiframe`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use groundwork_benches::Frame5WithHistory;
use groundwork_core::config::PastQuery;

fn multi_frame(c: &mut Criterion) {
    let mut g = c.benchmark_group("multi_frame_query_kitti_frame5");
    g.sample_size(20);
    let cases = [1u32, 2, 4, 8, 16]
        .map(|nf| (nf, PastQuery::Regridded))
        .into_iter()
        .chain([(16, PastQuery::PerFrame)]);
    for (nf, past) in cases {
        let mut scene = Frame5WithHistory::new(nf, past).expect("history");
        let mut out = vec![0.0; scene.points.len()];
        let id = match past {
            PastQuery::Regridded => BenchmarkId::from_parameter(nf),
            PastQuery::PerFrame => BenchmarkId::new("per_frame", nf),
        };
        g.bench_with_input(id, &nf, |b, _| {
            b.iter(|| {
                let frames = scene.query(&mut out).expect("query");
                assert_eq!(frames, nf as usize, "history frames queried");
            })
        });
    }
    g.finish();
}

criterion_group!(benches, multi_frame);
criterion_main!(benches);
