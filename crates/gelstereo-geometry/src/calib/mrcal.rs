//! mrcal `.cameramodel` files: one Python-literal dict per camera.
//!
//! Keys read: `lensmodel` (`LENSMODEL_PINHOLE`, `LENSMODEL_OPENCV4`, `5`, `8`, `12`; any other model is
//! rejected by name; the legacy key names `distortion_model` / `lens_model` and the `DISTORTION_`
//! prefix are accepted like mrcal does), `intrinsics` (`fx fy cx cy` then the distortion in OpenCV
//! order), `extrinsics` or `rt_cam_ref` (`rt_cam_ref` = Rodrigues `r` then `t`, mapping points in the
//! reference frame into this camera's frame), `imagersize` (`[width, height]`). Other keys
//! (`valid_intrinsics_region`, `optimization_inputs`, `icam_intrinsics`) are parsed and ignored.
//!
//! The reference frame is the LEFT camera: the left model's extrinsics are zero and the right
//! model's are `right_from_left`. Translations are in mm (mrcal itself is unit-agnostic).
//! We write numbers in Rust's shortest round-trip form (mrcal writes 10 significant digits).

use std::fmt::Write as _;
use std::path::Path;

use gelstereo_core::ImageSize;
use gelstereo_core::limits::{ECHO_CHARS, shorten};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use super::pyliteral::{self, Value};
use crate::camera::{Camera, Distortion, StereoRig};
use crate::error::{Error, Result};

/// One parsed `.cameramodel`: the camera and its `rt_cam_ref` as an isometry `cam_from_ref`.
struct Model {
    camera: Camera,
    cam_from_ref: Isometry3<f64>,
}

fn lens_model_name(n_distortion: usize) -> Option<&'static str> {
    match n_distortion {
        0 => Some("LENSMODEL_PINHOLE"),
        4 => Some("LENSMODEL_OPENCV4"),
        5 => Some("LENSMODEL_OPENCV5"),
        8 => Some("LENSMODEL_OPENCV8"),
        12 => Some("LENSMODEL_OPENCV12"),
        _ => None,
    }
}

fn numbers(
    path: &Path,
    key: &str,
    v: &Value,
    expected_len: Option<usize>,
    expected: &str,
) -> Result<Vec<f64>> {
    let bad = || Error::BadValue {
        path: path.to_path_buf(),
        key: key.to_owned(),
        expected: expected.to_owned(),
        found: v.describe(),
    };
    let Value::List(items) = v else { return Err(bad()) };
    let out: Option<Vec<f64>> = items.iter().map(Value::as_f64).collect();
    let out = out.ok_or_else(bad)?;
    if expected_len.is_some_and(|n| n != out.len()) {
        return Err(bad());
    }
    Ok(out)
}

/// The file's text parsed as the Python dict literal a mrcal .cameramodel is.
fn read_dict(path: &Path) -> Result<Vec<(String, Value)>> {
    let bytes = super::structure::read_at_most(path)?;
    let text = String::from_utf8(bytes).map_err(|e| Error::Syntax {
        path: path.to_path_buf(),
        line: 0,
        message: format!(
            "not UTF-8 text (an invalid byte at offset {}): expected a mrcal .cameramodel",
            e.utf8_error().valid_up_to()
        ),
    })?;
    let value = pyliteral::parse(&text).map_err(|e| Error::Syntax {
        path: path.to_path_buf(),
        line: e.line,
        message: format!("not a Python literal: {}", e.message),
    })?;
    let Value::Dict(dict) = value else {
        return Err(Error::Syntax {
            path: path.to_path_buf(),
            line: 1,
            message: format!(
                "expected a dict (a mrcal .cameramodel), found {}",
                value.describe()
            ),
        });
    };
    Ok(dict)
}

