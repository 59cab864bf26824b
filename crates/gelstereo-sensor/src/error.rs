//! The one error type of this crate.

use std::path::{Path, PathBuf};

/// What can be wrong with a sensor description or a recording's `meta.json`: each error names the
/// file, the field and what was expected against what was found.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file that is not valid JSON or misses / misspells a field.
    #[error("{}: {message}", path.display())]
    SensorSyntax {
        /// The file.
        path: PathBuf,
        /// serde's message (field name, line and column).
        message: String,
    },
    /// A field holds a value outside its valid range.
    #[error("{source_name}: field '{field}': expected {expected}, found {found}")]
    SensorField {
        /// The file (or "built-in sensor").
        source_name: String,
        /// Dotted field path, e.g. `grid.pitch_mm`.
        field: String,
        /// What would be valid.
        expected: String,
        /// What was found.
        found: String,
    },
    /// Reading a file failed at the OS level.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error (in the message, not repeated as a cause).
        error: std::io::Error,
    },
    /// The gel's facts out of the contact mechanics' range.
    #[error("gel mechanics: {0}")]
    Mechanics(#[from] gelstereo_mechanics::Error),
    /// A camera of the description cannot be built.
    #[error(transparent)]
    Geometry(#[from] gelstereo_geometry::Error),
}

/// Result with this crate's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

pub(crate) fn io_err(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Error {
    let path = path.into();
    move |error| Error::Io { path, error }
}

/// The error of a JSON file (`path`) that does not parse into what was expected.
pub fn syntax(path: &Path, e: &serde_json::Error) -> Error {
    Error::SensorSyntax {
        path: path.to_owned(),
        message: e.to_string(),
    }
}

/// The error of a field of `path` holding a value outside its range.
pub fn field(path: &Path, name: &str, expected: &str, found: &str) -> Error {
    Error::SensorField {
        source_name: path.display().to_string(),
        field: name.to_owned(),
        expected: expected.to_owned(),
        found: found.to_owned(),
    }
}
