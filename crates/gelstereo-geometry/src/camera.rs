//! Pinhole cameras with OpenCV's distortion model, and the calibrated stereo rig.
//!
//! The projection is OpenCV's (`cv::projectPoints`, see the "Detailed Description" of the calib3d
//! module): with `x' = X/Z`, `y' = Y/Z`, `r² = x'² + y'²`,
//!
//! ```text
//! x'' = x' (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶) + 2 p1 x'y' + p2 (r² + 2x'²) + s1 r² + s2 r⁴
//! y'' = y' (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶) + p1 (r² + 2y'²) + 2 p2 x'y' + s3 r² + s4 r⁴
//! u = fx x'' + cx,  v = fy y'' + cy
//! ```
//!
//! Pixel (0, 0) is the centre of the top-left pixel, as in OpenCV and mrcal. No skew.

use gelstereo_core::{ImageSize, Point2};
use nalgebra::{Isometry3, Matrix2, Point3, Unit, Vector2, Vector3};

use crate::error::{Error, Result};

/// Lens distortion coefficients in OpenCV order `k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]]`.
///
/// Valid lengths are 0 (pinhole), 4, 5, 8 and 12; OpenCV's 14-coefficient tilted model is rejected by
/// name ([`Error::TiltedDistortion`]). Build it with [`Distortion::new`] to have the length checked;
/// projection treats missing trailing coefficients as zero.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Distortion {
    /// The coefficients, OpenCV order.
    pub coeffs: Vec<f64>,
}

/// Names of OpenCV's distortion coefficients, in order.
pub const DISTORTION_NAMES: [&str; 12] = [
    "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
];

impl Distortion {
    /// No distortion (a pure pinhole camera).
    pub fn none() -> Self {
        Self { coeffs: Vec::new() }
    }

    /// Checked constructor: 0, 4, 5, 8 or 12 finite coefficients.
    pub fn new(coeffs: Vec<f64>) -> Result<Self> {
        let d = Self { coeffs };
        d.validate()?;
        Ok(d)
    }

    /// Checks the number of coefficients and that they are finite.
    pub fn validate(&self) -> Result<()> {
        match self.coeffs.len() {
            0 | 4 | 5 | 8 | 12 => {}
            14 => return Err(Error::TiltedDistortion),
            count => return Err(Error::DistortionCount { count }),
        }
        for (name, &value) in DISTORTION_NAMES.iter().zip(&self.coeffs) {
            if !value.is_finite() {
                return Err(Error::InvalidParameter {
                    name: (*name).to_owned(),
                    value,
                    expected: "a finite number",
                });
            }
        }
        Ok(())
    }

    /// The 12 coefficients with missing trailing ones set to zero.
    pub fn padded(&self) -> [f64; 12] {
        let mut out = [0.0; 12];
        for (o, c) in out.iter_mut().zip(&self.coeffs) {
            *o = *c;
        }
        out
    }

    /// True when every coefficient is zero (or there are none).
    pub fn is_zero(&self) -> bool {
        self.coeffs.iter().all(|&c| c == 0.0)
    }