/// The lens model named by `lm` (the value of `lm_key`; the older `DISTORTION_` spelling taken
/// as `LENSMODEL_`) and its number of distortion coefficients; only OpenCV's models are read.
fn lens_model(path: &Path, lm_key: &str, lm: &Value) -> Result<(String, usize)> {
    let Value::Str(model) = lm else {
        return Err(Error::BadValue {
            path: path.to_path_buf(),
            key: lm_key.to_owned(),
            expected: "a string naming the lens model".to_owned(),
            found: lm.describe(),
        });
    };
    let model = model.replace("DISTORTION", "LENSMODEL");
    let n_dist = match model.as_str() {
        "LENSMODEL_PINHOLE" => 0,
        "LENSMODEL_OPENCV4" => 4,
        "LENSMODEL_OPENCV5" => 5,
        "LENSMODEL_OPENCV8" => 8,
        "LENSMODEL_OPENCV12" => 12,
        _ => {
            return Err(Error::UnsupportedLensModel {
                path: path.to_path_buf(),
                model: shorten(&model, ECHO_CHARS).into_owned(),
            });
        }
    };
    Ok((model, n_dist))
}

/// The image width and height from `imagersize`: positive whole numbers of pixels.
fn image_dims(path: &Path, size: &[f64]) -> Result<[u32; 2]> {
    let mut dims = [0u32; 2];
    for (d, v) in dims.iter_mut().zip(size) {
        if !(v.fract() == 0.0 && *v >= 1.0 && *v <= f64::from(u32::MAX)) {
            return Err(Error::BadValue {
                path: path.to_path_buf(),
                key: "imagersize".to_owned(),
                expected: "positive whole numbers of pixels".to_owned(),
                found: format!("{v}"),
            });
        }
        // Checked above: a positive whole number that fits.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        {
            *d = *v as u32;
        }
    }
    Ok(dims)
}

fn read_model(path: &Path) -> Result<Model> {
    let dict = read_dict(path)?;
    let get = |keys: &[&str], expected: &str| -> Result<(&str, &Value)> {
        for key in keys {
            if let Some((k, v)) = dict.iter().find(|(k, _)| k == key) {
                return Ok((k.as_str(), v));
            }
        }
        Err(Error::MissingKey {
            path: path.to_path_buf(),
            key: keys.join(" or "),
            expected: expected.to_owned(),
        })
    };
    let (lm_key, lm) = get(
        &["lensmodel", "distortion_model", "lens_model"],
        "the lens model name, e.g. 'LENSMODEL_OPENCV8'",
    )?;
    let (model, n_dist) = lens_model(path, lm_key, lm)?;
    let (_, iv) = get(&["intrinsics"], "fx fy cx cy and the distortion coefficients")?;
    let intr = numbers(
        path,
        "intrinsics",
        iv,
        Some(4 + n_dist),
        &format!(
            "a list of {} numbers (fx fy cx cy + {n_dist} distortion coefficients of {model})",
            4 + n_dist
        ),
    )?;
    let (ext_key, ev) = get(
        &["extrinsics", "rt_cam_ref"],
        "rt_cam_ref: Rodrigues r then t (6 numbers)",
    )?;
    let rt = numbers(
        path,
        ext_key,
        ev,
        Some(6),
        "a list of 6 numbers (rt_cam_ref: Rodrigues r then t)",
    )?;
    let (_, sv) = get(&["imagersize"], "[width, height] in pixels")?;
    let size = numbers(
        path,
        "imagersize",
        sv,
        Some(2),
        "a list of 2 integers [width, height]",
    )?;
    let dims = image_dims(path, &size)?;
    let camera = Camera {
        image_size: ImageSize {
            width: dims[0],
            height: dims[1],
        },
        fx: intr[0],
        fy: intr[1],
        cx: intr[2],
        cy: intr[3],
        distortion: Distortion {
            coeffs: intr[4..].to_vec(),
        },
    };
    camera.validate().map_err(|e| Error::BadValue {
        path: path.to_path_buf(),
        key: "intrinsics".to_owned(),
        expected: "valid intrinsics".to_owned(),
        found: e.to_string(),
    })?;
    let cam_from_ref = Isometry3::from_parts(
        Translation3::new(rt[3], rt[4], rt[5]),
        UnitQuaternion::from_scaled_axis(Vector3::new(rt[0], rt[1], rt[2])),
    );
    Ok(Model { camera, cam_from_ref })
}

