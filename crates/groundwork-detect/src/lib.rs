//! groundwork-detect: the fallback detector of TerraSeg's "implicit pipeline" (§1): ground
//! segmentation, then spatial clustering of what is left, gives class-agnostic object
//! proposals — the fallback when a learned detector fails or meets an object it was never
//! trained on.
//!
//! Per scan ([`Detector::detect`]): the points move into the sensor's ground-aligned frame
//! (x forward, y left, z up, origin on the ground below the sensor); a local ground height
//! map is built from the ground points; non-ground points between `min_height` and
//! `max_height` above it are clustered by Euclidean distance on a bird's-eye grid of
//! vertical column segments ([`cluster`]); uncertain ground points touching a cluster join
//! it; each cluster becomes a [`Proposal`] with an oriented box ([`bbox`]), and every
//! point gets its proposal's id (0: none).
//!
//! Pure algorithm: no I/O, no IPC. Deterministic: the same output on any number of
//! threads (the passes over the scan, the clustering's halves and bands and the boxes run
//! on rayon's pool).

pub mod bbox;
pub mod cluster;
pub mod config;
mod detector;
mod grid;
mod ground_map;

pub use config::DetectorConfig;
pub use detector::{DetectError, DetectionReport, Detections, Detector, Proposal, ProposalFlags};
