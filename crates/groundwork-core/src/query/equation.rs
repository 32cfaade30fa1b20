//! A point's ground probability (paper §III-E, and §III-F over several frames), written once
//! in its readable scalar form. The query computes it 16 points per SIMD vector
//! (`query::probabilities`); its tests hold those vectors to [`ground_probability`] bit for
//! bit, and the whole query to [`ground_probability_of`].
//!
//! For a point q and the components k that answer for it (its own segment's in this scan,
//! and those of the past frames that reach it), with log-density
//! l_k(q) = log N(q; μ_k, Σ_k) + log π_k and the component's three likelihoods (flatness
//! p_λ, orientation p_θ and elevation p_e, [`crate::likelihood`]):
//!
//! ```text
//! w_k  = exp(l_k(q) − max_j l_j(q))          responsibilities, up to their sum
//! P(q) = (Σ w_k p_λ,k / Σ w_k) · (Σ w_k p_θ,k / Σ w_k) · (Σ w_k p_e,k / Σ w_k)
//! ```
//!
//! clamped to [0, 1]; a point that no component answers for gets 0. Ground continuity
//! (`crate::continuity`) then raises points on ground that continues from confident ground;
//! it is a step of its own, after this.

/// One component's term in a point's equation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ComponentTerm {
    /// log N(q; μ, Σ) + log π: the component's log-density at the point, nats.
    pub log_density: f64,
    /// Flatness likelihood p_λ, in [0, 1].
    pub flatness: f64,
    /// Orientation likelihood p_θ, in [0, 1].
    pub orientation: f64,
    /// Elevation likelihood p_e, in [0, 1].
    pub elevation: f64,
}

/// The equation in f64 over every term that answers for a point: the reference the query
/// is tested against (the query keeps f32 sums relative to one reference log-density).
pub fn ground_probability_of(terms: &[ComponentTerm]) -> f64 {
    let Some(top) = terms.iter().map(|t| t.log_density).reduce(f64::max) else {
        return 0.0;
    };
    let (mut sum, mut flat, mut orient, mut elev) = (0.0, 0.0, 0.0, 0.0);
    for t in terms {
        let w = (t.log_density - top).exp();
        sum += w;
        flat += w * t.flatness;
        orient += w * t.orientation;
        elev += w * t.elevation;
    }
    ((flat / sum) * (orient / sum) * (elev / sum)).clamp(0.0, 1.0)
}

/// The last step as the query takes it, from the point's sums: `sum` = Σ w_k and the three
/// Σ w_k · p. The query's vectors compute exactly this, lane by lane: one correctly rounded
/// division, the products in this order, and `clamp` (a NaN passes as it does here).
#[inline]
pub fn ground_probability(sum: f32, flat: f32, orient: f32, elev: f32) -> f32 {
    if sum > 0.0 {
        let inv = 1.0 / sum;
        ((flat * inv) * (orient * inv) * (elev * inv)).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn term(log_density: f64, p: f64) -> ComponentTerm {
        ComponentTerm {
            log_density,
            flatness: p,
            orientation: p,
            elevation: p,
        }
    }

    #[test]
    fn one_component_gives_the_product_of_its_likelihoods() {
        let t = ComponentTerm {
            log_density: -3.0,
            flatness: 0.9,
            orientation: 0.8,
            elevation: 0.5,
        };
        assert!((ground_probability_of(&[t]) - 0.36).abs() < 1e-12);
        assert_eq!(ground_probability_of(&[]), 0.0);
        assert_eq!(ground_probability(0.0, 1.0, 1.0, 1.0), 0.0);
    }

    #[test]
    fn the_likelier_component_has_the_say() {
        // e^-20 against 1: the far component's likelihoods barely count.
        let p = ground_probability_of(&[term(0.0, 1.0), term(-20.0, 0.0)]);
        assert!(p > 0.999_999 && p < 1.0, "{p}");
        // Equal densities: the mean of each likelihood, then the product.
        let p = ground_probability_of(&[term(-1.0, 1.0), term(-1.0, 0.0)]);
        assert!((p - 0.125).abs() < 1e-12, "{p}");
    }

    #[test]
    fn the_f32_step_is_the_f64_equation_rounded() {
        let terms = [term(0.0, 0.9), term(-1.5, 0.2)];
        let w = (-1.5f64).exp();
        let (sum, part) = (1.0 + w, 0.9 + w * 0.2);
        let p = ground_probability(sum as f32, part as f32, part as f32, part as f32);
        assert!((f64::from(p) - ground_probability_of(&terms)).abs() < 1e-6);
    }
}
