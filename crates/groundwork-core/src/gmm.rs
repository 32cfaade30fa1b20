//! One segment's Gaussian mixture, fitted with EM (paper §III-B).
//!
//! Choices where the paper is silent (see also docs/algorithm.md):
//! - EM stops after `max_iterations` or as soon as the mean log-likelihood per point
//!   improves by less than `tolerance`; that per-segment test lets easy segments stop
//!   after two or three iterations while hard ones get up to the cap.
//! - `covariance_regularization` is added to the diagonal after every M-step, so no
//!   component becomes singular (planar patches, repeated points, tiny segments).
//! - Pruning follows the paper: after every iteration, components that are the most
//!   likely one for fewer than τ_N points are removed. A segment with fewer than τ_N points
//!   therefore ends with no component, i.e. no model: its points get probability 0 in a
//!   single-frame query (older frames may still answer for them in a multi-frame query).
//! - Work is done on coordinates relative to the segment centroid, so second moments do
//!   not lose precision to catastrophic cancellation far from the sensor.

use wide::bytemuck::cast;
use wide::{f32x8, i32x8};

use crate::config::GmmConfig;
use crate::fastmath::{exp_nonpositive, ln_from, ln_positive, round_i32};

const LN_2PI: f64 = 1.837_877_066_409_345_5;

/// A symmetric 3×3 matrix stored as its upper triangle: xx, xy, xz, yy, yz, zz.
pub type Sym3 = [f64; 6];

/// A fitted Gaussian component (in the frame the points were given in).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gaussian {
    /// Mixture weight π.
    pub weight: f64,
    /// Mean μ.
    pub mean: [f64; 3],
    /// Covariance Σ (regularised).
    pub covariance: Sym3,
}

/// Outcome of fitting one segment.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SegmentFit {
    /// Surviving components (may be empty: see the module notes).
    pub components: Vec<Gaussian>,
    /// EM iterations run.
    pub iterations: u32,
    /// Mean log-likelihood per point after the last iteration.
    pub mean_log_likelihood: f64,
}

/// Inverse and log-determinant of a symmetric positive-definite 3×3 matrix, or `None` if it
/// is not positive definite.
pub fn sym3_inverse(m: &Sym3) -> Option<(Sym3, f64)> {
    let [a, b, c, d, e, f] = *m;
    // Cofactors of [[a b c] [b d e] [c e f]].
    let c00 = d * f - e * e;
    let c01 = c * e - b * f;
    let c02 = b * e - c * d;
    let det = a * c00 + b * c01 + c * c02;
    if !(det > 0.0 && det.is_finite() && a > 0.0) {
        return None;
    }
    let c11 = a * f - c * c;
    let c12 = b * c - a * e;
    let c22 = a * d - b * b;
    let inv = 1.0 / det;
    Some((
        [
            c00 * inv,
            c01 * inv,
            c02 * inv,
            c11 * inv,
            c12 * inv,
            c22 * inv,
        ],
        det.ln(),
    ))
}

/// Mahalanobis form dᵀ P d for a symmetric P stored as its upper triangle.
#[inline(always)]
pub fn quad_form(p: &Sym3, dx: f64, dy: f64, dz: f64) -> f64 {
    p[0] * dx * dx
        + p[3] * dy * dy
        + p[5] * dz * dz
        + 2.0 * (p[1] * dx * dy + p[2] * dx * dz + p[4] * dy * dz)
}

/// Component parameters prepared for evaluating log(π·N(x | μ, Σ)).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Evaluator {
    pub mean: [f64; 3],
    pub precision: Sym3,
    /// ln π − ½ ln|Σ| − (3/2) ln 2π
    pub log_coef: f64,
}

impl Evaluator {
    /// `None` when the covariance is not positive definite or the weight is not positive.
    pub fn new(g: &Gaussian) -> Option<Self> {
        let (precision, log_det) = sym3_inverse(&g.covariance)?;
        if g.weight.is_nan() || g.weight <= 0.0 {
            return None;
        }
        Some(Self {
            mean: g.mean,
            precision,
            log_coef: g.weight.ln() - 0.5 * log_det - 1.5 * LN_2PI,
        })
    }

