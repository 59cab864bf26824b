//! Conversions between this crate's types and OpenCV matrices, for callers that mix the two (and
//! for the checkerboard calibration).

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use opencv::core::{Mat, MatTrait, MatTraitConst, Scalar};

use crate::camera::{Camera, Distortion};
use crate::error::{Error, Result};

pub(crate) fn cv_err(context: impl Into<String>) -> impl FnOnce(opencv::Error) -> Error {
    let context = context.into();
    move |source| Error::OpenCv { context, source }
}

/// A `rows` x `cols` `CV_64F` matrix from row-major `data` (missing entries are zero).
pub fn mat_from_rows(rows: usize, cols: usize, data: &[f64]) -> Result<Mat> {
    let too_big = |n: usize| Error::InvalidParameter {
        name: "matrix size".to_owned(),
        // Only used to report a size that does not fit an i32.
        #[allow(clippy::cast_precision_loss)]
        value: n as f64,
        expected: "a matrix size that fits an int",
    };
    let r = i32::try_from(rows).map_err(|_| too_big(rows))?;
    let c = i32::try_from(cols).map_err(|_| too_big(cols))?;
    let mut m = Mat::new_rows_cols_with_default(r, c, opencv::core::CV_64F, Scalar::all(0.0))
        .map_err(cv_err("Mat::new"))?;
    if cols > 0 {
        for (i, v) in data.iter().enumerate().take(rows * cols) {
            let (ri, ci) = (
                i32::try_from(i / cols).unwrap_or(0),
                i32::try_from(i % cols).unwrap_or(0),
            );
            *m.at_2d_mut::<f64>(ri, ci).map_err(cv_err("Mat::at"))? = *v;
        }
    }
    Ok(m)
}

/// The elements of a single-channel matrix (any depth) as f64, row-major, with its shape.
pub fn mat_to_rows(m: &Mat) -> Result<(usize, usize, Vec<f64>)> {
    if m.empty() {
        return Ok((0, 0, Vec::new()));
    }
    let mut m64 = Mat::default();
    m.convert_to(&mut m64, opencv::core::CV_64F, 1.0, 0.0)
        .map_err(cv_err("Mat::convertTo"))?;
    let (rows, cols) = (m64.rows(), m64.cols() * m64.channels());
    let m64 = m64.reshape(1, rows).map_err(cv_err("Mat::reshape"))?;
    let mut data = Vec::new();
    for r in 0..rows {
        for c in 0..cols {
            data.push(*m64.at_2d::<f64>(r, c).map_err(cv_err("Mat::at"))?);
        }
    }
    Ok((
        usize::try_from(rows).unwrap_or(0),
        usize::try_from(cols).unwrap_or(0),
        data,
    ))
}

/// OpenCV's 3x3 camera matrix of `camera`.
pub fn camera_matrix(camera: &Camera) -> Result<Mat> {
    mat_from_rows(3, 3, camera.k_matrix().transpose().as_slice())
}

/// OpenCV's distortion vector (1 x N) of `camera`.
pub fn distortion_coeffs(camera: &Camera) -> Result<Mat> {
    mat_from_rows(1, camera.distortion.coeffs.len(), &camera.distortion.coeffs)
}

/// `R` (3x3) and `T` (3x1) of an isometry, as OpenCV matrices.
pub fn rotation_translation(iso: &Isometry3<f64>) -> Result<(Mat, Mat)> {
    let r = iso.rotation.to_rotation_matrix().into_inner();
    Ok((
        mat_from_rows(3, 3, r.transpose().as_slice())?,
        mat_from_rows(3, 1, iso.translation.vector.as_slice())?,
    ))
}

/// The isometry `p -> R p + T` from OpenCV's `R` (3x3, or a 3-vector Rodrigues) and `T` (3 values).
pub fn isometry_from_rt(r: &Mat, t: &Mat) -> Result<Isometry3<f64>> {
    let (rr, rc, rd) = mat_to_rows(r)?;
    let (_, _, td) = mat_to_rows(t)?;
    let bad = |what: &str| Error::Calibration(format!("OpenCV returned {what}"));
    if td.len() != 3 {
        return Err(bad("a translation without 3 values"));
    }
    let rotation = if rr == 3 && rc == 3 {
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(&rd)))
    } else if rd.len() == 3 {
        UnitQuaternion::from_scaled_axis(nalgebra::Vector3::new(rd[0], rd[1], rd[2]))
    } else {
        return Err(bad("a rotation that is neither 3x3 nor a 3-vector"));
    };
    Ok(Isometry3::from_parts(
        Translation3::new(td[0], td[1], td[2]),
        rotation,
    ))
}

/// A camera from OpenCV's camera matrix and distortion vector; errors when `K` has skew or is not
/// 3x3, or the distortion has an unsupported length.
pub fn camera_from_cv(image_size: gelstereo_core::ImageSize, k: &Mat, d: &Mat) -> Result<Camera> {
    let (kr, kc, kd) = mat_to_rows(k)?;
    if kr != 3 || kc != 3 {
        return Err(Error::Calibration(format!(
            "OpenCV returned a {kr}x{kc} camera matrix"
        )));
    }
    let (_, _, dd) = mat_to_rows(d)?;
    let camera = Camera {
        image_size,
        fx: kd[0],
        fy: kd[4],
        cx: kd[2],
        cy: kd[5],
        distortion: Distortion::new(dd)?,
    };
    camera.validate()?;
    Ok(camera)
}
