//! Velodyne data packets (VLP-16, Puck Hi-Res, VLP-32C, HDL-32E, HDL-64E S2/S3): 1206-byte
//! UDP payloads of 12 blocks, each an azimuth and 32 measurements (distance, reflectivity),
//! then the sensor's time (µs since the top of the hour), the return mode and the model.
//!
//! Decoding follows the user manuals' packet and timing tables, with the conventions of the
//! ROS driver (and `velodyne_decoder`, which the tests compare with): a firing's azimuth is
//! the block's, advanced by the packet's mean rotation rate times the firing's time offset,
//! rounded to the 0.01° unit; x forward, y left, z up; returns with no distance, or out of
//! [`MIN_RANGE`, `MAX_RANGE`], are dropped.

pub mod calibration;

pub use calibration::{Calibration, LaserCorrection};

use crate::PacketError;

/// A data packet's UDP payload size.
pub const PACKET_SIZE: usize = 1206;
/// The UDP port Velodyne sensors send data packets to, unless configured otherwise.
pub const DATA_PORT: u16 = 2368;
/// Blocks per packet.
const BLOCKS: usize = 12;
/// Measurements per block.
const FIRINGS: usize = 32;
/// Bytes per block: flag, azimuth, 32 × (distance, reflectivity).
const BLOCK_SIZE: usize = 4 + FIRINGS * 3;
/// Azimuth units per turn (0.01°).
const TURN: u32 = 36_000;
/// A block's flag: the upper laser bank (all 16/32-beam sensors) and the HDL-64E's lower.
const UPPER_BANK: u16 = 0xEEFF;
const LOWER_BANK: u16 = 0xDDFF;
/// Returns nearer than this are the sensor's own housing or noise, metres.
pub const MIN_RANGE: f32 = 0.1;
/// Beyond every model's rated range, metres.
pub const MAX_RANGE: f32 = 250.0;

/// The sensor models decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Model {
    /// VLP-16 (Puck, Puck LITE).
    Vlp16,
    /// VLP-16 Hi-Res (Puck Hi-Res).
    PuckHiRes,
    /// VLP-32C (Ultra Puck).
    Vlp32c,
    /// HDL-32E.
    Hdl32e,
    /// HDL-64E S2 / S2.1 (needs its calibration file).
    Hdl64eS2,
    /// HDL-64E S3 (needs its calibration file).
    Hdl64eS3,
}

impl Model {
    /// Every model, for listings.
    pub const ALL: [Model; 6] = [
        Model::Vlp16,
        Model::PuckHiRes,
        Model::Vlp32c,
        Model::Hdl32e,
        Model::Hdl64eS2,
        Model::Hdl64eS3,
    ];

    /// The model a packet's last byte names (the HDL-64E leaves it unset).
    pub fn from_packet_byte(b: u8) -> Option<Self> {
        match b {
            0x21 => Some(Self::Hdl32e),
            0x22 => Some(Self::Vlp16),
            0x24 => Some(Self::PuckHiRes),
            0x28 => Some(Self::Vlp32c),
            _ => None,
        }
    }

    /// The byte this model's packets carry (None: the HDL-64E's carry none).
    pub fn packet_byte(self) -> Option<u8> {
        match self {
            Self::Hdl32e => Some(0x21),
            Self::Vlp16 => Some(0x22),
            Self::PuckHiRes => Some(0x24),
            Self::Vlp32c => Some(0x28),
            Self::Hdl64eS2 | Self::Hdl64eS3 => None,
        }
    }

