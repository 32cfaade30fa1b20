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
//!
//! The grid is sparse: the points are radix-sorted by cell number (the cells in two halves,
//! split at their median, each gathered, sorted and cut on its own core), the occupied cells
//! form one sorted list (about 10 000 of the grid's million cells on a KITTI scan), and the
//! neighbours of each cell are looked up in a ring of the rows within reach, each loaded
//! once from that list as a bitmap as the cells are visited in order. Every pass is
//! sequential over a few hundred kilobytes; a dense cell array of the whole grid (13.7 MB)
//! cost a cache miss per neighbour look and was 2–3× slower.

use crate::config::DetectorConfig;
use crate::grid::SquareGrid;
use rayon::prelude::*;

/// Points of one cell within one height interval.
#[derive(Debug, Clone, Copy)]
struct Segment {
    z_min: f32,
    z_max: f32,
}

/// A point being bucketed: its cell, its height and its index.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Entry {
    cell: u32,
    z: f32,
    point: u32,
}

/// An occupied cell and its segments.
#[derive(Debug, Clone, Copy)]
struct Occupied {
    cell: u32,
    first: u32,
    len: u32,
}

/// The occupied cells of a scan in cell order, and where each grid row starts among them.
#[derive(Debug, Clone, Default)]
struct Occupancy {
    cells: Vec<Occupied>,
    /// Per grid row, its first cell in `cells` (and one past the last row).
    row_start: Vec<u32>,
}

impl Occupancy {
    /// Indexes the rows of `cells` (after they were filled) for a grid `side` cells wide.
    fn index_rows(&mut self, side: usize) {
        self.row_start.clear();
        self.row_start.resize(side + 1, 0);
        for c in &self.cells {
            self.row_start[c.cell as usize / side + 1] += 1;
        }
        for r in 1..=side {
            self.row_start[r] += self.row_start[r - 1];
        }
    }

    /// Indices into `cells` of grid row `row`'s cells.
    fn row(&self, row: usize) -> std::ops::Range<usize> {
        self.row_start[row] as usize..self.row_start[row + 1] as usize
    }
}

/// Bits per radix-sort pass: 2 048 counters stay in L1.
const DIGIT_BITS: u32 = 11;

/// Sorts `entries` by cell number (stable LSD radix sort; cell numbers below 2^`bits`).
fn sort_by_cell(entries: &mut Vec<Entry>, spare: &mut Vec<Entry>, bits: u32) {
    sort_by_cell_from(0, entries, spare, bits);
}

/// The entries of `runs` whose cell is in `cells`, each entry's point shifted by its run's
/// offset, into `entries` sorted by cell number as [`sort_by_cell`] sorts them: its first
/// pass scatters straight from the runs.
fn gather_by_cell(
    runs: &[(&[Entry], u32)],
    cells: std::ops::Range<u32>,
    entries: &mut Vec<Entry>,
    spare: &mut Vec<Entry>,
    bits: u32,
) {
    let runs = if cells.is_empty() { &[][..] } else { runs };
    let source = || {
        runs.iter().flat_map(|&(run, offset)| {
            run.iter()
                .filter(|e| cells.contains(&e.cell))
                .map(move |e| Entry {
                    point: e.point + offset,
                    ..*e
                })
        })
    };
    scatter_by_digit(source, 0, entries, false);
    sort_by_cell_from(DIGIT_BITS, entries, spare, bits);
}

/// [`sort_by_cell`]'s passes from the digit at bit `first` on (the lower digits sorted).
fn sort_by_cell_from(first: u32, entries: &mut Vec<Entry>, spare: &mut Vec<Entry>, bits: u32) {
    for shift in (first..bits).step_by(DIGIT_BITS as usize) {
        if scatter_by_digit(|| entries.iter().copied(), shift, spare, true) {
            std::mem::swap(entries, spare);
        }
    }
}

