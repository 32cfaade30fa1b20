//! Branch-free `exp` and `ln` for f32 that the compiler vectorises.
//!
//! EM spends most of its time exponentiating log-densities to responsibilities; `f32::exp`
//! is a scalar libm call that blocks auto-vectorisation. Responsibilities need about 1e-6
//! relative accuracy, which a degree-6 polynomial on the reduced argument gives.

use crate::simd::{Vf, Vi};
use wide::bytemuck::cast;

/// Rounds to the nearest integer (ties to even) for |v| < 2³¹ (beyond, the result wraps):
/// adding 1.5·2⁵² leaves the integer in the low mantissa bits (two's complement for
/// negatives), a plain add that vectorises where `as` saturates lane by lane.
#[inline(always)]
pub(crate) fn round_i32(v: f64) -> i32 {
    const MAGIC: f64 = 6_755_399_441_055_744.0;
    (v + MAGIC).to_bits() as u32 as i32
}

/// What the exponential needs of its lanes: `f32` itself or the query's vector of them. One
/// body serves the EM (scalar code that the compiler vectorises) and the query (16 lanes),
/// so their bits agree.
pub trait ExpLanes:
    Copy + std::ops::Add<Output = Self> + std::ops::Sub<Output = Self> + std::ops::Mul<Output = Self>
{
    fn splat(v: f32) -> Self;
    /// self·m + a, rounded once.
    fn fma(self, m: Self, a: Self) -> Self;
    /// The float whose bits are self's shifted left by 23.
    fn shl23(self) -> Self;
}

impl ExpLanes for f32 {
    #[inline(always)]
    fn splat(v: f32) -> Self {
        v
    }
    #[inline(always)]
    fn fma(self, m: Self, a: Self) -> Self {
        self.mul_add(m, a)
    }
    #[inline(always)]
    fn shl23(self) -> Self {
        f32::from_bits(self.to_bits() << 23)
    }
}

impl ExpLanes for Vf {
    #[inline(always)]
    fn splat(v: f32) -> Self {
        Vf::splat(v)
    }
    #[inline(always)]
    fn fma(self, m: Self, a: Self) -> Self {
        self.mul_add(m, a)
    }
    #[inline(always)]
    fn shl23(self) -> Self {
        cast::<Vi, Vf>(cast::<Vf, Vi>(self) << 23)
    }
}

/// e^x for x ≤ 0 (the callers subtract the maximum first). Inputs below −87 return about
/// 1e-38; NaN is not expected. Relative error below 2e-6 on [−20, 0] and below 2e-5 on
/// [−87, −20] (the rounding of x·log2(e)), where weights are negligible anyway.
#[inline(always)]
pub fn exp_nonpositive(x: f32) -> f32 {
    exp2_from((x * std::f32::consts::LOG2_E).max(-126.0))
}

/// Adding it rounds t to the nearest integer i: the low mantissa bits of the sum then hold
/// 2^22 + 127 + i, and shifting them left by 23 drops everything but 127 + i, the biased
/// exponent of 2^i. (A float-to-int cast would do, but a saturating `as i32` turns into a
/// scalar conversion per lane.)
pub(crate) const EXP2_ROUND: f32 = 12_583_039.0; // 1.5·2^23 + 127

/// 2^f = 1 + f·(c1 + f·(c2 + …)) on |f| ≤ 1/2: degree 5, minimax for the relative error
/// of e^y on |y| ≤ ln2/2 with y = f·ln 2 folded into the coefficients: below 1.1e-7
/// before rounding.
pub(crate) const EXP2_POLY: [f32; 5] = [
    0.001_330_027_2,
    0.009_669_71,
    0.055_505_6,
    0.240_222_8,
    std::f32::consts::LN_2,
];

/// 2^t on a vector, for t ≤ 127 (the query keeps log-densities in bits, so that no
/// exponential pays a multiplication by log2(e) and one by ln 2). Inputs below −126 return
/// about 1e-38; NaN is not expected.
#[inline(always)]
pub fn exp2_v(t: Vf) -> Vf {
    exp2_from(t.max(Vf::splat(-126.0)))
}

