//! Packets built from the manual's layout: decoded, checked, fuzzed.

use proptest::prelude::*;

use super::*;

/// A single-return packet of `model` whose every firing measures `distance_units`, block
/// azimuths `az0 + k·step`.
pub(crate) fn packet(model: Model, az0: u16, step: u16, distance_units: u16) -> Vec<u8> {
    let mut p = vec![0u8; PACKET_SIZE];
    for i in 0..BLOCKS {
        let at = i * BLOCK_SIZE;
        let flag = if model.is_hdl64e() && i % 2 == 1 {
            LOWER_BANK
        } else {
            UPPER_BANK
        };
        p[at..at + 2].copy_from_slice(&flag.to_le_bytes());
        let az = ((az0 as u32 + i as u32 * step as u32) % TURN) as u16;
        p[at + 2..at + 4].copy_from_slice(&az.to_le_bytes());
        for j in 0..FIRINGS {
            let m = at + 4 + j * 3;
            p[m..m + 2].copy_from_slice(&distance_units.to_le_bytes());
            p[m + 2] = (j * 7 % 256) as u8;
        }
    }
    p[1200..1204].copy_from_slice(&1_234_567u32.to_le_bytes());
    p[1204] = 0x37;
    p[1205] = model.packet_byte().unwrap_or(0);
    p
}

#[test]
fn a_vlp16_packet_gives_384_returns_on_a_sphere_with_the_manuals_elevations() {
    let d = Decoder::new(Model::Vlp16, None).unwrap();
    // 10 m (5000 × 2 mm), azimuth 0.2° a block (10 Hz).
    let bytes = packet(Model::Vlp16, 9_000, 20, 5_000);
    let p = d.check(&bytes).unwrap();
    assert_eq!(p.return_mode, ReturnMode::Strongest);
    assert_eq!(p.toh_us(), 1_234_567);
    let mut returns = Vec::new();
    d.decode(&p, |r| returns.push(r));
    assert_eq!(returns.len(), 384);
    assert_eq!(d.count(&p), 384);
    for r in &returns {
        let range = (r.x * r.x + r.y * r.y + r.z * r.z).sqrt();
        // Off the sphere by the lasers' vertical offsets only (at most 12 mm).
        assert!((range - 10.0).abs() < 0.012, "{range}");
    }
    // The first firing: laser 0 at −15°, azimuth 90° clockwise from forward: to the right;
    // its origin 11.2 mm above the centre.
    let r = returns[0];
    assert!((r.z - 10.0 * (-15f32).to_radians().sin() - 0.0112).abs() < 1e-4);
    assert!(r.x.abs() < 1e-3 && r.y < -9.0, "{r:?}");
    assert_eq!(r.ring, 0);
    // Laser 1 (+1°) is ring 8; the second sequence of a block fires 55.296 µs later.
    assert_eq!(returns[1].ring, 8);
    assert!((returns[16].time - 55.296e-6).abs() < 1e-9);
    // Firing times grow within the packet; the azimuth turns clockwise with them.
    assert!(returns.windows(2).all(|w| w[1].time >= w[0].time));
}

#[test]
fn the_range_gate_and_empty_firings_drop_returns() {
    let d = Decoder::new(Model::Vlp32c, None).unwrap();
    let none = packet(Model::Vlp32c, 0, 20, 0);
    assert_eq!(d.count(&d.check(&none).unwrap()), 0);
    // 4 mm units: 20 units is 8 cm, below the 0.1 m gate.
    let near = packet(Model::Vlp32c, 0, 20, 20);
    assert_eq!(d.count(&d.check(&near).unwrap()), 0);
    let ok = packet(Model::Vlp32c, 35_990, 20, 2_500);
    let p = d.check(&ok).unwrap();
    let mut n = 0;
    d.decode(&p, |_| n += 1);
    assert_eq!((n, d.count(&p)), (384, 384));
}

#[test]
fn dual_return_packets_give_both_returns_once_each() {
    let d = Decoder::new(Model::Vlp16, None).unwrap();
    let mut bytes = packet(Model::Vlp16, 100, 0, 5_000);
    bytes[1204] = 0x39;
    // Blocks in pairs on the same azimuth: even blocks last, odd strongest.
    for i in 0..BLOCKS {
        let az = (100 + (i / 2) * 20) as u16;
        bytes[i * BLOCK_SIZE + 2..i * BLOCK_SIZE + 4].copy_from_slice(&az.to_le_bytes());
        if i % 2 == 1 {
            // The strongest differs from the last on the first firing only.
            let m = i * BLOCK_SIZE + 4;
            bytes[m..m + 2].copy_from_slice(&4_000u16.to_le_bytes());
        }
    }
    let p = d.check(&bytes).unwrap();
    assert_eq!(p.return_mode, ReturnMode::Dual);
    let mut returns = Vec::new();
    d.decode(&p, |r| returns.push(r));
    // 6 firings × 32 measurements, and one extra on each pair's first measurement.
    assert_eq!(returns.len(), 6 * 32 + 6);
    assert_eq!(d.count(&p), returns.len());
}