/// One stable counting pass: the entries `source` yields (it is read twice: counted, then
/// placed) into `out`, ordered by the digit of their cell at bit `shift`. With
/// `skip_one_bucket`, entries that all share that digit are not moved; returns whether
/// `out` was written.
#[inline(always)]
fn scatter_by_digit<I: Iterator<Item = Entry>>(
    source: impl Fn() -> I,
    shift: u32,
    out: &mut Vec<Entry>,
    skip_one_bucket: bool,
) -> bool {
    let mut counts = [0u32; 1 << DIGIT_BITS];
    let mask = (1u32 << DIGIT_BITS) - 1;
    let mut n = 0u32;
    for e in source() {
        counts[((e.cell >> shift) & mask) as usize] += 1;
        n += 1;
    }
    if skip_one_bucket && counts.contains(&n) {
        return false; // one bucket: nothing moves
    }
    let mut sum = 0;
    for c in counts.iter_mut() {
        (*c, sum) = (sum, sum + *c);
    }
    out.clear();
    out.resize(n as usize, Entry::default());
    for e in source() {
        let slot = &mut counts[((e.cell >> shift) & mask) as usize];
        out[*slot as usize] = e;
        *slot += 1;
    }
    true
}

/// Sorts one cell's entries by height, ties in input order (they arrive in input order: the
/// radix sort is stable). Most cells hold a handful of points: an insertion sort on an
/// integer key that orders like `f32::total_cmp`; a wall's crowded cells take the library
/// sort.
fn sort_by_height(run: &mut [Entry]) {
    if run.len() > 24 {
        run.sort_unstable_by(|a, b| a.z.total_cmp(&b.z).then(a.point.cmp(&b.point)));
        return;
    }
    let key = |e: &Entry| {
        let b = e.z.to_bits() as i32;
        b ^ (((b >> 31) as u32) >> 1) as i32
    };
    for k in 1..run.len() {
        let e = run[k];
        let ke = key(&e);
        let mut m = k;
        while m > 0 && key(&run[m - 1]) > ke {
            run[m] = run[m - 1];
            m -= 1;
        }
        run[m] = e;
    }
}

/// The grid rows around the current query row, dense: a ring of at least 2·`reach_max` + 1
/// rows (a power of two: a row's place is a mask, not a division), each an occupancy bitmap
/// and, per occupied column, its cell. Queries come
/// in ascending row order, so each row is loaded once; a look at a neighbour is a bit test
/// in a row that stays in cache (a dense grid of the whole scan, 13.7 MB, cost a cache
/// miss per look).
#[derive(Debug, Clone, Default)]
struct RowRing {
    reach_max: i32,
    side: usize,
    rows: usize,
    /// Bitmap words per row (one spare: a window may read one word past the row).
    words: usize,
    bits: Vec<u64>,
    /// Per occupied column, a copy of its cell (one load less per neighbour look).
    slot: Vec<Occupied>,
    /// The grid row each ring row holds.
    held: Vec<i32>,
}

impl RowRing {
    fn reset(&mut self, side: usize, reach_max: i32) {
        self.reach_max = reach_max;
        self.side = side;
        self.rows = (2 * reach_max as usize + 1).next_power_of_two();
        self.words = side.div_ceil(64) + 1;
        self.bits.clear();
        self.bits.resize(self.rows * self.words, 0);
        // Read only where a bit is set.
        self.slot.resize(
            self.rows * side,
            Occupied {
                cell: 0,
                first: 0,
                len: 0,
            },
        );
        self.held.clear();
        self.held.resize(self.rows, -1);
    }

