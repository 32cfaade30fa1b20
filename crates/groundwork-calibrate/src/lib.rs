//! groundwork-calibrate: fit groundwork to a new sensor from its raw scans, without labels.
//!
//! - [`mount`]: the sensor's height, roll and pitch above the ground, by ground-plane
//!   consensus ([`plane`]) over many scans, with the spread across scans as confidence and a
//!   refusal (with the reason) when the scans cannot determine it.
//! - [`params`]: with the mount fixed, the segmenter's likelihood parameters and ground
//!   threshold fitted to reference labels, judged on held-out scans; [`pseudo`]: that fit
//!   on the PseudoLabeler's labels of a sample of the scans, whole.
//! - [`zones`]: the zone model's near edge, from where the sensor first sees ground on the
//!   mount found, and its inner boundaries scaled with the height found where the layout
//!   follows the beams (`zones.scale_with_height`).
//!
//! - [`calibrate`]: all of it in order, as `groundwork calibrate` and Python's
//!   `groundwork.calibrate` run it; [`Calibration::to_toml`] is the file it writes.
//!
//! Pure algorithm: the caller reads the scans and writes the file.

#![warn(missing_docs)]

pub mod calibration;
pub mod mount;
pub mod params;
pub mod plane;
pub mod pseudo;
mod text;
pub mod zones;

pub use calibration::{
    CalibrateOptions, CalibrateProgress, Calibration, NearEdge, ScanInput, ScanReport, calibrate,
};
pub use mount::{
    MountEstimate, MountSearchConfig, OneSidedGround, combine, estimate_mount, frame_mount,
};
pub use params::{
    Agreement, GroundChange, GroundValue, LabeledScan, ParamFit, ParamSearchConfig, RoundScore,
    fit_parameters, ground_changes,
};
pub use plane::{NoGround, PlaneFit, PlaneSearchConfig, Surface, ground_plane};
pub use pseudo::{FitProgress, fit_to_pseudo_labels};
pub use zones::{
    HEIGHT_SCALE_DEAD_BAND, HeightScale, MountZones, NearEdgeConfig, NearGround,
    combine_near_ground, near_ground, scan_near_ground, view_near_ground, zones_for_mount,
    zones_scaled_to_height, zones_with_near_edge,
};

/// Why a calibration could not be done.
#[derive(Debug, Clone, thiserror::Error)]
pub enum CalibrateError {
    /// A setting is out of its range.
    #[error("calibration setting {0}")]
    Config(String),
    /// The scans cannot determine what was asked (no flat ground, too few scans, scans that
    /// disagree): the reason.
    #[error("cannot calibrate: {0}")]
    Refused(String),
}

impl CalibrateError {
    /// The message without "cannot calibrate" for a refusal: for a step after the mount
    /// (the parameter fit), whose refusal leaves the mount calibrated.
    pub fn reason(&self) -> String {
        match self {
            Self::Refused(why) => why.clone(),
            e => e.to_string(),
        }
    }
}
