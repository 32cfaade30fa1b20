//! Synthetic LiDAR sequences with exact labels.
//!
//! A sensor's beam pattern ([`BeamPattern`]: elevations and azimuth steps of a spinning
//! sensor, or a solid-state rosette) is ray-cast from a vehicle driving a turning path
//! over a procedural [`Scene`] (terrain with curbs, ramps and hills; cars, people, poles,
//! buildings, vegetation), then given the sensor's errors (range noise, dropouts, foliage
//! penetration, multipath echoes below the ground, no-return placeholders). Every point
//! carries its SemanticKITTI class and object instance; every frame its sensor pose.
//!
//! Pure: no I/O. Deterministic for a seed, on any number of threads.

pub mod classes;
mod generate;
mod pattern;
mod scene;
mod shapes;

pub use generate::{Generator, SynthConfig, SynthScan};
pub use pattern::{BeamPattern, EgoBody, PATTERN_SENSORS, Scanning};
pub use scene::{Object, Scene, SceneKind, Surface};
pub use shapes::Shape;

/// Why a sequence cannot be generated.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// No beam pattern for this sensor.
    #[error("no beam pattern for sensor {0:?} (known: {known})", known = PATTERN_SENSORS.join(", "))]
    UnknownSensor(String),
    /// A parameter is out of range.
    #[error("invalid synthetic sequence: {0}")]
    Invalid(String),
}
