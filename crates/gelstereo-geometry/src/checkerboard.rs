//! Stereo checkerboard calibration with OpenCV: `findChessboardCorners` + `cornerSubPix` per view,
//! `calibrateCamera` per camera, then `stereoCalibrate` refining everything jointly.
//!
//! A board is given by its INNER corners (OpenCV's `patternSize`): a board of 10 x 7 squares has
//! 9 x 6 inner corners. Board coordinates: corner (col, row) at `(col * square_mm, row * square_mm, 0)`.
//!
//! [`render_view`] draws a board as a camera sees it (exact projection with the lens model,
//! 4 x 4 super-sampling); the tests use it to check the calibration against a known rig.

use gelstereo_core::limits::MAX_BOARD_CORNERS_PER_SIDE;
use gelstereo_core::{ImageSize, Point2};
use nalgebra::{Isometry3, Point3, Vector2, Vector3};
use opencv::core::{Mat, MatTraitConst, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vector};

// stereoCalibrate with per-view errors: its name in the bindings of the OpenCV the crate links (build.rs).
#[cfg(opencv_stereo_calibrate_rvecs)]
use opencv::calib3d::stereo_calibrate_1 as stereo_calibrate_per_view;
#[cfg(not(opencv_stereo_calibrate_rvecs))]
use opencv::calib3d::stereo_calibrate_extended as stereo_calibrate_per_view;

use crate::camera::{Camera, StereoRig};
use crate::cv::{camera_from_cv, cv_err, isometry_from_rt};
use crate::error::{Error, Result};
use crate::triangulation::{TriangulationConfig, Triangulator};

/// A checkerboard: inner corners and square size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Board {
    /// Inner corners per row (along x).
    pub inner_cols: u32,
    /// Inner corners per column (along y).
    pub inner_rows: u32,
    /// Side of one square, mm.
    pub square_mm: f64,
}

impl Board {
    /// A board from `"COLSxROWS"` (inner corners, e.g. `"9x6"`) and the square size in mm.
    pub fn parse(spec: &str, square_mm: f64) -> Result<Board> {
        let (c, r) = spec.split_once(['x', 'X']).ok_or_else(|| {
            Error::Calibration(format!(
                "board '{spec}': expected COLSxROWS inner corners, e.g. 9x6"
            ))
        })?;
        let parse = |s: &str| match s.trim().parse::<u32>() {
            Ok(n) if (2..=MAX_BOARD_CORNERS_PER_SIDE).contains(&n) => Ok(n),
            _ => Err(Error::Calibration(format!(
                "board '{spec}': '{s}' inner corners: expected a whole number from 2 to \
                 {MAX_BOARD_CORNERS_PER_SIDE}"
            ))),
        };
        let board = Board {
            inner_cols: parse(c)?,
            inner_rows: parse(r)?,
            square_mm,
        };
        if !(square_mm.is_finite() && square_mm > 0.0 && square_mm <= MAX_SQUARE_MM) {
            return Err(Error::InvalidParameter {
                name: "square_mm (--square-mm)".to_owned(),
                value: square_mm,
                expected: "a square size above 0 and at most 1000 mm",
            });
        }
        Ok(board)
    }

    /// Number of inner corners.
    pub fn corner_count(&self) -> usize {
        self.inner_cols as usize * self.inner_rows as usize
    }

    /// The inner corners in board coordinates (mm), row by row, as OpenCV orders them.
    pub fn object_points(&self) -> Vec<Point3<f64>> {
        (0..self.inner_rows)
            .flat_map(|r| {
                (0..self.inner_cols).map(move |c| {
                    Point3::new(f64::from(c) * self.square_mm, f64::from(r) * self.square_mm, 0.0)
                })
            })
            .collect()
    }

    fn pattern_size(&self) -> Result<Size> {
        let c =
            i32::try_from(self.inner_cols).map_err(|_| Error::Calibration("board too large".to_owned()))?;
        let r =
            i32::try_from(self.inner_rows).map_err(|_| Error::Calibration("board too large".to_owned()))?;
        Ok(Size::new(c, r))
    }
}

