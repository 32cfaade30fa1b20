//! The concentric zone model: zones of rings of sectors in the horizontal plane of the
//! ground-aligned frame (Patchwork++'s CZM).

use std::f64::consts::TAU;

use crate::config::ZoneConfig;
use crate::error::ConfigError;

/// Zone models with up to this many zones get the vectorised [`ZoneModel::bin_many`].
const MAX_FAST_ZONES: usize = 8;

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

    /// Packed bins of many points at once (f32, ground-aligned frame): `u32::MAX` for near
    /// points, the segment index otherwise, with bit 31 set beyond max range.
    ///
    /// Branch-free so that the compiler vectorises it: zone parameters are picked with
    /// selects from tables padded to `MAX_FAST_ZONES`, atan2 is a select-based polynomial.
    /// Models with more zones fall back to [`ZoneModel::bin`]. Agrees with `bin` except for
    /// points within f32 rounding of a boundary.
    pub fn bin_many(&self, xs: &[f32], ys: &[f32], out: &mut [u32]) {
        const NEAR: u32 = u32::MAX;
        const BEYOND: u32 = 1 << 31;
        let nz = self.rings.len();
        if nz > MAX_FAST_ZONES {
            for ((o, &x), &y) in out.iter_mut().zip(xs).zip(ys) {
                *o = match self.bin(f64::from(x), f64::from(y)) {
                    Bin::Near => NEAR,
                    Bin::Segment(s) => s,
                    Bin::Beyond(s) => s | BEYOND,
                };
            }
            return;
        }
        // Per-zone tables, padded with copies of the last zone (never selected).
        let pad = |f: &dyn Fn(usize) -> f32| -> [f32; MAX_FAST_ZONES] {
            std::array::from_fn(|k| f(k.min(nz - 1)))
        };
        let lower = pad(&|k| self.boundaries[k] as f32);
        let width = pad(&|k| self.ring_width[k] as f32);
        let rings = pad(&|k| self.rings[k] as f32);
        let sectors = pad(&|k| self.sectors[k] as f32);
        let offset = pad(&|k| self.zone_offset[k] as f32);
        // Upper edges of zones 0..nz-1; +inf past the last so the count stops there.
        let upper: [f32; MAX_FAST_ZONES] = std::array::from_fn(|k| {
            if k + 1 < nz {
                self.boundaries[k + 1] as f32
            } else {
                f32::INFINITY
            }
        });
        let near = self.near_radius as f32;
        let max_range = self.boundaries[nz] as f32;
        for ((o, &x), &y) in out.iter_mut().zip(xs).zip(ys) {
            let r = (x * x + y * y).sqrt();
            let mut z = 0.0f32;
            for u in upper {
                z += if r >= u { 1.0 } else { 0.0 };
            }
            let (mut lo, mut w, mut nr, mut ns, mut off) = (0.0, 1.0, 1.0, 1.0, 0.0);
            for k in 0..MAX_FAST_ZONES {
                let hit = z == k as f32;
                lo = if hit { lower[k] } else { lo };
                w = if hit { width[k] } else { w };
                nr = if hit { rings[k] } else { nr };
                ns = if hit { sectors[k] } else { ns };
                off = if hit { offset[k] } else { off };
            }
            // max/min rather than clamp: clamp's argument check blocks vectorisation.
            let ring = ((r - lo) / w).floor().max(0.0).min(nr - 1.0);
            let beyond = r >= max_range;
            let ring = if beyond { nr - 1.0 } else { ring };
            let theta = crate::fastmath::atan2_f32(y, x);
            let theta = if theta < 0.0 {
                theta + std::f32::consts::TAU
            } else {
                theta
            };
            let sector = (theta * ns / std::f32::consts::TAU)
                .floor()
                .max(0.0)
                .min(ns - 1.0);
            let idx = (off + ring * ns + sector) as i32 as u32;
            let idx = if beyond { idx | BEYOND } else { idx };
            *o = if r < near { NEAR } else { idx };
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

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> ZoneModel {
        ZoneModel::new(&ZoneConfig::default(), 0.0).unwrap()
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
    fn batch_binning_agrees_with_scalar_binning() {
        let m = model();
        let (mut xs, mut ys) = (vec![], vec![]);
        for i in 0..20_000 {
            let a = i as f64 * 0.006_283_1 + 0.001;
            // Radii offset from every ring edge (edges fall on multiples of ~0.05 m here).
            let r = (i % 1000) as f64 * 0.1 + 0.0123;
            xs.push((r * a.cos()) as f32);
            ys.push((r * a.sin()) as f32);
        }
        xs.push(0.0);
        ys.push(0.0);
        let mut batch = vec![0; xs.len()];
        m.bin_many(&xs, &ys, &mut batch);
        let mut differ = 0;
        for ((&x, &y), &b) in xs.iter().zip(&ys).zip(&batch) {
            let want = match m.bin(f64::from(x), f64::from(y)) {
                Bin::Near => u32::MAX,
                Bin::Segment(s) => s,
                Bin::Beyond(s) => s | (1 << 31),
            };
            differ += usize::from(want != b);
        }
        // Only points within f32 rounding of a ring or sector edge may differ.
        assert!(
            differ <= 2,
            "{differ} of {} points binned differently",
            xs.len()
        );
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
