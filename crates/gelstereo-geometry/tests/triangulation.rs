//! Triangulation against OpenCV's `triangulatePoints`, mrcal 2.2's `triangulate` (fixture written by
//! `tests/data/generate.py`), a numerical optimiser of the same cost, and the rejection rules.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::time::Instant;

use gelstereo_core::{Point2, View};
use gelstereo_geometry::{
    Error, Rejection, StereoRig, Triangulated, TriangulationConfig, TriangulationMethod, Triangulator, cv,
};
use nalgebra::{Point3, Vector3};
use opencv::core::{Mat, MatTraitConst, Point2d, TermCriteria, TermCriteria_Type, Vector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const METHODS: [TriangulationMethod; 4] = [
    TriangulationMethod::Midpoint,
    TriangulationMethod::LeeCiveraMid2,
    TriangulationMethod::Lindstrom,
    TriangulationMethod::PixelOptimal,
];

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn rig() -> StereoRig {
    StereoRig::read_opencv(data("opencv8.yaml")).unwrap()
}

fn triangulator(method: TriangulationMethod) -> Triangulator {
    Triangulator::new(
        rig(),
        TriangulationConfig {
            method,
            ..Default::default()
        },
    )
    .unwrap()
}

/// Points on and around the reference sensor's gel (cameras 24 mm behind it), in the left frame,
/// visible in both views.
fn gel_points(rng: &mut ChaCha8Rng, n: usize) -> Vec<(Point3<f64>, Point2, Point2)> {
    let rig = rig();
    let mut out = Vec::new();
    while out.len() < n {
        let p = Point3::new(
            rng.random_range(-9.0..13.0),
            rng.random_range(-9.0..9.0),
            rng.random_range(20.0..30.0),
        );
        if let Some((l, r)) = rig.project(&p)
            && rig.left.contains(l)
            && rig.right.contains(r)
        {
            out.push((p, l, r));
        }
    }
    out
}

#[test]
fn exact_on_noise_free_pairs_and_matches_opencv_triangulate_points() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let pts = gel_points(&mut rng, 300);
    let rig = rig();
    for method in METHODS {
        let t = triangulator(method);
        let mut worst = 0.0f64;
        for (p, l, r) in &pts {
            let got = t.triangulate(*l, *r).unwrap();
            worst = worst.max((got.p_in_left_mm - p).norm());
            assert!(got.max_reprojection_error_px() < 1e-8, "{method:?}: {got:?}");
        }
        eprintln!("{method:?}: noise-free worst 3-D error {worst:.3e} mm");
        assert!(worst < 1e-9, "{method:?}: {worst:e} mm");
    }

    // OpenCV: undistort with OpenCV itself, then DLT with P1 = [I|0], P2 = [R|T].
    let undist = |cam: &gelstereo_geometry::Camera, px: Vec<Point2d>| -> Vector<Point2d> {
        let src: Vector<Point2d> = px.into_iter().collect();
        let mut dst = Vector::<Point2d>::new();
        let criteria = TermCriteria::new(TermCriteria_Type::COUNT as i32, 500, 0.0).unwrap();
        opencv::calib3d::undistort_points_iter(
            &src,
            &mut dst,
            &cv::camera_matrix(cam).unwrap(),
            &cv::distortion_coeffs(cam).unwrap(),
            &Mat::default(),
            &Mat::default(),
            criteria,
        )
        .unwrap();
        dst
    };
    let ul = undist(
        &rig.left,
        pts.iter().map(|(_, l, _)| Point2d::new(l.x, l.y)).collect(),
    );
    let ur = undist(
        &rig.right,
        pts.iter().map(|(_, _, r)| Point2d::new(r.x, r.y)).collect(),
    );
    let r = rig.right_from_left.rotation.to_rotation_matrix().into_inner();
    let tr = rig.right_from_left.translation.vector;
    let p1 = cv::mat_from_rows(
        3,
        4,
        &[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
    )
    .unwrap();
    let p2 = cv::mat_from_rows(
        3,
        4,
        &[
            r[(0, 0)],
            r[(0, 1)],
            r[(0, 2)],
            tr.x,
            r[(1, 0)],
            r[(1, 1)],
            r[(1, 2)],
            tr.y,
            r[(2, 0)],
            r[(2, 1)],
            r[(2, 2)],
            tr.z,
        ],
    )
    .unwrap();
    let mut x4 = Mat::default();
    opencv::calib3d::triangulate_points(&p1, &p2, &ul, &ur, &mut x4).unwrap();
    let (rows, cols, h) = cv::mat_to_rows(&x4).unwrap();
    assert_eq!((rows, cols), (4, pts.len()));
    assert_eq!(x4.typ(), opencv::core::CV_64F);
    let ours = triangulator(TriangulationMethod::default());
    let mut worst = 0.0f64;
    for (i, (_, l, r)) in pts.iter().enumerate() {
        let w = h[3 * cols + i];
        let cvp = Point3::new(h[i] / w, h[cols + i] / w, h[2 * cols + i] / w);
        worst = worst.max((ours.triangulate(*l, *r).unwrap().p_in_left_mm - cvp).norm());
    }
    eprintln!("vs OpenCV triangulatePoints (noise-free): worst {worst:.3e} mm");
    assert!(worst < 1e-6, "{worst:e}");
}

/// mrcal.triangulate on noisy pixels (0.3 px), mrcal-written OPENCV8 models.
#[test]
fn matches_mrcal_mid2_and_lindstrom_on_noisy_pixels() {
    let rig = StereoRig::read_mrcal(
        data("opencv8_left.cameramodel"),
        data("opencv8_right.cameramodel"),
    )
    .unwrap();
    let text = std::fs::read_to_string(data("triangulation_mrcal.csv")).unwrap();
    let rows: Vec<Vec<f64>> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 200);
    let config = |method| TriangulationConfig {
        method,
        max_reprojection_error_px: f64::INFINITY,
        ..Default::default()
    };
    let mid2 = Triangulator::new(rig.clone(), config(TriangulationMethod::LeeCiveraMid2)).unwrap();
    let lind = Triangulator::new(rig.clone(), config(TriangulationMethod::Lindstrom)).unwrap();
    let (mut w_mid2, mut w_lind) = (0.0f64, 0.0f64);
    for row in &rows {
        let (l, r) = (Point2::new(row[0], row[1]), Point2::new(row[2], row[3]));
        let m = mid2.triangulate(l, r).unwrap().p_in_left_mm;
        w_mid2 = w_mid2.max((m - Point3::new(row[7], row[8], row[9])).norm());
        let n = lind.triangulate(l, r).unwrap().p_in_left_mm;
        w_lind = w_lind.max((n - Point3::new(row[10], row[11], row[12])).norm());
    }
    eprintln!("vs mrcal 2.2: Mid2 worst {w_mid2:.3e} mm, Lindstrom worst {w_lind:.3e} mm");
    // mrcal unprojects iteratively to its own tolerance: agreement to 1e-8 mm (10 pm).
    assert!(w_mid2 < 1e-8 && w_lind < 1e-8, "{w_mid2:e} {w_lind:e}");
}

