//! Camera models, calibration files and triangulation for a stereo GelStereo sensor.
//!
//! Conventions (see docs/design.md): pixel (0, 0) is the centre of the top-left pixel; camera frame x right,
//! y down, z forward; 3-D in mm in the LEFT camera's frame; `p_in_right = right_from_left * p_in_left`.
//!
//! Modules: [`camera`] (pinhole + OpenCV distortion, [`StereoRig`]), [`calib`] (calibration files),
//! [`cv`] (conversions to and from OpenCV matrices), [`triangulation`] (mid-point, Lee-Civera Mid2,
//! Lindstrom, pixel-optimal; per-point reprojection error and rejection), [`checkerboard`] (stereo
//! checkerboard calibration with OpenCV).
//!
//! ```
//! use gelstereo_geometry::nalgebra::Point3;
//! use gelstereo_geometry::{StereoRig, TriangulationConfig, Triangulator};
//!
//! // OpenCV YAML/XML, "left.cameramodel,right.cameramodel" or a folder holding that mrcal pair.
//! let rig = StereoRig::load(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/opencv8.yaml"))?;
//! let marker = Point3::new(1.0, -2.0, 25.0); // mm, left camera frame
//! let (left_px, right_px) = rig.project(&marker).expect("in front of both cameras");
//! let triangulator = Triangulator::new(rig, TriangulationConfig::default())?;
//! let found = triangulator.triangulate(left_px, right_px).expect("a consistent pair");
//! assert!((found.p_in_left_mm - marker).norm() < 1e-9);
//! assert!(found.max_reprojection_error_px() < 1e-9);
//! # Ok::<(), gelstereo_geometry::Error>(())
//! ```

pub mod calib;
pub mod camera;
pub mod checkerboard;
pub mod cv;
pub mod error;
pub mod triangulation;

/// The `nalgebra` this crate's API uses (points, isometries), re-exported.
pub use nalgebra;

pub use calib::CalibrationPath;
pub use camera::{Camera, Distortion, StereoRig};
pub use checkerboard::{
    Board, CalibrationOptions, CalibrationReport, CornerDetector, PairError, StereoCorners,
};
pub use error::{Error, Result};
pub use triangulation::{Rejection, Triangulated, TriangulationConfig, TriangulationMethod, Triangulator};
