//! Times the triangulation of one frame of the reference sensor's 23 x 23 = 529 markers with each
//! method. Run in release:
//!
//! ```text
//! cargo build --release -p gelstereo-geometry --example triangulation_speed
//! target/release/examples/triangulation_speed [CALIBRATION]
//! ```
//! CALIBRATION defaults to the OpenCV8 test fixture (`tests/data/opencv8.yaml`).

use std::time::Instant;

use gelstereo_core::Point2;
use gelstereo_geometry::{StereoRig, TriangulationConfig, TriangulationMethod, Triangulator};
use nalgebra::Point3;

/// CPU time (user + system) this process has used, s, from /proc/self/stat (Linux; 10 ms ticks).
/// On a shared machine wall time includes time other processes held the core; CPU time does not.
fn cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let fields: Vec<&str> = stat.rsplit(')').next()?.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let default = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/opencv8.yaml").to_owned();
    let path = std::env::args().nth(1).unwrap_or(default);
    let rig = StereoRig::load(&path)?;
    // A 23 x 23 grid, 0.8 mm pitch, on a gently curved surface 24-26 mm in front of the left camera
    // (the reference sensor's gel seen from its left camera).
    let mut left = Vec::new();
    let mut right = Vec::new();
    for row in 0..23 {
        for col in 0..23 {
            let (x, y) = (f64::from(col - 11) * 0.8 + 5.0, f64::from(row - 11) * 0.8);
            let p = Point3::new(x, y, 25.0 + 0.01 * (x * x + y * y).sqrt());
            if let Some((l, r)) = rig.project(&p) {
                left.push(l);
                right.push(r);
            }
        }
    }
    println!("{} markers visible in both views", left.len());
    for method in [
        TriangulationMethod::Midpoint,
        TriangulationMethod::LeeCiveraMid2,
        TriangulationMethod::Lindstrom,
        TriangulationMethod::PixelOptimal,
    ] {
        let t = Triangulator::new(
            rig.clone(),
            TriangulationConfig {
                method,
                ..Default::default()
            },
        )?;
        let frames = 2000;
        let start = Instant::now();
        let cpu0 = cpu_s();
        let mut ok = 0;
        let mut best_us = f64::INFINITY;
        for _ in 0..frames {
            let t0 = Instant::now();
            ok = t
                .triangulate_all(&left, &right)?
                .iter()
                .filter(|r| r.is_ok())
                .count();
            best_us = best_us.min(t0.elapsed().as_secs_f64() * 1e6);
        }
        let mean_us = start.elapsed().as_secs_f64() * 1e6 / f64::from(frames);
        let cpu_us = cpu0
            .zip(cpu_s())
            .map_or(f64::NAN, |(a, b)| (b - a) * 1e6 / f64::from(frames));
        // Wall-clock mean and min include time other processes took the core; CPU time does not.
        println!(
            "{method:?}: {ok} triangulated, per frame: CPU {cpu_us:.1} us, wall {best_us:.1} us (min) / \
             {mean_us:.1} us (mean), one thread"
        );
    }
    // The parts: undistortion and projection of one view.
    let start = Instant::now();
    let mut acc = 0.0;
    for _ in 0..2000 {
        for p in &left {
            acc += rig.left.undistort(*p).map_or(0.0, |n| n.x);
        }
    }
    let undistort_ns = start.elapsed().as_secs_f64() * 1e9 / 2000.0 / left.len() as f64;
    let start = Instant::now();
    for _ in 0..2000 {
        for p in &left {
            acc += rig
                .left
                .project(&Point3::new(p.x * 1e-3, p.y * 1e-3, 1.0))
                .map_or(0.0, |q: Point2| q.x);
        }
    }
    let project_ns = start.elapsed().as_secs_f64() * 1e9 / 2000.0 / left.len() as f64;
    println!("undistort {undistort_ns:.0} ns, project {project_ns:.0} ns per point (checksum {acc:.3})");
    Ok(())
}
