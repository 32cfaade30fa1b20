//! groundwork-eval: the runner that segments a sequence and scores it against its labels,
//! per scan and pooled, with speed; object proposals against instance labels. The metrics
//! and the papers' protocols are `groundwork_io::metrics` (the service's consumer scores
//! with them too), the sequences `groundwork_io::Sequence`, the configuration
//! `groundwork_io::config`.

pub mod objects;
pub mod sequence;

// Defined beside the label classes (`groundwork_io::metrics`), shared with the service.
pub use groundwork_io::metrics::{Confusion, Metrics, Protocol};
pub use objects::{ObjectMatch, ObjectScore, score_objects};
pub use sequence::{EvalReport, ScanResult, SequenceError, evaluate, median, side_by_side};
