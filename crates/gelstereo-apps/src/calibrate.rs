//! Stereo checkerboard calibration from two folders of images (`gelstereo calibrate`): pairs the
//! images by file name, finds the board in both views in parallel, calibrates with OpenCV
//! ([`gelstereo_geometry::checkerboard`]).

use std::path::{Path, PathBuf};

use gelstereo_core::{ImageSize, Point2};
use gelstereo_geometry::checkerboard::{CalibrationReport, calibrate_stereo, find_corners};
use gelstereo_geometry::{Board, CalibrationOptions, StereoCorners};
use rayon::prelude::*;

use gelstereo::{Error, Result};

/// A calibration from two folders, with what was left out.
#[derive(Debug, Clone)]
pub struct FolderCalibration {
    /// OpenCV's result: the rig, RMS and epipolar errors, per-pair errors.
    pub report: CalibrationReport,
    /// The images' size.
    pub image_size: ImageSize,
    /// Image pairs found (same file name in both folders).
    pub pairs: usize,
    /// Pairs whose board was not found: `NAME (left|right|both)`.
    pub not_found: Vec<String>,
    /// Images without a counterpart in the other folder.
    pub unpaired: Vec<String>,
}

impl FolderCalibration {
    /// The figures as JSON (errors, pairs used, rejected images), with `calibration` the path the
    /// rig was written to.
    pub fn to_json(&self, calibration: &str) -> serde_json::Value {
        let report = &self.report;
        serde_json::json!({
            "pairs": self.pairs,
            "pairs_used": report.pairs_used,
            "board_not_found": self.not_found,
            "unpaired": self.unpaired,
            "rms_left_px": report.rms_left_px,
            "rms_right_px": report.rms_right_px,
            "rms_stereo_px": report.rms_stereo_px,
            "epipolar_rms_px": report.epipolar_rms_px,
            "epipolar_max_px": report.epipolar_max_px,
            "baseline_mm": report.rig.baseline_mm(),
            "per_pair": report
                .per_pair
                .iter()
                .map(|p| serde_json::json!({"name": p.name, "left_rms_px": p.left_rms_px, "right_rms_px": p.right_rms_px}))
                .collect::<Vec<_>>(),
            "calibration": calibration,
        })
    }
}

/// One detected pair: file name, image size, left and right corners (`None`: board not found).
type Detected = (String, ImageSize, Option<Vec<Point2>>, Option<Vec<Point2>>);

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// A file name and the left and right images of that name.
type NamedPair = (String, PathBuf, PathBuf);

/// Pairs `left_dir` and `right_dir` by file name.
fn pair_images(left_dir: &Path, right_dir: &Path) -> Result<(Vec<NamedPair>, Vec<String>)> {
    let left = gelstereo_io::images::list_images(left_dir)?;
    let right = gelstereo_io::images::list_images(right_dir)?;
    let mut unpaired = Vec::new();
    let mut pairs = Vec::new();
    for l in &left {
        let name = file_name(l);
        match right.iter().find(|r| file_name(r) == name) {
            Some(r) => pairs.push((name, l.clone(), r.clone())),
            None => unpaired.push(format!("{} (no right image)", l.display())),
        }
    }
    for r in &right {
        if !left.iter().any(|l| file_name(l) == file_name(r)) {
            unpaired.push(format!("{} (no left image)", r.display()));
        }
    }
    if pairs.is_empty() {
        return Err(Error::Invalid(format!(
            "no image pairs: {} and {} share no image file names ({} and {} images)",
            left_dir.display(),
            right_dir.display(),
            left.len(),
            right.len()
        )));
    }
    Ok((pairs, unpaired))
}

fn detect(name: &str, l: &Path, r: &Path, board: &Board, options: &CalibrationOptions) -> Result<Detected> {
    let li = gelstereo_io::images::read_image(l)?;
    let ri = gelstereo_io::images::read_image(r)?;
    let (ls, rs) = (gelstereo::image_size(&li), gelstereo::image_size(&ri));
    if ls != rs {
        return Err(Error::Invalid(format!(
            "{}: {}x{} but {}: {}x{}; both cameras must have the same image size",
            l.display(),
            ls.width,
            ls.height,
            r.display(),
            rs.width,
            rs.height
        )));
    }
    let lc =
        find_corners(&li, board, options).map_err(|e| Error::from(e).context(l.display().to_string()))?;
    let rc =
        find_corners(&ri, board, options).map_err(|e| Error::from(e).context(r.display().to_string()))?;
    Ok((name.to_owned(), ls, lc, rc))
}

