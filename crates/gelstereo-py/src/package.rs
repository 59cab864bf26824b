//! What the installed Python package hands the extension: the folder of its own models.

use std::path::PathBuf;

use pyo3::prelude::*;

/// Makes `folder` (the package's `models/`, passed by `gelstereo/__init__.py` when imported) the
/// default models of `Pipeline` and `detect`; a `models=` keyword still wins.
#[pyfunction]
#[pyo3(name = "_use_package_models")]
pub fn use_package_models(folder: PathBuf) {
    // A second import of the package (e.g. after a reload) names the same folder.
    gelstereo::models::use_shipped_models(folder);
}
