//! A Velodyne sensor's laser table: per laser its vertical angle, its azimuth offset and,
//! for the HDL-64E, the factory's distance and offset corrections.
//!
//! Read from the calibration file format of the ROS `velodyne_pointcloud` driver (YAML,
//! angles in radians; `velodyne_decoder` and Autoware read the same files), or built in
//! from the user manuals for the sensors that ship without one.

use std::path::Path;

use serde::Deserialize;

use super::Model;
use crate::PacketError;

/// One laser's corrections, as the calibration file names them (radians, metres).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct LaserCorrection {
    /// The laser's number in the packets.
    pub laser_id: usize,
    /// Azimuth offset: the laser points this much clockwise of the block's azimuth.
    pub rot_correction: f32,
    /// Elevation.
    pub vert_correction: f32,
    /// Added to every distance (HDL-64E).
    #[serde(default)]
    pub dist_correction: f32,
    /// Distance corrections at the near point along x and y (HDL-64E two-point calibration).
    #[serde(default)]
    pub dist_correction_x: f32,
    /// See `dist_correction_x`.
    #[serde(default)]
    pub dist_correction_y: f32,
    /// Height of the laser's origin above the sensor's.
    #[serde(default)]
    pub vert_offset_correction: f32,
    /// Horizontal offset of the laser's origin.
    #[serde(default)]
    pub horiz_offset_correction: f32,
    /// Intensity correction (HDL-64E): clamp range.
    #[serde(default = "max_intensity")]
    pub max_intensity: f32,
    /// See `max_intensity`.
    #[serde(default)]
    pub min_intensity: f32,
    /// Intensity correction (HDL-64E): focal distance and slope.
    #[serde(default)]
    pub focal_distance: f32,
    /// See `focal_distance`.
    #[serde(default)]
    pub focal_slope: f32,
}

fn max_intensity() -> f32 {
    255.0
}

/// The file as written by the ROS driver's tools.
#[derive(Debug, Deserialize)]
struct CalibrationFile {
    #[serde(default)]
    num_lasers: Option<usize>,
    distance_resolution: f32,
    lasers: Vec<LaserCorrection>,
}

/// A sensor's laser table, indexed by laser number.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Metres per unit of a packet's distance field.
    pub distance_resolution: f32,
    /// One entry per laser, in laser-number order.
    pub lasers: Vec<LaserCorrection>,
    /// Each laser's ring: its rank by elevation, lowest first.
    pub rings: Vec<u16>,
}

impl Calibration {
    /// A table from its lasers (any order; each number from 0 to n − 1 exactly once).
    pub fn new(distance_resolution: f32, mut lasers: Vec<LaserCorrection>) -> Result<Self, String> {
        if !(distance_resolution.is_finite() && distance_resolution > 0.0) {
            return Err(format!(
                "distance_resolution {distance_resolution} is not a positive length"
            ));
        }
        lasers.sort_by_key(|l| l.laser_id);
        for (k, l) in lasers.iter().enumerate() {
            if l.laser_id != k {
                return Err(format!(
                    "laser_id {} where {k} was expected: each laser from 0 to {} exactly once",
                    l.laser_id,
                    lasers.len() - 1
                ));
            }
            let values = [
                l.rot_correction,
                l.vert_correction,
                l.dist_correction,
                l.dist_correction_x,
                l.dist_correction_y,
                l.vert_offset_correction,
                l.horiz_offset_correction,
                l.max_intensity,
                l.min_intensity,
                l.focal_distance,
                l.focal_slope,
            ];
            if values.iter().any(|v| !v.is_finite()) {
                return Err(format!("laser {k}: a correction is not a finite number"));
            }
            if l.min_intensity.floor() > l.max_intensity.floor() {
                return Err(format!(
                    "laser {k}: min_intensity {} above max_intensity {}",
                    l.min_intensity, l.max_intensity
                ));
            }
        }
        if ![16, 32, 64].contains(&lasers.len()) {
            return Err(format!(
                "{} lasers: Velodyne sensors have 16, 32 or 64",
                lasers.len()
            ));
        }
        // Rings by elevation, ties in laser order (as the ROS driver numbers them).
        let mut order: Vec<usize> = (0..lasers.len()).collect();
        order.sort_by(|&a, &b| {
            lasers[a]
                .vert_correction
                .total_cmp(&lasers[b].vert_correction)
        });
        let mut rings = vec![0u16; lasers.len()];
        for (ring, &laser) in order.iter().enumerate() {
            rings[laser] = ring as u16;
        }
        Ok(Self {
            distance_resolution,
            lasers,
            rings,
        })
    }

    /// Reads a calibration file (the ROS driver's YAML).
    pub fn read(path: &Path) -> Result<Self, PacketError> {
        let bad = |reason: String| PacketError::Calibration {
            path: path.display().to_string(),
            reason,
        };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let file: CalibrationFile =
            serde_yaml_ng::from_str(&text).map_err(|e| bad(e.to_string()))?;
        if let Some(n) = file.num_lasers
            && n != file.lasers.len()
        {
            return Err(bad(format!(
                "num_lasers is {n} but {} lasers are listed",
                file.lasers.len()
            )));
        }
        Self::new(file.distance_resolution, file.lasers).map_err(bad)
    }

