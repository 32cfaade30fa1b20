//! The local ground height: a bird's-eye grid of the mean height of the ground points in
//! each cell; a cell without ground (under a car, behind a wall) takes the mean of the
//! nearest ring of cells that has some; with none near, the ground there is unknown (a car
//! in a dip far away, all its ground hidden: guessing a height would drop the car).

use crate::grid::SquareGrid;

/// A square grid centred on the sensor, reused from scan to scan.
#[derive(Debug, Clone, Default)]
pub(crate) struct GroundMap {
    grid: SquareGrid,
    search: i32,
    sum: Vec<f32>,
    count: Vec<u32>,
    /// Resolved height per cell (cells are resolved lazily): NaN until asked, infinite
    /// where unknown.
    resolved: Vec<f32>,
    touched: Vec<u32>,
}

impl GroundMap {
    pub(crate) fn new(cell: f32, max_range: f32, search: u32) -> Self {
        let grid = SquareGrid::new(cell, max_range);
        Self {
            grid,
            search: search as i32,
            sum: vec![0.0; grid.len()],
            count: vec![0; grid.len()],
            resolved: vec![f32::NAN; grid.len()],
            touched: Vec::new(),
        }
    }

    /// Forgets the previous scan (only the cells it touched).
    pub(crate) fn clear(&mut self) {
        for &c in &self.touched {
            let c = c as usize;
            self.sum[c] = 0.0;
            self.count[c] = 0;
        }
        self.touched.clear();
        self.resolved.fill(f32::NAN);
    }

    /// Adds a ground point.
    #[inline]
    pub(crate) fn add(&mut self, x: f32, y: f32, z: f32) {
        if let Some((i, j)) = self.grid.cell_of(x, y) {
            let c = self.grid.index(i, j);
            if self.count[c] == 0 {
                self.touched.push(c as u32);
            }
            self.sum[c] += z;
            self.count[c] += 1;
        }
    }

    /// The ground height below (x, y), if there is ground near.
    pub(crate) fn height(&mut self, x: f32, y: f32) -> Option<f32> {
        let (i, j) = self.grid.cell_of(x, y)?;
        let c = self.grid.index(i, j);
        let mut r = self.resolved[c];
        if r.is_nan() {
            r = self.search_from(i, j).unwrap_or(f32::INFINITY);
            self.resolved[c] = r;
        }
        r.is_finite().then_some(r)
    }

    fn search_from(&self, i: i32, j: i32) -> Option<f32> {
        for ring in 0..=self.search {
            let (mut sum, mut count) = (0.0f64, 0u64);
            for di in -ring..=ring {
                for dj in -ring..=ring {
                    if di.abs() != ring && dj.abs() != ring {
                        continue; // inside the ring: seen before
                    }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cell_without_ground_takes_the_nearest_ring() {
        let mut m = GroundMap::new(1.0, 20.0, 3);
        m.add(0.5, 0.5, 0.2);
        m.add(0.6, 0.4, 0.4);
        m.add(5.5, 0.5, 9.0);
        assert!((m.height(0.1, 0.9).unwrap() - 0.3).abs() < 1e-6);
        // Two cells away from the first cell, three from the far one.
        assert!((m.height(2.5, 0.5).unwrap() - 0.3).abs() < 1e-6);
        // Nothing within three rings: unknown.
        assert_eq!(m.height(-10.0, -10.0), None);
        m.clear();
        assert_eq!(m.height(0.5, 0.5), None);
    }
}
