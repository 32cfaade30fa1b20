//! Calibrated probabilities: the last step of a scan (docs/accuracy.md, "Reliability").
//!
//! The equation's value (`query::equation`, raised by continuity) orders points well but
//! does not say how often a point is ground: on KITTI no point passes 0.85 and points at
//! 0.5–0.6 are ground 72 % of the time. A monotone map, fitted once on labelled scans of
//! the sensor and shipped with its preset (`[probability] map`), turns it into the fraction
//! of points that are ground. The decision does not move: a point is ground when its
//! equation value reaches `ground.ground_threshold`, and the map's value there is the
//! threshold a user applies to the output ([`ProbabilityMap::threshold`]); the map keeps
//! every point on its side of it, rounding included.

use crate::config::ProbabilityConfig;
use rayon::prelude::*;

/// The map of one configuration, ready to apply.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbabilityMap {
    /// Calibrated values at the equation values 0, 1/(n−1), …, 1 (empty: identity).
    knots: Vec<f32>,
    /// The decision threshold on the equation's value (`ground.ground_threshold`).
    raw_threshold: f32,
    /// Its value under the map: the threshold on the output.
    threshold: f32,
    /// The largest f32 below `threshold`: where every point under the raw threshold ends.
    below: f32,
}

impl ProbabilityMap {
    /// The map of `cfg` around the decision threshold `raw_threshold`. `cfg` must have
    /// passed [`ProbabilityConfig::validate`] (strictly increasing values in [0, 1]).
    pub fn new(cfg: &ProbabilityConfig, raw_threshold: f32) -> Self {
        let mut map = Self {
            knots: cfg.map.clone(),
            raw_threshold,
            threshold: raw_threshold,
            below: raw_threshold,
        };
        map.threshold = map.value(raw_threshold);
        map.below = next_down(map.threshold);
        map
    }

    /// Whether the map changes anything.
    pub fn is_identity(&self) -> bool {
        self.knots.is_empty()
    }

    /// The decision threshold on the output: a point is ground when its output is at least
    /// this (the map's value at `ground.ground_threshold`).
    pub fn threshold(&self) -> f32 {
        self.threshold
    }

    /// The map at one equation value, linear between knots.
    fn value(&self, p: f32) -> f32 {
        let n = self.knots.len();
        if n < 2 {
            return p;
        }
        let last = (n - 1) as f32;
        let t = (p.clamp(0.0, 1.0) * last).min(last);
        // t is in [0, last] (`min` also turns NaN into `last`): converted through u32, the
        // loop vectorises (a conversion to usize does not).
        let i = (t as u32 as usize).min(n - 2);
        let (a, b) = (self.knots[i], self.knots[i + 1]);
        // `min`: a rounded step never passes the next knot (monotone across knots).
        (a + (t - i as f32) * (b - a)).min(b)
    }

    /// Maps every probability of a scan in place, keeping each on its side of the
    /// threshold: a value at or above `ground.ground_threshold` maps to at least
    /// [`ProbabilityMap::threshold`], one below it to less. `marks` has one entry per
    /// point; points the segmenter did not judge (`judged` of their mark false: inside the
    /// near edge or the ego radius, placeholders, beyond the coordinate bound) keep their 0.
    pub fn apply<M: Sync>(&self, out: &mut [f32], marks: &[M], judged: impl Fn(&M) -> bool + Sync) {
        debug_assert_eq!(marks.len(), out.len(), "one mark per point");
        if self.is_identity() {
            return;
        }
        // In parts on the worker threads (each point on its own: the same bits on any).
        const PART: usize = 16 * 1024;
        out.par_chunks_mut(PART)
            .zip(marks.par_chunks(PART))
            .for_each(|(out, marks)| self.apply_part(out, marks, &judged));
    }

    /// [`ProbabilityMap::apply`] on a part of a scan. A function of its own, the marks
    /// zipped with the points: as a closure's body indexing the scan's marks it was not
    /// vectorised (1.8× the instructions).
    fn apply_part<M>(&self, out: &mut [f32], marks: &[M], judged: impl Fn(&M) -> bool) {
        // Both sides worked out and one chosen, without a branch: which side a point is on
        // follows the scene, and a branch on it mispredicted (most of this pass's time).
        for (p, mark) in out.iter_mut().zip(marks) {
            let v = self.value(*p);
            let mapped = if *p >= self.raw_threshold {
                v.max(self.threshold)
            } else {
                v.min(self.below)
            };
            *p = if judged(mark) { mapped } else { *p };
        }
    }
}

