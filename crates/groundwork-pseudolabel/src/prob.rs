//! From a signed margin to a ground probability.

/// σ(x) = 1 / (1 + e^−x).
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `p` if below 0.5, else the largest f32 below 0.5: a non-ground decision whose margin
/// is too small for σ to show in f32 still reads as non-ground.
#[inline]
pub fn below_half(p: f32) -> f32 {
    if p < 0.5 { p } else { BELOW_HALF }
}

/// The largest f32 below 0.5.
const BELOW_HALF: f32 = f32::from_bits(0.5f32.to_bits() - 1);