/// Calibrates a stereo rig from the checkerboard images of `left_dir` and `right_dir` (paired by file
/// name; all of one size).
pub fn calibrate_folders(
    left_dir: &Path,
    right_dir: &Path,
    board: &Board,
    options: &CalibrationOptions,
) -> Result<FolderCalibration> {
    options.validate()?;
    let (pairs, unpaired) = pair_images(left_dir, right_dir)?;
    // Detect in parallel; keep the file order.
    let detected: Vec<Result<Detected>> = pairs
        .par_iter()
        .map(|(name, l, r)| detect(name, l, r, board, options))
        .collect();
    let mut size: Option<(ImageSize, String)> = None;
    let mut views = Vec::new();
    let mut not_found = Vec::new();
    for d in detected {
        let (name, s, lc, rc) = d?;
        match &size {
            None => size = Some((s, name.clone())),
            Some((first, first_name)) if *first != s => {
                return Err(Error::Invalid(format!(
                    "{name} is {}x{} but {first_name} is {}x{}: all images must have one size",
                    s.width, s.height, first.width, first.height
                )));
            }
            _ => {}
        }
        match (lc, rc) {
            (Some(left), Some(right)) => views.push(StereoCorners { name, left, right }),
            (None, Some(_)) => not_found.push(format!("{name} (left)")),
            (Some(_), None) => not_found.push(format!("{name} (right)")),
            (None, None) => not_found.push(format!("{name} (both)")),
        }
    }
    let Some((image_size, _)) = size else {
        return Err(Error::Invalid("no images read".into()));
    };
    let report = calibrate_stereo(board, image_size, &views, options).map_err(|e| {
        Error::from(e).context(format!(
            "calibrating from {} and {}",
            left_dir.display(),
            right_dir.display()
        ))
    })?;
    Ok(FolderCalibration {
        report,
        image_size,
        pairs: pairs.len(),
        not_found,
        unpaired,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_geometry::nalgebra::Point3;
    use gelstereo_geometry::{CalibrationPath, CornerDetector, StereoRig};
    use gelstereo_sim::SensorSpec;
    use gelstereo_sim::checkerboard::write_checkerboard_set;

    /// The simulator's checkerboard set for the reference sensor (rendered through its cameras with
    /// blur, noise and vignetting, true calibration alongside), plus one pair without a board and one
    /// left image without a right counterpart.
    fn simulated_set(dir: &Path, board: &Board, poses: usize) -> StereoRig {
        let sensor = SensorSpec::reference().build().unwrap();
        write_checkerboard_set(dir, &sensor, board, poses, 6, false).unwrap();
        let blank =
            opencv::core::Mat::new_rows_cols_with_default(480, 640, opencv::core::CV_8UC1, 128.into())
                .unwrap();
        for name in ["left/blank.png", "right/blank.png", "left/lonely.png"] {
            gelstereo_io::images::write_image(&dir.join(name), &blank).unwrap();
        }
        StereoRig::load(dir.join("calib.yaml").to_str().unwrap()).unwrap()
    }

    /// 3-D RMSE (mm) of points on and around the gel (left frame, 23-26 mm deep) projected through
    /// `truth` and triangulated with `est`.
    fn gel_rmse_mm(truth: &StereoRig, est: &StereoRig) -> f64 {
        let t = gelstereo_geometry::Triangulator::new(est.clone(), Default::default()).unwrap();
        let (mut sum2, mut n) = (0.0, 0u32);
        for i in -8..=8 {
            for j in -8..=8 {
                for z in [23.0, 24.5, 26.0] {
                    let p = Point3::new(f64::from(i), f64::from(j), z);
                    if let Some((l, r)) = truth.project(&p) {
                        sum2 += (t.triangulate(l, r).unwrap().p_in_left_mm - p).norm_squared();
                        n += 1;
                    }
                }
            }
        }
        (sum2 / f64::from(n)).sqrt()
    }

    #[test]
    fn calibrates_the_simulators_boards_and_writes_both_formats() {
        let board = Board::parse("9x6", 1.5).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let set = dir.path().join("set");
        let truth = simulated_set(&set, &board, 12);
        // Both detectors: classic for the YAML, sector-based for the mrcal pair.
        for (out, detector, bound_mm) in [("calib.yaml", "classic", 0.03), ("models", "sb", 0.08)] {
            let out = dir.path().join(out).to_string_lossy().into_owned();
            let options = CalibrationOptions {
                detector: detector.parse().unwrap(),
                ..Default::default()
            };
            let calibration =
                calibrate_folders(&set.join("left"), &set.join("right"), &board, &options).unwrap();
            calibration.report.rig.save(&out).unwrap();
            let est = StereoRig::load(&out).unwrap();
            assert!(
                (est.baseline_mm() - truth.baseline_mm()).abs() < 0.02,
                "{}",
                est.baseline_mm()
            );
            assert!(
                (est.left.fx / truth.left.fx - 1.0).abs() < 0.003,
                "{}",
                est.left.fx
            );
            let report = calibration.to_json(&out);
            assert_eq!(report["pairs"], 13);
            assert_eq!(report["pairs_used"], 12);
            assert!(report["rms_stereo_px"].as_f64().unwrap() < 0.15, "{report}");
            assert!(report["epipolar_rms_px"].as_f64().unwrap() < 0.15, "{report}");
            assert_eq!(report["board_not_found"][0], "blank.png (both)");
            assert_eq!(report["unpaired"].as_array().unwrap().len(), 1);
            assert_eq!(report["per_pair"].as_array().unwrap().len(), 12);
            assert_eq!(report["per_pair"][0]["name"], "000000.png");
            assert_eq!(report["calibration"], out.as_str());
            let rmse = gel_rmse_mm(&truth, &est);
            eprintln!("{detector}: gel 3-D RMSE {rmse:.4} mm with the calibrated rig; {report}");
            assert!(rmse < bound_mm, "{detector}: {rmse}");
        }
    }

    #[test]
    fn errors_are_clear() {
        let dir = tempfile::tempdir().unwrap();
        let (l, r) = (dir.path().join("l"), dir.path().join("r"));
        std::fs::create_dir_all(&l).unwrap();
        std::fs::create_dir_all(&r).unwrap();
        let e = Board::parse("9by6", 1.5).unwrap_err().to_string();
        assert!(e.contains("9by6"), "{e}");
        let e = CalibrationPath::parse("x.json").unwrap_err().to_string();
        assert!(e.contains("x.json") && e.contains(".yaml"), "{e}");
        let board = Board::parse("9x6", 1.5).unwrap();
        let e = calibrate_folders(&l, &r, &board, &CalibrationOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("no image pairs"), "{e}");
        let e = "fancy".parse::<CornerDetector>().unwrap_err().to_string();
        assert!(e.contains("fancy") && e.contains("classic or sb"), "{e}");
    }
}
