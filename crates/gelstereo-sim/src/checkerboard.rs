//! Checkerboard targets seen through the simulated sensor's cameras, for calibration work: the
//! board is drawn by `gelstereo_geometry::checkerboard::render_view` (exact ray casting through
//! the lens model, 4 x 4 supersampling) and then goes through the sensor's optics (defocus,
//! vignetting, noise) like the gel images.
//!
//! A set on disk: `OUT/left/NNNNNN.png`, `OUT/right/NNNNNN.png`, the true calibration
//! (`calib.yaml`, `left.cameramodel`, `right.cameramodel`), `corners.csv` (ground-truth projections
//! of every inner corner, OpenCV order) and `poses.json` (`left_from_board` per image).

use std::fmt::Write as _;
use std::path::Path;

use gelstereo_core::{Point2, StereoPair};
use gelstereo_geometry::Board;
use gelstereo_geometry::checkerboard::{RayGrid, render_view};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, MatTraitManual, Size};
use opencv::imgproc;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::dataset::begin_output;
use crate::error::{Error, Result, cv_err, io_err};
use gelstereo_sensor::Sensor;

/// How the target images are degraded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetLook {
    /// Defocus blur, Gaussian sigma in px (0: none).
    pub blur_px: f64,
    /// Noise standard deviation, grey levels.
    pub noise: f64,
    /// Relative darkening at the image corners.
    pub vignette: f64,
}

impl Default for TargetLook {
    /// Mild, like the reference sensor's gel images: 0.7 px blur, 1.5 grey levels of noise, 20 %
    /// vignetting.
    fn default() -> Self {
        Self {
            blur_px: 0.7,
            noise: 1.5,
            vignette: 0.2,
        }
    }
}

/// Both camera's ray lookups for a sensor (build once, render many poses).
pub struct TargetRenderer<'a> {
    sensor: &'a Sensor,
    rays: StereoPair<RayGrid>,
}

impl<'a> TargetRenderer<'a> {
    /// Prepares the ray lookups of both cameras of `sensor` (about 0.3 M undistortions per view).
    pub fn new(sensor: &'a Sensor) -> Self {
        Self {
            sensor,
            rays: StereoPair::new(RayGrid::new(&sensor.rig.left), RayGrid::new(&sensor.rig.right)),
        }
    }

    /// Renders `board` at `left_from_board` in both views (8-bit grey), degraded by `look`; `seed`
    /// drives the noise.
    pub fn render(
        &self,
        board: &Board,
        left_from_board: &Isometry3<f64>,
        look: &TargetLook,
        seed: u64,
    ) -> Result<StereoPair<Mat>> {
        let right_from_board = self.sensor.rig.right_from_left * left_from_board;
        let left = render_view(&self.rays.left, board, left_from_board)?;
        let right = render_view(&self.rays.right, board, &right_from_board)?;
        Ok(StereoPair::new(
            degrade(left, look, seed)?,
            degrade(right, look, seed ^ 0x5151)?,
        ))
    }

    /// Ground-truth projections of the inner corners (OpenCV order) in both views.
    pub fn corners(
        &self,
        board: &Board,
        left_from_board: &Isometry3<f64>,
    ) -> StereoPair<Vec<Option<Point2>>> {
        let pts = board.object_points();
        let rig = &self.sensor.rig;
        StereoPair::new(
            pts.iter()
                .map(|p| rig.left.project(&(left_from_board * p)))
                .collect(),
            pts.iter()
                .map(|p| rig.right.project(&(rig.right_from_left * (left_from_board * p))))
                .collect(),
        )
    }
}

/// Renders one stereo view of a checkerboard through the sensor's cameras: a convenience over
/// [`TargetRenderer`] for a single pose.
pub fn render_checkerboard(
    sensor: &Sensor,
    board: &Board,
    left_from_board: &Isometry3<f64>,
    look: &TargetLook,
    seed: u64,
) -> Result<StereoPair<Mat>> {
    TargetRenderer::new(sensor).render(board, left_from_board, look, seed)
}

