//! Stable decisions: the same scene gives the same ground. A rounding error in the input
//! (one ulp on every coordinate, the digits a text format keeps) must not move the labels;
//! a permuted scan gives the same probabilities, permuted. Measured on the real labeled
//! frames 0–2 and on synthetic scenes; `-- --nocapture` prints the figures.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test

use groundwork_core::config::MountConfig;
use groundwork_core::{GroundMethod, Point, Segmenter, SegmenterConfig};
use groundwork_io::{load_config, read_scan, sensor_preset};
use groundwork_synth::{Generator, SynthConfig};
use groundwork_tests::{SceneKind, hdl64e_preset, kitti_sequence, synthetic};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_distr::{Distribution, Normal};

fn hdl64e_single_frame() -> SegmenterConfig {
    let mut cfg = load_config(&hdl64e_preset()).unwrap();
    cfg.history.frames = 1;
    cfg
}

fn frame(i: usize) -> Vec<Point> {
    let path = kitti_sequence().join(format!("velodyne/{i:06}.bin"));
    read_scan(&path, usize::MAX).unwrap().points
}

/// Single-frame probabilities from a fresh segmenter (no height-filter state).
fn probabilities(cfg: &SegmenterConfig, points: &[Point]) -> Vec<f32> {
    let mut seg = Segmenter::new(cfg.clone()).unwrap();
    let mut p = vec![0.0; points.len()];
    seg.segment_scan(points, None, &mut p).unwrap();
    p
}

/// How two runs over the same points differ.
#[derive(Debug, Clone, Copy, Default)]
struct Change {
    points: usize,
    /// Ground decisions that differ.
    flipped: usize,
    /// Probabilities that differ by more than 0.01.
    moved: usize,
    /// Largest probability difference.
    max: f32,
}

impl Change {
    fn between(a: &[f32], b: &[f32], threshold: f32) -> Self {
        assert_eq!(a.len(), b.len());
        let mut c = Change {
            points: a.len(),
            ..Default::default()
        };
        for (&p, &q) in a.iter().zip(b) {
            c.flipped += usize::from((p >= threshold) != (q >= threshold));
            let d = (p - q).abs();
            c.moved += usize::from(d > 0.01);
            c.max = c.max.max(d);
        }
        c
    }

    /// Adds another run's counts (pooled over scans).
    fn merge(&mut self, other: Change) {
        self.points += other.points;
        self.flipped += other.flipped;
        self.moved += other.moved;
        self.max = self.max.max(other.max);
    }

    fn flip_rate(&self) -> f64 {
        100.0 * self.flipped as f64 / self.points as f64
    }

    fn moved_rate(&self) -> f64 {
        100.0 * self.moved as f64 / self.points as f64
    }
}

/// Every coordinate one ulp up (`np.nextafter(x, inf)` on the f32 scan): about 4e-6 m at
/// 50 m, far below any sensor's noise.
fn one_ulp_up(points: &[Point]) -> Vec<Point> {
    points
        .iter()
        .map(|p| Point {
            x: p.x.next_up(),
            y: p.y.next_up(),
            z: p.z.next_up(),
            ..*p
        })
        .collect()
}

/// How one ulp on every coordinate changes the probabilities of `points`, printed.
fn one_ulp_change(cfg: &SegmenterConfig, points: &[Point], what: &str) -> Change {
    let c = Change::between(
        &probabilities(cfg, points),
        &probabilities(cfg, &one_ulp_up(points)),
        cfg.decision_threshold(),
    );
    eprintln!(
        "{what}: one ulp: {} flipped ({:.3} %), {} moved > 0.01 ({:.3} %), max {:.4}",
        c.flipped,
        c.flip_rate(),
        c.moved,
        c.moved_rate(),
        c.max
    );
    c
}

/// One ulp flips at most 0.05 % of the decisions and moves no probability by more than 0.01.
const MAX_FLIP_PERCENT: f64 = 0.05;
const MAX_CHANGE: f32 = 0.01;

#[test]
fn one_ulp_on_every_coordinate_does_not_move_the_ground_of_frames_0_to_2() {
    let cfg = hdl64e_single_frame();
    for i in 0..3 {
        let c = one_ulp_change(&cfg, &frame(i), &format!("frame {i}"));
        assert!(c.flip_rate() <= MAX_FLIP_PERCENT, "frame {i}: {c:?}");
        assert!(c.max <= MAX_CHANGE, "frame {i}: {c:?}");
    }
}

/// The synthetic scenes turned about the vertical by `yaw` (radians).
fn turned(points: &[Point], yaw: f32) -> Vec<Point> {
    let (s, c) = yaw.sin_cos();
    points
        .iter()
        .map(|p| Point {
            x: c * p.x - s * p.y,
            y: s * p.x + c * p.y,
            ..*p
        })
        .collect()
}