/// Which OpenCV corner detector [`find_corners`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CornerDetector {
    /// `findChessboardCorners` (adaptive threshold, normalised image) refined by `cornerSubPix`.
    #[default]
    Classic,
    /// `findChessboardCornersSB` (Duda & Frese, "Accurate Detection and Localization of Checkerboard
    /// Corners for Calibration", BMVC 2018) with `CALIB_CB_ACCURACY`: more robust to blur and noise.
    SectorBased,
}

impl std::str::FromStr for CornerDetector {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "classic" => Ok(Self::Classic),
            "sb" => Ok(Self::SectorBased),
            other => Err(Error::Calibration(format!(
                "unknown corner detector '{other}': expected classic or sb"
            ))),
        }
    }
}

/// Settings of [`find_corners`] and [`calibrate_stereo`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibrationOptions {
    /// Distortion coefficients to estimate: 4 (`CALIB_FIX_K3`), 5 (OpenCV's default model),
    /// 8 (`CALIB_RATIONAL_MODEL`) or 12 (`+ CALIB_THIN_PRISM_MODEL`). Default 5, OpenCV's default.
    /// The 12-coefficient model's thin-prism terms trade off with the principal point and the
    /// tangential terms unless the views cover the whole image: check the 3-D result before using it.
    pub distortion_coeffs: usize,
    /// Half-size of the `cornerSubPix` search window, px. Default 5 (OpenCV's samples use 5 or 11);
    /// it must stay below half a square's size in the image.
    pub subpix_half_window_px: i32,
    /// The fewest usable stereo pairs. Default 5: each view of a plane gives 8 constraints, and a
    /// handful of varied poses are needed for a stable focal length and distortion.
    pub min_pairs: usize,
    /// The corner detector. Default [`CornerDetector::Classic`], OpenCV's long-standing one.
    pub detector: CornerDetector,
}

/// Largest checkerboard square accepted, mm (a 1 m square is already far beyond a tactile sensor's
/// view; larger numbers only overflow OpenCV's float corner coordinates).
pub const MAX_SQUARE_MM: f64 = 1000.0;

/// Largest `cornerSubPix` half-window accepted, px.
pub const MAX_SUBPIX_HALF_WINDOW_PX: i32 = 50;

impl CalibrationOptions {
    /// Checks each field's range, so that OpenCV never sees a value it would assert on.
    pub fn validate(&self) -> Result<()> {
        if !(1..=MAX_SUBPIX_HALF_WINDOW_PX).contains(&self.subpix_half_window_px) {
            return Err(Error::InvalidParameter {
                name: "subpix_half_window_px (--subpix-window)".to_owned(),
                value: f64::from(self.subpix_half_window_px),
                expected: "1 to 50 px (below half a square in the image)",
            });
        }
        if ![4, 5, 8, 12].contains(&self.distortion_coeffs) {
            return Err(Error::DistortionCount {
                count: self.distortion_coeffs,
            });
        }
        Ok(())
    }
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        Self {
            distortion_coeffs: 5,
            subpix_half_window_px: 5,
            min_pairs: 5,
            detector: CornerDetector::Classic,
        }
    }
}