fn degrade(img: Mat, look: &TargetLook, seed: u64) -> Result<Mat> {
    let mut img = if look.blur_px > 0.05 {
        let mut out = Mat::default();
        imgproc::gaussian_blur_def(&img, &mut out, Size::new(0, 0), look.blur_px)
            .map_err(cv_err("target blur"))?;
        out
    } else {
        img
    };
    let (w, h) = (img.cols() as usize, img.rows() as usize);
    let buf = img.data_bytes_mut().map_err(cv_err("target buffer"))?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (hw, hh) = (0.5 * w as f64, 0.5 * h as f64);
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = ((x as f64 - hw) / hw, (y as f64 - hh) / hh);
            let vig = 1.0 - look.vignette * 0.5 * (dx * dx + dy * dy);
            // Uniform noise with the requested standard deviation.
            let n = (rng.random::<f64>() - 0.5) * 12f64.sqrt() * look.noise;
            let v = &mut buf[y * w + x];
            *v = (f64::from(*v) * vig + n).round().clamp(0.0, 255.0) as u8;
        }
    }
    Ok(img)
}

/// `count` random board poses (`left_from_board`) in front of the gel, with every inner corner
/// visible in both views at least one square from the border: the board's centre within 3 mm of
/// the gel centre and up to 4 mm nearer or farther, tilted up to 25 degrees, turned up to 15.
pub fn random_poses(sensor: &Sensor, board: &Board, count: usize, seed: u64) -> Result<Vec<Isometry3<f64>>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let fully_visible = |pose: &Isometry3<f64>| {
        let size = sensor.spec.image_size();
        let m = 1.0 * board.square_mm * sensor.pitch_px() / sensor.spec.grid.pitch_mm;
        let inside = |p: Option<Point2>| {
            p.is_some_and(|p| {
                p.x > m
                    && p.y > m
                    && p.x < f64::from(size.width) - 1.0 - m
                    && p.y < f64::from(size.height) - 1.0 - m
            })
        };
        board.object_points().iter().all(|p| {
            let l = pose * p;
            inside(sensor.rig.left.project(&l))
                && inside(sensor.rig.right.project(&(sensor.rig.right_from_left * l)))
        })
    };
    let centre = Vector3::new(
        0.5 * f64::from(board.inner_cols - 1) * board.square_mm,
        0.5 * f64::from(board.inner_rows - 1) * board.square_mm,
        0.0,
    );
    let mut poses = Vec::with_capacity(count);
    let mut tries = 0;
    while poses.len() < count {
        tries += 1;
        if tries > 200 * count.max(1) {
            return Err(Error::Parameter {
                name: "checkerboard",
                value: format!(
                    "{}x{} inner corners of {} mm",
                    board.inner_cols, board.inner_rows, board.square_mm
                ),
                expected: "a board small enough to be seen whole by both cameras (try a smaller --square-mm)"
                    .into(),
            });
        }
        let tilt = UnitQuaternion::from_euler_angles(
            rng.random_range(-25f64..25.0).to_radians(),
            rng.random_range(-25f64..25.0).to_radians(),
            rng.random_range(-15f64..15.0).to_radians(),
        );
        let at = Vector3::new(
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
            rng.random_range(-4.0..4.0),
        );
        let sensor_from_board = Isometry3::from_parts(Translation3::from(at), tilt)
            * Isometry3::translation(-centre.x, -centre.y, 0.0);
        let pose = sensor.left_from_sensor * sensor_from_board;
        if fully_visible(&pose) {
            poses.push(pose);
        }
    }
    Ok(poses)
}

/// Most poses of a checkerboard calibration set (a calibration needs 15 to 50).
pub const MAX_POSES: usize = 10_000;

