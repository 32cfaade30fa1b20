//! A small fully connected network with SiLU activations, its hand-written backward pass
//! and AdamW: the elevation map g(x, y) of the PseudoLabeler.
//!
//! Activations are row-major (one row per point), so every layer is one `sgemm` of
//! `matrixmultiply`. Parameters live in one flat vector (per layer: weights out × in, then
//! biases), which keeps the optimiser a single loop.

use rand::Rng;
use wide::f32x8;

/// The network's shape and parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Mlp {
    /// Layer widths, input first (2) and output last (1).
    sizes: Vec<usize>,
    /// All parameters, layer by layer: weights (out × in, row-major), then biases.
    params: Vec<f32>,
}

/// Intermediate values of one forward pass, kept for the backward pass. Reused across
/// iterations so that training allocates nothing per step.
#[derive(Debug, Default, Clone)]
pub struct Workspace {
    /// Per layer: its input activations (rows × in).
    inputs: Vec<Vec<f32>>,
    /// Per hidden layer: σ(z) of its pre-activations (rows × out).
    sigmoids: Vec<Vec<f32>>,
    /// Per hidden layer: its pre-activations z (rows × out).
    pre: Vec<Vec<f32>>,
    /// The output, one value per row.
    output: Vec<f32>,
    /// Gradient buffers (rows × widest layer), two for ping-pong.
    grad_a: Vec<f32>,
    grad_b: Vec<f32>,
}

impl Workspace {
    /// The last forward pass's outputs.
    pub fn output(&self) -> &[f32] {
        &self.output
    }
}

/// C (m × n, row-major) = A · B + beta · C, with arbitrary strides for A and B.
///
/// `unsafe` because `matrixmultiply` takes raw pointers and strides.
/// The bounds are checked here, always, so no caller can make it read or write outside
/// the slices.
#[allow(clippy::too_many_arguments, unsafe_code)]
fn gemm(
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    (rsa, csa): (usize, usize),
    b: &[f32],
    (rsb, csb): (usize, usize),
    beta: f32,
    c: &mut [f32],
) {
    assert!(m == 0 || k == 0 || a.len() > (m - 1) * rsa + (k - 1) * csa);
    assert!(k == 0 || n == 0 || b.len() > (k - 1) * rsb + (n - 1) * csb);
    assert!(c.len() >= m * n);
    // SAFETY: the asserts above show that every element the strides address lies inside
    // its slice, and c cannot alias a or b (a mutable and two shared borrows).
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            1.0,
            a.as_ptr(),
            rsa as isize,
            csa as isize,
            b.as_ptr(),
            rsb as isize,
            csb as isize,
            beta,
            c.as_mut_ptr(),
            n as isize,
            1,
        );
    }
}

