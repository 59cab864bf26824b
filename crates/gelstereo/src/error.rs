//! The facade's error: the stage crates' errors, and what the facade itself checks (input, outputs).

use std::path::PathBuf;

/// Everything [`crate::Pipeline`], the sources and the sinks can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Localization failed (model loading, inference, image checks).
    #[error(transparent)]
    Markers(#[from] gelstereo_markers::Error),
    /// Calibration or triangulation failed.
    #[error(transparent)]
    Geometry(#[from] gelstereo_geometry::Error),
    /// The reference frame could not be indexed, or the views not paired.
    #[error(transparent)]
    Matching(#[from] gelstereo_matching::Error),
    /// Tracking, contact or slip failed.
    #[error(transparent)]
    Tracking(#[from] gelstereo_tracking::Error),
    /// Reading frames or writing exports failed.
    #[error(transparent)]
    Io(#[from] gelstereo_io::Error),
    /// A sensor description or a recording's `meta.json` could not be read or built.
    #[error(transparent)]
    Sensor(#[from] gelstereo_sensor::Error),
    /// The simulator failed (evaluation, adaptation).
    #[error(transparent)]
    Sim(#[from] gelstereo_sim::Error),
    /// OpenCV failed outside the stage crates (padding, drawing, capture).
    #[error(transparent)]
    OpenCv(#[from] opencv::Error),
    /// A file or folder could not be read or written.
    #[error("{path}: {source}")]
    File {
        /// The file or folder.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The reader of a stream closed it (`gelstereo track --jsonl - | head -1`): not a failure, the
    /// end of the run.
    #[error("{}: the reader closed the stream", name.display())]
    ReaderClosed {
        /// The stream: its path, or `standard output`.
        name: PathBuf,
    },
    /// An input that does not fit what the pipeline expects (named, with what was expected).
    #[error("{0}")]
    Invalid(String),
    /// `what` went wrong because of `source`.
    #[error("{what}")]
    Context {
        /// What was being done.
        what: String,
        /// Why it failed.
        #[source]
        source: Box<Error>,
    },
}

impl Error {
    /// Wraps `self` with what was being done.
    pub fn context(self, what: impl Into<String>) -> Self {
        Error::Context {
            what: what.into(),
            source: Box::new(self),
        }
    }

    /// The message with its whole chain of causes, `outer: inner: ...` (for bindings that show one
    /// string).
    pub fn full_message(&self) -> String {
        let mut text = self.to_string();
        let mut cause = std::error::Error::source(self);
        while let Some(c) = cause {
            let s = c.to_string();
            if !text.ends_with(&s) {
                text.push_str(": ");
                text.push_str(&s);
            }
            cause = c.source();
        }
        text
    }

    /// Whether the stage error behind `self` says the view does not show the whole lattice.
    pub(crate) fn lattice_cut(&self) -> bool {
        matches!(
            self,
            Error::Matching(
                gelstereo_matching::Error::IncompleteGrid { .. }
                    | gelstereo_matching::Error::StereoAlignment { .. }
            )
        )
    }
}

/// The facade's result.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// `Err(Error::File)` for an I/O error on `path`.
pub fn file_err(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::File {
        path: path.to_path_buf(),
        source,
    }
}
