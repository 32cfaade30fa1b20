//! The query's hottest loop, past components' weights against a fixed reference (the fast
//! path of [`LaneSums::add_segment`](super::LaneSums)), in 512-bit registers on CPUs that
//! have AVX-512. The portable build targets x86-64-v3, where a 16-lane vector is two AVX2
//! registers and the loop spills; this copy is chosen at run time, so the same binary still
//! runs on any x86-64-v3 CPU. It performs the same operations in the same order as the
//! portable loop (two components interleaved, each accumulated in turn), so the results are
//! bit for bit the same.

#![allow(unsafe_code)] // intrinsics, and the run-time dispatch into them

use core::arch::x86_64::{
    __m512, __mmask16, _mm512_add_ps, _mm512_castps_si512, _mm512_castsi512_ps,
    _mm512_cmpneq_epi32_mask, _mm512_fmadd_ps, _mm512_fmsub_ps, _mm512_fnmadd_ps,
    _mm512_maskz_mov_ps, _mm512_max_ps, _mm512_mul_ps, _mm512_set1_ps, _mm512_setzero_si512,
    _mm512_slli_epi32, _mm512_sub_ps,
};

use super::{LOG_FLOOR, QComp};
use crate::fastmath::{EXP2_POLY, EXP2_ROUND};
use crate::simd::Vf;

/// Whether this CPU runs `eval_run_avx512` and [`add_fixed`] (`is_x86_feature_detected`
/// caches the answer).
#[inline]
pub(super) fn available() -> bool {
    // What `eval_run_avx512` is compiled with.
    std::is_x86_feature_detected!("avx512f")
        && std::is_x86_feature_detected!("avx512vl")
        && std::is_x86_feature_detected!("avx512bw")
        && std::is_x86_feature_detected!("avx512dq")
}

#[inline(always)]
fn wide(v: Vf) -> __m512 {
    // SAFETY: both are 16 f32 lanes in 64 bytes (`wide`'s is `repr(C)`: lanes 0–7, then
    // 8–15), no padding, any bit pattern valid.
    unsafe { core::mem::transmute::<Vf, __m512>(v) }
}

#[inline(always)]
fn narrow(v: __m512) -> Vf {
    // SAFETY: as in `wide`.
    unsafe { core::mem::transmute::<__m512, Vf>(v) }
}

/// Running sums of one vector of points: Σw, Σw·p_λ, Σw·p_θ, Σw·p_e.
pub(super) type Sums = [Vf; 4];

/// Adds, in the lanes of `hit` (all bits set or clear), the weights of `comps` at points
/// `p` relative to `reference`, as the portable loop in `LaneSums::add_segment` does.
///
/// # Safety
/// The CPU must have AVX-512F ([`available`]). Call it only from a function compiled with
/// AVX-512F enabled: it is inlined there, and its intrinsics with it (a caller without the
/// feature gets no inlined intrinsics, only slow calls).
#[inline(always)]
pub(super) unsafe fn add_fixed(
    comps: &[QComp],
    p: &[Vf; 3],
    reference: Vf,
    hit: Vf,
    sums: Sums,
) -> Sums {
    // SAFETY: the caller runs with AVX-512F enabled.
    unsafe {
        let p = p.map(wide);
        let reference = wide(reference);
        let hit = _mm512_cmpneq_epi32_mask(_mm512_castps_si512(wide(hit)), _mm512_setzero_si512());
        let mut acc = sums.map(wide);
        // Two components at a time: their dependency chains overlap.
        let mut pairs = comps.chunks_exact(2);
        for pair in &mut pairs {
            let w0 = weight(&pair[0], &p, reference, hit);
            let w1 = weight(&pair[1], &p, reference, hit);
            accumulate(&mut acc, w0, &pair[0]);
            accumulate(&mut acc, w1, &pair[1]);
        }
        for q in pairs.remainder() {
            accumulate(&mut acc, weight(q, &p, reference, hit), q);
        }
        acc.map(narrow)
    }
}

