//! Reading `gelstereo track --jsonl` back into `gelstereo.Frame`s: `read_stream(path)` for a file,
//! `parse_frame(line)` for a line from a pipe or a socket (the facade's
//! [`gelstereo::sink::parse_frame_line`]).

use std::path::PathBuf;
use std::sync::Mutex;

use gelstereo::sink::{parse_frame_line, read_frames};
use gelstereo::{FrameOutput, GelFrame};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::error::{message, to_py};
use crate::pipeline::PyFrame;

type Frames = Box<dyn Iterator<Item = gelstereo::Result<(FrameOutput, Option<GelFrame>)>> + Send>;

/// Reads one line of a `gelstereo track --jsonl` stream into the `Frame` that `Pipeline.process`
/// returned for it, to the stream's precision (camera-frame positions through the line's gel
/// frame). Not in the stream, and so empty: `log` and `earlier` (earlier frames are lines of their
/// own).
///
/// Args:
///     line: the JSON line (a trailing newline is allowed).
///
/// Raises:
///     ValueError: the line is not a frame of schema gelstereo-frame/1; the message names the field
///         and what was expected.
#[pyfunction]
pub fn parse_frame(py: Python<'_>, line: &str) -> PyResult<PyFrame> {
    let (output, gel) =
        parse_frame_line(line.trim_end(), "line").map_err(|e| PyValueError::new_err(message(&e)))?;
    PyFrame::new(py, output, gel.as_ref())
}

/// Reads a `gelstereo track --jsonl` file frame by frame: `for frame in read_stream(path)`, each a
/// `Frame` as `parse_frame` gives it. Blank lines are skipped.
///
/// Raises:
///     GelstereoError: the file cannot be opened.
///     ValueError (while iterating): a line is not a frame; the message names the file and line.
#[pyfunction]
pub fn read_stream(path: PathBuf) -> PyResult<StreamReader> {
    let file = std::fs::File::open(&path).map_err(|e| {
        to_py(&gelstereo::Error::File {
            path: path.clone(),
            source: e,
        })
    })?;
    let frames = read_frames(std::io::BufReader::new(file), &path.display().to_string());
    Ok(StreamReader {
        frames: Mutex::new(Box::new(frames)),
    })
}

/// The frames of a stream file, read one at a time (`read_stream`).
#[pyclass(module = "gelstereo", name = "StreamReader")]
pub struct StreamReader {
    frames: Mutex<Frames>,
}

#[pymethods]
impl StreamReader {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__(&self, py: Python<'_>) -> PyResult<Option<PyFrame>> {
        let next = py.detach(|| match self.frames.lock() {
            Ok(mut frames) => Ok(frames.next()),
            Err(_) => Err(PyValueError::new_err("the stream reader failed earlier")),
        })?;
        match next {
            None => Ok(None),
            Some(Ok((output, gel))) => PyFrame::new(py, output, gel.as_ref()).map(Some),
            Some(Err(e)) => Err(PyValueError::new_err(message(&e))),
        }
    }
}