/// σ(z) for a slice, eight lanes at a time (`f32::exp` is a scalar libm call).
fn sigmoid_into(z: &[f32], s: &mut [f32]) {
    let one = f32x8::splat(1.0);
    let mut zc = z.chunks_exact(8);
    let mut sc = s.chunks_exact_mut(8);
    for (zi, si) in (&mut zc).zip(&mut sc) {
        let v = f32x8::from(<[f32; 8]>::try_from(zi).unwrap_or_default());
        // Clamped so that exp never overflows: σ(−80) is 0 in f32 anyway.
        let e = (-v.max(f32x8::splat(-80.0))).exp();
        si.copy_from_slice(&(one / (one + e)).to_array());
    }
    for (zi, si) in zc.remainder().iter().zip(sc.into_remainder()) {
        *si = 1.0 / (1.0 + (-zi.max(-80.0)).exp());
    }
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
        Self { sizes, params }
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

    /// The flat parameter vector, to update.
    pub fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
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

    /// Forward pass over `x` (rows × 2, row-major); the output (one per row) is in
    /// `ws.output()`, and `ws` keeps what [`Mlp::backward`] needs.
    pub fn forward(&self, x: &[f32], ws: &mut Workspace) {
        let rows = x.len() / 2;
        let n_layers = self.sizes.len() - 1;
        ws.inputs.resize_with(n_layers, Vec::new);
        ws.sigmoids.resize_with(n_layers - 1, Vec::new);
        ws.pre.resize_with(n_layers - 1, Vec::new);
        ws.inputs[0].clear();
        ws.inputs[0].extend_from_slice(&x[..rows * 2]);
        for (l, (wo, bo, i, o)) in self.layers().enumerate() {
            let w = &self.params[wo..bo];
            let b = &self.params[bo..bo + o];
            let last = l == n_layers - 1;
            let mut z = if last {
                std::mem::take(&mut ws.output)
            } else {
                std::mem::take(&mut ws.pre[l])
            };
            z.resize(rows * o, 0.0);
            for row in z.chunks_exact_mut(o) {
                row.copy_from_slice(b);
            }
            // z = a · wᵀ + b: w is out × in row-major, so wᵀ has strides (1, in).
            gemm(rows, i, o, &ws.inputs[l], (i, 1), w, (1, i), 1.0, &mut z);
            if last {
                ws.output = z;
            } else {
                let mut s = std::mem::take(&mut ws.sigmoids[l]);
                s.resize(z.len(), 0.0);
                sigmoid_into(&z, &mut s);
                let next = &mut ws.inputs[l + 1];
                next.clear();
                next.extend(z.iter().zip(&s).map(|(&z, &s)| z * s));
                ws.sigmoids[l] = s;
                ws.pre[l] = z;
            }
        }
    }

    /// Backward pass of the last [`Mlp::forward`] on `ws`: `d_output` is ∂L/∂output per
    /// row; ∂L/∂θ is added to `grad` (same layout as the parameters).
    pub fn backward(&self, ws: &mut Workspace, d_output: &[f32], grad: &mut [f32]) {
        let rows = d_output.len();
        let layers: Vec<_> = self.layers().collect();
        let mut dz = std::mem::take(&mut ws.grad_a);
        let mut da = std::mem::take(&mut ws.grad_b);
        dz.clear();
        dz.extend_from_slice(d_output);
        for (l, &(wo, bo, i, o)) in layers.iter().enumerate().rev() {
            let a = &ws.inputs[l];
            // ∂W (out × in) += dzᵀ · a; dz is rows × out.
            gemm(o, rows, i, &dz, (1, o), a, (i, 1), 1.0, &mut grad[wo..bo]);
            for row in dz.chunks_exact(o) {
                for (g, &d) in grad[bo..bo + o].iter_mut().zip(row) {
                    *g += d;
                }
            }
            if l == 0 {
                break;
            }
            // ∂a (rows × in) = dz · W, then through SiLU: silu'(z) = σ(z)(1 + z(1 − σ(z))).
            da.resize(rows * i, 0.0);
            gemm(
                rows,
                o,
                i,
                &dz,
                (o, 1),
                &self.params[wo..bo],
                (i, 1),
                0.0,
                &mut da,
            );
            let (z, s) = (&ws.pre[l - 1], &ws.sigmoids[l - 1]);
            for ((d, &z), &s) in da.iter_mut().zip(z).zip(s) {
                *d *= s * (1.0 + z * (1.0 - s));
            }
            std::mem::swap(&mut dz, &mut da);
        }
        ws.grad_a = dz;
        ws.grad_b = da;
    }

    /// The outputs for `x` (rows × 2) into `out` (`ws` is scratch).
    pub fn predict(&self, x: &[f32], out: &mut [f32], ws: &mut Workspace) {
        self.forward(x, ws);
        out.copy_from_slice(&ws.output);
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
    fn loss(net: &Mlp, x: &[f32], c: &[f32]) -> f64 {
        let mut ws = Workspace::default();
        net.forward(x, &mut ws);
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
        let x: Vec<f32> = (0..rows * 2).map(|_| rng.random_range(-1.0..1.0)).collect();
        let c: Vec<f32> = (0..rows).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut ws = Workspace::default();
        net.forward(&x, &mut ws);
        let mut grad = vec![0.0; net.len()];
        net.backward(&mut ws, &c, &mut grad);
        let h = 1e-2f32;
        let mut worst = 0.0f64;
        for (k, &analytic) in grad.iter().enumerate() {
            let mut plus = net.clone();
            plus.params_mut()[k] += h;
            let mut minus = net.clone();
            minus.params_mut()[k] -= h;
            let numeric = (loss(&plus, &x, &c) - loss(&minus, &x, &c)) / (2.0 * f64::from(h));
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

    #[test]
    fn sigmoid_matches_the_scalar_formula() {
        let z: Vec<f32> = (-200..200).map(|i| i as f32 * 0.37).collect();
        let mut s = vec![0.0; z.len()];
        sigmoid_into(&z, &mut s);
        for (&z, &s) in z.iter().zip(&s) {
            let want = 1.0 / (1.0 + (-f64::from(z)).exp());
            assert!(
                (f64::from(s) - want).abs() < 1e-6,
                "σ({z}) = {s}, want {want}"
            );
        }
    }
}
