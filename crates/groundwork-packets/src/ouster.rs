//! Ouster lidar packets (OS0, OS1, OS2; firmware 2.x and later) with the metadata JSON the
//! sensor gives (`http://<sensor>/api/v1/sensor/metadata`, or the file its tools save).
//!
//! A packet holds `columns_per_packet` columns (16 by default) of one frame; a column is a
//! timestamp, its measurement id (the column's index in the frame) and a status, then one
//! pixel per beam. Two pixel layouts are read: `LEGACY` (12 bytes, 20-bit range) and
//! `RNG19_RFL8_SIG16_NIR16` (12 bytes, 19-bit range), the default of firmware 2.2 and
//! later. Positions follow Ouster's documented lookup table (`XYZLut` of ouster-sdk, which
//! the tests compare with): each pixel's direction from the beam's altitude and azimuth and
//! the column's encoder angle, the beam's origin offset, then the lidar-to-sensor
//! transform; range in mm. The sensor frame is Ouster's (x forward, y left, z up).

use std::path::Path;

use serde_json::Value;

use crate::PacketError;
use crate::scan::{PacketCounters, ScanPackets};

/// The UDP port Ouster sensors send lidar packets to, unless configured otherwise.
pub const LIDAR_PORT: u16 = 7502;

/// The pixel layouts read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Profile {
    /// Firmware 1.x's layout, still selectable.
    Legacy,
    /// `RNG19_RFL8_SIG16_NIR16`: single return.
    Single,
}

/// What decoding needs of a sensor's metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct Metadata {
    /// Columns per frame (512, 1024, 2048).
    pub columns_per_frame: usize,
    /// Beams (16, 32, 64, 128).
    pub pixels_per_column: usize,
    /// Columns per packet.
    pub columns_per_packet: usize,
    /// The pixel layout.
    pub profile: Profile,
    /// The first and last column the sensor sends.
    pub column_window: (usize, usize),
    /// Per beam: elevation and azimuth offset, degrees.
    pub altitude_deg: Vec<f64>,
    /// See `altitude_deg`.
    pub azimuth_deg: Vec<f64>,
    /// Beam origin relative to the lidar (4×4 row-major, mm).
    pub beam_to_lidar: [f64; 16],
    /// Lidar to sensor frame (4×4 row-major, mm).
    pub lidar_to_sensor: [f64; 16],
    /// The product line (e.g. `OS-1-64`), for the logs.
    pub product: String,
}

fn numbers(v: &Value) -> Option<Vec<f64>> {
    v.as_array()?.iter().map(Value::as_f64).collect()
}

fn matrix(v: &Value) -> Option<[f64; 16]> {
    let n = numbers(v)?;
    n.try_into().ok()
}