    /// The occupied cells of row `row`, columns `c0` ..= `c1` (`c1` − `c0` < 64), as
    /// (column offset from `c0`, the cell), loading the row if it is new.
    #[inline]
    fn row(
        &mut self,
        occupied: &Occupancy,
        row: i32,
        (c0, c1): (i32, i32),
    ) -> impl Iterator<Item = (i32, Occupied)> + use<'_> {
        let mut bits = 0;
        let mut base = 0;
        if (0..self.side as i32).contains(&row) && c0 <= c1 {
            let k = row as usize & (self.rows - 1);
            if self.held[k] != row {
                self.load(occupied, k, row);
            }
            let words = &self.bits[k * self.words..(k + 1) * self.words];
            bits = if c0 >= 0 {
                // Two words as one: a double shift, no branch on the bit offset.
                let (w, b) = ((c0 / 64) as usize, (c0 % 64) as u32);
                let pair = (u128::from(words[w + 1]) << 64) | u128::from(words[w]);
                (pair >> b) as u64
            } else {
                words[0].checked_shl((-c0) as u32).unwrap_or(0) // columns below 0 are empty
            };
            bits &= u64::MAX >> (63 - (c1 - c0) as u32);
            base = k * self.side;
        }
        let slot = &self.slot;
        std::iter::from_fn(move || {
            if bits == 0 {
                return None;
            }
            let d = bits.trailing_zeros() as i32;
            bits &= bits - 1;
            Some((d, slot[base + (c0 + d) as usize]))
        })
    }

    #[cold]
    fn load(&mut self, occupied: &Occupancy, k: usize, row: i32) {
        let words = &mut self.bits[k * self.words..(k + 1) * self.words];
        words.fill(0);
        let first = row as usize * self.side;
        let range = occupied.row(row as usize);
        for c in &occupied.cells[range] {
            let col = c.cell as usize - first;
            words[col / 64] |= 1 << (col % 64);
            self.slot[k * self.side + col] = *c;
        }
        self.held[k] = row;
    }
}

/// The clustering grid and its scratch, reused from scan to scan.
#[derive(Debug, Clone, Default)]
pub struct ClusterGrid {
    grid: SquareGrid,
    /// Bits of the largest cell number.
    cell_bits: u32,
    entries: Vec<Entry>,
    spare: Vec<Entry>,
    /// Occupied cells of the last scan.
    occupied: Occupancy,
    segments: Vec<Segment>,
    /// The widest look-around of the last scan, in cells.
    reach_max: i32,
    ring: RowRing,
    /// One per thread of the join; the first one's union-find holds the merged result.
    bands: Vec<Band>,
    component: Vec<u32>,
    /// The points in two halves of the grid, each gathered, sorted and cut on its own core.
    halves: [Half; 2],
    /// Fewest entries worth cutting on two cores.
    split_min: usize,
    /// Every 64th entry's cell, to split the entries at their median cell.
    sample: Vec<u32>,
}

/// One half of the grid's cells (those below a split cell, or the others): its entries in
/// cell order, their column segments, and each entry's segment.
#[derive(Debug, Clone, Default)]
struct Half {
    entries: Vec<Entry>,
    spare: Vec<Entry>,
    columns: Columns,
    segment_of: Vec<u32>,
}

impl Half {
    /// Gathers the entries of `runs` (each entry's point shifted by its run's offset) whose
    /// cell is in `cells`, sorts them by cell and cuts their columns.
    fn gather_and_cut(
        &mut self,
        runs: &[(&[Entry], u32)],
        cells: std::ops::Range<u32>,
        bits: u32,
        grid: &SquareGrid,
        cfg: &DetectorConfig,
    ) {
        gather_by_cell(runs, cells, &mut self.entries, &mut self.spare, bits);
        self.segment_of.resize(self.entries.len(), 0);
        self.columns
            .cut(&mut self.entries, &mut self.segment_of, grid, cfg);
    }
}

/// The column segments of a run of entries (whole cells, in cell order), numbered from 0.
#[derive(Debug, Clone, Default)]
struct Columns {
    segments: Vec<Segment>,
    cells: Vec<Occupied>,
    /// Range of the farthest cell.
    r_max: f32,
}

impl Columns {
    /// Sorts each cell's entries by height and cuts them into segments wherever two
    /// neighbours in height are more than the vertical distance apart; writes each entry's
    /// segment into `segment_of`.
    fn cut(
        &mut self,
        entries: &mut [Entry],
        segment_of: &mut [u32],
        grid: &SquareGrid,
        cfg: &DetectorConfig,
    ) {
        self.segments.clear();
        self.cells.clear();
        self.r_max = 0.0;
        let (mut rest, mut rest_of) = (entries, segment_of);
        while let Some(first) = rest.first() {
            let cell = first.cell;
            let len = rest
                .iter()
                .position(|e| e.cell != cell)
                .unwrap_or(rest.len());
            let (run, tail) = rest.split_at_mut(len);
            let (run_of, tail_of) = rest_of.split_at_mut(len);
            (rest, rest_of) = (tail, tail_of);
            sort_by_height(run);
            let (i, j) = grid.ij(cell);
            let r = grid.range(i, j);
            let gap = cfg.vertical_distance_at(r);
            self.r_max = self.r_max.max(r);
            let first = self.segments.len() as u32;
            for (e, of) in run.iter().zip(run_of) {
                let in_cell = self.segments.len() as u32 > first;
                match self.segments.last_mut() {
                    Some(s) if in_cell && e.z - s.z_max <= gap => {
                        s.z_max = e.z;
                    }
                    _ => self.segments.push(Segment {
                        z_min: e.z,
                        z_max: e.z,
                    }),
                }
                *of = self.segments.len() as u32 - 1;
            }
            self.cells.push(Occupied {
                cell,
                first,
                len: self.segments.len() as u32 - first,
            });
        }
    }
}

