//! A small fully connected network with SiLU activations, its hand-written backward pass
//! and AdamW: the elevation map g(x, y) of the PseudoLabeler.
//!
//! Activations are stored by blocks of 4 × 8 points (`ROW_BLOCK` vectors): within a block, one
//! row of vectors per feature. Every layer is then a few hand-blocked loops of fused
//! multiply-adds over points whose operands are contiguous, whatever the layer widths. (A
//! general `sgemm` spent as long packing these thin matrices as multiplying them.) A pass's
//! points are padded to whole blocks: padded points have zero inputs and are never read
//! back, and a zero ∂L/∂output gives them zero gradients exactly.
//!
//! Every sum runs in a fixed order that depends on the widths and the number of points
//! only, with fused multiply-adds (x86-64-v3 and aarch64 both have them): the same bits on
//! every machine these builds run on. Where the CPU has AVX-512 the per-point passes (the
//! layers, σ, SiLU) take 16 points a register instead of 8 (`avx512`): each point's value is
//! the same operations in the same order, so the bits are the same too.
//!
//! Parameters live in one flat vector (per layer: weights out × in, row-major, then
//! biases), which keeps the optimiser a single loop.

use rand::Rng;
use wide::f32x8;

#[cfg(target_arch = "x86_64")]
mod avx512;

/// Calls `avx512::$fast` where the CPU has AVX-512 ([`groundwork_core::cpu::avx512`]) and
/// returns; otherwise falls through to the portable code after it. The copies give the same
/// bits, so the choice changes only the time.
macro_rules! avx512_if_present {
    ($fast:ident($($arg:expr),*)) => {
        #[cfg(target_arch = "x86_64")]
        if groundwork_core::cpu::avx512() {
            #[allow(unsafe_code)]
            // SAFETY: every function of `avx512` is compiled with exactly the features
            // `cpu::avx512` checks for.
            unsafe {
                avx512::$fast($($arg),*)
            };
            return;
        }
    };
}

/// Points per vector.
const LANES: usize = 8;
/// Vectors of points per block: a pass's points are padded to a multiple of
/// `ROW_BLOCK × LANES`.
const ROW_BLOCK: usize = 4;
/// Outputs per step of the layer kernel (4 outputs × 2 vectors of points: eight
/// accumulators, which leaves registers for the operands on AVX2's sixteen).
const OUT_BLOCK: usize = 4;

/// The network's shape and parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    /// Layer widths, input first (2) and output last (1).
    sizes: Vec<usize>,
    /// All parameters, layer by layer: weights (out × in, row-major), then biases.
    params: Vec<f32>,
    /// The same, each layer's weights transposed (in × out), as the forward pass reads
    /// them. Kept in step with `params` by every change ([`Mlp::update`]): the forward pass
    /// runs for every chunk of every mini-batch, the parameters change once per step.
    transposed: Vec<f32>,
}

/// Intermediate values of one forward pass, kept for the backward pass. Reused across
/// iterations so that training allocates nothing per step.
#[derive(Debug, Default, Clone)]
pub struct Workspace {
    /// Points of the last forward pass.
    rows: usize,
    /// Blocks of `ROW_BLOCK` vectors (the points, padded).
    blocks: usize,
    /// Per layer: its input activations (blocks × in × `ROW_BLOCK`).
    inputs: Vec<Vec<f32x8>>,
    /// Per hidden layer: σ(z) of its pre-activations (blocks × out × `ROW_BLOCK`).
    sigmoids: Vec<Vec<f32x8>>,
    /// Per hidden layer: its pre-activations z (blocks × out × `ROW_BLOCK`).
    pre: Vec<Vec<f32x8>>,
    /// The output, one value per point (one feature: blocked is plain order).
    output: Vec<f32x8>,
    /// Gradient buffers (blocks × widest layer × `ROW_BLOCK`), two for ping-pong.
    grad_a: Vec<f32x8>,
    grad_b: Vec<f32x8>,
}

impl Workspace {
    /// The last forward pass's outputs, one per point.
    pub fn output(&self) -> &[f32] {
        &bytemuck::cast_slice(&self.output)[..self.rows]
    }
}

