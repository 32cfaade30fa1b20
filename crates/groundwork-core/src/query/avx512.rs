//! The query's hottest loop, past components' weights against a fixed reference (the fast
//! path of [`LaneSums::add_segment`](super::LaneSums)), in 512-bit registers on CPUs that
//! have AVX-512. The portable build targets x86-64-v3, where a 16-lane vector is two AVX2
//! registers and the loop spills; this copy is chosen at run time, so the same binary still
//! runs on any x86-64-v3 CPU. It performs the same operations in the same order as the
//! portable loop (two components interleaved, each accumulated in turn), so the results are
//! bit for bit the same.

#![allow(unsafe_code)] // intrinsics, and the run-time dispatch into them

use core::arch::x86_64::{
    __m512, __mmask16, _CMP_GE_OQ, _mm512_abs_ps, _mm512_add_epi32, _mm512_add_ps,
    _mm512_castps_si512, _mm512_castsi512_ps, _mm512_cmp_ps_mask, _mm512_cmpneq_epi32_mask,
    _mm512_fmadd_ps, _mm512_fmsub_ps, _mm512_fnmadd_ps, _mm512_maskz_compress_epi32,
    _mm512_maskz_mov_ps, _mm512_max_ps, _mm512_mul_ps, _mm512_set1_epi32, _mm512_set1_ps,
    _mm512_setr_epi32, _mm512_setzero_ps, _mm512_setzero_si512, _mm512_slli_epi32,
    _mm512_storeu_si512, _mm512_sub_ps,
};

use super::regrid::BoundBlock;
use super::{LOG_FLOOR, QComp};
use crate::fastmath::{EXP2_POLY, EXP2_ROUND};
use crate::simd::Vf;

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
/// The CPU must have AVX-512F ([`crate::cpu::avx512`]). Call it only from a function compiled with
/// AVX-512F enabled: it is inlined there, and its intrinsics with it (a caller without the
/// feature gets no inlined intrinsics, only slow calls).
#[inline(always)]
pub(super) unsafe fn add_fixed<'c>(
    comps: impl Iterator<Item = &'c QComp>,
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
        let mut comps = comps;
        while let Some(q0) = comps.next() {
            let Some(q1) = comps.next() else {
                accumulate(&mut acc, weight(q0, &p, reference, hit), q0);
                break;
            };
            let w0 = weight(q0, &p, reference, hit);
            let w1 = weight(q1, &p, reference, hit);
            accumulate(&mut acc, w0, q0);
            accumulate(&mut acc, w1, q1);
        }
        acc.map(narrow)
    }
}

/// [`list_reaching`](super::regrid::list_reaching) in 512-bit registers, with the same
/// arithmetic (so the same lists); the indices of the reaching lanes are packed with one
/// compress per block.
///
/// # Safety
/// As [`add_fixed`].
#[inline(always)]
pub(super) unsafe fn list_reaching(
    blocks: &[BoundBlock],
    lo: [f32; 3],
    hi: [f32; 3],
    floor: f32,
    live: &mut [u32],
) -> usize {
    // SAFETY: as the caller's; every store is to `live[n..n + 16]`, checked.
    unsafe {
        let s = _mm512_set1_ps;
        let [cx, cy, cz] = std::array::from_fn(|k| s(0.5 * (lo[k] + hi[k])));
        let [hx, hy, hz] = std::array::from_fn(|k| s(0.5 * (hi[k] - lo[k])));
        let floor = s(floor);
        let zero = _mm512_setzero_ps();
        let mut index = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        let step = _mm512_set1_epi32(16);
        let mut n = 0;
        for block in blocks {
            let [u0, u1, u2, u3, u4, u5] = block.u.map(wide);
            let [a0, a1, a2, a3, a4, a5] = block.u.map(|u| _mm512_abs_ps(wide(u)));
            let [b0, b1, b2] = block.b.map(wide);
            let m1 = _mm512_fmadd_ps(u0, cx, _mm512_fmadd_ps(u1, cy, _mm512_fmsub_ps(u2, cz, b0)));
            let r1 = _mm512_fmadd_ps(a0, hx, _mm512_fmadd_ps(a1, hy, _mm512_mul_ps(a2, hz)));
            let m2 = _mm512_fmadd_ps(u3, cy, _mm512_fmsub_ps(u4, cz, b1));
            let r2 = _mm512_fmadd_ps(a3, hy, _mm512_mul_ps(a4, hz));
            let m3 = _mm512_fmsub_ps(u5, cz, b2);
            let r3 = _mm512_mul_ps(a5, hz);
            let near = |m, r| _mm512_max_ps(_mm512_sub_ps(_mm512_abs_ps(m), r), zero);
            let (d1, d2, d3) = (near(m1, r1), near(m2, r2), near(m3, r3));
            let top = _mm512_fnmadd_ps(
                d1,
                d1,
                _mm512_fnmadd_ps(d2, d2, _mm512_fnmadd_ps(d3, d3, wide(block.c))),
            );
            let reach = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(top, floor);
            let out = &mut live[n..n + 16];
            _mm512_storeu_si512(
                out.as_mut_ptr().cast(),
                _mm512_maskz_compress_epi32(reach, index),
            );
            n += reach.count_ones() as usize;
            index = _mm512_add_epi32(index, step);
        }
        n
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
    use crate::query::{LaneSums, log_density, regrid};
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
        /// The AVX-512 lists of reaching components are the portable ones (same order).
        #[test]
        fn lists_the_components_the_portable_bound_lists(
            comps in proptest::collection::vec(comp(), 0..40),
            lo in proptest::array::uniform3(-40.0f32..40.0),
            size in proptest::array::uniform3(0.0f32..5.0),
            floor in -60.0f32..10.0,
        ) {
            if !crate::cpu::avx512() {
                return Ok(());
            }
            let hi = std::array::from_fn(|k| lo[k] + size[k]);
            let blocks: Vec<BoundBlock> = comps.chunks(16).map(BoundBlock::of).collect();
            let mut want = vec![0; comps.len() + 16];
            let n = regrid::list_reaching::<false>(&blocks, lo, hi, floor, &mut want);
            let mut got = vec![0; comps.len() + 16];
            #[allow(unsafe_code)]
            // SAFETY: checked above.
            let m = unsafe { list_reaching(&blocks, lo, hi, floor, &mut got) };
            prop_assert_eq!(&got[..m], &want[..n]);
        }

        /// The AVX-512 loop gives the portable loop's sums bit for bit (on a CPU without
        /// AVX-512 there is nothing to compare, and the case passes).
        #[test]
        fn gives_the_portable_sums_bit_for_bit(
            comps in proptest::collection::vec(comp(), 0..12),
            xyz in proptest::array::uniform3(proptest::array::uniform16(-40.0f32..40.0)),
            hit in proptest::array::uniform16(proptest::bool::ANY),
            start in proptest::array::uniform4(0.0f32..2.0),
        ) {
            if !crate::cpu::avx512() {
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
            let got = unsafe { add_fixed(comps.iter(), &p, reference, hit, start.map(Vf::splat)) };
            for (g, w) in got.iter().zip([want.sum, want.flat, want.orient, want.elev]) {
                prop_assert_eq!(g.to_array().map(f32::to_bits), w.to_array().map(f32::to_bits));
            }
        }
    }
}