    /// The manual's table for a sensor that needs no calibration file (None: the HDL-64E,
    /// whose every unit has its own).
    pub fn builtin(model: Model) -> Option<Self> {
        // (elevation, azimuth offset) in degrees, by laser number, from the user manuals;
        // the azimuth offset is the manual's (counter-clockwise positive), the opposite of
        // the file's `rot_correction`.
        let (resolution, table): (f32, Vec<(f64, f64)>) = match model {
            Model::Vlp16 => (
                0.002,
                (0..16)
                    .map(|k| (interleaved(k, -15.0, 1.0, 2.0), 0.0))
                    .collect(),
            ),
            Model::PuckHiRes => (
                0.002,
                (0..16)
                    .map(|k| (interleaved(k, -10.0, 2.0 / 3.0, 4.0 / 3.0), 0.0))
                    .collect(),
            ),
            Model::Hdl32e => (0.002, HDL32E_ELEVATION.iter().map(|&e| (e, 0.0)).collect()),
            Model::Vlp32c => (0.004, VLP32C.to_vec()),
            Model::Hdl64eS2 | Model::Hdl64eS3 => return None,
        };
        // Each laser's origin sits off the sensor's centre: the beams cross at a focal point
        // this far from the axis (the sensors' envelope drawings), which puts a laser
        // pointing down at `e` this much higher; the HDL-32E's and the Puck Hi-Res's
        // drawings list the offsets themselves.
        let focal: f32 = match model {
            Model::Vlp16 | Model::PuckHiRes => 41.91e-3,
            Model::Vlp32c => 42.4e-3,
            _ => 28.83e-3,
        };
        let listed: Option<&[f32]> = match model {
            Model::PuckHiRes => Some(&PUCK_HIRES_OFFSETS),
            Model::Hdl32e => Some(&HDL32E_OFFSETS),
            _ => None,
        };
        let lasers = table
            .iter()
            .enumerate()
            .map(|(k, &(elevation, offset))| {
                // As the drivers compute it: degrees to radians in f64, then f32.
                let vert = (elevation * std::f64::consts::PI / 180.0) as f32;
                LaserCorrection {
                    laser_id: k,
                    rot_correction: (-offset * std::f64::consts::PI / 180.0) as f32,
                    vert_correction: vert,
                    dist_correction: 0.0,
                    dist_correction_x: 0.0,
                    dist_correction_y: 0.0,
                    vert_offset_correction: listed.map_or(focal * (-vert).tan(), |o| o[k]),
                    horiz_offset_correction: 0.0,
                    max_intensity: 255.0,
                    min_intensity: 0.0,
                    focal_distance: 0.0,
                    focal_slope: 0.0,
                }
            })
            .collect();
        Self::new(resolution, lasers).ok()
    }

    /// Whether the HDL-64E's distance, offset and intensity corrections apply (any field
    /// beyond the two angles set).
    pub fn is_advanced(&self) -> bool {
        self.lasers.iter().any(|l| {
            l.dist_correction != 0.0
                || l.dist_correction_x != 0.0
                || l.dist_correction_y != 0.0
                || l.horiz_offset_correction != 0.0
                || l.max_intensity != 255.0
                || l.min_intensity != 0.0
                || l.focal_distance != 0.0
                || l.focal_slope != 0.0
        })
    }
}

/// The Puck's interleaved fan: even lasers climb from `low`, odd ones from `first_odd`,
/// `step` apart (rounded to the manual's three decimals).
fn interleaved(k: usize, low: f64, first_odd: f64, step: f64) -> f64 {
    let e = if k.is_multiple_of(2) {
        low + step * (k / 2) as f64
    } else {
        first_odd + step * (k / 2) as f64
    };
    (e * 1000.0).round() / 1000.0
}

/// HDL-32E elevations by laser number (user manual), degrees.
const HDL32E_ELEVATION: [f64; 32] = [
    -30.67, -9.33, -29.33, -8.0, -28.0, -6.67, -26.67, -5.33, -25.33, -4.0, -24.0, -2.67, -22.67,
    -1.33, -21.33, 0.0, -20.0, 1.33, -18.67, 2.67, -17.33, 4.0, -16.0, 5.33, -14.67, 6.67, -13.33,
    8.0, -12.0, 9.33, -10.67, 10.67,
];

/// Puck Hi-Res lasers' vertical offsets (envelope drawing 86-0129), metres.
const PUCK_HIRES_OFFSETS: [f32; 16] = [
    7.4e-3, -0.9e-3, 6.5e-3, -1.8e-3, 5.5e-3, -2.7e-3, 4.6e-3, -3.7e-3, 3.7e-3, -4.6e-3, 2.7e-3,
    -5.5e-3, 1.8e-3, -6.5e-3, 0.9e-3, -7.4e-3,
];

