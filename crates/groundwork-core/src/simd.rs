//! The SIMD vectors of the hot loops (binning and the query): 16 f32 lanes, one AVX-512
//! register where the CPU has it, two AVX2 registers otherwise (`wide` picks at compile
//! time from the target features).

/// f32 lanes.
pub(crate) type Vf = wide::f32x16;
/// i32 lanes (masks, packed bins).
pub(crate) type Vi = wide::i32x16;
/// Lanes per vector.
pub(crate) const LANES: usize = 16;

/// Lanes `j..j + w` of a slice of f64 (w ≤ [`LANES`]), rounded to f32, zero-padded.
#[inline(always)]
pub(crate) fn load_f64(v: &[f64], j: usize, w: usize) -> Vf {
    match v[j..].first_chunk::<LANES>() {
        Some(a) => Vf::new(a.map(|x| x as f32)),
        None => {
            let mut a = [0.0; LANES];
            for (o, &x) in a.iter_mut().zip(&v[j..j + w]) {
                *o = x as f32;
            }
            Vf::new(a)
        }
    }
}

/// The smallest lane (for finite lanes; a NaN lane may or may not win): halves folded in
/// registers, not sixteen dependent scalar minimums.
#[inline(always)]
pub(crate) fn lane_min(v: Vf) -> f32 {
    let [a, b]: [wide::f32x8; 2] = wide::bytemuck::cast(v);
    let [c, d]: [wide::f32x4; 2] = wide::bytemuck::cast(a.fast_min(b));
    let m = c.fast_min(d).to_array();
    m[0].min(m[1]).min(m[2].min(m[3]))
}
