//! Rough per-stage timings of the simulator on the reference sensor (development aid).
use std::time::Instant;

use gelstereo_sim::dataset::{DatasetConfig, plan};
use gelstereo_sim::physics::{Layer, SurfaceGrid, deform};
use gelstereo_sim::render::{StereoOptics, ViewJob, marker_truth, render_view};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut cfg = DatasetConfig::new(15, 40, 7);
    cfg.randomization = gelstereo_sim::Randomization::Appearance;
    let exps = plan(&cfg)?;
    let mut t = [0.0f64; 4];
    let mut n = 0;
    for e in exps {
        let sensor = e.sensor.build()?;
        let optics = StereoOptics::new(&sensor);
        let grid = SurfaceGrid::new(&sensor.spec.gel);
        let layer = Layer::new(&sensor.spec.gel, grid);
        for f in (0..40).step_by(4) {
            let pose = e.script.pose(f);
            let t0 = Instant::now();
            let def = deform(&sensor.spec.gel, &layer, &e.script, &pose);
            let t1 = Instant::now();
            let markers = marker_truth(&sensor, &optics, &def);
            let t2 = Instant::now();
            let img = render_view(&ViewJob {
                optics: &optics.left,
                view: 0,
                def: &def,
                markers: &markers,
                appearance: &e.appearance,
                dot_radius_mm: 0.2,
                lattice_half_mm: 8.8,
                seed: 1,
                previous: None,
                ridges: None,
            })?;
            let t3 = Instant::now();
            let _ = gelstereo_sim::render::encode_png(&img)?;
            let t4 = Instant::now();
            t[0] += (t1 - t0).as_secs_f64();
            t[1] += (t2 - t1).as_secs_f64();
            t[2] += (t3 - t2).as_secs_f64();
            t[3] += (t4 - t3).as_secs_f64();
            n += 1;
        }
    }
    let ms = t.map(|v| 1e3 * v / n as f64);
    println!(
        "{n} frames: deform {:.2} ms, truth {:.2} ms, render one view {:.2} ms, png one view {:.2} ms",
        ms[0], ms[1], ms[2], ms[3]
    );
    Ok(())
}