#[test]
fn malformed_packets_are_named_not_decoded() {
    let d = Decoder::new(Model::Vlp16, None).unwrap();
    let good = packet(Model::Vlp16, 0, 20, 5_000);
    let e = d.check(&good[..1000]).unwrap_err().to_string();
    assert!(e.contains("1000 bytes"), "{e}");
    let mut other = good.clone();
    other[1205] = 0x28;
    assert!(d.check(&other).unwrap_err().to_string().contains("0x28"));
    let mut mode = good.clone();
    mode[1204] = 0x11;
    assert!(matches!(d.check(&mode), Err(PacketError::ReturnMode(0x11))));
    let mut flag = good.clone();
    flag[3 * BLOCK_SIZE] = 0;
    assert!(matches!(
        d.check(&flag),
        Err(PacketError::BlockFlag { block: 3, .. })
    ));
    let mut az = good;
    az[2..4].copy_from_slice(&36_000u16.to_le_bytes());
    assert!(matches!(d.check(&az), Err(PacketError::Azimuth { .. })));
    // The HDL-64E needs its own table.
    let e = Decoder::new(Model::Hdl64eS3, None).unwrap_err().to_string();
    assert!(e.contains("--sensor-config"), "{e}");
    let e = Decoder::new(Model::Vlp16, Calibration::builtin(Model::Vlp32c))
        .unwrap_err()
        .to_string();
    assert!(e.contains("32 lasers") && e.contains("16"), "{e}");
}

fn hdl64e_calibration() -> Calibration {
    let lasers = (0..64)
        .map(|k| LaserCorrection {
            laser_id: k,
            rot_correction: ((k % 8) as f32 - 4.0) * 0.01,
            vert_correction: (-24.9 + 0.42 * k as f32).to_radians(),
            dist_correction: 1.2 + 0.001 * k as f32,
            dist_correction_x: 1.25,
            dist_correction_y: 1.22,
            vert_offset_correction: 0.2 - 0.001 * k as f32,
            horiz_offset_correction: 0.026 * if k % 2 == 0 { 1.0 } else { -1.0 },
            max_intensity: 230.0,
            min_intensity: 10.0,
            focal_distance: 10.0,
            focal_slope: 1.1,
        })
        .collect();
    Calibration::new(0.002, lasers).unwrap()
}

#[test]
fn hdl64e_packets_use_both_banks_and_the_factory_corrections() {
    let d = Decoder::new(Model::Hdl64eS3, Some(hdl64e_calibration())).unwrap();
    let bytes = packet(Model::Hdl64eS3, 1_000, 8, 10_000);
    let p = d.check(&bytes).unwrap();
    let mut returns = Vec::new();
    d.decode(&p, |r| returns.push(r));
    assert_eq!(returns.len(), 384);
    // Lower-bank blocks hold lasers 32–63: rings spread over all 64.
    let rings: std::collections::BTreeSet<u16> = returns.iter().map(|r| r.ring).collect();
    assert_eq!(rings.len(), 64);
    for r in &returns {
        let range = (r.x * r.x + r.y * r.y + r.z * r.z).sqrt();
        // 20 m plus about 1.2 m of distance correction, the offsets a few centimetres.
        assert!((range - 21.2).abs() < 0.3, "{range}");
        assert!((10.0..=230.0).contains(&r.intensity));
    }
}

proptest! {
    /// Any bytes: a named error or returns, never a panic; every return finite and within
    /// the range gate (plus the HDL-64E's offsets), the count equal to what is decoded.
    #[test]
    fn any_bytes_are_refused_or_decoded_to_finite_returns(
        model in prop::sample::select(Model::ALL.to_vec()),
        bytes in prop::collection::vec(any::<u8>(), 0..1300),
        az0 in 0u16..36_000,
        step in 0u16..400,
        noise in prop::collection::vec((0usize..PACKET_SIZE, any::<u8>()), 0..64),
    ) {
        let calibration = model.is_hdl64e().then(hdl64e_calibration);
        let d = Decoder::new(model, calibration).unwrap();
        // Random bytes (almost always refused) and a good packet with random damage.
        let mut damaged = packet(model, az0, step, 3_000);
        for (at, b) in noise {
            damaged[at] = b;
        }
        for bytes in [bytes, damaged] {
            if let Ok(p) = d.check(&bytes) {
                let mut n = 0;
                d.decode(&p, |r| {
                    n += 1;
                    assert!(r.x.is_finite() && r.y.is_finite() && r.z.is_finite());
                    let range = (r.x * r.x + r.y * r.y + r.z * r.z).sqrt();
                    assert!(range <= MAX_RANGE + 1.0, "{range}");
                });
                prop_assert_eq!(n, d.count(&p));
                prop_assert!(n <= 2 * BLOCKS * FIRINGS);
            }
        }
    }
}