impl Metadata {
    /// Reads the sensor's metadata JSON: the nested layout of firmware 2.x and later
    /// (`beam_intrinsics`, `lidar_data_format`, ...) or the flat one of 1.x.
    pub fn read(path: &Path) -> Result<Self, PacketError> {
        let text = std::fs::read_to_string(path).map_err(|e| PacketError::Calibration {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_json(&text).map_err(|reason| PacketError::Calibration {
            path: path.display().to_string(),
            reason,
        })
    }

    /// Parses metadata JSON.
    pub fn from_json(text: &str) -> Result<Self, String> {
        let root: Value = serde_json::from_str(text).map_err(|e| e.to_string())?;
        // Firmware 2.x nests sections; 1.x has their keys at the top.
        let section = |name: &str| root.get(name).unwrap_or(&root);
        let beams = section("beam_intrinsics");
        let format = root.get("lidar_data_format").or(root.get("data_format"));
        let format = format
            .ok_or("no lidar_data_format (or data_format): not an Ouster sensor's metadata")?;
        let need = |v: Option<&Value>, what: &str| -> Result<Value, String> {
            v.cloned().ok_or_else(|| format!("no {what}"))
        };
        let size = |key: &str| -> Result<usize, String> {
            format
                .get(key)
                .and_then(Value::as_u64)
                .map(|n| n as usize)
                .ok_or_else(|| format!("lidar_data_format has no {key}"))
        };
        let altitude_deg = numbers(&need(
            beams.get("beam_altitude_angles"),
            "beam_altitude_angles",
        )?)
        .ok_or("beam_altitude_angles: not a list of numbers")?;
        let azimuth_deg = numbers(&need(
            beams.get("beam_azimuth_angles"),
            "beam_azimuth_angles",
        )?)
        .ok_or("beam_azimuth_angles: not a list of numbers")?;
        let origin_mm = beams
            .get("lidar_origin_to_beam_origin_mm")
            .and_then(Value::as_f64)
            .unwrap_or(0.0);
        // Older metadata gives only the beam origin's distance along x.
        let beam_to_lidar = match beams.get("beam_to_lidar_transform") {
            Some(v) => matrix(v).ok_or("beam_to_lidar_transform: not 16 numbers")?,
            None => [
                1.0, 0.0, 0.0, origin_mm, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0,
                1.0,
            ],
        };
        let lidar_to_sensor = match section("lidar_intrinsics").get("lidar_to_sensor_transform") {
            Some(v) => matrix(v).ok_or("lidar_to_sensor_transform: not 16 numbers")?,
            None => return Err("no lidar_to_sensor_transform".into()),
        };
        let profile = match format
            .get("udp_profile_lidar")
            .and_then(Value::as_str)
            .unwrap_or("LEGACY")
        {
            "LEGACY" => Profile::Legacy,
            "RNG19_RFL8_SIG16_NIR16" => Profile::Single,
            other => {
                return Err(format!(
                    "udp_profile_lidar {other} is not read yet: set the sensor to RNG19_RFL8_SIG16_NIR16 or LEGACY"
                ));
            }
        };
        let columns_per_frame = size("columns_per_frame")?;
        let pixels_per_column = size("pixels_per_column")?;
        let columns_per_packet = size("columns_per_packet")?;
        let window = format
            .get("column_window")
            .and_then(numbers)
            .filter(|w| w.len() == 2)
            .map(|w| (w[0] as usize, w[1] as usize))
            .unwrap_or((0, columns_per_frame.saturating_sub(1)));
        let m = Self {
            columns_per_frame,
            pixels_per_column,
            columns_per_packet,
            profile,
            column_window: window,
            altitude_deg,
            azimuth_deg,
            beam_to_lidar,
            lidar_to_sensor,
            product: root
                .get("sensor_info")
                .and_then(|s| s.get("prod_line"))
                .or(root.get("prod_line"))
                .and_then(Value::as_str)
                .unwrap_or("Ouster")
                .to_string(),
        };
        m.check()?;
        Ok(m)
    }

    fn check(&self) -> Result<(), String> {
        let (w, h, c) = (
            self.columns_per_frame,
            self.pixels_per_column,
            self.columns_per_packet,
        );
        if ![512, 1024, 2048, 4096].contains(&w) {
            return Err(format!("columns_per_frame {w}: 512, 1024, 2048 or 4096"));
        }
        if !(1..=256).contains(&h) || !(1..=64).contains(&c) {
            return Err(format!(
                "pixels_per_column {h} / columns_per_packet {c} out of range"
            ));
        }
        if self.altitude_deg.len() != h || self.azimuth_deg.len() != h {
            return Err(format!(
                "{} altitude and {} azimuth angles for {h} beams",
                self.altitude_deg.len(),
                self.azimuth_deg.len()
            ));
        }
        let all = self
            .altitude_deg
            .iter()
            .chain(&self.azimuth_deg)
            .chain(&self.beam_to_lidar)
            .chain(&self.lidar_to_sensor);
        if all.clone().any(|v| !v.is_finite()) {
            return Err("a beam angle or transform entry is not a finite number".into());
        }
        if self.column_window.0 >= w || self.column_window.1 >= w {
            return Err(format!(
                "column_window {:?} beyond {w} columns",
                self.column_window
            ));
        }
        Ok(())
    }

    /// Bytes of a lidar packet.
    pub fn packet_size(&self) -> usize {
        let (packet_header, column_header, column_footer, packet_footer) = match self.profile {
            Profile::Legacy => (0, 16, 4, 0),
            Profile::Single => (32, 12, 0, 32),
        };
        packet_header
            + self.columns_per_packet
                * (column_header + 12 * self.pixels_per_column + column_footer)
            + packet_footer
    }
}

/// One return, decoded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Return {
    /// Position (metres, the sensor frame).
    pub x: f32,
    /// See `x`.
    pub y: f32,
    /// See `x`.
    pub z: f32,
    /// The signal photons (0–65535), as the ROS driver's `intensity`.
    pub intensity: f32,
    /// The beam (row, top 0).
    pub row: u16,
    /// The column (measurement id).
    pub column: u16,
    /// The column's time, ns (the sensor's clock).
    pub time_ns: u64,
}

/// A checked packet.
#[derive(Debug, Clone, Copy)]
pub struct PacketView<'a> {
    bytes: &'a [u8],
    /// The frame it belongs to.
    pub frame_id: u16,
}