/// The board's inner corners in a grey or BGR image, refined to sub-pixel accuracy; `None` when the
/// board is not found. Corners are ordered row by row as [`Board::object_points`], with the first
/// corner the one nearest the image's top-left (so left and right views agree for a board seen
/// roughly upright).
pub fn find_corners(image: &Mat, board: &Board, options: &CalibrationOptions) -> Result<Option<Vec<Point2>>> {
    options.validate()?;
    let gray = if image.channels() == 1 {
        image.clone()
    } else {
        let mut g = Mat::default();
        opencv::imgproc::cvt_color(image, &mut g, opencv::imgproc::COLOR_BGR2GRAY, 0)
            .map_err(cv_err("cvtColor"))?;
        g
    };
    let mut corners: Vector<Point2f> = Vector::new();
    match options.detector {
        CornerDetector::Classic => {
            let flags = opencv::calib3d::CALIB_CB_ADAPTIVE_THRESH | opencv::calib3d::CALIB_CB_NORMALIZE_IMAGE;
            let found =
                opencv::calib3d::find_chessboard_corners(&gray, board.pattern_size()?, &mut corners, flags)
                    .map_err(cv_err("findChessboardCorners"))?;
            if !found || corners.len() != board.corner_count() {
                return Ok(None);
            }
            let w = options.subpix_half_window_px.max(1);
            let criteria = TermCriteria::new(
                (TermCriteria_Type::COUNT as i32) | (TermCriteria_Type::EPS as i32),
                100,
                1e-6,
            )
            .map_err(cv_err("TermCriteria"))?;
            opencv::imgproc::corner_sub_pix(
                &gray,
                &mut corners,
                Size::new(w, w),
                Size::new(-1, -1),
                criteria,
            )
            .map_err(cv_err("cornerSubPix"))?;
        }
        CornerDetector::SectorBased => {
            let flags = opencv::calib3d::CALIB_CB_NORMALIZE_IMAGE
                | opencv::calib3d::CALIB_CB_EXHAUSTIVE
                | opencv::calib3d::CALIB_CB_ACCURACY;
            let found = opencv::calib3d::find_chessboard_corners_sb(
                &gray,
                board.pattern_size()?,
                &mut corners,
                flags,
            )
            .map_err(cv_err("findChessboardCornersSB"))?;
            if !found || corners.len() != board.corner_count() {
                return Ok(None);
            }
        }
    }
    let mut pts: Vec<Point2> = corners
        .iter()
        .map(|p| Point2::new(f64::from(p.x), f64::from(p.y)))
        .collect();
    // OpenCV may start from any of the two ends of the grid: make the first corner the top-left one.
    if let (Some(first), Some(last)) = (pts.first(), pts.last())
        && (last.x - first.x) + (last.y - first.y) < 0.0
    {
        pts.reverse();
    }
    Ok(Some(pts))
}

/// The corners of one board pose seen by both cameras.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoCorners {
    /// A name for reports (the image file name).
    pub name: String,
    /// Left view corners, [`Board::object_points`] order.
    pub left: Vec<Point2>,
    /// Right view corners, same order.
    pub right: Vec<Point2>,
}

/// The result of a stereo calibration, with its quality figures.
#[derive(Debug, Clone)]
pub struct CalibrationReport {
    /// The calibrated rig.
    pub rig: StereoRig,
    /// Stereo pairs used.
    pub pairs_used: usize,
    /// RMS reprojection error of the left camera's own calibration (`calibrateCamera`), px.
    pub rms_left_px: f64,
    /// RMS reprojection error of the right camera's own calibration, px.
    pub rms_right_px: f64,
    /// RMS reprojection error of the joint stereo calibration (`stereoCalibrate`, both views), px.
    pub rms_stereo_px: f64,
    /// RMS epipolar error of all corner pairs under the calibrated rig, px (see
    /// [`Triangulator::epipolar_error_px`]).
    pub epipolar_rms_px: f64,
    /// Largest epipolar error of a corner pair, px.
    pub epipolar_max_px: f64,
    /// RMS reprojection error of each pair in the stereo solve, in the order given.
    pub per_pair: Vec<PairError>,
}

/// The reprojection error of one stereo pair in the joint calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct PairError {
    /// The pair's name ([`StereoCorners::name`]).
    pub name: String,
    /// RMS over the left view's corners, px.
    pub left_rms_px: f64,
    /// RMS over the right view's corners, px.
    pub right_rms_px: f64,
}

fn model_flags(n: usize) -> Result<i32> {
    use opencv::calib3d::{CALIB_FIX_K3, CALIB_RATIONAL_MODEL, CALIB_THIN_PRISM_MODEL};
    match n {
        4 => Ok(CALIB_FIX_K3),
        5 => Ok(0),
        8 => Ok(CALIB_RATIONAL_MODEL),
        12 => Ok(CALIB_RATIONAL_MODEL | CALIB_THIN_PRISM_MODEL),
        count => Err(Error::Calibration(format!(
            "cannot estimate {count} distortion coefficients: expected 4, 5, 8 or 12"
        ))),
    }
}

