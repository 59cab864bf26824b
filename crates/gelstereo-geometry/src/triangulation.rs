//! Two-view triangulation from undistorted rays, with per-point reprojection error and rejection.
//!
//! Methods ([`TriangulationMethod`]):
//! - [`Midpoint`](TriangulationMethod::Midpoint): the classical mid-point of the common perpendicular
//!   of the two rays (least-squares depths).
//! - [`LeeCiveraMid2`](TriangulationMethod::LeeCiveraMid2): the "Mid2" generalised mid-point of
//!   S. H. Lee and J. Civera, "Triangulation: Why Optimize?", BMVC 2019 (arXiv:1907.11917): depths
//!   from the sine rule, `λ0 = |f1 × t| / |f0 × f1|`, `λ1 = |f0 × t| / |f0 × f1|`, point
//!   `(λ0 f0 + t + λ1 f1) / 2`, with the paper's chirality test.
//! - [`Lindstrom`](TriangulationMethod::Lindstrom): P. Lindstrom, "Triangulation Made Easy", CVPR 2010,
//!   the two-iteration `niter2` algorithm: the L2-optimal correction of both points in the normalised
//!   (undistorted, `z = 1`) image planes so that they satisfy the epipolar constraint exactly, then
//!   the intersection of the corrected rays.
//! - [`PixelOptimal`](TriangulationMethod::PixelOptimal) (default): Lindstrom's point refined by
//!   Gauss-Newton on the reprojection error in PIXELS of both views, distortion included (the
//!   maximum-likelihood estimate under isotropic pixel noise; Hartley & Zisserman, "Multiple View
//!   Geometry", 2nd ed., sec. 12.1). Lindstrom alone is optimal in the normalised plane, which
//!   differs from pixels by the focal lengths and the local distortion scale.
//!
//! Every result carries its reprojection error in pixels in both views; a pair is rejected with a
//! [`Rejection`] (never NaN) when a pixel cannot be undistorted, the rays are (nearly) parallel, the
//! point lies behind a camera, or the reprojection error exceeds a bound.

use gelstereo_core::{Point2, StereoPair, View};
use nalgebra::{Matrix3, Matrix3x4, Point3, Vector2, Vector3, Vector4};

use crate::camera::{Camera, StereoRig};
use crate::error::{Error, Result};

/// Which triangulation method to use (see the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TriangulationMethod {
    /// Mid-point of the common perpendicular.
    Midpoint,
    /// Lee & Civera (2019) Mid2.
    LeeCiveraMid2,
    /// Lindstrom (2010) niter2: optimal in the normalised image planes.
    Lindstrom,
    /// Lindstrom, then Gauss-Newton on the pixel reprojection error (distortion included).
    #[default]
    PixelOptimal,
}

/// Settings of a [`Triangulator`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulationConfig {
    /// The method.
    pub method: TriangulationMethod,
    /// Reject a pair whose reprojection error in either view exceeds this, px. Default 2 px: about
    /// 4 sigma of the sub-pixel noise of a good marker localizer, and an eighth of the reference
    /// sensor's marker pitch (~16 px), so a pair from neighbouring markers cannot pass.
    pub max_reprojection_error_px: f64,
    /// Reject rays closer than this to parallel (angle between them), rad. Default 1e-4 rad: at the
    /// reference sensor's 10 mm baseline that is a point ~100 m away; markers subtend ~0.4 rad.
    pub min_ray_angle_rad: f64,
    /// Gauss-Newton iterations of [`TriangulationMethod::PixelOptimal`] (it stops earlier, after a
    /// step below 1e-7 mm, taken without evaluating the cost again: 2e-6 px at the reference
    /// sensor's 24 mm and 520 px). Default 5; two suffice at sub-pixel noise.
    pub max_refine_iterations: usize,
}

impl Default for TriangulationConfig {
    fn default() -> Self {
        Self {
            method: TriangulationMethod::default(),
            max_reprojection_error_px: 2.0,
            min_ray_angle_rad: 1e-4,
            max_refine_iterations: 5,
        }
    }
}

