//! groundwork-msg: the messages every groundwork process exchanges, and nothing else.
//!
//! iceoryx2 identifies a payload type by its full path, so these types must be defined in
//! exactly one crate that every process links: this one. All are `#[repr(C)]` and
//! `ZeroCopySend`; they live in shared memory and are read in place.
//!
//! Topics (service names are `<prefix>/scans`, `<prefix>/masks`):
//! - `scans`: payload `[ScanPoint]`, user header [`ScanHeader`];
//! - `masks`: payload `[f32]` (ground probability per point, scan order), header
//!   [`MaskHeader`];
//! - `proposals`: payload `[u32]` (the detector's proposal id per point, scan order, 0 for
//!   none), header [`ProposalsHeader`] with up to [`MAX_PROPOSALS`] fixed-size
//!   [`ProposalRecord`]s.
//!
//! A message is a `#[repr(C)]` header and a slice, written in place into iceoryx2's shared
//! memory. Every header starts with [`SCHEMA_VERSION`]: a reader refuses (and counts) a
//! message of another layout, and any change of a layout bumps it.
//!
//! ```
//! use groundwork_msg::{MaskHeader, MaskStatus, SCHEMA_VERSION, ScanHeader, ScanPoint};
//!
//! let scan = ScanHeader { sequence: 7, point_count: 2, ..ScanHeader::default() };
//! assert_eq!(scan.schema_version, SCHEMA_VERSION);
//! assert_eq!(scan.has_pose, 0, "no pose unless one is set");
//! let points = [ScanPoint { x: 5.0, y: 0.0, z: -1.7, intensity: 0.3 }; 2];
//! let mask = MaskHeader { scan_sequence: scan.sequence, point_count: points.len() as u32, ..MaskHeader::default() };
//! assert_eq!(mask.status, MaskStatus::OK);
//! // 16 bytes per point: the KITTI .bin layout, copied into shared memory as it is.
//! assert_eq!(std::mem::size_of_val(&points), 32);
//! ```

#![warn(missing_docs)]

use iceoryx2::prelude::ZeroCopySend;

/// Bumped on every incompatible change of a header or payload layout.
pub const SCHEMA_VERSION: u32 = 4;

/// One LiDAR return, 16 bytes, the KITTI `.bin` layout.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
pub struct ScanPoint {
    /// Forward, metres (sensor frame).
    pub x: f32,
    /// Left, metres.
    pub y: f32,
    /// Up, metres.
    pub z: f32,
    /// Intensity.
    pub intensity: f32,
}

impl From<&ScanPoint> for groundwork_core::Point {
    fn from(p: &ScanPoint) -> Self {
        Self {
            x: p.x,
            y: p.y,
            z: p.z,
            intensity: p.intensity,
        }
    }
}

impl From<groundwork_core::Point> for ScanPoint {
    fn from(p: groundwork_core::Point) -> Self {
        Self {
            x: p.x,
            y: p.y,
            z: p.z,
            intensity: p.intensity,
        }
    }
}

/// Lets the segmenter read scans in place, straight from shared memory.
impl groundwork_core::PointXyz for ScanPoint {
    #[inline]
    fn xyz(&self) -> [f32; 3] {
        [self.x, self.y, self.z]
    }
}

/// Monotonic timestamps (ns, `CLOCK_MONOTONIC`, comparable across processes on one
/// machine) written by each stage; 0 = not reached.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
pub struct StageStamps {
    /// Producer, just before the loan is filled (the scan "exists").
    pub produced_ns: u64,
    /// Producer, just before `send`.
    pub published_ns: u64,
    /// Segmenter, on receipt.
    pub segmenter_received_ns: u64,
    /// Segmenter, just before sending the mask.
    pub segmenter_published_ns: u64,
}

/// A coordinate frame name (ROS `header.frame_id`), NUL-padded UTF-8 of at most 63 bytes.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
pub struct FrameId {
    bytes: [u8; 64],
}

impl Default for FrameId {
    fn default() -> Self {
        Self { bytes: [0; 64] }
    }
}

impl FrameId {
    /// `name`, cut at a character boundary to 63 bytes (frame names are short: `velodyne`,
    /// `os_sensor`, `livox_frame`); names with a NUL end there.
    pub fn new(name: &str) -> Self {
        let name = name.split('\0').next().unwrap_or("");
        let mut end = name.len().min(63);
        while !name.is_char_boundary(end) {
            end -= 1;
        }
        let mut bytes = [0; 64];
        bytes[..end].copy_from_slice(&name.as_bytes()[..end]);
        Self { bytes }
    }

