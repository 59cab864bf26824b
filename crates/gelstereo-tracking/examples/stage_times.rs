//! Median time of each stage of `StereoSession::track` on a synthetic 23 x 23 stereo press (no
//! images, no localizer): where the tracking part of the pipeline spends its time.
//!
//! `cargo run --release -p gelstereo-tracking --example stage_times`

use std::time::Instant;

use gelstereo_core::{GridIndex, GridShape, ImageSize, Point2};
use gelstereo_geometry::{Camera, StereoRig, TriangulationConfig, TriangulationMethod, Triangulator};
use gelstereo_tracking::{
    ContactConfig, ReferenceSurface, SessionConfig, SlipConfig, SlipDetector, StereoSession, Tracker,
    TrackerConfig,
};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let size = ImageSize {
        width: 640,
        height: 480,
    };
    let cam = Camera::pinhole(size, 520.0, 520.0, 319.5, 239.5);
    let rig = StereoRig {
        left: cam.clone(),
        right: cam,
        right_from_left: Isometry3::from_parts(
            Translation3::new(-9.8, 0.0, 2.0),
            UnitQuaternion::from_euler_angles(0.0, -0.2, 0.0),
        ),
    };
    let shape = GridShape::REFERENCE;
    let scene = |d: f64, s: f64| -> Vec<Point3<f64>> {
        shape
            .indices()
            .map(|i| {
                let (x, y) = ((f64::from(i.col) - 11.0) * 0.8, (f64::from(i.row) - 11.0) * 0.8);
                let w = (d - ((x - s).powi(2) + y * y) / 12.0).max(0.0);
                Point3::new(x + 0.5 * s * (w > 0.0) as u8 as f64, y, 24.0 - w)
            })
            .collect()
    };
    let views =
        |p: &[Point3<f64>]| -> (Vec<Point2>, Vec<Point2>) { p.iter().filter_map(|q| rig.project(q)).unzip() };
    let (l0, r0) = views(&scene(0.0, 0.0));
    let ids: Vec<GridIndex> = shape.indices().collect();
    let lref: Vec<(GridIndex, Point2)> = ids.iter().copied().zip(l0.iter().copied()).collect();
    let rref: Vec<(GridIndex, Point2)> = ids.iter().copied().zip(r0.iter().copied()).collect();
    let frames: Vec<(Vec<Point2>, Vec<Point2>)> = (0..60)
        .map(|f| views(&scene(0.01 * f as f64, 0.02 * f as f64)))
        .collect();
    for method in [TriangulationMethod::PixelOptimal, TriangulationMethod::Lindstrom] {
        let tri = Triangulator::new(
            rig.clone(),
            TriangulationConfig {
                method,
                ..Default::default()
            },
        )?;
        let mut session = StereoSession::new(shape, &lref, &rref, tri.clone(), SessionConfig::default())?;
        let mut whole = Vec::new();
        for (k, (l, r)) in frames.iter().enumerate() {
            let t0 = Instant::now();
            session.track(k as u32, l, r)?;
            whole.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        let (mut t_track, mut t_tri, mut t_contact, mut t_slip) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut tl = Tracker::new(shape, &lref, TrackerConfig::default())?;
        let mut tr = Tracker::new(shape, &rref, TrackerConfig::default())?;
        let reference: Vec<Option<[f64; 3]>> =
            scene(0.0, 0.0).iter().map(|p| Some([p.x, p.y, p.z])).collect();
        let mut surface = ReferenceSurface::new(shape, &reference, ContactConfig::default())?;
        let mut slip = SlipDetector::new(SlipConfig::default())?;
        for (l, r) in &frames {
            let t0 = Instant::now();
            let a = tl.update(l);
            let b = tr.update(r);
            let t1 = Instant::now();
            let pos: Vec<Option<[f64; 3]>> = a
                .markers
                .iter()
                .zip(&b.markers)
                .map(|(x, y)| match (x.position_px, y.position_px) {
                    (Some(p), Some(q)) => tri
                        .triangulate(p, q)
                        .ok()
                        .map(|t| [t.p_in_left_mm.x, t.p_in_left_mm.y, t.p_in_left_mm.z]),
                    _ => None,
                })
                .collect();
            let t2 = Instant::now();
            let c = surface.analyze(&pos)?;
            let t3 = Instant::now();
            slip.update(&surface, &c);
            let t4 = Instant::now();
            t_track.push((t1 - t0).as_secs_f64() * 1e3);
            t_tri.push((t2 - t1).as_secs_f64() * 1e3);
            t_contact.push((t3 - t2).as_secs_f64() * 1e3);
            t_slip.push((t4 - t3).as_secs_f64() * 1e3);
        }
        println!(
            "{method:?}: whole track() {:.3} ms; 2 x tracker {:.3} ms, triangulation {:.3} ms, contact {:.3} ms, slip {:.3} ms (medians over {} frames)",
            median(whole),
            median(t_track),
            median(t_tri),
            median(t_contact),
            median(t_slip),
            frames.len()
        );
    }
    Ok(())
}
