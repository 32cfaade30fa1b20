//! groundwork-eval: metrics, the SemanticKITTI protocols of both papers, and the runner
//! that segments a sequence folder and scores it; object proposals against instance labels;
//! the whole configuration of a run (every method's section).

pub mod methods_config;
pub mod metrics;
pub mod objects;
pub mod sequence;

pub use methods_config::{
    MethodsConfig, load_methods_config_layers, load_methods_config_over, parse_methods_config,
};
pub use metrics::{Confusion, Metrics, Protocol};
pub use objects::{ObjectMatch, ObjectScore, score_objects};
pub use sequence::{
    EvalReport, ScanResult, Sequence, SequenceError, evaluate, median, side_by_side,
};