    /// Unit covariance at the component's mean, for a component whose covariance is unusable.
    pub fn unit(g: &Gaussian) -> Self {
        Self {
            mean: g.mean,
            precision: [1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
            log_coef: g.weight.max(1e-300).ln() - 1.5 * LN_2PI,
        }
    }
}

/// U (rows' non-zero entries) and b = U·mean with UᵀU = P/2, for P given by its upper
/// triangle. A precision that is not positive definite (not produced by the fit, which
/// regularises covariances) is factored through its diagonal, clamped at 0.
pub(crate) fn half_precision_factor(p: &[f64; 6], mean: &[f64; 3]) -> ([f64; 6], [f64; 3]) {
    // Cholesky by hand: nalgebra's generic factorisation, called per component and EM
    // iteration, was 4 % of a scan.
    let h = p.map(|v| 0.5 * v);
    let u0 = h[0].sqrt();
    let (u1, u2) = (h[1] / u0, h[2] / u0);
    let u3 = (h[3] - u1 * u1).sqrt();
    let u4 = (h[4] - u1 * u2) / u3;
    let u5 = (h[5] - u2 * u2 - u4 * u4).sqrt();
    let u = [u0, u1, u2, u3, u4, u5];
    // `> 0` is false for NaN too: not positive definite.
    let u = if u0 > 0.0 && u3 > 0.0 && u5 > 0.0 {
        u
    } else {
        let d = |v: f64| v.max(0.0).sqrt();
        [d(h[0]), 0.0, 0.0, d(h[3]), 0.0, d(h[5])]
    };
    let b = [
        u[0] * mean[0] + u[1] * mean[1] + u[2] * mean[2],
        u[3] * mean[1] + u[4] * mean[2],
        u[5] * mean[2],
    ];
    (u, b)
}

/// Lanes of the hand-shaped reductions: 8 × f32 fills an AVX register and two SSE ones.
const LANES: usize = 8;

/// Per-thread buffers for EM, reused across segments so fitting does not allocate per
/// segment once warm.
#[derive(Debug, Default)]
pub struct EmScratch {
    x: Vec<f32>,
    y: Vec<f32>,
    z: Vec<f32>,
    /// Fit weight: 1 inside a drawn cube, in (0, 1) near a face between a drawn and an
    /// undrawn cube, 0 for the padding up to a multiple of `LANES`.
    w: Vec<f32>,
    /// Component-major log-densities, then responsibilities: `k × padded`.
    resp: Vec<f32>,
    max: Vec<f32>,
    /// w / Σ_c e^{l_c − max}
    inv: Vec<f32>,
    best: Vec<u32>,
    /// (sort key, index) of the candidate points, in canonical order.
    order: Vec<(u64, u32)>,
    /// Indices of the points fitted (weight > 0), in canonical order.
    fitted: Vec<u32>,
    /// Cube hash of every point of the segment.
    hashes: Vec<u32>,
    /// 1 where a point lies within the face band of its cube.
    near: Vec<u8>,
    spare: Vec<(u64, u32)>,
    counts: Vec<u32>,
    /// Summary cells' scatter per point (xx, xy, xz, yy, yz, zz), beside their means in
    /// `x`, `y`, `z` and counts in `w`: per block of `LANES` cells, the six entries' lanes
    /// one after the other (one stream for the E- and M-step loops, not six).
    cov: Vec<f32>,
    /// Open-addressing table of the summary cells (index into `cells`, `u32::MAX` free).
    slots: Vec<u32>,
    cells: Vec<Cell>,
    /// Every point's summary cell and place in it (quanta from the corner), x, y, z blocks.
    keys: Vec<i32>,
    places: Vec<i32>,
    /// EM's components, the M-step's next ones, their support and their E-step forms:
    /// reused from iteration to iteration and segment to segment (a `Vec` each per
    /// iteration was about 2,800 allocations a KITTI scan).
    comps: Vec<Gaussian>,
    next: Vec<Gaussian>,
    owned: Vec<u32>,
    lanes: Vec<Lanes>,
}

/// Sorts `src` into `dst[..src.len()]` (`dst` grows as needed, never shrinks: refilling it
/// per segment was a memset of every point) by key, then by `tie` for equal keys; every
/// key is at most `max_key`. Keys spread evenly, so a counting sort on their top bits
/// (about one bucket per element) leaves only neighbours out of order, which an insertion
/// sort then fixes: linear time, against n·log n comparisons of a general sort.
fn sort_by_key(
    src: &[(u64, u32)],
    dst: &mut Vec<(u64, u32)>,
    counts: &mut Vec<u32>,
    max_key: u64,
    mut tie: impl FnMut(u32, u32) -> std::cmp::Ordering,
) {
    let m = src.len();
    if dst.len() < m {
        dst.resize(m, (0, 0));
    }
    let v = &mut dst[..m];
    if m <= 16 {
        v.copy_from_slice(src);
    } else {
        let bits = usize::BITS - (m - 1).leading_zeros(); // 2^bits ≥ m
        let shift = (u64::BITS - max_key.leading_zeros()).saturating_sub(bits);
        counts.clear();
        counts.resize((max_key >> shift) as usize + 2, 0);
        for e in src {
            counts[(e.0 >> shift) as usize + 1] += 1;
        }
        for b in 1..counts.len() {
            counts[b] += counts[b - 1];
        }
        for e in src {
            let slot = &mut counts[(e.0 >> shift) as usize];
            v[*slot as usize] = *e;
            *slot += 1;
        }
    }
    for i in 1..m {
        let e = v[i];
        let mut j = i;
        while j > 0 && (v[j - 1].0 > e.0 || (v[j - 1].0 == e.0 && tie(v[j - 1].1, e.1).is_gt())) {
            v[j] = v[j - 1];
            j -= 1;
        }
        v[j] = e;
    }
}

/// Edge of the cubes that choose a dense segment's fit points (m). Much finer than any
/// component (a ground component spans metres and a few centimetres of height), coarse
/// enough that a rounding error almost never moves a point into another cube.
const CUBE_EDGE: f64 = 0.02;
/// Within this share of the edge from a face, a point's weight slides linearly from its
/// own cube's draw to its neighbour's (half and half on the face): the fit is a continuous
/// function of the coordinates. One ulp of an f32 coordinate at 50 m is 2e-4 of the edge.
const FACE_BAND: f64 = 0.005;

/// The mean of `v` (not empty), exactly independent of the order of `v`: each value is
/// rounded to a multiple of 2⁻²⁴ m (6e-8 m) and the multiples are summed as integers. A
/// float sum would round differently for every order of the same points. Values beyond
/// ±2²⁷ m (no LiDAR range) give a meaningless mean, never a panic.
fn exact_mean(v: &[f64]) -> f64 {
    // Adding 1.5·2²⁸ puts a value in the binade whose ulp is 2⁻²⁴: the low bits of the sum
    // are the value rounded to that ulp (round to nearest even), read as an integer.
    const MAGIC: f64 = 402_653_184.0; // 1.5 · 2^28
    const QUANTUM: f64 = 1.0 / 16_777_216.0; // 2^-24
    let base = MAGIC.to_bits() as i64;
    let sum = v.iter().fold(0i64, |acc, &x| {
        acc.wrapping_add(((x + MAGIC).to_bits() as i64).wrapping_sub(base))
    });
    sum as f64 * QUANTUM / v.len() as f64
}

/// A well-mixed 32-bit hash of a cube's integer coordinates (murmur3's finaliser). 32-bit
/// multiplies vectorise on every x86-64-v3 and aarch64 CPU; 64-bit ones do not.
#[inline(always)]
fn cube_hash(ix: i32, iy: i32, iz: i32) -> u32 {
    let mut h = (ix as u32)
        .wrapping_mul(0x9e37_79b1)
        .wrapping_add((iy as u32).wrapping_mul(0x85eb_ca77))
        .wrapping_add((iz as u32).wrapping_mul(0xc2b2_ae3d));
    h ^= h >> 16;
    h = h.wrapping_mul(0x85eb_ca6b);
    h ^= h >> 13;
    h = h.wrapping_mul(0xc2b2_ae35);
    h ^ (h >> 16)
}

/// Cube index and place in the cube (in [0, 1)) of one coordinate.
#[inline(always)]
fn cube_coordinate(v: f64) -> (i32, f64) {
    // Beyond ±2³¹ cubes (43,000 km) the index wraps, harmlessly.
    let q = v * (1.0 / CUBE_EDGE);
    let f = q.floor();
    (round_i32(f), q - f)
}

/// Share of the own cube (vs the neighbour `step` away) for a place `t` in the cube:
/// 1 outside the band, ½ on the face.
#[inline(always)]
fn face_share(t: f64) -> (f64, i32) {
    if t < FACE_BAND {
        (0.5 + 0.5 * t / FACE_BAND, -1)
    } else if t > 1.0 - FACE_BAND {
        (0.5 + 0.5 * (1.0 - t) / FACE_BAND, 1)
    } else {
        (1.0, 0)
    }
}

/// Fit weight of a point near a face: the draws (`hash <= threshold`) of its cube and of
/// the neighbours across the near faces, blended trilinearly by [`face_share`].
fn band_weight(x: f64, y: f64, z: f64, threshold: u32) -> f32 {
    let ((cx, tx), (cy, ty), (cz, tz)) =
        (cube_coordinate(x), cube_coordinate(y), cube_coordinate(z));
    let shares = [face_share(tx), face_share(ty), face_share(tz)];
    let mut w = 0.0;
    for corner in 0..8u32 {
        let mut share = 1.0;
        let mut cube = [cx, cy, cz];
        for (a, &(own, step)) in shares.iter().enumerate() {
            if corner >> a & 1 == 0 {
                share *= own;
            } else if step == 0 {
                share = 0.0;
            } else {
                share *= 1.0 - own;
                cube[a] = cube[a].saturating_add(step);
            }
        }
        if share > 0.0 && cube_hash(cube[0], cube[1], cube[2]) <= threshold {
            w += share;
        }
    }
    w as f32
}

/// Puts the points whose cube is drawn (`hash <= threshold`) and, when `banded`, those
/// near a face of their cube, into `spare[..kept]` (grown as needed, never cleared) with
/// their sort key, and returns `kept`. The key is the cube hash rotated, so that the draw
/// (its top bits) does not crowd the counting sort's buckets. Branch-free: a filtered push
/// mispredicted on every other point.
fn gather_candidates(
    hashes: &[u32],
    near: &[u8],
    spare: &mut Vec<(u64, u32)>,
    threshold: u32,
    banded: bool,
) -> usize {
    if spare.len() < hashes.len() {
        spare.resize(hashes.len(), (0, 0));
    }
    let mut kept = 0;
    for (i, (&h, &near)) in hashes.iter().zip(near).enumerate() {
        spare[kept] = (u64::from(h.rotate_left(16)), i as u32);
        kept += usize::from((h <= threshold) | (banded & (near != 0)));
    }
    kept
}

/// f32 parameters of one component for the vectorised E-step.
#[derive(Debug, Clone, Copy)]
struct Lanes {
    /// The mean (the M-step's moments are taken about it).
    m: [f32; 3],
    /// log π N(x) = c − |U·x − b|² (see [`half_precision_factor`]): nine fused
    /// multiply-adds per point.
    u: [f32; 6],
    b: [f32; 3],
    c: f32,
}

/// The `LANES` values of `v` from `o` (zeros past its end, which the callers never reach:
/// every array holds a multiple of `LANES`).
#[inline(always)]
fn v8(v: &[f32], o: usize) -> f32x8 {
    f32x8::new(
        v.get(o..)
            .and_then(|v| v.first_chunk::<LANES>())
            .copied()
            .unwrap_or([0.0; LANES]),
    )
}

/// Blocks of points whose sums of responsibilities share one ln (see the E-step).
const LN_GROUP: usize = 16;

/// Fills `s.x`, `s.y`, `s.z`, `s.w` (unpadded) with the points EM fits of a segment
/// fitted by subsample (or whole), relative to the returned centroid; returns the centroid
/// and the total fit weight.
fn subsample(
    xs: &[f64],
    ys: &[f64],
    zs: &[f64],
    cfg: &GmmConfig,
    s: &mut EmScratch,
) -> ([f64; 3], f64) {
    let n = xs.len();
    // Dense segments are fitted on a subsample of about `max_fit_points` points chosen by
    // the geometry: space is cut into 2 cm cubes, and a cube is drawn (its points fitted)
    // when a hash of its integer coordinates falls within the segment's share. Near a face
    // a point's weight slides between the draws of the cubes it touches, so the fit is a
    // continuous function of the coordinates: a rounding error does not pick another
    // subsample. Points are fitted in the order of their cube's hash, then of their
    // coordinates: EM's float sums see the same sequence whatever order a driver delivers
    // points in, so the fit (and every output) is exactly independent of it. Support
    // counts are scaled back to the whole segment for τ_N pruning.
    let stride = match cfg.max_fit_points {
        0 => 1,
        cap => n.div_ceil(cap as usize).max(1),
    };
    let threshold = (u64::from(u32::MAX) / stride as u64) as u32;
    let banded = stride > 1;
    // Cube hashes and "near a face" first in a plain loop (vectorised), then the candidate
    // points (`gather_candidates`).
    // The cubes are laid from the segment's mean, not from the sensor: a scan moved as a
    // whole (a pose, a frame change, the last bit of every coordinate rounded up) keeps
    // every point in its cube. (Buffers grown as needed, never shrunk: no memset per
    // segment.)
    if s.hashes.len() < n {
        s.hashes.resize(n, 0);
    }
    if s.near.len() < n {
        s.near.resize(n, 0);
    }
    let cells = s.hashes[..n].iter_mut().zip(&mut s.near[..n]);
    let points = xs.iter().zip(ys).zip(zs);
    let anchor = if banded {
        [xs, ys, zs].map(exact_mean)
    } else {
        [0.0; 3]
    };
    if banded {
        for ((h, near), ((&x, &y), &z)) in cells.zip(points) {
            let ((cx, tx), (cy, ty), (cz, tz)) = (
                cube_coordinate(x - anchor[0]),
                cube_coordinate(y - anchor[1]),
                cube_coordinate(z - anchor[2]),
            );
            let band = |t: f64| !(FACE_BAND..=1.0 - FACE_BAND).contains(&t);
            *h = cube_hash(cx, cy, cz);
            *near = u8::from(band(tx) | band(ty) | band(tz));
        }
    } else {
        // Every point is fitted: only the order is needed, from the coordinates' bits.
        let fold = |v: f64| {
            let b = v.to_bits();
            (b ^ (b >> 32)) as u32 as i32
        };
        for ((h, near), ((&x, &y), &z)) in cells.zip(points) {
            *h = cube_hash(fold(x), fold(y), fold(z));
            *near = 0;
        }
    }
    let kept = gather_candidates(
        &s.hashes[..n],
        &s.near[..n],
        &mut s.spare,
        threshold,
        banded,
    );
    let lexicographic = |a: u32, b: u32| {
        let (a, b) = (a as usize, b as usize);
        xs[a]
            .total_cmp(&xs[b])
            .then(ys[a].total_cmp(&ys[b]))
            .then(zs[a].total_cmp(&zs[b]))
    };
    sort_by_key(
        &s.spare[..kept],
        &mut s.order,
        &mut s.counts,
        u64::from(u32::MAX),
        lexicographic,
    );
    for v in [&mut s.x, &mut s.y, &mut s.z, &mut s.w] {
        v.clear();
    }
    // Every candidate written at the running end, kept when its weight is positive
    // (branch-free, as `gather_candidates`).
    s.fitted.resize(kept, 0);
    s.w.resize(kept, 0.0);
    let mut fitted = 0;
    for &(_, i) in &s.order[..kept] {
        let w = if banded && s.near[i as usize] != 0 {
            let i = i as usize;
            band_weight(
                xs[i] - anchor[0],
                ys[i] - anchor[1],
                zs[i] - anchor[2],
                threshold,
            )
        } else {
            1.0
        };
        s.fitted[fitted] = i;
        s.w[fitted] = w;
        fitted += usize::from(w > 0.0);
    }
    s.fitted.truncate(fitted);
    s.w.truncate(fitted);
    if s.fitted.is_empty() {
        // No cube drawn (a few cubes holding every point, none within the share): fit
        // every point, in the same canonical order, rather than nothing.
        let all = gather_candidates(&s.hashes[..n], &s.near[..n], &mut s.spare, u32::MAX, false);
        sort_by_key(
            &s.spare[..all],
            &mut s.order,
            &mut s.counts,
            u64::from(u32::MAX),
            lexicographic,
        );
        s.fitted.extend(s.order[..all].iter().map(|e| e.1));
        s.w.resize(all, 1.0);
    }
    let total_weight: f64 = s.w.iter().map(|&w| f64::from(w)).sum();
    let mut centroid = [0.0; 3];
    for (&i, &w) in s.fitted.iter().zip(&s.w) {
        let (i, w) = (i as usize, f64::from(w));
        centroid[0] += w * xs[i];
        centroid[1] += w * ys[i];
        centroid[2] += w * zs[i];
    }
    let centroid = centroid.map(|c| c / total_weight);
    // Written in place, not pushed: a push's length update per point kept the scattered
    // reads from overlapping.
    let m = s.fitted.len();
    for v in [&mut s.x, &mut s.y, &mut s.z] {
        v.resize(m, 0.0);
    }
    for (((&i, x), y), z) in s.fitted.iter().zip(&mut s.x).zip(&mut s.y).zip(&mut s.z) {
        let i = i as usize;
        *x = (xs[i] - centroid[0]) as f32;
        *y = (ys[i] - centroid[1]) as f32;
        *z = (zs[i] - centroid[2]) as f32;
    }
    (centroid, total_weight)
}

/// Quantum (m) of the summaries' integer moments: 2⁻¹⁶ m, 15 µm. A cell edge of at most
/// 2 m is 2¹⁷ quanta, its squares 2³⁴: an i64 holds the sums of 2²⁹ points.
const SUMMARY_QUANTUM: f64 = 1.0 / 65_536.0;

/// Integer moments of the points in one summary cell, about the cell's corner.
#[derive(Debug, Clone, Copy, Default)]
struct Cell {
    hash: u32,
    key: [i32; 3],
    n: u32,
    s: [i64; 3],
    ss: [i64; 6],
}

/// Fills `s.x`, `s.y`, `s.z` with the means of the cells (edges `cell`: horizontal,
/// vertical) that a segment's points fall in, relative to the returned centroid, `s.w`
/// with their counts and `s.cov` with their scatter (per point, about the cell's mean);
/// returns the centroid and the number of points.
///
/// Every sum is of integers (coordinates in [`SUMMARY_QUANTUM`] about the segment's exact
/// mean), so a cell's moments do not depend on the order of its points, and cells are
/// fitted in the order of their hash, then of their key: the fit is exactly independent
/// of the order points arrive in. The cells are laid from the segment's mean, as the
/// subsample's cubes are, so a scan moved as a whole keeps its summaries.
fn summarise(
    xs: &[f64],
    ys: &[f64],
    zs: &[f64],
    cell: [f64; 2],
    s: &mut EmScratch,
) -> ([f64; 3], f64) {
    let n = xs.len();
    let anchor = [xs, ys, zs].map(exact_mean);
    let edge = [cell[0], cell[0], cell[1]].map(|e| (e / SUMMARY_QUANTUM).round().max(1.0) as i64);
    let size = (2 * n).next_power_of_two();
    s.slots.clear();
    s.slots.resize(size, u32::MAX);
    s.cells.clear();
    let mask = size - 1;
    let inv_edge = edge.map(|e| 1.0 / (e as f64 * SUMMARY_QUANTUM));
    let edge_f = edge.map(|e| e as f64);
    // Points arrive along the rings, and runs of them fall in one cell: a run is summed
    // in registers and added to its cell (found by hash) when the run ends. The run lives
    // in plain locals handed over by value (count, sums, products): kept in a `Cell` that
    // the flush borrowed, it went through memory every point (a store-to-load chain, most
    // of this function).
    let flush = |run: (u32, [i64; 3], [i64; 6]),
                 key: [i32; 3],
                 slots: &mut [u32],
                 cells: &mut Vec<Cell>| {
        let (rn, rs, rss) = run;
        if rn == 0 {
            return;
        }
        let hash = cube_hash(key[0], key[1], key[2]);
        let mut slot = hash as usize & mask;
        let c = loop {
            match slots[slot] {
                u32::MAX => {
                    slots[slot] = cells.len() as u32;
                    cells.push(Cell {
                        hash,
                        key,
                        ..Cell::default()
                    });
                    break cells.len() - 1;
                }
                c if cells[c as usize].key == key => break c as usize,
                _ => slot = (slot + 1) & mask,
            }
        };
        let c = &mut cells[c];
        c.n += rn;
        for (a, b) in c.s.iter_mut().zip(rs) {
            *a += b;
        }
        for (a, b) in c.ss.iter_mut().zip(rss) {
            *a += b;
        }
    };
    // The cell of every point, and its place in the cell in quanta from the cell's
    // corner, in one plain loop (vectorised; no integer division), then the runs.
    for v in [&mut s.keys, &mut s.places] {
        v.clear();
        v.resize(3 * n, 0);
    }
    let axes = [xs, ys, zs];
    for a in 0..3 {
        let (keys, places) = (&mut s.keys[a * n..][..n], &mut s.places[a * n..][..n]);
        for ((k, p), &v) in keys.iter_mut().zip(places.iter_mut()).zip(axes[a]) {
            let t = (v - anchor[a]) * inv_edge[a];
            let f = t.floor();
            *k = round_i32(f);
            *p = round_i32((t - f) * edge_f[a]);
        }
    }
    let (kx, ky, kz) = (&s.keys[..n], &s.keys[n..2 * n], &s.keys[2 * n..]);
    let (px, py, pz) = (&s.places[..n], &s.places[n..2 * n], &s.places[2 * n..]);
    let mut key = [i32::MIN; 3];
    let (mut rn, mut r0, mut r1, mut r2) = (0u32, 0i64, 0i64, 0i64);
    let (mut q0, mut q1, mut q2, mut q3, mut q4, mut q5) = (0i64, 0i64, 0i64, 0i64, 0i64, 0i64);
    for i in 0..n {
        let k = [kx[i], ky[i], kz[i]];
        if k != key {
            let run = (rn, [r0, r1, r2], [q0, q1, q2, q3, q4, q5]);
            flush(run, key, &mut s.slots, &mut s.cells);
            key = k;
            (rn, r0, r1, r2) = (0, 0, 0, 0);
            (q0, q1, q2, q3, q4, q5) = (0, 0, 0, 0, 0, 0);
        }
        let (l0, l1, l2) = (i64::from(px[i]), i64::from(py[i]), i64::from(pz[i]));
        rn += 1;
        r0 += l0;
        r1 += l1;
        r2 += l2;
        q0 += l0 * l0;
        q1 += l0 * l1;
        q2 += l0 * l2;
        q3 += l1 * l1;
        q4 += l1 * l2;
        q5 += l2 * l2;
    }
    let run = (rn, [r0, r1, r2], [q0, q1, q2, q3, q4, q5]);
    flush(run, key, &mut s.slots, &mut s.cells);
    // Cells in the order of their hash, then of their key (no two cells share one): (hash,
    // position in `cells`) pairs through the linear-time key sort, not the 96-byte cells
    // through a comparison sort (2 % of a scan's time on one thread).
    let cells = &s.cells;
    s.spare.clear();
    s.spare.extend(
        cells
            .iter()
            .enumerate()
            .map(|(i, c)| (u64::from(c.hash), i as u32)),
    );
    sort_by_key(
        &s.spare,
        &mut s.order,
        &mut s.counts,
        u64::from(u32::MAX),
        |a, b| cells[a as usize].key.cmp(&cells[b as usize].key),
    );
    let m = cells.len();
    let sorted = || s.order[..m].iter().map(|&(_, i)| &cells[i as usize]);
    // The centroid from the exact total of the quantised coordinates (integers: any order).
    let mut total = [0i128; 3];
    for c in cells {
        for a in 0..3 {
            total[a] +=
                i128::from(c.key[a]) * i128::from(edge[a]) * i128::from(c.n) + i128::from(c.s[a]);
        }
    }
    let offset = total.map(|t| t as f64 / n as f64 * SUMMARY_QUANTUM);
    let centroid = [0, 1, 2].map(|a| anchor[a] + offset[a]);
    for v in [&mut s.x, &mut s.y, &mut s.z, &mut s.w] {
        v.clear();
        v.reserve(m);
    }
    s.cov.clear();
    s.cov.resize(m.div_ceil(LANES) * LANES * 6, 0.0);
    let q2 = SUMMARY_QUANTUM * SUMMARY_QUANTUM;
    let pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];
    for (j, c) in sorted().enumerate() {
        let k = f64::from(c.n);
        let mean = [0, 1, 2].map(|a| c.s[a] as f64 / k);
        for (a, v) in [&mut s.x, &mut s.y, &mut s.z].into_iter().enumerate() {
            let corner = (i64::from(c.key[a]) * edge[a]) as f64;
            v.push(((corner + mean[a]) * SUMMARY_QUANTUM - offset[a]) as f32);
        }
        s.w.push(k as f32);
        let block = j / LANES * LANES * 6 + j % LANES;
        for (e, (&ss, (a, b))) in c.ss.iter().zip(pairs).enumerate() {
            s.cov[block + e * LANES] = ((ss as f64 / k - mean[a] * mean[b]) * q2).max(0.0) as f32;
        }
    }
    (centroid, n as f64)
}

