//! The synthetic GelStereo sensor: elastic gel deformation under indenters, stereo rendering through
//! calibrated cameras, and exact ground truth, written as recordings and datasets.
//!
//! # Conventions
//! As in docs/design.md: pixel (0, 0) is the centre of the top-left pixel; camera frames x right, y down,
//! z forward; ground truth in mm in the LEFT camera's frame; `p_in_right = right_from_left *
//! p_in_left`. Marker (row, col): row grows with y, col with x in the left view. The simulator's own
//! *sensor frame* is described in [`sensor`].
//!
//! Ground-truth image positions are the projections of each marker's 3-D centre through the written
//! calibration ([`gelstereo_geometry::Camera::project`]): reprojecting `X_mm, Y_mm, Z_mm` with
//! `calib.yaml` gives `x_left, y_left, x_right, y_right` exactly.
//!
//! # Pipeline
//! [`sensor`] (the description, from `gelstereo-sensor`) -> [`motion`] script of an [`indenter`] -> [`physics::deform`] per frame ->
//! [`render`] both views -> [`dataset`] on disk. [`checkerboard`] renders calibration targets
//! through the same cameras.

pub mod appearance;
pub mod calibration;
pub mod checkerboard;
pub mod dataset;
pub mod error;
pub mod indenter;
pub mod manifest;
pub mod motion;
pub mod physics;
pub mod render;
pub mod variant;

/// The sensor description, from [`gelstereo_sensor`] (kept here under its old path for the
/// simulator's users).
pub use gelstereo_sensor::spec as sensor;

pub use appearance::Appearance;
pub use dataset::{DatasetConfig, Experiment, Randomization, Simulator, Split, write_dataset};
pub use error::{Error, Result};
pub use gelstereo_sensor::RecordingMeta;
pub use gelstereo_sensor::{Sensor, SensorSpec};
pub use indenter::{Indenter, SHAPES};
pub use manifest::DatasetManifest;
pub use motion::{MotionKind, Pose, Script};

/// Name and version written into every `dataset.json` and `meta.json`.
pub const GENERATOR_VERSION: &str = concat!("gelstereo-sim ", env!("CARGO_PKG_VERSION"));
