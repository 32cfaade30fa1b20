//! Euclidean clustering on a bird's-eye grid of vertical column segments.
//!
//! The points of each grid cell, sorted by height, are cut into segments wherever two
//! neighbours in height are more than the vertical cluster distance d_v apart. Two segments
//! join when the lower bounds of the distances between their points that the grid gives —
//! the horizontal gap h between their cells and the vertical gap v between their height
//! intervals — satisfy (h / d_h)² + (v / d_v)² ≤ 1: Euclidean single-linkage clustering in
//! a metric stretched vertically (a scanning sensor's rings are farther apart than its
//! points along a ring), up to one cell diagonal (points at most √2·cell farther apart may
//! join; points within the distance always join). It keeps a car apart from the crown
//! above it, and it costs one sort and a bounded look around each segment instead of a
//! radius query per point: a wall near the sensor holds hundreds of points per square
//! metre, which is what makes point-wise radius search (a k-d tree) slow here.

use crate::config::DetectorConfig;
use crate::grid::SquareGrid;

/// Points of one cell within one height interval.
#[derive(Debug, Clone, Copy)]
struct Segment {
    z_min: f32,
    z_max: f32,
}

/// A grid cell: the scan that last used it (cells of older scans are empty), and its
/// segments (valid where `scan` is current). One record, so a look at a neighbour is one
/// memory access.
#[derive(Debug, Clone, Copy, Default)]
struct Cell {
    scan: u32,
    first: u32,
    len: u32,
}

/// The clustering grid and its scratch, reused from scan to scan.
#[derive(Debug, Clone, Default)]
pub struct ClusterGrid {
    grid: SquareGrid,
    cells: Vec<Cell>,
    /// One bit per cell, set where the current scan has points: a neighbour look is a bit
    /// test in a bitmap that stays in cache, not a miss in the 1 000 × 1 000 cell array.
    occupancy: Vec<u64>,
    words_per_row: usize,
    scan: u32,
    /// Occupied cells of the current scan, in grid order.
    occupied: Vec<u32>,
    /// Scratch: each point's cell, and the points bucketed by cell.
    cell_of_point: Vec<u32>,
    order: Vec<u32>,
    segments: Vec<Segment>,
    parent: Vec<u32>,
    component: Vec<u32>,
}

impl ClusterGrid {
    /// A grid of `cell` metres covering ±`max_range`.
    pub fn new(cell: f32, max_range: f32) -> Self {
        let grid = SquareGrid::new(cell, max_range);
        let words_per_row = grid.side.div_ceil(64) + 1; // + 1: a window may read one word past
        Self {
            grid,
            cells: vec![Cell::default(); grid.len()],
            occupancy: vec![0; grid.side * words_per_row],
            words_per_row,
            ..Default::default()
        }
    }

    /// Bits of row `i`, columns `j0 .. j0 + 64` (clipped to the grid; bit k is column j0 + k).
    #[inline]
    fn row_bits(&self, i: i32, j0: i32) -> u64 {
        let n = self.grid.side as i32;
        if i < 0 || i >= n {
            return 0;
        }
        let row = &self.occupancy[i as usize * self.words_per_row..][..self.words_per_row];
        if j0 >= 0 {
            let (w, b) = ((j0 / 64) as usize, (j0 % 64) as u32);
            let lo = row.get(w).copied().unwrap_or(0) >> b;
            let hi = if b == 0 {
                0
            } else {
                row.get(w + 1).copied().unwrap_or(0) << (64 - b)
            };
            lo | hi
        } else {
            // Columns below 0 are empty.
            row[0].checked_shl((-j0) as u32).unwrap_or(0)
        }
    }

    /// The current scan's record of cell (i, j), if it has points.
    #[inline]
    fn occupied_cell(&self, i: i32, j: i32) -> Option<Cell> {
        if !self.grid.contains(i, j) {
            return None;
        }
        let c = self.cells[self.grid.index(i, j)];
        (c.scan == self.scan).then_some(c)
    }

