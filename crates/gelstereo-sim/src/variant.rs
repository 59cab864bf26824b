//! Random sensor variants for domain randomisation: other marker grids (8 to 30 per side), image
//! sizes (320x240 to 1280x720), pitches, dot sizes, distances and lens distortions, so that a model
//! trained on them also works on other marker sensors (GelSight-type).

use rand::Rng;

use gelstereo_sensor::{CameraSpec, CamerasSpec, GelSpec, GridSpec, Lattice, Membrane, SensorSpec};

const RESOLUTIONS: [(u32, u32); 7] = [
    (320, 240),
    (400, 300),
    (480, 360),
    (640, 480),
    (800, 600),
    (960, 540),
    (1280, 720),
];

/// A random sensor: grid, image size, pitch in the image (10 to 45 px), dot-to-pitch ratio,
/// camera distance and baseline, distortion. Either every marker is visible in both views at rest,
/// or (half of the variants) the grid overfills the images and 45-95 % of the markers are.
pub fn random_variant(base: &SensorSpec, rng: &mut impl Rng) -> SensorSpec {
    for _ in 0..50 {
        if let Some(s) = try_variant(base, rng) {
            return s;
        }
    }
    base.clone()
}

fn try_variant(base: &SensorSpec, rng: &mut impl Rng) -> Option<SensorSpec> {
    let (w, h) = RESOLUTIONS[rng.random_range(0..RESOLUTIONS.len())];
    // Half of the variants fill part of the image; the others overfill it like a GelSight, with
    // markers cut by the image border (those outside are flagged not visible).
    let overfill = rng.random_bool(0.5);
    let fill = if overfill {
        rng.random_range(1.0..1.35)
    } else {
        rng.random_range(0.55..0.9)
    };
    // Pitch in the image: 10-45 px, and the grid must fit.
    let pitch_px: f64 = rng.random_range(10.0..45.0);
    let max_cols = ((f64::from(w) * fill / pitch_px) as u16 + 1).min(30);
    let max_rows = ((f64::from(h) * fill / pitch_px) as u16 + 1).min(30);
    if max_cols < 8 || max_rows < 8 {
        return None;
    }
    let cols = rng.random_range(8..=max_cols);
    let rows = rng.random_range(8..=max_rows);
    let pitch_mm = rng.random_range(0.6..1.8);
    let dist = rng.random_range(15.0..32.0);
    let baseline = dist * rng.random_range(0.25..0.5);
    let f = pitch_px * dist / pitch_mm;
    let dot = pitch_mm * rng.random_range(0.3..0.6);
    let span = 0.5 * f64::from(rows.max(cols) - 1) * pitch_mm;
    // The gel must cover everything a camera sees: ray half-angle times distance, plus baseline.
    let view_half = dist * (f64::from(w.max(h)) / (2.0 * f)) * 1.8 + baseline;
    let half_extent = view_half.max(span + 2.0 * pitch_mm);
    let rig = RigDraw {
        f,
        size_px: (w, h),
        baseline,
        dist,
        k1_min: -0.15,
    };
    let left = rig.camera(-1.0, rng);
    let right = rig.camera(1.0, rng);
    let spec = SensorSpec {
        name: format!("variant-{rows}x{cols}-{w}x{h}"),
        grid: GridSpec {
            rows,
            cols,
            pitch_mm,
            dot_diameter_mm: dot,
            lattice: Lattice::Square,
        },
        gel: GelSpec {
            thickness_mm: pitch_mm * rng.random_range(2.5..4.0),
            half_extent_mm: half_extent,
            grid_spacing_mm: 2.0 * half_extent / 90.0,
            friction: rng.random_range(0.4..1.0),
            modulus_kpa: base.gel.modulus_kpa,
            poisson: rng.random_range(0.40..0.49),
        },
        cameras: CamerasSpec {
            image_width: w,
            image_height: h,
            left,
            right,
        },
        membrane: None,
    };
    let sensor = spec.build().ok()?;
    let ok = if overfill {
        (0.45..0.95).contains(&sensor.visible_fraction_at_rest(0.0))
    } else {
        sensor.all_markers_visible_at_rest(0.6 * pitch_px)
    };
    ok.then_some(spec)
}