/// log π N(x) of one component (`lc`) for every point into `row`; with `CELLS`, for
/// every summary cell the mean over its points: the density at the cell's mean less
/// tr(UᵀU S), S the cell's scatter from `cov` (see [`EmScratch`]).
#[inline(always)]
fn log_densities<const CELLS: bool>(row: &mut [f32], xyz: [&[f32]; 3], cov: &[f32], lc: &Lanes) {
    let (u, b) = (lc.u, lc.b);
    // |U v|² = vᵀ (UᵀU) v; the entries of UᵀU, off-diagonal ones doubled.
    let a = [
        u[0] * u[0],
        2.0 * u[0] * u[1],
        2.0 * u[0] * u[2],
        u[1] * u[1] + u[3] * u[3],
        2.0 * (u[1] * u[2] + u[3] * u[4]),
        u[2] * u[2] + u[4] * u[4] + u[5] * u[5],
    ];
    let (u, b, a) = (
        u.map(f32x8::splat),
        b.map(f32x8::splat),
        a.map(f32x8::splat),
    );
    let lc_c = f32x8::splat(lc.c);
    let mut covs = cov.chunks_exact(6 * LANES);
    for (((r, x), y), z) in row
        .chunks_exact_mut(LANES)
        .zip(xyz[0].chunks_exact(LANES))
        .zip(xyz[1].chunks_exact(LANES))
        .zip(xyz[2].chunks_exact(LANES))
    {
        let (x, y, z) = (v8(x, 0), v8(y, 0), v8(z, 0));
        let top = if CELLS {
            let Some(cv) = covs.next() else {
                break; // cannot happen: `cov` holds six lanes per point lane
            };
            let c = |e: usize| v8(cv, e * LANES);
            let spread = a[0].mul_add(
                c(0),
                a[1].mul_add(
                    c(1),
                    a[2].mul_add(c(2), a[3].mul_add(c(3), a[4].mul_add(c(4), a[5] * c(5)))),
                ),
            );
            lc_c - spread
        } else {
            lc_c
        };
        let u3 = u[5].mul_add(z, -b[2]);
        let u2 = u[3].mul_add(y, u[4].mul_add(z, -b[1]));
        let u1 = u[0].mul_add(x, u[1].mul_add(y, u[2].mul_add(z, -b[0])));
        let l = (-u1).mul_add(u1, (-u2).mul_add(u2, (-u3).mul_add(u3, top)));
        r.copy_from_slice(&l.to_array());
    }
}