/// Turns one sensor's lidar packets into returns.
#[derive(Debug, Clone)]
pub struct Decoder {
    meta: Metadata,
    packet_size: usize,
    column_size: usize,
    /// Per pixel (row-major over columns: `row * W + column`): direction and offset, m
    /// per mm of range and m.
    direction: Vec<[f64; 3]>,
    offset: Vec<[f64; 3]>,
}

impl Decoder {
    /// A decoder for the sensor the metadata describes.
    pub fn new(meta: Metadata) -> Self {
        let (w, h) = (meta.columns_per_frame, meta.pixels_per_column);
        let b = &meta.beam_to_lidar;
        let t = &meta.lidar_to_sensor;
        let (bx, bz) = (b[3], b[11]);
        let beam_distance = if bz != 0.0 { bx.hypot(bz) } else { bx };
        let mut direction = vec![[0.0; 3]; w * h];
        let mut offset = vec![[0.0; 3]; w * h];
        let step = std::f64::consts::PI * 2.0 / w as f64;
        for col in 0..w {
            let encoder = 2.0 * std::f64::consts::PI - col as f64 * step;
            for row in 0..h {
                let azimuth = -meta.azimuth_deg[row] * std::f64::consts::PI / 180.0;
                let altitude = meta.altitude_deg[row] * std::f64::consts::PI / 180.0;
                let d = [
                    (encoder + azimuth).cos() * altitude.cos(),
                    (encoder + azimuth).sin() * altitude.cos(),
                    altitude.sin(),
                ];
                let o = [
                    encoder.cos() * bx - d[0] * beam_distance,
                    encoder.sin() * bx - d[1] * beam_distance,
                    -d[2] * beam_distance + bz,
                ];
                let rotate = |v: [f64; 3]| -> [f64; 3] {
                    std::array::from_fn(|i| {
                        v[0] * t[i * 4] + v[1] * t[i * 4 + 1] + v[2] * t[i * 4 + 2]
                    })
                };
                let (rd, ro) = (rotate(d), rotate(o));
                let i = row * w + col;
                direction[i] = rd.map(|v| v * 1e-3);
                offset[i] = std::array::from_fn(|k| (ro[k] + t[k * 4 + 3]) * 1e-3);
            }
        }
        let column_size = match meta.profile {
            Profile::Legacy => 16 + 12 * h + 4,
            Profile::Single => 12 + 12 * h,
        };
        Self {
            packet_size: meta.packet_size(),
            column_size,
            meta,
            direction,
            offset,
        }
    }

    /// The metadata in use.
    pub fn metadata(&self) -> &Metadata {
        &self.meta
    }