/// Why a pair was not triangulated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rejection {
    /// The pixel could not be undistorted (outside the distortion model's valid region).
    Undistortion {
        /// Which view.
        view: View,
    },
    /// The rays are parallel or nearly so.
    ParallelRays {
        /// Angle between the rays, rad.
        angle_rad: f64,
    },
    /// The rays meet behind a camera (or the point is on its plane).
    BehindCamera {
        /// The camera.
        view: View,
    },
    /// The reprojection error in a view is larger than the configured bound.
    Reprojection {
        /// Reprojection error in the left view, px.
        left_px: f64,
        /// Reprojection error in the right view, px.
        right_px: f64,
        /// The bound, px.
        bound_px: f64,
    },
}

impl std::fmt::Display for Rejection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = |v: &View| match v {
            View::Left => "left",
            View::Right => "right",
        };
        match self {
            Rejection::Undistortion { view } => {
                write!(
                    f,
                    "the {} pixel cannot be undistorted (outside the lens model's range)",
                    name(view)
                )
            }
            Rejection::ParallelRays { angle_rad } => {
                write!(f, "the rays are nearly parallel ({angle_rad:.3e} rad apart)")
            }
            Rejection::BehindCamera { view } => write!(f, "the rays meet behind the {} camera", name(view)),
            Rejection::Reprojection {
                left_px,
                right_px,
                bound_px,
            } => write!(
                f,
                "reprojection error {left_px:.3} px (left), {right_px:.3} px (right) exceeds {bound_px} px"
            ),
        }
    }
}

/// A triangulated marker.
#[derive(Debug, Clone, PartialEq)]
pub struct Triangulated {
    /// The point in the LEFT camera frame, mm.
    pub p_in_left_mm: Point3<f64>,
    /// Distance between the reprojected point and the observation in each view, px.
    pub reprojection_error_px: StereoPair<f64>,
}

impl Triangulated {
    /// The larger of the two reprojection errors, px.
    pub fn max_reprojection_error_px(&self) -> f64 {
        self.reprojection_error_px
            .left
            .max(self.reprojection_error_px.right)
    }
}

/// Triangulates left/right pixel pairs of a calibrated [`StereoRig`].
#[derive(Debug, Clone)]
pub struct Triangulator {
    rig: StereoRig,
    config: TriangulationConfig,
    /// `left_from_right` rotation.
    r_lr: Matrix3<f64>,
    /// `right_from_left` rotation.
    r_rl: Matrix3<f64>,
    /// `right_from_left` translation, mm.
    t_rl: Vector3<f64>,
    /// Right camera centre in the left frame, mm.
    c_right_in_left: Vector3<f64>,
    /// Essential matrix with `x_left^T E x_right = 0` (normalised coordinates).
    e_lr: Matrix3<f64>,
    /// `tan(min_ray_angle_rad)` below 45 degrees (`check_ray_angle`), else `None`.
    min_ray_tan: Option<f64>,
}

/// A Gauss-Newton step of [`TriangulationMethod::PixelOptimal`] this short (mm) ends the refinement.
const NEGLIGIBLE_STEP_MM: f64 = 1e-7;

/// A 3-vector's cross-product matrix `[v]x`.
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

impl Triangulator {
    /// A triangulator for `rig` (validated here).
    pub fn new(rig: StereoRig, config: TriangulationConfig) -> Result<Self> {
        rig.validate()?;
        for (name, value) in [
            ("max_reprojection_error_px", config.max_reprojection_error_px),
            ("min_ray_angle_rad", config.min_ray_angle_rad),
        ] {
            if value.is_nan() || value < 0.0 {
                return Err(Error::InvalidParameter {
                    name: name.to_owned(),
                    value,
                    expected: "a number >= 0 (infinity disables the check)",
                });
            }
        }
        let r_rl = rig.right_from_left.rotation.to_rotation_matrix().into_inner();
        let t_rl = rig.right_from_left.translation.vector;
        let r_lr = r_rl.transpose();
        let c_right_in_left = -(r_lr * t_rl);
        // x_right ~ R x_left + t  =>  x_right^T [t]x R x_left = 0  =>  x_left^T (R^T [t]x^T) x_right = 0.
        let e_lr = r_lr * skew(&t_rl).transpose();
        Ok(Self {
            rig,
            config,
            r_lr,
            r_rl,
            t_rl,
            c_right_in_left,
            e_lr,
            min_ray_tan: (config.min_ray_angle_rad < std::f64::consts::FRAC_PI_4)
                .then(|| config.min_ray_angle_rad.tan()),
        })
    }