/// 2^t for t in [−126, 127], without a clamp; the integer part is rounded with
/// [`EXP2_ROUND`].
#[inline(always)]
pub fn exp2_from<T: ExpLanes>(t: T) -> T {
    let round = T::splat(EXP2_ROUND);
    let shifted = t + round;
    let f = t - (shifted - round); // in [−0.5, 0.5]
    let [c5, c4, c3, c2, c1] = EXP2_POLY.map(T::splat);
    let p = f.fma(c5, c4);
    let p = f.fma(p, c3);
    let p = f.fma(p, c2);
    let p = f.fma(p, c1);
    let p = f.fma(p, T::splat(1.0));
    p * shifted.shl23()
}

/// What the logarithm needs of its lanes: `f32` itself or eight of them (the EM's
/// stopping rule, per point or per summary cell). One body, so their bits agree.
pub trait LnLanes:
    Copy
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Div<Output = Self>
{
    fn splat(v: f32) -> Self;
    /// The unbiased binary exponent e (as a float) and the mantissa m in [1, 2) of a
    /// positive normal float: self = m·2^e.
    fn exponent_mantissa(self) -> (Self, Self);
}

impl LnLanes for f32 {
    #[inline(always)]
    fn splat(v: f32) -> Self {
        v
    }
    #[inline(always)]
    fn exponent_mantissa(self) -> (Self, Self) {
        let bits = self.to_bits();
        let e = ((bits >> 23) & 0xff) as i32 - 127;
        (e as f32, f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000))
    }
}

impl LnLanes for wide::f32x8 {
    #[inline(always)]
    fn splat(v: f32) -> Self {
        wide::f32x8::splat(v)
    }
    #[inline(always)]
    fn exponent_mantissa(self) -> (Self, Self) {
        use wide::i32x8;
        let bits: i32x8 = cast(self);
        let e: i32x8 = ((bits >> 23) & i32x8::splat(0xff)) - i32x8::splat(127);
        let m = cast((bits & i32x8::splat(0x007f_ffff)) | i32x8::splat(0x3f80_0000));
        (e.round_float(), m)
    }
}

/// ln x for finite x ≥ 1e-30 (the callers pass sums of responsibilities ≥ 1), on any
/// [`LnLanes`]. Absolute error below 1e-5 (the series' truncation near m = 2).
#[inline(always)]
pub fn ln_from<T: LnLanes>(x: T) -> T {
    let (e, m) = x.exponent_mantissa();
    // ln m = 2 atanh((m − 1)/(m + 1)).
    let one = T::splat(1.0);
    let s = (m - one) / (m + one); // in [0, 1/3)
    let s2 = s * s;
    let c = T::splat;
    let atanh = s
        * (one
            + s2 * (c(1.0 / 3.0) + s2 * (c(1.0 / 5.0) + s2 * (c(1.0 / 7.0) + s2 * c(1.0 / 9.0)))));
    c(2.0) * atanh + e * c(std::f32::consts::LN_2)
}

