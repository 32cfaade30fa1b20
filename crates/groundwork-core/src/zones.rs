//! The concentric zone model: zones of rings of sectors in the horizontal plane of the
//! ground-aligned frame (Patchwork++'s CZM).

use std::f64::consts::TAU;

use crate::simd::{LANES, Vf, Vi};
use wide::bytemuck::cast;

use crate::config::ZoneConfig;
use crate::error::ConfigError;
use crate::fastmath::atan2_v;

const TAU_F32: f32 = std::f32::consts::TAU;

/// Where a point falls in the zone model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bin {
    /// Inside `min_range` (or the ego radius): never ground.
    Near,
    /// In segment `n` (index into the flat segment list).
    Segment(u32),
    /// Beyond `max_range`; carries the outermost-ring segment of the point's sector.
    Beyond(u32),
}

/// Flat-indexed zone model. Segment indices run zone by zone, ring by ring, sector by
/// sector: `zone_offset[z] + ring * sectors[z] + sector`.
#[derive(Debug, Clone)]
pub struct ZoneModel {
    boundaries: Vec<f64>,
    rings: Vec<u32>,
    sectors: Vec<u32>,
    ring_width: Vec<f64>,
    zone_offset: Vec<u32>,
    near_radius: f64,
    segments: u32,
}

/// Identity of a segment, for reports and the height filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SegmentId {
    /// Zone, 0-based.
    pub zone: u32,
    /// Ring within the zone, 0-based from the inside.
    pub ring: u32,
    /// Sector, 0-based counter-clockwise from +x.
    pub sector: u32,
}

impl ZoneModel {
    /// Builds the model; `ego_radius` widens the "near" disc beyond `min_range` if larger.
    pub fn new(cfg: &ZoneConfig, ego_radius: f64) -> Result<Self, ConfigError> {
        let boundaries = cfg.resolved_boundaries()?;
        let mut zone_offset = Vec::with_capacity(cfg.rings.len());
        let mut total = 0u32;
        let mut ring_width = Vec::new();
        for (z, (&r, &s)) in cfg.rings.iter().zip(&cfg.sectors).enumerate() {
            zone_offset.push(total);
            total += r * s;
            ring_width.push((boundaries[z + 1] - boundaries[z]) / f64::from(r));
        }
        Ok(Self {
            near_radius: boundaries[0].max(ego_radius),
            boundaries,
            rings: cfg.rings.clone(),
            sectors: cfg.sectors.clone(),
            ring_width,
            zone_offset,
            segments: total,
        })
    }

    /// Number of segments (504 for the default model).
    pub fn segment_count(&self) -> usize {
        self.segments as usize
    }

    /// Number of segments in zone 1 (the innermost zone).
    pub fn first_zone_segments(&self) -> usize {
        (self.rings[0] * self.sectors[0]) as usize
    }

    /// The bin of a point at (x, y) in the ground-aligned frame.
    #[inline]
    pub fn bin(&self, x: f64, y: f64) -> Bin {
        let r = (x * x + y * y).sqrt();
        if r < self.near_radius {
            return Bin::Near;
        }
        let last = self.rings.len() - 1;
        let (zone, beyond) = if r >= self.boundaries[last + 1] {
            (last, true)
        } else {
            // At most a handful of zones: a linear scan beats a binary search.
            let mut z = 0;
            while r >= self.boundaries[z + 1] {
                z += 1;
            }
            (z, false)
        };
        let rings = self.rings[zone];
        let ring = if beyond {
            rings - 1
        } else {
            (((r - self.boundaries[zone]) / self.ring_width[zone]) as u32).min(rings - 1)
        };
        let sectors = self.sectors[zone];
        let mut theta = crate::fastmath::atan2(y, x);
        if theta < 0.0 {
            theta += TAU;
        }
        let sector = ((theta * f64::from(sectors) / TAU) as u32).min(sectors - 1);
        let idx = self.zone_offset[zone] + ring * sectors + sector;
        if beyond {
            Bin::Beyond(idx)
        } else {
            Bin::Segment(idx)
        }
    }

    /// Zone, ring and sector of a flat segment index.
    pub fn segment_id(&self, idx: u32) -> Option<SegmentId> {
        if idx >= self.segments {
            return None;
        }
        let zone = self.zone_offset.iter().rposition(|&o| o <= idx)?;
        let local = idx - self.zone_offset[zone];
        let s = self.sectors[zone];
        Some(SegmentId {
            zone: zone as u32,
            ring: local / s,
            sector: local % s,
        })
    }
}

