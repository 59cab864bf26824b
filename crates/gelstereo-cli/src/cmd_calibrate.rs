//! `gelstereo calibrate`: stereo checkerboard calibration. Pairs the images of LEFT_DIR and
//! RIGHT_DIR by file name, finds the board in both views, calibrates with OpenCV
//! ([`gelstereo_apps::calibrate`]), prints the RMS reprojection and epipolar errors and writes
//! the calibration (OpenCV YAML/XML or a mrcal pair, by the path given to `--out`).

use std::path::PathBuf;

use anyhow::Context;
use gelstereo::geometry::{Board, CalibrationOptions, CalibrationPath};
use gelstereo_apps::calibrate::{FolderCalibration, calibrate_folders};

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
    /// The sensor's design baseline, mm (the distance between the cameras' centres): the printed
    /// baseline is checked against it. A wrong --square-mm leaves the RMS error as it is and scales
    /// the baseline and every 3-D figure, so this is the check that catches it.
    #[arg(long, value_name = "MM", value_parser = parse_baseline)]
    design_baseline_mm: Option<f64>,
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
    let calibration = calibrate_folders(&args.left_dir, &args.right_dir, &board, &options)?;
    let FolderCalibration {
        report,
        image_size,
        pairs,
        not_found,
        unpaired,
    } = &calibration;
    for u in unpaired {
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
    println!(
        "{}",
        baseline_check(rig.baseline_mm(), args.design_baseline_mm, args.square_mm)
    );
    println!("wrote {}", args.out);
    if let Some(path) = &args.report {
        let json = calibration.to_json(&args.out);
        gelstereo::core::files::write_whole(path, serde_json::to_string_pretty(&json)?.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Largest relative difference between the measured and the design baseline taken as agreement.
const BASELINE_TOLERANCE: f64 = 0.05;

/// What the measured baseline says of the square size: with a design baseline, whether they
/// agree (and the square size that would make them agree when not); without one, what to compare.
fn baseline_check(measured_mm: f64, design_mm: Option<f64>, square_mm: f64) -> String {
    let Some(design) = design_mm else {
        return format!(
            "CHECK the baseline ({measured_mm:.3} mm) against your sensor's design: the RMS cannot reveal a \
             wrong --square-mm, which scales the baseline and every 3-D figure (--design-baseline-mm MM checks it)"
        );
    };
    let ratio = measured_mm / design;
    if (ratio - 1.0).abs() <= BASELINE_TOLERANCE {
        format!("baseline agrees with the design's {design} mm (ratio {ratio:.3})")
    } else {
        format!(
            "WARNING: the baseline is {ratio:.3} x the design's {design} mm: is --square-mm {square_mm} right? \
             Squares of {:.4} mm would give the design baseline (every 3-D figure scales with it)",
            square_mm / ratio
        )
    }
}

fn parse_baseline(text: &str) -> Result<f64, String> {
    gelstereo::core::limits::parse_number_in(text, 0.1, 1000.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_baseline_off_the_design_names_the_square_size_that_fits() {
        let warning = baseline_check(12.0, Some(10.0), 1.8);
        assert!(
            warning.contains("1.200 x") && warning.contains("1.5000 mm"),
            "{warning}"
        );
        assert!(baseline_check(10.2, Some(10.0), 1.5).contains("agrees"));
        assert!(baseline_check(10.2, None, 1.5).contains("CHECK the baseline (10.200 mm)"));
    }
}