    /// The rig.
    pub fn rig(&self) -> &StereoRig {
        &self.rig
    }

    /// The settings.
    pub fn config(&self) -> &TriangulationConfig {
        &self.config
    }

    /// Triangulates one pair of pixels (left, right) into the left camera frame.
    pub fn triangulate(&self, left: Point2, right: Point2) -> Result<Triangulated, Rejection> {
        let nl = self
            .rig
            .left
            .undistort(left)
            .ok_or(Rejection::Undistortion { view: View::Left })?;
        let nr = self
            .rig
            .right
            .undistort(right)
            .ok_or(Rejection::Undistortion { view: View::Right })?;
        let (p, residual) = self.point_from_normalized(nl, nr, left, right)?;
        let (el, er) = match residual {
            Some(r) => (r.xy().norm(), Vector2::new(r.z, r.w).norm()),
            None => {
                let el = reprojection(&self.rig.left, &p, left)
                    .ok_or(Rejection::BehindCamera { view: View::Left })?;
                let pr = Point3::from(self.r_rl * p.coords + self.t_rl);
                let er = reprojection(&self.rig.right, &pr, right)
                    .ok_or(Rejection::BehindCamera { view: View::Right })?;
                (el, er)
            }
        };
        let bound = self.config.max_reprojection_error_px;
        if el > bound || er > bound {
            return Err(Rejection::Reprojection {
                left_px: el,
                right_px: er,
                bound_px: bound,
            });
        }
        Ok(Triangulated {
            p_in_left_mm: p,
            reprojection_error_px: StereoPair::new(el, er),
        })
    }

    /// Triangulates many pairs: `left[i]` with `right[i]`. Errors only when the lengths differ; each
    /// pair's own result says whether it was rejected.
    pub fn triangulate_all(
        &self,
        left: &[Point2],
        right: &[Point2],
    ) -> Result<Vec<Result<Triangulated, Rejection>>> {
        if left.len() != right.len() {
            return Err(Error::LengthMismatch {
                left_len: left.len(),
                right_len: right.len(),
            });
        }
        Ok(left
            .iter()
            .zip(right)
            .map(|(l, r)| self.triangulate(*l, *r))
            .collect())
    }

    /// Epipolar error of a pair, px: the distance of each undistorted point from the epipolar line of
    /// the other (in the normalised plane, scaled by that camera's mean focal length), averaged over
    /// the two views. `None` when a pixel cannot be undistorted.
    pub fn epipolar_error_px(&self, left: Point2, right: Point2) -> Option<f64> {
        let nl = self.rig.left.undistort(left)?;
        let nr = self.rig.right.undistort(right)?;
        Some(self.epipolar_error_normalized(nl, nr))
    }

    /// [`Triangulator::epipolar_error_px`] from normalised coordinates.
    pub fn epipolar_error_normalized(&self, nl: Vector2<f64>, nr: Vector2<f64>) -> f64 {
        let x = Vector3::new(nl.x, nl.y, 1.0);
        let xp = Vector3::new(nr.x, nr.y, 1.0);
        let line_in_left = self.e_lr * xp;
        let line_in_right = self.e_lr.transpose() * x;
        let c = x.dot(&line_in_left).abs();
        let dl = c / line_in_left.xy().norm() * 0.5 * (self.rig.left.fx + self.rig.left.fy);
        let dr = c / line_in_right.xy().norm() * 0.5 * (self.rig.right.fx + self.rig.right.fy);
        0.5 * (dl + dr)
    }

