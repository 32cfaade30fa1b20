//! The SIMD vectors of the hot loops (binning and the query): 16 f32 lanes, one AVX-512
//! register where the CPU has it, two AVX2 registers otherwise (`wide` picks at compile
//! time from the target features).

/// f32 lanes.
pub(crate) type Vf = wide::f32x16;
/// i32 lanes (masks, packed bins).
pub(crate) type Vi = wide::i32x16;
/// Lanes per vector.
pub(crate) const LANES: usize = 16;