    /// The name; `None` if empty (unknown) or not UTF-8 (a corrupted header).
    pub fn get(&self) -> Option<&str> {
        let len = self.bytes.iter().position(|&b| b == 0).unwrap_or(64);
        std::str::from_utf8(&self.bytes[..len])
            .ok()
            .filter(|s| !s.is_empty())
    }
}

/// Header of a scan message.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
pub struct ScanHeader {
    /// Must equal [`SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Points in the payload (must equal the slice length).
    pub point_count: u32,
    /// Producer's sequence number, strictly increasing per producer run.
    pub sequence: u64,
    /// Identifies the producer run (changes when a producer restarts).
    pub producer_epoch: u64,
    /// Sensor timestamp (ns, sensor clock).
    pub sensor_timestamp_ns: u64,
    /// Index of the scan in its source (file index for replays), for label lookup.
    pub source_index: u64,
    /// Stage timestamps.
    pub stamps: StageStamps,
    /// 1 if `pose` holds the sensor's world pose, 0 for "no pose".
    pub has_pose: u32,
    /// Where the scan came from (also keeps `pose` 8-byte aligned).
    pub source: ScanSource,
    /// World from sensor, 4×4 row-major.
    pub pose: [f64; 16],
    /// The scan's coordinate frame, where its source names one.
    pub frame_id: FrameId,
}

impl Default for ScanHeader {
    fn default() -> Self {
        Self {
            schema_version: SCHEMA_VERSION,
            point_count: 0,
            sequence: 0,
            producer_epoch: 0,
            sensor_timestamp_ns: 0,
            source_index: 0,
            stamps: StageStamps::default(),
            has_pose: 0,
            source: ScanSource::PRODUCER,
            pose: IDENTITY,
            frame_id: FrameId::default(),
        }
    }
}

const IDENTITY: [f64; 16] = [
    1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
];

/// The stage that published a scan.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, ZeroCopySend)]
pub struct ScanSource(pub u32);

impl ScanSource {
    /// The producer (files, recordings, synthetic scans).
    pub const PRODUCER: Self = Self(0);
    /// The ROS 2 bridge (a PointCloud2 from DDS).
    pub const ROS2: Self = Self(1);
    /// The producer, decoding a sensor's packets (live or from a capture).
    pub const PACKETS: Self = Self(2);
}

/// Outcome of segmenting a scan: 0 = segmented, anything else names why the scan was
/// rejected (the mask then has no payload).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, ZeroCopySend)]
pub struct MaskStatus(pub u32);

impl MaskStatus {
    /// Segmented; the payload holds one probability per point.
    pub const OK: Self = Self(0);
    /// `schema_version` differs from [`SCHEMA_VERSION`].
    pub const BAD_SCHEMA: Self = Self(1);
    /// `point_count` differs from the payload length.
    pub const COUNT_MISMATCH: Self = Self(2);
    /// No points.
    pub const EMPTY: Self = Self(3);
    /// More points than the segmenter accepts.
    pub const TOO_MANY_POINTS: Self = Self(4);
    /// A NaN or infinite coordinate.
    pub const NON_FINITE: Self = Self(5);
    /// Any other rejection (e.g. an invalid pose).
    pub const OTHER: Self = Self(6);

    /// Short name for logs and reports.
    pub fn name(self) -> &'static str {
        match self.0 {
            0 => "ok",
            1 => "bad_schema",
            2 => "count_mismatch",
            3 => "empty",
            4 => "too_many_points",
            5 => "non_finite",
            _ => "other",
        }
    }
}

