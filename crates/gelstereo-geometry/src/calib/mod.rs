//! Calibration files: OpenCV FileStorage (YAML/XML) and mrcal `.cameramodel` pairs.
//!
//! [`StereoRig::load`] and [`StereoRig::save`] pick the format from the path:
//! - `*.yaml`, `*.yml`, `*.xml`: OpenCV FileStorage ([`StereoRig::read_opencv`]);
//! - `LEFT.cameramodel,RIGHT.cameramodel` (two paths joined by a comma): a mrcal pair;
//! - `A.yml,B.yml` (OpenCV files joined by a comma): keys read from either, e.g. the
//!   `intrinsics.yml,extrinsics.yml` of OpenCV's stereo_calib sample (reading only);
//! - a directory: the mrcal pair `DIR/left.cameramodel` and `DIR/right.cameramodel`.

pub(crate) mod filestorage;
pub mod mrcal;
pub mod opencv;
pub(crate) mod pyliteral;
pub(crate) mod structure;

use std::ffi::OsStr;
use std::path::{Path, PathBuf};

use crate::camera::StereoRig;
use crate::error::{Error, Result};

/// Where a calibration lives, as decided from its path by [`CalibrationPath::parse`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CalibrationPath {
    /// An OpenCV FileStorage YAML file.
    OpenCvYaml(PathBuf),
    /// An OpenCV FileStorage XML file.
    OpenCvXml(PathBuf),
    /// Several OpenCV FileStorage files read together (keys from the first file that has them).
    OpenCvFiles(Vec<PathBuf>),
    /// A pair of mrcal `.cameramodel` files.
    Mrcal {
        /// The left camera's model (the reference frame).
        left: PathBuf,
        /// The right camera's model.
        right: PathBuf,
    },
}

impl CalibrationPath {
    /// Decides the format: `.yaml`/`.yml`/`.xml` (any case) are OpenCV; `A,B` is a mrcal pair when
    /// both are `.cameramodel`, several OpenCV files when all are `.yaml`/`.yml`/`.xml`; an existing
    /// directory, or a path without an extension, is a directory holding `left.cameramodel` and
    /// `right.cameramodel`.
    pub fn parse(spec: impl AsRef<Path>) -> Result<Self> {
        let spec = spec.as_ref();
        let unknown = || Error::UnknownFormat {
            path: spec.display().to_string(),
        };
        if let Some(parts) = comma_separated(spec.as_os_str()) {
            let has_ext = |p: &Path, exts: &[&str]| {
                p.extension()
                    .is_some_and(|e| exts.iter().any(|x| e.eq_ignore_ascii_case(x)))
            };
            if let [l, r] = parts.as_slice()
                && has_ext(l, &["cameramodel"])
                && has_ext(r, &["cameramodel"])
            {
                return Ok(Self::Mrcal {
                    left: l.clone(),
                    right: r.clone(),
                });
            }
            if parts.iter().all(|p| has_ext(p, &["yaml", "yml", "xml"])) {
                return Ok(Self::OpenCvFiles(parts));
            }
            return Err(unknown());
        }
        let path = spec.to_path_buf();
        let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
        match ext.as_deref() {
            Some("yaml" | "yml") => Ok(Self::OpenCvYaml(path)),
            Some("xml") => Ok(Self::OpenCvXml(path)),
            _ if path.is_dir() || ext.is_none() => Ok(Self::Mrcal {
                left: path.join("left.cameramodel"),
                right: path.join("right.cameramodel"),
            }),
            _ => Err(unknown()),
        }
    }
}

/// The parts of a comma-separated spec, each trimmed of spaces; `None` without a comma. On Unix the
/// spec is split as bytes, so a part whose name is not UTF-8 keeps its name.
fn comma_separated(spec: &OsStr) -> Option<Vec<PathBuf>> {
    #[cfg(unix)]
    {
        use std::os::unix::ffi::OsStrExt;
        let bytes = spec.as_bytes();
        bytes.contains(&b',').then(|| {
            bytes
                .split(|b| *b == b',')
                .map(|part| PathBuf::from(OsStr::from_bytes(part.trim_ascii())))
                .collect()
        })
    }
    #[cfg(not(unix))]
    {
        let text = spec.to_string_lossy();
        text.contains(',')
            .then(|| text.split(',').map(|p| PathBuf::from(p.trim())).collect())
    }
}

impl StereoRig {
    /// Reads a calibration, choosing the format from the path (see [`CalibrationPath::parse`]).
    pub fn load(spec: impl AsRef<Path>) -> Result<StereoRig> {
        let spec = spec.as_ref();
        match CalibrationPath::parse(spec)? {
            CalibrationPath::OpenCvYaml(p) | CalibrationPath::OpenCvXml(p) => StereoRig::read_opencv(p),
            CalibrationPath::OpenCvFiles(files) => {
                let paths: Vec<&Path> = files.iter().map(PathBuf::as_path).collect();
                StereoRig::read_opencv_files(&paths)
            }
            CalibrationPath::Mrcal { left, right } => StereoRig::read_mrcal(left, right),
        }
    }

    /// Writes the calibration, choosing the format from the path (see [`CalibrationPath::parse`]); a
    /// directory for a mrcal pair is created if needed.
    pub fn save(&self, spec: impl AsRef<Path>) -> Result<()> {
        let spec = spec.as_ref();
        match CalibrationPath::parse(spec)? {
            CalibrationPath::OpenCvYaml(p) => self.write_opencv_yaml(p),
            CalibrationPath::OpenCvXml(p) => self.write_opencv_xml(p),
            CalibrationPath::OpenCvFiles(_) => Err(Error::UnknownFormat {
                path: format!(
                    "{} (several OpenCV files are for reading only; write one .yaml)",
                    spec.display()
                ),
            }),
            CalibrationPath::Mrcal { left, right } => {
                for p in [&left, &right] {
                    if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
                        std::fs::create_dir_all(dir).map_err(|source| Error::Io {
                            path: dir.to_path_buf(),
                            source,
                        })?;
                    }
                }
                self.write_mrcal(left, right)
            }
        }
    }
}
