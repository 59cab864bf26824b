//! Projection and undistortion against OpenCV 4.6 (`cv::projectPoints`, `cv::undistortPointsIter`)
//! on seeded random points, for 4, 5, 8 and 12 distortion coefficients. Tolerance 1e-6 px.
#![allow(clippy::unwrap_used)]

use gelstereo_core::{ImageSize, Point2};
use gelstereo_geometry::{Camera, Distortion, cv};
use nalgebra::Point3;
use opencv::core::{Mat, Point2d, Point3d, TermCriteria, TermCriteria_Type, Vector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const TOL_PX: f64 = 1e-6;

fn camera(coeffs: &[f64]) -> Camera {
    Camera {
        image_size: ImageSize {
            width: 640,
            height: 480,
        },
        fx: 520.0,
        fy: 521.5,
        cx: 321.3,
        cy: 238.4,
        distortion: Distortion::new(coeffs.to_vec()).unwrap(),
    }
}

/// Strong but monotonic distortion over the 640x480 image (a wide-angle lens of the kind used in
/// visuotactile sensors), each model a prefix of the 12-coefficient one.
const D12: [f64; 12] = [
    -0.28, 0.09, 1.2e-3, -8e-4, -0.012, 0.05, -0.02, 0.004, 1.5e-3, -4e-4, 9e-4, 2e-4,
];

#[test]
fn project_points_matches_opencv() {
    let mut rng = ChaCha8Rng::seed_from_u64(61);
    for n in [4, 5, 8, 12] {
        let cam = camera(&D12[..n]);
        let pts: Vec<Point3<f64>> = (0..500)
            .map(|_| {
                let z = rng.random_range(5.0..60.0);
                Point3::new(
                    rng.random_range(-0.6..0.6) * z,
                    rng.random_range(-0.45..0.45) * z,
                    z,
                )
            })
            .collect();
        let obj: Vector<Point3d> = pts.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect();
        let zero = Mat::from_slice(&[0.0f64; 3]).unwrap();
        let mut img: Vector<Point2d> = Vector::new();
        opencv::calib3d::project_points_def(
            &obj,
            &zero,
            &zero,
            &cv::camera_matrix(&cam).unwrap(),
            &cv::distortion_coeffs(&cam).unwrap(),
            &mut img,
        )
        .unwrap();
        let mut worst = 0.0f64;
        for (p, q) in pts.iter().zip(img.iter()) {
            let ours = cam.project(p).unwrap();
            worst = worst.max(ours.distance(Point2::new(q.x, q.y)));
        }
        eprintln!("projectPoints, {n} coefficients: worst difference {worst:.3e} px");
        assert!(worst < TOL_PX, "{n} coefficients: worst {worst:e} px");
    }
}

#[test]
fn undistort_points_matches_opencv() {
    let mut rng = ChaCha8Rng::seed_from_u64(62);
    for n in [4, 5, 8, 12] {
        let cam = camera(&D12[..n]);
        let px: Vec<Point2> = (0..500)
            .map(|_| Point2::new(rng.random_range(0.0..639.0), rng.random_range(0.0..479.0)))
            .collect();
        let src: Vector<Point2d> = px.iter().map(|p| Point2d::new(p.x, p.y)).collect();
        let mut dst: Vector<Point2d> = Vector::new();
        // OpenCV's default stops after 5 fixed-point iterations (~0.1 px here); run it to convergence.
        let criteria = TermCriteria::new(TermCriteria_Type::COUNT as i32, 500, 0.0).unwrap();
        opencv::calib3d::undistort_points_iter(
            &src,
            &mut dst,
            &cv::camera_matrix(&cam).unwrap(),
            &cv::distortion_coeffs(&cam).unwrap(),
            &Mat::default(),
            &Mat::default(),
            criteria,
        )
        .unwrap();
        let (mut worst, mut worst_reproj) = (0.0f64, 0.0f64);
        for (p, q) in px.iter().zip(dst.iter()) {
            let ours = cam.undistort(*p).unwrap();
            // Compared in pixels of an ideal camera with the same K.
            let d = ((ours.x - q.x) * cam.fx).hypot((ours.y - q.y) * cam.fy);
            worst = worst.max(d);
            worst_reproj = worst_reproj.max(cam.project_normalized(ours).unwrap().distance(*p));
        }
        eprintln!(
            "undistortPointsIter, {n} coefficients: worst difference {worst:.3e} px, ours reprojects to {worst_reproj:.3e} px"
        );
        assert!(worst < TOL_PX, "{n} coefficients: worst {worst:e} px");
        assert!(
            worst_reproj < 1e-9,
            "{n} coefficients: reprojection {worst_reproj:e} px"
        );
    }
}