/// Sum of squared reprojection errors (px^2) of `p` in both views.
fn cost_px2(rig: &StereoRig, p: &Point3<f64>, l: Point2, r: Point2) -> f64 {
    let (ql, qr) = rig.project(p).unwrap();
    ql.distance(l).powi(2) + qr.distance(r).powi(2)
}

/// Lindstrom is optimal in the normalised planes: a numerical optimiser (Nelder-Mead-free, central
/// differences + Newton on the same cost) cannot improve it; PixelOptimal minimises the pixel cost,
/// so no other method (nor a perturbation) does better there.
#[test]
fn optimal_methods_are_optimal_for_their_cost() {
    let rig = rig();
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let pts = gel_points(&mut rng, 200);
    let t: Vec<Triangulator> = METHODS
        .iter()
        .map(|&method| {
            Triangulator::new(
                rig.clone(),
                TriangulationConfig {
                    method,
                    max_reprojection_error_px: f64::INFINITY,
                    ..Default::default()
                },
            )
            .unwrap()
        })
        .collect();
    let (mut worst_lind_gain, mut rmse) = (0.0f64, [0.0f64; 4]);
    for (p, l, r) in &pts {
        let l = Point2::new(
            l.x + rng.random_range(-0.5..0.5),
            l.y + rng.random_range(-0.5..0.5),
        );
        let r = Point2::new(
            r.x + rng.random_range(-0.5..0.5),
            r.y + rng.random_range(-0.5..0.5),
        );
        let res: Vec<Triangulated> = t.iter().map(|t| t.triangulate(l, r).unwrap()).collect();
        for (i, x) in res.iter().enumerate() {
            rmse[i] += (x.p_in_left_mm - p).norm_squared();
        }
        // Normalised-plane cost, minimised numerically from Lindstrom's point.
        let nl = rig.left.undistort(l).unwrap();
        let nr = rig.right.undistort(r).unwrap();
        let ncost = |x: &Vector3<f64>| {
            let xr = rig.right_from_left * Point3::from(*x);
            (x.x / x.z - nl.x).powi(2)
                + (x.y / x.z - nl.y).powi(2)
                + (xr.x / xr.z - nr.x).powi(2)
                + (xr.y / xr.z - nr.y).powi(2)
        };
        let mut x = res[2].p_in_left_mm.coords;
        let c0 = ncost(&x);
        let h = 1e-4;
        for _ in 0..20 {
            let mut g = Vector3::zeros();
            let mut hess = nalgebra::Matrix3::zeros();
            for a in 0..3 {
                let ea = Vector3::ith(a, h);
                g[a] = (ncost(&(x + ea)) - ncost(&(x - ea))) / (2.0 * h);
                for b in 0..3 {
                    let eb = Vector3::ith(b, h);
                    hess[(a, b)] = (ncost(&(x + ea + eb)) - ncost(&(x + ea - eb)) - ncost(&(x - ea + eb))
                        + ncost(&(x - ea - eb)))
                        / (4.0 * h * h);
                }
            }
            let Some(step) = hess.try_inverse().map(|hi| hi * g) else {
                break;
            };
            if ncost(&(x - step)) < ncost(&x) {
                x -= step;
            } else {
                break;
            }
        }
        worst_lind_gain = worst_lind_gain.max((c0 - ncost(&x)) / c0.max(1e-30));
        // Pixel cost: PixelOptimal is no worse than any method, nor than small perturbations.
        let best = cost_px2(&rig, &res[3].p_in_left_mm, l, r);
        for x in &res {
            assert!(best <= cost_px2(&rig, &x.p_in_left_mm, l, r) * (1.0 + 1e-9) + 1e-18);
        }
        for a in 0..3 {
            for s in [-1e-4, 1e-4] {
                let q = res[3].p_in_left_mm + Vector3::ith(a, s);
                assert!(best <= cost_px2(&rig, &q, l, r) + 1e-15);
            }
        }
    }
    let n = pts.len() as f64;
    eprintln!(
        "uniform +-0.5 px noise, RMSE mm: midpoint {:.5}, mid2 {:.5}, lindstrom {:.5}, pixel-optimal {:.5}; \
         numerical optimiser improves Lindstrom's normalised cost by at most {worst_lind_gain:.2e} (relative)",
        (rmse[0] / n).sqrt(),
        (rmse[1] / n).sqrt(),
        (rmse[2] / n).sqrt(),
        (rmse[3] / n).sqrt()
    );
    assert!(worst_lind_gain < 1e-6, "{worst_lind_gain:e}");
}