fn to_f32_points(points: &[Point2]) -> Vector<Point2f> {
    // OpenCV's calibration takes single-precision image points.
    #[allow(clippy::cast_possible_truncation)]
    points
        .iter()
        .map(|p| Point2f::new(p.x as f32, p.y as f32))
        .collect()
}

/// Every pair must hold all the board's corners in both views, and there must be enough pairs.
fn check_stereo_views(board: &Board, views: &[StereoCorners], options: &CalibrationOptions) -> Result<()> {
    let n = board.corner_count();
    for v in views {
        if v.left.len() != n || v.right.len() != n {
            return Err(Error::Calibration(format!(
                "{}: {} left and {} right corners, the board has {n}",
                v.name,
                v.left.len(),
                v.right.len()
            )));
        }
    }
    if views.len() < options.min_pairs.max(1) {
        return Err(Error::Calibration(format!(
            "{} stereo pairs with the board found in both views; at least {} are needed",
            views.len(),
            options.min_pairs.max(1)
        )));
    }
    Ok(())
}

/// The per-pair left and right RMS errors of `stereoCalibrate` (`per_view`, one row of two
/// per pair), named after their pairs.
fn pair_errors(views: &[StereoCorners], per_view: &Mat) -> Result<Vec<PairError>> {
    let (pv_rows, pv_cols, pv) = crate::cv::mat_to_rows(per_view)?;
    if pv_rows != views.len() || pv_cols != 2 {
        return Err(Error::Calibration(format!(
            "stereoCalibrate returned {pv_rows}x{pv_cols} per-view errors for {} pairs",
            views.len()
        )));
    }
    Ok(views
        .iter()
        .zip(pv.chunks_exact(2))
        .map(|(v, e)| PairError {
            name: v.name.clone(),
            left_rms_px: e[0],
            right_rms_px: e[1],
        })
        .collect())
}

/// RMS and largest epipolar error of all corner pairs under the calibrated `rig`, an
/// independent check of the calibration (the corners that cannot be undistorted are left out).
fn epipolar_errors(rig: &StereoRig, views: &[StereoCorners]) -> Result<(f64, f64)> {
    let tri = Triangulator::new(rig.clone(), TriangulationConfig::default())?;
    let (mut sum2, mut max, mut count) = (0.0, 0.0f64, 0usize);
    for v in views {
        for (l, r) in v.left.iter().zip(&v.right) {
            if let Some(e) = tri.epipolar_error_px(*l, *r) {
                sum2 += e * e;
                max = max.max(e);
                count += 1;
            }
        }
    }
    if count == 0 {
        return Err(Error::Calibration(
            "no corner could be undistorted with the calibrated rig".to_owned(),
        ));
    }
    #[allow(clippy::cast_precision_loss)]
    let epipolar_rms_px = (sum2 / count as f64).sqrt();
    Ok((epipolar_rms_px, max))
}