    /// The 3-D point from normalised coordinates, by the configured method (no reprojection bound),
    /// with its pixel residuals (left x, y, right x, y) where the method computed them.
    fn point_from_normalized(
        &self,
        nl: Vector2<f64>,
        nr: Vector2<f64>,
        left_px: Point2,
        right_px: Point2,
    ) -> Result<(Point3<f64>, Option<Vector4<f64>>), Rejection> {
        let f0 = Vector3::new(nl.x, nl.y, 1.0);
        let f1 = self.r_lr * Vector3::new(nr.x, nr.y, 1.0);
        self.check_ray_angle(&f0, &f1)?;
        let t = self.c_right_in_left;
        let (p, residual) = match self.config.method {
            TriangulationMethod::Midpoint => (midpoint(&f0, &f1, &t)?, None),
            TriangulationMethod::LeeCiveraMid2 => (mid2(&f0, &f1, &t)?, None),
            TriangulationMethod::Lindstrom => (self.lindstrom(nl, nr)?, None),
            TriangulationMethod::PixelOptimal => {
                let p0 = self.lindstrom(nl, nr)?;
                self.refine_px(p0, left_px, right_px)
            }
        };
        let in_right = self.r_rl * p + self.t_rl;
        if p.z.is_nan() || p.z <= 0.0 {
            return Err(Rejection::BehindCamera { view: View::Left });
        }
        if in_right.z.is_nan() || in_right.z <= 0.0 {
            return Err(Rejection::BehindCamera { view: View::Right });
        }
        Ok((Point3::from(p), residual))
    }

    /// Rejects rays `f0`, `f1` (left frame) less than `min_ray_angle_rad` apart. The angle
    /// `atan2(|f0 x f1|, f0 . f1)` is only computed for a rejection: below a right angle it is
    /// under the bound exactly when `|f0 x f1| < tan(bound) (f0 . f1)`.
    fn check_ray_angle(&self, f0: &Vector3<f64>, f1: &Vector3<f64>) -> Result<(), Rejection> {
        let (sine, cosine) = (f0.cross(f1).norm(), f0.dot(f1));
        let clearly_apart = self
            .min_ray_tan
            .is_some_and(|tan| cosine <= 0.0 || sine >= tan * cosine * (1.0 + 1e-12));
        if clearly_apart && sine.is_finite() {
            return Ok(());
        }
        let bound = self.config.min_ray_angle_rad;
        let angle_rad = sine.atan2(cosine);
        if angle_rad.is_nan() || angle_rad < bound {
            return Err(Rejection::ParallelRays { angle_rad });
        }
        Ok(())
    }

    /// Lindstrom's niter2 in the normalised planes, then the intersection of the corrected rays.
    fn lindstrom(&self, nl: Vector2<f64>, nr: Vector2<f64>) -> Result<Vector3<f64>, Rejection> {
        let e = &self.e_lr;
        let x = Vector3::new(nl.x, nl.y, 1.0);
        let xp = Vector3::new(nr.x, nr.y, 1.0);
        let e2 = e.fixed_view::<2, 2>(0, 0).into_owned();
        let mut n = (e * xp).xy();
        let mut np = (e.transpose() * x).xy();
        let a = n.dot(&(e2 * np));
        let b = 0.5 * (n.norm_squared() + np.norm_squared());
        let c = x.dot(&(e * xp));
        let d = (b * b - a * c).sqrt();
        let mut lambda = c / (b + d);
        let dx = n * lambda;
        let dxp = np * lambda;
        n -= e2 * dxp;
        np -= e2.transpose() * dx;
        lambda *= 2.0 * d / (n.norm_squared() + np.norm_squared());
        let xc = x - Vector3::new(lambda * n.x, lambda * n.y, 0.0);
        let xpc = xp - Vector3::new(lambda * np.x, lambda * np.y, 0.0);
        if !(xc.iter().chain(xpc.iter()).all(|v| v.is_finite())) {
            return Err(Rejection::ParallelRays { angle_rad: 0.0 });
        }
        // The corrected rays intersect: their mid-point is the intersection.
        midpoint(&xc, &(self.r_lr * xpc), &self.c_right_in_left)
    }