#[test]
fn rejections_are_typed_and_never_nan() {
    let rig = rig();
    let t = triangulator(TriangulationMethod::default());
    // Parallel rays: a point 1e6 mm away.
    let far = Point3::new(0.0, 0.0, 1e7);
    let (l, r) = rig.project(&far).unwrap();
    assert!(
        matches!(t.triangulate(l, r), Err(Rejection::ParallelRays { .. })),
        "{:?}",
        t.triangulate(l, r)
    );
    // Divergent rays: swap the views' horizontal positions so the rays meet behind the cameras.
    let (l, r) = rig.project(&Point3::new(1.0, 0.0, 25.0)).unwrap();
    let rl = Point2::new(l.x - 150.0, l.y);
    let rr = Point2::new(r.x + 150.0, r.y);
    for method in METHODS {
        let got = triangulator(method).triangulate(rl, rr);
        assert!(
            matches!(got, Err(Rejection::BehindCamera { .. })),
            "{method:?}: {got:?}"
        );
    }
    // Off the epipolar line by 6 px: rejected by the 2 px bound, accepted with an infinite bound.
    let (l, r) = rig.project(&Point3::new(1.0, 2.0, 25.0)).unwrap();
    let off = Point2::new(r.x, r.y + 6.0);
    match t.triangulate(l, off) {
        Err(Rejection::Reprojection {
            left_px,
            right_px,
            bound_px,
        }) => {
            assert!(
                bound_px == 2.0 && left_px + right_px > 2.0 && left_px.is_finite() && right_px.is_finite()
            )
        }
        other => panic!("{other:?}"),
    }
    let loose = Triangulator::new(
        rig.clone(),
        TriangulationConfig {
            max_reprojection_error_px: f64::INFINITY,
            ..Default::default()
        },
    )
    .unwrap();
    let got = loose.triangulate(l, off).unwrap();
    assert!(got.max_reprojection_error_px() > 1.0);
    assert!((t.epipolar_error_px(l, off).unwrap() - 6.0).abs() < 1.0);
    assert!(t.epipolar_error_px(l, r).unwrap() < 1e-9);
    // NaN pixels.
    assert!(t.triangulate(Point2::new(f64::NAN, 1.0), r).is_err());
    // Lengths.
    assert!(matches!(
        t.triangulate_all(&[l, l], &[r]),
        Err(Error::LengthMismatch {
            left_len: 2,
            right_len: 1
        })
    ));
    // Garbage pairs: every result is either a typed rejection or finite.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut rejected = [0usize; 4];
    for method in METHODS {
        let t = triangulator(method);
        for _ in 0..2000 {
            let l = Point2::new(
                rng.random_range(-2000.0..2000.0),
                rng.random_range(-2000.0..2000.0),
            );
            let r = Point2::new(
                rng.random_range(-2000.0..2000.0),
                rng.random_range(-2000.0..2000.0),
            );
            match t.triangulate(l, r) {
                Ok(x) => {
                    assert!(x.p_in_left_mm.coords.iter().all(|v| v.is_finite()));
                    assert!(x.p_in_left_mm.z > 0.0 && x.max_reprojection_error_px() <= 2.0);
                }
                Err(Rejection::Undistortion { .. }) => rejected[0] += 1,
                Err(Rejection::ParallelRays { angle_rad }) => {
                    assert!(!angle_rad.is_nan());
                    rejected[1] += 1
                }
                Err(Rejection::BehindCamera { view }) => {
                    assert!(matches!(view, View::Left | View::Right));
                    rejected[2] += 1
                }
                Err(Rejection::Reprojection {
                    left_px, right_px, ..
                }) => {
                    assert!(!left_px.is_nan() && !right_px.is_nan());
                    rejected[3] += 1
                }
            }
        }
    }
    eprintln!("garbage pairs rejected: undistortion/parallel/behind/reprojection = {rejected:?}");
    assert!(rejected[2] > 0 && rejected[3] > 0);
}

