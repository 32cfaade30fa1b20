//! A square bird's-eye grid centred on the sensor: the geometry the clustering grid and the
//! ground height map share.

/// Cells of `cell` metres covering ±`max_range` (plus one cell), row-major by x then y.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct SquareGrid {
    /// Side of a cell, metres.
    pub(crate) cell: f32,
    /// 1 / cell: a multiplication per coordinate instead of a division.
    inv_cell: f32,
    half: i32,
    /// Cells per side.
    pub(crate) side: usize,
}

impl SquareGrid {
    pub(crate) fn new(cell: f32, max_range: f32) -> Self {
        let half = (max_range / cell).ceil() as i32 + 1;
        Self {
            cell,
            inv_cell: 1.0 / cell,
            half,
            side: (2 * half) as usize,
        }
    }

    /// Cells in the grid.
    pub(crate) fn len(&self) -> usize {
        self.side * self.side
    }

    /// The cell (row, column) holding (x, y), if inside.
    #[inline]
    pub(crate) fn cell_of(&self, x: f32, y: f32) -> Option<(i32, i32)> {
        let i = (x * self.inv_cell).floor() as i32 + self.half;
        let j = (y * self.inv_cell).floor() as i32 + self.half;
        self.contains(i, j).then_some((i, j))
    }

    #[inline]
    pub(crate) fn contains(&self, i: i32, j: i32) -> bool {
        let n = self.side as i32;
        i >= 0 && j >= 0 && i < n && j < n
    }

    /// Linear index of a cell inside the grid.
    #[inline]
    pub(crate) fn index(&self, i: i32, j: i32) -> usize {
        i as usize * self.side + j as usize
    }

    /// Row and column of a linear index.
    #[inline]
    pub(crate) fn ij(&self, index: u32) -> (i32, i32) {
        // Cell numbers fit in u32 (the clustering grid stores them so): a 32-bit division
        // is half the latency of a 64-bit one, once per occupied cell.
        let side = self.side as u32;
        ((index / side) as i32, (index % side) as i32)
    }

    /// Horizontal range of a cell's centre.
    #[inline]
    pub(crate) fn range(&self, i: i32, j: i32) -> f32 {
        let x = (i - self.half) as f32 * self.cell + 0.5 * self.cell;
        let y = (j - self.half) as f32 * self.cell + 0.5 * self.cell;
        (x * x + y * y).sqrt()
    }
}