/// Look-around in cells for a horizontal distance (at most 31 cells: the configuration
/// keeps distances under 30 cells).
fn reach(d: f32, cell: f32) -> i32 {
    ((d / cell).floor() as i32 + 1).min(31)
}

/// Column offsets of a look-around row: 0 ..= 31 (`reach` keeps distances under 31 cells).
const MAX_HALF: usize = 32;

/// The look-around of a cell for a horizontal distance d_h: per row offset 0, 1, …, the
/// columns on either side whose gap to the cell is within d_h, and the squared gap over
/// d_h² of each column offset (the same products the join would compute per neighbour, so
/// the window is exact: every neighbour it yields is within d_h). Recomputed only when d_h
/// changes (it is constant within `cluster_distance / distance_per_metre` of the sensor).
#[derive(Debug, Default)]
struct Window {
    dh: f32,
    /// Per row offset: the columns on either side, and per column offset 0 ..= that,
    /// (gap / d_h)².
    rows: Vec<(i32, [f32; MAX_HALF])>,
}

impl Window {
    fn update(&mut self, dh: f32, cell: f32) {
        if dh == self.dh {
            return;
        }
        self.dh = dh;
        self.rows.clear();
        let reach = reach(dh, cell);
        let inv_dh2 = 1.0 / (dh * dh);
        for di in 0..=reach {
            let gx = (di - 1).max(0) as f32 * cell;
            let room = dh * dh - gx * gx;
            if room < 0.0 {
                break;
            }
            // Never past the bound that rounding could blur (the test below decides).
            let bound = (2 + (room.sqrt() / cell) as i32).min(reach);
            let mut row = [f32::INFINITY; MAX_HALF];
            let mut half = -1;
            for (dj, h) in row.iter_mut().enumerate().take(bound as usize + 1) {
                let gy = (dj as i32 - 1).max(0) as f32 * cell;
                *h = (gx * gx + gy * gy) * inv_dh2;
                if *h > 1.0 {
                    break; // the gap only grows with the column offset
                }
                half = dj as i32;
            }
            if half < 0 {
                break; // and with the row offset
            }
            self.rows.push((half, row));
        }
    }
}

fn find(parent: &mut [u32], mut a: u32) -> u32 {
    while parent[a as usize] != a {
        let up = parent[parent[a as usize] as usize];
        parent[a as usize] = up;
        a = up;
    }
    a
}

/// One thread's share of the join: its union-find and its rows.
#[derive(Debug, Clone, Default)]
struct Band {
    parent: Vec<u32>,
    ring: RowRing,
}

