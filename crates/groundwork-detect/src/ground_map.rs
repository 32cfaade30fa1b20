//! The local ground height: a bird's-eye grid of the mean height of the ground points in
//! each cell; a cell without ground (under a car, behind a wall) takes the mean of the
//! nearest ring of cells that has some; with none near, the ground there is unknown (a car
//! in a dip far away, all its ground hidden: guessing a height would drop the car).

use std::sync::atomic::{AtomicU32, Ordering};

use crate::grid::SquareGrid;

/// A square grid centred on the sensor, reused from scan to scan.
#[derive(Debug, Default)]
pub(crate) struct GroundMap {
    grid: SquareGrid,
    search: i32,
    sum: Vec<f32>,
    count: Vec<u32>,
    /// Resolved height per cell (cells are resolved lazily, by whichever thread asks
    /// first: every thread computes the same value), as `f32` bits: NaN until asked,
    /// infinite where unknown.
    resolved: Vec<AtomicU32>,
    /// The cells with ground, per half of the map.
    touched: [Vec<u32>; 2],
}

const UNRESOLVED: u32 = 0x7fc0_0000; // f32::NAN's bits

impl GroundMap {
    pub(crate) fn new(cell: f32, max_range: f32, search: u32) -> Self {
        let grid = SquareGrid::new(cell, max_range);
        Self {
            grid,
            search: search as i32,
            sum: vec![0.0; grid.len()],
            count: vec![0; grid.len()],
            resolved: (0..grid.len())
                .map(|_| AtomicU32::new(UNRESOLVED))
                .collect(),
            touched: Default::default(),
        }
    }

    /// Forgets the previous scan (only the cells it touched).
    pub(crate) fn clear(&mut self) {
        for touched in &mut self.touched {
            for &c in touched.iter() {
                let c = c as usize;
                self.sum[c] = 0.0;
                self.count[c] = 0;
            }
            touched.clear();
        }
        for r in &mut self.resolved {
            *r.get_mut() = UNRESOLVED;
        }
    }

    /// The cell of a ground point at (x, y), if inside the map (for [`add`](Self::add)).
    #[inline]
    pub(crate) fn cell(&self, x: f32, y: f32) -> Option<u32> {
        let (i, j) = self.grid.cell_of(x, y)?;
        Some(self.grid.index(i, j) as u32)
    }

    /// The map of one scan's ground points, given as (cell from [`cell`](Self::cell),
    /// height) in lists taken in order. The sums are `f32`: each cell's points are added
    /// in that order whatever the threads do (each half of the map is one thread's), so
    /// the heights are the same from run to run.
    pub(crate) fn fill(&mut self, lists: &[&[(u32, f32)]]) {
        self.clear();
        let mid = self.sum.len() / 2;
        let (sum0, sum1) = self.sum.split_at_mut(mid);
        let (count0, count1) = self.count.split_at_mut(mid);
        let [touched0, touched1] = &mut self.touched;
        rayon::join(
            || add_half(lists, 0, sum0, count0, touched0),
            || add_half(lists, mid, sum1, count1, touched1),
        );
    }

    /// The ground height below (x, y), if there is ground near. Safe to ask from many
    /// threads at once.
    pub(crate) fn height(&self, x: f32, y: f32) -> Option<f32> {
        let (i, j) = self.grid.cell_of(x, y)?;
        let c = self.grid.index(i, j);
        let mut r = f32::from_bits(self.resolved[c].load(Ordering::Relaxed));
        if r.is_nan() {
            r = self.search_from(i, j).unwrap_or(f32::INFINITY);
            self.resolved[c].store(r.to_bits(), Ordering::Relaxed);
        }
        r.is_finite().then_some(r)
    }

    fn search_from(&self, i: i32, j: i32) -> Option<f32> {
        for ring in 0..=self.search {
            let (mut sum, mut count) = (0.0f64, 0u64);
            for di in -ring..=ring {
                // Only the ring itself (the cells inside it were seen before): whole rows
                // at its top and bottom, the two ends of the rows between, in row-major
                // order as ever (the sums are added in the same order).
                let step = if di.abs() == ring {
                    1
                } else {
                    2 * ring as usize // ring ≥ 1 here: at ring 0 the only row is its top
                };
                for dj in (-ring..=ring).step_by(step) {
                    let (a, b) = (i + di, j + dj);
                    if !self.grid.contains(a, b) {
                        continue;
                    }
                    let c = self.grid.index(a, b);
                    sum += f64::from(self.sum[c]);
                    count += u64::from(self.count[c]);
                }
            }
            if count > 0 {
                return Some((sum / count as f64) as f32);
            }
        }
        None
    }
}

/// Adds the points of `lists` that fall in the cells `first` .. `first + sum.len()`.
fn add_half(
    lists: &[&[(u32, f32)]],
    first: usize,
    sum: &mut [f32],
    count: &mut [u32],
    touched: &mut Vec<u32>,
) {
    for &(c, z) in lists.iter().flat_map(|l| l.iter()) {
        let Some(k) = (c as usize).checked_sub(first).filter(|&k| k < sum.len()) else {
            continue;
        };
        if count[k] == 0 {
            touched.push(c);
        }
        sum[k] += z;
        count[k] += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cell_without_ground_takes_the_nearest_ring() {
        let mut m = GroundMap::new(1.0, 20.0, 3);
        let points: Vec<(u32, f32)> = [[0.5, 0.5, 0.2], [0.6, 0.4, 0.4], [5.5, 0.5, 9.0]]
            .iter()
            .map(|&[x, y, z]| (m.cell(x, y).unwrap(), z))
            .collect();
        // Given in two lists: the same map as in one.
        m.fill(&[&points[..1], &points[1..]]);
        assert!((m.height(0.1, 0.9).unwrap() - 0.3).abs() < 1e-6);
        // Two cells away from the first cell, three from the far one.
        assert!((m.height(2.5, 0.5).unwrap() - 0.3).abs() < 1e-6);
        // Nothing within three rings: unknown.
        assert_eq!(m.height(-10.0, -10.0), None);
        // A cell in the other half of the map.
        let below = m.cell(-3.5, 0.5).unwrap();
        m.fill(&[&[(below, -1.0)]]);
        assert_eq!(m.height(-3.5, 1.5), Some(-1.0));
        assert_eq!(m.height(0.5, 0.5), None);
        m.clear();
        assert_eq!(m.height(0.5, 0.5), None);
    }
}
