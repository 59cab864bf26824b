//! The one error type of this crate.

use std::path::PathBuf;

/// Everything that can go wrong in `gelstereo-sim`: invalid sensor files, impossible parameters,
/// output that cannot be written.
///
/// Sensor-file errors name the file, the field and what was expected against what was found.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A simulation parameter (command-line option, dataset setting) is impossible.
    #[error("invalid parameter {name} = {value}: expected {expected}")]
    Parameter {
        /// Parameter name, e.g. `frames_per_experiment`.
        name: &'static str,
        /// The value given.
        value: String,
        /// What would be valid.
        expected: String,
    },
    /// The output folder exists and is not empty (and overwriting was not asked for).
    #[error("{}: output folder exists and is not empty (pass --force to replace it)", path.display())]
    OutputNotEmpty {
        /// The folder.
        path: PathBuf,
    },
    /// `--force` was asked for, but the output is not a folder gelstereo wrote: it is left alone.
    #[error("{}: {why}; refusing to replace it (choose another output or remove it yourself)", path.display())]
    OutputNotOurs {
        /// The file or folder.
        path: PathBuf,
        /// Why it is not ours.
        why: String,
    },
    /// The run was stopped (SIGINT / SIGTERM) before it finished; nothing was written.
    #[error("interrupted: the partial output was removed")]
    Interrupted,
    /// Reading or writing a file failed at the OS level.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The OS error (in the message, not repeated as a cause).
        error: std::io::Error,
    },
    /// An OpenCV call failed.
    #[error("OpenCV {context}: {error}")]
    OpenCv {
        /// What we were doing.
        context: String,
        /// OpenCV's error (in the message, not repeated as a cause).
        error: opencv::Error,
    },
    /// PNG encoding failed.
    #[error("PNG encoding: {0}")]
    Png(String),
    /// The gel's facts or the physics grid out of the contact mechanics' range.
    #[error("gel mechanics: {0}")]
    Mechanics(#[from] gelstereo_mechanics::Error),
    /// A sensor description or `meta.json` that cannot be used (from `gelstereo-sensor`).
    #[error(transparent)]
    Sensor(#[from] gelstereo_sensor::Error),
    /// A camera or calibration error from `gelstereo-geometry`.
    #[error(transparent)]
    Geometry(#[from] gelstereo_geometry::Error),
}

/// Result with this crate's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

pub(crate) fn io_err(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Error {
    let path = path.into();
    move |error| Error::Io { path, error }
}

pub(crate) fn cv_err(context: &str) -> impl FnOnce(opencv::Error) -> Error + '_ {
    move |error| Error::OpenCv {
        context: context.to_owned(),
        error,
    }
}
