//! groundwork-eval: metrics, the SemanticKITTI protocols of both papers, and the runner
//! that segments a sequence folder and scores it; object proposals against instance labels.

pub mod metrics;
pub mod objects;
pub mod sequence;

pub use metrics::{Confusion, Metrics, Protocol};
pub use objects::{ObjectMatch, ObjectScore, score_objects};
pub use sequence::{
    EvalReport, ScanResult, Sequence, SequenceError, evaluate, median, side_by_side,
};
