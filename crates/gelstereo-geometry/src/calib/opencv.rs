//! OpenCV FileStorage calibration files (YAML and XML): read by [`super::filestorage`] (safe Rust:
//! OpenCV's own reader crashes on some damaged files), written through OpenCV.
//!
//! Keys: `K1 D1 K2 D2 R T image_width image_height` (the names `stereoCalibrate` outputs take in most
//! tools); `M1`/`M2` are accepted for `K1`/`K2` (OpenCV's `samples/cpp/stereo_calib.cpp`). `R` is
//! a 3x3 rotation matrix (a 3-vector is read as a Rodrigues vector), `T` a 3-vector in mm,
//! `p_in_right = R p_in_left + T`. The image size may also be given as `image_size` or
//! `imageSize` = `[width, height]`. Other keys (`E`, `F`, `R1`, `P1`, `Q`, ...) are ignored.
//! [`StereoRig::read_opencv_files`] reads keys spread over several files (the stereo_calib sample
//! writes `intrinsics.yml` and `extrinsics.yml`).

use std::path::{Path, PathBuf};

use gelstereo_core::ImageSize;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{FileStorage, FileStorageTrait, FileStorageTraitConst};

use super::filestorage::{self, Value};
use crate::camera::{Camera, Distortion, StereoRig};
use crate::cv::mat_from_rows as mat;
use crate::error::{Error, Result};

/// A numeric matrix read from a file: `rows` x `cols`, row-major.
struct Numbers {
    rows: usize,
    cols: usize,
    data: Vec<f64>,
}

impl Numbers {
    fn shape(&self) -> String {
        format!("a {}x{} matrix", self.rows, self.cols)
    }
    fn is_vector(&self) -> bool {
        self.rows == 1 || self.cols == 1 || self.data.is_empty()
    }
}

fn cv(context: impl Into<String>) -> impl FnOnce(opencv::Error) -> Error {
    let context = context.into();
    move |source| Error::OpenCv { context, source }
}

/// A value read as a matrix: a number (1x1), a sequence of numbers (1xN) or an OpenCV matrix map
/// (`rows`, `cols`, `dt`, `data`).
fn numbers(value: &Value, path: &Path, key: &str) -> Result<Numbers> {
    let bad = |found: String| Error::BadValue {
        path: path.to_path_buf(),
        key: key.to_owned(),
        expected: "a numeric matrix (!!opencv-matrix) or a sequence of numbers".to_owned(),
        found,
    };
    match value {
        Value::Number(v) => Ok(Numbers {
            rows: 1,
            cols: 1,
            data: vec![*v],
        }),
        Value::Seq(items) => {
            let data = sequence_numbers(items)
                .map_err(|i| bad(format!("a sequence whose item {i} is not a number")))?;
            Ok(Numbers {
                rows: 1,
                cols: data.len(),
                data,
            })
        }
        Value::Map(_) => matrix(value).map_err(|why| bad(format!("a map that is not a matrix: {why}"))),
        other => Err(bad(other.describe())),
    }
}

/// The numbers of a sequence, or the index of the first item that is not one.
fn sequence_numbers(items: &[Value]) -> std::result::Result<Vec<f64>, usize> {
    items
        .iter()
        .enumerate()
        .map(|(i, item)| match item {
            Value::Number(v) => Ok(*v),
            _ => Err(i),
        })
        .collect()
}

