//! Query time against N_f = 1, 2, 4, 8, 16 fitted frames for KITTI frame 5 (124k points),
//! with the default (regridded) past query, and with the per-frame one at 16 frames
//! (`per_frame/16`).
//!
//! History: the six vendored scans, then copies of them placed 0.8 m apart behind the
//! vehicle (KITTI's speed at 10 Hz) to reach 15 past frames. Frame 5 is fitted once and
//! queried against that fixed history (`query_model_posed` leaves the history alone, so
//! every iteration sees the same realistic spread of past poses); fit time does not depend
//! on N_f.
//!
//! `cargo bench -p groundwork-benches --bench multiframe`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use groundwork_benches::{kitti_frame, kitti_sequence, preset};
use groundwork_core::config::PastQuery;
use groundwork_core::{Pose, Segmenter};
use nalgebra::{Translation3, Vector3};

fn multi_frame(c: &mut Criterion) {
    let seq = kitti_sequence();
    let cam = groundwork_io::read_poses(&seq.join("poses.txt")).expect("poses");
    let tr = groundwork_io::read_calib_tr(&seq.join("calib.txt")).expect("calib");
    let poses = groundwork_io::lidar_poses(&cam, &tr);
    let scans: Vec<_> = (0..6).map(|i| kitti_frame(i).expect("frame")).collect();
    let query_pose = poses[5];
    let mut g = c.benchmark_group("multi_frame_query_kitti_frame5");
    g.sample_size(20);
    let cases = [1u32, 2, 4, 8, 16]
        .map(|nf| (nf, PastQuery::Regridded))
        .into_iter()
        .chain([(16, PastQuery::PerFrame)]);
    for (nf, past) in cases {
        let mut cfg = preset().expect("preset");
        cfg.history.frames = nf;
        cfg.history.query = past;
        let mut seg = Segmenter::new(cfg).expect("config");
        // Oldest first: frame k steps behind the query pose.
        for k in (1..nf as usize).rev() {
            let back =
                Translation3::from(query_pose.rotation * Vector3::new(-0.8 * k as f64, 0.0, 0.0));
            let pose: Pose = back * query_pose;
            let pts = &scans[(6 - (k % 6)) % 6];
            let mut out = vec![0.0; pts.len()];
            seg.segment(pts, Some(&pose), &mut out)
                .expect("history frame");
        }
        let pts = &scans[5];
        let model = seg.fit(pts).expect("fit");
        let mut out = vec![0.0; pts.len()];
        let id = match past {
            PastQuery::Regridded => BenchmarkId::from_parameter(nf),
            PastQuery::PerFrame => BenchmarkId::new("per_frame", nf),
        };
        g.bench_with_input(id, &nf, |b, _| {
            b.iter(|| {
                let frames = seg
                    .query_model_posed(&model, pts, &query_pose, &mut out)
                    .expect("query");
                assert_eq!(frames, nf as usize, "history frames queried");
            })
        });
    }
    g.finish();
}

criterion_group!(benches, multi_frame);
criterion_main!(benches);
