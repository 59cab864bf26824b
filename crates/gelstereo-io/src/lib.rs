//! Frame sources (image folders, stereo recordings, video files, cameras) and exports (CSV, JSON, PLY).
//!
//! Images are read as 8-bit BGR [`opencv::core::Mat`]s (OpenCV's channel order); pixel (0, 0) is the
//! centre of the top-left pixel, as everywhere in gelstereo.

pub mod atomic;
pub mod figures;
pub mod images;
pub mod ply;
pub mod video;

use std::path::PathBuf;

pub use atomic::AtomicFile;

/// Errors of frame sources and exports. Each names the file it concerns.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file or folder could not be read or written at the OS level.
    #[error("I/O error on {path}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error (the error's source: shown by `{:#}` / error chains).
        source: std::io::Error,
    },
    /// The file exists but is not an image OpenCV can decode (corrupt, truncated or another format).
    #[error(
        "{path}: cannot decode as an image (expected PNG, JPEG, BMP, TIFF or PNM; the file is corrupt or of another type)"
    )]
    Decode {
        /// The file.
        path: PathBuf,
    },
    /// A PNG or JPEG that ends before its end marker (cut short by a copy or a crash).
    #[error(
        "{path}: cannot decode: truncated image (the file ends before its PNG IEND chunk / JPEG end-of-image marker)"
    )]
    Truncated {
        /// The file.
        path: PathBuf,
    },
    /// An image or video frame larger than gelstereo reads (`gelstereo_core::limits`).
    #[error("{path}: {what}")]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size and the limits.
        what: String,
    },
    /// A video file could not be opened, or one of its frames could not be decoded.
    #[error("{path}: {what}")]
    Video {
        /// The video file.
        path: PathBuf,
        /// What went wrong, e.g. "cannot open as a video".
        what: String,
    },
    /// A folder does not have the layout expected of it (e.g. a stereo recording without `right/`).
    #[error("{path}: {what}")]
    Layout {
        /// The folder.
        path: PathBuf,
        /// What was expected and what was found.
        what: String,
    },
    /// A figure could not be drawn or written.
    #[error("{path}: cannot draw the figure: {what}")]
    Figure {
        /// The figure file.
        path: PathBuf,
        /// What went wrong.
        what: String,
    },
    /// OpenCV reported an error while working on `path`.
    #[error("OpenCV failed on {path}")]
    OpenCv {
        /// The file concerned.
        path: PathBuf,
        /// OpenCV's error.
        source: opencv::Error,
    },
}

/// Result with the io [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;
