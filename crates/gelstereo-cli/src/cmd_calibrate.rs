//! `gelstereo calibrate`: stereo checkerboard calibration. Pairs the images of LEFT_DIR and
//! RIGHT_DIR by file name, finds the board in both views, calibrates with OpenCV
//! ([`gelstereo::calibrate`]), prints the RMS reprojection and epipolar errors and writes
//! the calibration (OpenCV YAML/XML or a mrcal pair, by the path given to `--out`).

use std::path::PathBuf;

use anyhow::Context;
use gelstereo::calibrate::{FolderCalibration, calibrate_folders};
use gelstereo_geometry::{Board, CalibrationOptions, CalibrationPath};

/// Arguments of `gelstereo calibrate`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The board's INNER corners, COLSxROWS (OpenCV's pattern size): a board of 10 x 7 squares is 9x6.
    #[arg(long, value_name = "COLSxROWS")]
    board: String,
    /// Side of one square, mm.
    #[arg(long, value_name = "S")]
    square_mm: f64,
    /// Where to write the calibration: FILE.yaml / FILE.yml / FILE.xml (OpenCV FileStorage),
    /// LEFT.cameramodel,RIGHT.cameramodel, or a folder (mrcal pair left.cameramodel, right.cameramodel).
    #[arg(long, value_name = "FILE")]
    out: String,
    /// Distortion coefficients to estimate: 4, 5 (OpenCV's default model), 8 (rational) or 12
    /// (rational + thin prism).
    #[arg(long, default_value_t = 5)]
    distortion: usize,
    /// Half-size of the cornerSubPix window, px (keep it below half a square in the image).
    #[arg(long, default_value_t = 5)]
    subpix_window: i32,
    /// Corner detector: classic (findChessboardCorners + cornerSubPix) or sb (findChessboardCornersSB,
    /// more robust to blur and noise).
    #[arg(long, default_value = "classic")]
    detector: String,
    /// Also write the figures (errors, pairs used, rejected images) as JSON to this file.
    #[arg(long, value_name = "FILE.json")]
    report: Option<PathBuf>,
    /// Folder of left images.
    left_dir: PathBuf,
    /// Folder of right images (same file names as the left ones).
    right_dir: PathBuf,
}

