//! Synthetic stereo marker scenes for the matching tests: a planar 23 x 23 marker lattice seen by a
//! calibrated, distorted stereo rig, deformed by a smooth indentation + shear field, with missing
//! markers, spurious detections (dust) and localisation noise. Every detection knows its true index.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use gelstereo_core::{Detection, GridIndex, GridShape, ImageSize, Point2};
use gelstereo_geometry::{Camera, Distortion, StereoRig};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub const SHAPE: GridShape = GridShape { rows: 23, cols: 23 };
pub const PITCH_MM: f64 = 0.6;
pub const DEPTH_MM: f64 = 25.0;
pub const BASELINE_MM: f64 = 6.0;

/// A camera of the synthetic rig: 640 x 480, f = 600 px, OpenCV 5-coefficient distortion.
pub fn camera(fx: f64) -> Camera {
    Camera {
        image_size: ImageSize {
            width: 640,
            height: 480,
        },
        fx,
        fy: fx * 1.002,
        cx: 319.5,
        cy: 239.5,
        distortion: Distortion::new(vec![-0.12, 0.06, 0.0008, -0.0005, -0.01]).unwrap(),
    }
}

/// The rig: right camera 6 mm to the right, turned by `yaw_deg` about y and `roll_deg` about z.
pub fn rig(yaw_deg: f64, roll_deg: f64) -> StereoRig {
    let rot = UnitQuaternion::from_euler_angles(0.0, yaw_deg.to_radians(), roll_deg.to_radians());
    // Right camera centre C (left frame); p_right = R (p_left - C) = R p_left - R C.
    let c = Vector3::new(BASELINE_MM, 0.0, 0.0);
    let t = -(rot * c);
    StereoRig {
        left: camera(600.0),
        right: camera(590.0),
        right_from_left: Isometry3::from_parts(Translation3::from(t), rot),
    }
}

/// Deformation of the gel: a Gaussian bump of `depth_mm` towards the cameras and a lateral shear of
/// `shear_mm` (along x and half of it along y), both centred at (`cx_mm`, `cy_mm`) on the lattice
/// with width `sigma_mm`.
#[derive(Debug, Clone, Copy)]
pub struct Deformation {
    pub cx_mm: f64,
    pub cy_mm: f64,
    pub sigma_mm: f64,
    pub depth_mm: f64,
    pub shear_mm: f64,
}

impl Deformation {
    pub const NONE: Deformation = Deformation {
        cx_mm: 0.0,
        cy_mm: 0.0,
        sigma_mm: 1.0,
        depth_mm: 0.0,
        shear_mm: 0.0,
    };

    pub fn scaled(&self, s: f64) -> Self {
        Self {
            depth_mm: self.depth_mm * s,
            shear_mm: self.shear_mm * s,
            ..*self
        }
    }
}

/// 3-D marker positions in the left camera frame, row-major.
pub fn markers_mm(def: &Deformation) -> Vec<Point3<f64>> {
    SHAPE
        .indices()
        .map(|idx| {
            let x = (f64::from(idx.col) - 11.0) * PITCH_MM + BASELINE_MM / 2.0;
            let y = (f64::from(idx.row) - 11.0) * PITCH_MM;
            let (u, v) = (x - BASELINE_MM / 2.0 - def.cx_mm, y - def.cy_mm);
            let g = (-(u * u + v * v) / (2.0 * def.sigma_mm * def.sigma_mm)).exp();
            Point3::new(
                x + def.shear_mm * g,
                y + 0.5 * def.shear_mm * g,
                DEPTH_MM - def.depth_mm * g,
            )
        })
        .collect()
}

/// Detections of one view with their true indices (`None` for dust).
#[derive(Debug, Clone)]
pub struct ViewDetections {
    pub detections: Vec<Detection>,
    pub truth: Vec<Option<GridIndex>>,
}

/// Options for the imperfections of the detections.
#[derive(Debug, Clone, Copy)]
pub struct Imperfections {
    pub missing: f64,
    pub dust: usize,
    pub noise_px: f64,
}

pub const CLEAN: Imperfections = Imperfections {
    missing: 0.0,
    dust: 0,
    noise_px: 0.0,
};

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-12);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Projects `points` (left frame) into the view with `cam` and pose `cam_from_left`, drops
/// `missing` of them, adds noise and `dust` spurious points (at least half a pitch from any marker),
/// and shuffles.
pub fn view(
    cam: &Camera,
    cam_from_left: &Isometry3<f64>,
    points: &[Point3<f64>],
    imp: Imperfections,
    seed: u64,
) -> ViewDetections {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut items: Vec<(Point2, Option<GridIndex>)> = Vec::new();
    let projected: Vec<Point2> = points
        .iter()
        .map(|p| cam.project(&(cam_from_left * p)).unwrap())
        .collect();
    for (idx, p) in SHAPE.indices().zip(&projected) {
        if rng.random::<f64>() < imp.missing || !cam.contains(*p) {
            continue;
        }
        let q = Point2::new(
            p.x + imp.noise_px * gauss(&mut rng),
            p.y + imp.noise_px * gauss(&mut rng),
        );
        items.push((q, Some(idx)));
    }
    let (x0, x1) = projected
        .iter()
        .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.x), a.1.max(p.x)));
    let (y0, y1) = projected
        .iter()
        .fold((f64::MAX, f64::MIN), |a, p| (a.0.min(p.y), a.1.max(p.y)));
    let pitch = (projected[1].x - projected[0].x).abs();
    let mut added = 0;
    while added < imp.dust {
        let q = Point2::new(
            rng.random_range(x0 - pitch..x1 + pitch),
            rng.random_range(y0 - pitch..y1 + pitch),
        );
        if projected.iter().all(|p| p.distance(q) > 0.5 * pitch) {
            items.push((q, None));
            added += 1;
        }
    }
    // Fisher-Yates shuffle so that input order carries no information.
    for i in (1..items.len()).rev() {
        let j = rng.random_range(0..=i);
        items.swap(i, j);
    }
    ViewDetections {
        detections: items
            .iter()
            .map(|(p, _)| Detection {
                position: *p,
                confidence: 1.0,
            })
            .collect(),
        truth: items.iter().map(|(_, t)| *t).collect(),
    }
}

/// Left and right detections of a stereo frame.
pub fn stereo_frame(
    rig: &StereoRig,
    def: &Deformation,
    imp: Imperfections,
    seed: u64,
) -> (ViewDetections, ViewDetections) {
    let pts = markers_mm(def);
    let left = view(&rig.left, &Isometry3::identity(), &pts, imp, seed);
    let right = view(
        &rig.right,
        &rig.right_from_left,
        &pts,
        imp,
        seed.wrapping_mul(7919).wrapping_add(1),
    );
    (left, right)
}

/// Outcome of an indexing against the truth.
#[derive(Debug, Default, Clone, Copy)]
pub struct Score {
    /// True markers given.
    pub markers: usize,
    /// True markers indexed correctly.
    pub correct: usize,
    /// True markers indexed with a wrong index.
    pub wrong: usize,
    /// Dust detections that received an index.
    pub dust_indexed: usize,
}

pub fn score(view: &gelstereo_matching::IndexedView, truth: &[Option<GridIndex>]) -> Score {
    let mut s = Score::default();
    for (d, t) in truth.iter().enumerate() {
        match (t, view.index_of(d)) {
            (Some(t), Some(i)) if *t == i => s.correct += 1,
            (Some(_), Some(_)) => s.wrong += 1,
            (None, Some(_)) => s.dust_indexed += 1,
            _ => {}
        }
        if t.is_some() {
            s.markers += 1;
        }
    }
    s
}