/// An OpenCV matrix map, as `cv::FileNode >> cv::Mat` reads one: `data` holds rows x cols x channels
/// numbers; `dt` is the element type with an optional channel count (`d`, `f`, `3d`, ...).
fn matrix(map: &Value) -> std::result::Result<Numbers, String> {
    let count = |key: &str| -> std::result::Result<usize, String> {
        match map.get(key) {
            Some(Value::Number(v)) if v.fract() == 0.0 && (0.0..=1e6).contains(v) => {
                // Checked above: a whole number in [0, 1e6].
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                Ok(*v as usize)
            }
            Some(other) => Err(format!(
                "'{key}' is {}, expected a whole number",
                other.describe()
            )),
            None => Err(format!("no '{key}'")),
        }
    };
    let (rows, cols) = (count("rows")?, count("cols")?);
    let channels = match map.get("dt") {
        Some(Value::Text(dt)) => element_channels(dt)?,
        Some(other) => return Err(format!("'dt' is {}, expected a type such as d", other.describe())),
        None => return Err("no 'dt'".to_owned()),
    };
    if channels != 1 {
        return Err(format!("a matrix with {channels} channels"));
    }
    let data = match map.get("data") {
        Some(Value::Seq(items)) => {
            sequence_numbers(items).map_err(|i| format!("'data' item {i} is not a number"))?
        }
        Some(Value::Number(v)) => vec![*v],
        Some(Value::Empty) | None if rows * cols == 0 => Vec::new(),
        Some(other) => return Err(format!("'data' is {}", other.describe())),
        None => return Err("no 'data'".to_owned()),
    };
    if data.len() != rows * cols {
        return Err(format!("{rows}x{cols} with {} numbers in 'data'", data.len()));
    }
    Ok(Numbers { rows, cols, data })
}

/// The channel count of an OpenCV element type (`d` = 1, `3d` = 3); the type letter must be one
/// OpenCV writes (`u c w s i f d`).
fn element_channels(dt: &str) -> std::result::Result<usize, String> {
    let digits: String = dt.chars().take_while(char::is_ascii_digit).collect();
    let rest = &dt[digits.len()..];
    if rest.len() != 1 || !"ucwsifd".contains(rest) {
        return Err(format!("'dt' is '{dt}', expected an element type such as d"));
    }
    if digits.is_empty() {
        return Ok(1);
    }
    digits.parse().map_err(|_| format!("'dt' is '{dt}'"))
}

/// The files a calibration is read from; a key is taken from the first file that has it.
struct Sources {
    files: Vec<(PathBuf, Value)>,
}

impl Sources {
    fn open(paths: &[&Path]) -> Result<Sources> {
        let mut files = Vec::new();
        for path in paths {
            std::fs::metadata(path).map_err(|source| Error::Io {
                path: path.to_path_buf(),
                source,
            })?;
            let checked = super::structure::read_calibration_file(path)?;
            let root = filestorage::parse(path, &checked.text, checked.xml)?;
            files.push((path.to_path_buf(), root));
        }
        Ok(Sources { files })
    }

    /// All the files, for errors about a key none of them has.
    fn all_paths(&self) -> PathBuf {
        let names: Vec<String> = self.files.iter().map(|(p, _)| p.display().to_string()).collect();
        PathBuf::from(names.join(" + "))
    }

    /// The first file holding the first of `keys` found with a value: (file, key, value).
    fn find<'a>(&'a self, keys: &[&'a str]) -> Option<(&'a Path, &'a str, &'a Value)> {
        keys.iter().find_map(|key| {
            self.files.iter().find_map(|(path, root)| {
                root.get(key)
                    .filter(|v| **v != Value::Empty)
                    .map(|v| (path.as_path(), *key, v))
            })
        })
    }

    fn required(&self, keys: &[&str], expected: &str) -> Result<(PathBuf, String, Numbers)> {
        match self.find(keys) {
            Some((path, key, value)) => Ok((path.to_path_buf(), key.to_owned(), numbers(value, path, key)?)),
            None => Err(Error::MissingKey {
                path: self.all_paths(),
                key: keys.join(" or "),
                expected: expected.to_owned(),
            }),
        }
    }
}

fn check_finite(path: &Path, key: &str, m: &Numbers) -> Result<()> {
    if let Some(v) = m.data.iter().find(|v| !v.is_finite()) {
        return Err(Error::BadValue {
            path: path.to_path_buf(),
            key: key.to_owned(),
            expected: "finite numbers".to_owned(),
            found: format!("{v}"),
        });
    }
    Ok(())
}

