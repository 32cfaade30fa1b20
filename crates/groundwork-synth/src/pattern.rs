//! Beam patterns: the ray directions a sensor fires in one frame, in its own frame (x
//! forward, y left, z up), with the range limits, noise and dropouts of its family.

use std::f64::consts::{PI, TAU};

use glam::DVec3;

use crate::shapes::Shape;

/// How the beams sweep the scene.
#[derive(Debug, Clone, PartialEq)]
pub enum Scanning {
    /// A spinning multi-beam sensor: one ring per elevation angle, `columns` azimuth steps
    /// per revolution.
    Spinning {
        /// Elevation of each beam, degrees, top to bottom.
        elevations_deg: Vec<f64>,
        /// Azimuth steps per revolution.
        columns: u32,
    },
    /// A solid-state sensor steered by two counter-rotating prisms (Livox): a rosette that
    /// never repeats, so each frame covers different gaps of its field of view.
    Rosette {
        /// Full horizontal field of view, degrees.
        horizontal_deg: f64,
        /// Full vertical field of view, degrees.
        vertical_deg: f64,
        /// Elevation of the field's centre, degrees (0: centred on the horizon).
        vertical_center_deg: f64,
        /// Returns per frame.
        points: u32,
    },
}

/// The vehicle body as the sensor sees it (its points are the ego points the presets'
/// `ego_radius` removes): a body up to 1 m and a cabin under the sensor, centred below it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EgoBody {
    /// Length along the vehicle's x, metres.
    pub length: f64,
    /// Width, metres.
    pub width: f64,
    /// How far below the sensor origin the cabin's roof is, metres.
    pub top_below_sensor: f64,
}

impl EgoBody {
    /// Body and cabin in the vehicle's ground-aligned frame, for a sensor `height` up.
    pub fn boxes(&self, height: f64) -> [Shape; 2] {
        let roof = (height - self.top_below_sensor).max(0.4);
        let body_top = roof.min(1.0);
        let part = |length: f64, width: f64, top: f64| Shape::Box {
            center: DVec3::new(0.0, 0.0, 0.5 * (top + 0.3)),
            half: DVec3::new(length / 2.0, width / 2.0, 0.5 * (top - 0.3)),
            yaw: 0.0,
        };
        [
            part(self.length, self.width, body_top),
            part(0.45 * self.length, self.width - 0.2, roof),
        ]
    }
}

/// One sensor family's pattern and error model.
#[derive(Debug, Clone, PartialEq)]
pub struct BeamPattern {
    /// The sensor preset this pattern belongs to.
    pub sensor: String,
    /// The sweep.
    pub scanning: Scanning,
    /// Shortest and longest return, metres (along the beam).
    pub min_range: f64,
    /// Longest return, metres.
    pub max_range: f64,
    /// Standard deviation of the range error, metres.
    pub range_noise: f64,
    /// Probability that a beam which hits something returns nothing.
    pub dropout: f64,
    /// Probability that a return off the ground is a multipath echo, measured too long
    /// and so placed below the ground surface (labelled SemanticKITTI `outlier`).
    pub multipath: f64,
    /// Whether a beam without return still yields a point at (0, 0, 0), as Ouster and Livox
    /// drivers emit in organized clouds; otherwise it yields nothing.
    pub placeholders: bool,
    /// The vehicle's own body, if the sensor sees it.
    pub ego: Option<EgoBody>,
    /// Time per frame, seconds.
    pub period: f64,
}

/// Names of the sensors with a pattern (the presets of `config/sensors/`).
pub const PATTERN_SENSORS: &[&str] = &[
    "hdl64e", "hdl32e", "vlp16", "vlp32c", "os1-64", "os1-128", "pandar64", "livox", "os0-64",
    "os2-64", "xt32", "qt128", "helios", "mid360", "m1",
];

const CAR: EgoBody = EgoBody {
    length: 4.6,
    width: 1.9,
    top_below_sensor: 0.3,
};

fn linspace(top: f64, bottom: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| top + (bottom - top) * i as f64 / (n - 1) as f64)
        .collect()
}

