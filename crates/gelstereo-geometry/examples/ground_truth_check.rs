//! Triangulates the ground-truth 2-D marker positions of simulated recordings (`gelstereo simulate`)
//! and compares them with their 3-D ground truth: a check that the recording's calibration files and
//! this crate's camera model and triangulation agree. Both calibration formats of the recording
//! (`calib.yaml` and the mrcal pair) are used.
//!
//! ```text
//! cargo build --release -p gelstereo-geometry --example ground_truth_check
//! target/release/examples/ground_truth_check [--calib CALIBRATION] RECORDING...
//! ```
//! With `--calib`, that calibration (e.g. one from `gelstereo calibrate`) is used instead of the
//! recording's own files: the 3-D error then measures the calibration on the gel's markers.
//! Markers with `visible_left` and `visible_right` = 1 (when those columns exist) are used.

use std::collections::HashMap;

use gelstereo_core::Point2;
use gelstereo_geometry::{StereoRig, TriangulationConfig, Triangulator};
use nalgebra::Point3;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut dirs: Vec<String> = std::env::args().skip(1).collect();
    let mut calib = None;
    if dirs.first().is_some_and(|a| a == "--calib") {
        if dirs.len() < 2 {
            return Err("--calib needs a calibration".into());
        }
        calib = Some(dirs.remove(1));
        dirs.remove(0);
    }
    if dirs.is_empty() {
        return Err("usage: ground_truth_check [--calib CALIBRATION] RECORDING...".into());
    }
    for dir in dirs {
        let text = std::fs::read_to_string(format!("{dir}/markers.csv"))?;
        let mut lines = text.lines();
        let header: HashMap<&str, usize> = lines
            .next()
            .ok_or("empty markers.csv")?
            .split(',')
            .enumerate()
            .map(|(i, h)| (h, i))
            .collect();
        let col = |name: &str| {
            header
                .get(name)
                .copied()
                .ok_or(format!("{dir}/markers.csv: no column '{name}'"))
        };
        let cols = [
            col("x_left")?,
            col("y_left")?,
            col("x_right")?,
            col("y_right")?,
            col("X_mm")?,
            col("Y_mm")?,
            col("Z_mm")?,
        ];
        let visible = [
            header.get("visible_left").copied(),
            header.get("visible_right").copied(),
        ];
        let rigs = match &calib {
            Some(c) => vec![(c.clone(), StereoRig::load(c)?)],
            None => vec![
                (
                    "calib.yaml".to_owned(),
                    StereoRig::load(format!("{dir}/calib.yaml"))?,
                ),
                ("mrcal".to_owned(), StereoRig::load(&dir)?),
            ],
        };
        for (name, rig) in rigs {
            let t = Triangulator::new(rig, TriangulationConfig::default())?;
            let (mut sum2, mut n, mut worst, mut rejected, mut worst_px) =
                (0.0, 0usize, 0.0f64, 0usize, 0.0f64);
            for line in lines.clone() {
                let f: Vec<&str> = line.split(',').collect();
                if visible.iter().flatten().any(|&i| f.get(i) != Some(&"1")) {
                    continue;
                }
                let mut v = [0.0; 7];
                for (o, &i) in v.iter_mut().zip(&cols) {
                    *o = f.get(i).ok_or("short row")?.parse()?;
                }
                match t.triangulate(Point2::new(v[0], v[1]), Point2::new(v[2], v[3])) {
                    Ok(x) => {
                        let e = (x.p_in_left_mm - Point3::new(v[4], v[5], v[6])).norm();
                        sum2 += e * e;
                        n += 1;
                        worst = worst.max(e);
                        worst_px = worst_px.max(x.max_reprojection_error_px());
                    }
                    Err(_) => rejected += 1,
                }
            }
            #[allow(clippy::cast_precision_loss)]
            let rmse = (sum2 / n.max(1) as f64).sqrt();
            println!(
                "{dir} [{name}]: {n} markers, 3-D RMSE {rmse:.2e} mm, worst {worst:.2e} mm, \
                 worst reprojection {worst_px:.2e} px, rejected {rejected}"
            );
        }
    }
    Ok(())
}
