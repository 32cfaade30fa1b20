//! Ground likelihoods of a fitted component (paper §III-C).

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

/// Eigen-analysis of a symmetric covariance, in closed form: the smallest eigenvalue by the
/// trigonometric solution of the characteristic cubic, its eigenvector as the longest cross
/// product of two rows of Σ − λI. nalgebra's iterative `SymmetricEigen`, run once per fitted
/// component, was 6 % of a scan's CPU time.
pub fn flatness(cov: &Sym3) -> Flatness {
    let [a, b, c, d, e, f] = *cov; // xx, xy, xz, yy, yz, zz
    let off = b * b + c * c + e * e;
    let q = (a + d + f) / 3.0;
    let (aq, dq, fq) = (a - q, d - q, f - q);
    let p = ((aq * aq + dq * dq + fq * fq + 2.0 * off) / 6.0).sqrt();
    if !(off > 0.0 && p > 0.0) {
        // Diagonal (or not finite): the axes are the eigenvectors; z alone is untilted.
        let lambda_min = a.min(d).min(f);
        let tilt = if f <= a.min(d) {
            0.0
        } else {
            std::f64::consts::FRAC_PI_2
        };
        return Flatness { lambda_min, tilt };
    }
    // det((Σ − qI)/p) / 2 = cos 3φ; the eigenvalues are q + 2p·cos(φ + 2πk/3).
    let det = aq * (dq * fq - e * e) - b * (b * fq - e * c) + c * (b * e - dq * c);
    let r = (det / (2.0 * p * p * p)).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    let lambda_min = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
    let rows = [
        [a - lambda_min, b, c],
        [b, d - lambda_min, e],
        [c, e, f - lambda_min],
    ];
    let cross = |u: [f64; 3], v: [f64; 3]| {
        [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ]
    };
    let norm2 = |v: &[f64; 3]| v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    let v = [
        cross(rows[0], rows[1]),
        cross(rows[0], rows[2]),
        cross(rows[1], rows[2]),
    ]
    .into_iter()
    .max_by(|x, y| norm2(x).total_cmp(&norm2(y)))
    .unwrap_or([0.0, 0.0, 1.0]);
    let n = norm2(&v).sqrt();
    let cos = if n > 0.0 {
        (v[2].abs() / n).clamp(0.0, 1.0)
    } else {
        1.0 // all three eigenvalues equal: no direction is the normal; call it level
    };
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

    proptest::proptest! {
        /// The closed form against nalgebra's iterative eigen-solver, on covariances of any
        /// orientation with eigenvalues from the regulariser's 1e-4 to 10 m².
        #[test]
        fn closed_form_matches_nalgebra(
            l in proptest::array::uniform3(-4.0f64..1.0),
            angles in proptest::array::uniform3(-3.2f64..3.2),
        ) {
            use nalgebra::{Matrix3, Rotation3, SymmetricEigen};
            let r = Rotation3::from_euler_angles(angles[0], angles[1], angles[2]);
            let d = Matrix3::from_diagonal(&nalgebra::Vector3::from(l.map(|v| 10f64.powf(v))));
            let m = r.matrix() * d * r.matrix().transpose();
            let cov = [m[(0, 0)], m[(0, 1)], m[(0, 2)], m[(1, 1)], m[(1, 2)], m[(2, 2)]];
            let eig = SymmetricEigen::new(Matrix3::new(
                cov[0], cov[1], cov[2], cov[1], cov[3], cov[4], cov[2], cov[4], cov[5],
            ));
            let mut order = [0, 1, 2];
            order.sort_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]));
            let (min, mid) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
            let f = flatness(&cov);
            let scale = eig.eigenvalues.abs().max();
            proptest::prop_assert!((f.lambda_min - min).abs() <= 1e-10 * scale, "{f:?} {min}");
            // The normal is defined where the smallest eigenvalue stands apart.
            if mid - min > 1e-3 * scale {
                let v = eig.eigenvectors.column(order[0]);
                let tilt = (v[2].abs() / v.norm()).clamp(0.0, 1.0).acos();
                proptest::prop_assert!((f.tilt - tilt).abs() < 1e-5, "{f:?} {tilt}");
            }
        }
    }
}