    /// Applies the distortion to normalised coordinates `(x/z, y/z)`; returns the distorted
    /// normalised point and its 2x2 Jacobian with respect to the input, or `None` where the rational
    /// model's denominator vanishes or the result is not finite.
    pub fn distort_with_jacobian(&self, xy: Vector2<f64>) -> Option<(Vector2<f64>, Matrix2<f64>)> {
        match self.coeffs[..] {
            [k1, k2, p1, p2] => return distort_polynomial([k1, k2, p1, p2, 0.0], xy),
            [k1, k2, p1, p2, k3] => return distort_polynomial([k1, k2, p1, p2, k3], xy),
            _ => {}
        }
        let [k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4] = self.padded();
        let (x, y) = (xy.x, xy.y);
        let r2 = x * x + y * y;
        let r4 = r2 * r2;
        let a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let b = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6));
        if b == 0.0 {
            return None;
        }
        // One division: trackers distort every marker several times a frame.
        let inv_b = 1.0 / b;
        let radial = a * inv_b;
        let da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let db = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2);
        let d_radial = (da - radial * db) * inv_b;
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4;
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4;
        let dsx = s1 + 2.0 * s2 * r2;
        let dsy = s3 + 2.0 * s4 * r2;
        let j00 = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x + 2.0 * x * dsx;
        let j01 = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * y * dsx;
        let j10 = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * x * dsy;
        let j11 = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x + 2.0 * y * dsy;
        let out = Vector2::new(xd, yd);
        let jac = Matrix2::new(j00, j01, j10, j11);
        let finite = (xd + yd + j00 + j01 + j10 + j11).is_finite();
        finite.then_some((out, jac))
    }

    /// Applies the distortion to normalised coordinates `(x/z, y/z)`.
    pub fn distort(&self, xy: Vector2<f64>) -> Option<Vector2<f64>> {
        self.distort_with_jacobian(xy).map(|(d, _)| d)
    }

    /// Inverts [`Distortion::distort`]: the normalised point whose distortion is `distorted`.
    ///
    /// Starts, like `cv::undistortPoints`, from the distorted point itself, then runs Newton's method
    /// with the analytic Jacobian (step-halving when a step does not reduce the residual) until the
    /// residual is below 1e-14 (about 1e-11 px at f = 1000 px). `None` when it does not converge in
    /// 100 iterations or the Jacobian is singular.
    pub fn undistort(&self, distorted: Vector2<f64>) -> Option<Vector2<f64>> {
        if self.is_zero() {
            return Some(distorted);
        }
        const TOL: f64 = 1e-14;
        // Newton's residual after a step of length s is about s^2 x the distortion's curvature over
        // its slope: ~1e-16 after a step of 1e-8 (`undistortion_residual_is_within_its_tolerance`).
        const NEGLIGIBLE_STEP: f64 = 1e-8;
        let mut x = distorted;
        let (fx0, mut jac) = self.distort_with_jacobian(x)?;
        let mut res = fx0 - distorted;
        for _ in 0..100 {
            // Squared norms: no square roots in the loop.
            if res.norm_squared() <= TOL * TOL {
                return Some(x);
            }
            let det = jac[(0, 0)] * jac[(1, 1)] - jac[(0, 1)] * jac[(1, 0)];
            if det == 0.0 || !det.is_finite() {
                return None;
            }
            let inv_det = 1.0 / det;
            let step = Vector2::new(
                (jac[(1, 1)] * res.x - jac[(0, 1)] * res.y) * inv_det,
                (jac[(0, 0)] * res.y - jac[(1, 0)] * res.x) * inv_det,
            );
            if step.norm_squared() <= NEGLIGIBLE_STEP * NEGLIGIBLE_STEP {
                // Quadratic convergence: what is left after this step is ~ step^2, far below TOL,
                // so the step is taken without evaluating the distortion once more.
                return Some(x - step);
            }
            let mut t = 1.0;
            loop {
                let cand = x - step * t;
                if let Some((f2, j2)) = self.distort_with_jacobian(cand) {
                    let r2 = f2 - distorted;
                    if r2.norm_squared() < res.norm_squared() {
                        x = cand;
                        jac = j2;
                        res = r2;
                        break;
                    }
                }
                t *= 0.5;
                if t < 1e-6 {
                    return (res.norm() <= 1e-10).then_some(x);
                }
            }
        }
        (res.norm() <= 1e-10).then_some(x)
    }
}

/// [`Distortion::distort_with_jacobian`] of the common 4- and 5-coefficient model (`k1 k2 p1 p2
/// [k3]`): the same arithmetic without the rational and thin-prism terms, whose zero coefficients
/// leave every result bit as it is (the denominator is exactly 1, the added terms exactly 0), at
/// about half the cost; trackers distort every marker several times a frame.
fn distort_polynomial(
    [k1, k2, p1, p2, k3]: [f64; 5],
    xy: Vector2<f64>,
) -> Option<(Vector2<f64>, Matrix2<f64>)> {
    let (x, y) = (xy.x, xy.y);
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    let d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
    let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let j00 = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x;
    let j01 = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y;
    let j11 = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x;
    let jac = Matrix2::new(j00, j01, j01, j11);
    let finite = (xd + yd + j00 + j01 + j01 + j11).is_finite();
    finite.then_some((Vector2::new(xd, yd), jac))
}

/// A pinhole camera with OpenCV distortion. Intrinsics in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Size of the images this calibration is valid for.
    pub image_size: ImageSize,
    /// Focal length along x, px.
    pub fx: f64,
    /// Focal length along y, px.
    pub fy: f64,
    /// Principal point x, px ((0, 0) = centre of the top-left pixel).
    pub cx: f64,
    /// Principal point y, px.
    pub cy: f64,
    /// Lens distortion.
    pub distortion: Distortion,
}

impl Camera {
    /// A camera without distortion.
    pub fn pinhole(image_size: ImageSize, fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self {
            image_size,
            fx,
            fy,
            cx,
            cy,
            distortion: Distortion::none(),
        }
    }