fn camera_matrix(path: &Path, key: &str, m: &Numbers) -> Result<(f64, f64, f64, f64)> {
    if m.rows != 3 || m.cols != 3 {
        return Err(Error::BadValue {
            path: path.to_path_buf(),
            key: key.to_owned(),
            expected: "a 3x3 camera matrix".to_owned(),
            found: m.shape(),
        });
    }
    check_finite(path, key, m)?;
    let d = &m.data;
    let bad = |expected: &str, found: String| Error::BadValue {
        path: path.to_path_buf(),
        key: key.to_owned(),
        expected: expected.to_owned(),
        found,
    };
    if d[1] != 0.0 {
        return Err(bad(
            "zero skew K[0][1] (skew is not supported)",
            format!("{}", d[1]),
        ));
    }
    if d[3] != 0.0 || d[6] != 0.0 || d[7] != 0.0 || d[8] != 1.0 {
        return Err(bad(
            "last row [0, 0, 1] and K[1][0] = 0",
            format!("{:?}", [d[3], d[6], d[7], d[8]]),
        ));
    }
    if d[0] <= 0.0 || d[4] <= 0.0 {
        return Err(bad(
            "positive focal lengths",
            format!("fx = {}, fy = {}", d[0], d[4]),
        ));
    }
    Ok((d[0], d[4], d[2], d[5]))
}

fn distortion(path: &Path, key: &str, m: &Numbers) -> Result<Distortion> {
    if !m.is_vector() {
        return Err(Error::BadValue {
            path: path.to_path_buf(),
            key: key.to_owned(),
            expected: "a vector of 0, 4, 5, 8 or 12 distortion coefficients".to_owned(),
            found: m.shape(),
        });
    }
    check_finite(path, key, m)?;
    Distortion::new(m.data.clone()).map_err(|e| Error::BadValue {
        path: path.to_path_buf(),
        key: key.to_owned(),
        expected: "0, 4, 5, 8 or 12 distortion coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]])"
            .to_owned(),
        found: format!("{} ({e})", m.shape()),
    })
}

fn image_size(src: &Sources) -> Result<ImageSize> {
    let as_u32 = |path: &Path, key: &str, v: f64| -> Result<u32> {
        if v.fract() == 0.0 && v >= 1.0 && v <= f64::from(u32::MAX) {
            // Checked above: a positive whole number that fits.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            Ok(v as u32)
        } else {
            Err(Error::BadValue {
                path: path.to_path_buf(),
                key: key.to_owned(),
                expected: "a positive whole number of pixels".to_owned(),
                found: format!("{v}"),
            })
        }
    };
    let single = |path: &Path, key: &str, n: &Value| -> Result<u32> {
        let v = numbers(n, path, key)?;
        if v.data.len() != 1 {
            return Err(Error::BadValue {
                path: path.to_path_buf(),
                key: key.to_owned(),
                expected: "a single integer".to_owned(),
                found: v.shape(),
            });
        }
        as_u32(path, key, v.data[0])
    };
    if let (Some((wp, wk, wn)), Some((hp, hk, hn))) =
        (src.find(&["image_width"]), src.find(&["image_height"]))
    {
        return Ok(ImageSize {
            width: single(wp, wk, wn)?,
            height: single(hp, hk, hn)?,
        });
    }
    if let Some((path, key, n)) = src.find(&["image_size", "imageSize"]) {
        let n = numbers(n, path, key)?;
        if n.data.len() != 2 {
            return Err(Error::BadValue {
                path: path.to_path_buf(),
                key: key.to_owned(),
                expected: "[width, height]".to_owned(),
                found: n.shape(),
            });
        }
        return Ok(ImageSize {
            width: as_u32(path, key, n.data[0])?,
            height: as_u32(path, key, n.data[1])?,
        });
    }
    Err(Error::MissingKey {
        path: src.all_paths(),
        key: "image_width and image_height".to_owned(),
        expected: "the calibrated image size in pixels, two integers (or image_size: [width, height]); \
                   OpenCV's stereo_calib sample does not write it: add it"
            .to_owned(),
    })
}