    /// Its name on the command line and in the docs.
    pub fn name(self) -> &'static str {
        match self {
            Self::Vlp16 => "vlp16",
            Self::PuckHiRes => "vlp16-hires",
            Self::Vlp32c => "vlp32c",
            Self::Hdl32e => "hdl32e",
            Self::Hdl64eS2 => "hdl64e-s2",
            Self::Hdl64eS3 => "hdl64e",
        }
    }

    /// The model of a name ([`Model::name`]).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name() == name)
    }

    /// Whether the packets hold 64 lasers in upper and lower banks.
    fn is_hdl64e(self) -> bool {
        matches!(self, Self::Hdl64eS2 | Self::Hdl64eS3)
    }

    /// Each measurement's firing time after the packet's first, seconds: the manuals'
    /// timing tables, by block and measurement.
    fn timings(self) -> [[f32; FIRINGS]; BLOCKS] {
        let mut t = [[0f32; FIRINGS]; BLOCKS];
        for (i, block) in t.iter_mut().enumerate() {
            for (j, time) in block.iter_mut().enumerate() {
                let us = match self {
                    // 16 lasers fire one after another 2.304 µs apart; a block holds two
                    // such sequences, 55.296 µs apart.
                    Self::Vlp16 | Self::PuckHiRes => {
                        55.296 * (2 * i + j / 16) as f64 + 2.304 * (j % 16) as f64
                    }
                    // Lasers fire in pairs, 2.304 µs apart; 55.296 µs a block.
                    Self::Vlp32c => 55.296 * i as f64 + 2.304 * (j / 2) as f64,
                    // One laser after another 1.152 µs apart; 46.08 µs a block.
                    Self::Hdl32e => 46.08 * i as f64 + 1.152 * j as f64,
                    // Upper and lower banks fire together, four lasers at a time.
                    Self::Hdl64eS2 => {
                        48.0 * (i / 2) as f64
                            + 6.0 * (j / 4) as f64
                            + [0.0, 1.26, 2.46, 3.66][j % 4]
                    }
                    Self::Hdl64eS3 => {
                        57.6 * (i / 2) as f64 + 7.2 * (j / 4) as f64 + [0.0, 1.3, 2.5, 3.7][j % 4]
                    }
                };
                *time = (us * 1e-6) as f32;
            }
        }
        t
    }
}

/// How a packet's returns were chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReturnMode {
    /// The strongest return per firing.
    Strongest,
    /// The last return per firing.
    Last,
    /// Both: blocks in pairs (last, strongest) on the same firing.
    Dual,
}

/// One return, decoded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Return {
    /// Position (metres, x forward, y left, z up).
    pub x: f32,
    /// See `x`.
    pub y: f32,
    /// See `x`.
    pub z: f32,
    /// Calibrated reflectivity, 0–255.
    pub intensity: f32,
    /// The ring (rank of the laser's elevation, lowest 0).
    pub ring: u16,
    /// Firing time after the packet's first firing, seconds.
    pub time: f32,
}

/// A checked packet's fields.
#[derive(Debug, Clone, Copy)]
pub struct PacketView<'a> {
    bytes: &'a [u8],
    /// How the returns were chosen.
    pub return_mode: ReturnMode,
}

impl<'a> PacketView<'a> {
    fn block_flag(&self, i: usize) -> u16 {
        u16_at(self.bytes, i * BLOCK_SIZE)
    }

    /// Block `i`'s azimuth, 0.01° units.
    pub fn azimuth(&self, i: usize) -> u16 {
        u16_at(self.bytes, i * BLOCK_SIZE + 2)
    }

    /// The last block's azimuth (where the sensor has turned to by the packet's end).
    pub fn last_azimuth(&self) -> u16 {
        self.azimuth(BLOCKS - 1)
    }

    /// The sensor's time: µs since the top of the hour.
    pub fn toh_us(&self) -> u32 {
        let b = &self.bytes[1200..1204];
        u32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }

    fn measurement(&self, block: usize, j: usize) -> (u16, u8) {
        let at = block * BLOCK_SIZE + 4 + j * 3;
        (u16_at(self.bytes, at), self.bytes[at + 2])
    }
}

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}

/// Turns packets of one sensor into returns.
#[derive(Debug, Clone)]
pub struct Decoder {
    model: Model,
    calibration: Calibration,
    advanced: bool,
    timings: [[f32; FIRINGS]; BLOCKS],
    /// cos and sin of every azimuth unit.
    cos_azimuth: Vec<f32>,
    sin_azimuth: Vec<f32>,
    /// Per laser: cos/sin of the azimuth offset and of the elevation.
    lasers: Vec<LaserTrig>,
}

#[derive(Debug, Clone, Copy)]
struct LaserTrig {
    cos_rot: f32,
    sin_rot: f32,
    cos_vert: f32,
    sin_vert: f32,
    /// The HDL-64E's intensity correction: (1 − focal distance / 131)², and the clamp.
    focal_squared: f32,
    min_intensity: f32,
    max_intensity: f32,
}