    /// Checks a UDP payload: size, and every column's measurement id within the frame.
    pub fn check<'a>(&self, bytes: &'a [u8]) -> Result<PacketView<'a>, PacketError> {
        if bytes.len() != self.packet_size {
            return Err(PacketError::Size {
                got: bytes.len(),
                expected: self.packet_size,
            });
        }
        let frame_id = match self.meta.profile {
            Profile::Legacy => u16::from_le_bytes([bytes[10], bytes[11]]),
            Profile::Single => u16::from_le_bytes([bytes[2], bytes[3]]),
        };
        let view = PacketView { bytes, frame_id };
        for c in 0..self.meta.columns_per_packet {
            let (_, m, _) = self.column(&view, c);
            if m as usize >= self.meta.columns_per_frame {
                return Err(PacketError::Azimuth {
                    block: c,
                    azimuth: m,
                });
            }
        }
        Ok(view)
    }

    fn column_at(&self, c: usize) -> usize {
        let header = if self.meta.profile == Profile::Single {
            32
        } else {
            0
        };
        header + c * self.column_size
    }

    /// Column `c`'s timestamp, measurement id and validity.
    fn column(&self, p: &PacketView, c: usize) -> (u64, u16, bool) {
        let at = self.column_at(c);
        let b = p.bytes;
        let mut ts = [0u8; 8];
        ts.copy_from_slice(&b[at..at + 8]);
        let m = u16::from_le_bytes([b[at + 8], b[at + 9]]);
        let valid = match self.meta.profile {
            Profile::Legacy => {
                let s = at + self.column_size - 4;
                b[s..s + 4] == [0xFF; 4]
            }
            Profile::Single => b[at + 10] & 1 == 1,
        };
        (u64::from_le_bytes(ts), m, valid)
    }

    /// The packet's first column: its measurement id and timestamp.
    pub fn first_column(&self, p: &PacketView) -> (u16, u64) {
        let (ts, m, _) = self.column(p, 0);
        (m, ts)
    }

    /// Every pixel with a range, in packet order: (row, column, range mm, timestamp,
    /// signal).
    fn pixels(&self, p: &PacketView, mut each: impl FnMut(usize, usize, u32, u64, u16)) {
        let h = self.meta.pixels_per_column;
        let mask = match self.meta.profile {
            Profile::Legacy => 0xF_FFFF,
            Profile::Single => 0x7_FFFF,
        };
        let (start, end) = self.meta.column_window;
        for c in 0..self.meta.columns_per_packet {
            let (ts, m, valid) = self.column(p, c);
            let m = m as usize;
            let in_window = if start <= end {
                (start..=end).contains(&m)
            } else {
                m >= start || m <= end
            };
            if !valid || !in_window {
                continue;
            }
            let first = self.column_at(c)
                + if self.meta.profile == Profile::Legacy {
                    16
                } else {
                    12
                };
            for row in 0..h {
                let at = first + row * 12;
                let b = &p.bytes[at..at + 12];
                let range = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) & mask;
                if range == 0 {
                    continue;
                }
                let signal = u16::from_le_bytes([b[6], b[7]]);
                each(row, m, range, ts, signal);
            }
        }
    }

    /// How many returns [`Decoder::decode`] gives for a checked packet.
    pub fn count(&self, p: &PacketView) -> usize {
        let mut n = 0;
        self.pixels(p, |_, _, _, _, _| n += 1);
        n
    }

    /// Decodes a checked packet's returns, column by column, top beam first.
    pub fn decode(&self, p: &PacketView, mut sink: impl FnMut(Return)) {
        let w = self.meta.columns_per_frame;
        self.pixels(p, |row, m, range, ts, signal| {
            let i = row * w + m;
            let (d, o) = (self.direction[i], self.offset[i]);
            let r = range as f64;
            sink(Return {
                x: (r * d[0] + o[0]) as f32,
                y: (r * d[1] + o[1]) as f32,
                z: (r * d[2] + o[2]) as f32,
                intensity: signal as f32,
                row: row as u16,
                column: m as u16,
                time_ns: ts,
            });
        });
    }

    /// The returns a scan's packets decode to.
    pub fn count_scan(&self, scan: &ScanPackets) -> usize {
        scan.packets()
            .filter_map(|p| self.check(p).ok())
            .map(|p| self.count(&p))
            .sum()
    }

    /// Decodes a scan's returns in packet order.
    pub fn decode_scan(&self, scan: &ScanPackets, mut sink: impl FnMut(Return)) {
        for bytes in scan.packets() {
            if let Ok(p) = self.check(bytes) {
                self.decode(&p, &mut sink);
            }
        }
    }
}

/// Gathers an Ouster sensor's packets into frames: a frame ends with the packet that holds
/// the last column of the column window, or when a packet of another frame arrives. Lost
/// packets are counted from gaps in the column sequence (frame id × columns per frame +
/// measurement id), late ones when it runs back.
#[derive(Debug)]
pub struct Assembler {
    current: ScanPackets,
    frame: Option<u16>,
    /// The frame last completed: its late packets are counted, not made a scan.
    finished: Option<u16>,
    /// The previous packet's column position (frame id, first measurement id).
    previous: Option<(u16, u16)>,
    counters: PacketCounters,
    columns_per_frame: usize,
    columns_per_packet: usize,
    last_column: usize,
}

impl Assembler {
    /// An assembler for packets the decoder checks.
    pub fn new(meta: &Metadata) -> Self {
        Self {
            current: ScanPackets::default(),
            frame: None,
            finished: None,
            previous: None,
            counters: PacketCounters::default(),
            columns_per_frame: meta.columns_per_frame,
            columns_per_packet: meta.columns_per_packet,
            last_column: meta.column_window.1,
        }
    }

    /// The counters so far.
    pub fn counters(&self) -> &PacketCounters {
        &self.counters
    }

