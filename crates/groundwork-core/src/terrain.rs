//! Terrain following: a step after ground continuity, where the papers are silent
//! (docs/algorithm.md, "Terrain following"; issue 89).
//!
//! Continuity reaches a metre; beyond 20 m the rings of a scan lie further apart than that,
//! and there most missed ground lies where a segment's mixture has no ground-like component
//! at the point's height at all (one beam's arc, a component over road and kerb), or where
//! a component metres below the road (a reflection) has become the segment's reference. On
//! a steep city street most of the ground lost is of that kind, and the lower parts of
//! parked cars are called ground because the component they share with the road has its
//! mean near the road (docs/dev/real-sensors-notes.md).
//!
//! Here the scan's confident ground gives the terrain: in narrow sectors around the
//! sensor, cells a metre deep hold the weighted mean height of the confident ground in
//! them; walking each sector outward from the sensor's foot, a cell's height is the
//! terrain where it continues the terrain nearer the sensor (its grade bounded), and where
//! a cell has no confident ground the terrain carries on at its last grade for a few
//! metres, trusted less with distance. Then a point the mixtures leave below the threshold
//! that lies at the terrain's height is raised towards ground, and a point called ground
//! that stands clearly above the terrain (a car's skirt, a wall's foot) is lowered.
//!
//! Stable as continuity is: the sums are integers (exact in any order), the per-point rules
//! are ramps.

use crate::config::TerrainConfig;
// The same fixed point and ramps as continuity's: weights and heights in 2⁻¹⁶.
use crate::continuity::{HEIGHT_CLAMP, HEIGHT_ONE, Ramp, WEIGHT_ONE};
use crate::fastmath::round_i32;
use rayon::prelude::*;
use wide::f64x4;

/// The terrain of one scan, kept between scans for its buffers.
#[derive(Debug, Default, Clone)]
pub(crate) struct TerrainScratch {
    /// Per cell: Σ weight, Σ weight · height (fixed point).
    sums: Vec<[i64; 2]>,
    /// The same over the points at or below their cell's mean.
    lower: Vec<[i64; 2]>,
    /// Per cell: its terrain.
    terrain: Vec<TerrainCell>,
    /// Per sector with one: the height of its first cell of confident ground.
    first: Vec<f64>,
    /// Per cell, then one more for points without a cell: its terrain as f64 lanes
    /// (height, raise, lower, reach) for the last pass.
    lanes: Vec<[f64; 4]>,
    /// Gap cells as the terrain beside them changes them (cell, its new terrain).
    beside: Vec<(usize, TerrainCell)>,
    /// Per point: its cell (one past the last cell: none).
    cells: Vec<u32>,
    /// Per cell: its mean height rounded down, fixed point (`i64::MIN`: no weight).
    means: Vec<i64>,
    /// Per point: its confident weight and height, fixed point (for the lower mean).
    weights: Vec<i32>,
    heights: Vec<i32>,
}

/// One cell's terrain.
#[derive(Debug, Default, Clone, Copy)]
struct TerrainCell {
    /// The terrain's height (m, ground-aligned frame).
    height: f32,
    /// How far it is trusted to raise points (0: no terrain).
    raise: f32,
    /// How far it is trusted to lower them.
    lower: f32,
    /// How high above `height` the ground could be before lowering starts (0 where the
    /// cell's own confident ground is the terrain; carried on past it, what the terrain
    /// could rise over the gap, so that a slope that starts to climb is not lowered while
    /// a car's hood where the road is hidden is).
    reach: f32,
    /// The cell's own confident ground continued the terrain (not a gap cell).
    continued: bool,
}

/// Sectors either way a gap cell looks for confident terrain beside it.
const LATERAL: usize = 3;

/// A monotone stand-in for the azimuth in [0, 4) (no trigonometry): the "diamond angle".
/// Per quadrant y/(x+y), 1 − x/(−x+y), 2 − y/(−x−y), 3 + x/(x−y): every denominator is
/// |x| + |y| (the same bits), so one division and selects serve all four, and a loop
/// over points vectorises.
#[inline(always)]
fn diamond_angle(x: f64, y: f64) -> f64 {
    let (upper, right) = (y >= 0.0, x >= 0.0);
    let f = if upper == right { y } else { x } / (x.abs() + y.abs());
    match (upper, right) {
        (true, true) => f,
        (true, false) => 1.0 - f,
        (false, false) => 2.0 - f,
        (false, true) => 3.0 + f,
    }
}

