//! The ROS 2 bridge's own work per KITTI scan (frame 0, 124,668 points), beside DDS and
//! shared memory: `cloud_in`, a cloud's CDR into the points the bridge publishes (serde's
//! deserialization as ros2-client does it, `cdr_only`; then the layout checks, the search
//! for placeholders and the copy of every point into a buffer the size of the scan, as
//! into a loaned sample, point by point, `points_only`; the bridge's copy into a zeroed
//! sample, one pass over the records checking the coordinates as it goes,
//! `points_one_pass`), and `answer` (the
//! cloud with `ground_probability`,
//! and the non-ground records).
//!
//! `cargo bench -p groundwork-benches --bench ros2`

use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use groundwork_benches::kitti_frame;
use groundwork_io::Scan;
use groundwork_io::pointcloud2::{CloudPoints, encode, select_records, with_probability};
use groundwork_msg::ScanPoint;
use groundwork_ros2::msg::PointCloud2;

type Le = byteorder::LittleEndian;

fn per_cloud(c: &mut Criterion) {
    let points = kitti_frame(0).expect("vendored frame");
    let n = points.len();
    // A driver's cloud: x, y, z, intensity and (as the recording encoder writes) one more
    // float field; the serde form the DDS reader hands over.
    let probs: Vec<f32> = (0..n).map(|i| (i % 10) as f32 / 10.0).collect();
    let bytes = encode(
        &Scan::dense(points),
        &probs,
        1_700_000_000_000_000_000,
        "velodyne",
    );
    let label = Path::new("bench");
    let mut g = c.benchmark_group("ros2_per_cloud");
    g.sample_size(30);
    let mut sample = vec![ScanPoint::default(); n];
    let mut copy = |view: &groundwork_io::pointcloud2::CloudRef<'_>| {
        let pts = CloudPoints::new(label, view, n).expect("points");
        for (i, out) in sample.iter_mut().enumerate().take(pts.len()) {
            let p = pts.point(i);
            *out = ScanPoint {
                x: p.x,
                y: p.y,
                z: p.z,
                intensity: p.intensity,
            };
        }
        pts.len()
    };
    g.bench_function("cloud_in", |b| {
        b.iter(|| {
            let (msg, _) = cdr_encoding::from_bytes::<PointCloud2, Le>(&bytes[4..]).expect("cdr");
            copy(&msg.view())
        })
    });
    let (msg, _) = cdr_encoding::from_bytes::<PointCloud2, Le>(&bytes[4..]).expect("cdr");
    g.bench_function("cdr_only", |b| {
        b.iter(|| cdr_encoding::from_bytes::<PointCloud2, Le>(&bytes[4..]).expect("cdr"))
    });
    g.bench_function("points_only", |b| b.iter(|| copy(&msg.view())));
    // The bridge's copy: one pass over the records into the (zeroed) sample, checking
    // the coordinates as it goes.
    let mut zeroed = vec![ScanPoint::default(); n];
    g.bench_function("points_one_pass", |b| {
        b.iter(|| {
            zeroed.fill(ScanPoint::default());
            let view = msg.view();
            let pts = CloudPoints::unsearched(label, &view, n).expect("points");
            pts.copy_into(&mut zeroed, ScanPoint::from)
        })
    });
    let keep: Vec<bool> = probs.iter().map(|&p| p < 0.5).collect();
    g.bench_function("answer", |b| {
        b.iter(|| {
            let view = msg.view();
            let with = with_probability(label, &view, &probs, n).expect("points");
            let non = select_records(label, &view, &keep, n).expect("nonground");
            (with, non)
        })
    });
    g.finish();
}

criterion_group!(benches, per_cloud);
criterion_main!(benches);