/// [`ln_from`] on one float.
#[inline(always)]
pub fn ln_positive(x: f32) -> f32 {
    ln_from(x)
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

/// atan2(y, x) in (−π, π] on a vector, without branches (selects only). Absolute error
/// below 1e-6 rad; atan2(0, 0) = 0.
#[inline(always)]
pub fn atan2_v(y: Vf, x: Vf) -> Vf {
    use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};
    let c = Vf::splat;
    let (ax, ay) = (x.abs(), y.abs());
    let (num, den) = (ax.fast_min(ay), ax.fast_max(ay));
    // t = num/den ∈ [0, 1]; above tan(π/8), atan t = π/4 + atan((t − 1)/(t + 1)), and
    // (t − 1)/(t + 1) = (num − den)/(num + den): one division either way, and no chain
    // of two.
    let big = num.simd_gt(c(std::f32::consts::SQRT_2 - 1.0) * den);
    let u = big.select(num - den, num) / big.select(num + den, den);
    let u = den.simd_gt(Vf::ZERO).select(u, Vf::ZERO);
    let u2 = u * u;
    // atan u = u·(1 + u²·q(u²)), q of degree 3 fitted for least maximum error on
    // |u| ≤ tan(π/8): below 5e-9 before rounding.
    let series = u2.mul_add(c(0.079_025_87), c(-0.138_244_5));
    let series = u2.mul_add(series, c(0.199_718_79));
    let series = u2.mul_add(series, c(-0.333_327_56));
    let series = u2.mul_add(series, c(1.0));
    let a = u.mul_add(series, big.select(c(FRAC_PI_4), Vf::ZERO));
    let a = ay.simd_gt(ax).select(c(FRAC_PI_2) - a, a);
    let a = x.simd_lt(Vf::ZERO).select(c(PI) - a, a);
    y.simd_lt(Vf::ZERO).select(-a, a)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::LANES;

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
    fn exp_scalar_and_vector_give_the_same_bits() {
        // The EM's scalar exponential and the query's vector one share their reduction and
        // polynomial: one accuracy test covers both.
        let mut x = -90.0f32;
        while x <= 0.0 {
            let t = (x * std::f32::consts::LOG2_E).max(-126.0);
            assert_eq!(
                exp_nonpositive(x).to_bits(),
                exp2_v(Vf::splat(t)).to_array()[0].to_bits(),
                "{x}"
            );
            x += 0.000_37;
        }
    }

    #[test]
    fn ln_on_one_and_on_eight_lanes_gives_the_same_bits() {
        // The EM's stopping rule sums one or the other (subsample or summary cells): the
        // same sum of responsibilities must give the same bits, and both must be ln.
        let mut x = 1.0f32;
        while x < 1e6 {
            let v: [f32; 8] = std::array::from_fn(|i| x * (1.0 + i as f32 * 0.013));
            for (&g, &xi) in ln_from(wide::f32x8::new(v)).to_array().iter().zip(&v) {
                assert_eq!(g.to_bits(), ln_positive(xi).to_bits(), "{xi}");
                assert!((f64::from(g) - f64::from(xi).ln()).abs() < 1e-5, "{xi}");
            }
            x *= 1.0007;
        }
    }

    #[test]
    fn exp2_vector_matches_std() {
        let worst = |lo: f32, hi: f32| {
            let mut w: f64 = 0.0;
            let mut t = lo;
            while t <= hi {
                let v: [f32; LANES] = std::array::from_fn(|i| t + i as f32 * 1e-3);
                for (g, &ti) in exp2_v(Vf::new(v)).to_array().iter().zip(&v) {
                    let want = f64::from(ti).exp2();
                    w = w.max(((f64::from(*g) - want) / want).abs());
                }
                t += 0.017;
            }
            w
        };
        // The whole domain, from where weights are negligible to where they would overflow
        // soon: the polynomial's error, as the reduction t − round(t) is exact.
        let w = worst(-126.0, 127.0);
        assert!(w < 3e-7, "worst relative error on [-126, 127]: {w}");
        assert_eq!(exp2_v(Vf::splat(0.0)).to_array(), [1.0; LANES]);
        assert_eq!(exp2_v(Vf::splat(-3.0)).to_array(), [0.125; LANES]);
        assert!(exp2_v(Vf::splat(-1e30)).to_array()[0] < 1e-37);
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
    fn atan2_x8_matches_std() {
        for i in 0..20_000 {
            let a = i as f32 * std::f32::consts::TAU / 20_000.0 - std::f32::consts::PI;
            let ys: [f32; LANES] = std::array::from_fn(|k| (1.0 + 10.0 * k as f32) * a.sin());
            let xs: [f32; LANES] = std::array::from_fn(|k| (1.0 + 10.0 * k as f32) * a.cos());
            let got = atan2_v(Vf::new(ys), Vf::new(xs)).to_array();
            for k in 0..LANES {
                let d = (got[k] - ys[k].atan2(xs[k])).abs();
                // ±π are the same direction.
                assert!(
                    d.min((d - std::f32::consts::TAU).abs()) < 1e-6,
                    "{} {}: {}",
                    ys[k],
                    xs[k],
                    got[k]
                );
            }
        }
        let zero = atan2_v(Vf::ZERO, Vf::ZERO).to_array();
        assert_eq!(zero, [0.0; LANES]);
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