/// Where the points fall among the cells, and their weights and heights in fixed point.
#[derive(Debug, Clone, Copy)]
struct Placement {
    half_cell: f64,
    max_range: f64,
    per_sector: f64,
    last_sector: u32,
    inv_cell: f64,
    bins: u32,
    /// The cell of a point without one (one past the last).
    none: u32,
    confidence: Ramp,
}

impl Placement {
    /// Each point's cell, confident weight and height, in one straight pass without a
    /// branch (it vectorises: a third of the step's time went to a per-point loop with
    /// branches and pushes). A function of its own with the constants in locals: as a
    /// closure's body it read them again for every point and was not vectorised.
    fn place(
        self,
        (x, y, z, p): (&[f64], &[f64], &[f64], &[f32]),
        cells: &mut [u32],
        weights: &mut [i32],
        heights: &mut [i32],
    ) {
        let Placement {
            half_cell,
            max_range,
            per_sector,
            last_sector,
            inv_cell,
            bins,
            none,
            confidence,
        } = self;
        let points = x.iter().zip(y).zip(z).zip(p);
        let fixed = weights.iter_mut().zip(heights.iter_mut());
        for ((cell, (w, h)), (((&px, &py), &pz), &p)) in cells.iter_mut().zip(fixed).zip(points) {
            let r = (px * px + py * py).sqrt();
            // NaN fails the comparison: no cell.
            let inside = (r >= half_cell) & (r < max_range);
            let q = ((diamond_angle(px, py) * per_sector) as u32).min(last_sector);
            let b = ((r * inv_cell) as u32).min(bins - 1);
            *cell = if inside { q * bins + b } else { none };
            let c = confidence.at(f64::from(p));
            *w = if inside { round_i32(c * WEIGHT_ONE) } else { 0 };
            *h = round_i32(pz.clamp(-HEIGHT_CLAMP, HEIGHT_CLAMP) * HEIGHT_ONE);
        }
    }
}

/// Points changed across the threshold by the terrain: raised to ground, lowered from it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct TerrainChange {
    pub raised: usize,
    pub lowered: usize,
}