    /// Gauss-Newton on the pixel reprojection error of both views, from `p0` (left frame, mm); with
    /// the residuals at the point returned, where they are known.
    fn refine_px(
        &self,
        p0: Vector3<f64>,
        left_px: Point2,
        right_px: Point2,
    ) -> (Vector3<f64>, Option<Vector4<f64>>) {
        let mut p = p0;
        let cost = |p: &Vector3<f64>| -> Option<(Vector4<f64>, Matrix3x4<f64>)> {
            let (rl, jl) = residual_and_jacobian(&self.rig.left, p, left_px)?;
            let pr = self.r_rl * p + self.t_rl;
            let (rr, jr) = residual_and_jacobian(&self.rig.right, &pr, right_px)?;
            let jr = jr * self.r_rl;
            let r = Vector4::new(rl.x, rl.y, rr.x, rr.y);
            let mut jt = Matrix3x4::zeros();
            jt.fixed_view_mut::<3, 2>(0, 0).copy_from(&jl.transpose());
            jt.fixed_view_mut::<3, 2>(0, 2).copy_from(&jr.transpose());
            Some((r, jt))
        };
        let Some((mut r, mut jt)) = cost(&p) else {
            return (p0, None);
        };
        for _ in 0..self.config.max_refine_iterations {
            let h = jt * jt.transpose();
            let g = jt * r;
            let Some(step) = h.cholesky().map(|c| c.solve(&g)) else {
                break;
            };
            let cand = p - step;
            if step.norm() < NEGLIGIBLE_STEP_MM {
                // Converged: what a further step could change is ~ this step squared, and the
                // residuals at `cand` are those at `p` moved along the Jacobian, to that order.
                return (cand, Some(r - jt.transpose() * step));
            }
            match cost(&cand) {
                Some((r2, jt2)) if r2.norm_squared() <= r.norm_squared() => {
                    p = cand;
                    r = r2;
                    jt = jt2;
                }
                _ => break,
            }
        }
        (p, Some(r))
    }
}

/// Pixel residual (projection - observation) of `p_in_cam` and its 2x3 Jacobian.
fn residual_and_jacobian(
    camera: &Camera,
    p_in_cam: &Vector3<f64>,
    observed: Point2,
) -> Option<(Vector2<f64>, nalgebra::Matrix2x3<f64>)> {
    if p_in_cam.z.is_nan() || p_in_cam.z <= 0.0 {
        return None;
    }
    let iz = 1.0 / p_in_cam.z;
    let n = Vector2::new(p_in_cam.x * iz, p_in_cam.y * iz);
    let (d, jd) = camera.distortion.distort_with_jacobian(n)?;
    let r = Vector2::new(
        camera.fx * d.x + camera.cx - observed.x,
        camera.fy * d.y + camera.cy - observed.y,
    );
    let dn = nalgebra::Matrix2x3::new(iz, 0.0, -n.x * iz, 0.0, iz, -n.y * iz);
    let f = nalgebra::Matrix2::new(camera.fx, 0.0, 0.0, camera.fy);
    Some((r, f * jd * dn))
}

/// Distance between the projection of `p_in_cam` and `observed`, px; `None` behind the camera.
fn reprojection(camera: &Camera, p_in_cam: &Point3<f64>, observed: Point2) -> Option<f64> {
    camera.project(p_in_cam).map(|q| q.distance(observed))
}

/// Classical mid-point: rays `λ0 f0` and `t + λ1 f1` (left frame), least-squares depths.
fn midpoint(f0: &Vector3<f64>, f1: &Vector3<f64>, t: &Vector3<f64>) -> Result<Vector3<f64>, Rejection> {
    let (a, b, c) = (f0.dot(f0), f0.dot(f1), f1.dot(f1));
    let (d, e) = (f0.dot(t), f1.dot(t));
    let den = a * c - b * b;
    if den.is_nan() || den <= f64::EPSILON * a * c {
        return Err(Rejection::ParallelRays { angle_rad: 0.0 });
    }
    let l0 = (c * d - b * e) / den;
    let l1 = (b * d - a * e) / den;
    if l0.is_nan() || l0 <= 0.0 {
        return Err(Rejection::BehindCamera { view: View::Left });
    }
    if l1.is_nan() || l1 <= 0.0 {
        return Err(Rejection::BehindCamera { view: View::Right });
    }
    Ok((f0 * l0 + t + f1 * l1) * 0.5)
}