    fn find(&mut self, mut a: u32) -> u32 {
        while self.parent[a as usize] != a {
            let up = self.parent[self.parent[a as usize] as usize];
            self.parent[a as usize] = up;
            a = up;
        }
        a
    }

    fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        // The smaller root wins: the result does not depend on the order of unions.
        if ra < rb {
            self.parent[rb as usize] = ra;
        } else if rb < ra {
            self.parent[ra as usize] = rb;
        }
    }

    /// Clusters `points` (ground-aligned x, y, z; finite): writes a component number per
    /// point into `labels` (`u32::MAX` for a point outside the grid) and returns how many
    /// components there are. Components are numbered in the order of their first cell in
    /// the grid; the result depends only on the points, not on their order.
    pub fn cluster(
        &mut self,
        points: &[[f32; 3]],
        cfg: &DetectorConfig,
        labels: &mut Vec<u32>,
    ) -> usize {
        self.scan = self.scan.wrapping_add(1);
        if self.scan == 0 {
            // Once in 4 billion scans: stamps from the previous wrap would look current.
            self.cells.fill(Cell::default());
            self.scan = 1;
        }
        // Clear the previous scan's occupancy bits.
        for &c in &self.occupied {
            let (i, j) = self.grid.ij(c);
            self.occupancy[i as usize * self.words_per_row + j as usize / 64] = 0;
        }
        self.occupied.clear();

        // Bucket the points by cell (a counting sort: `len` counts, then `first` is the
        // bucket's offset), cells in grid order, each bucket sorted by height.
        let mut cell_of = std::mem::take(&mut self.cell_of_point);
        cell_of.clear();
        for p in points {
            let Some((i, j)) = self.grid.cell_of(p[0], p[1]) else {
                cell_of.push(u32::MAX);
                continue;
            };
            let c = self.grid.index(i, j);
            let cell = &mut self.cells[c];
            if cell.scan != self.scan {
                *cell = Cell {
                    scan: self.scan,
                    first: 0,
                    len: 0,
                };
                self.occupied.push(c as u32);
                self.occupancy[i as usize * self.words_per_row + j as usize / 64] |= 1 << (j % 64);
            }
            cell.len += 1;
            cell_of.push(c as u32);
        }
        self.occupied.sort_unstable();
        let mut offset = 0u32;
        for &c in &self.occupied {
            let cell = &mut self.cells[c as usize];
            cell.first = offset;
            offset += cell.len;
            cell.len = 0;
        }
        let mut order = std::mem::take(&mut self.order);
        order.clear();
        order.resize(offset as usize, 0);
        for (k, &c) in cell_of.iter().enumerate() {
            if c != u32::MAX {
                let cell = &mut self.cells[c as usize];
                order[(cell.first + cell.len) as usize] = k as u32;
                cell.len += 1;
            }
        }
        self.cell_of_point = cell_of;

        // Column segments, and the point → segment map (in `labels` for now); each cell's
        // record then names its segments instead of its points.
        labels.clear();
        labels.resize(points.len(), u32::MAX);
        self.segments.clear();
        for &c in &self.occupied {
            let (i, j) = self.grid.ij(c);
            let gap = cfg.vertical_distance_at(self.grid.range(i, j));
            let cell = self.cells[c as usize];
            let bucket = &mut order[cell.first as usize..(cell.first + cell.len) as usize];
            bucket.sort_unstable_by(|&a, &b| {
                points[a as usize][2]
                    .total_cmp(&points[b as usize][2])
                    .then(a.cmp(&b))
            });
            let first = self.segments.len() as u32;
            for &k in bucket.iter() {
                let z = points[k as usize][2];
                let in_cell = self.segments.len() as u32 > first;
                match self.segments.last_mut() {
                    Some(s) if in_cell && z - s.z_max <= gap => s.z_max = z,
                    _ => self.segments.push(Segment { z_min: z, z_max: z }),
                }
                labels[k as usize] = self.segments.len() as u32 - 1;
            }
            self.cells[c as usize] = Cell {
                scan: self.scan,
                first,
                len: self.segments.len() as u32 - first,
            };
        }
        self.order = order;

        // Join segments of neighbouring cells (each pair of cells looked at once).
        let n = self.segments.len();
        self.parent.clear();
        self.parent.extend(0..n as u32);
        for k in 0..self.occupied.len() {
            let cell = self.occupied[k];
            let a = self.cells[cell as usize];
            let (i, j) = self.grid.ij(cell);
            // The distances of this cell's range serve its whole look-around (d changes by
            // a few millimetres across it).
            let r = self.grid.range(i, j);
            let (dh, dv) = (cfg.distance_at(r), cfg.vertical_distance_at(r));
            let (inv_dh2, inv_dv) = (1.0 / (dh * dh), 1.0 / dv);
            // (At most 31 cells: the configuration keeps d under 30 cells.)
            let reach = ((dh / self.grid.cell).floor() as i32 + 1).min(31);
            for di in 0..=reach {
                let gx = (di - 1).max(0) as f32 * self.grid.cell;
                // Occupied columns j − reach ..= j + reach of row i + di.
                let width = 2 * reach + 1;
                let mut bits = self.row_bits(i + di, j - reach) & (u64::MAX >> (64 - width));
                if di == 0 {
                    bits &= !((1u64 << (reach + 1)) - 1); // this row: only columns after j
                }
                while bits != 0 {
                    let dj = bits.trailing_zeros() as i32 - reach;
                    bits &= bits - 1;
                    let gy = (dj.abs() - 1).max(0) as f32 * self.grid.cell;
                    let h = (gx * gx + gy * gy) * inv_dh2;
                    if h > 1.0 {
                        continue;
                    }
                    let b = self.cells[self.grid.index(i + di, j + dj)];
                    for s in a.first..a.first + a.len {
                        let sa = self.segments[s as usize];
                        for t in b.first..b.first + b.len {
                            let sb = self.segments[t as usize];
                            let v =
                                (sa.z_min - sb.z_max).max(sb.z_min - sa.z_max).max(0.0) * inv_dv;
                            if h + v * v <= 1.0 {
                                self.union(s, t);
                            }
                        }
                    }
                }
            }
        }

        // Dense component numbers in segment order (cell order, then height).
        self.component.clear();
        self.component.resize(n, u32::MAX);
        let mut components = 0u32;
        for s in 0..n as u32 {
            let root = self.find(s);
            if self.component[root as usize] == u32::MAX {
                self.component[root as usize] = components;
                components += 1;
            }
            self.component[s as usize] = self.component[root as usize];
        }
        for l in labels.iter_mut() {
            if *l != u32::MAX {
                *l = self.component[*l as usize];
            }
        }
        components as usize
    }

    /// The component of the last [`cluster`](Self::cluster) call that a point at (x, y, z)
    /// touches (by the same distance rule), nearest in height first; `None` if none.
    pub fn touching(&self, p: [f32; 3], cfg: &DetectorConfig) -> Option<u32> {
        let (i, j) = self.grid.cell_of(p[0], p[1])?;
        let r = self.grid.range(i, j);
        let (dh, dv) = (cfg.distance_at(r), cfg.vertical_distance_at(r));
        let reach = (dh / self.grid.cell).floor() as i32 + 1;
        let mut best: Option<(f32, u32)> = None;
        for di in -reach..=reach {
            for dj in -reach..=reach {
                let Some(b) = self.occupied_cell(i + di, j + dj) else {
                    continue;
                };
                let gx = (di.abs() - 1).max(0) as f32 * self.grid.cell;
                let gy = (dj.abs() - 1).max(0) as f32 * self.grid.cell;
                for t in b.first..b.first + b.len {
                    let b = self.segments[t as usize];
                    let v = (b.z_min - p[2]).max(p[2] - b.z_max).max(0.0) / dv;
                    let g = (gx * gx + gy * gy) / (dh * dh) + v * v;
                    if g <= 1.0 && best.is_none_or(|(bg, _)| g < bg) {
                        best = Some((g, self.component[t as usize]));
                    }
                }
            }
        }
        best.map(|(_, c)| c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blob(c: [f32; 3], n: usize, spread: f32) -> Vec<[f32; 3]> {
        (0..n)
            .map(|k| {
                let t = k as f32 / n as f32;
                [
                    c[0] + spread * (t * 37.0).sin(),
                    c[1] + spread * (t * 53.0).cos(),
                    c[2] + spread * (t * 11.0).sin(),
                ]
            })
            .collect()
    }

    fn same(labels: &[u32], a: std::ops::Range<usize>, b: std::ops::Range<usize>) -> bool {
        labels[a.start] == labels[b.start]
    }

    #[test]
    fn groups_farther_apart_than_the_distance_stay_apart_and_nearer_ones_join() {
        let cfg = DetectorConfig::default(); // d = 0.5 near the sensor
        let mut pts = blob([10.0, 0.0, 0.8], 50, 0.3);
        pts.extend(blob([10.0, 2.0, 0.8], 50, 0.3)); // gap ≈ 1.4 m
        pts.extend(blob([10.0, 0.0, 2.6], 50, 0.2)); // above the first, gap ≈ 1.3 m
        let mut labels = Vec::new();
        let mut grid = ClusterGrid::new(cfg.cell_size, cfg.max_range);
        assert_eq!(grid.cluster(&pts, &cfg, &mut labels), 3);
        assert!(!same(&labels, 0..50, 50..100));
        assert!(!same(&labels, 0..50, 100..150));
        assert!(labels[..50].iter().all(|&l| l == labels[0]));
        // A bridge of points 0.3 m apart joins the first two.
        let bridge: Vec<[f32; 3]> = (0..8).map(|k| [10.0, 0.3 + 0.2 * k as f32, 0.8]).collect();
        pts.extend(bridge);
        assert_eq!(grid.cluster(&pts, &cfg, &mut labels), 2);
        assert!(same(&labels, 0..50, 50..100));
    }

    #[test]
    fn far_points_join_over_larger_gaps() {
        let cfg = DetectorConfig::default();
        let mut grid = ClusterGrid::new(cfg.cell_size, cfg.max_range);
        let mut labels = Vec::new();
        // Two rings of a far car, 0.9 m apart in height: one object at 60 m (d_v = 1.2),
        // two at 10 m (d_v = 0.5).
        for x in [60.0f32, 10.0] {
            let pts: Vec<[f32; 3]> = (0..40)
                .map(|k| [x, 0.05 * k as f32, if k % 2 == 0 { 0.3 } else { 1.2 }])
                .collect();
            let n = grid.cluster(&pts, &cfg, &mut labels);
            assert_eq!(n, if x > 30.0 { 1 } else { 2 }, "at {x} m");
        }
    }

    #[test]
    fn the_result_does_not_depend_on_point_order() {
        let cfg = DetectorConfig::default();
        let mut pts = blob([5.0, 5.0, 0.5], 80, 1.5);
        pts.extend(blob([-8.0, 3.0, 1.0], 80, 0.7));
        let mut grid = ClusterGrid::new(cfg.cell_size, cfg.max_range);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        let na = grid.cluster(&pts, &cfg, &mut a);
        let rev: Vec<[f32; 3]> = pts.iter().rev().copied().collect();
        let nb = grid.cluster(&rev, &cfg, &mut b);
        assert_eq!(na, nb);
        b.reverse();
        assert_eq!(a, b);
    }

    #[test]
    fn a_point_touching_a_cluster_finds_it() {
        let cfg = DetectorConfig::default();
        let pts = blob([10.0, 0.0, 0.8], 50, 0.3);
        let mut grid = ClusterGrid::new(cfg.cell_size, cfg.max_range);
        let mut labels = Vec::new();
        grid.cluster(&pts, &cfg, &mut labels);
        assert_eq!(grid.touching([10.0, 0.2, 0.3], &cfg), Some(labels[0]));
        assert_eq!(grid.touching([10.0, 3.0, 0.3], &cfg), None);
    }
}