    /// Checks that the intrinsics are finite, the focal lengths positive, the image non-empty and
    /// the distortion of a supported length.
    pub fn validate(&self) -> Result<()> {
        for (name, value) in [("fx", self.fx), ("fy", self.fy)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(Error::InvalidParameter {
                    name: name.to_owned(),
                    value,
                    expected: "a finite focal length > 0 px",
                });
            }
        }
        for (name, value) in [("cx", self.cx), ("cy", self.cy)] {
            if !value.is_finite() {
                return Err(Error::InvalidParameter {
                    name: name.to_owned(),
                    value,
                    expected: "a finite principal point",
                });
            }
        }
        for (name, value) in [
            ("image_width", self.image_size.width),
            ("image_height", self.image_size.height),
        ] {
            if value == 0 {
                return Err(Error::InvalidParameter {
                    name: name.to_owned(),
                    value: 0.0,
                    expected: "an image size > 0 px",
                });
            }
        }
        self.distortion.validate()?;
        self.check_inner_pixels_undistort()
    }

    /// Checks that the centre and the four points halfway between it and the corners have rays:
    /// absurd distortion coefficients (k1 = 1e300) are finite but leave no pixel with a ray, and
    /// every marker would be lost. (The corners themselves may lie past where a fitted polynomial
    /// turns over, outside the region the calibration board covered.)
    fn check_inner_pixels_undistort(&self) -> Result<()> {
        if self.distortion.is_zero() {
            return Ok(());
        }
        let (w, h) = (
            f64::from(self.image_size.width) - 1.0,
            f64::from(self.image_size.height) - 1.0,
        );
        for (x, y) in [
            (w / 2.0, h / 2.0),
            (w / 4.0, h / 4.0),
            (3.0 * w / 4.0, h / 4.0),
            (w / 4.0, 3.0 * h / 4.0),
            (3.0 * w / 4.0, 3.0 * h / 4.0),
        ] {
            if self.undistort(Point2::new(x, y)).is_none() {
                return Err(Error::Calibration(format!(
                    "distortion {:?}: pixel ({x}, {y}) has no ray (undistortion does not converge); \
                     expected coefficients under which the pixels inside the image have one",
                    self.distortion.coeffs
                )));
            }
        }
        Ok(())
    }

    /// The 3x3 camera matrix `K`.
    pub fn k_matrix(&self) -> nalgebra::Matrix3<f64> {
        nalgebra::Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// Projects a point given in this camera's frame (mm) to pixels. `None` when `z <= 0` (behind
    /// or on the camera plane) or the distortion model is singular there.
    pub fn project(&self, p_in_cam: &Point3<f64>) -> Option<Point2> {
        if p_in_cam.z.is_nan() || p_in_cam.z <= 0.0 {
            return None;
        }
        let n = Vector2::new(p_in_cam.x / p_in_cam.z, p_in_cam.y / p_in_cam.z);
        self.project_normalized(n)
    }

    /// Projects normalised coordinates `(x/z, y/z)` to pixels (distortion, then `K`).
    pub fn project_normalized(&self, xy: Vector2<f64>) -> Option<Point2> {
        let d = self.distortion.distort(xy)?;
        let p = Point2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy);
        (p.x.is_finite() && p.y.is_finite()).then_some(p)
    }

    /// The normalised coordinates `(x/z, y/z)` of the ray through pixel `p` (iterative undistortion,
    /// like `cv::undistortPoints` but run to convergence). `None` when the iteration does not converge.
    pub fn undistort(&self, p: Point2) -> Option<Vector2<f64>> {
        let d = Vector2::new((p.x - self.cx) / self.fx, (p.y - self.cy) / self.fy);
        if !(d.x.is_finite() && d.y.is_finite()) {
            return None;
        }
        self.distortion.undistort(d)
    }

    /// Unit direction (camera frame, z > 0) of the ray through pixel `p`.
    pub fn ray(&self, p: Point2) -> Option<Unit<Vector3<f64>>> {
        let n = self.undistort(p)?;
        Some(Unit::new_normalize(Vector3::new(n.x, n.y, 1.0)))
    }

    /// Whether pixel `p` lies inside the image (pixel centres from 0 to size - 1, plus half a pixel).
    pub fn contains(&self, p: Point2) -> bool {
        p.x >= -0.5
            && p.y >= -0.5
            && p.x < f64::from(self.image_size.width) - 0.5
            && p.y < f64::from(self.image_size.height) - 0.5
    }

    /// Checks that an image of `size` matches this calibration; `camera` ("left"/"right") is named in
    /// the error.
    pub fn check_image_size(&self, camera: &'static str, size: ImageSize) -> Result<()> {
        if size == self.image_size {
            Ok(())
        } else {
            Err(Error::ImageSizeMismatch {
                camera,
                expected_width: self.image_size.width,
                expected_height: self.image_size.height,
                found_width: size.width,
                found_height: size.height,
            })
        }
    }
}

