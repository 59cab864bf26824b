//! The Python package `gelstereo`: numpy arrays in and out over the gelstereo libraries, with no
//! logic of its own (docs/design.md, "Layout (workspace)").
//!
//! - [`image`]: numpy `HxW` grey / `HxWx3` BGR `uint8` arrays to OpenCV images (one copy).
//! - [`detect`]: `gelstereo.detect(image, method="marknet-mre")`, markers as an `(N, 3)` array.
//! - [`pipeline`]: `gelstereo.Pipeline` over the facade's `Pipeline`; `process` gives a
//!   `gelstereo.Frame` (markers as a dict of numpy arrays, `Contact`, slip state, timestamp).
//! - [`source`]: `gelstereo.open(source)`, the frames of a recording, video or cameras as numpy
//!   images.
//! - [`stream`]: `gelstereo.read_stream(path)` / `parse_frame(line)`, the `--jsonl` stream read
//!   back into `gelstereo.Frame`s.
//! - [`postprocess`]: `gelstereo.postprocess`, Marknet's input layout, decoding and
//!   post-processing for the trainer's own networks (one implementation for Rust and Python).
//! - [`package`]: the installed package's own models (`python/gelstereo/__init__.py` passes them).
//!
//! The extension module is `gelstereo._gelstereo`; the package `gelstereo`
//! (`python/gelstereo/__init__.py`) points ONNX Runtime at the `onnxruntime` package's library and
//! re-exports the module's names.
//!
//! Every Rust error becomes a `gelstereo.GelstereoError` carrying the Rust message with its causes;
//! arrays of the wrong type or shape raise `TypeError` / `ValueError`. Work on images runs with the
//! GIL released, so other Python threads run meanwhile.
//!
//! Built by maturin (`crates/gelstereo-py/pyproject.toml`, installed by `scripts/setup.sh`); tested
//! from Python (`crates/gelstereo-py/tests`).

mod detect;
mod error;
mod image;
mod package;
mod pipeline;
mod postprocess;
mod source;
mod stream;

use pyo3::prelude::*;

/// The extension module `gelstereo._gelstereo` (the package `gelstereo` re-exports its names).
#[pymodule]
#[pyo3(name = "_gelstereo")]
fn gelstereo_module(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("GelstereoError", m.py().get_type::<error::GelstereoError>())?;
    m.add_function(wrap_pyfunction!(detect::detect, m)?)?;
    m.add_function(wrap_pyfunction!(package::use_package_models, m)?)?;
    m.add_class::<pipeline::PyPipeline>()?;
    m.add_class::<pipeline::PyFrame>()?;
    m.add_class::<pipeline::PyContact>()?;
    m.add_function(wrap_pyfunction!(stream::parse_frame, m)?)?;
    m.add_function(wrap_pyfunction!(stream::read_stream, m)?)?;
    m.add_class::<stream::StreamReader>()?;
    m.add_function(wrap_pyfunction!(source::open, m)?)?;
    m.add_class::<source::FrameReader>()?;
    m.add_class::<source::InputFrame>()?;
    m.add_submodule(&postprocess::module(m.py())?)?;
    Ok(())
}