/// The sum of a vector's lanes in one fixed order on every target (`reduce_add`'s order
/// differs between AVX and NEON).
#[inline(always)]
fn lane_sum(v: f32x8) -> f32 {
    let t = v.to_array();
    ((t[0] + t[4]) + (t[2] + t[6])) + ((t[1] + t[5]) + (t[3] + t[7]))
}

/// z = W · a (+ bias) for every block of points: `wk` holds W by input (q × p: the weights
/// of input k to the p outputs, contiguous), `a` has q features and `z` gets p. Each output
/// sums its q terms in input order, starting from its bias. In 512-bit registers where the
/// CPU has AVX-512 (the same bits).
fn layer(wk: &[f32], bias: Option<&[f32]>, p: usize, q: usize, a: &[f32x8], z: &mut [f32x8]) {
    avx512_if_present!(layer(wk, bias, p, q, a, z));
    layer_portable(wk, bias, p, q, a, z);
}

/// [`layer`] in `wide`'s vectors of 8.
fn layer_portable(
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
        let mut o = 0;
        while o + OUT_BLOCK <= p {
            layer_step::<OUT_BLOCK, { ROW_BLOCK / 2 }>(wk, bias, p, a, z, o, 0);
            layer_step::<OUT_BLOCK, { ROW_BLOCK / 2 }>(wk, bias, p, a, z, o, ROW_BLOCK / 2);
            o += OUT_BLOCK;
        }
        // Single outputs (a narrow layer such as the last): four independent chains.
        for o in o..p {
            layer_step::<1, ROW_BLOCK>(wk, bias, p, a, z, o, 0);
        }
    }
}

/// Outputs o0..o0+O of vectors i0..i0+R of one block.
#[inline(always)]
fn layer_step<const O: usize, const R: usize>(
    wk: &[f32],
    bias: Option<&[f32]>,
    p: usize,
    a: &[f32x8],
    z: &mut [f32x8],
    o0: usize,
    i0: usize,
) {
    let mut acc = [[f32x8::ZERO; R]; O];
    if let Some(b) = bias {
        for (acc, &b) in acc.iter_mut().zip(&b[o0..o0 + O]) {
            *acc = [f32x8::splat(b); R];
        }
    }
    for (ak, wk) in a.chunks_exact(ROW_BLOCK).zip(wk.chunks_exact(p)) {
        let ak = &ak[i0..i0 + R];
        for (acc, &w) in acc.iter_mut().zip(&wk[o0..o0 + O]) {
            let w = f32x8::splat(w);
            for (acc, &ak) in acc.iter_mut().zip(ak) {
                *acc = ak.mul_add(w, *acc);
            }
        }
    }
    for (j, acc) in acc.iter().enumerate() {
        z[(o0 + j) * ROW_BLOCK + i0..][..R].copy_from_slice(acc);
    }
}

/// g (p × q, row-major) += d · aᵀ summed over points: `d` has p features, `a` has q. Each
/// entry sums its lanes in block order, then adds the lanes.
fn outer_sum(d: &[f32x8], a: &[f32x8], p: usize, q: usize, g: &mut [f32]) {
    let mut o = 0;
    while o + 2 <= p {
        outer_step::<2>(d, a, p, q, o, g);
        o += 2;
    }
    if o < p {
        outer_step::<1>(d, a, p, q, o, g);
    }
}

/// Rows o0..o0+O of g.
#[inline(always)]
fn outer_step<const O: usize>(
    d: &[f32x8],
    a: &[f32x8],
    p: usize,
    q: usize,
    o0: usize,
    g: &mut [f32],
) {
    let mut k = 0;
    while k < q {
        // Four inputs at a time, fewer at the end (the missing ones repeat the last and
        // are not kept).
        let kb = (q - k).min(4);
        let ks: [usize; 4] = std::array::from_fn(|i| k + i.min(kb - 1));
        let mut acc = [[f32x8::ZERO; 4]; O];
        for (d, a) in d
            .chunks_exact(p * ROW_BLOCK)
            .zip(a.chunks_exact(q * ROW_BLOCK))
        {
            // The block's rows as fixed-size arrays, taken once: the loop over its vectors
            // then has no bounds check per vector.
            let ar: [&[f32x8; ROW_BLOCK]; 4] = std::array::from_fn(|n| row(a, ks[n]));
            let dr: [&[f32x8; ROW_BLOCK]; O] = std::array::from_fn(|j| row(d, o0 + j));
            for i in 0..ROW_BLOCK {
                for (acc, dr) in acc.iter_mut().zip(&dr) {
                    for (acc, ar) in acc.iter_mut().zip(&ar) {
                        *acc = dr[i].mul_add(ar[i], *acc);
                    }
                }
            }
        }
        for (j, acc) in acc.iter().enumerate() {
            for (n, &acc) in acc.iter().enumerate().take(kb) {
                g[(o0 + j) * q + k + n] += lane_sum(acc);
            }
        }
        k += kb;
    }
}