impl BeamPattern {
    /// The pattern of a sensor preset (case-insensitive), from its data sheet.
    pub fn for_sensor(name: &str) -> Option<Self> {
        let name = name.to_ascii_lowercase();
        let spinning = |elevations_deg: Vec<f64>, columns: u32| Scanning::Spinning {
            elevations_deg,
            columns,
        };
        let base = |scanning: Scanning, max_range: f64, range_noise: f64| BeamPattern {
            sensor: name.clone(),
            scanning,
            min_range: 0.5,
            max_range,
            range_noise,
            dropout: 0.02,
            multipath: 0.002,
            placeholders: false,
            ego: None,
            period: 0.1,
        };
        let p = match name.as_str() {
            // Upper block 1/3° apart from +2°, lower block 1/2° apart down to −24.9°; about
            // 2 000 firings per revolution at 10 Hz (KITTI: ~120 000 returns).
            "hdl64e" => {
                let mut e = linspace(2.0, -8.33, 32);
                e.extend(linspace(-8.87, -24.9, 32));
                base(spinning(e, 2000), 120.0, 0.02)
            }
            // 32 beams 1.33° apart from +10.67° to −30.67°, 20 Hz (nuScenes: ~34 000).
            "hdl32e" => BeamPattern {
                ego: Some(CAR),
                period: 0.05,
                ..base(spinning(linspace(10.67, -30.67, 32), 1085), 70.0, 0.02)
            },
            // 16 beams 2° apart, ±15°, 0.2° azimuth steps.
            "vlp16" => BeamPattern {
                ego: Some(EgoBody {
                    length: 0.9,
                    width: 0.6,
                    top_below_sensor: 0.3,
                }),
                ..base(spinning(linspace(15.0, -15.0, 16), 1800), 100.0, 0.03)
            },
            // Beams packed around the horizon, sparse toward +15° and −25°.
            "vlp32c" => {
                let e = vec![
                    15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667, 0.333, 0.0,
                    -0.333, -0.667, -1.0, -1.333, -1.667, -2.0, -2.333, -2.667, -3.0, -3.333,
                    -3.667, -4.0, -4.667, -5.333, -6.148, -7.254, -8.843, -11.31, -15.639, -25.0,
                ];
                BeamPattern {
                    ego: Some(CAR),
                    ..base(spinning(e, 1800), 200.0, 0.03)
                }
            }
            // Uniform over 45° (OS1), 90° (OS0) or 22.5° (OS2); an organized image in which
            // no-return pixels are (0, 0, 0).
            "os1-64" | "os1-128" | "os0-64" | "os2-64" => {
                let (half_fov, beams, columns, range) = match name.as_str() {
                    "os1-64" => (22.5, 64, 1024, 120.0),
                    "os1-128" => (22.5, 128, 2048, 120.0),
                    "os0-64" => (45.0, 64, 1024, 50.0),
                    _ => (11.25, 64, 1024, 240.0),
                };
                BeamPattern {
                    placeholders: true,
                    ego: Some(EgoBody {
                        length: 1.6,
                        width: 1.2,
                        top_below_sensor: 0.6,
                    }),
                    ..base(
                        spinning(linspace(half_fov, -half_fov, beams), columns),
                        range,
                        0.015,
                    )
                }
            }
            // Hesai XT32: 32 beams 1° apart, +15° to −16°, 0.18° azimuth steps.
            "xt32" => BeamPattern {
                ego: Some(CAR),
                ..base(spinning(linspace(15.0, -16.0, 32), 2000), 120.0, 0.01)
            },
            // Hesai QT128: 128 beams over ±52.6°, 0.4° azimuth steps, short range.
            "qt128" => BeamPattern {
                ego: Some(EgoBody {
                    length: 0.9,
                    width: 0.6,
                    top_below_sensor: 0.3,
                }),
                ..base(spinning(linspace(52.6, -52.6, 128), 900), 50.0, 0.02)
            },
            // RoboSense Helios-32 (5515): 70° with the beams packed around the horizon.
            "helios" => {
                let mut e = linspace(15.0, 2.0, 8);
                e.extend(linspace(1.0, -8.0, 16));
                e.extend(linspace(-10.0, -55.0, 8));
                BeamPattern {
                    ego: Some(CAR),
                    ..base(spinning(e, 1800), 150.0, 0.02)
                }
            }
            // Livox Mid-360: all around, −7° to +52°, non-repetitive, 20 000 per frame.
            "mid360" => BeamPattern {
                min_range: 0.1,
                ego: Some(EgoBody {
                    length: 0.7,
                    width: 0.5,
                    top_below_sensor: 0.15,
                }),
                ..base(
                    Scanning::Rosette {
                        horizontal_deg: 360.0,
                        vertical_deg: 59.0,
                        vertical_center_deg: 22.5,
                        points: 20_000,
                    },
                    70.0,
                    0.02,
                )
            },
            // RoboSense M1: 120° × 25° forward, 75 000 per frame; its MEMS raster is
            // approximated by the rosette's coverage of the same field.
            "m1" => base(
                Scanning::Rosette {
                    horizontal_deg: 120.0,
                    vertical_deg: 25.0,
                    vertical_center_deg: 0.0,
                    points: 75_000,
                },
                200.0,
                0.02,
            ),
            // Dense 1/6° beams around the horizon, 2°-ish steps above and below.
            "pandar64" => {
                let mut e = vec![15.0, 11.0, 8.0, 5.0, 3.0, 2.0];
                e.extend(linspace(1.833, -6.0, 48));
                e.extend(linspace(-7.0, -25.0, 10));
                BeamPattern {
                    ego: Some(CAR),
                    ..base(spinning(e, 1800), 200.0, 0.02)
                }
            }
            "livox" => BeamPattern {
                placeholders: true,
                ..base(
                    Scanning::Rosette {
                        horizontal_deg: 70.0,
                        vertical_deg: 30.0,
                        vertical_center_deg: 0.0,
                        points: 24_000,
                    },
                    190.0,
                    0.02,
                )
            },
            _ => return None,
        };
        Some(p)
    }