/// Weight of component `q` at points `[x, y, z]` relative to `reference`, in the lanes of
/// `hit` (0 elsewhere): the portable `weight`'s, operation for operation.
///
/// # Safety
/// As [`add_fixed`].
#[inline(always)]
unsafe fn weight(q: &QComp, &[x, y, z]: &[__m512; 3], reference: __m512, hit: __mmask16) -> __m512 {
    // SAFETY: as the caller's.
    unsafe {
        let s = _mm512_set1_ps;
        // log_density (bits).
        let u = q.u;
        let u3 = _mm512_fmsub_ps(s(u[5]), z, s(q.b[2]));
        let u2 = _mm512_fmadd_ps(s(u[3]), y, _mm512_fmsub_ps(s(u[4]), z, s(q.b[1])));
        let u1 = _mm512_fmadd_ps(
            s(u[0]),
            x,
            _mm512_fmadd_ps(s(u[1]), y, _mm512_fmsub_ps(s(u[2]), z, s(q.b[0]))),
        );
        let l = _mm512_fnmadd_ps(
            u1,
            u1,
            _mm512_fnmadd_ps(u2, u2, _mm512_fnmadd_ps(u3, u3, s(q.c))),
        );
        let t = _mm512_max_ps(_mm512_sub_ps(l, reference), s(-LOG_FLOOR));
        // exp2_from (fastmath).
        let round = s(EXP2_ROUND);
        let shifted = _mm512_add_ps(t, round);
        let f = _mm512_sub_ps(t, _mm512_sub_ps(shifted, round));
        let [c5, c4, c3, c2, c1] = EXP2_POLY;
        let e = _mm512_fmadd_ps(f, s(c5), s(c4));
        let e = _mm512_fmadd_ps(f, e, s(c3));
        let e = _mm512_fmadd_ps(f, e, s(c2));
        let e = _mm512_fmadd_ps(f, e, s(c1));
        let e = _mm512_fmadd_ps(f, e, s(1.0));
        let scale = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_castps_si512(shifted)));
        _mm512_maskz_mov_ps(hit, _mm512_mul_ps(e, scale))
    }
}

/// Adds weights `w` of component `q` to the sums (`LaneSums::add_weight`).
///
/// # Safety
/// As [`add_fixed`].
#[inline(always)]
unsafe fn accumulate([sum, flat, orient, elev]: &mut [__m512; 4], w: __m512, q: &QComp) {
    // SAFETY: as the caller's.
    unsafe {
        let s = _mm512_set1_ps;
        *sum = _mm512_add_ps(*sum, w);
        *flat = _mm512_fmadd_ps(w, s(q.flat), *flat);
        *orient = _mm512_fmadd_ps(w, s(q.orient), *orient);
        *elev = _mm512_fmadd_ps(w, s(q.elev), *elev);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::query::{LaneSums, log_density};
    use proptest::prelude::*;

    fn comp() -> impl Strategy<Value = QComp> {
        (
            proptest::array::uniform6(-3.0f32..3.0),
            proptest::array::uniform3(-60.0f32..60.0),
            -20.0f32..20.0,
            proptest::array::uniform3(0.0f32..1.0),
        )
            .prop_map(|(u, b, c, [flat, orient, elev])| QComp {
                u,
                b,
                c,
                flat,
                orient,
                elev,
            })
    }

    proptest! {
        /// The AVX-512 loop gives the portable loop's sums bit for bit (on a CPU without
        /// AVX-512 there is nothing to compare, and the case passes).
        #[test]
        fn gives_the_portable_sums_bit_for_bit(
            comps in proptest::collection::vec(comp(), 0..12),
            xyz in proptest::array::uniform3(proptest::array::uniform16(-40.0f32..40.0)),
            hit in proptest::array::uniform16(proptest::bool::ANY),
            start in proptest::array::uniform4(0.0f32..2.0),
        ) {
            if !available() {
                return Ok(());
            }
            let p = xyz.map(Vf::new);
            // The reference is the largest log-density (as the query's own model makes it),
            // or a fixed one where there is no component.
            let reference = comps
                .iter()
                .map(|q| log_density(q, p[0], p[1], p[2]))
                .reduce(|a, b| a.max(b))
                .unwrap_or(Vf::splat(-5.0));
            let hit = Vf::new(hit.map(|h| if h { f32::from_bits(u32::MAX) } else { 0.0 }));
            let [sum, flat, orient, elev] = start.map(Vf::splat);
            let mut want = LaneSums { max: reference, sum, flat, orient, elev };
            for q in &comps {
                want.add_component(q, p[0], p[1], p[2], reference, hit);
            }
            #[allow(unsafe_code)]
            // SAFETY: checked above.
            let got = unsafe { add_fixed(&comps, &p, reference, hit, start.map(Vf::splat)) };
            for (g, w) in got.iter().zip([want.sum, want.flat, want.orient, want.elev]) {
                prop_assert_eq!(g.to_array().map(f32::to_bits), w.to_array().map(f32::to_bits));
            }
        }
    }
}