/// The M-step's sums for one component, lane by lane, about its current mean `m`: Σg,
/// Σg·d (x, y, z) and Σg·d·dᵀ (xx, xy, xz, yy, yz, zz), g = responsibility × weight
/// (`row` × `inv`), d = x − m; with `CELLS` each cell's own scatter joins the second
/// moments, weighted as its mean. Ten vector accumulators: kept in registers.
#[inline(always)]
fn moments<const CELLS: bool>(
    row: &[f32],
    inv: &[f32],
    xyz: [&[f32]; 3],
    cov: &[f32],
    m: [f32; 3],
) -> [[f32; LANES]; 10] {
    let zero = f32x8::splat(0.0);
    let (mut s0, mut s1, mut s2, mut s3, mut s4) = (zero, zero, zero, zero, zero);
    let (mut s5, mut s6, mut s7, mut s8, mut s9) = (zero, zero, zero, zero, zero);
    let m = m.map(f32x8::splat);
    let mut covs = cov.chunks_exact(6 * LANES);
    for ((((r, inv), x), y), z) in row
        .chunks_exact(LANES)
        .zip(inv.chunks_exact(LANES))
        .zip(xyz[0].chunks_exact(LANES))
        .zip(xyz[1].chunks_exact(LANES))
        .zip(xyz[2].chunks_exact(LANES))
    {
        let g = v8(r, 0) * v8(inv, 0);
        let (dx, dy, dz) = (v8(x, 0) - m[0], v8(y, 0) - m[1], v8(z, 0) - m[2]);
        let (gx, gy, gz) = (g * dx, g * dy, g * dz);
        if CELLS {
            let Some(cv) = covs.next() else {
                break; // cannot happen: `cov` holds six lanes per point lane
            };
            let c = |e: usize| v8(cv, e * LANES);
            s4 = g.mul_add(c(0), s4);
            s5 = g.mul_add(c(1), s5);
            s6 = g.mul_add(c(2), s6);
            s7 = g.mul_add(c(3), s7);
            s8 = g.mul_add(c(4), s8);
            s9 = g.mul_add(c(5), s9);
        }
        s0 += g;
        s1 += gx;
        s2 += gy;
        s3 += gz;
        s4 = gx.mul_add(dx, s4);
        s5 = gx.mul_add(dy, s5);
        s6 = gx.mul_add(dz, s6);
        s7 = gy.mul_add(dy, s7);
        s8 = gy.mul_add(dz, s8);
        s9 = gz.mul_add(dz, s9);
    }
    [s0, s1, s2, s3, s4, s5, s6, s7, s8, s9].map(|v| v.to_array())
}

