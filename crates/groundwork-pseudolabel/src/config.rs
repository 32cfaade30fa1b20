//! Every parameter of the PseudoLabeler and of RANSAC, with the TerraSeg paper's values as
//! defaults where it gives one. TOML sections `[pseudolabeler]` and `[ransac]`; unknown keys
//! are errors.

use groundwork_core::ConfigError;
use serde::{Deserialize, Serialize};

/// TerraSeg's PseudoLabeler (§3.3): a per-scan MLP elevation map g(x, y).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PseudoLabelerConfig {
    /// Hidden layer widths of the MLP (input 2, output 1, SiLU between).
    pub hidden: Vec<usize>,
    /// Points drawn afresh (uniformly, with replacement) for each iteration.
    pub batch_size: usize,
    /// AdamW learning rate.
    pub learning_rate: f64,
    /// AdamW decoupled weight decay (on weights, not biases).
    pub weight_decay: f64,
    /// AdamW β1.
    pub beta1: f64,
    /// AdamW β2.
    pub beta2: f64,
    /// AdamW ε.
    pub epsilon: f64,
    /// Huber δ of the loss above the surface, metres (paper: 0.05).
    pub huber_delta: f32,
    /// Decay of the loss EMA that drives the schedule and early stopping.
    pub ema_decay: f64,
    /// Stop when the loss EMA has not improved for this many iterations (paper: 150).
    pub early_stop_patience: u32,
    /// Early stopping: the EMA counts as improved when below its best × (1 − this)
    /// (the schedule has its own, `plateau_min_improvement`).
    pub min_improvement: f64,
    /// Reduce-on-plateau: iterations without EMA improvement before the rate drops.
    pub plateau_patience: u32,
    /// Reduce-on-plateau: the EMA counts as improved for the schedule when below its best
    /// × (1 − this). The same 1 % as `min_improvement` by default; on hills a smaller one
    /// with a longer `plateau_patience` keeps the rate up while the map is still following
    /// the terrain (docs/offline-labels.md, "Hills").
    pub plateau_min_improvement: f64,
    /// Reduce-on-plateau: factor the learning rate is multiplied by.
    pub plateau_factor: f64,
    /// Reduce-on-plateau: the learning rate never drops below this.
    pub min_learning_rate: f64,
    /// Hard cap on iterations (a scan that never plateaus still ends).
    pub max_iterations: u32,
    /// Pre-filter: points below this global height quantile are left out of the fit
    /// (paper: "0.5", read as 0.5 %). They are still labelled by the residual rule.
    pub prefilter_quantile: f64,
    /// The network's output is added to this low height quantile of the fitted points, so
    /// that it starts near the ground.
    pub output_bias_quantile: f64,
    /// Ground if z − g(x, y) ≤ this, metres (paper: D = 0.40).
    pub ground_distance: f32,
    /// Post-processing pillar edge, metres (paper: 0.5).
    pub pillar_size: f32,
    /// Post-processing: only points within ± this of g(x, y) take part, metres (paper: 1.5).
    pub pillar_window: f32,
    /// Post-processing: in a pillar holding both classes, points more than τ above its
    /// lowest point become non-ground, metres (paper: 0.05).
    pub pillar_tau: f32,
    /// Softness of the probability around a decision boundary, metres: p = σ(margin / w).
    pub probability_width: f32,
    /// Seed of the initialisation and the mini-batches.
    pub seed: u64,
}

impl Default for PseudoLabelerConfig {
    fn default() -> Self {
        Self {
            hidden: vec![32, 32],
            batch_size: 4096,
            learning_rate: 1e-2,
            weight_decay: 1e-2,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            huber_delta: 0.05,
            ema_decay: 0.9,
            early_stop_patience: 150,
            min_improvement: 0.01,
            plateau_patience: 10,
            plateau_min_improvement: 0.01,
            plateau_factor: 0.1,
            min_learning_rate: 1e-4,
            max_iterations: 2000,
            prefilter_quantile: 0.005,
            output_bias_quantile: 0.05,
            ground_distance: 0.40,
            pillar_size: 0.5,
            pillar_window: 1.5,
            pillar_tau: 0.05,
            probability_width: 0.05,
            seed: 0,
        }
    }
}

fn check(ok: bool, field: &str, reason: &str) -> Result<(), ConfigError> {
    if ok {
        Ok(())
    } else {
        Err(ConfigError {
            field: field.into(),
            reason: reason.into(),
        })
    }
}

fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

impl PseudoLabelerConfig {
    /// Checks every value; the error names the offending field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let f = |n: &str| format!("pseudolabeler.{n}");
        check(
            !self.hidden.is_empty() && self.hidden.iter().all(|&w| (1..=1024).contains(&w)),
            &f("hidden"),
            "one or more widths in 1..=1024",
        )?;
        check(
            (1..=1 << 20).contains(&self.batch_size),
            &f("batch_size"),
            "must be in 1..=1048576",
        )?;
        check(
            positive(self.learning_rate),
            &f("learning_rate"),
            "must be > 0",
        )?;
        check(
            self.weight_decay.is_finite() && self.weight_decay >= 0.0,
            &f("weight_decay"),
            "must be ≥ 0",
        )?;
        for (v, n) in [
            (self.beta1, "beta1"),
            (self.beta2, "beta2"),
            (self.ema_decay, "ema_decay"),
        ] {
            check((0.0..1.0).contains(&v), &f(n), "must be in [0, 1)")?;
        }
        check(positive(self.epsilon), &f("epsilon"), "must be > 0")?;
        check(
            (0.0..1.0).contains(&self.plateau_factor) && self.plateau_factor > 0.0,
            &f("plateau_factor"),
            "must be in (0, 1)",
        )?;
        check(
            self.min_learning_rate.is_finite() && self.min_learning_rate >= 0.0,
            &f("min_learning_rate"),
            "must be ≥ 0",
        )?;
        for (v, n) in [
            (self.min_improvement, "min_improvement"),
            (self.plateau_min_improvement, "plateau_min_improvement"),
        ] {
            check((0.0..1.0).contains(&v), &f(n), "must be in [0, 1)")?;
        }
        check(
            self.max_iterations >= 1,
            &f("max_iterations"),
            "must be ≥ 1",
        )?;
        for (v, n) in [
            (self.prefilter_quantile, "prefilter_quantile"),
            (self.output_bias_quantile, "output_bias_quantile"),
        ] {
            check((0.0..1.0).contains(&v), &f(n), "must be in [0, 1)")?;
        }
        for (v, n) in [
            (self.huber_delta, "huber_delta"),
            (self.pillar_size, "pillar_size"),
            (self.pillar_window, "pillar_window"),
            (self.probability_width, "probability_width"),
        ] {
            check(positive(f64::from(v)), &f(n), "must be > 0")?;
        }
        for (v, n) in [
            (self.ground_distance, "ground_distance"),
            (self.pillar_tau, "pillar_tau"),
        ] {
            check(v.is_finite() && v >= 0.0, &f(n), "must be finite and ≥ 0")?;
        }
        Ok(())
    }
}

/// The RANSAC plane baseline of both papers' tables.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RansacConfig {
    /// Plane hypotheses (each from three points drawn at random).
    pub iterations: u32,
    /// A point within this distance of the plane is an inlier (ground), metres.
    pub inlier_distance: f32,
    /// Hypotheses whose normal leans more than this from the vertical are not ground
    /// planes (a wall may hold more points than the road), degrees; 90 disables it.
    pub max_tilt_deg: f64,
    /// Refit the best plane to its inliers by least squares before labelling.
    pub refit: bool,
    /// Softness of the probability around the inlier distance, metres.
    pub probability_width: f32,
    /// Seed of the hypotheses.
    pub seed: u64,
}

impl Default for RansacConfig {
    fn default() -> Self {
        Self {
            iterations: 200,
            inlier_distance: 0.2,
            max_tilt_deg: 30.0,
            refit: true,
            probability_width: 0.05,
            seed: 0,
        }
    }
}

impl RansacConfig {
    /// Checks every value; the error names the offending field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check(
            (1..=1_000_000).contains(&self.iterations),
            "ransac.iterations",
            "must be in 1..=1000000",
        )?;
        check(
            positive(f64::from(self.inlier_distance)),
            "ransac.inlier_distance",
            "must be > 0",
        )?;
        check(
            self.max_tilt_deg.is_finite() && (0.0..=90.0).contains(&self.max_tilt_deg),
            "ransac.max_tilt_deg",
            "must be in [0, 90]",
        )?;
        check(
            positive(f64::from(self.probability_width)),
            "ransac.probability_width",
            "must be > 0",
        )
    }
}