/// Calibrates a stereo rig from corner pairs of `board` in images of `image_size`.
pub fn calibrate_stereo(
    board: &Board,
    image_size: ImageSize,
    views: &[StereoCorners],
    options: &CalibrationOptions,
) -> Result<CalibrationReport> {
    options.validate()?;
    check_stereo_views(board, views, options)?;
    let flags = model_flags(options.distortion_coeffs)?;
    // Single precision is what OpenCV's calibration functions take.
    #[allow(clippy::cast_possible_truncation)]
    let obj_one: Vector<Point3f> = board
        .object_points()
        .iter()
        .map(|p| Point3f::new(p.x as f32, p.y as f32, p.z as f32))
        .collect();
    let obj: Vector<Vector<Point3f>> = views.iter().map(|_| obj_one.clone()).collect();
    let img_l: Vector<Vector<Point2f>> = views.iter().map(|v| to_f32_points(&v.left)).collect();
    let img_r: Vector<Vector<Point2f>> = views.iter().map(|v| to_f32_points(&v.right)).collect();
    let w = i32::try_from(image_size.width).map_err(|_| Error::Calibration("image too wide".to_owned()))?;
    let h = i32::try_from(image_size.height).map_err(|_| Error::Calibration("image too tall".to_owned()))?;
    let size = Size::new(w, h);
    let criteria = TermCriteria::new(
        (TermCriteria_Type::COUNT as i32) | (TermCriteria_Type::EPS as i32),
        60,
        1e-10,
    )
    .map_err(cv_err("TermCriteria"))?;
    let mono = |img: &Vector<Vector<Point2f>>, which: &str| -> Result<(Mat, Mat, f64)> {
        let mut k = Mat::default();
        let mut d = Mat::default();
        let mut rvecs: Vector<Mat> = Vector::new();
        let mut tvecs: Vector<Mat> = Vector::new();
        let rms = opencv::calib3d::calibrate_camera(
            &obj, img, size, &mut k, &mut d, &mut rvecs, &mut tvecs, flags, criteria,
        )
        .map_err(cv_err(format!("calibrateCamera ({which} camera)")))?;
        Ok((k, d, rms))
    };
    let (mut k1, mut d1, rms_left_px) = mono(&img_l, "left")?;
    let (mut k2, mut d2, rms_right_px) = mono(&img_r, "right")?;
    let (mut r, mut t, mut e, mut f) = (Mat::default(), Mat::default(), Mat::default(), Mat::default());
    let mut per_view = Mat::default();
    let rms_stereo_px = stereo_calibrate_per_view(
        &obj,
        &img_l,
        &img_r,
        &mut k1,
        &mut d1,
        &mut k2,
        &mut d2,
        size,
        &mut r,
        &mut t,
        &mut e,
        &mut f,
        &mut per_view,
        flags | opencv::calib3d::CALIB_USE_INTRINSIC_GUESS,
        criteria,
    )
    .map_err(cv_err("stereoCalibrate"))?;
    let per_pair = pair_errors(views, &per_view)?;
    let keep = |d: &Mat| -> Result<Mat> {
        // calibrateCamera returns 5 coefficients with k3 fixed at 0 for the 4-coefficient model.
        let (_, _, mut v) = crate::cv::mat_to_rows(d)?;
        v.truncate(options.distortion_coeffs);
        crate::cv::mat_from_rows(1, v.len(), &v)
    };
    let left = camera_from_cv(image_size, &k1, &keep(&d1)?)?;
    let right = camera_from_cv(image_size, &k2, &keep(&d2)?)?;
    let rig = StereoRig {
        left,
        right,
        right_from_left: isometry_from_rt(&r, &t)?,
    };
    rig.validate()?;
    for (name, v) in [
        ("left", rms_left_px),
        ("right", rms_right_px),
        ("stereo", rms_stereo_px),
    ] {
        if !v.is_finite() {
            return Err(Error::Calibration(format!(
                "OpenCV returned a non-finite {name} RMS error"
            )));
        }
    }
    let (epipolar_rms_px, max) = epipolar_errors(&rig, views)?;
    Ok(CalibrationReport {
        rig,
        pairs_used: views.len(),
        rms_left_px,
        rms_right_px,
        rms_stereo_px,
        epipolar_rms_px,
        epipolar_max_px: max,
        per_pair,
    })
}

/// Normalised coordinates of the pixel-corner lattice of a camera, for [`render_view`].
///
/// Entry `(v * (width + 1) + u)` is the ray through the image point `(u - 0.5, v - 0.5)`, the
/// top-left corner of pixel `(u, v)`; `None` where the lens model cannot be inverted.
#[derive(Debug, Clone)]
pub struct RayGrid {
    size: ImageSize,
    rays: Vec<Option<Vector2<f64>>>,
}

impl RayGrid {
    /// Undistorts every pixel corner of `camera` (about 0.3 M points for 640 x 480).
    pub fn new(camera: &Camera) -> RayGrid {
        let (w, h) = (
            camera.image_size.width as usize,
            camera.image_size.height as usize,
        );
        let mut rays = Vec::with_capacity((w + 1) * (h + 1));
        for v in 0..=h {
            for u in 0..=w {
                #[allow(clippy::cast_precision_loss)]
                rays.push(camera.undistort(Point2::new(u as f64 - 0.5, v as f64 - 0.5)));
            }
        }
        RayGrid {
            size: camera.image_size,
            rays,
        }
    }
}

