//! The network's per-point passes in 512-bit registers, on CPUs that have AVX-512
//! ([`groundwork_core::cpu::avx512`]). The portable build targets x86-64-v3, where a vector
//! holds 8 points; here one holds 16, two neighbouring vectors of a block's row, which are
//! contiguous. Every value is computed by the same operations in the same order as in the
//! portable code (a layer's output sums its inputs in input order from its bias, per
//! point), so the results are bit for bit the same. The weight gradients, which sum over
//! points, stay portable: 16 lanes would sum them in another order.

#![allow(unsafe_code)] // the loads and stores of two vectors, and the run-time dispatch

use core::arch::x86_64::{
    __m512, _mm512_add_ps, _mm512_castps_si512, _mm512_castsi512_ps, _mm512_div_ps,
    _mm512_fmadd_ps, _mm512_fnmadd_ps, _mm512_loadu_ps, _mm512_max_ps, _mm512_min_ps,
    _mm512_mul_ps, _mm512_roundscale_ps, _mm512_set1_ps, _mm512_setzero_ps, _mm512_slli_epi32,
    _mm512_storeu_ps, _mm512_sub_ps, _mm512_xor_si512,
};

use wide::f32x8;

use super::{OUT_BLOCK, ROW_BLOCK};

/// Two neighbouring vectors (16 points).
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
#[inline]
fn load(v: &[f32x8; 2]) -> __m512 {
    // SAFETY: the reference covers 16 contiguous f32 (`f32x8` is 8 f32 in 32 bytes);
    // unaligned loads take any address.
    unsafe { _mm512_loadu_ps(v.as_ptr().cast::<f32>()) }
}

/// Stores 16 points into two neighbouring vectors.
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
#[inline]
fn store(v: &mut [f32x8; 2], x: __m512) {
    // SAFETY: as in `load`, for a unique borrow.
    unsafe { _mm512_storeu_ps(v.as_mut_ptr().cast::<f32>(), x) }
}

/// [`super::layer`]: z = W · a (+ bias), every output's terms summed in input order.
///
/// # Safety
/// The CPU must have AVX-512F, VL, BW and DQ ([`groundwork_core::cpu::avx512`]).
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
pub(super) unsafe fn layer(
    wk: &[f32],
    bias: Option<&[f32]>,
    p: usize,
    q: usize,
    a: &[f32x8],
    z: &mut [f32x8],
) {
    debug_assert!(wk.len() == p * q && a.len() / q == z.len() / p);
    for (a, z) in a
        .chunks_exact(q * ROW_BLOCK)
        .zip(z.chunks_exact_mut(p * ROW_BLOCK))
    {
        // A block's rows are ROW_BLOCK = 4 vectors: two pairs each.
        let (a, z) = (a.as_chunks::<2>().0, z.as_chunks_mut::<2>().0);
        let mut o = 0;
        while o + OUT_BLOCK <= p {
            layer_step::<OUT_BLOCK>(wk, bias, p, a, z, o);
            o += OUT_BLOCK;
        }
        for o in o..p {
            layer_step::<1>(wk, bias, p, a, z, o);
        }
    }
}

/// Outputs o0..o0+O of one block (`a` its q rows, `z` its p rows, as pairs of vectors),
/// all four of its vectors (two registers) per output.
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
#[inline]
fn layer_step<const O: usize>(
    wk: &[f32],
    bias: Option<&[f32]>,
    p: usize,
    a: &[[f32x8; 2]],
    z: &mut [[f32x8; 2]],
    o0: usize,
) {
    const { assert!(ROW_BLOCK == 4) };
    let mut acc = [[_mm512_setzero_ps(); 2]; O];
    if let Some(b) = bias {
        for (acc, &b) in acc.iter_mut().zip(&b[o0..o0 + O]) {
            *acc = [_mm512_set1_ps(b); 2];
        }
    }
    for (ak, wk) in a.chunks_exact(2).zip(wk.chunks_exact(p)) {
        let (lo, hi) = (load(&ak[0]), load(&ak[1]));
        for (acc, &w) in acc.iter_mut().zip(&wk[o0..o0 + O]) {
            let w = _mm512_set1_ps(w);
            // The portable `ak.mul_add(w, acc)`: one rounding of ak·w + acc.
            acc[0] = _mm512_fmadd_ps(lo, w, acc[0]);
            acc[1] = _mm512_fmadd_ps(hi, w, acc[1]);
        }
    }
    for (j, acc) in acc.iter().enumerate() {
        let r = (o0 + j) * 2;
        store(&mut z[r], acc[0]);
        store(&mut z[r + 1], acc[1]);
    }
}