/// Header of a mask message.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
pub struct MaskHeader {
    /// Must equal [`SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Values in the payload.
    pub point_count: u32,
    /// Sequence number of the scan this mask answers.
    pub scan_sequence: u64,
    /// Producer epoch of that scan.
    pub producer_epoch: u64,
    /// The scan's sensor timestamp.
    pub sensor_timestamp_ns: u64,
    /// The scan's source index.
    pub source_index: u64,
    /// The scan's stamps, completed by the segmenter.
    pub stamps: StageStamps,
    /// Segmented or why not.
    pub status: MaskStatus,
    /// Points at or above the ground threshold.
    pub ground_points: u32,
    /// Models queried (1 = single frame).
    pub frames_queried: u32,
    /// Fit time, µs.
    pub fit_us: u32,
    /// Query time, µs.
    pub query_us: u32,
    /// Points beyond the segmenter's coordinate bound (corrupted returns): probability 0.
    pub out_of_bounds_points: u32,
    /// Identifies the segmenter run (changes when a segmenter restarts).
    pub segmenter_epoch: u64,
    /// Masks this segmenter run published before this one (0, 1, 2, …): a gap is a mask
    /// lost on the way, while a gap in `scan_sequence` may be a scan the segmenter never
    /// received.
    pub mask_sequence: u64,
    /// The scan's coordinate frame.
    pub frame_id: FrameId,
    /// 1 if `mount` holds the mount the scan was segmented with, 0 for none (a writer
    /// that does not know it): a stage that works in the ground-aligned frame follows it,
    /// so that it stays with a segmenter that corrects its mount (`mount_check.mode`).
    pub has_mount: u32,
    /// Zero (keeps `mount` 8-byte aligned).
    pub reserved: u32,
    /// Ground-aligned frame from sensor, 4×4 row-major.
    pub mount: [f64; 16],
}

impl Default for MaskHeader {
    fn default() -> Self {
        Self {
            schema_version: SCHEMA_VERSION,
            point_count: 0,
            scan_sequence: 0,
            producer_epoch: 0,
            sensor_timestamp_ns: 0,
            source_index: 0,
            stamps: StageStamps::default(),
            status: MaskStatus::OK,
            ground_points: 0,
            frames_queried: 0,
            fit_us: 0,
            query_us: 0,
            out_of_bounds_points: 0,
            segmenter_epoch: 0,
            mask_sequence: 0,
            frame_id: FrameId::default(),
            has_mount: 0,
            reserved: 0,
            mount: IDENTITY,
        }
    }
}

/// Proposals one message carries; farther ones are dropped (counted in the header, and
/// their points' ids published as 0). A street scan holds 100–200.
pub const MAX_PROPOSALS: usize = 512;

/// One object proposal (the detector crate's `Proposal`, flattened): ground-aligned sensor frame,
/// metres, radians.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
pub struct ProposalRecord {
    /// 1, 2, … nearest first: the id its points carry in the payload.
    pub id: u32,
    /// Points in the cluster.
    pub points: u32,
    /// The detector's `ProposalFlags` bits (0: object-like).
    pub flags: u32,
    /// Local ground height below the box centre.
    pub ground_z: f32,
    /// Mean of the points.
    pub centroid: [f32; 3],
    /// Box centre in the ground plane.
    pub center: [f32; 2],
    /// Heading of the box's long side, (−π/2, π/2].
    pub yaw: f32,
    /// Long side.
    pub length: f32,
    /// Short side.
    pub width: f32,
    /// Lowest point above the local ground.
    pub bottom: f32,
    /// Highest point above the local ground.
    pub height: f32,
}

impl ProposalRecord {
    /// The box's centre in the ground-aligned frame (`base_footprint`): over its ground
    /// point, midway between its lowest and highest point.
    pub fn box_center(&self) -> [f64; 3] {
        [
            f64::from(self.center[0]),
            f64::from(self.center[1]),
            f64::from(self.ground_z) + 0.5 * f64::from(self.bottom + self.height),
        ]
    }

    /// The box's extent: along its heading (`yaw`), across it, and up.
    pub fn box_size(&self) -> [f64; 3] {
        [
            f64::from(self.length),
            f64::from(self.width),
            f64::from(self.height - self.bottom),
        ]
    }

    /// The box's rotation, a turn by `yaw` about the vertical, as a unit quaternion
    /// (x, y, z, w).
    pub fn box_rotation(&self) -> [f64; 4] {
        let half = 0.5 * f64::from(self.yaw);
        [0.0, 0.0, half.sin(), half.cos()]
    }
}

