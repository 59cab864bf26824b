//! Rust errors as Python exceptions.

use pyo3::PyErr;
use pyo3::exceptions::PyRuntimeError;

pyo3::create_exception!(
    gelstereo,
    GelstereoError,
    PyRuntimeError,
    "An error of the gelstereo libraries: a file, model, calibration or image they cannot use. The \
     message is the Rust error with its causes."
);

/// `error` and its chain of causes in one line, e.g. "cannot read data/models/mre.onnx: No such
/// file or directory (os error 2)".
pub fn message(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(c) = cause {
        let more = c.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
        cause = c.source();
    }
    text
}

/// `error` as a `GelstereoError` carrying [`message`].
pub fn to_py(error: &(dyn std::error::Error + 'static)) -> PyErr {
    GelstereoError::new_err(message(error))
}
