//! Synthetic marker sequences for the tests: a lattice under a smooth press-then-slide deformation,
//! with detector noise, missed and spurious markers. The ground truth is exact.

use gelstereo_core::{GridIndex, GridShape, Point2};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A 2-D lattice sequence.
pub(crate) struct Sequence2 {
    pub shape: GridShape,
    pub pitch_px: f64,
    /// Ground-truth positions per frame, row-major.
    pub truth: Vec<Vec<Point2>>,
    /// Detections per frame with the true id of each (None for spurious ones).
    pub detections: Vec<Vec<(Point2, Option<GridIndex>)>>,
}

/// Press (frames 0..press) growing a radial bulge, then a slide of `slide_px` in x over the rest.
pub(crate) fn press_then_slide(
    frames: usize,
    miss: f64,
    spurious: f64,
    noise_px: f64,
    slide_px: f64,
    seed: u64,
) -> Sequence2 {
    let press = frames / 3;
    let slide = |f: usize| {
        if f > press {
            slide_px * ((f - press) as f64 / (frames - press - 1).max(1) as f64)
        } else {
            0.0
        }
    };
    let detector = Detector {
        miss,
        spurious,
        noise_px,
        seed,
    };
    pressed_lattice(frames, press, slide, &detector)
}

/// Press over `press` frames, then slides of the contact given as whole steps in x, px, one per
/// frame after the press (sudden starts and stops), then `press` frames at rest.
pub(crate) fn press_then_steps(press: usize, steps_px: &[f64], detector: &Detector) -> Sequence2 {
    let frames = 2 * press + steps_px.len() + 1;
    let slide = |f: usize| steps_px.iter().take(f.saturating_sub(press + 1)).sum();
    pressed_lattice(frames, press, slide, detector)
}

/// How the detections are drawn from the truth: the share of markers missed per frame, spurious
/// detections per frame as a share of the markers, uniform noise of `noise_px` width, the seed.
pub(crate) struct Detector {
    pub miss: f64,
    pub spurious: f64,
    pub noise_px: f64,
    pub seed: u64,
}

/// The reference lattice (pitch 20 px) under a press growing over frames 0..press and the slide
/// `slide(frame)` in x (px; 0.2 of it in y) carried by the contact region (a Gaussian of 3 pitches).
fn pressed_lattice(
    frames: usize,
    press: usize,
    slide: impl Fn(usize) -> f64,
    detector: &Detector,
) -> Sequence2 {
    let Detector {
        miss,
        spurious,
        noise_px,
        seed,
    } = *detector;
    let shape = GridShape::REFERENCE;
    let pitch = 20.0;
    let (x0, y0) = (100.0, 40.0);
    let centre = (x0 + 11.0 * pitch, y0 + 11.0 * pitch);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut truth = Vec::new();
    let mut detections = Vec::new();
    for f in 0..frames {
        let a = (f as f64 / press as f64).min(1.0);
        let s = slide(f);
        let mut pts = Vec::new();
        let mut dets = Vec::new();
        for idx in shape.indices() {
            let (bx, by) = (x0 + f64::from(idx.col) * pitch, y0 + f64::from(idx.row) * pitch);
            let (dx, dy) = (bx - centre.0, by - centre.1);
            let r2 = dx * dx + dy * dy;
            let w = (-r2 / (2.0 * (3.0 * pitch).powi(2))).exp();
            // Radial bulge up to 4 px plus the slide carried by the contact region.
            let bulge = 4.0 * a * w / (3.0 * pitch);
            let p = Point2::new(bx + bulge * dx + s * w, by + bulge * dy + 0.2 * s * w);
            pts.push(p);
            if rng.random::<f64>() >= miss {
                let n = Point2::new(
                    p.x + noise_px * (rng.random::<f64>() - 0.5),
                    p.y + noise_px * (rng.random::<f64>() - 0.5),
                );
                dets.push((n, Some(idx)));
            }
        }
        let extra = (spurious * shape.count() as f64) as usize;
        for _ in 0..extra {
            dets.push((
                Point2::new(rng.random_range(80.0..560.0), rng.random_range(20.0..500.0)),
                None,
            ));
        }
        // Detectors report in raster order, not id order.
        dets.sort_by(|a, b| a.0.y.total_cmp(&b.0.y).then(a.0.x.total_cmp(&b.0.x)));
        truth.push(pts);
        detections.push(dets);
    }
    Sequence2 {
        shape,
        pitch_px: pitch,
        truth,
        detections,
    }
}