/// Follows the terrain of one scan (points in the ground-aligned frame, input order, with
/// their probabilities in `out`) out to `max_range`, raising and lowering as the module
/// says. `threshold` is the decision threshold on `out`.
pub(crate) fn follow_terrain(
    cfg: &TerrainConfig,
    max_range: f64,
    (x, y, z): (&[f64], &[f64], &[f64]),
    out: &mut [f32],
    threshold: f32,
    scratch: &mut TerrainScratch,
) -> TerrainChange {
    if !cfg.enabled || out.is_empty() {
        return TerrainChange::default();
    }
    let sectors = cfg.sectors as usize;
    let bins = ((max_range / cfg.cell).ceil() as usize).max(1);
    let cells = sectors * bins;
    let placement = Placement {
        half_cell: cfg.cell * 0.5,
        max_range,
        per_sector: sectors as f64 / 4.0,
        last_sector: sectors as u32 - 1,
        inv_cell: 1.0 / cfg.cell,
        bins: bins as u32,
        none: cells as u32,
        confidence: Ramp::new(cfg.confident),
    };
    // The per-point passes run in as many parts as there are worker threads, each summing
    // into its own cells (integer sums: the parts add up to the same cells in any split).
    let n = out.len();
    let parts = rayon::current_num_threads().clamp(1, 8);
    let part = n.div_ceil(parts);
    scratch.cells.resize(n, 0);
    scratch.weights.resize(n, 0);
    scratch.heights.resize(n, 0);
    // One more cell per part, where the points without a cell go (with weight 0): the
    // sums then take every point without a branch.
    let slots = cells + 1;
    scratch.sums.clear();
    scratch.sums.resize(parts * slots, [0, 0]);
    scratch.lower.clear();
    scratch.lower.resize(parts * slots, [0, 0]);
    scratch.means.clear();
    scratch.terrain.clear();
    scratch.terrain.resize(cells, TerrainCell::default());
    scratch
        .cells
        .par_chunks_mut(part)
        .zip(scratch.weights.par_chunks_mut(part))
        .zip(scratch.heights.par_chunks_mut(part))
        .zip(scratch.sums.par_chunks_mut(slots))
        .enumerate()
        .for_each(|(k, (((part_cells, weights), heights), sums))| {
            let r = k * part..(k * part + part_cells.len());
            let points = (&x[r.clone()], &y[r.clone()], &z[r.clone()], &out[r]);
            // Cells, weights and heights, then the confident ground's sums.
            placement.place(points, part_cells, weights, heights);
            for ((&cell, &w), &h) in part_cells.iter().zip(&*weights).zip(&*heights) {
                let s = &mut sums[cell as usize];
                s[0] += i64::from(w);
                s[1] += i64::from(w) * i64::from(h);
            }
        });
    let (sums, other_sums) = scratch.sums.split_at_mut(slots);
    add_parts(sums, other_sums);
    // Each cell's mean height rounded down: h ≤ Σwh / Σw exactly where h ≤ ⌊Σwh / Σw⌋ (h
    // an integer, Σw > 0).
    scratch.means.extend(sums.iter().map(
        |&[sw, swh]| {
            if sw > 0 { swh.div_euclid(sw) } else { i64::MIN }
        },
    ));
    let means: &[i64] = &scratch.means;
    // The lower mean: again over the confident points at or below their cell's mean, so
    // that the few returns of a car's skirt among a cell's road do not lift it (the
    // confident ground of a cell is mostly road; what stands on it is above).
    let sums: &[[i64; 2]] = sums;
    scratch
        .cells
        .par_chunks(part)
        .zip(scratch.weights.par_chunks(part))
        .zip(scratch.heights.par_chunks(part))
        .zip(scratch.lower.par_chunks_mut(slots))
        .for_each(|(((part_cells, weights), heights), lower)| {
            for ((&cell, &w), &h) in part_cells.iter().zip(weights).zip(heights) {
                let h = i64::from(h);
                let w = if h <= means[cell as usize] {
                    i64::from(w)
                } else {
                    0
                };
                let l = &mut lower[cell as usize];
                l[0] += w;
                l[1] += w * h;
            }
        });
    let (lower, other_lower) = scratch.lower.split_at_mut(slots);
    add_parts(lower, other_lower);
    let (sums, lower): (&[[i64; 2]], &[[i64; 2]]) = (sums, lower);
    // The ground at the sensor's foot: the median over the sectors of the first cell of
    // confident ground within `gap` (0, the mount's, if too few sectors have one). Not the
    // mount's height alone, which is only as right as the mount: the first cells beside a
    // foot set too high would fail the tight bound below everywhere.
    // A cell's confident ground, where it has enough to count (half of `support`): its
    // lower mean height.
    let confident = |cell: usize| {
        let [lw, lwh] = lower[cell];
        let weight = sums[cell][0] as f64 / WEIGHT_ONE;
        (lw > 0 && weight >= cfg.support * 0.5).then(|| lwh as f64 / lw as f64 / HEIGHT_ONE)
    };
    scratch.first.clear();
    for q in 0..sectors {
        let row = q * bins;
        let first = (0..bins)
            .take_while(|&b| (b as f64 + 0.5) * cfg.cell <= cfg.gap.max(cfg.cell))
            .find_map(|b| confident(row + b));
        scratch.first.extend(first);
    }
    let foot = if scratch.first.len() * 4 >= sectors {
        scratch.first.sort_by(f64::total_cmp);
        scratch.first[scratch.first.len() / 2]
    } else {
        0.0
    };
    // From the foot, where the vehicle stands on the ground (the frame is aligned to it),
    // the grade can only have grown from 0 to `grade` over `gap`: the ground within `run`
    // of it lies within this of the foot's height. A car's side beside the vehicle, seen
    // before the lowest beam meets the road, stands above that.
    let from_foot = |run: f64| {
        let run = run.max(0.0);
        cfg.step + cfg.grade * run * run.min(cfg.gap) / (2.0 * cfg.gap.max(f64::MIN_POSITIVE))
    };
    // Each sector, outward from the sensor's foot.
    let (full_support, over_gap) = (Ramp::new([0.0, cfg.support]), Ramp::new([0.0, cfg.gap]));
    for q in 0..sectors {
        let row = q * bins;
        let (mut last_b, mut last_h, mut slope) = (-0.5f64, foot, 0.0f64);
        for b in 0..bins {
            let centre = (b as f64 + 0.5) * cfg.cell;
            let run = centre - last_b * cfg.cell;
            let predicted = last_h + slope * run;
            let support = full_support.at(sums[row + b][0] as f64 / WEIGHT_ONE);
            let bound = if last_b < 0.0 {
                from_foot(run)
            } else {
                cfg.step + cfg.grade * run
            };
            let continues = confident(row + b).filter(|h| (h - predicted).abs() <= bound);
            scratch.terrain[row + b] = match continues {
                Some(h) => {
                    let grade = ((h - last_h) / run).clamp(-cfg.grade, cfg.grade);
                    slope = 0.7 * slope + 0.3 * grade;
                    (last_b, last_h) = (b as f64 + 0.5, h);
                    TerrainCell {
                        height: h as f32,
                        raise: support as f32,
                        lower: support as f32,
                        reach: 0.0,
                        continued: true,
                    }
                }
                _ => {
                    let gap = run - 0.5 * cfg.cell;
                    let trust = 1.0 - over_gap.at(gap);
                    // How far the ground could have risen since the last confident cell:
                    // from the steepest fall to the steepest climb over the gap (from the
                    // foot, as above).
                    let reach = if last_b < 0.0 {
                        from_foot(gap)
                    } else {
                        cfg.step + 2.0 * cfg.grade * gap.max(0.0)
                    };
                    TerrainCell {
                        height: predicted as f32,
                        raise: trust as f32,
                        lower: trust as f32,
                        reach: reach as f32,
                        continued: false,
                    }
                }
            };
        }
    }
    // Beside the gap: a cell past the last confident one of its sector whose neighbouring
    // sectors (up to `LATERAL` either way) hold confident terrain at the same range (a
    // parked car hides the road behind it, not beside it): the nearest such terrain raises
    // as the cell's own would, trusted less with each sector across, and the lowest
    // ceiling of the two ways (along: the climb over the gap; across: `grade` over the
    // distance to that sector) is where lowering starts. Only the walk's own cells are
    // read, so the order the sectors are visited in does not matter.
    let sector_width = std::f64::consts::TAU / sectors as f64;
    scratch.beside.clear();
    for q in 0..sectors {
        // The sectors either way, k = 1..=LATERAL, nearer first (worked out once a sector:
        // a modulo per gap cell and neighbour was a tenth of this step).
        let sides: [[usize; 2]; LATERAL] = std::array::from_fn(|i| {
            [
                (q + i + 1) % sectors,
                (q + sectors - (i + 1) % sectors) % sectors,
            ]
        });
        for b in 0..bins {
            let cell = scratch.terrain[q * bins + b];
            if cell.continued {
                continue;
            }
            let across = (b as f64 + 0.5) * cfg.cell * sector_width;
            let mut ceiling = (f64::from(cell.height) + f64::from(cell.reach), cell.lower);
            let mut near: Option<(f32, f32)> = None;
            for (k, pair) in (1..=LATERAL).zip(sides) {
                for n in pair {
                    let side = scratch.terrain[n * bins + b];
                    let (hn, support) = (side.height, side.lower);
                    if !side.continued || support <= 0.0 {
                        continue;
                    }
                    let c = f64::from(hn) + cfg.step + cfg.grade * across * k as f64;
                    if c < ceiling.0 {
                        ceiling = (c, support);
                    }
                    let t = support * (1.0 - k as f32 / (LATERAL + 1) as f32);
                    // The nearer, then the lower of two at the same distance.
                    if near.is_none_or(|(hm, tm)| t > tm || (t == tm && hn < hm)) {
                        near = Some((hn, t));
                    }
                }
            }
            let (height, raise) = match near {
                Some((hn, t)) if t > cell.raise => (hn, t),
                _ => (cell.height, cell.raise),
            };
            scratch.beside.push((
                q * bins + b,
                TerrainCell {
                    height,
                    raise,
                    lower: ceiling.1,
                    reach: (ceiling.0 - f64::from(height)).max(0.0) as f32,
                    continued: false,
                },
            ));
        }
    }
    for &(cell, t) in &scratch.beside {
        scratch.terrain[cell] = t;
    }
    // Raise the points at the terrain's height, lower those standing above it. The two
    // bands never meet (`tolerance` ends below where `veto` begins), so one formula serves
    // every point, continuous in its probability.
    let judge = Judge {
        tolerance: Ramp::new(cfg.tolerance),
        veto: Ramp::new(cfg.veto),
        probability: cfg.probability,
        lower: cfg.lower,
    };
    // A point without a cell reads the last entry, which has no terrain.
    let no_cell = [0.0; 4];
    let to_lanes = |c: &TerrainCell| [c.height, c.raise, c.lower, c.reach].map(f64::from);
    scratch.lanes.clear();
    scratch.lanes.extend(scratch.terrain.iter().map(to_lanes));
    scratch.lanes.push(no_cell);
    let lanes: &[[f64; 4]] = &scratch.lanes;
    let [raised, lowered] = out
        .par_chunks_mut(part)
        .zip(scratch.cells.par_chunks(part))
        .zip(z.par_chunks(part))
        .map(|((out, part_cells), z)| {
            let mut counts = [0usize; 2];
            let mut judge_four = |p: &mut [f32], cells: [u32; 4], z: [f64; 4]| {
                let old: [f32; 4] = std::array::from_fn(|k| p.get(k).copied().unwrap_or(0.0));
                let new = judge.four(lanes, cells, z, old);
                for ((p, old), new) in p.iter_mut().zip(old).zip(new) {
                    counts[0] += usize::from((old < threshold) & (new >= threshold));
                    counts[1] += usize::from((old >= threshold) & (new < threshold));
                    *p = new;
                }
            };
            // Four points at a time: each point's terrain gathered, then one formula over
            // the four; a last partial four padded with points that have no cell.
            let whole = out.len() / 4 * 4;
            let (out, rest) = out.split_at_mut(whole);
            let quads = out.chunks_exact_mut(4).zip(part_cells.chunks_exact(4));
            for ((p, cells), z) in quads.zip(z.chunks_exact(4)) {
                judge_four(
                    p,
                    std::array::from_fn(|k| cells[k]),
                    std::array::from_fn(|k| z[k]),
                );
            }
            if !rest.is_empty() {
                let pad = |k: usize| whole + k;
                judge_four(
                    rest,
                    std::array::from_fn(|k| {
                        part_cells.get(pad(k)).copied().unwrap_or(cells as u32)
                    }),
                    std::array::from_fn(|k| z.get(pad(k)).copied().unwrap_or(0.0)),
                );
            }
            counts
        })
        .reduce(|| [0, 0], |a, b| [a[0] + b[0], a[1] + b[1]]);
    TerrainChange { raised, lowered }
}