/// Lee & Civera Mid2 with their chirality test (sec. 5 of the paper): among the four sign choices
/// of the sine-rule depths, (+, +) must give the closest pair of ray points.
fn mid2(f0: &Vector3<f64>, f1: &Vector3<f64>, t: &Vector3<f64>) -> Result<Vector3<f64>, Rejection> {
    let f0 = f0.normalize();
    let f1 = f1.normalize();
    let s = f0.cross(&f1).norm();
    let l0 = f1.cross(t).norm() / s;
    let l1 = f0.cross(t).norm() / s;
    if !(l0.is_finite() && l1.is_finite()) {
        return Err(Rejection::ParallelRays {
            angle_rad: s.atan2(f0.dot(&f1)).abs(),
        });
    }
    let gap = |s0: f64, s1: f64| (t + f1 * (s1 * l1) - f0 * (s0 * l0)).norm_squared();
    let pp = gap(1.0, 1.0);
    if pp > gap(-1.0, 1.0) {
        return Err(Rejection::BehindCamera { view: View::Left });
    }
    if pp > gap(1.0, -1.0) {
        return Err(Rejection::BehindCamera { view: View::Right });
    }
    if pp > gap(-1.0, -1.0) {
        return Err(Rejection::BehindCamera { view: View::Left });
    }
    Ok((f0 * l0 + t + f1 * l1) * 0.5)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;

    fn triangulator(min_ray_angle_rad: f64) -> Triangulator {
        let size = gelstereo_core::ImageSize {
            width: 640,
            height: 480,
        };
        let camera = Camera::pinhole(size, 520.0, 520.0, 320.0, 240.0);
        let rig = StereoRig {
            left: camera.clone(),
            right: camera,
            right_from_left: nalgebra::Isometry3::translation(-10.0, 0.0, 0.0),
        };
        let config = TriangulationConfig {
            min_ray_angle_rad,
            ..Default::default()
        };
        Triangulator::new(rig, config).unwrap()
    }

    /// The angle test without the arctangent decides as `atan2(|f0 x f1|, f0 . f1) < bound` does,
    /// for rays from parallel to opposite, at bounds below and above 45 degrees, and reports that
    /// angle when it rejects.
    #[test]
    fn the_ray_angle_test_decides_as_the_arctangent() {
        let f0 = Vector3::new(0.1, -0.2, 1.0);
        let axis = f0.cross(&Vector3::new(0.3, 0.5, 0.2)).normalize();
        for bound in [1e-4, 0.3, 1.0, 2.0] {
            let t = triangulator(bound);
            let mut rejected = 0;
            for k in 0..=4000 {
                let angle = std::f64::consts::PI * f64::from(k) / 4000.0 + 1e-13 * f64::from(k % 3);
                for near in [angle, bound, bound * (1.0 + 1e-15), bound * (1.0 - 1e-15)] {
                    let rotation = nalgebra::Rotation3::new(axis * near);
                    let f1 = (rotation * f0) * 1.7;
                    let exact = f0.cross(&f1).norm().atan2(f0.dot(&f1));
                    match t.check_ray_angle(&f0, &f1) {
                        Ok(()) => assert!(exact >= bound, "{near} kept against {bound}"),
                        Err(Rejection::ParallelRays { angle_rad }) => {
                            assert!(exact < bound, "{near} rejected against {bound}");
                            assert_eq!(angle_rad, exact);
                            rejected += 1;
                        }
                        Err(other) => panic!("{other:?}"),
                    }
                }
            }
            assert!(rejected > 0, "{bound}");
        }
        let t = triangulator(1e-4);
        let nan = Vector3::new(f64::NAN, 0.0, 1.0);
        assert!(t.check_ray_angle(&nan, &Vector3::new(0.0, 0.0, 1.0)).is_err());
    }
}