/// Row `r` of a block (features × `ROW_BLOCK` vectors); zeros past the end (never reached:
/// blocks are whole).
#[inline(always)]
fn row(block: &[f32x8], r: usize) -> &[f32x8; ROW_BLOCK] {
    const NONE: &[f32x8; ROW_BLOCK] = &[f32x8::ZERO; ROW_BLOCK];
    block
        .get(r * ROW_BLOCK..)
        .and_then(|v| v.first_chunk::<ROW_BLOCK>())
        .unwrap_or(NONE)
}

/// A hidden layer's activation: σ(z) into `s` and SiLU, z σ(z), into `next`.
fn activate(z: &[f32x8], s: &mut Vec<f32x8>, next: &mut Vec<f32x8>) {
    avx512_if_present!(activate(z, s, next));
    activate_portable(z, s, next);
}

/// [`activate`] in `wide`'s vectors of 8.
fn activate_portable(z: &[f32x8], s: &mut Vec<f32x8>, next: &mut Vec<f32x8>) {
    s.clear();
    s.extend(z.iter().map(|&z| sigmoid(z)));
    next.clear();
    next.extend(z.iter().zip(s.iter()).map(|(&z, &s)| z * s));
}

/// The backward pass through SiLU: `d` ×= silu'(z) = σ(z)(1 + z(1 − σ(z))).
fn silu_backward(d: &mut [f32x8], z: &[f32x8], s: &[f32x8]) {
    avx512_if_present!(silu_backward(d, z, s));
    silu_backward_portable(d, z, s);
}

/// [`silu_backward`] in `wide`'s vectors of 8.
fn silu_backward_portable(d: &mut [f32x8], z: &[f32x8], s: &[f32x8]) {
    let one = f32x8::ONE;
    for ((d, &z), &s) in d.iter_mut().zip(z).zip(s) {
        *d *= s * z.mul_add(one - s, one);
    }
}

/// σ(z) for every lane.
///
/// e^−z is `wide`'s `exp` arithmetic (Cody–Waite reduction by ln 2, the same degree-5
/// polynomial, the same rounding) without its handling of NaN, infinities and subnormal
/// results, which cost a quarter of training time here: −z is clamped to [−87, 80], where
/// the power of two is a normal number, and beyond which σ is 1 or 0 in f32 anyway.
#[inline(always)]
fn sigmoid(z: f32x8) -> f32x8 {
    let one = f32x8::ONE;
    let t = (-z).max(f32x8::splat(-87.0)).min(f32x8::splat(80.0));
    let n = (t * f32x8::LOG2_E).round_ties_even();
    let r = n.mul_neg_add(f32x8::splat(0.693_359_4), t);
    let r = n.mul_neg_add(f32x8::splat(-2.121_944_4e-4), r);
    let (r2, c) = (r * r, |v: f32| f32x8::splat(v));
    let r4 = r2 * r2;
    let poly = c(1.0 / 120.0).mul_add(r, c(1.0 / 24.0)).mul_add(
        r2,
        c(1.0 / 5040.0)
            .mul_add(r, c(1.0 / 720.0))
            .mul_add(r4, c(1.0 / 6.0).mul_add(r, c(0.5))),
    );
    // 2^n from the exponent bits: n + 127 placed at bit 23.
    let biased = n + f32x8::splat(127.0 + 8_388_608.0);
    let pow2: f32x8 = bytemuck::cast(bytemuck::cast::<f32x8, wide::i32x8>(biased) << 23);
    let e = (poly.mul_add(r2, r) + one) * pow2;
    one / (one + e)
}