impl Decoder {
    /// A decoder for `model` with its calibration (None: the manual's table; required for
    /// the HDL-64E).
    pub fn new(model: Model, calibration: Option<Calibration>) -> Result<Self, PacketError> {
        let calibration = match calibration {
            Some(c) => c,
            None => Calibration::builtin(model).ok_or(PacketError::NeedsCalibration {
                model: model.name(),
            })?,
        };
        let lasers_needed = match model {
            Model::Vlp16 | Model::PuckHiRes => 16,
            Model::Vlp32c | Model::Hdl32e => 32,
            Model::Hdl64eS2 | Model::Hdl64eS3 => 64,
        };
        if calibration.lasers.len() != lasers_needed {
            return Err(PacketError::CalibrationMismatch {
                model: model.name(),
                lasers: calibration.lasers.len(),
                expected: lasers_needed,
            });
        }
        let deg_to_rad = (std::f64::consts::PI / 180.0) as f32;
        let (cos_azimuth, sin_azimuth) = (0..TURN)
            .map(|k| {
                let a = 0.01f32 * k as f32 * deg_to_rad;
                (a.cos(), a.sin())
            })
            .unzip();
        let lasers = calibration
            .lasers
            .iter()
            .map(|l| {
                let focal = 1.0 - l.focal_distance / 131.0;
                LaserTrig {
                    cos_rot: l.rot_correction.cos(),
                    sin_rot: l.rot_correction.sin(),
                    cos_vert: l.vert_correction.cos(),
                    sin_vert: l.vert_correction.sin(),
                    focal_squared: focal * focal,
                    min_intensity: l.min_intensity.floor(),
                    max_intensity: l.max_intensity.floor(),
                }
            })
            .collect();
        Ok(Self {
            model,
            advanced: calibration.is_advanced(),
            calibration,
            timings: model.timings(),
            cos_azimuth,
            sin_azimuth,
            lasers,
        })
    }

    /// The model decoded.
    pub fn model(&self) -> Model {
        self.model
    }

    /// The laser table in use.
    pub fn calibration(&self) -> &Calibration {
        &self.calibration
    }