/// Fits a GMM to one segment's points (structure of arrays, equal lengths) by EM.
/// Returns no components for an empty segment.
pub fn fit_segment(xs: &[f64], ys: &[f64], zs: &[f64], cfg: &GmmConfig) -> SegmentFit {
    fit_segment_with(xs, ys, zs, cfg, &mut EmScratch::default())
}

/// [`fit_segment`] with caller-provided scratch buffers: initialise, then E-step and
/// M-step (with pruning) until the stopping rule, each a function below.
///
/// The E-step runs in f32 over component-major arrays so that every inner loop is a
/// straight loop over points that the compiler vectorises; sufficient statistics are taken
/// relative to each component's current mean (small numbers, no cancellation) and the
/// M-step itself runs in f64.
pub fn fit_segment_with(
    xs: &[f64],
    ys: &[f64],
    zs: &[f64],
    cfg: &GmmConfig,
    s: &mut EmScratch,
) -> SegmentFit {
    let n = xs.len();
    debug_assert!(ys.len() == n && zs.len() == n);
    if n == 0 {
        return SegmentFit::default();
    }
    let (zmin, zmax) = zs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &z| {
            (lo.min(z), hi.max(z))
        });
    // What EM runs on, centred: a dense segment's summary cells, or its (subsampled) points.
    let summary = cfg.summary_cell != [0.0, 0.0]
        && cfg.max_fit_points != 0
        && n > cfg.max_fit_points as usize;
    let (centroid, total_weight) = if summary {
        summarise(xs, ys, zs, cfg.summary_cell, s)
    } else {
        subsample(xs, ys, zs, cfg, s)
    };
    let scale = n as f64 / total_weight;
    let np = s.pad_to_lanes(summary);
    // Taken out of the scratch for the loop (the passes borrow the rest of it), put back
    // after.
    let (mut comps, mut next, mut owned, mut lanes) = (
        std::mem::take(&mut s.comps),
        std::mem::take(&mut s.next),
        std::mem::take(&mut s.owned),
        std::mem::take(&mut s.lanes),
    );
    initial_components(n, (zmin, zmax), centroid[2], cfg, &mut comps);
    s.resp.resize(comps.len() * np, 0.0);
    owned.clear();
    owned.resize(comps.len(), 0);

    let mut prev_ll = f64::NEG_INFINITY;
    let mut mean_ll = f64::NEG_INFINITY;
    let mut iterations = 0;
    for _ in 0..cfg.max_iterations {
        iterations += 1;
        let k = comps.len();
        evaluators(&comps, &mut lanes);
        // E-step: each component's log-density at every point, the best per point, the
        // responsibilities, the log-likelihood, and each component's support.
        component_log_densities(s, &lanes, np, summary);
        best_components(s, k, np);
        relative_densities(s, k, np);
        let ll = normalise_responsibilities(s, summary);
        support(s, &mut owned[..k], scale);
        // M-step (closed form, paper eq. 2), pruning weakly supported components.
        m_step(s, &lanes, &owned, cfg, np, summary, &mut next);
        let pruned = next.len() != comps.len();
        std::mem::swap(&mut comps, &mut next);
        weights_summing_to_one(&mut comps);
        mean_ll = ll / total_weight;
        if comps.is_empty() {
            break;
        }
        // The stopping rule compares like with like: not across a pruning step.
        if !pruned && (mean_ll - prev_ll).abs() < cfg.tolerance {
            break;
        }
        prev_ll = mean_ll;
    }

    for g in &mut comps {
        for (m, c) in g.mean.iter_mut().zip(centroid) {
            *m += c;
        }
    }
    let fit = SegmentFit {
        components: comps.clone(),
        iterations,
        mean_log_likelihood: mean_ll,
    };
    (s.comps, s.next, s.owned, s.lanes) = (comps, next, owned, lanes);
    fit
}

impl EmScratch {
    /// Pads the fitted points (or cells) to a multiple of `LANES` with zero weight and
    /// sizes the per-point buffers. Returns the padded count.
    fn pad_to_lanes(&mut self, summary: bool) -> usize {
        let np = self.x.len().div_ceil(LANES) * LANES;
        for v in [&mut self.x, &mut self.y, &mut self.z, &mut self.w] {
            v.resize(np, 0.0);
        }
        // Only summary cells have a scatter of their own (the point path never reads `cov`).
        if summary {
            self.cov.resize(np * 6, 0.0);
        }
        self.max.resize(np, 0.0);
        self.inv.resize(np, 0.0);
        self.best.resize(np, 0);
        np
    }
}

