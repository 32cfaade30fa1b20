//! The SIMD vectors of the hot loops (binning and the query): 16 f32 lanes, one AVX-512
//! register where the CPU has it, two AVX2 registers otherwise (`wide` picks at compile
//! time from the target features).

/// f32 lanes.
pub(crate) type Vf = wide::f32x16;
/// i32 lanes (masks, packed bins).
pub(crate) type Vi = wide::i32x16;
/// Lanes per vector.
pub(crate) const LANES: usize = 16;

/// Lanes `j..j + w` of a slice (w ≤ [`LANES`]), zero-padded.
#[inline(always)]
pub(crate) fn load(v: &[f32], j: usize, w: usize) -> Vf {
    match v[j..].first_chunk::<LANES>() {
        Some(a) => Vf::new(*a),
        None => {
            let mut a = [0.0; LANES];
            a[..w].copy_from_slice(&v[j..j + w]);
            Vf::new(a)
        }
    }
}