/// Runs `gelstereo calibrate`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let board = Board::parse(&args.board, args.square_mm)?;
    // Check the output path before the (slow) calibration.
    CalibrationPath::parse(&args.out)?;
    let options = CalibrationOptions {
        distortion_coeffs: args.distortion,
        subpix_half_window_px: args.subpix_window,
        detector: args.detector.parse()?,
        ..Default::default()
    };
    let FolderCalibration {
        report,
        image_size,
        pairs,
        not_found,
        unpaired,
    } = calibrate_folders(&args.left_dir, &args.right_dir, &board, &options)?;
    for u in &unpaired {
        eprintln!("warning: skipped {u}");
    }
    if !not_found.is_empty() {
        eprintln!(
            "warning: a {}x{}-corner board was not found in {} of {} pairs: {}",
            board.inner_cols,
            board.inner_rows,
            not_found.len(),
            pairs,
            not_found.join(", ")
        );
    }
    if args.distortion == 12 {
        eprintln!(
            "warning: the 12-coefficient model's thin-prism terms trade off with the principal point \
             unless the boards cover the whole image; compare with --distortion 5 or 8"
        );
    }
    report
        .rig
        .save(&args.out)
        .with_context(|| format!("writing {}", args.out))?;
    let rig = &report.rig;
    println!(
        "calibrated from {} of {} image pairs ({}x{} px)",
        report.pairs_used, pairs, image_size.width, image_size.height
    );
    println!(
        "RMS reprojection error: left {:.4} px, right {:.4} px, stereo {:.4} px",
        report.rms_left_px, report.rms_right_px, report.rms_stereo_px
    );
    println!(
        "epipolar error: RMS {:.4} px, max {:.4} px",
        report.epipolar_rms_px, report.epipolar_max_px
    );
    let mut worst = report.per_pair.clone();
    worst.sort_by(|a, b| (b.left_rms_px.max(b.right_rms_px)).total_cmp(&a.left_rms_px.max(a.right_rms_px)));
    let worst: Vec<String> = worst
        .iter()
        .take(3)
        .map(|p| format!("{} ({:.3} / {:.3} px)", p.name, p.left_rms_px, p.right_rms_px))
        .collect();
    println!("worst pairs (left / right RMS): {}", worst.join(", "));
    for (name, c) in [("left", &rig.left), ("right", &rig.right)] {
        println!(
            "{name}: fx {:.3} fy {:.3} cx {:.3} cy {:.3} px, distortion {:?}",
            c.fx, c.fy, c.cx, c.cy, c.distortion.coeffs
        );
    }
    let t = rig.right_from_left.translation.vector;
    println!(
        "baseline {:.4} mm, T = [{:.4}, {:.4}, {:.4}] mm, rotation {:.4} deg",
        rig.baseline_mm(),
        t.x,
        t.y,
        t.z,
        rig.right_from_left.rotation.angle().to_degrees()
    );
    println!("wrote {}", args.out);
    if let Some(path) = &args.report {
        let json = serde_json::json!({
            "pairs": pairs,
            "pairs_used": report.pairs_used,
            "board_not_found": not_found,
            "unpaired": unpaired,
            "rms_left_px": report.rms_left_px,
            "rms_right_px": report.rms_right_px,
            "rms_stereo_px": report.rms_stereo_px,
            "epipolar_rms_px": report.epipolar_rms_px,
            "epipolar_max_px": report.epipolar_max_px,
            "baseline_mm": rig.baseline_mm(),
            "per_pair": report
                .per_pair
                .iter()
                .map(|p| serde_json::json!({"name": p.name, "left_rms_px": p.left_rms_px, "right_rms_px": p.right_rms_px}))
                .collect::<Vec<_>>(),
            "calibration": args.out,
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_geometry::StereoRig;
    use gelstereo_geometry::nalgebra::Point3;
    use gelstereo_sim::SensorSpec;
    use gelstereo_sim::checkerboard::write_checkerboard_set;
    use std::path::Path;

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
            let args = Args {
                board: "9x6".into(),
                square_mm: 1.5,
                out: dir.path().join(out).to_string_lossy().into_owned(),
                distortion: 5,
                subpix_window: 5,
                detector: detector.into(),
                report: Some(dir.path().join("report.json")),
                left_dir: set.join("left"),
                right_dir: set.join("right"),
            };
            run(&args).unwrap();
            let est = StereoRig::load(&args.out).unwrap();
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
            let report: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(dir.path().join("report.json")).unwrap())
                    .unwrap();
            assert_eq!(report["pairs"], 13);
            assert_eq!(report["pairs_used"], 12);
            assert!(report["rms_stereo_px"].as_f64().unwrap() < 0.15, "{report}");
            assert!(report["epipolar_rms_px"].as_f64().unwrap() < 0.15, "{report}");
            assert_eq!(report["board_not_found"][0], "blank.png (both)");
            assert_eq!(report["unpaired"].as_array().unwrap().len(), 1);
            assert_eq!(report["per_pair"].as_array().unwrap().len(), 12);
            assert_eq!(report["per_pair"][0]["name"], "000000.png");
            let rmse = gel_rmse_mm(&truth, &est);
            eprintln!("{detector}: gel 3-D RMSE {rmse:.4} mm with the calibrated rig; {report}");
            assert!(rmse < bound_mm, "{detector}: {rmse}");
        }
    }

    #[test]
    fn errors_are_clear() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("l")).unwrap();
        std::fs::create_dir_all(dir.path().join("r")).unwrap();
        let args = |board: &str, out: &str| Args {
            board: board.into(),
            square_mm: 1.5,
            out: out.into(),
            distortion: 5,
            subpix_window: 5,
            detector: "classic".into(),
            report: None,
            left_dir: dir.path().join("l"),
            right_dir: dir.path().join("r"),
        };
        let e = run(&args("9by6", "x.yaml")).unwrap_err().to_string();
        assert!(e.contains("9by6"), "{e}");
        let e = run(&args("9x6", "x.json")).unwrap_err().to_string();
        assert!(e.contains("x.json") && e.contains(".yaml"), "{e}");
        let e = run(&args("9x6", "x.yaml")).unwrap_err().to_string();
        assert!(e.contains("no image pairs"), "{e}");
        let mut a = args("9x6", "x.yaml");
        a.detector = "fancy".into();
        let e = run(&a).unwrap_err().to_string();
        assert!(e.contains("fancy") && e.contains("classic or sb"), "{e}");
    }
}