    /// Checks a UDP payload: size, model byte, return mode, block flags.
    pub fn check<'a>(&self, bytes: &'a [u8]) -> Result<PacketView<'a>, PacketError> {
        if bytes.len() != PACKET_SIZE {
            return Err(PacketError::Size {
                got: bytes.len(),
                expected: PACKET_SIZE,
            });
        }
        let model_byte = bytes[1205];
        let mode_byte = bytes[1204];
        if let Some(expected) = self.model.packet_byte()
            && model_byte != expected
        {
            return Err(PacketError::Model {
                got: model_byte,
                expected: self.model.name(),
            });
        }
        let return_mode = if self.model.is_hdl64e() {
            // The HDL-64E has no mode byte: dual-return packets repeat each azimuth.
            if u16_at(bytes, 2) == u16_at(bytes, 2 * BLOCK_SIZE + 2) {
                ReturnMode::Dual
            } else {
                ReturnMode::Strongest
            }
        } else {
            match mode_byte {
                0x37 => ReturnMode::Strongest,
                0x38 => ReturnMode::Last,
                0x39 => ReturnMode::Dual,
                b => return Err(PacketError::ReturnMode(b)),
            }
        };
        let view = PacketView { bytes, return_mode };
        for i in 0..BLOCKS {
            let flag = view.block_flag(i);
            let ok = flag == UPPER_BANK || (self.model.is_hdl64e() && flag == LOWER_BANK);
            if !ok {
                return Err(PacketError::BlockFlag { block: i, flag });
            }
            if u32::from(view.azimuth(i)) >= TURN {
                return Err(PacketError::Azimuth {
                    block: i,
                    azimuth: view.azimuth(i),
                });
            }
        }
        Ok(view)
    }

    /// Calls `each` with every measurement of a checked packet that has a distance, in the
    /// order the ROS driver emits them: (laser, azimuth unit, firing time, raw distance,
    /// reflectivity). In dual-return mode a firing's two returns come last first, then the
    /// strongest; one return where both are the same.
    fn measurements(&self, p: &PacketView, mut each: impl FnMut(usize, u16, f32, u16, u8)) {
        let dual = p.return_mode == ReturnMode::Dual;
        let span = p.azimuth(BLOCKS - 1) as i32 - p.azimuth(0) as i32;
        let azimuth_diff = span.rem_euclid(TURN as i32) as f32;
        let last = if dual { (BLOCKS - 1) / 2 } else { BLOCKS - 1 };
        let rotation_rate = azimuth_diff / (self.timings[last][0] - self.timings[0][0]);
        let azimuth_at = |block: usize, dt: f32| -> u16 {
            let a = p.azimuth(block) as f32 + rotation_rate * dt;
            // Non-negative (the rate and dt are): a subtraction wraps it, save on a
            // damaged packet whose rate is absurd.
            let a = (a + TURN as f32).round() as i64;
            let wrapped = if a < 2 * TURN as i64 {
                a - TURN as i64 * i64::from(a >= TURN as i64)
            } else {
                a.rem_euclid(TURN as i64)
            };
            wrapped as u16
        };
        if self.model.is_hdl64e() {
            for i in 0..BLOCKS {
                let bank = if p.block_flag(i) == LOWER_BANK { 32 } else { 0 };
                if !dual {
                    let t0 = self.timings[i / 2 * 2][0];
                    for j in 0..FIRINGS {
                        let (d, r) = p.measurement(i, j);
                        if d == 0 {
                            continue;
                        }
                        let time = self.timings[i][j];
                        each(bank + j, azimuth_at(i, time - t0), time, d, r);
                    }
                } else if i % 4 < 2 {
                    // Blocks 0, 1 (strongest) and 2, 3 (last) share a firing: upper, lower.
                    let t0 = self.timings[i / 4 * 2][0];
                    for j in 0..FIRINGS {
                        let strongest = p.measurement(i, j);
                        let last = p.measurement(i + 2, j);
                        if strongest.0 == 0 && last.0 == 0 {
                            continue;
                        }
                        let time = self.timings[i / 4 * 2 + i % 2][j];
                        both(
                            &mut each,
                            bank + j,
                            azimuth_at(i, time - t0),
                            time,
                            last,
                            strongest,
                        );
                    }
                }
            }
            return;
        }
        let lasers = self.calibration.lasers.len();
        let step = if dual { 2 } else { 1 };
        for i in (0..BLOCKS).step_by(step) {
            let row = if dual { i / 2 } else { i };
            let t0 = self.timings[row][0];
            for j in 0..FIRINGS {
                // A 16-laser block holds two firing sequences, one after the other.
                let laser = if lasers == 16 { j % 16 } else { j };
                let time = self.timings[row][j];
                if dual {
                    let last = p.measurement(i, j);
                    let strongest = p.measurement(i + 1, j);
                    if last.0 == 0 && strongest.0 == 0 {
                        continue;
                    }
                    both(
                        &mut each,
                        laser,
                        azimuth_at(i, time - t0),
                        time,
                        last,
                        strongest,
                    );
                } else {
                    let (d, r) = p.measurement(i, j);
                    if d == 0 {
                        continue;
                    }
                    each(laser, azimuth_at(i, time - t0), time, d, r);
                }
            }
        }
    }

    /// The measured range of a raw distance on a laser, after the laser's distance
    /// correction: what the range gate sees.
    fn gated_range(&self, laser: usize, raw: u16) -> f32 {
        let d = raw as f32 * self.calibration.distance_resolution;
        if self.advanced {
            d + self.calibration.lasers[laser].dist_correction
        } else {
            d
        }
    }

    fn in_range(r: f32) -> bool {
        (MIN_RANGE..=MAX_RANGE).contains(&r)
    }

    /// How many returns [`Decoder::decode`] gives for a checked packet (no trigonometry:
    /// to size a scan before decoding it in place).
    pub fn count(&self, p: &PacketView) -> usize {
        let mut n = 0;
        self.measurements(p, |laser, _, _, raw, _| {
            n += usize::from(Self::in_range(self.gated_range(laser, raw)));
        });
        n
    }

    /// Decodes a checked packet's returns, in the sensor's firing order.
    pub fn decode(&self, p: &PacketView, mut sink: impl FnMut(Return)) {
        self.measurements(p, |laser, azimuth, time, raw, reflectivity| {
            let range = self.gated_range(laser, raw);
            if !Self::in_range(range) {
                return;
            }
            let t = &self.lasers[laser];
            let (ca, sa) = (
                self.cos_azimuth[azimuth as usize],
                self.sin_azimuth[azimuth as usize],
            );
            // cos and sin of (azimuth − the laser's offset).
            let cos_rot = ca * t.cos_rot + sa * t.sin_rot;
            let sin_rot = sa * t.cos_rot - ca * t.sin_rot;
            let ring = self.calibration.rings[laser];
            let c = &self.calibration.lasers[laser];
            if !self.advanced {
                let xy = range * t.cos_vert;
                sink(Return {
                    x: xy * cos_rot,
                    y: -xy * sin_rot,
                    z: range * t.sin_vert + c.vert_offset_correction,
                    intensity: reflectivity as f32,
                    ring,
                    time,
                });
                return;
            }
            sink(self.advanced_return(
                c,
                t,
                raw,
                range,
                (cos_rot, sin_rot),
                reflectivity,
                ring,
                time,
            ));
        });
    }

    /// The HDL-64E's factory corrections (user manual, appendix on calibration): two-point
    /// distance correction within 25 m, the lasers' offsets from the sensor's centre, the
    /// intensity's focal correction.
    #[allow(clippy::too_many_arguments)]
    fn advanced_return(
        &self,
        c: &LaserCorrection,
        t: &LaserTrig,
        raw: u16,
        corrected: f32,
        (cos_rot, sin_rot): (f32, f32),
        reflectivity: u8,
        ring: u16,
        time: f32,
    ) -> Return {
        const FAR_POINT: f32 = 25.04;
        const NEAR_X: f32 = 2.40;
        const NEAR_Y: f32 = 1.93;
        // Products with the reciprocals, not divisions (a divide is the slowest step here;
        // the results differ from the quotient's in the last bit at most).
        const PER_X: f32 = 1.0 / (FAR_POINT - NEAR_X);
        const PER_Y: f32 = 1.0 / (FAR_POINT - NEAR_Y);
        let measured = raw as f32 * self.calibration.distance_resolution;
        let (mut cx, mut cy, mut cz) = (c.dist_correction, c.dist_correction, c.dist_correction);
        let two_point = c.dist_correction_x != 0.0 && c.dist_correction_y != 0.0;
        if two_point && measured < FAR_POINT {
            let xy = corrected * t.cos_vert;
            let xx = (xy * sin_rot).abs();
            let yy = (xy * cos_rot).abs();
            let kx = (xx - NEAR_X) * PER_X;
            let ky = (yy - NEAR_Y) * PER_Y;
            cx = kx * c.dist_correction + (1.0 - kx) * c.dist_correction_x;
            cy = ky * c.dist_correction + (1.0 - ky) * c.dist_correction_y;
            // The mean of x and y for z (the manual's use of y alone reads as a slip).
            cz = (cx + cy) * 0.5;
        }
        let x_offset = c.horiz_offset_correction * -cos_rot;
        let y_offset = c.horiz_offset_correction * sin_rot;
        // The manual's frame (x right, y forward), turned into x forward, y left.
        let mx = (measured + cx) * t.cos_vert * sin_rot + x_offset;
        let my = (measured + cy) * t.cos_vert * cos_rot + y_offset;
        let z = (measured + cz) * t.sin_vert + c.vert_offset_correction;
        let near = 1.0 - raw as f32 * (1.0 / 65535.0);
        let intensity =
            reflectivity as f32 + 256.0 * c.focal_slope * (t.focal_squared - near * near).abs();
        Return {
            x: my,
            y: -mx,
            z,
            // Bounds checked when the calibration was read (min ≤ max).
            intensity: intensity.max(t.min_intensity).min(t.max_intensity),
            ring,
            time,
        }
    }
}

/// A dual-return firing's returns: last, then strongest; one where both are the same.
fn both(
    each: &mut impl FnMut(usize, u16, f32, u16, u8),
    laser: usize,
    azimuth: u16,
    time: f32,
    last: (u16, u8),
    strongest: (u16, u8),
) {
    if last.0 == strongest.0 {
        each(laser, azimuth, time, strongest.0, strongest.1);
        return;
    }
    if last.0 > 0 {
        each(laser, azimuth, time, last.0, last.1);
    }
    if strongest.0 > 0 {
        each(laser, azimuth, time, strongest.0, strongest.1);
    }
}

#[cfg(test)]
pub(crate) mod tests;
