//! Branch-free `exp` and `ln` for f32 that the compiler vectorises.
//!
//! EM spends most of its time exponentiating log-densities to responsibilities; `f32::exp`
//! is a scalar libm call that blocks auto-vectorisation. Responsibilities need about 1e-6
//! relative accuracy, which a degree-6 polynomial on the reduced argument gives.

/// e^x for x ≤ 0 (the callers subtract the maximum first). Inputs below −87 return about
/// 1e-38; NaN is not expected. Relative error below 2e-6 on [−20, 0] and below 2e-5 on
/// [−87, −20] (the f32 range reduction), where weights are negligible anyway.
#[inline(always)]
pub fn exp_nonpositive(x: f32) -> f32 {
    let x = x.max(-87.0);
    let t = x * std::f32::consts::LOG2_E;
    // Nearest integer of t without a libm call: floor(t + 0.5), where truncation rounds
    // toward zero and the comparison corrects negative values.
    let u = t + 0.5;
    let ti = u as i32;
    let fi = ti - i32::from((ti as f32) > u);
    let f = t - fi as f32; // in [−0.5, 0.5]
    // 2^f = e^{f·ln2} with |f·ln2| ≤ 0.35: Taylor to degree 6 errs by < 2e-7.
    let y = f * std::f32::consts::LN_2;
    let p = 1.0
        + y * (1.0
            + y * (0.5
                + y * (1.0 / 6.0 + y * (1.0 / 24.0 + y * (1.0 / 120.0 + y * (1.0 / 720.0))))));
    p * f32::from_bits(((fi + 127) as u32) << 23)
}

/// ln x for finite x ≥ 1e-30 (the callers pass sums of responsibilities ≥ 1).
/// Absolute error below 1e-6.
#[inline(always)]
pub fn ln_positive(x: f32) -> f32 {
    let bits = x.to_bits();
    let e = ((bits >> 23) & 0xff) as i32 - 127;
    // Mantissa m in [1, 2); use the identity ln m = 2 atanh((m − 1)/(m + 1)).
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let s = (m - 1.0) / (m + 1.0); // in [0, 1/3)
    let s2 = s * s;
    let atanh =
        s * (1.0 + s2 * (1.0 / 3.0 + s2 * (1.0 / 5.0 + s2 * (1.0 / 7.0 + s2 * (1.0 / 9.0)))));
    2.0 * atanh + e as f32 * std::f32::consts::LN_2
}

/// atan2(y, x) in (−π, π] with absolute error below 1e-8 rad: enough to pick a sector
/// (a point that close to a sector boundary may land on either side, deterministically).
#[inline(always)]
pub fn atan2(y: f64, x: f64) -> f64 {
    use std::f64::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let (num, den) = if ax >= ay { (ay, ax) } else { (ax, ay) };
    if den == 0.0 {
        return 0.0;
    }
    let t = num / den; // in [0, 1]
    // Reduce to |u| ≤ tan(π/8) ≈ 0.414 with atan t = π/4 + atan((t − 1)/(t + 1)); there the
    // Taylor series to degree 17 errs by less than 0.414^19 / 19 ≈ 3e-9.
    let big = t > std::f64::consts::SQRT_2 - 1.0;
    let u = if big { (t - 1.0) / (t + 1.0) } else { t };
    let u2 = u * u;
    let mut series = 1.0 / 17.0;
    for k in (0..8).rev() {
        series = 1.0 / (2 * k + 1) as f64 - u2 * series;
    }
    let a = u * series
        + if big {
            std::f64::consts::FRAC_PI_4
        } else {
            0.0
        };
    let a = if ay > ax { FRAC_PI_2 - a } else { a };
    let a = if x < 0.0 { PI - a } else { a };
    if y < 0.0 { -a } else { a }
}

/// atan2 for f32 without branches (selects only), so loops over points vectorise.
/// Absolute error below 1e-6 rad; atan2_f32(0, 0) = 0.
#[inline(always)]
pub fn atan2_f32(y: f32, x: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let (num, den) = (ax.min(ay), ax.max(ay));
    let t = if den > 0.0 { num / den } else { 0.0 };
    let big = t > std::f32::consts::SQRT_2 - 1.0;
    let u = if big { (t - 1.0) / (t + 1.0) } else { t };
    let u2 = u * u;
    // atan u = u Σ (−u²)^k / (2k + 1), |u| ≤ 0.414: eight terms reach f32 precision.
    let series = 1.0
        - u2 * (1.0 / 3.0
            - u2 * (1.0 / 5.0
                - u2 * (1.0 / 7.0
                    - u2 * (1.0 / 9.0 - u2 * (1.0 / 11.0 - u2 * (1.0 / 13.0 - u2 / 15.0))))));
    let a = u * series + if big { FRAC_PI_4 } else { 0.0 };
    let a = if ay > ax { FRAC_PI_2 - a } else { a };
    let a = if x < 0.0 { PI - a } else { a };
    if y < 0.0 { -a } else { a }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_matches_std_on_its_domain() {
        let worst = |lo: f32, hi: f32| {
            let mut w: f32 = 0.0;
            let mut x = lo;
            while x <= hi {
                let (a, b) = (exp_nonpositive(x), x.exp());
                w = w.max(((a - b) / b).abs());
                x += 0.001_3;
            }
            w
        };
        let near = worst(-20.0, 0.0);
        assert!(near < 2e-6, "worst relative error on [-20, 0]: {near}");
        let far = worst(-87.0, -20.0);
        assert!(far < 2e-5, "worst relative error on [-87, -20]: {far}");
        assert_eq!(exp_nonpositive(0.0), 1.0);
        assert!(exp_nonpositive(-1e9) < 1e-37);
    }

    #[test]
    fn atan2_matches_std() {
        let mut worst: f64 = 0.0;
        for i in 0..20_000 {
            let a = i as f64 * std::f64::consts::TAU / 20_000.0 - std::f64::consts::PI;
            for r in [0.001, 1.0, 80.0] {
                let (y, x) = (r * a.sin(), r * a.cos());
                let d = (atan2(y, x) - y.atan2(x)).abs();
                // ±π are the same direction.
                worst = worst.max(d.min((d - std::f64::consts::TAU).abs()));
            }
        }
        assert!(worst < 1e-8, "worst {worst}");
        assert_eq!(atan2(0.0, 0.0), 0.0);
    }

    #[test]
    fn atan2_f32_matches_std() {
        let mut worst: f32 = 0.0;
        for i in 0..20_000 {
            let a = i as f32 * std::f32::consts::TAU / 20_000.0 - std::f32::consts::PI;
            let (y, x) = (50.0 * a.sin(), 50.0 * a.cos());
            let d = (atan2_f32(y, x) - y.atan2(x)).abs();
            worst = worst.max(d.min((d - std::f32::consts::TAU).abs()));
        }
        assert!(worst < 1e-6, "worst {worst}");
        assert_eq!(atan2_f32(0.0, 0.0), 0.0);
    }

    #[test]
    fn ln_matches_std() {
        let mut worst: f32 = 0.0;
        let mut x = 1e-6f32;
        while x < 1e6 {
            worst = worst.max((ln_positive(x) - x.ln()).abs());
            x *= 1.001_7;
        }
        assert!(worst < 2e-6, "worst absolute error {worst}");
    }
}