/// HDL-32E lasers' vertical offsets (envelope drawing 86-0106), metres.
const HDL32E_OFFSETS: [f32; 32] = [
    17.17e-3, 4.76e-3, 16.27e-3, 4.07e-3, 15.4e-3, 3.38e-3, 14.54e-3, 2.7e-3, 13.71e-3, 2.02e-3,
    12.89e-3, 1.35e-3, 12.09e-3, 0.67e-3, 11.31e-3, 0.0, 10.54e-3, -0.67e-3, 9.78e-3, -1.35e-3,
    9.04e-3, -2.02e-3, 8.3e-3, -2.7e-3, 7.58e-3, -3.38e-3, 6.86e-3, -4.07e-3, 6.15e-3, -4.76e-3,
    5.45e-3, -5.45e-3,
];

/// VLP-32C (elevation, azimuth offset) by laser number (user manual), degrees.
const VLP32C: [(f64, f64); 32] = [
    (-25.0, 1.4),
    (-1.0, -4.2),
    (-1.667, 1.4),
    (-15.639, -1.4),
    (-11.31, 1.4),
    (0.0, -1.4),
    (-0.667, 4.2),
    (-8.843, -1.4),
    (-7.254, 1.4),
    (0.333, -4.2),
    (-0.333, 1.4),
    (-6.148, -1.4),
    (-5.333, 4.2),
    (1.333, -1.4),
    (0.667, 4.2),
    (-4.0, -1.4),
    (-4.667, 1.4),
    (1.667, -4.2),
    (1.0, 1.4),
    (-3.667, -4.2),
    (-3.333, 4.2),
    (3.333, -1.4),
    (2.333, 1.4),
    (-2.667, -1.4),
    (-3.0, 1.4),
    (7.0, -1.4),
    (4.667, 1.4),
    (-2.333, -4.2),
    (-2.0, 4.2),
    (15.0, -1.4),
    (10.333, 1.4),
    (-1.333, -1.4),
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_tables_have_the_manuals_fans() {
        let v = Calibration::builtin(Model::Vlp16).unwrap();
        let deg: Vec<f32> = v
            .lasers
            .iter()
            .map(|l| l.vert_correction.to_degrees())
            .collect();
        assert!((deg[0] + 15.0).abs() < 1e-4 && (deg[1] - 1.0).abs() < 1e-4);
        assert!((deg[15] - 15.0).abs() < 1e-4);
        // Rings climb with elevation: laser 0 (−15°) is ring 0, laser 15 (+15°) ring 15.
        assert_eq!((v.rings[0], v.rings[1], v.rings[15]), (0, 8, 15));
        let hires = Calibration::builtin(Model::PuckHiRes).unwrap();
        assert!((hires.lasers[13].vert_correction.to_degrees() - 8.667).abs() < 1e-4);
        let c = Calibration::builtin(Model::Vlp32c).unwrap();
        assert_eq!(c.distance_resolution, 0.004);
        assert!((c.lasers[0].rot_correction.to_degrees() + 1.4).abs() < 1e-4);
        assert!(Calibration::builtin(Model::Hdl64eS3).is_none());
        assert!(!c.is_advanced());
        // The VLP-16 manual's vertical corrections: 11.2 mm for laser 0 (−15°), −0.7 mm
        // for laser 1 (+1°).
        assert!((v.lasers[0].vert_offset_correction - 11.2e-3).abs() < 0.1e-3);
        assert!((v.lasers[1].vert_offset_correction + 0.7e-3).abs() < 0.1e-3);
    }

    #[test]
    fn a_calibration_file_is_read_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cal.yaml");
        let mut text = String::from("distance_resolution: 0.002\nlasers:\n");
        for k in (0..16).rev() {
            text += &format!(
                "  - {{laser_id: {k}, rot_correction: 0.01, vert_correction: {}, dist_correction: 0.01, two_pt_correction_available: false}}\n",
                (k as f32 - 8.0) * 0.02
            );
        }
        std::fs::write(&path, &text).unwrap();
        let c = Calibration::read(&path).unwrap();
        assert_eq!(c.lasers.len(), 16);
        assert_eq!(c.lasers[3].laser_id, 3);
        assert!(c.is_advanced());
        std::fs::write(&path, text.replace("laser_id: 3,", "laser_id: 4,")).unwrap();
        let e = Calibration::read(&path).unwrap_err().to_string();
        assert!(e.contains("cal.yaml") && e.contains("exactly once"), "{e}");
        std::fs::write(
            &path,
            text.replace(
                "laser_id: 5,",
                "laser_id: 5, min_intensity: 200, max_intensity: 100,",
            ),
        )
        .unwrap();
        let e = Calibration::read(&path).unwrap_err().to_string();
        assert!(
            e.contains("laser 5: min_intensity 200 above max_intensity 100"),
            "{e}"
        );
        std::fs::write(&path, "lasers: [").unwrap();
        let e = Calibration::read(&path).unwrap_err().to_string();
        assert!(e.contains("cal.yaml"), "{e}");
    }
}
