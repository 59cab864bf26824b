//! `gelstereo.detect`: marker centres in one image.

use std::collections::BTreeMap;
use std::collections::btree_map::Entry;
use std::sync::Mutex;

use gelstereo::markers::{Localizer, LocalizerConfig, Method, create_localizer};
use numpy::PyArray2;
use numpy::ndarray::Array2;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::error::{GelstereoError, to_py};

/// Localizers built so far, per method: loading a model takes longer than running it, so a loop
/// calling `detect` loads each once. Each remembers the marker pitch per image size, as
/// `gelstereo detect` does over the images of one call, but runs every image on the whole network
/// input: the images of a loop may come from either camera of a stereo sensor, and a window learnt
/// on one camera's lattice would send every image of the other back to the whole input, at the cost
/// of both passes.
static LOCALIZERS: Mutex<BTreeMap<Method, Box<dyn Localizer + Send>>> = Mutex::new(BTreeMap::new());

/// Marker centres in one image.
///
/// Args:
///     image: numpy uint8 array, HxW (grey) or HxWx3 (BGR, as OpenCV reads; HxWx4 BGRA also).
///     method: "marknet-mre" (default), "marknet", "blob" or "yolo", as `gelstereo detect --method`,
///         with the shipped models (the package's own, or data/models of a checkout) and the tuned
///         blob parameters (data/blob_params.json).
///
/// Returns:
///     float64 array of shape (N, 3): x, y (pixels, (0, 0) = centre of the top-left pixel) and
///     confidence in (0, 1] (1 for the blob detector), sorted by y, then x.
///
/// Raises:
///     TypeError, ValueError: the image is not such an array, or the method is unknown.
///     GelstereoError: the method's models cannot be loaded, or the image is too small.
#[pyfunction]
#[pyo3(signature = (image, method = "marknet-mre"))]
pub fn detect<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    method: &str,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let method: Method = method
        .parse()
        .map_err(|e: gelstereo::markers::Error| PyValueError::new_err(e.to_string()))?;
    let image = crate::image::to_mat("image", image)?;
    let rows = py.detach(|| {
        let mut cache = LOCALIZERS
            .lock()
            .map_err(|_| GelstereoError::new_err("a localizer failed in another thread"))?;
        let localizer = match cache.entry(method) {
            Entry::Occupied(built) => built.into_mut(),
            Entry::Vacant(slot) => {
                let config = LocalizerConfig {
                    lattice_window: false,
                    ..gelstereo::models::localizer_config()
                };
                slot.insert(create_localizer(method, &config).map_err(|e| to_py(&e))?)
            }
        };
        let detections = localizer.detect(&image).map_err(|e| to_py(&e))?;
        PyResult::Ok(
            detections
                .iter()
                .map(|d| [d.position.x, d.position.y, f64::from(d.confidence)])
                .collect::<Vec<_>>(),
        )
    })?;
    Ok(PyArray2::from_owned_array(py, Array2::from(rows)))
}
