//! Camera models, calibration files and triangulation for a stereo GelStereo sensor.
//!
//! Conventions (see DESIGN.md): pixel (0, 0) is the centre of the top-left pixel; camera frame x right,
//! y down, z forward; 3-D in mm in the LEFT camera's frame; `p_in_right = right_from_left * p_in_left`.
//!
//! Modules: [`camera`] (pinhole + OpenCV distortion, [`StereoRig`]), [`calib`] (calibration files),
//! [`cv`] (conversions to and from OpenCV matrices), [`triangulation`] (mid-point, Lee-Civera Mid2,
//! Lindstrom, pixel-optimal; per-point reprojection error and rejection), [`checkerboard`] (stereo
//! checkerboard calibration with OpenCV).

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
pub use checkerboard::{Board, CalibrationOptions, CalibrationReport, CornerDetector, StereoCorners};
pub use error::{Error, Result};
pub use triangulation::{Rejection, Triangulated, TriangulationConfig, TriangulationMethod, Triangulator};