    /// Rays per frame.
    pub fn rays_per_frame(&self) -> usize {
        match &self.scanning {
            Scanning::Spinning {
                elevations_deg,
                columns,
            } => elevations_deg.len() * *columns as usize,
            Scanning::Rosette { points, .. } => *points as usize,
        }
    }

    /// Rows × columns of the organized image, for spinning sensors (beam-major).
    pub fn image(&self) -> Option<(usize, usize)> {
        match &self.scanning {
            Scanning::Spinning {
                elevations_deg,
                columns,
            } => Some((elevations_deg.len(), *columns as usize)),
            Scanning::Rosette { .. } => None,
        }
    }

    /// Unit ray directions of frame `frame` in the sensor frame: beam by beam (row-major
    /// image) for spinning sensors, in firing order for the rosette, which continues where
    /// the previous frame stopped.
    pub fn rays(&self, frame: u64) -> Vec<DVec3> {
        match &self.scanning {
            Scanning::Spinning {
                elevations_deg,
                columns,
            } => {
                let mut rays = Vec::with_capacity(self.rays_per_frame());
                for el in elevations_deg {
                    let (se, ce) = el.to_radians().sin_cos();
                    for c in 0..*columns {
                        // Clockwise from behind, as Velodyne and Ouster number columns.
                        let az = PI - TAU * f64::from(c) / f64::from(*columns);
                        let (sa, ca) = az.sin_cos();
                        rays.push(DVec3::new(ce * ca, ce * sa, se));
                    }
                }
                rays
            }
            Scanning::Rosette {
                horizontal_deg,
                vertical_deg,
                vertical_center_deg,
                points,
            } => {
                let (half_h, half_v) = (
                    (horizontal_deg / 2.0).to_radians(),
                    (vertical_deg / 2.0).to_radians(),
                );
                // Two prisms deflect the beam by equal angles while turning at speeds whose
                // ratio is irrational (−e²): the sum of the two deflections traces a
                // rosette filling the unit disc, stretched here to the field of view.
                const RATIO: f64 = -7.389_056_098_930_65;
                // Ten turns of the first prism per frame.
                let step = 10.0 * TAU / f64::from(*points);
                let start = frame * u64::from(*points);
                (0..u64::from(*points))
                    .map(|i| {
                        let t = (start + i) as f64 * step;
                        let u = 0.5 * (t.cos() + (RATIO * t).cos());
                        let v = 0.5 * (t.sin() + (RATIO * t).sin());
                        let (az, el) = (u * half_h, vertical_center_deg.to_radians() + v * half_v);
                        let (se, ce) = el.sin_cos();
                        let (sa, ca) = az.sin_cos();
                        DVec3::new(ce * ca, ce * sa, se)
                    })
                    .collect()
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn every_preset_has_a_pattern_of_unit_rays() {
        for name in PATTERN_SENSORS {
            let p = BeamPattern::for_sensor(name).unwrap();
            let rays = p.rays(0);
            assert_eq!(rays.len(), p.rays_per_frame(), "{name}");
            assert!(
                rays.iter().all(|r| (r.length() - 1.0).abs() < 1e-12),
                "{name}"
            );
        }
        assert!(BeamPattern::for_sensor("HDL64E").is_some());
        assert!(BeamPattern::for_sensor("nope").is_none());
    }

    #[test]
    fn spinning_elevations_match_the_data_sheets() {
        let p = BeamPattern::for_sensor("hdl64e").unwrap();
        let Scanning::Spinning { elevations_deg, .. } = &p.scanning else {
            panic!("spinning")
        };
        assert_eq!(elevations_deg.len(), 64);
        assert!((elevations_deg[0] - 2.0).abs() < 1e-9 && (elevations_deg[63] + 24.9).abs() < 1e-9);
        for name in ["vlp32c", "pandar64", "os1-128"] {
            let p = BeamPattern::for_sensor(name).unwrap();
            let Scanning::Spinning { elevations_deg, .. } = &p.scanning else {
                panic!("spinning")
            };
            assert!(
                elevations_deg.windows(2).all(|w| w[0] > w[1]),
                "{name}: top to bottom"
            );
        }
    }

    #[test]
    fn the_mid360_sees_all_around_from_below_the_horizon_to_52_degrees_up() {
        let p = BeamPattern::for_sensor("mid360").unwrap();
        let rays = p.rays(0);
        let el: Vec<f64> = rays.iter().map(|r| r.z.asin().to_degrees()).collect();
        assert!(el.iter().all(|e| (-7.0 - 1e-9..=52.0 + 1e-9).contains(e)));
        assert!(el.iter().any(|e| *e < -5.0) && el.iter().any(|e| *e > 50.0));
        // Every quarter of the circle is covered.
        for q in 0..4 {
            let lo = -180.0 + 90.0 * f64::from(q);
            assert!(
                rays.iter()
                    .any(|r| (lo..lo + 90.0).contains(&r.y.atan2(r.x).to_degrees())),
                "quarter {q}"
            );
        }
    }

    #[test]
    fn the_rosette_stays_in_its_field_of_view_and_never_repeats() {
        let p = BeamPattern::for_sensor("livox").unwrap();
        let (a, b) = (p.rays(0), p.rays(1));
        for r in a.iter().chain(&b) {
            let az = r.y.atan2(r.x).to_degrees();
            let el = r.z.asin().to_degrees();
            assert!(
                az.abs() <= 35.0 + 1e-9 && el.abs() <= 15.0 + 1e-9,
                "{az} {el}"
            );
        }
        // The next frame's rays are new directions, not the same pattern again.
        let same = a
            .iter()
            .zip(&b)
            .filter(|(x, y)| (**x - **y).length() < 1e-4)
            .count();
        assert!(same < a.len() / 100, "{same} repeated");
        // Both halves of the field are covered in one frame.
        assert!(a.iter().any(|r| r.y > 0.4) && a.iter().any(|r| r.y < -0.4));
        assert!(a.iter().any(|r| r.z > 0.2) && a.iter().any(|r| r.z < -0.2));
    }
}