/// Header of a proposals message.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
pub struct ProposalsHeader {
    /// Must equal [`SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Ids in the payload (the scan's points).
    pub point_count: u32,
    /// Sequence number of the scan.
    pub scan_sequence: u64,
    /// Producer epoch of that scan.
    pub producer_epoch: u64,
    /// The scan's sensor timestamp.
    pub sensor_timestamp_ns: u64,
    /// The scan's source index.
    pub source_index: u64,
    /// The mask's stamps (producer and segmenter).
    pub stamps: StageStamps,
    /// Detector, on receipt of the mask.
    pub detector_received_ns: u64,
    /// Detector, just before `send`.
    pub detector_published_ns: u64,
    /// Identifies the detector run (changes when a detector restarts).
    pub detector_epoch: u64,
    /// Detection time (ground removal, clustering, boxes), µs.
    pub detect_us: u32,
    /// Valid entries of `records`.
    pub proposal_count: u32,
    /// Proposals beyond [`MAX_PROPOSALS`] left out (farthest first).
    pub dropped_proposals: u32,
    /// Reserved, keeps `records` aligned.
    pub reserved: u32,
    /// The proposals, nearest first.
    pub records: [ProposalRecord; MAX_PROPOSALS],
}

impl Default for ProposalsHeader {
    fn default() -> Self {
        Self {
            schema_version: SCHEMA_VERSION,
            point_count: 0,
            scan_sequence: 0,
            producer_epoch: 0,
            sensor_timestamp_ns: 0,
            source_index: 0,
            stamps: StageStamps::default(),
            detector_received_ns: 0,
            detector_published_ns: 0,
            detector_epoch: 0,
            detect_us: 0,
            proposal_count: 0,
            dropped_proposals: 0,
            reserved: 0,
            records: [ProposalRecord::default(); MAX_PROPOSALS],
        }
    }
}

impl ProposalsHeader {
    /// The valid records.
    pub fn proposals(&self) -> &[ProposalRecord] {
        &self.records[..(self.proposal_count as usize).min(MAX_PROPOSALS)]
    }
}

/// `CLOCK_MONOTONIC` in ns: the one clock all stages stamp with.
pub fn monotonic_ns() -> u64 {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::Monotonic);
    t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64
}

/// The wall clock in ns since 1970 (the monotonic clock if the wall clock is before it).
pub fn wall_clock_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or_else(|_| monotonic_ns())
}

/// A run identifier: wall-clock ns at start, distinct across restarts.
pub fn new_epoch() -> u64 {
    wall_clock_ns()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_ids_keep_short_names_and_cut_long_ones_at_a_character() {
        assert_eq!(FrameId::new("velodyne").get(), Some("velodyne"));
        assert_eq!(FrameId::new("").get(), None);
        assert_eq!(FrameId::default().get(), None);
        assert_eq!(FrameId::new("a\0b").get(), Some("a"));
        let long = "é".repeat(40); // 80 bytes
        let cut = FrameId::new(&long);
        assert_eq!(cut.get(), Some("é".repeat(31).as_str())); // 62 bytes
        // A corrupted header (bytes that are not UTF-8) is no name, not a panic.
        let mut bad = FrameId::new("ok");
        bad.bytes[0] = 0xff;
        assert_eq!(bad.get(), None);
    }

    #[test]
    fn layouts_are_stable() {
        assert_eq!(std::mem::size_of::<ScanPoint>(), 16);
        assert_eq!(std::mem::size_of::<StageStamps>(), 32);
        assert_eq!(std::mem::align_of::<ScanHeader>(), 8);
        // 4 + 4 + 8 × 4 + 32 + 4 + 4 + 128 + 64 (frame id)
        assert_eq!(std::mem::size_of::<ScanHeader>(), 272);
        assert_eq!(ScanHeader::default().schema_version, SCHEMA_VERSION);
        // 4 + 4 + 8 × 4 + 32 + 4 × 6 + 8 × 2 + 64 (frame id) + 4 + 4 + 128 (mount)
        assert_eq!(std::mem::size_of::<MaskHeader>(), 312);
        assert_eq!(std::mem::size_of::<ProposalRecord>(), 56);
        assert_eq!(
            std::mem::size_of::<ProposalsHeader>(),
            4 + 4 + 8 * 4 + 32 + 8 * 3 + 4 * 4 + 56 * MAX_PROPOSALS
        );
    }

    #[test]
    fn monotonic_clock_advances() {
        let a = monotonic_ns();
        let b = monotonic_ns();
        assert!(b >= a && a > 0);
    }
}
