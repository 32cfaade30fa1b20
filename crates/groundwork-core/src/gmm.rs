//! One segment's Gaussian mixture, fitted with EM (paper §III-B).
//!
//! Choices where the paper is silent (see also README "Choices"):
//! - EM stops after `max_iterations` or as soon as the mean log-likelihood per point
//!   improves by less than `tolerance`; that per-segment test lets easy segments stop
//!   after two or three iterations while hard ones get up to the cap.
//! - `covariance_regularization` is added to the diagonal after every M-step, so no
//!   component becomes singular (planar patches, repeated points, tiny segments).
//! - Pruning follows the paper: after every iteration, components that are the most
//!   likely one for fewer than τ_N points are removed. A segment with fewer than τ_N points
//!   therefore ends with no component, i.e. no model: its points get probability 0 in a
//!   single-frame query (older frames may still answer for them in a multi-frame query).
//! - Work is done on coordinates relative to the segment centroid, so second moments do
//!   not lose precision to catastrophic cancellation far from the sensor.

use crate::config::GmmConfig;

const LN_2PI: f64 = 1.837_877_066_409_345_5;

/// A symmetric 3×3 matrix stored as its upper triangle: xx, xy, xz, yy, yz, zz.
pub type Sym3 = [f64; 6];

/// A fitted Gaussian component (in the frame the points were given in).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gaussian {
    /// Mixture weight π.
    pub weight: f64,
    /// Mean μ.
    pub mean: [f64; 3],
    /// Covariance Σ (regularised).
    pub covariance: Sym3,
}

/// Outcome of fitting one segment.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SegmentFit {
    /// Surviving components (may be empty: see the module notes).
    pub components: Vec<Gaussian>,
    /// EM iterations run.
    pub iterations: u32,
    /// Mean log-likelihood per point after the last iteration.
    pub mean_log_likelihood: f64,
}

/// Inverse and log-determinant of a symmetric positive-definite 3×3 matrix, or `None` if it
/// is not positive definite.
pub fn sym3_inverse(m: &Sym3) -> Option<(Sym3, f64)> {
    let [a, b, c, d, e, f] = *m;
    // Cofactors of [[a b c] [b d e] [c e f]].
    let c00 = d * f - e * e;
    let c01 = c * e - b * f;
    let c02 = b * e - c * d;
    let det = a * c00 + b * c01 + c * c02;
    if !(det > 0.0 && det.is_finite() && a > 0.0) {
        return None;
    }
    let c11 = a * f - c * c;
    let c12 = b * c - a * e;
    let c22 = a * d - b * b;
    let inv = 1.0 / det;
    Some((
        [
            c00 * inv,
            c01 * inv,
            c02 * inv,
            c11 * inv,
            c12 * inv,
            c22 * inv,
        ],
        det.ln(),
    ))
}

/// Mahalanobis form dᵀ P d for a symmetric P stored as its upper triangle.
#[inline(always)]
pub fn quad_form(p: &Sym3, dx: f64, dy: f64, dz: f64) -> f64 {
    p[0] * dx * dx
        + p[3] * dy * dy
        + p[5] * dz * dz
        + 2.0 * (p[1] * dx * dy + p[2] * dx * dz + p[4] * dy * dz)
}

/// Component parameters prepared for evaluating log(π·N(x | μ, Σ)).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Evaluator {
    pub mean: [f64; 3],
    pub precision: Sym3,
    /// ln π − ½ ln|Σ| − (3/2) ln 2π
    pub log_coef: f64,
}

impl Evaluator {
    /// `None` when the covariance is not positive definite or the weight is not positive.
    pub fn new(g: &Gaussian) -> Option<Self> {
        let (precision, log_det) = sym3_inverse(&g.covariance)?;
        if !(g.weight > 0.0) {
            return None;
        }
        Some(Self {
            mean: g.mean,
            precision,
            log_coef: g.weight.ln() - 0.5 * log_det - 1.5 * LN_2PI,
        })
    }

    /// Unit covariance at the component's mean, for a component whose covariance is unusable.
    pub fn unit(g: &Gaussian) -> Self {
        Self {
            mean: g.mean,
            precision: [1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
            log_coef: g.weight.max(1e-300).ln() - 1.5 * LN_2PI,
        }
    }

    #[inline(always)]
    pub fn log_density(&self, x: f64, y: f64, z: f64) -> f64 {
        let q = quad_form(
            &self.precision,
            x - self.mean[0],
            y - self.mean[1],
            z - self.mean[2],
        );
        self.log_coef - 0.5 * q
    }
}

/// Running sums of one component's sufficient statistics for the M-step.
#[derive(Debug, Clone, Copy, Default)]
struct Moments {
    n: f64,
    s: [f64; 3],
    ss: Sym3,
    /// Points for which this component is the most likely one.
    owned: u32,
}

/// Fits a GMM to one segment's points (structure of arrays, equal lengths) by EM.
/// Returns no components for an empty segment.
pub fn fit_segment(xs: &[f64], ys: &[f64], zs: &[f64], cfg: &GmmConfig) -> SegmentFit {
    let n = xs.len();
    debug_assert!(ys.len() == n && zs.len() == n);
    if n == 0 {
        return SegmentFit::default();
    }
    let nf = n as f64;
    let centroid = [
        xs.iter().sum::<f64>() / nf,
        ys.iter().sum::<f64>() / nf,
        zs.iter().sum::<f64>() / nf,
    ];
    let (zmin, zmax) = zs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &z| {
            (lo.min(z), hi.max(z))
        });
    let reg = cfg.covariance_regularization;