fn write_model(path: &Path, camera: &Camera, rt: [f64; 6], note: &str) -> Result<()> {
    camera.validate()?;
    let n = camera.distortion.coeffs.len();
    let name = lens_model_name(n).ok_or(Error::DistortionCount { count: n })?;
    let mut s = String::new();
    let list = |v: &[f64]| v.iter().map(|x| format!(" {x:?},")).collect::<String>();
    let intr: Vec<f64> = [camera.fx, camera.fy, camera.cx, camera.cy]
        .into_iter()
        .chain(camera.distortion.coeffs.iter().copied())
        .collect();
    // Writing to a String cannot fail.
    let _ = write!(
        s,
        "# {note}\n{{\n    'lensmodel':  '{name}',\n\n    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n    \
         'intrinsics': [{}],\n\n    # extrinsics are rt_fromref\n    'extrinsics': [{}],\n\n    \
         'imagersize': [ {}, {},],\n}}\n",
        list(&intr),
        list(&rt),
        camera.image_size.width,
        camera.image_size.height
    );
    gelstereo_core::files::write_whole(path, s.as_bytes()).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// `rt` (Rodrigues r, then t) of an isometry.
pub(crate) fn rt_of(iso: &Isometry3<f64>) -> [f64; 6] {
    let r = iso.rotation.scaled_axis();
    let t = iso.translation.vector;
    [r.x, r.y, r.z, t.x, t.y, t.z]
}

impl StereoRig {
    /// Reads a pair of mrcal `.cameramodel` files (see the [module docs](self)).
    ///
    /// The two models' extrinsics may use any common reference frame: the rig's `right_from_left` is
    /// `right_from_ref * left_from_ref⁻¹`, so a pair written by mrcal with the left camera at the
    /// reference gives `right_from_left` = the right model's `rt_cam_ref`.
    pub fn read_mrcal(left: impl AsRef<Path>, right: impl AsRef<Path>) -> Result<StereoRig> {
        let l = read_model(left.as_ref())?;
        let r = read_model(right.as_ref())?;
        let right_from_left = r.cam_from_ref * l.cam_from_ref.inverse();
        let rig = StereoRig {
            left: l.camera,
            right: r.camera,
            right_from_left,
        };
        rig.validate().map_err(|e| Error::BadValue {
            path: right.as_ref().to_path_buf(),
            key: "extrinsics".to_owned(),
            expected: "a valid stereo pair with the left model".to_owned(),
            found: e.to_string(),
        })?;
        // Keep the exactly-written case exact: when the left model sits at the reference, use the
        // right model's extrinsics as they are (no composition round-off).
        if rt_of(&l.cam_from_ref).iter().all(|&v| v == 0.0) {
            return Ok(StereoRig {
                right_from_left: r.cam_from_ref,
                ..rig
            });
        }
        Ok(rig)
    }

    /// Writes the rig as two mrcal `.cameramodel` files with the LEFT camera as the reference
    /// (left extrinsics zero, right extrinsics = `right_from_left` as `rt`).
    pub fn write_mrcal(&self, left: impl AsRef<Path>, right: impl AsRef<Path>) -> Result<()> {
        self.validate()?;
        write_model(
            left.as_ref(),
            &self.left,
            [0.0; 6],
            "gelstereo left camera (reference frame); translations in mm",
        )?;
        write_model(
            right.as_ref(),
            &self.right,
            rt_of(&self.right_from_left),
            "gelstereo right camera; extrinsics = rt_cam_ref with ref = left camera; translations in mm",
        )
    }
}
