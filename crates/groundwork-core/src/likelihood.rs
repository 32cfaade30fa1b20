//! Ground likelihoods of a fitted component (paper §III-C).

use nalgebra::{Matrix3, SymmetricEigen};

use crate::config::Sigmoid;
use crate::gmm::Sym3;

/// The inverted sigmoid p(x, α, β) = 1 − 1/(1 + e^{−α(x−β)}), written as 1/(1 + e^{α(x−β)})
/// which is the same value without cancellation for large x.
#[inline]
pub fn inverted_sigmoid(x: f64, s: Sigmoid) -> f64 {
    let t = s.alpha * (x - s.beta);
    if t > 700.0 {
        0.0
    } else {
        1.0 / (1.0 + t.exp())
    }
}

/// Shape of a covariance: smallest eigenvalue and the angle between its eigenvector and the
/// vertical.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Flatness {
    /// Smallest eigenvalue λ_min (m²).
    pub lambda_min: f64,
    /// θ = arccos(|v_min · n_z|) in [0, π/2]. The eigenvector's sign is arbitrary, hence |·|.
    pub tilt: f64,
}

/// Eigen-analysis of a symmetric covariance.
pub fn flatness(cov: &Sym3) -> Flatness {
    let m = Matrix3::new(
        cov[0], cov[1], cov[2], cov[1], cov[3], cov[4], cov[2], cov[4], cov[5],
    );
    let eig = SymmetricEigen::new(m);
    let (i, &lambda_min) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .unwrap_or((2, &cov[5]));
    let v = eig.eigenvectors.column(i);
    let cos = (v[2].abs() / v.norm()).clamp(0.0, 1.0);
    Flatness {
        lambda_min,
        tilt: cos.acos(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FLAT: Sigmoid = Sigmoid {
        alpha: 40.0,
        beta: 0.06,
    };
    const TILT: Sigmoid = Sigmoid {
        alpha: 4.0,
        beta: 0.8,
    };

    #[test]
    fn sigmoid_at_known_inputs() {
        // p(β) = 0.5 exactly; p(0) > 0.9 as the paper tunes it; saturation at both ends.
        assert!((inverted_sigmoid(0.06, FLAT) - 0.5).abs() < 1e-15);
        let p0 = inverted_sigmoid(0.0, FLAT);
        assert!((p0 - 1.0 / (1.0 + (-2.4f64).exp())).abs() < 1e-12 && p0 > 0.9);
        assert!((inverted_sigmoid(0.0, TILT) - 1.0 / (1.0 + (-3.2f64).exp())).abs() < 1e-12);
        assert_eq!(inverted_sigmoid(1e6, FLAT), 0.0);
        assert!((inverted_sigmoid(-1e6, FLAT) - 1.0).abs() < 1e-15);
        // Monotonically decreasing.
        assert!(inverted_sigmoid(0.5, TILT) > inverted_sigmoid(1.0, TILT));
    }

    #[test]
    fn flat_horizontal_patch_has_small_eigenvalue_and_no_tilt() {
        let f = flatness(&[1.0, 0.0, 0.0, 2.0, 0.0, 0.001]);
        assert!((f.lambda_min - 0.001).abs() < 1e-12);
        assert!(f.tilt.abs() < 1e-6);
    }

    #[test]
    fn vertical_wall_is_tilted_ninety_degrees() {
        // Thin in y, extended in x and z: normal is horizontal.
        let f = flatness(&[1.0, 0.0, 0.0, 0.001, 0.0, 1.0]);
        assert!((f.tilt - std::f64::consts::FRAC_PI_2).abs() < 1e-6);
    }

    #[test]
    fn slope_of_thirty_degrees_has_thirty_degree_tilt() {
        // Plane z = tan(30°)·x: spread along (cos, 0, sin), thin along the normal.
        let (s, c) = 30f64.to_radians().sin_cos();
        let (a, b) = (1.0, 1e-4); // variance along the slope and along the normal
        let cov = [
            a * c * c + b * s * s,
            0.0,
            (a - b) * c * s,
            1.0,
            0.0,
            a * s * s + b * c * c,
        ];
        let f = flatness(&cov);
        assert!((f.tilt - 30f64.to_radians()).abs() < 1e-6, "{f:?}");
        // The sign of the eigenvector does not matter: mirrored slope, same tilt.
        let mirrored = [cov[0], 0.0, -cov[2], 1.0, 0.0, cov[5]];
        assert!((flatness(&mirrored).tilt - f.tilt).abs() < 1e-9);
    }
}