/// Writes a checkerboard calibration set (see the module docs) for `sensor` into `out`: `count`
/// random poses, seed `seed`. Refuses a non-empty `out` unless `force`; nothing half-written is
/// left as if complete.
pub fn write_checkerboard_set(
    out: &Path,
    sensor: &Sensor,
    board: &Board,
    count: usize,
    seed: u64,
    force: bool,
) -> Result<()> {
    if !(1..=MAX_POSES).contains(&count) {
        return Err(Error::Parameter {
            name: "poses",
            value: count.to_string(),
            expected: format!("1 to {MAX_POSES}"),
        });
    }
    let poses = random_poses(sensor, board, count, seed)?;
    let pending = begin_output(out, force)?;
    let tmp = &pending.tmp;
    let result = (|| -> Result<()> {
        for v in ["left", "right"] {
            std::fs::create_dir_all(tmp.join(v)).map_err(io_err(tmp.join(v)))?;
        }
        let renderer = TargetRenderer::new(sensor);
        let look = TargetLook::default();
        poses
            .par_iter()
            .enumerate()
            .try_for_each(|(i, pose)| -> Result<()> {
                if gelstereo_core::interrupt::requested() {
                    return Err(Error::Interrupted);
                }
                let imgs = renderer.render(
                    board,
                    pose,
                    &look,
                    seed ^ (i as u64 + 1).wrapping_mul(0x9E37_79B9),
                )?;
                for (name, img) in [("left", &imgs.left), ("right", &imgs.right)] {
                    let path = tmp.join(name).join(format!("{i:06}.png"));
                    std::fs::write(&path, encode_grey_png(img)?).map_err(io_err(&path))?;
                }
                Ok(())
            })?;
        let mut csv = String::from("image,corner,X_board_mm,Y_board_mm,x_left,y_left,x_right,y_right\n");
        let obj = board.object_points();
        let mut json = Vec::new();
        for (i, pose) in poses.iter().enumerate() {
            let c = renderer.corners(board, pose);
            for (k, p) in obj.iter().enumerate() {
                let cell = |q: Option<Point2>| {
                    q.map(|q| format!("{:.6},{:.6}", q.x, q.y))
                        .unwrap_or_else(|| ",".into())
                };
                let _ = writeln!(
                    csv,
                    "{i:06},{k},{:.6},{:.6},{},{}",
                    p.x,
                    p.y,
                    cell(c.left[k]),
                    cell(c.right[k])
                );
            }
            let t = pose.translation.vector;
            let r = pose.rotation.scaled_axis();
            json.push(serde_json::json!({ "image": format!("{i:06}"), "rvec": [r.x, r.y, r.z], "tvec_mm": [t.x, t.y, t.z] }));
        }
        std::fs::write(tmp.join("corners.csv"), csv).map_err(io_err(tmp.join("corners.csv")))?;
        let meta = serde_json::json!({
            "generator": crate::GENERATOR_VERSION,
            "sensor": sensor.spec.name,
            "board": { "inner_cols": board.inner_cols, "inner_rows": board.inner_rows, "square_mm": board.square_mm },
            "seed": seed,
            "left_from_board": json,
        });
        let text = serde_json::to_string_pretty(&meta).unwrap_or_default();
        std::fs::write(tmp.join("poses.json"), text + "\n").map_err(io_err(tmp.join("poses.json")))?;
        crate::calibration::write_calibration(&sensor.rig, tmp)
    })();
    result?;
    pending.finish()
}

fn encode_grey_png(img: &Mat) -> Result<Vec<u8>> {
    let (w, h) = (img.cols() as u32, img.rows() as u32);
    let data = img.data_bytes().map_err(cv_err("target buffer"))?;
    gelstereo_io::images::encode_png(data, (w, h), 1, png::Compression::Fastest, None)
        .map_err(|e| Error::Png(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SensorSpec;
    use gelstereo_geometry::CalibrationOptions;
    use gelstereo_geometry::checkerboard::find_corners;

    #[test]
    fn rendered_boards_are_found_where_the_truth_says() {
        let sensor = SensorSpec::reference().build().unwrap();
        let board = Board::parse("7x5", 1.5).unwrap();
        let poses = random_poses(&sensor, &board, 2, 3).unwrap();
        let r = TargetRenderer::new(&sensor);
        for pose in &poses {
            let imgs = r.render(&board, pose, &TargetLook::default(), 1).unwrap();
            let truth = r.corners(&board, pose);
            for (img, gt) in [(&imgs.left, &truth.left), (&imgs.right, &truth.right)] {
                let found = find_corners(img, &board, &CalibrationOptions::default())
                    .unwrap()
                    .unwrap();
                let worst = found
                    .iter()
                    .zip(gt)
                    .map(|(a, b)| a.distance(b.unwrap()))
                    .fold(0.0, f64::max);
                assert!(worst < 0.3, "corner error {worst} px");
            }
        }
        let e = random_poses(&sensor, &Board::parse("9x6", 10.0).unwrap(), 1, 1)
            .unwrap_err()
            .to_string();
        assert!(e.contains("--square-mm"), "{e}");
    }
}