/// Image sizes of [`random_wide_variant`], from a GelSight Mini's 320x240 to full HD; the common
/// VGA-class sizes are listed twice (the large ones cost the most to render and to train on).
const WIDE_RESOLUTIONS: [(u32, u32); 14] = [
    (320, 240),
    (320, 240),
    (400, 300),
    (427, 320),
    (427, 320),
    (480, 360),
    (640, 360),
    (640, 480),
    (640, 480),
    (800, 600),
    (960, 540),
    (1280, 720),
    (1280, 720),
    (1920, 1080),
];

/// A random sensor of the widened domain: image 320x240 to 1920x1080, marker pitch in the image
/// 8 to 100 px (log-uniform), 4 to 60 markers per side, square (half), hexagonal or irregular
/// lattices, dots 0.25-0.75 of the pitch on a gel of Poisson ratio 0.35-0.49 (its bulge squeezes
/// dots at indenter rims), and one in five on a round and one in five on a
/// trapezoidal membrane with the housing around it in view. Without a membrane, half overfill the
/// images (markers cut by every border).
pub fn random_wide_variant(base: &SensorSpec, rng: &mut impl Rng) -> SensorSpec {
    for _ in 0..50 {
        if let Some(s) = try_wide_variant(base, rng) {
            return s;
        }
    }
    random_variant(base, rng)
}

fn try_wide_variant(base: &SensorSpec, rng: &mut impl Rng) -> Option<SensorSpec> {
    let (w, h) = WIDE_RESOLUTIONS[rng.random_range(0..WIDE_RESOLUTIONS.len())];
    let pitch_px = (rng.random_range(8f64.ln()..100f64.ln())).exp();
    let layout = WideLayout::draw((w, h), pitch_px, rng)?;
    let (rows, cols, row_step) = (layout.rows, layout.cols, layout.row_step);
    let pitch_mm = rng.random_range(0.6..2.5);
    let dist = rng.random_range(12.0..35.0);
    let baseline = dist * rng.random_range(0.2..0.5);
    let f = pitch_px * dist / pitch_mm;
    let dot = pitch_mm * rng.random_range(0.25..0.75);
    let span = 0.5 * f64::from(rows.max(cols)) * pitch_mm;
    let view_half = dist * (f64::from(w.max(h)) / (2.0 * f)) * 1.8 + baseline;
    let half_extent = view_half.max(span + 2.0 * pitch_mm);
    let half_x = 0.5 * f64::from(cols - 1) * pitch_mm;
    let half_y = 0.5 * f64::from(rows - 1) * pitch_mm * row_step;
    let membrane = draw_wide_membrane(layout.membrane_kind, half_x, half_y, dot, rng);
    let rig = RigDraw {
        f,
        size_px: (w, h),
        baseline,
        dist,
        k1_min: -0.2,
    };
    let left = rig.camera(-1.0, rng);
    let right = rig.camera(1.0, rng);
    let spec = SensorSpec {
        name: format!("wide-{rows}x{cols}-{w}x{h}"),
        grid: GridSpec {
            rows,
            cols,
            pitch_mm,
            dot_diameter_mm: dot,
            lattice: layout.lattice,
        },
        gel: GelSpec {
            thickness_mm: pitch_mm * rng.random_range(2.0..4.0),
            half_extent_mm: half_extent,
            grid_spacing_mm: 2.0 * half_extent / 90.0,
            friction: rng.random_range(0.4..1.0),
            modulus_kpa: base.gel.modulus_kpa,
            poisson: rng.random_range(0.35..0.49),
        },
        cameras: CamerasSpec {
            image_width: w,
            image_height: h,
            left,
            right,
        },
        membrane,
    };
    wide_view_acceptable(&spec, pitch_px, layout.overfill).then_some(spec)
}

/// The lattice of a wide variant in the image: its kind, the membrane kind (0-2 none, 3 circle,
/// 4 trapezoid), whether it overfills the view, and its size.
struct WideLayout {
    lattice: Lattice,
    membrane_kind: i32,
    overfill: bool,
    /// Row spacing in pitches (below one on a hexagonal lattice).
    row_step: f64,
    rows: u16,
    cols: u16,
}