/// Renders the checkerboard as seen by a camera: 8-bit grey, `board` with one extra square on each
/// side (so its inner corners are as given), a white margin of one more square, a mid-grey
/// background. `cam_from_board` maps board coordinates (mm) into the camera frame. Each pixel is
/// the mean of 4 x 4 samples placed by bilinear interpolation of the rays of its corners.
pub fn render_view(grid: &RayGrid, board: &Board, cam_from_board: &Isometry3<f64>) -> Result<Mat> {
    let (w, h) = (grid.size.width as usize, grid.size.height as usize);
    let rot = cam_from_board.rotation.to_rotation_matrix().into_inner();
    let normal = rot * Vector3::z();
    let origin = cam_from_board.translation.vector;
    let plane_d = normal.dot(&origin);
    let rot_t = rot.transpose();
    let (cols, rows, s) = (
        f64::from(board.inner_cols),
        f64::from(board.inner_rows),
        board.square_mm,
    );
    let shade = |ray: Vector2<f64>| -> f64 {
        let d = Vector3::new(ray.x, ray.y, 1.0);
        let den = normal.dot(&d);
        if den.abs() < 1e-12 {
            return 128.0;
        }
        let lambda = plane_d / den;
        if lambda <= 0.0 {
            return 128.0;
        }
        let b = rot_t * (d * lambda - origin);
        let (x, y) = (b.x / s, b.y / s);
        if x < -2.0 || y < -2.0 || x > cols + 1.0 || y > rows + 1.0 {
            128.0
        } else if x < -1.0
            || y < -1.0
            || x > cols
            || y > rows
            || (x.floor() + y.floor()).rem_euclid(2.0) == 0.0
        {
            250.0
        } else {
            10.0
        }
    };
    const N: usize = 4;
    // Shade at every pixel corner first: a pixel whose four corners agree is uniform (squares are
    // much larger than a pixel, and a straight edge crossing a pixel separates its corners), so only
    // pixels on an edge are super-sampled.
    let corner_shade: Vec<Option<f64>> = grid.rays.iter().map(|r| r.map(shade)).collect();
    let mut out = vec![0u8; w * h];
    for v in 0..h {
        for u in 0..w {
            let at = |du: usize, dv: usize| grid.rays[(v + dv) * (w + 1) + u + du];
            let (Some(a), Some(b), Some(c), Some(d)) = (at(0, 0), at(1, 0), at(0, 1), at(1, 1)) else {
                out[v * w + u] = 128;
                continue;
            };
            let sh = |du: usize, dv: usize| corner_shade[(v + dv) * (w + 1) + u + du];
            if let Some(s00) = sh(0, 0)
                && sh(1, 0) == Some(s00)
                && sh(0, 1) == Some(s00)
                && sh(1, 1) == Some(s00)
            {
                // Shades are 10, 128 or 250: exact in u8.
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                {
                    out[v * w + u] = s00 as u8;
                }
                continue;
            }
            let mut acc = 0.0;
            for j in 0..N {
                #[allow(clippy::cast_precision_loss)]
                let fy = (j as f64 + 0.5) / N as f64;
                for i in 0..N {
                    #[allow(clippy::cast_precision_loss)]
                    let fx = (i as f64 + 0.5) / N as f64;
                    let top = a * (1.0 - fx) + b * fx;
                    let bottom = c * (1.0 - fx) + d * fx;
                    acc += shade(top * (1.0 - fy) + bottom * fy);
                }
            }
            #[allow(
                clippy::cast_possible_truncation,
                clippy::cast_sign_loss,
                clippy::cast_precision_loss
            )]
            {
                out[v * w + u] = (acc / (N * N) as f64).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    let mat = Mat::from_slice(&out).map_err(cv_err("Mat::from_slice"))?;
    let rows_i = i32::try_from(h).map_err(|_| Error::Calibration("image too tall".to_owned()))?;
    mat.reshape(1, rows_i)
        .map_err(cv_err("Mat::reshape"))?
        .try_clone()
        .map_err(cv_err("Mat::clone"))
}
