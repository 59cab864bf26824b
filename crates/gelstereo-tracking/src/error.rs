//! The tracking crate's error type.

use gelstereo_core::{GridIndex, GridShape};

/// Errors of tracking, displacement fields, contact geometry and slip detection. Each names the
/// input or setting concerned and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A configuration field is out of its valid range.
    #[error("tracking config '{field}': expected {expected}, found {found}")]
    Config {
        /// The field, e.g. `gate_pitch`.
        field: &'static str,
        /// The valid range.
        expected: String,
        /// The value given.
        found: String,
    },
    /// The reference frame cannot start a track: too few markers or duplicated ids.
    #[error("reference frame: expected {expected}, found {found}")]
    Reference {
        /// What a reference frame needs.
        expected: String,
        /// What it has.
        found: String,
    },
    /// A grid index lies outside the lattice.
    #[error("marker {index} lies outside the {}x{} lattice", shape.rows, shape.cols)]
    IndexOutside {
        /// The index.
        index: GridIndex,
        /// The lattice.
        shape: GridShape,
    },
    /// Two inputs that must describe the same markers or frames disagree in size.
    #[error("{what}: expected {expected}, found {found}")]
    Mismatch {
        /// Which inputs disagree.
        what: &'static str,
        /// The expected count or size.
        expected: String,
        /// What was given.
        found: String,
    },
    /// A line of the frame stream that is not a frame: names the stream and line, the field and
    /// what was expected.
    #[error("{0}")]
    Stream(String),
    /// The gel's facts or the contact mechanics' settings.
    #[error("gel mechanics: {0}")]
    Mechanics(#[from] gelstereo_mechanics::Error),
    /// A coordinate is NaN or infinite.
    #[error("{what}: expected finite coordinates, found {found}")]
    NotFinite {
        /// Which input.
        what: String,
        /// The value.
        found: String,
    },
}

/// Result with the tracking [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

pub(crate) fn config_err(field: &'static str, expected: &str, found: impl std::fmt::Display) -> Error {
    Error::Config {
        field,
        expected: expected.to_owned(),
        found: found.to_string(),
    }
}