/// Packed bin of a point (as [`LaneBinner::bin_block`] gives it): its segment index, with
/// `BEYOND` set for a point past the outer edge (queried against the outermost ring), or
/// `NEAR` for one inside the inner edge or the ego radius (probability 0).
pub(crate) const NEAR: u32 = u32::MAX;
/// See [`NEAR`].
pub(crate) const BEYOND: u32 = 1 << 31;

/// The zone model as SIMD constants: bins a vector of points at a time.
#[derive(Debug, Clone)]
pub(crate) struct LaneBinner {
    /// Per zone: lower edge, 1 / ring width, rings, sectors, first segment.
    zones: Vec<[Vf; 5]>,
    near: Vf,
    max_range: Vf,
    /// Per segment, its cell shrunk by [`CELL_MARGIN`]: r² bounds and the unit directions
    /// of its two sector edges, for [`LaneBinner::inside`].
    cells: Vec<[f32; 6]>,
}

/// Points closer than this (metres) to a cell's edge are left to the full binning, whose
/// f32 rounding (below 1e-4 m) could put them on either side.
const CELL_MARGIN: f64 = 2e-3;

impl LaneBinner {
    pub(crate) fn new(m: &ZoneModel) -> Self {
        let c = |v: f64| Vf::splat(v as f32);
        let zones = (0..m.rings.len())
            .map(|k| {
                [
                    c(m.boundaries[k]),
                    c(1.0 / m.ring_width[k]),
                    c(f64::from(m.rings[k])),
                    c(f64::from(m.sectors[k])),
                    c(f64::from(m.zone_offset[k])),
                ]
            })
            .collect();
        let mut cells = vec![[0.0; 6]; m.segments as usize];
        for k in 0..m.rings.len() {
            let step = TAU / f64::from(m.sectors[k]);
            for ring in 0..m.rings[k] {
                let lo = m.boundaries[k] + f64::from(ring) * m.ring_width[k];
                let lo = lo.max(m.near_radius) + CELL_MARGIN;
                let hi = m.boundaries[k] + f64::from(ring + 1) * m.ring_width[k] - CELL_MARGIN;
                for sector in 0..m.sectors[k] {
                    let (a0, a1) = (f64::from(sector) * step, f64::from(sector + 1) * step);
                    let idx = m.zone_offset[k] + ring * m.sectors[k] + sector;
                    cells[idx as usize] =
                        [lo * lo, hi * hi, a0.cos(), a0.sin(), a1.cos(), a1.sin()]
                            .map(|v| v as f32);
                }
            }
        }
        Self {
            zones,
            near: c(m.near_radius),
            max_range: c(m.boundaries[m.rings.len()]),
            cells,
        }
    }

    /// Lanes that lie inside segment `seg`'s cell by more than [`CELL_MARGIN`]: for them
    /// [`LaneBinner::bin`] would give `seg` (in range, not near), so the full binning can be
    /// skipped (no lane for an unknown segment). Sectors span less than π, so a cell is the
    /// ring between two radii intersected with two half-planes through the origin.
    #[inline(always)]
    pub(crate) fn inside(&self, seg: u32, x: Vf, y: Vf) -> Vf {
        let Some(&[lo2, hi2, c0, s0, c1, s1]) = self.cells.get(seg as usize) else {
            return Vf::ZERO;
        };
        let s = Vf::splat;
        let r2 = x.mul_add(x, y * y);
        let m = s(CELL_MARGIN as f32);
        // Signed distances from the edges: ahead of the first, behind the second.
        let after_first = s(c0).mul_sub(y, s(s0) * x);
        let before_second = s(s1).mul_sub(x, s(c1) * y);
        r2.simd_ge(s(lo2)) & r2.simd_lt(s(hi2)) & after_first.simd_ge(m) & before_second.simd_ge(m)
    }

    /// Segments of the zone model.
    pub(crate) fn segment_count(&self) -> usize {
        self.cells.len()
    }

    /// Packed bins of a block of ground-aligned points (x and y rounded to f32): `u32::MAX`
    /// for near points, the segment index otherwise, with bit 31 set beyond max range.
    /// Agrees with [`ZoneModel::bin`] except for points within f32 rounding of a boundary.
    #[inline(always)]
    pub(crate) fn bin_block(&self, x: [f32; LANES], y: [f32; LANES]) -> [u32; LANES] {
        cast(self.bin(Vf::new(x), Vf::new(y)))
    }