/// Joins the segments of each of `own` (cells in ascending order) to those of its
/// neighbours among the occupied cells (the rows at and after its own, and the columns
/// after it in its own row), in `band`'s union-find.
fn join_cells(
    own: &[Occupied],
    occupied: &Occupancy,
    segments: &[Segment],
    grid: &SquareGrid,
    cfg: &DetectorConfig,
    band: &mut Band,
) {
    let mut window = Window::default();
    for a in own {
        let (i, j) = grid.ij(a.cell);
        // The distances of this cell's range serve its whole look-around (d changes by a
        // few millimetres across it).
        let r = grid.range(i, j);
        let (dh, dv) = (cfg.distance_at(r), cfg.vertical_distance_at(r));
        window.update(dh, grid.cell);
        let inv_dv = 1.0 / dv;
        // A cell of one segment (most cells) keeps its set's root from link to link.
        let mut single =
            (a.len == 1).then(|| (find(&mut band.parent, a.first), segments[a.first as usize]));
        for (di, &(half, ref hs)) in window.rows.iter().enumerate() {
            let c0 = if di == 0 { j + 1 } else { j - half };
            for (d, b) in band.ring.row(occupied, i + di as i32, (c0, j + half)) {
                let h = hs[(c0 + d - j).unsigned_abs() as usize];
                if let Some((root, sa)) = single.as_mut() {
                    *root = link_near(&mut band.parent, segments, *root, *sa, b, h, inv_dv);
                    continue;
                }
                for s in a.first..a.first + a.len {
                    let root = find(&mut band.parent, s);
                    let sa = segments[s as usize];
                    link_near(&mut band.parent, segments, root, sa, b, h, inv_dv);
                }
            }
        }
    }
}

/// Links to the set whose root is `root` (segment `sa`'s) every segment of cell `b` within
/// the distance, `h` being the cells' squared horizontal gap over d_h²; returns the joined
/// set's root.
#[inline]
fn link_near(
    parent: &mut [u32],
    segments: &[Segment],
    mut root: u32,
    sa: Segment,
    b: Occupied,
    h: f32,
    inv_dv: f32,
) -> u32 {
    for t in b.first..b.first + b.len {
        if parent[t as usize] == root {
            continue; // joined before (the common case among a crowd's cells)
        }
        let sb = segments[t as usize];
        let v = (sa.z_min - sb.z_max).max(sb.z_min - sa.z_max).max(0.0) * inv_dv;
        if h + v * v <= 1.0 {
            root = link(parent, root, t);
        }
    }
    root
}

/// Joins `b`'s set to the set whose root is `root`; returns the joined set's root.
fn link(parent: &mut [u32], root: u32, b: u32) -> u32 {
    let rb = find(parent, b);
    // The smaller root wins: the result does not depend on the order of unions.
    if root < rb {
        parent[rb as usize] = root;
        root
    } else {
        parent[root as usize] = rb;
        rb
    }
}

/// Point number `point` at `p` as an entry of `grid`, if inside it.
#[inline]
fn entry_in(grid: &SquareGrid, p: [f32; 3], point: u32) -> Option<Entry> {
    let (i, j) = grid.cell_of(p[0], p[1])?;
    Some(Entry {
        cell: grid.index(i, j) as u32,
        z: p[2],
        point,
    })
}

/// `points` inside `grid` as entries, in input order, into `entries`.
fn entries_of(grid: &SquareGrid, points: &[[f32; 3]], entries: &mut Vec<Entry>) {
    entries.clear();
    entries.extend(
        points
            .iter()
            .enumerate()
            .filter_map(|(k, &p)| entry_in(grid, p, k as u32)),
    );
}

impl ClusterGrid {
    /// A grid of `cell` metres covering ±`max_range`.
    pub fn new(cell: f32, max_range: f32) -> Self {
        let grid = SquareGrid::new(cell, max_range);
        Self {
            grid,
            cell_bits: usize::BITS - grid.len().leading_zeros(),
            split_min: 4096,
            ..Default::default()
        }
    }

    /// `points` inside the grid as entries in cell order (within a cell, input order).
    fn bucket(&mut self, points: &[[f32; 3]]) {
        entries_of(&self.grid, points, &mut self.entries);
        sort_by_cell(&mut self.entries, &mut self.spare, self.cell_bits);
    }

    /// Point number `point` at `p` as an entry, if inside the grid.
    #[inline]
    pub(crate) fn entry(&self, p: [f32; 3], point: u32) -> Option<Entry> {
        entry_in(&self.grid, p, point)
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
        let mut entries = std::mem::take(&mut self.entries);
        entries_of(&self.grid, points, &mut entries);
        let found = self.cluster_runs(&[(&entries, 0)], points.len(), cfg, labels);
        self.entries = entries;
        found
    }