    /// Adds a checked packet; true when `out` holds a complete frame.
    pub fn push(
        &mut self,
        decoder: &Decoder,
        packet: &PacketView,
        bytes: &[u8],
        host_ns: u64,
        now_ns: u64,
        out: &mut ScanPackets,
    ) -> bool {
        let (m, ts) = decoder.first_column(packet);
        if self.count_gaps(packet.frame_id, m) {
            return false;
        }
        let mut complete = false;
        if self.frame.is_some_and(|f| f != packet.frame_id) && !self.current.is_empty() {
            self.current.hand_over(now_ns, out);
            complete = true;
        }
        self.frame = Some(packet.frame_id);
        self.current.push(bytes, host_ns, ts);
        self.counters.packets += 1;
        let last = m as usize + self.columns_per_packet - 1;
        if !complete && (m as usize..=last).contains(&self.last_column) {
            self.current.hand_over(now_ns, out);
            self.finished = Some(packet.frame_id);
            self.frame = None;
            return true;
        }
        complete
    }

    /// The packets gathered since the last frame, as a last, partial one (false: none).
    pub fn flush(&mut self, now_ns: u64, out: &mut ScanPackets) -> bool {
        if self.current.is_empty() {
            return false;
        }
        self.current.hand_over(now_ns, out);
        self.frame = None;
        true
    }