/// A calibrated stereo pair. The reference 3-D frame is the LEFT camera's; units mm.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoRig {
    /// The left camera (reference frame).
    pub left: Camera,
    /// The right camera.
    pub right: Camera,
    /// `p_in_right = right_from_left * p_in_left` (OpenCV `stereoCalibrate`'s `R`, `T`), mm.
    pub right_from_left: Isometry3<f64>,
}

impl StereoRig {
    /// Checks both cameras and that the extrinsics are finite with a non-zero baseline.
    pub fn validate(&self) -> Result<()> {
        self.left.validate()?;
        self.right.validate()?;
        let t = self.right_from_left.translation.vector;
        let q = self.right_from_left.rotation.coords;
        if !(t.iter().chain(q.iter()).all(|v| v.is_finite())) {
            return Err(Error::InvalidParameter {
                name: "right_from_left".to_owned(),
                value: f64::NAN,
                expected: "finite extrinsics",
            });
        }
        if t.norm().is_nan() || t.norm() <= 0.0 {
            return Err(Error::InvalidParameter {
                name: "T".to_owned(),
                value: t.norm(),
                expected: "a non-zero baseline",
            });
        }
        Ok(())
    }

    /// Baseline length, mm.
    pub fn baseline_mm(&self) -> f64 {
        self.right_from_left.translation.vector.norm()
    }

    /// `left_from_right`, the inverse of [`StereoRig::right_from_left`].
    pub fn left_from_right(&self) -> Isometry3<f64> {
        self.right_from_left.inverse()
    }

    /// Projects a point given in the LEFT camera frame (mm) into both views.
    pub fn project(&self, p_in_left: &Point3<f64>) -> Option<(Point2, Point2)> {
        let l = self.left.project(p_in_left)?;
        let r = self.right.project(&(self.right_from_left * p_in_left))?;
        Some((l, r))
    }