    /// [`cluster`](Self::cluster) for points given as runs of entries (made by
    /// [`entry`](Self::entry), numbered within their run) and each run's first point
    /// number: `points` points in all, numbered in run order.
    pub(crate) fn cluster_runs(
        &mut self,
        runs: &[(&[Entry], u32)],
        points: usize,
        cfg: &DetectorConfig,
        labels: &mut Vec<u32>,
    ) -> usize {
        labels.clear();
        labels.resize(points, u32::MAX);

        // The entries in two halves of the grid split at their median cell, each gathered,
        // sorted by cell and cut into column segments on its own core (each half numbering
        // its own segments; the second half's are then shifted past the first's: the same
        // numbers as one half gives). Whole cells, so the halves' segments are those of
        // the whole.
        let n_entries: usize = runs.iter().map(|(r, _)| r.len()).sum();
        let split = if n_entries < self.split_min || rayon::current_num_threads() == 1 {
            u32::MAX
        } else {
            self.sample.clear();
            let mut skip = 0;
            for (run, _) in runs {
                self.sample
                    .extend(run.iter().skip(skip).step_by(64).map(|e| e.cell));
                skip = (skip + 64 - run.len() % 64) % 64;
            }
            let mid = self.sample.len() / 2;
            *self.sample.select_nth_unstable(mid).1
        };
        let [h0, h1] = &mut self.halves;
        let (grid, bits) = (&self.grid, self.cell_bits);
        rayon::join(
            || h0.gather_and_cut(runs, 0..split, bits, grid, cfg),
            || h1.gather_and_cut(runs, split..u32::MAX, bits, grid, cfg),
        );
        let offset = h0.columns.segments.len() as u32;
        for s in h1.segment_of.iter_mut() {
            *s += offset;
        }
        let (h0, h1) = (&h0.columns, &h1.columns);
        self.segments.clear();
        self.segments.extend_from_slice(&h0.segments);
        self.segments.extend_from_slice(&h1.segments);
        self.occupied.cells.clear();
        self.occupied.cells.extend_from_slice(&h0.cells);
        self.occupied
            .cells
            .extend(h1.cells.iter().map(|c| Occupied {
                first: c.first + offset,
                ..*c
            }));
        let r_max = h0.r_max.max(h1.r_max);
        // The distance grows with range: the farthest cell has the widest look-around.
        self.reach_max = reach(cfg.distance_at(r_max), self.grid.cell).max(1);
        self.occupied.index_rows(self.grid.side);

        // Join segments of neighbouring cells (each pair of cells looked at once: the rows
        // at and after a cell's, and in its own row the columns after it). The cells are
        // split into bands of rows, one per thread, each with its own union-find; the
        // bands' unions are then merged (the components do not depend on the order).
        let n = self.segments.len();
        let bands = if self.occupied.cells.len() < 4096 {
            1
        } else {
            rayon::current_num_threads().clamp(1, 8)
        };
        self.bands.resize_with(bands, Band::default);
        let (occupied, segments, grid) = (&self.occupied, &self.segments[..], &self.grid);
        let cells = &occupied.cells;
        let reach_max = self.reach_max;
        let per_band = cells.len().div_ceil(bands);
        self.bands.par_iter_mut().enumerate().for_each(|(k, band)| {
            band.parent.clear();
            band.parent.extend(0..n as u32);
            band.ring.reset(grid.side, reach_max);
            let own =
                &cells[(k * per_band).min(cells.len())..((k + 1) * per_band).min(cells.len())];
            join_cells(own, occupied, segments, grid, cfg, band);
        });
        let (first, rest) = self.bands.split_at_mut(1);
        let parent = &mut first[0].parent;
        for band in rest {
            for s in 0..n as u32 {
                let other = find(&mut band.parent, s);
                if other != s {
                    let root = find(parent, s);
                    link(parent, root, other);
                }
            }
        }

        // Dense component numbers in segment order (cell order, then height).
        self.component.clear();
        self.component.resize(n, u32::MAX);
        let mut components = 0u32;
        for s in 0..n as u32 {
            let root = find(parent, s);
            if self.component[root as usize] == u32::MAX {
                self.component[root as usize] = components;
                components += 1;
            }
            self.component[s as usize] = self.component[root as usize];
        }
        for half in &self.halves {
            for (e, &s) in half.entries.iter().zip(&half.segment_of) {
                labels[e.point as usize] = self.component[s as usize];
            }
        }
        components as usize
    }

