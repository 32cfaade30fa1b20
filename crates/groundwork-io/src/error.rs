//! The one error type of the formats: every message names the file and the problem.

use std::path::{Path, PathBuf};

use thiserror::Error;

/// A file that could not be read or written, with the file named in the message.
#[derive(Debug, Error)]
pub enum FormatError {
    /// The operating system refused (missing file, permissions, disk full, …).
    ///
    /// The message carries the OS error; it is not also the error's `source`, or a report
    /// of the chain (anyhow's `{:#}`) would print it twice.
    #[error("{}: {cause}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        cause: std::io::Error,
    },
    /// The file's size does not fit its format: truncated or not that format.
    #[error("{}: {size} bytes is not a whole number of {record}-byte records (truncated, or not this format)", path.display())]
    Size {
        /// The file.
        path: PathBuf,
        /// Its size in bytes.
        size: u64,
        /// Bytes per record of the format.
        record: usize,
    },
    /// The file holds no points.
    #[error("{}: empty scan (0 points)", path.display())]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// A coordinate is NaN or infinite.
    #[error("{}: point {index} has a non-finite coordinate ({x}, {y}, {z})", path.display())]
    NonFinite {
        /// The file.
        path: PathBuf,
        /// Index of the first bad point.
        index: usize,
        /// Its coordinates.
        x: f32,
        /// Its coordinates.
        y: f32,
        /// Its coordinates.
        z: f32,
    },
    /// More points than the configured maximum.
    #[error("{}: {points} points, more than the configured maximum of {max}", path.display())]
    TooManyPoints {
        /// The file.
        path: PathBuf,
        /// Points in the file.
        points: usize,
        /// The maximum.
        max: usize,
    },
    /// A label file that does not match its scan.
    #[error("{}: {labels} labels, but the scan has {points} points", path.display())]
    LabelCount {
        /// The label file.
        path: PathBuf,
        /// Labels in it.
        labels: usize,
        /// Points in the scan.
        points: usize,
    },
    /// A text file with a malformed line.
    #[error("{}:{line}: {message}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// A configuration file that does not parse or does not validate.
    #[error("{}: {message}", path.display())]
    Config {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A file of a known format whose content is malformed (a lying header, a truncated
    /// body, a field that is missing or of the wrong type).
    #[error("{}: {message}", path.display())]
    Malformed {
        /// The file.
        path: PathBuf,
        /// What is wrong, and where.
        message: String,
    },
    /// A path that is not a regular file (a device, a FIFO, a socket, a folder).
    #[error("{}: {kind}, not a regular file: refused (only regular files are read)", path.display())]
    NotAFile {
        /// The path.
        path: PathBuf,
        /// What it is.
        kind: &'static str,
    },
    /// Outputs that would overwrite an input or each other.
    #[error("{}: {message}", path.display())]
    Collision {
        /// The output, or the first of two inputs.
        path: PathBuf,
        /// What collides with what.
        message: String,
    },
    /// A file kind this crate does not read.
    #[error("{}: unsupported file type (expected {expected})", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What would have been accepted.
        expected: &'static str,
    },
}

impl FormatError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            cause: source,
        }
    }

    pub(crate) fn malformed(path: &Path, message: impl Into<String>) -> Self {
        Self::Malformed {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }

    pub(crate) fn parse(path: &Path, line: usize, message: impl Into<String>) -> Self {
        Self::Parse {
            path: path.to_path_buf(),
            line,
            message: message.into(),
        }
    }
}