    /// Checks image sizes of a stereo frame against the calibration.
    pub fn check_image_sizes(&self, left: ImageSize, right: ImageSize) -> Result<()> {
        self.left.check_image_size("left", left)?;
        self.right.check_image_size("right", right)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(coeffs: Vec<f64>) -> Camera {
        Camera {
            image_size: ImageSize {
                width: 640,
                height: 480,
            },
            fx: 600.0,
            fy: 605.0,
            cx: 320.5,
            cy: 239.5,
            distortion: Distortion { coeffs },
        }
    }

    #[test]
    fn distortion_lengths() {
        for n in [0, 4, 5, 8, 12] {
            assert!(Distortion::new(vec![0.0; n]).is_ok(), "{n}");
        }
        assert!(matches!(
            Distortion::new(vec![0.0; 14]),
            Err(Error::TiltedDistortion)
        ));
        assert!(matches!(
            Distortion::new(vec![0.0; 6]),
            Err(Error::DistortionCount { count: 6 })
        ));
    }

    /// The 4- and 5-coefficient model's own path gives the bits of the full model with its other
    /// coefficients zero, and the same `None`s.
    #[test]
    fn the_polynomial_path_gives_the_full_models_bits() {
        for coeffs in [
            vec![-0.28, 0.09, 1e-3, -5e-4, -0.01],
            vec![0.3, -0.1, -2e-3, 4e-4],
        ] {
            let short = Distortion::new(coeffs.clone()).unwrap();
            let mut padded = coeffs.clone();
            padded.resize(8, 0.0);
            let full = Distortion::new(padded).unwrap();
            for k in 0..4000 {
                let t = f64::from(k);
                let xy = Vector2::new((t * 0.37).sin() * t * 2e-4, (t * 0.73).cos() * t * 3e-4);
                let bits = |d: Option<(Vector2<f64>, Matrix2<f64>)>| {
                    d.map(|(v, j)| (v.map(f64::to_bits), j.map(f64::to_bits)))
                };
                assert_eq!(
                    bits(short.distort_with_jacobian(xy)),
                    bits(full.distort_with_jacobian(xy)),
                    "{coeffs:?} at {xy:?}"
                );
            }
            let far = Vector2::new(1e200, 1e200);
            assert!(short.distort_with_jacobian(far).is_none());
            assert!(full.distort_with_jacobian(far).is_none());
        }
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let d = Distortion {
            coeffs: vec![
                -0.3, 0.12, 1e-3, -2e-3, -0.02, 0.05, -0.01, 0.003, 1e-3, -2e-4, 3e-4, 1e-4,
            ],
        };
        let x = Vector2::new(0.31, -0.22);
        let (_, jac) = d.distort_with_jacobian(x).unwrap();
        let h = 1e-7;
        for c in 0..2 {
            let mut e = Vector2::zeros();
            e[c] = h;
            let num = (d.distort(x + e).unwrap() - d.distort(x - e).unwrap()) / (2.0 * h);
            for r in 0..2 {
                assert!(
                    (num[r] - jac[(r, c)]).abs() < 1e-7,
                    "J[{r},{c}] {} vs {}",
                    num[r],
                    jac[(r, c)]
                );
            }
        }
    }

    #[test]
    fn project_undistort_round_trip() {
        let c = cam(vec![-0.28, 0.09, 8e-4, -5e-4, -0.01, 0.02, 0.001, -0.003]);
        for i in 0..20 {
            for j in 0..20 {
                let p = Point2::new(10.0 + 31.0 * f64::from(i), 8.0 + 24.0 * f64::from(j));
                let n = c.undistort(p).unwrap();
                let back = c.project_normalized(n).unwrap();
                assert!(back.distance(p) < 1e-9, "{p:?} -> {back:?}");
                let ray = c.ray(p).unwrap();
                let again = c.project(&Point3::from(ray.into_inner() * 37.0)).unwrap();
                assert!(again.distance(p) < 1e-9);
            }
        }
        assert!(c.project(&Point3::new(1.0, 1.0, 0.0)).is_none());
        assert!(c.project(&Point3::new(1.0, 1.0, -5.0)).is_none());
    }

    #[test]
    fn undistortion_residual_is_within_its_tolerance() {
        // A strong wide-angle model: its last Newton step is taken without a check.
        let c = cam(vec![-0.28, 0.09, 8e-4, -5e-4, -0.01, 0.02, 0.001, -0.003]);
        let mut worst: f64 = 0.0;
        for i in 0..=64 {
            for j in 0..=48 {
                let p = Point2::new(10.0 * f64::from(i), 10.0 * f64::from(j));
                let d = Vector2::new((p.x - c.cx) / c.fx, (p.y - c.cy) / c.fy);
                let n = c.distortion.undistort(d).unwrap();
                worst = worst.max((c.distortion.distort(n).unwrap() - d).norm());
            }
        }
        assert!(worst <= 1e-14, "largest residual {worst:e}");
    }

    #[test]
    fn invalid_parameters_are_named() {
        let bad = |f: &dyn Fn(&mut Camera)| {
            let mut c = cam(vec![0.0; 5]);
            f(&mut c);
            c.validate().unwrap_err().to_string()
        };
        assert!(bad(&|c| c.fx = 0.0).contains("fx = 0"));
        assert!(bad(&|c| c.fy = f64::NAN).contains("fy"));
        assert!(bad(&|c| c.cx = f64::INFINITY).contains("cx"));
        assert!(bad(&|c| c.image_size.height = 0).contains("image_height"));
        assert!(bad(&|c| c.distortion.coeffs[2] = f64::NAN).contains("p1"));
        assert!(bad(&|c| c.distortion.coeffs.push(0.0)).contains("6 coefficients"));
        let rig = StereoRig {
            left: cam(vec![]),
            right: cam(vec![]),
            right_from_left: Isometry3::translation(0.0, 0.0, 0.0),
        };
        assert!(rig.validate().unwrap_err().to_string().contains("baseline"));
        let rig = StereoRig {
            right_from_left: Isometry3::translation(f64::NAN, 0.0, 0.0),
            ..rig
        };
        assert!(rig.validate().unwrap_err().to_string().contains("finite"));
        // A NaN pixel has no ray.
        assert!(
            cam(vec![-0.2, 0.0, 0.0, 0.0])
                .ray(Point2::new(f64::NAN, 3.0))
                .is_none()
        );
    }

    #[test]
    fn image_size_mismatch_is_named() {
        let c = cam(vec![]);
        let e = c
            .check_image_size(
                "left",
                ImageSize {
                    width: 320,
                    height: 240,
                },
            )
            .unwrap_err();
        assert!(
            e.to_string().contains("640x480") && e.to_string().contains("320x240"),
            "{e}"
        );
    }
}
