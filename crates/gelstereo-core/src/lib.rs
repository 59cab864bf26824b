//! Types shared by every gelstereo crate: markers in an image, their grid identity, stereo pairs,
//! and the per-frame tables other tools read.
//!
//! # Conventions
//! - Image coordinates are pixels of the ORIGINAL image (never of a resized network input), OpenCV /
//!   mrcal convention: (0, 0) is the centre of the top-left pixel, x right, y down.
//! - Camera frame: x right, y down, z forward. The reference 3-D frame is the LEFT camera's.
//!   Units: mm for 3-D, px for images, s or ms for time; the unit is part of the name (`depth_mm`).
//! - Stereo extrinsics as OpenCV `stereoCalibrate` gives them, `p_in_right = R * p_in_left + T`,
//!   named `right_from_left` in code.
//! - Marker identity is its grid index (row, col) on the reference frame of the LEFT view: row grows
//!   with y, col grows with x, (0, 0) top-left. Ids are deterministic: anything that comes out of a
//!   hash map is sorted first.
//! - Geometry in f64, network tensors in f32.

pub mod files;
mod grid;
pub mod interrupt;
pub mod limits;
mod marker;
pub mod spatial;
pub mod stats;
pub mod table;
#[doc(hidden)]
pub mod testing;

pub use grid::{GridIndex, GridShape};
pub use marker::{Detection, ImageSize, MarkerStatus, Point2, SlipState, StereoPair, TieredDetections, View};
pub use table::{CsvTable, FrameSummary, MarkerRecord};

/// Errors of the shared types: parsing names and table files.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A word that should name one of a fixed set of values did not.
    #[error("unknown {what} '{found}': expected one of {expected}")]
    UnknownName {
        /// What kind of value was being parsed (e.g. "slip state").
        what: &'static str,
        /// The text that was read.
        found: String,
        /// The accepted words, comma separated.
        expected: &'static str,
    },
    /// A table file has a header or cell that does not follow its contract.
    #[error("{path}:{line}: column '{column}': expected {expected}, found '{found}'")]
    Table {
        /// The file (or stream name) being read.
        path: String,
        /// 1-based line number.
        line: usize,
        /// The column name.
        column: String,
        /// What the contract expects there.
        expected: String,
        /// What was found.
        found: String,
    },
    /// Reading or writing a table failed at the OS level.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
}

/// Result with the core [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;