    /// Counts lost and late packets; true if this one is late (and left out).
    fn count_gaps(&mut self, frame: u16, m: u16) -> bool {
        let w = self.columns_per_frame as i64;
        let cpp = self.columns_per_packet as i64;
        if let Some((pf, pm)) = self.previous {
            // Frames apart (the id wraps at 2^16), then columns apart.
            let frames = frame.wrapping_sub(pf) as i16 as i64;
            let advance = frames * w + m as i64 - pm as i64;
            if advance <= 0 || self.finished == Some(frame) && self.frame != Some(frame) {
                self.counters.out_of_order += 1;
                self.counters.lost = self.counters.lost.saturating_sub(1);
                return true;
            }
            if advance > cpp {
                self.counters.lost += ((advance - cpp) / cpp) as u64;
            }
        }
        self.previous = Some((frame, m));
        false
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn metadata_json(profile: &str) -> String {
        let altitude: Vec<f64> = (0..16).map(|k| 15.0 - 2.0 * k as f64).collect();
        let azimuth: Vec<f64> = (0..16).map(|k| [3.0, 1.0, -1.0, -3.0][k % 4]).collect();
        serde_json::json!({
            "sensor_info": {"prod_line": "OS-1-16"},
            "beam_intrinsics": {
                "beam_altitude_angles": altitude,
                "beam_azimuth_angles": azimuth,
                "lidar_origin_to_beam_origin_mm": 12.163
            },
            "lidar_intrinsics": {"lidar_to_sensor_transform":
                [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1]},
            "lidar_data_format": {"columns_per_frame": 512, "columns_per_packet": 16,
                "pixels_per_column": 16, "udp_profile_lidar": profile}
        })
        .to_string()
    }

    /// A packet of columns `m0..m0+16` of `frame`, every pixel at `range_mm`.
    fn packet(meta: &Metadata, frame: u16, m0: u16, range_mm: u32) -> Vec<u8> {
        let legacy = meta.profile == Profile::Legacy;
        let mut p = Vec::new();
        if !legacy {
            p.extend_from_slice(&1u16.to_le_bytes());
            p.extend_from_slice(&frame.to_le_bytes());
            p.resize(32, 0);
        }
        for c in 0..meta.columns_per_packet as u16 {
            p.extend_from_slice(&(1_000 + u64::from(m0 + c)).to_le_bytes());
            p.extend_from_slice(&(m0 + c).to_le_bytes());
            if legacy {
                p.extend_from_slice(&frame.to_le_bytes());
                p.extend_from_slice(&0u32.to_le_bytes());
            } else {
                p.extend_from_slice(&1u16.to_le_bytes());
            }
            for _ in 0..meta.pixels_per_column {
                p.extend_from_slice(&range_mm.to_le_bytes());
                p.extend_from_slice(&[7, 0, 0x10, 0x00, 0, 0, 0, 0]);
            }
            if legacy {
                p.extend_from_slice(&[0xFF; 4]);
            }
        }
        if !legacy {
            p.resize(p.len() + 32, 0);
        }
        p
    }

    #[test]
    fn pixels_lie_on_the_range_sphere_with_the_beams_elevation() {
        for profile in ["LEGACY", "RNG19_RFL8_SIG16_NIR16"] {
            let meta = Metadata::from_json(&metadata_json(profile)).unwrap();
            let d = Decoder::new(meta.clone());
            let bytes = packet(&meta, 3, 128, 10_000);
            assert_eq!(bytes.len(), meta.packet_size());
            let p = d.check(&bytes).unwrap();
            assert_eq!(p.frame_id, 3);
            let mut r = Vec::new();
            d.decode(&p, |x| r.push(x));
            assert_eq!((r.len(), d.count(&p)), (256, 256));
            for x in &r {
                // 10 m from the beam's origin, 12 mm off the axis and 36 mm up.
                let range = (x.x * x.x + x.y * x.y + (x.z - 0.036).powi(2)).sqrt();
                assert!((range - 10.0).abs() < 0.02, "{x:?}");
                let elevation = ((x.z - 0.036) / range).asin().to_degrees();
                assert!(
                    (elevation - (15.0 - 2.0 * x.row as f32)).abs() < 0.1,
                    "{x:?}"
                );
                assert_eq!(x.intensity, 16.0);
            }
            // Column 128 of 512 is a quarter turn: encoder 270°, the sensor frame turned
            // 180°, so the beam points along +y (left).
            assert!(r[0].y > 9.0 && r[0].x.abs() < 1.0, "{:?}", r[0]);
            assert_eq!((r[0].column, r[0].time_ns), (128, 1_128));
        }
    }

    #[test]
    fn frames_are_cut_at_their_last_column_and_gaps_counted() {
        let meta = Metadata::from_json(&metadata_json("RNG19_RFL8_SIG16_NIR16")).unwrap();
        let d = Decoder::new(meta.clone());
        let mut a = Assembler::new(&meta);
        let mut out = ScanPackets::default();
        let mut sizes = Vec::new();
        // Frames 7 and 8 (32 packets each), starting mid-frame; packet 40 lost; one late.
        let mut order: Vec<u16> = (10..64).filter(|&k| k != 40).collect();
        order.insert(20, 15);
        for k in order {
            let bytes = packet(&meta, 7 + k / 32, (k % 32) * 16, 5_000);
            let p = d.check(&bytes).unwrap();
            if a.push(&d, &p, &bytes, 0, 0, &mut out) {
                sizes.push(out.len());
            }
        }
        assert_eq!(sizes, [22, 31]);
        let c = a.counters();
        assert_eq!((c.lost, c.out_of_order, c.packets), (1, 1, 53));
    }

    #[test]
    fn metadata_faults_are_named() {
        assert!(
            Metadata::from_json("{}")
                .unwrap_err()
                .contains("lidar_data_format")
        );
        let e = Metadata::from_json(&metadata_json("RNG15_RFL8_NIR8")).unwrap_err();
        assert!(
            e.contains("RNG15_RFL8_NIR8") && e.contains("not read yet"),
            "{e}"
        );
        let bad =
            metadata_json("LEGACY").replace("\"pixels_per_column\":16", "\"pixels_per_column\":32");
        assert!(
            Metadata::from_json(&bad)
                .unwrap_err()
                .contains("for 32 beams")
        );
        let e = Metadata::read(Path::new("/nonexistent/meta.json"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("meta.json"), "{e}");
    }

    proptest! {
        /// Any bytes, or a good packet damaged: a named error or finite returns, the count
        /// equal to what is decoded, never a panic.
        #[test]
        fn any_bytes_are_refused_or_decoded(
            legacy in any::<bool>(),
            bytes in prop::collection::vec(any::<u8>(), 0..3000),
            noise in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..64),
        ) {
            let meta = Metadata::from_json(&metadata_json(if legacy { "LEGACY" } else { "RNG19_RFL8_SIG16_NIR16" })).unwrap();
            let d = Decoder::new(meta.clone());
            let mut damaged = packet(&meta, 1, 64, 3_000);
            for (at, b) in noise {
                let i = at.index(damaged.len());
                damaged[i] = b;
            }
            for bytes in [bytes, damaged] {
                if let Ok(p) = d.check(&bytes) {
                    let mut n = 0;
                    d.decode(&p, |r| {
                        n += 1;
                        assert!(r.x.is_finite() && r.y.is_finite() && r.z.is_finite());
                        assert!((r.x * r.x + r.y * r.y).sqrt() < 1_100.0);
                    });
                    prop_assert_eq!(n, d.count(&p));
                }
            }
        }
    }
}
