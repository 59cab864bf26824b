//! Compares a calibration with a reference one (e.g. `gelstereo calibrate`'s result with the true
//! calibration a `gelstereo simulate --checkerboard` set was rendered with): intrinsics, baseline,
//! rotation, and what matters for reconstruction: points projected through the REFERENCE and
//! triangulated with the OTHER, over a grid of depths in front of both cameras.
//!
//! ```text
//! cargo build --release -p gelstereo-geometry --example compare_calibrations
//! target/release/examples/compare_calibrations REFERENCE OTHER [Z_MIN_MM Z_MAX_MM]
//! ```
//! Calibrations are anything `StereoRig::load` reads. Depths default to 22-28 mm (the reference
//! sensor's gel is ~24.5 mm from its left camera).

use gelstereo_geometry::nalgebra::Point3;
use gelstereo_geometry::{StereoRig, TriangulationConfig, Triangulator};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        return Err("usage: compare_calibrations REFERENCE OTHER [Z_MIN_MM Z_MAX_MM]".into());
    }
    let truth = StereoRig::load(&args[1])?;
    let est = StereoRig::load(&args[2])?;
    let z_min: f64 = args.get(3).map_or(Ok(22.0), |s| s.parse())?;
    let z_max: f64 = args.get(4).map_or(Ok(28.0), |s| s.parse())?;
    for (name, t, e) in [
        ("left", &truth.left, &est.left),
        ("right", &truth.right, &est.right),
    ] {
        println!(
            "{name}: fx {:+.3} fy {:+.3} cx {:+.3} cy {:+.3} px (other - reference)",
            e.fx - t.fx,
            e.fy - t.fy,
            e.cx - t.cx,
            e.cy - t.cy
        );
    }
    let dr = (est.right_from_left.rotation.inverse() * truth.right_from_left.rotation)
        .angle()
        .to_degrees();
    let dt = (est.right_from_left.translation.vector - truth.right_from_left.translation.vector).norm();
    println!(
        "baseline {:.4} vs {:.4} mm; T differs by {dt:.4} mm, R by {dr:.4} deg",
        est.baseline_mm(),
        truth.baseline_mm()
    );
    // Every pixel step of 8 in the left image, at depths z_min..z_max: points seen by both cameras.
    let tri = Triangulator::new(
        est.clone(),
        TriangulationConfig {
            max_reprojection_error_px: f64::INFINITY,
            ..Default::default()
        },
    )?;
    let (mut sum2, mut n, mut worst, mut rejected) = (0.0, 0usize, 0.0f64, 0usize);
    let steps = 7;
    for k in 0..steps {
        let z = z_min + (z_max - z_min) * f64::from(k) / f64::from(steps - 1);
        for v in (0..truth.left.image_size.height).step_by(8) {
            for u in (0..truth.left.image_size.width).step_by(8) {
                let Some(ray) = truth
                    .left
                    .undistort(gelstereo_core::Point2::new(f64::from(u), f64::from(v)))
                else {
                    continue;
                };
                let p = Point3::new(ray.x * z, ray.y * z, z);
                let Some((l, r)) = truth.project(&p) else { continue };
                if !truth.right.contains(r) {
                    continue;
                }
                match tri.triangulate(l, r) {
                    Ok(x) => {
                        let e = (x.p_in_left_mm - p).norm();
                        sum2 += e * e;
                        n += 1;
                        worst = worst.max(e);
                    }
                    Err(_) => rejected += 1,
                }
            }
        }
    }
    #[allow(clippy::cast_precision_loss)]
    let rmse = (sum2 / n.max(1) as f64).sqrt();
    println!(
        "3-D: {n} points at {z_min}-{z_max} mm seen by both cameras: RMSE {rmse:.4} mm, worst {worst:.4} mm, rejected {rejected}"
    );
    Ok(())
}