    /// Packed bins (as [`LaneBinner::bin_block`]) of a vector of points, as i32 lanes: −1 near,
    /// bit 31 set beyond max range. Zone parameters are picked with selects, atan2 is a
    /// select-based polynomial: no branches, no gathers.
    #[inline(always)]
    pub(crate) fn bin(&self, x: Vf, y: Vf) -> Vi {
        let c = Vf::splat;
        let r = x.mul_add(x, y * y).sqrt();
        let [mut lo, mut inv_width, mut nr, mut ns, mut off] = self.zones[0];
        for &[zlo, zinv, znr, zns, zoff] in &self.zones[1..] {
            let hit = r.simd_ge(zlo);
            lo = hit.select(zlo, lo);
            inv_width = hit.select(zinv, inv_width);
            nr = hit.select(znr, nr);
            ns = hit.select(zns, ns);
            off = hit.select(zoff, off);
        }
        let beyond = r.simd_ge(self.max_range);
        // `max`, not `fast_max`: a NaN lane (a non-finite point, rejected later) must clamp
        // to 0 on every CPU. x86's maxps happens to return the second operand for NaN, NEON's
        // fmax returns NaN, whose bits then index far outside the segments.
        let ring = ((r - lo) * inv_width)
            .floor()
            .max(c(0.0))
            .fast_min(nr - c(1.0));
        let ring = beyond.select(nr - c(1.0), ring);
        let theta = atan2_v(y, x);
        let theta = theta.simd_lt(c(0.0)).select(theta + c(TAU_F32), theta);
        let sector = (theta * ns * c(1.0 / TAU_F32))
            .floor()
            .max(c(0.0))
            .fast_min(ns - c(1.0));
        // The index (< 2^23) lands in the low mantissa bits of idx + 2^23.
        let idx: Vi = cast(off + ring * ns + sector + c(8_388_608.0));
        let idx = idx & Vi::splat(0x007f_ffff);
        let beyond: Vi = cast(beyond);
        let idx = idx | (beyond & Vi::splat(i32::MIN));
        let near: Vi = cast(r.simd_lt(self.near));
        idx | near
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> ZoneModel {
        ZoneModel::new(&ZoneConfig::default(), 0.0).unwrap()
    }

    /// Distance of (x, y) to the nearest ring edge (m) and sector edge (rad).
    fn edge_distance(m: &ZoneModel, x: f64, y: f64) -> (f64, f64) {
        let r = x.hypot(y);
        let mut dr = f64::INFINITY;
        let mut da = f64::INFINITY;
        let theta = y.atan2(x).rem_euclid(TAU);
        for z in 0..m.rings.len() {
            for k in 0..=m.rings[z] {
                let edge = m.boundaries[z] + f64::from(k) * m.ring_width[z];
                dr = dr.min((r - edge).abs());
            }
            let step = TAU / f64::from(m.sectors[z]);
            let off = theta.rem_euclid(step);
            da = da.min(off.min(step - off));
        }
        (dr, da)
    }

    #[test]
    fn the_cell_test_implies_the_full_binning_result() {
        let m = model();
        let binner = LaneBinner::new(&m);
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let (mut confirmed, mut lanes) = (0, 0);
        for _ in 0..20_000 {
            // 16 neighbours, like consecutive points of a scan, anywhere within 85 m; the
            // guesses are the cells of the first and the last of them, as in the query.
            let (cx, cy) = (next() * 170.0 - 85.0, next() * 170.0 - 85.0);
            let spread = 0.05 + next() * 1.5;
            let x = Vf::new(std::array::from_fn(|_| cx + (next() - 0.5) * spread));
            let y = Vf::new(std::array::from_fn(|_| cy + (next() - 0.5) * spread));
            let packed = binner.bin(x, y).to_array();
            for guess in [packed[0], packed[LANES - 1]] {
                if guess < 0 {
                    continue; // near or beyond: never a guess
                }
                lanes += LANES;
                let inside = binner.inside(guess as u32, x, y).to_bitmask();
                for (k, &p) in packed.iter().enumerate() {
                    if inside >> k & 1 == 1 {
                        confirmed += 1;
                        assert_eq!(p, guess, "lane {k} of {packed:?}");
                    }
                }
            }
        }
        // The test must confirm most lanes, or it saves nothing.
        assert!(
            confirmed * 4 > lanes * 3,
            "{confirmed} of {lanes} lanes confirmed"
        );
        // A point on a sector edge, or on a ring edge, is never confirmed; its neighbours are.
        let on_sector_edge = Vf::new(std::array::from_fn(|i| if i == 3 { 0.0 } else { 5.0 }));
        let y = Vf::new(std::array::from_fn(|i| if i == 3 { 5.0 } else { 0.5 }));
        let seg = binner.bin(Vf::splat(5.0), Vf::splat(0.5)).to_array()[0] as u32;
        assert_eq!(
            binner.inside(seg, on_sector_edge, y).to_bitmask(),
            0xffff & !(1 << 3)
        );
        let edge = (m.boundaries[1] + m.ring_width[1]) as f32;
        let x = Vf::new(std::array::from_fn(
            |i| if i == 5 { edge } else { edge - 0.5 },
        ));
        let seg = binner
            .bin(Vf::splat(edge - 0.5), Vf::splat(0.01))
            .to_array()[0] as u32;
        assert_eq!(
            binner.inside(seg, x, Vf::splat(0.01)).to_bitmask(),
            0xffff & !(1 << 5)
        );
        // An unknown segment holds no lane.
        assert_eq!(binner.inside(u32::MAX, x, Vf::splat(0.01)).to_bitmask(), 0);
    }

    #[test]
    fn vectorised_binning_agrees_with_scalar_binning() {
        let m = model();
        // Deterministic pseudo-random points over ±100 m (beyond max range included), and
        // the tail lengths 1..7 of the vector loop.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((state >> 40) as f64 / (1u64 << 24) as f64) * 200.0 - 100.0
        };
        let binner = LaneBinner::new(&m);
        for n in [100_003usize, 1, 7, 9] {
            let (xs, ys): (Vec<f32>, Vec<f32>) =
                (0..n).map(|_| (next() as f32, next() as f32)).unzip();
            let mut out = vec![0; n];
            for ((x, y), out) in xs
                .chunks(LANES)
                .zip(ys.chunks(LANES))
                .zip(out.chunks_mut(LANES))
            {
                let lanes = |v: &[f32]| std::array::from_fn(|i| v.get(i).copied().unwrap_or(0.0));
                out.copy_from_slice(&binner.bin_block(lanes(x), lanes(y))[..out.len()]);
            }
            let mut mismatches = 0;
            for ((&x, &y), &got) in xs.iter().zip(&ys).zip(&out) {
                let want = match m.bin(f64::from(x), f64::from(y)) {
                    Bin::Near => u32::MAX,
                    Bin::Segment(s) => s,
                    Bin::Beyond(s) => s | (1 << 31),
                };
                if got != want {
                    let (dr, da) = edge_distance(&m, f64::from(x), f64::from(y));
                    assert!(
                        dr < 1e-4 || da < 1e-5,
                        "({x}, {y}): {got:#x} vs {want:#x}, {dr} m / {da} rad from an edge"
                    );
                    mismatches += 1;
                }
            }
            assert!(mismatches * 10_000 <= n, "{mismatches} of {n} differ");
        }
    }