    // Initialisation (paper §III-B1): K = min(ceil(N / N_min), K_max) components at the
    // horizontal mean, spread linearly in z from the lowest to the highest point, equal
    // weights, unit covariance.
    let k0 = n.div_ceil(cfg.n_min as usize).min(cfg.k_max as usize).max(1);
    let mut comps: Vec<Gaussian> = (0..k0)
        .map(|k| {
            let t = if k0 == 1 {
                0.5
            } else {
                k as f64 / (k0 - 1) as f64
            };
            Gaussian {
                weight: 1.0 / k0 as f64,
                mean: [0.0, 0.0, zmin + t * (zmax - zmin) - centroid[2]],
                covariance: [1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
            }
        })
        .collect();

    let mut evals: Vec<Evaluator> = Vec::with_capacity(k0);
    let mut moments: Vec<Moments> = vec![Moments::default(); k0];
    let mut logp: Vec<f64> = vec![0.0; k0];
    let mut prev_ll = f64::NEG_INFINITY;
    let mut mean_ll = f64::NEG_INFINITY;
    let mut iterations = 0;

    for _ in 0..cfg.max_iterations {
        iterations += 1;
        evals.clear();
        // With reg > 0 every covariance is positive definite; should rounding ever break
        // that, the component falls back to unit covariance instead of poisoning EM.
        evals.extend(
            comps
                .iter()
                .map(|g| Evaluator::new(g).unwrap_or_else(|| Evaluator::unit(g))),
        );
        let k = evals.len();
        moments[..k].fill(Moments::default());
        let mut ll = 0.0;

        // E-step fused with the accumulation of the M-step's sums: one pass over the points.
        for i in 0..n {
            let (x, y, z) = (xs[i] - centroid[0], ys[i] - centroid[1], zs[i] - centroid[2]);
            let mut best = 0;
            let mut max = f64::NEG_INFINITY;
            for (c, e) in evals.iter().enumerate() {
                let l = e.log_density(x, y, z);
                logp[c] = l;
                if l > max {
                    max = l;
                    best = c;
                }
            }
            let mut sum = 0.0;
            for l in &mut logp[..k] {
                *l = (*l - max).exp();
                sum += *l;
            }
            ll += max + sum.ln();
            let inv = 1.0 / sum;
            for (c, m) in moments[..k].iter_mut().enumerate() {
                let r = logp[c] * inv;
                m.n += r;
                let (rx, ry, rz) = (r * x, r * y, r * z);
                m.s[0] += rx;
                m.s[1] += ry;
                m.s[2] += rz;
                m.ss[0] += rx * x;
                m.ss[1] += rx * y;
                m.ss[2] += rx * z;
                m.ss[3] += ry * y;
                m.ss[4] += ry * z;
                m.ss[5] += rz * z;
            }
            moments[best].owned += 1;
        }

        // M-step (closed form, paper eq. 2), then pruning of weakly supported components.
        let mut next = Vec::with_capacity(k);
        for m in &moments[..k] {
            if m.owned < cfg.tau_n || m.n < 1e-9 {
                continue;
            }
            let inv = 1.0 / m.n;
            let mu = [m.s[0] * inv, m.s[1] * inv, m.s[2] * inv];
            let cov = [
                m.ss[0] * inv - mu[0] * mu[0] + reg,
                m.ss[1] * inv - mu[0] * mu[1],
                m.ss[2] * inv - mu[0] * mu[2],
                m.ss[3] * inv - mu[1] * mu[1] + reg,
                m.ss[4] * inv - mu[1] * mu[2],
                m.ss[5] * inv - mu[2] * mu[2] + reg,
            ];
            next.push(Gaussian {
                weight: m.n / nf,
                mean: mu,
                covariance: cov,
            });
        }
        let pruned = next.len() != comps.len();
        if pruned {
            // Removed components' mass is shared out so the weights still sum to one.
            let total: f64 = next.iter().map(|g| g.weight).sum();
            if total > 0.0 {
                for g in &mut next {
                    g.weight /= total;
                }
            }
        }
        comps = next;
        mean_ll = ll / nf;
        if comps.is_empty() {
            break;
        }
        // The convergence test only compares like with like: not across a pruning step.
        if !pruned && (mean_ll - prev_ll).abs() < cfg.tolerance {
            break;
        }
        prev_ll = mean_ll;
    }

    for g in &mut comps {
        for (m, c) in g.mean.iter_mut().zip(centroid) {
            *m += c;
        }
    }
    SegmentFit {
        components: comps,
        iterations,
        mean_log_likelihood: mean_ll,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    fn sample(
        rng: &mut rand::rngs::StdRng,
        n: usize,
        mean: [f64; 3],
        std: [f64; 3],
        out: &mut [Vec<f64>; 3],
    ) {
        for d in 0..3 {
            let dist = Normal::new(mean[d], std[d]).unwrap();
            for _ in 0..n {
                out[d].push(dist.sample(rng));
            }
        }
    }

    #[test]
    fn em_recovers_a_sampled_two_gaussian_mixture() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        // A flat "road" patch and a compact "object" 1.5 m above it, 3:1 in points.
        sample(&mut rng, 3000, [10.0, 2.0, -1.7], [1.0, 1.0, 0.03], &mut pts);
        sample(&mut rng, 1000, [10.5, 2.5, -0.2], [0.3, 0.3, 0.4], &mut pts);
        let cfg = GmmConfig {
            k_max: 2,
            max_iterations: 100,
            tolerance: 1e-9,
            ..GmmConfig::default()
        };
        let fit = fit_segment(&pts[0], &pts[1], &pts[2], &cfg);
        assert_eq!(fit.components.len(), 2);
        let mut c = fit.components.clone();
        c.sort_by(|a, b| a.mean[2].total_cmp(&b.mean[2]));
        let (road, obj) = (c[0], c[1]);
        assert!((road.weight - 0.75).abs() < 0.02, "{road:?}");
        assert!((road.mean[2] + 1.7).abs() < 0.01, "{road:?}");
        assert!((road.mean[0] - 10.0).abs() < 0.1);
        assert!((road.covariance[5] - 0.03f64.powi(2) - 1e-4).abs() < 3e-4);
        assert!((road.covariance[0] - 1.0).abs() < 0.1);
        assert!((obj.mean[2] + 0.2).abs() < 0.05, "{obj:?}");
        assert!((obj.covariance[5] - 0.16).abs() < 0.03, "{obj:?}");
        assert!((obj.covariance[0] - 0.09).abs() < 0.02, "{obj:?}");
    }

    #[test]
    fn weakly_supported_components_are_pruned_and_tiny_segments_have_no_model() {
        let cfg = GmmConfig::default();
        // 9 points < τ_N = 10: the single component is pruned.
        let xs: Vec<f64> = (0..9).map(|i| i as f64 * 0.1).collect();
        let fit = fit_segment(&xs, &xs, &vec![0.0; 9], &cfg);
        assert!(fit.components.is_empty());
        // Empty segment: nothing to fit.
        assert!(fit_segment(&[], &[], &[], &cfg).components.is_empty());
        // 200 points all on one flat patch: 8 components start, the weak ones go, and the
        // survivors each own at least τ_N points.
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(&mut rng, 200, [5.0, 0.0, 0.0], [1.0, 1.0, 0.01], &mut pts);
        let fit = fit_segment(&pts[0], &pts[1], &pts[2], &cfg);
        assert!(!fit.components.is_empty() && fit.components.len() < 8);
        let w: f64 = fit.components.iter().map(|g| g.weight).sum();
        assert!((w - 1.0).abs() < 1e-9);
    }

    #[test]
    fn degenerate_points_stay_finite_thanks_to_the_regulariser() {
        // 50 identical points: the covariance would be zero without regularisation.
        let fit = fit_segment(&[3.0; 50], &[1.0; 50], &[-1.0; 50], &GmmConfig::default());
        assert_eq!(fit.components.len(), 1);
        let g = fit.components[0];
        assert!(g.covariance.iter().all(|v| v.is_finite()));
        assert!((g.covariance[0] - 1e-4).abs() < 1e-9);
        assert!(sym3_inverse(&g.covariance).is_some());
    }

    #[test]
    fn converged_segments_stop_early() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(&mut rng, 15, [5.0, 0.0, 0.0], [1.0, 1.0, 0.01], &mut pts);
        let fit = fit_segment(&pts[0], &pts[1], &pts[2], &GmmConfig::default());
        // One component: the second iteration reproduces the first's log-likelihood.
        assert_eq!(fit.components.len(), 1);
        assert!(fit.iterations <= 3, "{}", fit.iterations);
    }

    #[test]
    fn sym3_inverse_matches_identity() {
        let m = [4.0, 1.0, 0.5, 3.0, 0.2, 2.0];
        let (p, logdet) = sym3_inverse(&m).unwrap();
        let full = |s: &Sym3| [[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]];
        let (a, b) = (full(&m), full(&p));
        for i in 0..3 {
            for j in 0..3 {
                let v: f64 = (0..3).map(|k| a[i][k] * b[k][j]).sum();
                assert!((v - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        let det = 4.0 * (3.0 * 2.0 - 0.04) - 1.0 * (2.0 - 0.1) + 0.5 * (0.2 - 1.5);
        assert!((logdet - f64::ln(det)).abs() < 1e-12);
        assert!(sym3_inverse(&[1.0, 2.0, 0.0, 1.0, 0.0, 1.0]).is_none());
    }
}