/// [`super::sigmoid`] of 16 points, the same operations in the same order.
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
#[inline]
fn sigmoid(z: __m512) -> __m512 {
    let c = _mm512_set1_ps;
    let one = c(1.0);
    // −z by the sign bit, as `wide`'s negation; then max and min against constants (never
    // NaN, so `wide`'s NaN select keeps these results).
    let neg = _mm512_castsi512_ps(_mm512_xor_si512(
        _mm512_castps_si512(z),
        _mm512_castps_si512(c(-0.0)),
    ));
    let t = _mm512_min_ps(_mm512_max_ps(neg, c(-87.0)), c(80.0));
    // Round to the nearest integer, ties to even, exceptions suppressed (`round_ties_even`).
    let n = _mm512_roundscale_ps::<0x08>(_mm512_mul_ps(t, c(core::f32::consts::LOG2_E)));
    let r = _mm512_fnmadd_ps(n, c(0.693_359_4), t);
    let r = _mm512_fnmadd_ps(n, c(-2.121_944_4e-4), r);
    let r2 = _mm512_mul_ps(r, r);
    let r4 = _mm512_mul_ps(r2, r2);
    let poly = _mm512_fmadd_ps(
        _mm512_fmadd_ps(c(1.0 / 120.0), r, c(1.0 / 24.0)),
        r2,
        _mm512_fmadd_ps(
            _mm512_fmadd_ps(c(1.0 / 5040.0), r, c(1.0 / 720.0)),
            r4,
            _mm512_fmadd_ps(c(1.0 / 6.0), r, c(0.5)),
        ),
    );
    let biased = _mm512_add_ps(n, c(127.0 + 8_388_608.0));
    let pow2 = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_castps_si512(biased)));
    let e = _mm512_mul_ps(_mm512_add_ps(_mm512_fmadd_ps(poly, r2, r), one), pow2);
    _mm512_div_ps(one, _mm512_add_ps(one, e))
}

/// A hidden layer's activation: σ(z) into `s` and SiLU, z σ(z), into `next` (both resized
/// to `z`'s length), as the portable forward pass.
///
/// # Safety
/// As [`layer`].
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
pub(super) unsafe fn activate(z: &[f32x8], s: &mut Vec<f32x8>, next: &mut Vec<f32x8>) {
    s.resize(z.len(), f32x8::ZERO);
    next.resize(z.len(), f32x8::ZERO);
    // Whole blocks: pairs only (an odd vector left would take the portable `sigmoid`).
    let (zp, zr) = z.as_chunks::<2>();
    let (sp, sr) = s.as_chunks_mut::<2>();
    let (np, nr) = next.as_chunks_mut::<2>();
    for ((z, s), n) in zp.iter().zip(sp).zip(np) {
        let zv = load(z);
        let sv = sigmoid(zv);
        store(s, sv);
        store(n, _mm512_mul_ps(zv, sv));
    }
    for ((&z, s), n) in zr.iter().zip(sr).zip(nr) {
        *s = super::sigmoid(z);
        *n = z * *s;
    }
}

/// The backward pass through SiLU: `d` ×= σ(z)(1 + z(1 − σ(z))), as the portable loop.
///
/// # Safety
/// As [`layer`].
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx512dq")]
pub(super) unsafe fn silu_backward(d: &mut [f32x8], z: &[f32x8], s: &[f32x8]) {
    let one = _mm512_set1_ps(1.0);
    // As the portable loop's zip: as far as the shortest.
    let n = d.len().min(z.len()).min(s.len());
    let (d, z, s) = (&mut d[..n], &z[..n], &s[..n]);
    let (dp, dr) = d.as_chunks_mut::<2>();
    let (zp, zr) = z.as_chunks::<2>();
    let (sp, sr) = s.as_chunks::<2>();
    for ((d, z), s) in dp.iter_mut().zip(zp).zip(sp) {
        let (dv, zv, sv) = (load(d), load(z), load(s));
        let g = _mm512_fmadd_ps(zv, _mm512_sub_ps(one, sv), one);
        store(d, _mm512_mul_ps(dv, _mm512_mul_ps(sv, g)));
    }
    // Whole blocks leave no odd vector; were one left, the portable step.
    super::silu_backward_portable(dr, zr, sr);
}