    #[test]
    fn default_model_has_504_segments() {
        let m = model();
        assert_eq!(m.segment_count(), 16 * 2 + 32 * 4 + 54 * 4 + 32 * 4);
        assert_eq!(m.segment_count(), 504);
        assert_eq!(m.first_zone_segments(), 32);
    }

    #[test]
    fn known_points_fall_into_known_segments() {
        let m = model();
        // Zone 1 spans 2.7 .. 12.3375 m in 2 rings of 4.81875 m; 16 sectors of 22.5°.
        assert_eq!(m.bin(3.0, 0.1), Bin::Segment(0));
        // Second ring, sector 4 (90°..112.5°): just left of the y axis.
        assert_eq!(m.bin(-0.5, 8.0), Bin::Segment(16 + 4));
        // Negative angles wrap: 350° is the last sector.
        let a = 350f64.to_radians();
        assert_eq!(m.bin(5.0 * a.cos(), 5.0 * a.sin()), Bin::Segment(15));
        // Zone 2 (12.3375 .. 21.975, 4 rings, 32 sectors): r = 13, angle 0 → first segment.
        assert_eq!(m.bin(13.0, 0.0), Bin::Segment(32));
        // Zone 4 (41.35 .. 80, ring width 9.6625): r = 79.9 → last ring.
        let id = match m.bin(0.0, -79.9) {
            Bin::Segment(i) => m.segment_id(i).unwrap(),
            other => panic!("{other:?}"),
        };
        assert_eq!((id.zone, id.ring, id.sector), (3, 3, 24));
    }

    #[test]
    fn out_of_range_points_are_near_or_beyond() {
        let m = model();
        assert_eq!(m.bin(0.0, 0.0), Bin::Near);
        assert_eq!(m.bin(2.69, 0.0), Bin::Near);
        assert!(matches!(m.bin(2.7, 0.0), Bin::Segment(0)));
        match m.bin(100.0, 0.0) {
            Bin::Beyond(i) => {
                let id = m.segment_id(i).unwrap();
                assert_eq!((id.zone, id.ring, id.sector), (3, 3, 0));
            }
            other => panic!("{other:?}"),
        }
        // The ego radius widens the near disc.
        let m = ZoneModel::new(&ZoneConfig::default(), 4.0).unwrap();
        assert_eq!(m.bin(3.5, 0.0), Bin::Near);
    }
}
