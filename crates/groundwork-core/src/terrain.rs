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
use crate::continuity::{HEIGHT_CLAMP, HEIGHT_ONE, WEIGHT_ONE, rise};
use crate::fastmath::round_i32;

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
    /// Gap cells as the terrain beside them changes them (cell, its new terrain).
    beside: Vec<(usize, TerrainCell)>,
    /// Per point: its cell (`u32::MAX`: none).
    cells: Vec<u32>,
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

/// A ramp from 0 at `from` to 1 at `to`, as a multiplication by the reciprocal of its
/// width: the per-point passes took two divisions a point through `rise`, and a division
/// costs several times a multiplication (scalar in the raise/lower pass). Within an ulp of
/// `rise`; a continuous ramp still, so stability does not hang on it.
#[derive(Debug, Clone, Copy)]
struct Ramp {
    from: f64,
    scale: f64,
}

impl Ramp {
    fn new([from, to]: [f64; 2]) -> Self {
        Self {
            from,
            scale: 1.0 / (to - from),
        }
    }

    #[inline(always)]
    fn at(self, v: f64) -> f64 {
        ((v - self.from) * self.scale).clamp(0.0, 1.0)
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
    let mut change = TerrainChange::default();
    if !cfg.enabled || out.is_empty() {
        return change;
    }
    let sectors = cfg.sectors as usize;
    let bins = ((max_range / cfg.cell).ceil() as usize).max(1);
    let cells = sectors * bins;
    scratch.sums.clear();
    scratch.sums.resize(cells, [0, 0]);
    scratch.terrain.clear();
    scratch.terrain.resize(cells, TerrainCell::default());
    let per_sector = sectors as f64 / 4.0;
    let inv_cell = 1.0 / cfg.cell;
    let confidence = Ramp::new(cfg.confident);
    // Cells, weights and heights in one straight pass without a branch (it vectorises:
    // a third of this step's time went to a per-point loop with branches and pushes),
    // then the confident ground's sums.
    let n = out.len();
    scratch.cells.resize(n, 0);
    scratch.weights.resize(n, 0);
    scratch.heights.resize(n, 0);
    let points = x.iter().zip(y).zip(z).zip(out.iter());
    let fixed = scratch.weights.iter_mut().zip(scratch.heights.iter_mut());
    for ((cell, (w, h)), (((&px, &py), &pz), &p)) in scratch.cells.iter_mut().zip(fixed).zip(points)
    {
        let r = (px * px + py * py).sqrt();
        // NaN fails the comparison: no cell.
        let inside = (r >= cfg.cell * 0.5) & (r < max_range);
        let q = ((diamond_angle(px, py) * per_sector) as u32).min(sectors as u32 - 1);
        let b = ((r * inv_cell) as u32).min(bins as u32 - 1);
        *cell = if inside {
            q * bins as u32 + b
        } else {
            u32::MAX
        };
        let c = confidence.at(f64::from(p));
        *w = if inside { round_i32(c * WEIGHT_ONE) } else { 0 };
        *h = round_i32(pz.clamp(-HEIGHT_CLAMP, HEIGHT_CLAMP) * HEIGHT_ONE);
    }
    for ((&cell, &w), &h) in scratch
        .cells
        .iter()
        .zip(&scratch.weights)
        .zip(&scratch.heights)
    {
        if w > 0 {
            let s = &mut scratch.sums[cell as usize];
            s[0] += i64::from(w);
            s[1] += i64::from(w) * i64::from(h);
        }
    }
    // The lower mean: again over the confident points at or below their cell's mean, so
    // that the few returns of a car's skirt among a cell's road do not lift it (the
    // confident ground of a cell is mostly road; what stands on it is above).
    scratch.lower.clear();
    scratch.lower.resize(cells, [0, 0]);
    for ((&cell, &w), &h) in scratch
        .cells
        .iter()
        .zip(&scratch.weights)
        .zip(&scratch.heights)
    {
        if w > 0 {
            let [sw, swh] = scratch.sums[cell as usize];
            // h ≤ swh / sw, in integers (sw > 0).
            if i128::from(h) * i128::from(sw) <= i128::from(swh) {
                let l = &mut scratch.lower[cell as usize];
                l[0] += i64::from(w);
                l[1] += i64::from(w) * i64::from(h);
            }
        }
    }
    // The ground at the sensor's foot: the median over the sectors of the first cell of
    // confident ground within `gap` (0, the mount's, if too few sectors have one). Not the
    // mount's height alone, which is only as right as the mount: the first cells beside a
    // foot set too high would fail the tight bound below everywhere.
    // A cell's confident ground, where it has enough to count (half of `support`): its
    // lower mean height.
    let confident = |cell: usize| {
        let [lw, lwh] = scratch.lower[cell];
        let weight = scratch.sums[cell][0] as f64 / WEIGHT_ONE;
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
    for q in 0..sectors {
        let row = q * bins;
        let (mut last_b, mut last_h, mut slope) = (-0.5f64, foot, 0.0f64);
        for b in 0..bins {
            let centre = (b as f64 + 0.5) * cfg.cell;
            let run = centre - last_b * cfg.cell;
            let predicted = last_h + slope * run;
            let support = rise(
                scratch.sums[row + b][0] as f64 / WEIGHT_ONE,
                [0.0, cfg.support],
            );
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
                    let trust = 1.0 - rise(gap, [0.0, cfg.gap]);
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
        for b in 0..bins {
            let cell = scratch.terrain[q * bins + b];
            if cell.continued {
                continue;
            }
            let across = (b as f64 + 0.5) * cfg.cell * sector_width;
            let mut ceiling = (f64::from(cell.height) + f64::from(cell.reach), cell.lower);
            let mut near: Option<(f32, f32)> = None;
            for k in 1..=LATERAL {
                for n in [(q + k) % sectors, (q + sectors - k % sectors) % sectors] {
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
    let (tolerance, veto) = (Ramp::new(cfg.tolerance), Ramp::new(cfg.veto));
    // Without a branch per point (which points have terrain, and which change, follow the
    // scene): a point without a cell reads cell 0 and keeps its value.
    let last = scratch.terrain.len() - 1;
    for ((p, &cell), &z) in out.iter_mut().zip(&scratch.cells).zip(z) {
        let TerrainCell {
            height,
            raise,
            lower,
            reach,
            ..
        } = scratch.terrain[(cell as usize).min(last)];
        let judged = (cell != u32::MAX) & (raise > 0.0);
        let above = z - f64::from(height);
        let trust = f64::from(raise);
        let old = *p;
        let matched = 1.0 - tolerance.at(above.abs());
        let raised = f64::from(old).max(cfg.probability * matched * trust);
        let lowered = if cfg.lower {
            f64::from(lower) * veto.at(above - f64::from(reach))
        } else {
            0.0
        };
        let new = (raised * (1.0 - lowered)) as f32;
        let moved = judged & (new != old);
        change.raised += usize::from(moved & (old < threshold) & (new >= threshold));
        change.lowered += usize::from(moved & (old >= threshold) & (new < threshold));
        *p = if moved { new } else { old };
    }
    change
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