/// The largest f32 below `v` (v itself at 0 or below: the map's lowest value is ≥ 0).
fn next_down(v: f32) -> f32 {
    if v > 0.0 {
        f32::from_bits(v.to_bits() - 1)
    } else {
        v
    }
}

/// Fits a map with `knots` values (≥ 2) from equation values and whether each point is
/// ground: the isotonic regression of ground on the value (pool adjacent violators, over
/// the points sorted by value), read at the knots, made strictly increasing by at least
/// `1e-4` a step. Where there are no points, the nearest fitted value holds.
pub fn fit_map(samples: &[(f32, bool)], knots: usize) -> Vec<f32> {
    let knots = knots.max(2);
    let mut sorted: Vec<(f32, bool)> = samples
        .iter()
        .copied()
        .filter(|(p, _)| p.is_finite())
        .collect();
    sorted.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    // Pool adjacent violators over blocks (mean value, ground fraction, weight), points
    // of equal value pooled first.
    let mut blocks: Vec<(f64, f64, f64)> = Vec::new();
    for &(p, g) in &sorted {
        let (p, g) = (f64::from(p), f64::from(u8::from(g)));
        match blocks.last_mut() {
            Some(last) if last.0 == p => {
                last.1 = (last.1 * last.2 + g) / (last.2 + 1.0);
                last.2 += 1.0;
            }
            _ => blocks.push((p, g, 1.0)),
        }
        while blocks.len() >= 2 {
            let (b, a) = (blocks[blocks.len() - 1], blocks[blocks.len() - 2]);
            if a.1 < b.1 {
                break;
            }
            let w = a.2 + b.2;
            blocks.pop();
            *blocks.last_mut().expect("two blocks") =
                ((a.0 * a.2 + b.0 * b.2) / w, (a.1 * a.2 + b.1 * b.2) / w, w);
        }
    }
    let at = |x: f64| -> f64 {
        match blocks.iter().position(|b| b.0 >= x) {
            None => blocks.last().map_or(x, |b| b.1),
            Some(0) => blocks[0].1,
            Some(k) => {
                let (a, b) = (blocks[k - 1], blocks[k]);
                a.1 + (x - a.0) / (b.0 - a.0) * (b.1 - a.1)
            }
        }
    };
    const STEP: f64 = 1e-4;
    let mut values: Vec<f64> = (0..knots)
        .map(|k| at(k as f64 / (knots - 1) as f64).clamp(0.0, 1.0))
        .collect();
    // Strictly increasing: up from the bottom, then down from the top where that passed 1.
    for k in 1..knots {
        values[k] = values[k].max(values[k - 1] + STEP);
    }
    for k in (0..knots).rev() {
        let cap = 1.0 - STEP * (knots - 1 - k) as f64;
        values[k] = values[k].min(cap);
    }
    values
        .iter()
        .map(|&v| (v.max(0.0) * 1e4).round() as f32 / 1e4)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn map(values: &[f32], threshold: f32) -> ProbabilityMap {
        ProbabilityMap::new(
            &ProbabilityConfig {
                map: values.to_vec(),
            },
            threshold,
        )
    }

    /// Expected calibration error over ten bins (`groundwork_io::Reliability` is the
    /// product's; this is the definition, for the tests).
    fn ece(samples: &[(f32, bool)]) -> f64 {
        let mut bins = [(0.0f64, 0.0f64, 0.0f64); 10];
        for &(p, g) in samples {
            let b = &mut bins[((p * 10.0) as usize).min(9)];
            *b = (b.0 + 1.0, b.1 + f64::from(p), b.2 + f64::from(u8::from(g)));
        }
        let n = samples.len() as f64;
        bins.iter().map(|b| (b.1 - b.2).abs() / n).sum()
    }

    #[test]
    fn the_map_is_linear_between_knots_and_moves_the_threshold() {
        let m = map(&[0.0, 0.2, 1.0], 0.5);
        assert_eq!(m.threshold(), 0.2);
        let mut out = [0.0, 0.25, 0.75, 1.0];
        let all = vec![true; out.len()];
        m.apply(&mut out, &all, |&j| j);
        assert_eq!(out[0], 0.0);
        assert!((out[1] - 0.1).abs() < 1e-6);
        assert!((out[2] - 0.6).abs() < 1e-6);
        assert_eq!(out[3], 1.0);
        let id = map(&[], 0.5);
        assert!(id.is_identity());
        assert_eq!(id.threshold(), 0.5);
    }

    #[test]
    fn a_fit_learns_how_often_points_are_ground() {
        // Points at value v are ground with frequency v²: the fit finds v² at the knots.
        let mut samples = Vec::new();
        for i in 0..=100 {
            let v = i as f32 / 100.0;
            let ground = (v * v * 1000.0).round() as usize;
            samples.extend((0..1000).map(|k| (v, k < ground)));
        }
        let values = fit_map(&samples, 11);
        for (k, &y) in values.iter().enumerate() {
            let x = k as f32 / 10.0;
            assert!((y - x * x).abs() < 0.01, "{k}: {y}");
        }
        let mapped: Vec<(f32, bool)> = samples
            .iter()
            .map(|&(p, g)| {
                let mut o = [p];
                map(&values, 0.5).apply(&mut o, &[true], |&j| j);
                (o[0], g)
            })
            .collect();
        assert!(ece(&samples) > 0.1);
        assert!(ece(&mapped) < 0.01, "{}", ece(&mapped));
    }

    #[test]
    fn a_fit_is_strictly_increasing_even_where_the_data_is_not() {
        // All ground, then none: isotonic pools everything; the knots still rise.
        let samples: Vec<(f32, bool)> = (0..100).map(|i| (i as f32 / 100.0, i < 50)).collect();
        let values = fit_map(&samples, 9);
        assert!(values.windows(2).all(|w| w[0] < w[1]), "{values:?}");
        assert!(values.iter().all(|v| (0.0..=1.0).contains(v)));
        assert!(ProbabilityConfig { map: values }.validate().is_ok());
    }

    proptest! {
        /// No point changes side: the output reaches the moved threshold exactly when the
        /// equation's value reached the configured one.
        #[test]
        fn decisions_do_not_change(
            mut steps in proptest::collection::vec(1e-4f32..0.3, 1..40),
            threshold in 0.0f32..=1.0,
            ps in proptest::collection::vec(0.0f32..=1.0, 1..200),
        ) {
            let total: f32 = steps.iter().sum::<f32>() * 1.01;
            let mut acc = 0.0;
            for s in steps.iter_mut() {
                acc += *s / total;
                *s = acc;
            }
            let m = map(&steps, threshold);
            let mut near = ps.clone();
            // Values a rounding bit either side of the threshold, too.
            near.extend([threshold, f32::from_bits(threshold.to_bits().saturating_sub(1)),
                         f32::from_bits(threshold.to_bits() + 1).min(1.0)]);
            let mut out = near.clone();
            let all = vec![true; out.len()];
            m.apply(&mut out, &all, |&j| j);
            for (&p, &o) in near.iter().zip(&out) {
                prop_assert_eq!(p >= threshold, o >= m.threshold(), "{} -> {}", p, o);
                prop_assert!((0.0..=1.0).contains(&o));
            }
            for w in near.iter().zip(&out).collect::<Vec<_>>().windows(2) {
                if w[0].0 < w[1].0 { prop_assert!(w[0].1 <= w[1].1); }
            }
        }

        /// The pass without a branch gives the bits of the plain form it replaced (a point
        /// at a time, a branch on each side, the index through usize), for any value: out
        /// of [0, 1], ±0, NaN, points not judged.
        #[test]
        fn apply_gives_the_bits_of_the_plain_form(
            knots in proptest::collection::vec(0.0f32..1.0, 2..30),
            threshold in 0.0f32..=1.0,
            ps in proptest::collection::vec(prop_oneof![
                4 => -0.5f32..1.5,
                1 => Just(f32::NAN),
                1 => Just(-0.0f32),
                1 => Just(1.0f32),
                1 => any::<f32>(),
            ], 1..300),
            judged in proptest::collection::vec(any::<bool>(), 300),
        ) {
            let mut knots = knots;
            knots.sort_by(f32::total_cmp);
            let m = map(&knots, threshold);
            let plain = |p: f32| {
                let n = m.knots.len();
                let last = (n - 1) as f32;
                let t = (p.clamp(0.0, 1.0) * last).min(last);
                let i = (t as usize).min(n - 2);
                let (a, b) = (m.knots[i], m.knots[i + 1]);
                let v = (a + (t - i as f32) * (b - a)).min(b);
                if p >= m.raw_threshold { v.max(m.threshold) } else { v.min(m.below) }
            };
            let mut out = ps.clone();
            let n = out.len();
            m.apply(&mut out, &judged[..n], |&j| j);
            for (i, (&p, &o)) in ps.iter().zip(&out).enumerate() {
                let want = if judged[i] { plain(p) } else { p };
                prop_assert_eq!(o.to_bits(), want.to_bits(), "{} -> {} not {}", p, o, want);
            }
        }
    }
}
