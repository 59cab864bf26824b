//! A camera's undistortion, tabulated on a coarse pixel grid to start Newton's method close to the
//! answer.
//!
//! [`Camera::undistort`] starts from the distorted point itself and needs four or five evaluations
//! of the distortion to converge; a tracker undistorts every marker of every frame in both views.
//! Interpolating a table of exact undistortions every [`GRID_STEP_PX`] pixels starts it within
//! ~1e-6 of the answer, and one Newton step finishes: the result is the same fixed point to the
//! same tolerance, at about half the cost.

use gelstereo_core::Point2;
use nalgebra::Vector2;

use crate::camera::Camera;

/// Spacing of the table's nodes, px. The distortion is smooth over a few pixels: bilinear
/// interpolation between nodes 8 px apart is off by ~1e-6 in normalised coordinates at the corners
/// of the reference sensor's lens, where Newton's method converges in one step.
pub const GRID_STEP_PX: f64 = 8.0;

/// Exact undistortions of a camera at the nodes of a pixel grid that covers its image with one
/// node to spare on every side.
#[derive(Debug, Clone)]
pub struct UndistortionGrid {
    camera: Camera,
    /// Pixel coordinates of node (0, 0).
    origin: Point2,
    cols: usize,
    rows: usize,
    /// Row-major normalised coordinates; NaN where the pixel has no ray.
    nodes: Vec<Vector2<f64>>,
}

impl UndistortionGrid {
    /// Tabulates `camera`'s undistortion (a few thousand undistortions for a 640 x 480 image).
    pub fn new(camera: &Camera) -> Self {
        let origin = Point2::new(-GRID_STEP_PX, -GRID_STEP_PX);
        let nodes_along = |len: u32| (f64::from(len) / GRID_STEP_PX).ceil() as usize + 3;
        let (cols, rows) = (
            nodes_along(camera.image_size.width),
            nodes_along(camera.image_size.height),
        );
        let nan = Vector2::new(f64::NAN, f64::NAN);
        let nodes = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (r, c)))
            .map(|(r, c)| {
                let p = Point2::new(
                    origin.x + c as f64 * GRID_STEP_PX,
                    origin.y + r as f64 * GRID_STEP_PX,
                );
                camera.undistort(p).unwrap_or(nan)
            })
            .collect();
        Self {
            camera: camera.clone(),
            origin,
            cols,
            rows,
            nodes,
        }
    }

    /// The camera tabulated.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// The normalised coordinates of the ray through pixel `p`: [`Camera::undistort`], started from
    /// the table. `None` where `Camera::undistort` gives none.
    pub fn undistort(&self, p: Point2) -> Option<Vector2<f64>> {
        let cam = &self.camera;
        let distorted = Vector2::new((p.x - cam.cx) / cam.fx, (p.y - cam.cy) / cam.fy);
        if !(distorted.x.is_finite() && distorted.y.is_finite()) {
            return None;
        }
        match self.interpolate(p) {
            Some(start) => cam.distortion.undistort_from(distorted, start),
            None => cam.distortion.undistort(distorted),
        }
    }

    /// Bilinear interpolation of the four nodes around `p`; `None` outside the table or where a
    /// node has no ray.
    fn interpolate(&self, p: Point2) -> Option<Vector2<f64>> {
        let gx = (p.x - self.origin.x) / GRID_STEP_PX;
        let gy = (p.y - self.origin.y) / GRID_STEP_PX;
        // Also rejects NaN.
        if !(gx >= 0.0 && gy >= 0.0) {
            return None;
        }
        let (c, r) = (gx.floor() as usize, gy.floor() as usize);
        if c + 1 >= self.cols || r + 1 >= self.rows {
            return None;
        }
        let (fx, fy) = (gx - c as f64, gy - r as f64);
        let at = |r: usize, c: usize| self.nodes[r * self.cols + c];
        let top = at(r, c) * (1.0 - fx) + at(r, c + 1) * fx;
        let bottom = at(r + 1, c) * (1.0 - fx) + at(r + 1, c + 1) * fx;
        let v = top * (1.0 - fy) + bottom * fy;
        (v.x.is_finite() && v.y.is_finite()).then_some(v)
    }
}

#[cfg(test)]
mod tests {
    use gelstereo_core::ImageSize;

    use super::*;
    use crate::camera::Distortion;

    fn camera(coeffs: Vec<f64>) -> Camera {
        Camera {
            distortion: Distortion::new(coeffs).unwrap(),
            ..Camera::pinhole(
                ImageSize {
                    width: 640,
                    height: 480,
                },
                520.0,
                518.0,
                321.0,
                243.0,
            )
        }
    }

    /// The table changes where Newton's method starts, not where it ends: every pixel of the image
    /// and a margin around it undistorts as `Camera::undistort` does, to its tolerance.
    #[test]
    fn the_grid_gives_the_cameras_undistortion() {
        for coeffs in [
            vec![-0.28, 0.09, 1e-3, -5e-4, -0.01],
            vec![0.4, -0.2, 2e-3, 1e-3, 0.05, 0.3, -0.1, 0.02],
            vec![],
        ] {
            let cam = camera(coeffs);
            let grid = UndistortionGrid::new(&cam);
            let mut compared = 0;
            for y in (-12..492).step_by(7) {
                for x in (-12..652).step_by(5) {
                    let p = Point2::new(f64::from(x) + 0.37, f64::from(y) + 0.61);
                    match (cam.undistort(p), grid.undistort(p)) {
                        (Some(a), Some(b)) => {
                            assert!((a - b).norm() < 1e-12, "{p:?}: {a:?} against {b:?}");
                            compared += 1;
                        }
                        (a, b) => assert_eq!(a.is_some(), b.is_some(), "{p:?}"),
                    }
                }
            }
            assert!(compared > 9000, "{compared}");
        }
    }

    /// A pixel with no finite coordinate has no ray, and the table never panics on one.
    #[test]
    fn non_finite_pixels_have_no_ray() {
        let grid = UndistortionGrid::new(&camera(vec![-0.28, 0.09, 0.0, 0.0]));
        for p in [
            Point2::new(f64::NAN, 3.0),
            Point2::new(3.0, f64::INFINITY),
            Point2::new(-1e300, 2.0),
        ] {
            assert!(grid.undistort(p).is_none(), "{p:?}");
        }
    }
}
