//! `gelstereo.open(source)`: the frames of a recording folder, a folder of images, a video (mono or
//! side-by-side stereo) or cameras, as numpy images, read ahead on a thread of their own (the
//! facade's [`gelstereo::source::FrameSource`], the reader `gelstereo track` uses).

use std::path::PathBuf;
use std::sync::Mutex;

use gelstereo::Images;
use gelstereo::source::{FrameSource, Prefetch};
use pyo3::exceptions::{PyTypeError, PyUserWarning};
use pyo3::prelude::*;

use crate::error::{message, to_py};
use crate::image::to_numpy;

/// Frames read ahead of the consumer.
const PREFETCH_FRAMES: usize = 4;

/// Opens a source of frames for `Pipeline.process`:
/// `for f in gelstereo.open("rec"): pipeline.process(f.left, f.right, f.timestamp)`.
///
/// Args:
///     source: a stereo recording folder (`left/`, `right/`), a folder of images (mono), a video
///         file, a camera index (int), two camera indices (a tuple, left and right, paired by
///         capture time) or the same as text ("0", "0,1").
///     side_by_side: a video or camera whose frames hold the left view in their left half and the
///         right view in their right half.
///     mono: a stereo recording's left view only.
///
/// Frame files are read in natural order (`2` before `10`); where names do not settle it (`1.png`
/// and `01.png`) a `UserWarning` says so, as does a video that ends before its declared length.
///
/// Raises:
///     GelstereoError: the source cannot be opened (a missing path, an unreadable video, a camera
///         that does not open).
#[pyfunction]
#[pyo3(signature = (source, *, side_by_side = false, mono = false))]
pub fn open(
    py: Python<'_>,
    source: &Bound<'_, PyAny>,
    side_by_side: bool,
    mono: bool,
) -> PyResult<FrameReader> {
    let opened = if let Ok(index) = source.extract::<i64>() {
        FrameSource::open_cameras(&[index.to_string()], side_by_side)
    } else if let Ok((left, right)) = source.extract::<(i64, i64)>() {
        FrameSource::open_cameras(&[left.to_string(), right.to_string()], false)
    } else if let Ok(path) = source.extract::<PathBuf>() {
        if path.exists() {
            match mono {
                true => FrameSource::open_left_view(&path),
                false => FrameSource::open_path(&path, side_by_side),
            }
        } else {
            FrameSource::open(&path.to_string_lossy())
        }
    } else {
        return Err(PyTypeError::new_err(
            "source: expected a path, a camera index or a (left, right) pair of camera indices",
        ));
    };
    let opened = opened.map_err(|e| to_py(&e))?;
    if let Some(warning) = opened.order_warning() {
        PyErr::warn(
            py,
            &py.get_type::<PyUserWarning>(),
            &std::ffi::CString::new(warning)?,
            1,
        )?;
    }
    Ok(FrameReader {
        is_stereo: opened.is_stereo(),
        frames: opened.len_hint(),
        reader: Mutex::new(Some(opened.prefetch(PREFETCH_FRAMES))),
    })
}

/// The frames of a source, in order (`gelstereo.open`).
///
/// Attributes:
///     is_stereo: whether frames carry a right view.
///     frames: the number of frames when the source declares it (a folder, a video), else None.
#[pyclass(module = "gelstereo", name = "FrameReader")]
pub struct FrameReader {
    #[pyo3(get)]
    is_stereo: bool,
    #[pyo3(get)]
    frames: Option<usize>,
    reader: Mutex<Option<Prefetch>>,
}

#[pymethods]
impl FrameReader {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__(&self, py: Python<'_>) -> PyResult<Option<InputFrame>> {
        let (next, end_warning) = py.detach(|| {
            let Ok(mut reader) = self.reader.lock() else {
                return (None, None);
            };
            let next = reader.as_mut().and_then(Iterator::next);
            // At the end, the reading thread says whether the source was cut short.
            let end_warning = match next {
                None => reader.take().and_then(Prefetch::finish),
                Some(_) => None,
            };
            (next, end_warning)
        });
        if let Some(warning) = end_warning {
            PyErr::warn(
                py,
                &py.get_type::<PyUserWarning>(),
                &std::ffi::CString::new(warning)?,
                1,
            )?;
        }
        let Some(frame) = next else { return Ok(None) };
        let (left, right, error) = match frame.images {
            Ok(Images::Stereo(pair)) => (
                Some(to_numpy(py, &pair.left)?.into_any().unbind()),
                Some(to_numpy(py, &pair.right)?.into_any().unbind()),
                None,
            ),
            Ok(Images::Mono(view)) => (Some(to_numpy(py, &view)?.into_any().unbind()), None, None),
            Err(e) => (None, None, Some(message(&e))),
        };
        Ok(Some(InputFrame {
            index: frame.index,
            timestamp: frame.time_s,
            left,
            right,
            error,
        }))
    }
}

/// One frame of a source: its images as numpy `uint8` arrays (BGR, as OpenCV reads).
///
/// Attributes:
///     index: frame number in the source, from 0.
///     timestamp: capture time, s (frame number / frame rate for files).
///     left: the left view (a mono sensor's view); None when the frame could not be read.
///     right: the right view; None for a mono source or an unreadable frame.
///     error: why the frame could not be read (the frame is then skipped or given to
///         `Pipeline.process` as it is); None for a frame read whole.
#[pyclass(module = "gelstereo", name = "InputFrame", frozen)]
pub struct InputFrame {
    #[pyo3(get)]
    index: usize,
    #[pyo3(get)]
    timestamp: f64,
    #[pyo3(get)]
    left: Option<Py<PyAny>>,
    #[pyo3(get)]
    right: Option<Py<PyAny>>,
    #[pyo3(get)]
    error: Option<String>,
}

#[pymethods]
impl InputFrame {
    fn __repr__(&self) -> String {
        let views = match (&self.left, &self.right, &self.error) {
            (_, _, Some(e)) => format!("error={e:?}"),
            (_, Some(_), _) => "stereo".to_owned(),
            _ => "mono".to_owned(),
        };
        format!(
            "gelstereo.InputFrame(index={}, timestamp={:.3}, {views})",
            self.index, self.timestamp
        )
    }
}