impl WideLayout {
    /// Draws a layout for a `size_px` image at `pitch_px`; None where fewer than four rows or
    /// columns fit.
    fn draw(size_px: (u32, u32), pitch_px: f64, rng: &mut impl Rng) -> Option<Self> {
        let (w, h) = size_px;
        let lattice = match rng.random_range(0..4) {
            0 | 1 => Lattice::Square,
            2 => Lattice::Hexagonal,
            _ => Lattice::Irregular {
                jitter_frac: rng.random_range(0.05..0.25),
                seed: rng.random(),
            },
        };
        let membrane_kind = rng.random_range(0..5);
        let overfill = membrane_kind < 3 && rng.random_bool(0.5);
        let fill = if overfill {
            rng.random_range(1.0..1.4)
        } else if membrane_kind >= 3 {
            rng.random_range(0.8..1.0)
        } else {
            rng.random_range(0.5..0.95)
        };
        let row_step = if lattice == Lattice::Hexagonal {
            0.75f64.sqrt()
        } else {
            1.0
        };
        let max_cols = ((f64::from(w) * fill / pitch_px) as u16 + 1).min(60);
        let max_rows = ((f64::from(h) * fill / (pitch_px * row_step)) as u16 + 1).min(60);
        if max_cols < 4 || max_rows < 4 {
            return None;
        }
        // An overfilling lattice takes the largest size (it must reach past the borders); membranes
        // are shaped from the lattice's extent, so keep it near the largest that fits.
        let least = |max: u16| {
            if overfill {
                max
            } else if membrane_kind >= 3 {
                (max * 4 / 5).max(4)
            } else {
                (max / 2).max(4)
            }
        };
        let cols = rng.random_range(least(max_cols)..=max_cols);
        let rows = rng.random_range(least(max_rows)..=max_rows);
        Some(Self {
            lattice,
            membrane_kind,
            overfill,
            row_step,
            rows,
            cols,
        })
    }
}

/// The membrane of a wide variant, shaped from the lattice's half extents (`half_x`, `half_y`)
/// so that its edge runs near the outer markers; None for kinds without one.
fn draw_wide_membrane(kind: i32, half_x: f64, half_y: f64, dot: f64, rng: &mut impl Rng) -> Option<Membrane> {
    match kind {
        3 => Some(Membrane::Circle {
            radius_mm: half_x.min(half_y) * rng.random_range(0.8..1.0) + 0.5 * dot,
        }),
        4 => {
            let wide = half_x * rng.random_range(0.85..1.0) + 0.5 * dot;
            let narrow = wide * rng.random_range(0.55..0.9);
            let (top, bottom) = if rng.random_bool(0.5) {
                (narrow, wide)
            } else {
                (wide, narrow)
            };
            Some(Membrane::Trapezoid {
                top_half_width_mm: top,
                bottom_half_width_mm: bottom,
                half_height_mm: half_y * rng.random_range(0.85..1.0) + 0.5 * dot,
            })
        }
        _ => None,
    }
}

/// A drawn wide sensor is kept when it builds, prints enough markers and shows them as its kind
/// promises: an overfilling lattice partly, any other whole (with a margin inside the view).
fn wide_view_acceptable(spec: &SensorSpec, pitch_px: f64, overfill: bool) -> bool {
    let Ok(sensor) = spec.build() else {
        return false;
    };
    let printed = spec
        .grid_shape()
        .indices()
        .filter(|i| spec.marker_printed(i.row, i.col))
        .count();
    if printed < 12 {
        return false;
    }
    let seen = sensor.visible_fraction_at_rest(0.0) * spec.grid_shape().count() as f64 / printed as f64;
    let seen_inside =
        sensor.visible_fraction_at_rest(0.6 * pitch_px) * spec.grid_shape().count() as f64 / printed as f64;
    if overfill {
        (0.45..0.95).contains(&seen)
    } else {
        seen_inside >= 0.999
    }
}