impl Mlp {
    /// A network with the given hidden widths (input 2, output 1), initialised as PyTorch's
    /// `nn.Linear` does: weights and biases uniform in ±1/√fan_in.
    pub fn new(hidden: &[usize], rng: &mut impl Rng) -> Self {
        let mut sizes = vec![2];
        sizes.extend_from_slice(hidden);
        sizes.push(1);
        let mut params = Vec::new();
        for w in sizes.windows(2) {
            let bound = 1.0 / (w[0] as f32).sqrt();
            for _ in 0..w[0] * w[1] + w[1] {
                params.push(rng.random_range(-bound..bound));
            }
        }
        let mut net = Self {
            sizes,
            params,
            transposed: Vec::new(),
        };
        net.transpose();
        net
    }

    /// Refreshes `transposed` from `params`.
    fn transpose(&mut self) {
        let layers: Vec<_> = self.layers().collect();
        self.transposed.clone_from(&self.params);
        for (wo, _, i, o) in layers {
            let (w, t) = (
                &self.params[wo..][..i * o],
                &mut self.transposed[wo..][..i * o],
            );
            for (k, t) in t.chunks_exact_mut(o).enumerate() {
                for (j, t) in t.iter_mut().enumerate() {
                    *t = w[j * i + k];
                }
            }
        }
    }

    /// Number of parameters.
    pub fn len(&self) -> usize {
        self.params.len()
    }

    /// Whether the network has no parameters (never, for a built one).
    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }

    /// The flat parameter vector.
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// Changes the parameters in place with `f` (given the flat vector).
    pub fn update(&mut self, f: impl FnOnce(&mut [f32])) {
        f(&mut self.params);
        self.transpose();
    }

    /// For each parameter, whether it is a weight (decayed by AdamW) rather than a bias.
    pub fn weight_mask(&self) -> Vec<bool> {
        let mut m = Vec::with_capacity(self.params.len());
        for w in self.sizes.windows(2) {
            m.extend(std::iter::repeat_n(true, w[0] * w[1]));
            m.extend(std::iter::repeat_n(false, w[1]));
        }
        m
    }

    /// (weights offset, biases offset, in, out) per layer.
    fn layers(&self) -> impl Iterator<Item = (usize, usize, usize, usize)> + '_ {
        let mut off = 0;
        self.sizes.windows(2).map(move |w| {
            let (i, o) = (w[0], w[1]);
            let l = (off, off + i * o, i, o);
            off += i * o + o;
            l
        })
    }

    /// Forward pass over the points (`x[r]`, `y[r]`) (`x` and `y` of equal length); the output
    /// (one per point) is in `ws.output()`, and `ws` keeps what [`Mlp::backward`] needs.
    pub fn forward(&self, x: &[f32], y: &[f32], ws: &mut Workspace) {
        let rows = x.len().min(y.len());
        let blocks = rows.div_ceil(LANES * ROW_BLOCK);
        let n_layers = self.sizes.len() - 1;
        ws.rows = rows;
        ws.blocks = blocks;
        ws.inputs.resize_with(n_layers, Vec::new);
        ws.sigmoids.resize_with(n_layers - 1, Vec::new);
        ws.pre.resize_with(n_layers - 1, Vec::new);
        let input = &mut ws.inputs[0];
        input.clear();
        input.resize(2 * ROW_BLOCK * blocks, f32x8::ZERO);
        let per_block = ROW_BLOCK * LANES;
        let lanes: &mut [f32] = bytemuck::cast_slice_mut(input);
        for ((block, x), y) in lanes
            .chunks_exact_mut(2 * per_block)
            .zip(x[..rows].chunks(per_block))
            .zip(y[..rows].chunks(per_block))
        {
            let (bx, by) = block.split_at_mut(per_block);
            bx[..x.len()].copy_from_slice(x);
            by[..y.len()].copy_from_slice(y);
        }
        for (l, (wo, bo, i, o)) in self.layers().enumerate() {
            let b = &self.params[bo..bo + o];
            let last = l == n_layers - 1;
            let mut z = if last {
                std::mem::take(&mut ws.output)
            } else {
                std::mem::take(&mut ws.pre[l])
            };
            z.resize(o * ROW_BLOCK * blocks, f32x8::ZERO);
            layer(
                &self.transposed[wo..bo],
                Some(b),
                o,
                i,
                &ws.inputs[l],
                &mut z,
            );
            if last {
                ws.output = z;
            } else {
                activate(&z, &mut ws.sigmoids[l], &mut ws.inputs[l + 1]);
                ws.pre[l] = z;
            }
        }
    }

    /// Backward pass of the last [`Mlp::forward`] on `ws`: `d_output` is ∂L/∂output per
    /// point; ∂L/∂θ is added to `grad` (same layout as the parameters).
    pub fn backward(&self, ws: &mut Workspace, d_output: &[f32], grad: &mut [f32]) {
        let (rows, vecs) = (ws.rows, ws.blocks * ROW_BLOCK);
        let layers: Vec<_> = self.layers().collect();
        let mut dz = std::mem::take(&mut ws.grad_a);
        let mut da = std::mem::take(&mut ws.grad_b);
        // Grown to the widest layer once, never cleared: every value read is written first
        // (zeroing them each pass showed as `memset` in the profile).
        let widest = self.sizes.iter().copied().max().unwrap_or(1) * vecs;
        for buf in [&mut dz, &mut da] {
            if buf.len() < widest {
                buf.resize(widest, f32x8::ZERO);
            }
        }
        // One feature: blocked order is point order; the padding's gradient is zero.
        let first = bytemuck::cast_slice_mut::<f32x8, f32>(&mut dz[..vecs]);
        first[..rows].copy_from_slice(&d_output[..rows]);
        first[rows..].fill(0.0);
        for (l, &(wo, bo, i, o)) in layers.iter().enumerate().rev() {
            let d = &dz[..o * vecs];
            // ∂W (out × in) += dz · aᵀ; ∂b += dz summed over points, in block order.
            outer_sum(d, &ws.inputs[l], o, i, &mut grad[wo..bo]);
            for (j, g) in grad[bo..bo + o].iter_mut().enumerate() {
                let mut sum = f32x8::ZERO;
                for block in d.chunks_exact(o * ROW_BLOCK) {
                    for &v in row(block, j) {
                        sum += v;
                    }
                }
                *g += lane_sum(sum);
            }
            if l == 0 {
                break;
            }
            // ∂a = Wᵀ · dz (W out × in is Wᵀ by input), then through SiLU:
            // silu'(z) = σ(z)(1 + z(1 − σ(z))).
            // (`layer` writes every element.)
            let a = &mut da[..i * vecs];
            layer(&self.params[wo..bo], None, i, o, d, a);
            silu_backward(a, &ws.pre[l - 1], &ws.sigmoids[l - 1]);
            std::mem::swap(&mut dz, &mut da);
        }
        ws.grad_a = dz;
        ws.grad_b = da;
    }

    /// The outputs for the points (`x[r]`, `y[r]`) into `out` (`ws` is scratch).
    pub fn predict(&self, x: &[f32], y: &[f32], out: &mut [f32], ws: &mut Workspace) {
        self.forward(x, y, ws);
        out.copy_from_slice(ws.output());
    }
}