    /// For each of `queries` (x, y, z), the component of the last
    /// [`cluster`](Self::cluster) call that it touches by the same distance rule, nearest
    /// first (in the stretched metric); `None` if none.
    pub fn touching(
        &mut self,
        queries: &[[f32; 3]],
        cfg: &DetectorConfig,
        out: &mut Vec<Option<u32>>,
    ) {
        out.clear();
        out.resize(queries.len(), None);
        // Queries in cell order, for the ring of rows.
        self.bucket(queries);
        let reach_max = self.entries.iter().fold(self.reach_max, |m, e| {
            let (i, j) = self.grid.ij(e.cell);
            m.max(reach(
                cfg.distance_at(self.grid.range(i, j)),
                self.grid.cell,
            ))
        });
        self.ring.reset(self.grid.side, reach_max);
        for e in &self.entries {
            let (i, j) = self.grid.ij(e.cell);
            let r = self.grid.range(i, j);
            let (dh, dv) = (cfg.distance_at(r), cfg.vertical_distance_at(r));
            let reach = reach(dh, self.grid.cell);
            let mut best: Option<(f32, u32)> = None;
            for di in -reach..=reach {
                let gx = (di.abs() - 1).max(0) as f32 * self.grid.cell;
                for (d, b) in self
                    .ring
                    .row(&self.occupied, i + di, (j - reach, j + reach))
                {
                    let gy = ((d - reach).abs() - 1).max(0) as f32 * self.grid.cell;
                    for t in b.first..b.first + b.len {
                        let s = self.segments[t as usize];
                        let v = (s.z_min - e.z).max(e.z - s.z_max).max(0.0) / dv;
                        let g = (gx * gx + gy * gy) / (dh * dh) + v * v;
                        if g <= 1.0 && best.is_none_or(|(bg, _)| g < bg) {
                            best = Some((g, self.component[t as usize]));
                        }
                    }
                }
            }
            out[e.point as usize] = best.map(|(_, c)| c);
        }
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
    fn cutting_the_columns_in_two_halves_changes_nothing() {
        let cfg = DetectorConfig::default();
        // Many cells, crowded ones among them (a wall), and objects on both sides of the
        // sensor, so that the halves' boundary falls among occupied rows.
        let mut pts = Vec::new();
        for k in 0..40 {
            let a = k as f32 * 0.157;
            pts.extend(blob([12.0 * a.cos(), 12.0 * a.sin(), 0.8], 120, 0.6));
        }
        pts.extend((0..3000).map(|k| [-6.0, -8.0 + 0.005 * k as f32, 0.2 + (k % 17) as f32 * 0.1]));
        let mut split = ClusterGrid::new(cfg.cell_size, cfg.max_range);
        let mut whole = ClusterGrid {
            split_min: usize::MAX,
            ..split.clone()
        };
        let (mut a, mut b) = (Vec::new(), Vec::new());
        // Split only where there is a second thread: give it one.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let n = pool.install(|| split.cluster(&pts, &cfg, &mut a));
        assert!(n > 1 && pts.len() >= split.split_min);
        let halves = split.halves.each_ref().map(|h| h.entries.len());
        assert!(halves.iter().all(|&h| h > pts.len() / 4), "{halves:?}");
        assert_eq!(whole.cluster(&pts, &cfg, &mut b), n);
        assert_eq!(a, b);
        assert_eq!(split.segments.len(), whole.segments.len());
    }

    #[test]
    fn a_point_touching_a_cluster_finds_it() {
        let cfg = DetectorConfig::default();
        let pts = blob([10.0, 0.0, 0.8], 50, 0.3);
        let mut grid = ClusterGrid::new(cfg.cell_size, cfg.max_range);
        let mut labels = Vec::new();
        grid.cluster(&pts, &cfg, &mut labels);
        let mut found = Vec::new();
        grid.touching(&[[10.0, 3.0, 0.3], [10.0, 0.2, 0.3]], &cfg, &mut found);
        assert_eq!(found, [None, Some(labels[0])]);
    }
}
