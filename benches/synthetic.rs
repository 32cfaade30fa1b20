//! Segmentation time of synthetic scans from 10k to 262k points (`groundwork-synth`, urban
//! scene, frame 0), each with its sensor's preset, single frame.
//!
//! `cargo bench -p groundwork-benches --bench synthetic`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use groundwork_core::Segmenter;
use groundwork_io::sensor_preset;
use groundwork_synth::{BeamPattern, Generator, Scanning, SceneKind, SynthConfig};

/// A change to a preset's beam pattern.
type Adjust = fn(&mut BeamPattern);

/// (preset, pattern adjustment): a Livox Mid-40-like 10 000-point frame, a VLP-16 at
/// 20 Hz, an HDL-64E, and an OS1-128 at 2048 columns (262 144 points, placeholders
/// included).
fn scans() -> Vec<(String, Vec<groundwork_core::Point>)> {
    let sensors: [(&str, Adjust); 4] = [
        ("livox", |p| {
            if let Scanning::Rosette { points, .. } = &mut p.scanning {
                *points = 10_000;
            }
        }),
        ("vlp16", |p| {
            if let Scanning::Spinning { columns, .. } = &mut p.scanning {
                *columns = 900;
            }
        }),
        ("hdl64e", |_| {}),
        ("os1-128", |_| {}),
    ];
    sensors
        .iter()
        .map(|(name, adjust)| {
            let preset = sensor_preset(name).expect("preset");
            let mut cfg =
                SynthConfig::new(name, preset.sensor.mount, SceneKind::Urban, 1).expect("pattern");
            adjust(&mut cfg.pattern);
            let scan = Generator::new(cfg, 1).expect("generator").scan(0);
            (name.to_string(), scan.points)
        })
        .collect()
}

fn synthetic(c: &mut Criterion) {
    let mut g = c.benchmark_group("synthetic_urban");
    g.sample_size(20);
    for (name, points) in scans() {
        let mut cfg = sensor_preset(&name).expect("preset");
        cfg.history.frames = 1;
        let mut seg = Segmenter::new(cfg).expect("valid preset");
        let mut out = vec![0.0f32; points.len()];
        g.bench_with_input(
            BenchmarkId::new(name, points.len()),
            &points,
            |b, points| b.iter(|| seg.segment(points, None, &mut out).expect("segment")),
        );
    }
    g.finish();
}

criterion_group!(benches, synthetic);
criterion_main!(benches);
