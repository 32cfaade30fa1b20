//! groundwork-pseudolabel: ground labels for raw scans without a trained model.
//!
//! - [`PseudoLabeler`]: TerraSeg's PseudoLabeler (Lentsch et al., §3.3): per scan, an MLP
//!   elevation map g(x, y) fitted by runtime optimisation of an asymmetric loss, then
//!   labels z − g ≤ D refined per pillar. Offline: slow, accurate, sensor-agnostic.
//! - [`Ransac`]: the plane baseline of both papers' tables.
//!
//! Pure algorithm: no I/O, no IPC. Both are deterministic for their seed on any number of
//! threads.

pub mod config;
pub mod labeler;
mod method;
pub mod mlp;
mod prob;
pub mod ransac;

pub use config::{PseudoLabelerConfig, RansacConfig};
pub use groundwork_core::frame::GroundFrame;
pub use labeler::{FitReport, PseudoLabeler};
pub use ransac::{Ransac, RansacReport};