/// AdamW (Loshchilov & Hutter) as PyTorch implements it: decoupled weight decay on the
/// parameters `decay` marks, bias-corrected moments.
#[derive(Debug, Clone)]
pub struct AdamW {
    m: Vec<f32>,
    v: Vec<f32>,
    decay: Vec<bool>,
    step: i32,
    /// β1, β2, ε, weight decay.
    pub beta1: f64,
    /// β2.
    pub beta2: f64,
    /// ε.
    pub epsilon: f64,
    /// Decoupled weight decay.
    pub weight_decay: f64,
}

impl AdamW {
    /// An optimiser for parameters where `decay[i]` says whether parameter i is decayed.
    pub fn new(decay: Vec<bool>, beta1: f64, beta2: f64, epsilon: f64, weight_decay: f64) -> Self {
        let n = decay.len();
        Self {
            m: vec![0.0; n],
            v: vec![0.0; n],
            decay,
            step: 0,
            beta1,
            beta2,
            epsilon,
            weight_decay,
        }
    }

    /// One step at learning rate `lr`.
    pub fn step(&mut self, params: &mut [f32], grad: &[f32], lr: f64) {
        self.step += 1;
        let (b1, b2) = (self.beta1 as f32, self.beta2 as f32);
        let bc1 = 1.0 - self.beta1.powi(self.step);
        let bc2 = 1.0 - self.beta2.powi(self.step);
        let step = (lr / bc1) as f32;
        let bc2_sqrt = bc2.sqrt() as f32;
        let eps = self.epsilon as f32;
        let shrink = (1.0 - lr * self.weight_decay) as f32;
        for ((((p, &g), m), v), &d) in params
            .iter_mut()
            .zip(grad)
            .zip(&mut self.m)
            .zip(&mut self.v)
            .zip(&self.decay)
        {
            if d {
                *p *= shrink;
            }
            *m = b1 * *m + (1.0 - b1) * g;
            *v = b2 * *v + (1.0 - b2) * g * g;
            *p -= step * *m / ((*v).sqrt() / bc2_sqrt + eps);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// Loss L = Σ_rows c_row · output_row, so ∂L/∂output = c.
    fn loss(net: &Mlp, x: &[f32], y: &[f32], c: &[f32]) -> f64 {
        let mut ws = Workspace::default();
        net.forward(x, y, &mut ws);
        ws.output()
            .iter()
            .zip(c)
            .map(|(&o, &c)| f64::from(o) * f64::from(c))
            .sum()
    }

    #[test]
    fn the_backward_pass_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let net = Mlp::new(&[7, 5, 6], &mut rng);
        let rows = 19; // not a multiple of any kernel width
        let x: Vec<f32> = (0..rows).map(|_| rng.random_range(-1.0..1.0)).collect();
        let y: Vec<f32> = (0..rows).map(|_| rng.random_range(-1.0..1.0)).collect();
        let c: Vec<f32> = (0..rows).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut ws = Workspace::default();
        net.forward(&x, &y, &mut ws);
        assert_eq!(ws.output().len(), rows);
        let mut grad = vec![0.0; net.len()];
        net.backward(&mut ws, &c, &mut grad);
        let h = 1e-2f32;
        let mut worst = 0.0f64;
        for (k, &analytic) in grad.iter().enumerate() {
            let mut plus = net.clone();
            plus.update(|p| p[k] += h);
            let mut minus = net.clone();
            minus.update(|p| p[k] -= h);
            let numeric =
                (loss(&plus, &x, &y, &c) - loss(&minus, &x, &y, &c)) / (2.0 * f64::from(h));
            let err = (numeric - f64::from(analytic)).abs() / (1e-2 + numeric.abs());
            worst = worst.max(err);
        }
        assert!(worst < 2e-3, "worst relative gradient error {worst:.2e}");
        // And the gradient is not trivially zero.
        assert!(grad.iter().filter(|g| g.abs() > 1e-4).count() > net.len() / 2);
    }

    #[test]
    fn adamw_decays_weights_but_not_biases() {
        let mut opt = AdamW::new(vec![true, false], 0.9, 0.999, 1e-8, 0.5);
        let mut p = vec![1.0f32, 1.0];
        opt.step(&mut p, &[0.0, 0.0], 0.1);
        assert!((p[0] - 0.95).abs() < 1e-6, "{p:?}");
        assert_eq!(p[1], 1.0);
        // With a gradient, the first step moves by about lr in the gradient's sign.
        let mut opt = AdamW::new(vec![false], 0.9, 0.999, 1e-8, 0.0);
        let mut p = vec![0.0f32];
        opt.step(&mut p, &[3.0], 0.1);
        assert!((p[0] + 0.1).abs() < 1e-5, "{p:?}");
    }

    #[cfg(target_arch = "x86_64")]
    /// Vectors of values spread over what the network sees and beyond: small and large,
    /// both signs, the sigmoid's clamps, zeros of both signs.
    fn values(n: usize, rng: &mut ChaCha8Rng) -> Vec<f32x8> {
        let mut v: Vec<f32> = (0..n * LANES)
            .map(|i| match i % 7 {
                0 => rng.random_range(-100.0f32..100.0),
                1 => rng.random_range(-1e-3f32..1e-3),
                _ => rng.random_range(-4.0f32..4.0),
            })
            .collect();
        for (i, x) in [0.0, -0.0, 87.5, -87.5, 80.0, -80.0, 1e30, -1e30]
            .into_iter()
            .enumerate()
        {
            v[i * 5] = x;
        }
        v.chunks_exact(LANES)
            .map(|c| f32x8::from(<[f32; LANES]>::try_from(c).unwrap_or_default()))
            .collect()
    }

    #[cfg(target_arch = "x86_64")]
    fn bits(v: &[f32x8]) -> Vec<u32> {
        v.iter()
            .flat_map(|v| v.to_array().map(f32::to_bits))
            .collect()
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_avx512_passes_give_the_portable_bits() {
        if !groundwork_core::cpu::avx512() {
            eprintln!("no AVX-512 here (or turned off): only the portable passes run");
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        // Widths as the network's (2 → 32 → 32 → 1) and odd ones (single outputs left
        // after blocks of four), with and without a bias; three blocks of points.
        for (p, q) in [(32, 2), (32, 32), (1, 32), (2, 32), (7, 5), (5, 1)] {
            let blocks = 3;
            let a = values(q * ROW_BLOCK * blocks, &mut rng);
            let wk: Vec<f32> = (0..p * q).map(|_| rng.random_range(-1.0..1.0)).collect();
            let b: Vec<f32> = (0..p).map(|_| rng.random_range(-1.0..1.0)).collect();
            for bias in [Some(&b[..]), None] {
                let mut want = vec![f32x8::ZERO; p * ROW_BLOCK * blocks];
                let mut got = want.clone();
                layer_portable(&wk, bias, p, q, &a, &mut want);
                #[allow(unsafe_code)]
                // SAFETY: the CPU has AVX-512 (checked above).
                unsafe {
                    avx512::layer(&wk, bias, p, q, &a, &mut got)
                };
                assert_eq!(
                    bits(&got),
                    bits(&want),
                    "layer {p} × {q}, bias {}",
                    bias.is_some()
                );
            }
        }
        let z = values(4 * 40, &mut rng);
        let (mut s0, mut n0, mut s1, mut n1) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        activate_portable(&z, &mut s0, &mut n0);
        #[allow(unsafe_code)]
        // SAFETY: as above.
        unsafe {
            avx512::activate(&z, &mut s1, &mut n1)
        };
        assert_eq!(bits(&s1), bits(&s0), "σ");
        assert_eq!(bits(&n1), bits(&n0), "SiLU");
        let d = values(z.len(), &mut rng);
        let (mut d0, mut d1) = (d.clone(), d);
        silu_backward_portable(&mut d0, &z, &s0);
        #[allow(unsafe_code)]
        // SAFETY: as above.
        unsafe {
            avx512::silu_backward(&mut d1, &z, &s0)
        };
        assert_eq!(bits(&d1), bits(&d0), "SiLU backward");
    }

    #[test]
    fn sigmoid_is_wides_exp_where_it_is_defined() {
        // Every argument where e^−z is a normal number, at a step that hits every exponent.
        let mut z = -80.0f32;
        while z <= 87.0 {
            let v = f32x8::from([
                z,
                -z,
                z * 0.5,
                z * 0.25,
                z * 0.125,
                z + 0.3,
                z - 0.3,
                z * 0.9,
            ]);
            let want = f32x8::ONE / (f32x8::ONE + (-v.max(f32x8::splat(-80.0))).exp());
            assert_eq!(sigmoid(v).to_array(), want.to_array(), "at {z}");
            z += 0.0137;
        }
        // Beyond the clamp, σ is exactly 0 or 1 as before.
        let v = f32x8::from([-1e3, -100.0, -80.0, 87.0, 88.0, 100.0, 1e3, 1e30]);
        let want = f32x8::ONE / (f32x8::ONE + (-v.max(f32x8::splat(-80.0))).exp());
        assert_eq!(sigmoid(v).to_array(), want.to_array());
    }

    #[test]
    fn sigmoid_matches_the_scalar_formula() {
        let z: Vec<f32> = (-200..200).map(|i| i as f32 * 0.37).collect();
        for (&z, &s) in z.iter().zip(
            z.chunks_exact(8)
                .flat_map(|z| {
                    sigmoid(f32x8::from(<[f32; 8]>::try_from(z).unwrap_or_default())).to_array()
                })
                .collect::<Vec<_>>()
                .iter(),
        ) {
            let want = 1.0 / (1.0 + (-f64::from(z)).exp());
            assert!(
                (f64::from(s) - want).abs() < 1e-6,
                "σ({z}) = {s}, want {want}"
            );
        }
    }
}
