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
    /// Where the two smallest eigenvalues draw together, the normal is not defined (a
    /// line-like cluster is thin in every direction across it), and θ blends towards the
    /// angle of the whole plane across the largest axis (see [`flatness`]).
    pub tilt: f64,
}

/// Relative gap (λ_mid − λ_min) / λ_mid below which the tilt is blended: at 0.2 and above,
/// the smallest eigenvector alone says what the normal is.
pub const DEFINED_NORMAL_GAP: f64 = 0.2;

/// Eigen-analysis of a symmetric covariance, in closed form: the eigenvalues by the
/// trigonometric solution of the characteristic cubic, the eigenvectors of the smallest and
/// the largest as the longest cross product of two rows of Σ − λI. nalgebra's iterative
/// `SymmetricEigen`, run once per fitted component, was 6 % of a scan's CPU time.
///
/// The tilt is a continuous function of Σ. With λ_min ≈ λ_mid, the smallest eigenvector
/// swings anywhere in the plane of the two on a rounding error (a ring of ground points,
/// thin across and under it, was called level or vertical by the last bit). So cos²θ is
/// the weighted mean of v_zᵀ over the two smallest eigenvectors, the middle one weighted
/// w = (1 − gap / [`DEFINED_NORMAL_GAP`])² (0 where the normal is defined); the middle
/// vector's v_z² is 1 − v_min,z² − v_max,z², and as w → 1 the ill-defined v_min drops out
/// of the sum: cos²θ = ((1 − w)·v_min,z² + w·(1 − v_max,z²)) / (1 + w).
pub fn flatness(cov: &Sym3) -> Flatness {
    let [a, b, c, d, e, f] = *cov; // xx, xy, xz, yy, yz, zz
    let off = b * b + c * c + e * e;
    let q = (a + d + f) / 3.0;
    let (aq, dq, fq) = (a - q, d - q, f - q);
    let p = ((aq * aq + dq * dq + fq * fq + 2.0 * off) / 6.0).sqrt();
    let blended = |lambda: [f64; 3], zmin2: f64, zmax2: f64| {
        let [lmin, lmid, _] = lambda;
        let gap = if lmid > 0.0 {
            ((lmid - lmin) / lmid).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let w = (1.0 - gap / DEFINED_NORMAL_GAP).max(0.0).powi(2);
        let cos2 = ((1.0 - w) * zmin2 + w * (1.0 - zmax2)) / (1.0 + w);
        Flatness {
            lambda_min: lmin,
            tilt: cos2.clamp(0.0, 1.0).sqrt().acos(),
        }
    };
    if !(off > 0.0 && p > 0.0) {
        // Diagonal (or not finite): the axes are the eigenvectors.
        let mut l = [(a, 0.0), (d, 0.0), (f, 1.0)];
        l.sort_by(|x, y| x.0.total_cmp(&y.0));
        return blended([l[0].0, l[1].0, l[2].0], l[0].1, l[2].1);
    }
    // det((Σ − qI)/p) / 2 = cos 3φ; the eigenvalues are q + 2p·cos(φ + 2πk/3).
    let det = aq * (dq * fq - e * e) - b * (b * fq - e * c) + c * (b * e - dq * c);
    let r = (det / (2.0 * p * p * p)).clamp(-1.0, 1.0);
    let phi = r.acos() / 3.0;
    use std::f64::consts::FRAC_PI_3;
    let lambda_max = q + 2.0 * p * phi.cos();
    let lambda_min = q + 2.0 * p * (phi + 2.0 * FRAC_PI_3).cos();
    let lambda_mid = 3.0 * q - lambda_max - lambda_min;
    // v_z² of the eigenvector of λ: the longest cross product of two rows of Σ − λI.
    let z2 = |lambda: f64| {
        let rows = [[a - lambda, b, c], [b, d - lambda, e], [c, e, f - lambda]];
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
        let n = norm2(&v);
        // All three eigenvalues equal: no direction stands out; a third of each axis.
        if n > 0.0 { v[2] * v[2] / n } else { 1.0 / 3.0 }
    };
    blended(
        [lambda_min, lambda_mid, lambda_max],
        z2(lambda_min),
        z2(lambda_max),
    )
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

    #[test]
    fn the_tilt_of_a_line_does_not_jump_with_its_last_bits() {
        // A ring of ground points: long along x, thin across it in y and z alike. Turned
        // about x, its smallest eigenvector swings between y and z; the tilt moves with
        // the covariance, never from level to vertical on a rounding error.
        let turned = |a: f64| {
            let (s, c) = a.sin_cos();
            let (ly, lz) = (1.05e-4, 1e-4);
            [
                1.0,
                0.0,
                0.0,
                c * c * ly + s * s * lz,
                c * s * (ly - lz),
                s * s * ly + c * c * lz,
            ]
        };
        let mut last = flatness(&turned(0.0)).tilt;
        for k in 1..=2000 {
            let t = flatness(&turned(f64::from(k) * 1e-3)).tilt;
            assert!((t - last).abs() < 0.01, "step {k}: {last} -> {t}");
            last = t;
        }
        // Where the normal is defined the blend leaves it alone.
        let ground = flatness(&[1.0, 0.0, 0.0, 0.5, 0.0, 1e-3]);
        assert!(ground.tilt.abs() < 1e-6);
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
            // The trigonometric solution loses digits where two eigenvalues nearly meet
            // (acos near ±1): up to ~5e-10 of the scale seen (1e-10 failed one case in
            // some thousands), immaterial to a likelihood.
            proptest::prop_assert!((f.lambda_min - min).abs() <= 1e-8 * scale, "{f:?} {min}");
            // The normal is defined where the smallest eigenvalue stands apart: there the
            // tilt is the smallest eigenvector's (elsewhere it is blended, on purpose).
            if mid - min >= DEFINED_NORMAL_GAP * mid {
                let v = eig.eigenvectors.column(order[0]);
                let tilt = (v[2].abs() / v.norm()).clamp(0.0, 1.0).acos();
                proptest::prop_assert!((f.tilt - tilt).abs() < 1e-5, "{f:?} {tilt}");
            }
        }
    }
}
