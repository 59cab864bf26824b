//! numpy images to OpenCV [`Mat`]s.

use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use opencv::core::{CV_8UC1, CV_8UC3, CV_8UC4, Mat, MatTraitManual, Scalar};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

const EXPECTED: &str = "a numpy uint8 array HxW (grey), HxWx3 (BGR, as OpenCV reads) or HxWx4 (BGRA)";

/// Copies `array` (named `what` in errors) into an 8-bit OpenCV image of 1, 3 or 4 channels. Any
/// memory layout is accepted (e.g. a slice or a channel-reversed view).
pub fn to_mat(what: &str, array: &Bound<'_, PyAny>) -> PyResult<Mat> {
    let untyped = array.cast::<PyUntypedArray>().map_err(|_| {
        PyTypeError::new_err(format!(
            "{what}: expected {EXPECTED}, found a {}",
            type_name(array)
        ))
    })?;
    let bytes = untyped.cast::<PyArrayDyn<u8>>().map_err(|_| {
        let dtype = untyped.dtype().str().map(|s| s.to_string()).unwrap_or_default();
        PyTypeError::new_err(format!("{what}: expected {EXPECTED}, found dtype {dtype}"))
    })?;
    let shape = untyped.shape().to_vec();
    let (rows, cols, kind) = match shape[..] {
        [h, w] => (h, w, CV_8UC1),
        [h, w, 1] => (h, w, CV_8UC1),
        [h, w, 3] => (h, w, CV_8UC3),
        [h, w, 4] => (h, w, CV_8UC4),
        _ => {
            return Err(PyValueError::new_err(format!(
                "{what}: expected {EXPECTED}, found shape {shape:?}"
            )));
        }
    };
    let side = |n: usize| {
        i32::try_from(n).map_err(|_| PyValueError::new_err(format!("{what}: {n} px is too large a side")))
    };
    let mut mat = Mat::new_rows_cols_with_default(side(rows)?, side(cols)?, kind, Scalar::all(0.0))
        .map_err(|e| crate::error::to_py(&e))?;
    let readonly = bytes.try_readonly()?;
    let view = readonly.as_array();
    let out = mat.data_bytes_mut().map_err(|e| crate::error::to_py(&e))?;
    match view.as_slice() {
        Some(contiguous) => out.copy_from_slice(contiguous),
        None => out.iter_mut().zip(view.iter()).for_each(|(o, v)| *o = *v),
    }
    Ok(mat)
}

fn type_name(object: &Bound<'_, PyAny>) -> String {
    object
        .get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "value".into())
}

/// Copies an 8-bit OpenCV image into a numpy array: `HxW` for one channel, `HxWxC` otherwise (BGR
/// for three, as OpenCV reads).
pub fn to_numpy<'py>(py: Python<'py>, mat: &Mat) -> PyResult<Bound<'py, PyArrayDyn<u8>>> {
    use opencv::core::{MatTraitConst, MatTraitConstManual};
    if mat.depth() != opencv::core::CV_8U {
        return Err(PyValueError::new_err(format!(
            "expected an 8-bit image, found OpenCV depth {}",
            mat.depth()
        )));
    }
    let (rows, cols, channels) = (mat.rows() as usize, mat.cols() as usize, mat.channels() as usize);
    let shape = if channels == 1 {
        vec![rows, cols]
    } else {
        vec![rows, cols, channels]
    };
    let contiguous;
    let mat = if mat.is_continuous() {
        mat
    } else {
        contiguous = mat.try_clone().map_err(|e| crate::error::to_py(&e))?;
        &contiguous
    };
    let bytes = mat.data_bytes().map_err(|e| crate::error::to_py(&e))?.to_vec();
    let array = numpy::ndarray::ArrayD::from_shape_vec(shape, bytes)
        .map_err(|e| PyValueError::new_err(format!("image of unexpected layout: {e}")))?;
    Ok(numpy::PyArrayDyn::from_owned_array(py, array))
}
