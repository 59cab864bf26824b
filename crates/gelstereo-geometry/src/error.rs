//! The one error type of this crate.

use std::path::PathBuf;

/// Everything that can go wrong in `gelstereo-geometry`: bad camera parameters, calibration files
/// that do not follow their format, degenerate geometry and failed calibrations.
///
/// File errors name the file, the key and what was expected against what was found.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A distortion vector whose length is not one of OpenCV's models we support.
    #[error(
        "unsupported distortion model with {count} coefficients: expected 0, 4, 5, 8 or 12 \
         (OpenCV order k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]])"
    )]
    DistortionCount {
        /// Number of coefficients given.
        count: usize,
    },
    /// OpenCV's 14-coefficient tilted (Scheimpflug) model, which we do not implement.
    #[error(
        "unsupported distortion model: 14 coefficients = OpenCV's tilted (Scheimpflug) model \
         (tauX, tauY), which gelstereo does not implement"
    )]
    TiltedDistortion,
    /// A camera parameter is out of its valid range (non-finite, non-positive focal length, ...).
    #[error("invalid camera parameter {name} = {value}: expected {expected}")]
    InvalidParameter {
        /// Parameter name (`fx`, `k1`, `image_width`, ...).
        name: String,
        /// The value found.
        value: f64,
        /// What would be valid.
        expected: &'static str,
    },
    /// Reading or writing a file failed at the OS level.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// A calibration file could not be parsed at all (syntax).
    #[error("{}: {}{message}", path.display(), at_line(*line))]
    Syntax {
        /// The file.
        path: PathBuf,
        /// 1-based line (0 when unknown).
        line: usize,
        /// What went wrong.
        message: String,
    },
    /// A key a calibration file must have is missing.
    #[error("{}: missing key '{key}' ({expected})", path.display())]
    MissingKey {
        /// The file.
        path: PathBuf,
        /// The key that is missing (alternatives separated by " or ").
        key: String,
        /// What the key should hold.
        expected: String,
    },
    /// A key holds a value of the wrong shape or type.
    #[error("{}: key '{key}': expected {expected}, found {found}", path.display())]
    BadValue {
        /// The file.
        path: PathBuf,
        /// The key.
        key: String,
        /// Expected shape / type / range.
        expected: String,
        /// What was found.
        found: String,
    },
    /// A lens model that gelstereo does not implement (mrcal `lensmodel`).
    #[error(
        "{}: key 'lensmodel': unsupported lens model '{model}': expected LENSMODEL_PINHOLE or \
         LENSMODEL_OPENCV4/5/8/12",
        path.display()
    )]
    UnsupportedLensModel {
        /// The file.
        path: PathBuf,
        /// The model named in the file.
        model: String,
    },
    /// A calibration path that names no format we know.
    #[error(
        "{path}: cannot tell the calibration format: expected a .yaml/.yml/.xml OpenCV FileStorage \
         file, 'left.cameramodel,right.cameramodel', or a directory holding left.cameramodel and \
         right.cameramodel"
    )]
    UnknownFormat {
        /// The path as given.
        path: String,
    },
    /// The two cameras of a rig are inconsistent with each other or with the data.
    #[error(
        "image size mismatch for the {camera} camera: calibration says {expected_width}x{expected_height}, image is {found_width}x{found_height}"
    )]
    ImageSizeMismatch {
        /// "left" or "right".
        camera: &'static str,
        /// Calibrated width.
        expected_width: u32,
        /// Calibrated height.
        expected_height: u32,
        /// Width of the image given.
        found_width: u32,
        /// Height of the image given.
        found_height: u32,
    },
    /// Triangulation inputs of different lengths.
    #[error("triangulation: {left_len} left points but {right_len} right points")]
    LengthMismatch {
        /// Number of left points.
        left_len: usize,
        /// Number of right points.
        right_len: usize,
    },
    /// Checkerboard calibration failed.
    #[error("calibration: {0}")]
    Calibration(String),
    /// An OpenCV call failed.
    #[error("OpenCV {context}: {source}")]
    OpenCv {
        /// What we were doing.
        context: String,
        /// OpenCV's error.
        source: opencv::Error,
    },
}

/// Result with this crate's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// `line N: ` for a known 1-based line, nothing when it is unknown (0).
fn at_line(line: usize) -> String {
    if line == 0 {
        String::new()
    } else {
        format!("line {line}: ")
    }
}