/// Initialisation (paper §III-B1): K = min(ceil(N / N_min), K_max) components at the
/// horizontal mean, spread linearly in z from the lowest to the highest point (`z_range`,
/// made relative to the centroid's `z_centre`), equal weights, unit covariance.
fn initial_components(
    n: usize,
    z_range: (f64, f64),
    z_centre: f64,
    cfg: &GmmConfig,
    comps: &mut Vec<Gaussian>,
) {
    let (zmin, zmax) = z_range;
    let k0 = n
        .div_ceil(cfg.n_min as usize)
        .min(cfg.k_max as usize)
        .max(1);
    comps.clear();
    comps.extend((0..k0).map(|k| {
        let t = if k0 == 1 {
            0.5
        } else {
            k as f64 / (k0 - 1) as f64
        };
        Gaussian {
            weight: 1.0 / k0 as f64,
            mean: [0.0, 0.0, zmin + t * (zmax - zmin) - z_centre],
            covariance: [1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
        }
    }));
}

/// Each component in the E-step's f32 form. With reg > 0 every covariance is positive
/// definite; should rounding ever break that, the component falls back to unit covariance
/// instead of poisoning EM.
fn evaluators(comps: &[Gaussian], lanes: &mut Vec<Lanes>) {
    lanes.clear();
    lanes.extend(comps.iter().map(|g| {
        let e = Evaluator::new(g).unwrap_or_else(|| Evaluator::unit(g));
        let (u, b) = half_precision_factor(&e.precision, &e.mean);
        Lanes {
            m: e.mean.map(|v| v as f32),
            u: u.map(|v| v as f32),
            b: b.map(|v| v as f32),
            c: e.log_coef as f32,
        }
    }));
}

/// E-step, pass 1: log π_c N(x | μ_c, Σ_c) for every component and point (component-major
/// rows of `resp`); for a summary cell its points' mean (`log_densities`).
fn component_log_densities(s: &mut EmScratch, lanes: &[Lanes], np: usize, summary: bool) {
    for (c, lc) in lanes.iter().enumerate() {
        let row = &mut s.resp[c * np..(c + 1) * np];
        if summary {
            log_densities::<true>(row, [&s.x, &s.y, &s.z], &s.cov, lc);
        } else {
            log_densities::<false>(row, [&s.x, &s.y, &s.z], &s.cov, lc);
        }
    }
}

/// The best of `k` components per point, and its log-density (for the log-sum-exp and for
/// the support counts). Block by block, the running best kept in registers: written as a
/// pass per component with selects, LLVM stored only the changed lanes with masked stores,
/// which Zen microcodes (a quarter of EM's time went there).
fn best_components(s: &mut EmScratch, k: usize, np: usize) {
    let block = |v: &[f32], o: usize| v.get(o..).and_then(|v| v.first_chunk::<LANES>()).copied();
    for (o, (m, b)) in (0..np).step_by(LANES).zip(
        s.max
            .chunks_exact_mut(LANES)
            .zip(s.best.chunks_exact_mut(LANES)),
    ) {
        let Some(first) = block(&s.resp, o) else {
            break; // cannot happen: every row holds np values, a multiple of LANES
        };
        let mut mv = f32x8::new(first);
        let mut bv = i32x8::splat(0);
        for c in 1..k {
            let Some(l) = block(&s.resp, c * np + o) else {
                break;
            };
            let lv = f32x8::new(l);
            // Lanes where this component is strictly better (false for NaN, as `>`).
            let gt = lv.simd_gt(mv);
            mv = gt.select(lv, mv);
            bv = cast::<f32x8, i32x8>(gt).select(i32x8::splat(c as i32), bv);
        }
        m.copy_from_slice(&mv.to_array());
        b.copy_from_slice(&cast::<i32x8, [u32; LANES]>(bv));
    }
}

/// E-step, pass 2: each density relative to the point's best (e^{l_c − max}), and their
/// sum per point in `inv`.
fn relative_densities(s: &mut EmScratch, k: usize, np: usize) {
    s.inv.fill(0.0);
    for c in 0..k {
        let row = &mut s.resp[c * np..(c + 1) * np];
        for ((r, &m), acc) in row.iter_mut().zip(&s.max).zip(s.inv.iter_mut()) {
            // Weights below e^-30 relative to the best are flushed to zero: they change
            // nothing, and their products in the M-step would be denormal floats, which
            // cost ~100 cycles each on x86.
            let d = *r - m;
            let e = if d < -30.0 { 0.0 } else { exp_nonpositive(d) };
            *r = e;
            *acc += e;
        }
    }
}

/// The normalisers w / Σ in `inv` (a point's responsibilities are its relative densities
/// times it) and the weighted log-likelihood, for the stopping rule. A point's
/// log-likelihood is its best log-density plus ln Σ, with Σ in [1, K]: the Σ of LN_GROUP
/// blocks are multiplied per lane (at most 64^16 = 2^96, no overflow) and one ln taken of
/// the product, instead of one per point (the ln's division was 15 % of EM). In explicit
/// vectors: written per lane, LLVM left the division scalar.
fn normalise_responsibilities(s: &mut EmScratch, summary: bool) -> f64 {
    let one = f32x8::splat(1.0);
    let mut ll_v = f32x8::splat(0.0);
    let mut prod = one;
    for (b, ((inv, m), w)) in s
        .inv
        .chunks_exact_mut(LANES)
        .zip(s.max.chunks_exact(LANES))
        .zip(s.w.chunks_exact(LANES))
        .enumerate()
    {
        let (Some(sum), Some(m), Some(w)) = (inv.first_chunk(), m.first_chunk(), w.first_chunk())
        else {
            break; // cannot happen: exact chunks of LANES
        };
        let (sum, m, w) = (f32x8::new(*sum), f32x8::new(*m), f32x8::new(*w));
        ll_v += w * m;
        inv.copy_from_slice(&(w / sum).to_array());
        if summary {
            // A cell counts as many points: its ln Σ weighted by its count.
            ll_v += w * ln_from(sum);
            continue;
        }
        prod *= w.simd_gt(f32x8::splat(0.0)).select(sum, one);
        if b % LN_GROUP == LN_GROUP - 1 {
            ll_v += f32x8::new(prod.to_array().map(ln_positive));
            prod = one;
        }
    }
    let ll_lanes = (ll_v + f32x8::new(prod.to_array().map(ln_positive))).to_array();
    ll_lanes.iter().map(|&v| f64::from(v)).sum()
}

/// Each component's support: the fit weight of the points it is best for, scaled to the
/// whole segment (`scale`), for pruning against τ_N. One vectorised count per component: a
/// scattered `owned[best] += 1` serialises on store-to-load forwarding.
fn support(s: &EmScratch, owned: &mut [u32], scale: f64) {
    for (c, o) in owned.iter_mut().enumerate() {
        // Lane-wise sums: a single f32 sum is a serial chain of adds.
        let (mut acc, cv) = (f32x8::splat(0.0), i32x8::splat(c as i32));
        for (b, w) in s.best.chunks_exact(LANES).zip(s.w.chunks_exact(LANES)) {
            let (Some(b), Some(w)) = (b.first_chunk::<LANES>(), w.first_chunk::<LANES>()) else {
                break; // cannot happen: exact chunks of LANES
            };
            let mine = cast::<i32x8, f32x8>(cast::<[u32; LANES], i32x8>(*b).simd_eq(cv));
            acc += mine & f32x8::new(*w);
        }
        let count: f64 = acc.to_array().iter().map(|&v| f64::from(v)).sum();
        *o = (count * scale).round() as u32;
    }
}

/// M-step (closed form, paper eq. 2) from moments about each component's current mean,
/// leaving out components whose support is below τ_N (pruning) or whose responsibilities
/// vanished. Weights are the responsibilities' sums, not yet normalised.
fn m_step(
    s: &EmScratch,
    lanes: &[Lanes],
    owned: &[u32],
    cfg: &GmmConfig,
    np: usize,
    summary: bool,
    next: &mut Vec<Gaussian>,
) {
    let reg = cfg.covariance_regularization;
    next.clear();
    for (c, lc) in lanes.iter().enumerate() {
        if owned[c] < cfg.tau_n {
            continue;
        }
        let row = &s.resp[c * np..(c + 1) * np];
        let xyz = [&s.x, &s.y, &s.z].map(|v| v.as_slice());
        let [s0, s1, s2, s3, s4, s5, s6, s7, s8, s9] = if summary {
            moments::<true>(row, &s.inv, xyz, &s.cov, lc.m)
        } else {
            moments::<false>(row, &s.inv, xyz, &s.cov, lc.m)
        };
        let sum = |a: [f32; LANES]| a.iter().map(|&v| f64::from(v)).sum::<f64>();
        let t = [
            sum(s0),
            sum(s1),
            sum(s2),
            sum(s3),
            sum(s4),
            sum(s5),
            sum(s6),
            sum(s7),
            sum(s8),
            sum(s9),
        ];
        let nk = t[0];
        if nk < 1e-9 {
            continue;
        }
        let d = [t[1] / nk, t[2] / nk, t[3] / nk];
        let m = lc.m.map(f64::from);
        next.push(Gaussian {
            weight: nk,
            mean: [m[0] + d[0], m[1] + d[1], m[2] + d[2]],
            covariance: [
                t[4] / nk - d[0] * d[0] + reg,
                t[5] / nk - d[0] * d[1],
                t[6] / nk - d[0] * d[2],
                t[7] / nk - d[1] * d[1] + reg,
                t[8] / nk - d[1] * d[2],
                t[9] / nk - d[2] * d[2] + reg,
            ],
        });
    }
}

/// The weights normalised: removed components' mass is shared out (and f32 rounding
/// undone) so that they sum to one.
fn weights_summing_to_one(comps: &mut [Gaussian]) {
    let total: f64 = comps.iter().map(|g| g.weight).sum();
    if total > 0.0 {
        for g in comps {
            g.weight /= total;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// `gmm.summary_cell` that fits a dense segment on its subsample.
    const SUBSAMPLE: [f64; 2] = [0.0, 0.0];

    fn sample(
        rng: &mut rand::rngs::StdRng,
        n: usize,
        mean: [f64; 3],
        std: [f64; 3],
        out: &mut [Vec<f64>; 3],
    ) {
        for d in 0..3 {
            let dist = Normal::new(mean[d], std[d]).unwrap();
            for _ in 0..n {
                out[d].push(dist.sample(rng));
            }
        }
    }

    /// A flat "road" patch and a compact "object" 1.5 m above it, 3:1 in points.
    fn road_and_object() -> [Vec<f64>; 3] {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(
            &mut rng,
            3000,
            [10.0, 2.0, -1.7],
            [1.0, 1.0, 0.03],
            &mut pts,
        );
        sample(&mut rng, 1000, [10.5, 2.5, -0.2], [0.3, 0.3, 0.4], &mut pts);
        pts
    }

    /// The road and object of [`road_and_object`], weights, means and covariances, as a
    /// fit on every point gives them.
    fn assert_road_and_object(fit: &SegmentFit) {
        let mut c = fit.components.clone();
        assert_eq!(c.len(), 2);
        c.sort_by(|a, b| a.mean[2].total_cmp(&b.mean[2]));
        let (road, obj) = (c[0], c[1]);
        assert!((road.weight - 0.75).abs() < 0.02, "{road:?}");
        assert!((road.mean[2] + 1.7).abs() < 0.01, "{road:?}");
        assert!((road.mean[0] - 10.0).abs() < 0.1, "{road:?}");
        assert!(
            (road.covariance[5] - 0.03f64.powi(2) - 1e-4).abs() < 3e-4,
            "{road:?}"
        );
        assert!((road.covariance[0] - 1.0).abs() < 0.1, "{road:?}");
        assert!((obj.mean[2] + 0.2).abs() < 0.05, "{obj:?}");
        assert!((obj.covariance[5] - 0.16).abs() < 0.03, "{obj:?}");
        assert!((obj.covariance[0] - 0.09).abs() < 0.02, "{obj:?}");
    }

    /// Two components fitted to convergence on every point of [`road_and_object`].
    fn two_components_to_convergence() -> GmmConfig {
        GmmConfig {
            k_max: 2,
            max_iterations: 100,
            tolerance: 1e-9,
            max_fit_points: 0,
            ..GmmConfig::default()
        }
    }

    #[test]
    fn em_recovers_a_sampled_two_gaussian_mixture() {
        let pts = road_and_object();
        let cfg = two_components_to_convergence();
        assert_road_and_object(&fit_segment(&pts[0], &pts[1], &pts[2], &cfg));

        // Fitted on a subsample of ~256 points, the same mixture comes out, less precisely.
        let sub = GmmConfig {
            max_fit_points: 256,
            summary_cell: SUBSAMPLE,
            ..cfg
        };
        let mut c = fit_segment(&pts[0], &pts[1], &pts[2], &sub).components;
        assert_eq!(c.len(), 2);
        c.sort_by(|a, b| a.mean[2].total_cmp(&b.mean[2]));
        assert!((c[0].weight - 0.75).abs() < 0.06, "{:?}", c[0]);
        assert!((c[0].mean[2] + 1.7).abs() < 0.02, "{:?}", c[0]);
        assert!((c[1].mean[2] + 0.2).abs() < 0.15, "{:?}", c[1]);
    }

    #[test]
    fn weakly_supported_components_are_pruned_and_tiny_segments_have_no_model() {
        let cfg = GmmConfig::default();
        // 9 points < τ_N = 10: the single component is pruned.
        let xs: Vec<f64> = (0..9).map(|i| i as f64 * 0.1).collect();
        let fit = fit_segment(&xs, &xs, &[0.0; 9], &cfg);
        assert!(fit.components.is_empty());
        // Empty segment: nothing to fit.
        assert!(fit_segment(&[], &[], &[], &cfg).components.is_empty());
        // 200 points all on one flat patch: 8 components start, the weak ones go, and the
        // survivors each own at least τ_N points.
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(&mut rng, 200, [5.0, 0.0, 0.0], [1.0, 1.0, 0.01], &mut pts);
        let fit = fit_segment(&pts[0], &pts[1], &pts[2], &cfg);
        assert!(!fit.components.is_empty() && fit.components.len() < 8);
        let w: f64 = fit.components.iter().map(|g| g.weight).sum();
        assert!((w - 1.0).abs() < 1e-9);
    }

    #[test]
    fn degenerate_points_stay_finite_thanks_to_the_regulariser() {
        // 50 identical points: the covariance would be zero without regularisation.
        let fit = fit_segment(&[3.0; 50], &[1.0; 50], &[-1.0; 50], &GmmConfig::default());
        assert_eq!(fit.components.len(), 1);
        let g = fit.components[0];
        assert!(g.covariance.iter().all(|v| v.is_finite()));
        assert!((g.covariance[0] - 1e-4).abs() < 1e-9);
        assert!(sym3_inverse(&g.covariance).is_some());
    }

    #[test]
    fn converged_segments_stop_early() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(&mut rng, 15, [5.0, 0.0, 0.0], [1.0, 1.0, 0.01], &mut pts);
        let fit = fit_segment(&pts[0], &pts[1], &pts[2], &GmmConfig::default());
        // One component: the second iteration reproduces the first's log-likelihood.
        assert_eq!(fit.components.len(), 1);
        assert!(fit.iterations <= 3, "{}", fit.iterations);
    }

    #[test]
    fn the_key_sort_orders_like_a_stable_comparison_sort() {
        use rand::Rng;
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        // One output buffer for all, longer than needed after the 1000 keys.
        let (mut dst, mut counts) = (Vec::new(), Vec::new());
        for (m, max_key) in [
            (0, u64::MAX),
            (1, u64::MAX),
            (16, u64::MAX),
            (17, u64::MAX),
            (256, u64::MAX / 3),
            (300, u64::MAX / 40),
            (1000, 5000),
            (64, 10),
        ] {
            let mut v: Vec<(u64, u32)> = (0..m as u32)
                .map(|i| (rng.random_range(0..=max_key), i))
                .collect();
            // Equal hashes too (the same point twice).
            if m > 2 {
                v[m - 1].0 = v[0].0;
            }
            let mut want = v.clone();
            want.sort_by_key(|e| e.0); // stable, as the hash sort is
            sort_by_key(&v, &mut dst, &mut counts, max_key, |a, b| a.cmp(&b));
            assert_eq!(&dst[..m], &want[..], "{m} keys up to {max_key}");
        }
    }

    #[test]
    fn the_exact_mean_ignores_order_and_matches_the_float_mean() {
        use rand::Rng;
        use rand::seq::SliceRandom;
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let mut v: Vec<f64> = (0..5000).map(|_| rng.random_range(-80.0..80.0)).collect();
        let m = exact_mean(&v);
        let float: f64 = v.iter().sum::<f64>() / v.len() as f64;
        assert!((m - float).abs() < 1e-7, "{m} vs {float}");
        for _ in 0..5 {
            v.shuffle(&mut rng);
            assert_eq!(exact_mean(&v).to_bits(), m.to_bits());
        }
        // Moved as a whole, the mean moves with it.
        let moved: Vec<f64> = v.iter().map(|x| x + 0.123).collect();
        assert!((exact_mean(&moved) - m - 0.123).abs() < 1e-7);
    }

    #[test]
    fn a_point_sliding_across_a_face_changes_its_weight_continuously() {
        let half = u32::MAX / 2;
        // A face between a drawn cube and an undrawn one, along x.
        let i = (0..1000)
            .find(|&i| (cube_hash(i, 3, -2) <= half) != (cube_hash(i + 1, 3, -2) <= half))
            .expect("a face between a drawn and an undrawn cube");
        let (y, z) = (3.5 * CUBE_EDGE, -1.5 * CUBE_EDGE);
        let face = f64::from(i + 1) * CUBE_EDGE;
        let weight = |x: f64| band_weight(x, y, z, half);
        // Away from the face each point has its cube's draw; on it, half of each.
        let own = |c: i32| {
            if cube_hash(c, 3, -2) <= half {
                1.0
            } else {
                0.0
            }
        };
        assert_eq!(weight(face - 0.3 * CUBE_EDGE), own(i));
        assert_eq!(weight(face + 0.3 * CUBE_EDGE), own(i + 1));
        assert!((weight(face) - 0.5).abs() < 1e-6);
        // Across the band the weight moves by steps no larger than the motion.
        let step = 1e-3 * FACE_BAND * CUBE_EDGE;
        let mut last = weight(face - 2.0 * FACE_BAND * CUBE_EDGE);
        for k in 1..4000 {
            let w = weight(face - 2.0 * FACE_BAND * CUBE_EDGE + f64::from(k) * step);
            assert!((0.0..=1.0).contains(&w));
            assert!((w - last).abs() <= 1e-3, "{k}: {last} -> {w}");
            last = w;
        }
    }

    #[test]
    fn a_dense_segment_moved_as_a_whole_keeps_its_fit() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(
            &mut rng,
            3000,
            [12.0, 3.0, -1.7],
            [1.0, 1.0, 0.02],
            &mut pts,
        );
        sample(&mut rng, 600, [12.3, 3.2, -0.9], [0.3, 0.3, 0.4], &mut pts);
        // Summary cells are laid from the segment's mean, the subsample's cubes are cut
        // relative to it: either path's fit moves with the segment.
        let shift = [0.37, -1.21, 0.0043];
        let moved: Vec<Vec<f64>> = (0..3)
            .map(|d| pts[d].iter().map(|v| v + shift[d]).collect())
            .collect();
        for cells in [[0.6, 0.12], SUBSAMPLE] {
            let cfg = GmmConfig {
                summary_cell: cells,
                ..GmmConfig::default()
            };
            let a = fit_segment(&pts[0], &pts[1], &pts[2], &cfg);
            let b = fit_segment(&moved[0], &moved[1], &moved[2], &cfg);
            assert_eq!(a.components.len(), b.components.len(), "{cells:?}");
            assert_eq!(a.iterations, b.iterations, "{cells:?}");
            for (ga, gb) in a.components.iter().zip(&b.components) {
                assert!((ga.weight - gb.weight).abs() < 1e-4, "{ga:?} {gb:?}");
                for ((mb, ma), d) in gb.mean.iter().zip(&ga.mean).zip(shift) {
                    assert!((mb - ma - d).abs() < 1e-4, "{ga:?} {gb:?}");
                }
                for (ca, cb) in ga.covariance.iter().zip(&gb.covariance) {
                    assert!((ca - cb).abs() < 1e-5, "{ga:?} {gb:?}");
                }
            }
        }
    }

    #[test]
    fn a_segment_with_no_cube_drawn_fits_every_point_in_any_order() {
        use rand::seq::SliceRandom;
        // 2000 points in a few 2 cm cubes and a share of 1/2000: no cube is drawn, so every
        // point is fitted, in the canonical order whatever the input order. (Two clusters
        // 12 mm apart across the mean keep the cube at the mean's corner empty: it hashes
        // to 0 and is drawn in every segment.)
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(&mut rng, 1000, [5.006, 0.994, -1.7], [0.001; 3], &mut pts);
        sample(&mut rng, 1000, [4.994, 1.006, -1.7], [0.001; 3], &mut pts);
        let cfg = GmmConfig {
            max_fit_points: 1,
            summary_cell: SUBSAMPLE,
            ..GmmConfig::default()
        };
        let fit = fit_segment(&pts[0], &pts[1], &pts[2], &cfg);
        assert!(!fit.components.is_empty());
        let mut order: Vec<usize> = (0..2000).collect();
        order.shuffle(&mut rng);
        let permuted: Vec<Vec<f64>> = (0..3)
            .map(|d| order.iter().map(|&i| pts[d][i]).collect())
            .collect();
        assert_eq!(
            fit_segment(&permuted[0], &permuted[1], &permuted[2], &cfg),
            fit
        );
    }

    #[test]
    fn summaries_give_the_mixture_of_every_point_in_any_order() {
        use rand::seq::SliceRandom;
        // The cells' own scatter keeps the road's thickness and the object's spread, which
        // their means alone would shrink: the fit of every point comes out.
        let pts = road_and_object();
        let cfg = GmmConfig {
            max_fit_points: 256,
            summary_cell: [0.6, 0.12],
            ..two_components_to_convergence()
        };
        let fit = fit_segment(&pts[0], &pts[1], &pts[2], &cfg);
        assert_road_and_object(&fit);

        // Integer moments and cells in the order of their hash: any input order gives the
        // same bits.
        let mut order: Vec<usize> = (0..4000).collect();
        order.shuffle(&mut rand::rngs::StdRng::seed_from_u64(8));
        let permuted: Vec<Vec<f64>> = (0..3)
            .map(|d| order.iter().map(|&i| pts[d][i]).collect())
            .collect();
        assert_eq!(
            fit_segment(&permuted[0], &permuted[1], &permuted[2], &cfg),
            fit
        );
    }

    #[test]
    fn summaries_hardly_move_when_every_point_moves_a_little() {
        // A dense road patch and a kerb-high object, every point moved by up to 0.5 mm
        // (a mount told 0.005° differently, 5 m away): the fit moves by micrometres, as a
        // continuous function of the points should.
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut pts = [Vec::new(), Vec::new(), Vec::new()];
        sample(&mut rng, 4000, [6.0, 0.0, -1.7], [1.5, 1.0, 0.02], &mut pts);
        sample(&mut rng, 800, [6.5, 0.8, -1.2], [0.4, 0.1, 0.25], &mut pts);
        let cfg = GmmConfig {
            summary_cell: [0.6, 0.12],
            ..GmmConfig::default()
        };
        let moved: Vec<Vec<f64>> = (0..3)
            .map(|d| {
                pts[d]
                    .iter()
                    .enumerate()
                    .map(|(i, v)| v + 5e-4 * ((i * 7 + d * 3) % 11) as f64 / 10.0)
                    .collect()
            })
            .collect();
        let a = fit_segment(&pts[0], &pts[1], &pts[2], &cfg);
        let b = fit_segment(&moved[0], &moved[1], &moved[2], &cfg);
        assert_eq!(a.components.len(), b.components.len());
        for (ga, gb) in a.components.iter().zip(&b.components) {
            assert!((ga.weight - gb.weight).abs() < 1e-3, "{ga:?} {gb:?}");
            for (ma, mb) in ga.mean.iter().zip(&gb.mean) {
                assert!((ma - mb).abs() < 1e-3, "{ga:?} {gb:?}");
            }
        }
    }

    #[test]
    fn sym3_inverse_matches_identity() {
        let m = [4.0, 1.0, 0.5, 3.0, 0.2, 2.0];
        let (p, logdet) = sym3_inverse(&m).unwrap();
        let full = |s: &Sym3| [[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]];
        let (a, b) = (full(&m), full(&p));
        // a · b must be the identity.
        for (i, row) in a.iter().enumerate() {
            for (j, want) in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]][i]
                .iter()
                .enumerate()
            {
                let v: f64 = row.iter().zip(&b).map(|(r, bk)| r * bk[j]).sum();
                assert!((v - want).abs() < 1e-12);
            }
        }
        let det = 4.0 * (3.0 * 2.0 - 0.04) - 1.0 * (2.0 - 0.1) + 0.5 * (0.2 - 1.5);
        assert!((logdet - f64::ln(det)).abs() < 1e-12);
        assert!(sym3_inverse(&[1.0, 2.0, 0.0, 1.0, 0.0, 1.0]).is_none());
    }
}
