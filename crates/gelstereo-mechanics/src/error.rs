//! Errors of the contact mechanics.

/// What can go wrong.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A fact or setting out of its range.
    #[error("{field}: expected {expected}, found {found}")]
    Invalid {
        /// The field, as a user names it.
        field: &'static str,
        /// What was expected.
        expected: String,
        /// What was found.
        found: String,
    },
    /// Fields of different sizes.
    #[error("{what}: expected {expected}, found {found}")]
    Mismatch {
        /// What disagrees.
        what: &'static str,
        /// What was expected.
        expected: String,
        /// What was found.
        found: String,
    },
}

/// The error of a fact or setting `field` that is not `expected`.
pub(crate) fn invalid(field: &'static str, expected: &str, found: impl std::fmt::Display) -> Error {
    Error::Invalid {
        field,
        expected: expected.to_owned(),
        found: found.to_string(),
    }
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, Error>;