/// The generator casts its rays at whole multiples of 0.18°, so about a thousand points of
/// every scan lie exactly on a sector boundary (every 22.5°), where the last bit of a
/// coordinate decides the segment — a real sensor's azimuths do not line up like that.
/// Turned by a few hundredths of a degree, the scenes test the segmenter, not that
/// coincidence (untouched, one ulp flips about 0.1 % of the urban scene's decisions:
/// whole segments gain or lose their boundary points).
#[test]
fn one_ulp_on_every_coordinate_does_not_move_the_ground_of_synthetic_scenes() {
    let cfg = hdl64e_single_frame();
    for scene in SceneKind::ALL {
        let generator = synthetic("hdl64e", scene, 1, None);
        for yaw in [0.0003, 0.001, 0.003, 0.01] {
            let points = turned(&generator.scan(0).points, yaw);
            let c = one_ulp_change(&cfg, &points, &format!("{scene:?} turned {yaw} rad"));
            assert!(c.flip_rate() <= MAX_FLIP_PERCENT, "{scene:?} {yaw}: {c:?}");
            // Measured: one case moves a segment's points at all, the urban scene turned
            // 0.01 rad: 47 probabilities by more than 0.01 (0.038 %), the largest 0.0204,
            // elsewhere below 0.001 (2026-12-07, cars standing tilted on the street; with
            // upright cars the parking scene turned 0.01 rad moved 30, by up to 0.013).
            assert!(
                c.moved_rate() <= 0.05 && c.max <= 2.5 * MAX_CHANGE,
                "{scene:?} {yaw}: {c:?}"
            );
        }
    }
}

#[test]
fn a_permuted_scan_gives_the_same_probabilities_permuted() {
    let cfg = hdl64e_single_frame();
    let points = frame(1);
    let want = probabilities(&cfg, &points);
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.shuffle(&mut rand::rngs::StdRng::seed_from_u64(41));
    let permuted: Vec<Point> = order.iter().map(|&i| points[i]).collect();
    let got = probabilities(&cfg, &permuted);
    for (k, &i) in order.iter().enumerate() {
        assert_eq!(
            got[k].to_bits(),
            want[i].to_bits(),
            "point {i} (at {k} after the shuffle)"
        );
    }
}

/// 1 mm of Gaussian noise on every coordinate is the method's true sensitivity (a sensor's
/// own noise is 1–2 cm). Measured 0.49 % on the subsample (the coordinate-bit hash that
/// chose the fit points before, d0f8323, flipped 1.11 % with the same draws, and the bound
/// keeps it below that); on summary cells 0.088 %, the probabilities moved by more than
/// 0.01 falling from 13.1 % to 1.9 % of the points.
#[test]
fn one_millimetre_of_jitter_flips_fewer_decisions_than_before() {
    for (cells, bar) in [([0.0, 0.0], 1.0), ([0.6, 0.12], 0.2)] {
        let mut cfg = hdl64e_single_frame();
        cfg.gmm.summary_cell = cells;
        let thr = cfg.decision_threshold();
        let noise = Normal::new(0.0f32, 0.001).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut total = Change::default();
        for i in 0..3 {
            let points = frame(i);
            let base = probabilities(&cfg, &points);
            for _ in 0..2 {
                let jittered: Vec<Point> = points
                    .iter()
                    .map(|p| Point {
                        x: p.x + noise.sample(&mut rng),
                        y: p.y + noise.sample(&mut rng),
                        z: p.z + noise.sample(&mut rng),
                        ..*p
                    })
                    .collect();
                total.merge(Change::between(&base, &probabilities(&cfg, &jittered), thr));
            }
        }
        eprintln!(
            "1 mm jitter, frames 0-2, 2 draws each, summary cells {cells:?}: {:.3} % \
             flipped, {:.3} % moved > 0.01",
            total.flip_rate(),
            total.moved_rate()
        );
        assert!(total.flip_rate() < bar, "{cells:?}: {total:?}");
    }
}

/// A mount told a two-hundredth of a degree differently turns the scan about the sensor:
/// points move by up to half a millimetre against each other within a near segment. A
/// dense segment fitted on its subsample of 2 cm cubes then sees about 2 % of its points
/// cross a cube face (a drawn cube's point leaves the fit, an undrawn one's joins), and EM
/// can settle in another optimum: on a Pandar64 street (mounted 0.8 m high, pitched 6°)
/// 3,272 decisions flip over six scans (0.49 %), 1,174 in one (a segment's road component
/// merging with a car's side). Fitted on summary cells of every point
/// (`gmm.summary_cell`), a point's move shifts its cell's moments by a fraction of it:
/// 145 (0.022 %), 131 of them in one scan, where a segment whose points change (across a
/// ring boundary) is fitted from another start.
#[test]
fn a_mount_a_two_hundredth_of_a_degree_off_moves_few_decisions_on_summaries() {
    let mount = |pitch_deg: f64| MountConfig {
        height: 0.8,
        pitch: pitch_deg.to_radians(),
        ..MountConfig::default()
    };
    let synth = SynthConfig::new("pandar64", mount(6.0), SceneKind::Urban, 0).unwrap();
    let generator = Generator::new(synth, 6).unwrap();
    let scans: Vec<Vec<Point>> = (0..6).map(|i| generator.scan(i).points).collect();
    let flips = |cells: [f64; 2]| {
        let mut cfg = sensor_preset("pandar64").unwrap();
        cfg.history.frames = 1;
        cfg.gmm.summary_cell = cells;
        let told = |pitch_deg: f64| {
            let mut cfg = cfg.clone();
            cfg.sensor.mount = mount(pitch_deg);
            cfg
        };
        let (a, b) = (told(6.0), told(6.005));
        let mut total = Change::default();
        for points in &scans {
            total.merge(Change::between(
                &probabilities(&a, points),
                &probabilities(&b, points),
                cfg.decision_threshold(),
            ));
        }
        total
    };
    let subsample = flips([0.0, 0.0]);
    let summaries = flips([0.6, 0.12]);
    eprintln!(
        "pitch told 6.000 vs 6.005 deg, six Pandar64 street scans: {} decisions flipped on \
         the subsample, {} on summaries (of {})",
        subsample.flipped, summaries.flipped, summaries.points
    );
    assert!(summaries.flip_rate() < 0.05, "{summaries:?}");
}
