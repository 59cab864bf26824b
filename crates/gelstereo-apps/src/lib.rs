//! gelstereo-apps: the applications built on the pipeline of the [`gelstereo`] facade, one module
//! per `gelstereo` command that is not `track` itself.
//!
//! - [`bench`](mod@bench): times [`gelstereo::Pipeline`] and [`gelstereo::track::run`] as they run
//!   (`gelstereo bench`), and the localizers alone ([`bench::localization`]).
//! - [`adapt`]: pseudo-labels from an unlabelled recording and the fine-tuning run that adapts the
//!   localizer to a sensor (`gelstereo adapt`).
//! - [`calibrate`]: stereo checkerboard calibration from two folders of images (`gelstereo calibrate`).
//! - [`calibrate_gel`]: the gel's modulus from presses of known force (`gelstereo calibrate-gel`).
//! - [`doctor`]: every component a user needs, checked, with a fix for each that is missing.
//! - [`eval`]: the paper's Table I of each localization method on a simulated dataset.
//! - [`reconstruct`]: localization, indexing, pairing and triangulation of a stereo recording into
//!   tables and point clouds, with its ground-truth evaluation (`gelstereo reconstruct`).
//! - [`truth`]: a simulated recording's ground-truth markers in place of a localizer
//!   (`gelstereo track --from-ground-truth`).
//!
//! They report [`gelstereo::Error`]s, like the pipeline they drive.

pub mod adapt;
pub mod bench;
pub mod calibrate;
pub mod calibrate_gel;
pub mod doctor;
pub mod eval;
pub mod reconstruct;
pub mod truth;

use std::path::{Path, PathBuf};

/// The Python of the checkout in `home` (`.venv`, made by `scripts/setup.sh`, with PyTorch, ONNX and
/// ONNX Runtime for `train/`).
pub fn project_python(home: &Path) -> PathBuf {
    home.join(".venv/bin/python")
}