/// The raising and lowering rule of the last pass, its constants worked out once.
#[derive(Debug, Clone, Copy)]
struct Judge {
    tolerance: Ramp,
    veto: Ramp,
    probability: f64,
    lower: bool,
}

impl Judge {
    /// The new probabilities of four points (their cells, heights and probabilities):
    /// raised towards `probability` at the terrain's height, lowered above its reach. A
    /// point its cell does not judge (no cell, or a cell without terrain) keeps its own,
    /// as does one whose probability the rule leaves as it was. In f64 lanes, without a
    /// branch: the same operations, in the same order, as one point at a time.
    #[inline(always)]
    fn four(&self, lanes: &[[f64; 4]], cells: [u32; 4], z: [f64; 4], old: [f32; 4]) -> [f32; 4] {
        let none = lanes.len() - 1;
        let t = cells.map(|c| f64x4::new(lanes[(c as usize).min(none)]));
        let [height, trust, lower, reach] = f64x4::transpose(t);
        let above = f64x4::new(z) - height;
        let old64 = f64x4::new(old.map(f64::from));
        let one = f64x4::ONE;
        let matched = one - self.tolerance.at4(above.abs());
        let raised = old64.fast_max(f64x4::splat(self.probability) * matched * trust);
        let new = if self.lower {
            raised * (one - lower * self.veto.at4(above - reach))
        } else {
            raised
        };
        let judged = trust.simd_gt(f64x4::ZERO).to_bitmask();
        let new = new.to_array().map(|v| v as f32);
        // Selects, not branches: which points change follows the scene.
        std::array::from_fn(|k| {
            let moved = ((judged >> k) & 1 == 1) & (new[k] != old[k]);
            if moved { new[k] } else { old[k] }
        })
    }
}