/// A stereo sensor with the optics of a GelSight Mini (320x240, dots about 11 px on a 31 px pitch
/// that overfills the image, 8 x 10 markers fully visible): a mono GelSight Mini is its left view.
pub fn gelsight_mini_like() -> SensorSpec {
    let (w, h) = (320u32, 240u32);
    let dist = 14.0;
    let pitch_mm = 1.1;
    let f = 31.0 * dist / pitch_mm;
    let cam = |x: f64| CameraSpec {
        fx: f,
        fy: f,
        cx: 159.5,
        cy: 119.5,
        distortion: vec![-0.12, 0.03, 0.0, 0.0, 0.0],
        position_mm: [x, 0.0, -dist],
        look_at_mm: [0.0, 0.0, 0.0],
    };
    SensorSpec {
        name: "gelsight-mini-like".into(),
        grid: GridSpec {
            rows: 10,
            cols: 12,
            pitch_mm,
            dot_diameter_mm: 0.39,
            lattice: Lattice::Square,
        },
        gel: GelSpec {
            thickness_mm: 3.0,
            half_extent_mm: 16.0,
            grid_spacing_mm: 0.36,
            friction: 0.8,
            modulus_kpa: gelstereo_sensor::REFERENCE_MODULUS_KPA,
            poisson: gelstereo_sensor::REFERENCE_POISSON,
        },
        cameras: CamerasSpec {
            image_width: w,
            image_height: h,
            left: cam(-3.0),
            right: cam(3.0),
        },
        membrane: None,
    }
}

/// [`gelsight_mini_like`] with jitter: pitch in the image +-15 %, dot size +-25 %, grid shift and
/// size, distortion, camera offsets; always overfilling the 320 x 240 images.
pub fn random_gelsight_mini_like(rng: &mut impl Rng) -> SensorSpec {
    let mut s = gelsight_mini_like();
    let k = rng.random_range(0.85..1.15);
    s.grid.rows = rng.random_range(9..=11);
    s.grid.cols = rng.random_range(11..=13);
    s.grid.dot_diameter_mm = 0.39 * rng.random_range(0.75..1.25);
    for (c, x) in [(&mut s.cameras.left, -1.0), (&mut s.cameras.right, 1.0)] {
        c.fx *= k;
        c.fy = c.fx * rng.random_range(0.99..1.01);
        c.cx += rng.random_range(-6.0..6.0);
        c.cy += rng.random_range(-6.0..6.0);
        c.distortion[0] = rng.random_range(-0.2..0.0);
        c.position_mm[0] = x * rng.random_range(2.0..4.0);
        c.look_at_mm = [rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0];
    }
    s.name = "gelsight-mini-like-jittered".into();
    s
}

/// What the two cameras of a generated sensor share: focal length `f` px, image size, baseline and
/// distance behind the gel in mm, and the lowest radial distortion k1 drawn.
struct RigDraw {
    f: f64,
    size_px: (u32, u32),
    baseline: f64,
    dist: f64,
    k1_min: f64,
}

impl RigDraw {
    /// One camera (`sign` -1 left, +1 right) with small random offsets and distortion; the draws
    /// come in a fixed order, so a seed gives the same sensor.
    fn camera(&self, sign: f64, rng: &mut dyn rand::RngCore) -> CameraSpec {
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * (rng.next_u32() as f64 / f64::from(u32::MAX));
        let (w, h) = self.size_px;
        CameraSpec {
            fx: self.f * u(0.99, 1.01),
            fy: self.f * u(0.99, 1.01),
            cx: 0.5 * f64::from(w - 1) + u(-0.02, 0.02) * f64::from(w),
            cy: 0.5 * f64::from(h - 1) + u(-0.02, 0.02) * f64::from(h),
            distortion: vec![
                u(self.k1_min, 0.05),
                u(-0.02, 0.05),
                u(-1e-3, 1e-3),
                u(-1e-3, 1e-3),
                u(-0.01, 0.01),
            ],
            position_mm: [sign * 0.5 * self.baseline, u(-0.1, 0.1), -self.dist],
            look_at_mm: [u(-0.3, 0.3), u(-0.3, 0.3), 0.0],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn variants_are_valid_and_varied() {
        let base = SensorSpec::reference();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut sizes = std::collections::BTreeSet::new();
        for _ in 0..20 {
            let v = random_variant(&base, &mut rng);
            let s = v.build().unwrap();
            assert!(s.visible_fraction_at_rest(0.0) >= 0.45, "{}", v.name);
            assert!((8..=30).contains(&v.grid.rows) && (8..=30).contains(&v.grid.cols));
            sizes.insert((v.cameras.image_width, v.grid.rows));
        }
        assert!(sizes.len() > 10);
        for _ in 0..10 {
            let v = random_gelsight_mini_like(&mut rng);
            let s = v.build().unwrap();
            let seen = s.visible_fraction_at_rest(0.0);
            assert!((0.4..1.0).contains(&seen), "{seen}");
            assert!((24.0..38.0).contains(&s.pitch_px()), "{}", s.pitch_px());
        }
    }
}