impl StereoRig {
    /// Reads an OpenCV FileStorage stereo calibration (YAML or XML; see the [module docs](self)).
    ///
    /// Errors name the file, the key and the expected against the actual shape.
    pub fn read_opencv(path: impl AsRef<Path>) -> Result<StereoRig> {
        Self::read_opencv_files(&[path.as_ref()])
    }

    /// Reads a stereo calibration whose keys are spread over several OpenCV FileStorage files, e.g.
    /// the `intrinsics.yml` and `extrinsics.yml` of OpenCV's stereo_calib sample (with the image
    /// size added). Each key is taken from the first file that has it.
    pub fn read_opencv_files(paths: &[&Path]) -> Result<StereoRig> {
        let src = Sources::open(paths)?;
        let first = paths.first().map(|p| p.to_path_buf()).unwrap_or_default();
        let mut cams = Vec::new();
        for (k, m, d) in [("K1", "M1", "D1"), ("K2", "M2", "D2")] {
            let (kpath, kkey, kn) = src.required(&[k, m], "the 3x3 camera matrix")?;
            let (fx, fy, cx, cy) = camera_matrix(&kpath, &kkey, &kn)?;
            let (dpath, dkey, dn) = src.required(&[d], "the distortion coefficients (OpenCV order)")?;
            let distortion = distortion(&dpath, &dkey, &dn)?;
            cams.push((fx, fy, cx, cy, distortion));
        }
        let size = image_size(&src)?;
        let (rpath, _, rn) = src.required(&["R"], "the 3x3 rotation right_from_left")?;
        let path = rpath.as_path();
        check_finite(path, "R", &rn)?;
        let rotation = if rn.rows == 3 && rn.cols == 3 {
            let m = Matrix3::from_row_slice(&rn.data);
            let ortho = (m.transpose() * m - Matrix3::identity()).abs().max();
            if ortho > 1e-6 || (m.determinant() - 1.0).abs() > 1e-6 {
                return Err(Error::BadValue {
                    path: path.to_path_buf(),
                    key: "R".to_owned(),
                    expected: "a rotation matrix (orthonormal, determinant 1, to 1e-6)".to_owned(),
                    found: format!("|R^T R - I| = {ortho:.3e}, det = {}", m.determinant()),
                });
            }
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m))
        } else if rn.is_vector() && rn.data.len() == 3 {
            UnitQuaternion::from_scaled_axis(Vector3::new(rn.data[0], rn.data[1], rn.data[2]))
        } else {
            return Err(Error::BadValue {
                path: path.to_path_buf(),
                key: "R".to_owned(),
                expected: "a 3x3 rotation matrix (or a 3-vector Rodrigues rotation)".to_owned(),
                found: rn.shape(),
            });
        };
        let (tpath, _, tn) = src.required(&["T"], "the translation right_from_left, mm")?;
        let path = tpath.as_path();
        check_finite(path, "T", &tn)?;
        if !(tn.is_vector() && tn.data.len() == 3) {
            return Err(Error::BadValue {
                path: path.to_path_buf(),
                key: "T".to_owned(),
                expected: "a 3x1 translation".to_owned(),
                found: tn.shape(),
            });
        }
        let translation = Translation3::new(tn.data[0], tn.data[1], tn.data[2]);
        if translation.vector.norm() == 0.0 {
            return Err(Error::BadValue {
                path: path.to_path_buf(),
                key: "T".to_owned(),
                expected: "a non-zero baseline".to_owned(),
                found: "[0, 0, 0]".to_owned(),
            });
        }
        let mut it = cams.into_iter().map(|(fx, fy, cx, cy, distortion)| Camera {
            image_size: size,
            fx,
            fy,
            cx,
            cy,
            distortion,
        });
        let (Some(left), Some(right)) = (it.next(), it.next()) else {
            return Err(Error::Calibration("internal: two cameras expected".to_owned()));
        };
        for (camera, key) in [(&left, "D1"), (&right, "D2")] {
            camera.validate().map_err(|e| Error::BadValue {
                path: first.clone(),
                key: key.to_owned(),
                expected: "distortion that leaves every image pixel a ray".to_owned(),
                found: e.to_string(),
            })?;
        }
        let rig = StereoRig {
            left,
            right,
            right_from_left: Isometry3::from_parts(translation, rotation),
        };
        rig.validate().map_err(|e| Error::BadValue {
            path: first.clone(),
            key: "K1/D1/K2/D2/R/T".to_owned(),
            expected: "a valid stereo calibration".to_owned(),
            found: e.to_string(),
        })?;
        Ok(rig)
    }

    /// Writes this rig as an OpenCV FileStorage YAML file (`K1 D1 K2 D2 R T image_width
    /// image_height`, numbers at full double precision).
    pub fn write_opencv_yaml(&self, path: impl AsRef<Path>) -> Result<()> {
        self.write_opencv(path.as_ref(), opencv::core::FileStorage_Mode::FORMAT_YAML as i32)
    }

    /// Writes this rig as an OpenCV FileStorage XML file (same keys as [`StereoRig::write_opencv_yaml`]).
    pub fn write_opencv_xml(&self, path: impl AsRef<Path>) -> Result<()> {
        self.write_opencv(path.as_ref(), opencv::core::FileStorage_Mode::FORMAT_XML as i32)
    }

    fn write_opencv(&self, path: &Path, format: i32) -> Result<()> {
        self.validate()?;
        if self.left.image_size != self.right.image_size {
            return Err(Error::InvalidParameter {
                name: "image_size".to_owned(),
                value: f64::from(self.right.image_size.width),
                expected: "the same image size for both cameras (the OpenCV format stores one)",
            });
        }
        // Into memory first, then whole to the file: a full disk or a kill mid-write never leaves a
        // cut calibration where a good one was.
        let name = if format == opencv::core::FileStorage_Mode::FORMAT_XML as i32 {
            ".xml"
        } else {
            ".yaml"
        };
        let ctx = || format!("writing {}", path.display());
        let mode = opencv::core::FileStorage_Mode::WRITE as i32
            | opencv::core::FileStorage_Mode::MEMORY as i32
            | format;
        let mut fs = FileStorage::new(name, mode, "").map_err(cv(ctx()))?;
        if !fs.is_opened().map_err(cv(ctx()))? {
            return Err(Error::Io {
                path: path.to_path_buf(),
                source: std::io::Error::other("OpenCV FileStorage could not open it for writing"),
            });
        }
        let size = self.left.image_size;
        let r = self.right_from_left.rotation.to_rotation_matrix().into_inner();
        let t = self.right_from_left.translation.vector;
        fs.write_comment("gelstereo stereo calibration: p_in_right = R * p_in_left + T (mm); pixel (0,0) = centre of the top-left pixel", false)
            .map_err(cv(ctx()))?;
        for (kkey, dkey, cam) in [("K1", "D1", &self.left), ("K2", "D2", &self.right)] {
            fs.write_mat(kkey, &mat(3, 3, cam.k_matrix().transpose().as_slice())?)
                .map_err(cv(ctx()))?;
            fs.write_mat(
                dkey,
                &mat(1, cam.distortion.coeffs.len(), &cam.distortion.coeffs)?,
            )
            .map_err(cv(ctx()))?;
        }
        fs.write_mat("R", &mat(3, 3, r.transpose().as_slice())?)
            .map_err(cv(ctx()))?;
        fs.write_mat("T", &mat(3, 1, t.as_slice())?).map_err(cv(ctx()))?;
        let w = i32::try_from(size.width).map_err(|_| Error::InvalidParameter {
            name: "image_width".to_owned(),
            value: f64::from(size.width),
            expected: "a width that fits an int",
        })?;
        let h = i32::try_from(size.height).map_err(|_| Error::InvalidParameter {
            name: "image_height".to_owned(),
            value: f64::from(size.height),
            expected: "a height that fits an int",
        })?;
        fs.write_i32("image_width", w).map_err(cv(ctx()))?;
        fs.write_i32("image_height", h).map_err(cv(ctx()))?;
        let text = fs.release_and_get_string().map_err(cv(ctx()))?;
        gelstereo_core::files::write_whole(path, text.as_bytes()).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })
    }
}