/// Adds the sums of the other parts (`parts`, one run of `cells.len()` each) into `cells`.
fn add_parts(cells: &mut [[i64; 2]], parts: &[[i64; 2]]) {
    for other in parts.chunks_exact(cells.len()) {
        for (c, o) in cells.iter_mut().zip(other) {
            c[0] += o[0];
            c[1] += o[1];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The diamond angle by one division and selects gives the bits of the quadrant by
    /// quadrant form it replaced, for any coordinates the step bins.
    #[test]
    fn the_diamond_angle_has_the_bits_of_the_quadrant_formula() {
        let plain = |x: f64, y: f64| {
            if y >= 0.0 {
                if x >= 0.0 {
                    y / (x + y)
                } else {
                    1.0 - x / (-x + y)
                }
            } else if x < 0.0 {
                2.0 - y / (-x - y)
            } else {
                3.0 + x / (x - y)
            }
        };
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(90);
        let special = [0.0, -0.0, 1e-300, -1e-300, 1.0, -1.0, 79.9, -0.3, 1e6];
        let mut pairs: Vec<(f64, f64)> = special
            .iter()
            .flat_map(|&x| special.iter().map(move |&y| (x, y)))
            .collect();
        pairs.extend((0..100_000).map(|_| {
            (
                rng.random_range(-100.0..100.0),
                rng.random_range(-100.0..100.0),
            )
        }));
        for (x, y) in pairs {
            let (a, b) = (diamond_angle(x, y), plain(x, y));
            // Where r = 0 (both zero) the quotient is NaN either way and the point has no
            // cell.
            assert!(
                a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                "({x}, {y}): {a} against {b}"
            );
        }
    }

    /// A road falling at 5 % away from the sensor along +x, 4 m wide, a point every 0.25 m
    /// out to 45 m: confident (0.9) out to 20 m, left at 0 beyond (the mixtures lost it);
    /// and a car's skirt 0.3 m above the road at 12 m, called ground (0.9).
    fn street() -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f32>, usize) {
        let (mut x, mut y, mut z, mut p) = (vec![], vec![], vec![], vec![]);
        for i in 8..180 {
            for j in -8..=8 {
                let r = f64::from(i) * 0.25;
                x.push(r);
                y.push(f64::from(j) * 0.25);
                z.push(-0.05 * r);
                p.push(if r < 20.0 { 0.9 } else { 0.0 });
            }
        }
        let skirt = x.len();
        // A beam's few returns off the skirt, among the road's many in its cells.
        for k in 0..6 {
            let r = 12.0 + f64::from(k) * 0.4;
            x.push(r);
            y.push(0.6);
            z.push(-0.05 * r + 0.3);
            p.push(0.9);
        }
        // A car beyond the confident road, hiding the road under it: its hood 0.9 m up,
        // called ground (the segment's lowest component).
        for k in 0..4 {
            let r = 20.2 + f64::from(k) * 0.4;
            x.push(r);
            y.push(-0.6);
            z.push(-0.05 * r + 0.9);
            p.push(0.9);
        }
        (x, y, z, p, skirt)
    }

    fn run(
        cfg: &TerrainConfig,
        (x, y, z): (&[f64], &[f64], &[f64]),
        p: &mut [f32],
    ) -> TerrainChange {
        follow_terrain(cfg, 80.0, (x, y, z), p, 0.5, &mut TerrainScratch::default())
    }

    /// The per-point passes split the scan into one part per worker thread: any number of
    /// threads gives the same bits and counts, including a scan whose length is not a
    /// multiple of four and points without a cell (at the foot, beyond the range).
    #[test]
    fn every_thread_count_gives_the_same_bits() {
        let (mut x, mut y, mut z, mut p, _) = street();
        for (px, py, pz, pp) in [
            (0.1, 0.0, -0.1, 0.9),
            (90.0, 1.0, -4.0, 0.3),
            (0.0, 0.0, 0.0, 0.0),
        ] {
            x.push(px);
            y.push(py);
            z.push(pz);
            p.push(pp);
        }
        assert_ne!(x.len() % 4, 0);
        let cfg = TerrainConfig {
            enabled: true,
            ..TerrainConfig::default()
        };
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut q = p.clone();
            let change = pool.install(|| run(&cfg, (&x, &y, &z), &mut q));
            (q.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), change)
        };
        let one = on(1);
        assert!(one.1.raised > 100 && one.1.lowered > 0, "{:?}", one.1);
        for threads in [2, 3, 5, 8] {
            assert_eq!(on(threads), one, "{threads} threads");
        }
    }

    #[test]
    fn the_far_ground_rises_and_a_skirt_above_the_road_falls() {
        let (x, y, z, mut p, skirt) = street();
        let cfg = TerrainConfig {
            enabled: true,
            ..TerrainConfig::default()
        };
        let change = run(&cfg, (&x, &y, &z), &mut p);
        // Past the confident road the lost road rises, trusted less with each metre of the
        // gap (10 m): to ground for the first few metres, towards it up to 30 m, and not
        // beyond.
        let at = |lo: f64, hi: f64| -> Vec<f32> {
            (0..skirt)
                .filter(|&i| x[i] >= lo && x[i] < hi)
                .map(|i| p[i])
                .collect()
        };
        assert!(
            at(20.0, 23.0).iter().all(|&v| v >= 0.5),
            "{:?}",
            at(20.0, 23.0)
        );
        assert!(at(24.0, 30.0).iter().all(|&v| v > 0.0 && v < 0.5));
        assert!(at(31.0, 45.0).iter().all(|&v| v == 0.0));
        // The skirt over seen road, and the hood where the road is hidden: more than the
        // steepest grade could have climbed since the last confident cell.
        assert!(p[skirt..].iter().all(|&v| v < 0.5), "{:?}", &p[skirt..]);
        assert!(change.raised > 100 && change.lowered == 10, "{change:?}");
        // Raising only: the same ground rises, nothing is lowered.
        let (x, y, z, mut q, _) = street();
        let raising = TerrainConfig {
            enabled: true,
            lower: false,
            ..TerrainConfig::default()
        };
        let only = run(&raising, (&x, &y, &z), &mut q);
        assert_eq!(only.raised, change.raised);
        assert_eq!(only.lowered, 0);
        assert!(q[skirt..].iter().all(|&v| v >= 0.9), "{:?}", &q[skirt..]);
        // Off: nothing moves.
        let (x, y, z, mut q, _) = street();
        let before = q.clone();
        let off = TerrainConfig::default();
        assert_eq!(run(&off, (&x, &y, &z), &mut q), TerrainChange::default());
        assert_eq!(q, before);
    }

    #[test]
    fn a_car_hiding_the_road_is_lowered_and_the_road_behind_it_raised_from_beside() {
        // A flat road seen from 4 to 30 m over ±12°, confident (0.9); straight ahead
        // (within 1.25°: two sectors) a car at 13–14 m hides it from 10 m on: its hood
        // 0.9 m up called ground, and the road behind it, from 17 m, lost by the
        // mixtures (0).
        let (mut x, mut y, mut z, mut p) = (vec![], vec![], vec![], vec![]);
        let (mut hood, mut behind) = (vec![], vec![]);
        for i in -24..=24 {
            let deg = f64::from(i) * 0.5;
            let ahead = deg.abs() < 1.25;
            for j in 16..120 {
                let r = f64::from(j) * 0.25;
                let (h, v) = match (ahead, r) {
                    (true, r) if (13.0..14.0).contains(&r) => {
                        hood.push(x.len());
                        (0.9, 0.9)
                    }
                    (true, r) if r >= 17.0 => {
                        behind.push(x.len());
                        (0.0, 0.0)
                    }
                    (true, r) if r >= 10.0 => continue,
                    _ => (0.0, 0.9),
                };
                let a = deg.to_radians();
                x.push(r * a.cos());
                y.push(r * a.sin());
                z.push(h);
                p.push(v);
            }
        }
        let cfg = TerrainConfig {
            enabled: true,
            ..TerrainConfig::default()
        };
        // Ahead, the hood is within what the road could have climbed since 10 m, and the
        // road behind the car is trusted too little to rise: what decides is the road
        // beside.
        run(&cfg, (&x, &y, &z), &mut p);
        assert!(
            hood.iter().all(|&i| p[i] < 0.5),
            "{:?}",
            hood.iter().map(|&i| p[i]).collect::<Vec<_>>()
        );
        assert!(
            behind.iter().all(|&i| p[i] >= 0.5),
            "{:?}",
            behind.iter().map(|&i| p[i]).collect::<Vec<_>>()
        );
    }

    #[test]
    fn a_car_side_beside_the_vehicle_is_not_taken_for_the_road_whatever_the_mount() {
        // A flat road all around, seen from 4 to 20 m (a point every degree and 0.25 m),
        // confident (0.9); on the left (80°–100°) a parked car's side 2–3.5 m away, 0.5 m
        // above the road, called ground (0.9), hiding the road up to 6 m. The road lies
        // at `road` in the frame: 0 where the mount is right, below or above the foot
        // where it is set too high or too low.
        for road in [0.0, -0.3, 0.2] {
            let (mut x, mut y, mut z, mut p) = (vec![], vec![], vec![], vec![]);
            let mut side = vec![];
            for deg in 0..360 {
                let a = f64::from(deg).to_radians();
                let left = (80..=100).contains(&deg);
                for j in 8..80 {
                    let r = f64::from(j) * 0.25;
                    let h = if left && r < 3.5 {
                        side.push(x.len());
                        road + 0.5
                    } else if (left && r < 6.0) || r < 4.0 {
                        continue;
                    } else {
                        road
                    };
                    x.push(r * a.cos());
                    y.push(r * a.sin());
                    z.push(h);
                    p.push(0.9);
                }
            }
            let cfg = TerrainConfig {
                enabled: true,
                ..TerrainConfig::default()
            };
            run(&cfg, (&x, &y, &z), &mut p);
            let sides: Vec<f32> = side.iter().map(|&i| p[i]).collect();
            assert!(sides.iter().all(|&v| v < 0.5), "road at {road}: {sides:?}");
            let kept = (0..p.len())
                .filter(|i| !side.contains(i) && p[*i] >= 0.5)
                .count();
            assert_eq!(kept, p.len() - side.len(), "road at {road}");
        }
    }

    #[test]
    fn a_permuted_scan_gives_the_same_probabilities_permuted() {
        let (x, y, z, p, _) = street();
        let cfg = TerrainConfig {
            enabled: true,
            ..TerrainConfig::default()
        };
        let mut want = p.clone();
        run(&cfg, (&x, &y, &z), &mut want);
        // Reversed, and every third point moved to the front.
        let order: Vec<usize> = (0..x.len())
            .rev()
            .filter(|i| i % 3 == 0)
            .chain((0..x.len()).filter(|i| i % 3 != 0))
            .collect();
        let pick = |v: &[f64]| order.iter().map(|&i| v[i]).collect::<Vec<_>>();
        let (px, py, pz) = (pick(&x), pick(&y), pick(&z));
        let mut got: Vec<f32> = order.iter().map(|&i| p[i]).collect();
        run(&cfg, (&px, &py, &pz), &mut got);
        for (k, &i) in order.iter().enumerate() {
            assert_eq!(got[k].to_bits(), want[i].to_bits(), "point {i}");
        }
    }
}