/// Each method's reported reprojection errors are the distances between the point's projections
/// and the pixels (the pixel-optimal method reuses its last Gauss-Newton residuals for them).
#[test]
fn reported_reprojection_errors_are_the_projections_distances() {
    let rig = rig();
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    for method in METHODS {
        let t = triangulator(method);
        for (_, l, r) in gel_points(&mut rng, 300) {
            let noisy = |p: Point2, rng: &mut ChaCha8Rng| {
                Point2::new(
                    p.x + rng.random_range(-0.6..0.6),
                    p.y + rng.random_range(-0.6..0.6),
                )
            };
            let (l, r) = (noisy(l, &mut rng), noisy(r, &mut rng));
            let Ok(found) = t.triangulate(l, r) else {
                continue;
            };
            let (pl, pr) = rig.project(&found.p_in_left_mm).unwrap();
            let errors = found.reprojection_error_px;
            assert!(
                (errors.left - pl.distance(l)).abs() < 1e-9,
                "{method:?}: {errors:?}"
            );
            assert!(
                (errors.right - pr.distance(r)).abs() < 1e-9,
                "{method:?}: {errors:?}"
            );
        }
    }
}

#[test]
fn many_markers_are_fast() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let pts = gel_points(&mut rng, 529);
    let l: Vec<Point2> = pts.iter().map(|p| p.1).collect();
    let r: Vec<Point2> = pts.iter().map(|p| p.2).collect();
    for method in METHODS {
        let t = triangulator(method);
        let start = Instant::now();
        let mut out = Vec::new();
        for _ in 0..20 {
            out = t.triangulate_all(&l, &r).unwrap();
        }
        let per_frame_ms = start.elapsed().as_secs_f64() * 1e3 / 20.0;
        assert!(out.iter().all(Result::is_ok));
        eprintln!("{method:?}: 529 markers in {per_frame_ms:.3} ms (test profile)");
        // Generous: the test profile is not fully optimised; see examples/triangulation_speed.rs.
        assert!(per_frame_ms < 20.0);
    }
}
