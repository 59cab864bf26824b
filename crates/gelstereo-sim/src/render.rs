//! Stereo rendering of the deformed gel: LED-lit background shaded from surface normals, markers as
//! anti-aliased projected ellipses, then defocus, vignetting, noise, JPEG and dust.
//!
//! Speed: the smooth background is shaded at half resolution through a per-camera lookup (the ray
//! of every pixel hits the rest surface at a known point), then upsampled; only the markers are
//! drawn at full resolution, each from its projected centre and the Jacobian of its projection.

use gelstereo_core::{GridIndex, Point2};
use gelstereo_geometry::Camera;
use nalgebra::{Isometry3, Matrix2, Point3, Vector2};
use opencv::core::{CV_8UC3, Mat, MatTraitConst, MatTraitConstManual, MatTraitManual, Scalar, Size, Vector};
use opencv::{imgcodecs, imgproc};

use crate::appearance::{Appearance, Housing, Texture};
use crate::error::{Result, cv_err};
use crate::physics::Deformation;
use gelstereo_sensor::{Membrane, Sensor, splitmix64};

/// Per-camera lookup: where each half-resolution pixel's ray meets the rest surface.
#[derive(Debug, Clone)]
pub struct ViewOptics {
    /// The camera.
    pub camera: Camera,
    /// This camera's frame from the sensor frame.
    pub cam_from_sensor: Isometry3<f64>,
    lo_w: usize,
    lo_h: usize,
    /// Rest-surface hit (sensor frame x, y, mm) and ray slope (dx/dz, dy/dz) per low-res pixel.
    rays: Vec<[f32; 4]>,
    /// Vignetting radius² (0 centre, 1 corner) per low-res pixel.
    radius2: Vec<f32>,
    /// Largest ray slope |dx/dz|, |dy/dz| over the pixels.
    max_slope: f32,
}

impl ViewOptics {
    /// Builds the lookup of `camera` placed at `cam_from_sensor`.
    pub fn new(camera: &Camera, cam_from_sensor: Isometry3<f64>) -> Self {
        let (w, h) = (
            camera.image_size.width as usize,
            camera.image_size.height as usize,
        );
        let (lo_w, lo_h) = (w.div_ceil(2), h.div_ceil(2));
        let sensor_from_cam = cam_from_sensor.inverse();
        let origin = sensor_from_cam.translation.vector;
        let mut rays = Vec::with_capacity(lo_w * lo_h);
        let mut radius2 = Vec::with_capacity(lo_w * lo_h);
        let (hw, hh) = (0.5 * w as f64, 0.5 * h as f64);
        for j in 0..lo_h {
            for i in 0..lo_w {
                // Low-res pixel i covers full-res pixels 2i and 2i+1: centre at 2i + 0.5.
                let p = Point2::new(2.0 * i as f64 + 0.5, 2.0 * j as f64 + 0.5);
                let ray = camera.ray(p).map(|r| sensor_from_cam.rotation * r.into_inner());
                let entry = match ray {
                    Some(d) if d.z > 1e-3 => {
                        let t = -origin.z / d.z;
                        [
                            (origin.x + t * d.x) as f32,
                            (origin.y + t * d.y) as f32,
                            (d.x / d.z) as f32,
                            (d.y / d.z) as f32,
                        ]
                    }
                    _ => [1e6, 1e6, 0.0, 0.0],
                };
                rays.push(entry);
                let (dx, dy) = ((p.x - hw) / hw, (p.y - hh) / hh);
                radius2.push((0.5 * (dx * dx + dy * dy)) as f32);
            }
        }
        let max_slope = rays
            .iter()
            .filter(|r| r[0] < 1e5)
            .map(|r| r[2].abs().max(r[3].abs()))
            .fold(0.0, f32::max);
        Self {
            camera: camera.clone(),
            cam_from_sensor,
            lo_w,
            lo_h,
            rays,
            radius2,
            max_slope,
        }
    }

    /// Projects a sensor-frame point into this view.
    pub fn project(&self, p_in_sensor: &Point3<f64>) -> Option<Point2> {
        self.camera.project(&(self.cam_from_sensor * p_in_sensor))
    }
}

/// Both views of a sensor.
#[derive(Debug, Clone)]
pub struct StereoOptics {
    /// Left view.
    pub left: ViewOptics,
    /// Right view.
    pub right: ViewOptics,
}

impl StereoOptics {
    /// Lookups of both cameras of `sensor`.
    pub fn new(sensor: &Sensor) -> Self {
        Self {
            left: ViewOptics::new(&sensor.rig.left, sensor.left_from_sensor),
            right: ViewOptics::new(&sensor.rig.right, sensor.right_from_sensor),
        }
    }
}

/// Ground truth of one marker in one frame.
#[derive(Debug, Clone, Copy)]
pub struct MarkerTruth {
    /// Grid identity.
    pub index: GridIndex,
    /// Rest position, sensor frame, mm.
    pub rest_mm: [f64; 2],
    /// Deformed centre, sensor frame, mm.
    pub position_sensor: Point3<f64>,
    /// Projected centre in each view (`None` behind a camera).
    pub px: [Option<Point2>; 2],
    /// Jacobian of the projection (px per mm of rest-surface offset) in each view.
    pub jacobian: [Option<Matrix2<f64>>; 2],
    /// Whether the marker is printed (inside the membrane); an unprinted one is never drawn and
    /// never visible.
    pub printed: bool,
    /// Whether the marker touches the object.
    pub in_contact: bool,
    /// Contact load under the marker, mm (0 outside contact; [`Deformation::load`]): drives the
    /// fading.
    pub load_mm: f64,
    /// Contact pressure at the marker's rest position, kPa (bilinear over the physics grid).
    pub pressure_kpa: f64,
    /// Whether the marker touches the object and its cell slips (traction at the friction limit).
    pub slipping: bool,
}

/// Ground truth of every marker of the sensor for deformation `def`.
pub fn marker_truth(sensor: &Sensor, optics: &StereoOptics, def: &Deformation) -> Vec<MarkerTruth> {
    let eps = 0.05;
    let views = [&optics.left, &optics.right];
    sensor
        .spec
        .grid_shape()
        .indices()
        .map(|index| {
            let [x, y] = sensor.spec.marker_rest_mm(index.row, index.col);
            let c = def.deformed(x, y);
            let offs = [
                def.deformed(x + eps, y),
                def.deformed(x - eps, y),
                def.deformed(x, y + eps),
                def.deformed(x, y - eps),
            ];
            let mut px = [None; 2];
            let mut jacobian = [None; 2];
            for (v, view) in views.iter().enumerate() {
                px[v] = view.project(&c);
                let p: Vec<Option<Point2>> = offs.iter().map(|o| view.project(o)).collect();
                if let (Some(a), Some(b), Some(cc), Some(d)) = (p[0], p[1], p[2], p[3]) {
                    let s = 0.5 / eps;
                    jacobian[v] = Some(Matrix2::new(
                        (a.x - b.x) * s,
                        (cc.x - d.x) * s,
                        (a.y - b.y) * s,
                        (cc.y - d.y) * s,
                    ));
                }
            }
            MarkerTruth {
                index,
                rest_mm: [x, y],
                position_sensor: c,
                px,
                jacobian,
                printed: sensor.spec.marker_printed(index.row, index.col),
                in_contact: def.in_contact(x, y),
                load_mm: def.grid.sample(&def.load, x, y).max(0.0),
                pressure_kpa: def.pressure_kpa(x, y),
                slipping: def.slipping(x, y),
            }
        })
        .collect()
}

/// Per-frame shading on the physics grid: colour offset from the surface slope (LEDs) and the
/// weight of the contact tint.
struct Shading {
    tex: Vec<[f32; 5]>,
    fields: Vec<[f32; 3]>,
    /// Rest-position box (x0, y0, x1, y1, mm) outside which the gel is undisturbed (< 2 um).
    active: [f32; 4],
    /// Largest indentation in the frame, mm.
    max_w: f32,
    /// Largest tangential displacement, mm.
    max_u: f32,
}

fn shading(def: &Deformation, app: &Appearance) -> Shading {
    let g = &def.grid;
    let n = g.n;
    let inv2s = (0.5 / g.spacing_mm) as f32;
    let mut tex = vec![[0.0f32; 5]; n * n];
    let mut fields = vec![[0.0f32; 3]; n * n];
    let mut active = [f32::INFINITY, f32::INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY];
    let (mut max_w, mut max_u) = (0.0f32, 0.0f32);
    for j in 0..n {
        for i in 0..n {
            let k = j * n + i;
            fields[k] = [def.w[k], def.ux[k], def.uy[k]];
            let u = def.ux[k].abs().max(def.uy[k].abs());
            if def.w[k].abs() > 2e-3 || u > 2e-3 {
                let [x, y] = g.node(i, j);
                active = [
                    active[0].min(x as f32),
                    active[1].min(y as f32),
                    active[2].max(x as f32),
                    active[3].max(y as f32),
                ];
                max_w = max_w.max(def.w[k].abs());
                max_u = max_u.max(u);
            }
            let gx = if i > 0 && i + 1 < n {
                (def.w[k + 1] - def.w[k - 1]) * inv2s
            } else {
                0.0
            };
            let gy = if j > 0 && j + 1 < n {
                (def.w[k + n] - def.w[k - n]) * inv2s
            } else {
                0.0
            };
            let norm = (1.0 + gx * gx + gy * gy).sqrt();
            let mut t = [0.0f32; 5];
            // Steep walls look darker (light leaves them sideways).
            let dim = 1.0 - 1.0 / norm;
            for (v, l) in t.iter_mut().zip(&app.light_dirs) {
                *v = -app.light_gain * (gx * l[0] + gy * l[1]) / norm - 60.0 * dim;
            }
            let load = def.load[k];
            let strength = if load > 0.0 { (load / 0.05).min(1.0) } else { 0.0 };
            t[3] = app.contact_tint_strength * strength;
            t[4] = strength;
            tex[k] = t;
        }
    }
    Shading {
        tex,
        fields,
        active,
        max_w,
        max_u,
    }
}

#[inline]
fn sample_n<const N: usize>(g: &crate::physics::SurfaceGrid, f: &[[f32; N]], x: f32, y: f32) -> [f32; N] {
    let n = g.n;
    let s = g.spacing_mm as f32;
    let h = g.half_mm as f32;
    let fx = ((x + h) / s).clamp(0.0, (n - 1) as f32 - 1e-3);
    let fy = ((y + h) / s).clamp(0.0, (n - 1) as f32 - 1e-3);
    let (i, j) = (fx as usize, fy as usize);
    let (ax, ay) = (fx - i as f32, fy - j as f32);
    let k = j * n + i;
    let (a, b, c, d) = (&f[k], &f[k + 1], &f[k + n], &f[k + n + 1]);
    let mut out = [0.0; N];
    for m in 0..N {
        let top = a[m] + (b[m] - a[m]) * ax;
        let bot = c[m] + (d[m] - c[m]) * ax;
        out[m] = top + (bot - top) * ay;
    }
    out
}

/// Draws a filled, anti-aliased ellipse into an RGB buffer: `jac` maps the unit disk to pixels
/// around `centre`. `soft` is the width of the edge ramp in px.
#[allow(clippy::too_many_arguments)]
fn splat(
    buf: &mut [u8],
    w: usize,
    h: usize,
    centre: Point2,
    jac: &Matrix2<f64>,
    rgb: [f32; 3],
    alpha: f32,
    soft: f32,
) {
    let Some(inv) = jac.try_inverse() else { return };
    let ex = jac[(0, 0)].hypot(jac[(0, 1)]) + f64::from(soft) + 1.0;
    let ey = jac[(1, 0)].hypot(jac[(1, 1)]) + f64::from(soft) + 1.0;
    let x0 = (centre.x - ex).floor().max(0.0) as usize;
    let y0 = (centre.y - ey).floor().max(0.0) as usize;
    let x1 = ((centre.x + ex).ceil().min(w as f64 - 1.0)).max(-1.0);
    let y1 = ((centre.y + ey).ceil().min(h as f64 - 1.0)).max(-1.0);
    if x1 < 0.0 || y1 < 0.0 || x0 as f64 > x1 || y0 as f64 > y1 {
        return;
    }
    let (x1, y1) = (x1 as usize, y1 as usize);
    let inv = inv.cast::<f32>();
    let inv_t = inv.transpose();
    for y in y0..=y1 {
        let dy = (y as f64 - centre.y) as f32;
        for x in x0..=x1 {
            let dx = (x as f64 - centre.x) as f32;
            let q = inv * Vector2::new(dx, dy);
            let rho = q.norm();
            let cov = if rho < 1e-6 {
                1.0
            } else {
                let grad = (inv_t * (q / rho)).norm();
                let sd = (rho - 1.0) / grad;
                (0.5 - sd / soft).clamp(0.0, 1.0)
            };
            if cov <= 0.0 {
                continue;
            }
            let a = alpha * cov;
            let o = (y * w + x) * 3;
            for c in 0..3 {
                let v = f32::from(buf[o + c]);
                buf[o + c] = (v + (rgb[c] - v) * a + 0.5) as u8;
            }
        }
    }
}

/// What to draw for one view of one frame.
pub struct ViewJob<'a> {
    /// The camera lookup.
    pub optics: &'a ViewOptics,
    /// 0 left, 1 right.
    pub view: usize,
    /// The frame's deformation.
    pub def: &'a Deformation,
    /// Marker ground truth (with projections of this view).
    pub markers: &'a [MarkerTruth],
    /// The recording's look.
    pub appearance: &'a Appearance,
    /// Dot radius on the gel, mm.
    pub dot_radius_mm: f64,
    /// Half-width of the marker lattice, mm (scales the LED gradient).
    pub lattice_half_mm: f64,
    /// Seed of this frame and view (noise).
    pub seed: u64,
    /// Marker ground truth at the start of the exposure (motion blur), if any; the exposure is
    /// centred on the frame's time.
    pub exposure_start: Option<&'a [MarkerTruth]>,
    /// Skin ridges to draw in the contact (fingertips).
    pub ridges: Option<Ridges>,
    /// The membrane's outline when the gel does not fill the view (housing outside it).
    pub membrane: Option<Membrane>,
}

/// Fingerprint-like ridges: concentric, slightly wavy ellipses around the indenter's centre,
/// drawn where the skin touches the gel.
#[derive(Debug, Clone, Copy)]
pub struct Ridges {
    /// Centre in material coordinates, mm.
    pub centre: [f32; 2],
    /// Orientation of the ellipses' x axis, radians.
    pub angle: f32,
    /// Aspect ratio of the ellipses (y over x).
    pub aspect: f32,
    /// Ridge period, mm.
    pub period_mm: f32,
}

impl Ridges {
    /// Ridge profile in [-1, 1] at material point (`x`, `y`).
    #[inline]
    fn value(&self, x: f32, y: f32) -> f32 {
        let (s, c) = self.angle.sin_cos();
        let (dx, dy) = (x - self.centre[0], y - self.centre[1]);
        let (lx, ly) = (c * dx + s * dy, -s * dx + c * dy);
        let r =
            (lx * lx + (ly / self.aspect).powi(2)).sqrt() + 0.12 * (1.7 * lx).sin() + 0.08 * (2.3 * ly).cos();
        (std::f32::consts::TAU * r / self.period_mm).sin()
    }
}

/// Renders one view: returns an RGB (not BGR) 8-bit image of the camera's size.
pub fn render_view(job: &ViewJob<'_>) -> Result<Mat> {
    let o = job.optics;
    let app = job.appearance;
    let (w, h) = (
        o.camera.image_size.width as usize,
        o.camera.image_size.height as usize,
    );
    let lo = render_background(job, &shading(job.def, app), w, h)?;
    let mut img = Mat::default();
    imgproc::resize(
        &lo,
        &mut img,
        Size::new(w as i32, h as i32),
        0.0,
        0.0,
        imgproc::INTER_LINEAR,
    )
    .map_err(cv_err("upsampling the background"))?;
    {
        let buf = img.data_bytes_mut().map_err(cv_err("image buffer"))?;
        draw_markers(job, buf, w, h);
        draw_dust(job, buf, w, h);
    }
    if app
        .textures
        .iter()
        .any(|t| !matches!(t, Texture::Fingerprint { .. }))
    {
        let buf = img.data_bytes_mut().map_err(cv_err("image buffer"))?;
        apply_stripes(buf, w, &app.textures);
    }
    apply_optics_and_sensor(job, img)
}

/// The gel and housing background at half resolution (the markers are drawn on the upsampled
/// image); `w` x `h` is the full image size.
fn render_background(job: &ViewJob<'_>, sh: &Shading, w: usize, h: usize) -> Result<Mat> {
    let o = job.optics;
    let app = job.appearance;
    let def = job.def;
    let mut lo = Mat::new_rows_cols_with_default(o.lo_h as i32, o.lo_w as i32, CV_8UC3, Scalar::all(0.0))
        .map_err(cv_err("allocating the background"))?;
    let buf = lo.data_bytes_mut().map_err(cv_err("background buffer"))?;
    let inv_half = (1.0 / job.lattice_half_mm) as f32;
    // Pixels whose ray meets the rest surface outside the disturbed box (grown by how far the
    // surface moved and the parallax of the indentation) see undisturbed gel.
    let m = sh.max_w * o.max_slope + sh.max_u + def.grid.spacing_mm as f32;
    let a = [
        sh.active[0] - m,
        sh.active[1] - m,
        sh.active[2] + m,
        sh.active[3] + m,
    ];
    let contact = def.contact_area_mm2 > 0.0 && a[0] <= a[2];
    let plain_housing = Housing {
        color: [30.0; 3],
        rim_color: [60.0; 3],
        rim_mm: 0.5,
        clutter: Vec::new(),
        glints: Vec::new(),
    };
    let housing = app.housing.as_ref().unwrap_or(&plain_housing);
    let lo_w = o.lo_w;
    for (k, px) in buf.chunks_exact_mut(3).enumerate() {
        let r = o.rays[k];
        if let Some(mem) = &job.membrane {
            let d = mem.signed_distance_mm(f64::from(r[0]), f64::from(r[1])) as f32;
            if d > 0.0 {
                px.copy_from_slice(&housing_pixel(
                    housing,
                    d,
                    r[0],
                    r[1],
                    1.0 - app.vignette * o.radius2[k],
                ));
                continue;
            }
        }
        let (mut hx, mut hy) = (r[0], r[1]);
        let mut t = [0.0f32; 5];
        let mut ridge = 0.0;
        if contact && hx >= a[0] && hx <= a[2] && hy >= a[1] && hy <= a[3] {
            (hx, hy, t, ridge) = sample_contact(job, sh, r);
        }
        if !app.textures.is_empty() {
            let (x, y) = (2.0 * (k % lo_w) as f32 + 0.5, 2.0 * (k / lo_w) as f32 + 0.5);
            ridge += gel_texture(&app.textures, x, y, w as f32, h as f32);
        }
        let gx = (hx * inv_half).clamp(-1.5, 1.5) * 0.5;
        let gy = (hy * inv_half).clamp(-1.5, 1.5) * 0.5;
        let gr = gx * gx + gy * gy;
        let vig = 1.0 - app.vignette * o.radius2[k];
        for c in 0..3 {
            let base = app.background[c]
                + app.gradient_x[c] * gx
                + app.gradient_y[c] * gy
                + app.gradient_radial[c] * gr
                + t[c]
                + ridge;
            let v = base + (app.contact_tint[c] - base) * t[3];
            // Float to u8 casts saturate.
            px[c] = (v * vig + 0.5) as u8;
        }
    }
    Ok(lo)
}

/// What a ray `r` (rest-plane point and slope) sees inside the disturbed box: where it meets
/// the deformed gel (`hx`, `hy`, refined once for the surface's own displacement), the shading
/// there, and the skin ridges; Newton rings add to the shading where the gel nearly touches.
fn sample_contact(job: &ViewJob<'_>, sh: &Shading, r: [f32; 4]) -> (f32, f32, [f32; 5], f32) {
    let app = job.appearance;
    let def = job.def;
    let mut ridge = 0.0;
    let f = sample_n(&def.grid, &sh.fields, r[0], r[1]);
    let f = sample_n(&def.grid, &sh.fields, r[0] - f[0] * r[2], r[1] - f[0] * r[3]);
    let hx = r[0] - f[0] * r[2];
    let hy = r[1] - f[0] * r[3];
    let (mx, my) = (hx - f[1], hy - f[2]);
    let mut t = sample_n(&def.grid, &sh.tex, mx, my);
    if let Some(rd) = &job.ridges
        && t[4] > 0.0
    {
        ridge = rd.value(mx, my) * t[4] * app.ridge_gain;
    }
    if let Some(nr) = &app.newton_rings {
        let depth = f[0].abs();
        let envelope = (depth / 0.01).min(1.0) * (1.0 - 0.6 * t[4]);
        let wave = (std::f32::consts::TAU * depth / nr.period_mm).cos() * envelope;
        for (c, amp) in nr.amplitude.iter().enumerate() {
            t[c] += amp * wave;
        }
    }
    (hx, hy, t, ridge)
}

/// Splats the printed markers visible in this view onto the full-resolution image, each with
/// its vignetting, contact fade, motion blur and glint.
fn draw_markers(job: &ViewJob<'_>, buf: &mut [u8], w: usize, h: usize) {
    let app = job.appearance;
    let r = job.dot_radius_mm;
    let (cxp, cyp) = (0.5 * w as f64, 0.5 * h as f64);
    for (k, m) in job.markers.iter().enumerate() {
        let (Some(c), Some(j), true) = (m.px[job.view], m.jacobian[job.view], m.printed) else {
            continue;
        };
        let fade = 1.0 - app.contact_fade * (m.load_mm / 0.05).min(1.0) as f32;
        let (dx, dy) = ((c.x - cxp) / cxp, (c.y - cyp) / cyp);
        let vig = 1.0 - app.vignette * (0.5 * (dx * dx + dy * dy)) as f32;
        let col = app.marker_color.map(|v| v * vig);
        let alpha = app.marker_alpha * fade;
        // Motion blur: the marker smears from where it was when the exposure began to as far
        // past its position at the frame's time (the middle of the exposure; the motion taken
        // as steady over it), so the smear's middle is its truth.
        let start = job
            .exposure_start
            .and_then(|p| p.get(k))
            .and_then(|p| p.px[job.view]);
        match start {
            Some(s) if 2.0 * s.distance(c) > 0.3 => {
                let end = Point2::new(2.0 * c.x - s.x, 2.0 * c.y - s.y);
                let steps = ((2.0 * s.distance(c)).ceil() as usize).clamp(2, 8);
                let a = 1.0 - (1.0 - alpha).powf(1.0 / steps as f32);
                for i in 0..steps {
                    let f = (i as f64 + 0.5) / steps as f64;
                    let p = Point2::new(s.x + (end.x - s.x) * f, s.y + (end.y - s.y) * f);
                    splat(buf, w, h, p, &(j * r), col, a, app.edge_softness_px);
                }
            }
            _ => splat(buf, w, h, c, &(j * r), col, alpha, app.edge_softness_px),
        }
        if let Some(g) = &app.glint {
            let pick = (splitmix64(k as u64 ^ u64::from(g.size.to_bits())) >> 40) as f32 / 16_777_216.0;
            if pick < g.share {
                let off = j * r * Vector2::new(f64::from(g.offset[0]), f64::from(g.offset[1]));
                let spot = Point2::new(c.x + off.x, c.y + off.y);
                let jac = j * (r * f64::from(g.size));
                splat(buf, w, h, spot, &jac, [250.0; 3], g.alpha * fade, 0.8);
            }
        }
    }
}

/// Splats the dust specks over the markers.
fn draw_dust(job: &ViewJob<'_>, buf: &mut [u8], w: usize, h: usize) {
    let scale = w as f64 / 640.0;
    for (k, d) in job.appearance.dust.iter().enumerate() {
        // Each view sees its own specks (they sit on the lens or at different parallax).
        let shift = if job.view == 0 {
            0.0
        } else {
            0.37 + 0.11 * k as f64
        };
        let at = Point2::new(((d.at[0] + shift) % 1.0) * w as f64, d.at[1] * h as f64);
        let (s, c) = d.angle.sin_cos();
        let (a, b) = (d.radius_px * d.elongation * scale, d.radius_px * scale);
        let jac = Matrix2::new(c * a, -s * b, s * a, c * b);
        splat(buf, w, h, at, &jac, d.color, d.alpha, 1.0);
    }
}

/// What the camera adds after the scene: defocus blur, sensor noise and JPEG compression.
fn apply_optics_and_sensor(job: &ViewJob<'_>, img: Mat) -> Result<Mat> {
    let app = job.appearance;
    let mut out = Mat::default();
    if app.blur_px > 0.05 {
        imgproc::gaussian_blur_def(&img, &mut out, Size::new(0, 0), app.blur_px)
            .map_err(cv_err("defocus blur"))?;
    } else {
        out = img;
    }
    if app.noise > 0.0 {
        let buf = out.data_bytes_mut().map_err(cv_err("image buffer"))?;
        // Uniform noise of standard deviation `noise` (sqrt(12) * sigma wide), in 8-bit fixed
        // point: byte b of a hash gives (2b - 255) / 512 * sqrt(12) * sigma, 8 samples per hash.
        let k = (12f32.sqrt() * app.noise / 512.0 * 256.0).round() as i32;
        let seed = job.seed;
        for (i, chunk) in buf.chunks_mut(8).enumerate() {
            let r = splitmix64(seed ^ (i as u64).wrapping_mul(0x2545_F491_4F6C_DD1D)).to_le_bytes();
            for (v, b) in chunk.iter_mut().zip(r) {
                let d = ((2 * i32::from(b) - 255) * k + 128) >> 8;
                *v = (i32::from(*v) + d).clamp(0, 255) as u8;
            }
        }
    }
    if let Some(q) = app.jpeg_quality {
        let mut enc = Vector::<u8>::new();
        let params = Vector::<i32>::from_slice(&[imgcodecs::IMWRITE_JPEG_QUALITY, q]);
        imgcodecs::imencode(".jpg", &out, &mut enc, &params).map_err(cv_err("JPEG encoding"))?;
        out = imgcodecs::imdecode(&enc, imgcodecs::IMREAD_COLOR).map_err(cv_err("JPEG decoding"))?;
    }
    Ok(out)
}

/// One housing pixel at signed distance `d_mm` outside the membrane, rest-plane point (`x`, `y`).
fn housing_pixel(hs: &Housing, d_mm: f32, x: f32, y: f32, vignette: f32) -> [u8; 3] {
    let rim = ((hs.rim_mm - d_mm) / (0.2 * hs.rim_mm + 1e-3)).clamp(0.0, 1.0);
    let mut c = [0; 3].map(|i| hs.color[i] + (hs.rim_color[i] - hs.color[i]) * rim);
    for q in &hs.clutter {
        let dist = (x - q[0]).hypot(y - q[1]);
        let cov = ((q[2] - dist) / (0.15 * q[2]) + 0.5).clamp(0.0, 1.0);
        for v in &mut c {
            *v += (q[3] - *v) * cov;
        }
    }
    for g in &hs.glints {
        let d2 = ((x - g[0]).powi(2) + (y - g[1]).powi(2)) / (g[2] * g[2]);
        let add = g[3] * (-d2).exp();
        for v in &mut c {
            *v += add;
        }
    }
    // Float to u8 casts saturate.
    c.map(|v| (v * vignette + 0.5) as u8)
}

/// Additive textures of the gel (fingerprints) at full-resolution pixel (`x`, `y`), grey levels.
fn gel_texture(textures: &[Texture], x: f32, y: f32, w: f32, h: f32) -> f32 {
    let mut v = 0.0;
    for t in textures {
        if let Texture::Fingerprint {
            at,
            period_px,
            radius_px,
            amplitude,
        } = *t
        {
            let (dx, dy) = (x - at[0] * w, y - at[1] * h);
            let r = dx.hypot(dy);
            if r < radius_px {
                let wobble = 0.8 * period_px * ((dx * 0.05).sin() + (dy * 0.07).cos());
                let fade = 1.0 - (r / radius_px).powi(2);
                v += amplitude * fade * (std::f32::consts::TAU * (r + wobble) / period_px).sin();
            }
        }
    }
    v
}

/// Multiplies an RGB buffer by the stripe textures (scan lines, banding, moire).
fn apply_stripes(buf: &mut [u8], w: usize, textures: &[Texture]) {
    use std::f32::consts::TAU;
    for (k, px) in buf.chunks_exact_mut(3).enumerate() {
        let (x, y) = ((k % w) as f32, (k / w) as f32);
        let mut gain = [1.0f32; 3];
        for t in textures {
            match *t {
                Texture::Bands {
                    period_px,
                    angle,
                    phase,
                    gain: g,
                    sharpness,
                } => {
                    let s = x * angle.cos() + y * angle.sin();
                    let p = ((TAU * s / period_px + phase).sin() * sharpness).clamp(-1.0, 1.0);
                    for c in 0..3 {
                        gain[c] *= 1.0 + g[c] * p;
                    }
                }
                Texture::Moire {
                    period_px,
                    angle,
                    detune,
                    twist,
                    gain: g,
                } => {
                    let s1 = x * angle.cos() + y * angle.sin();
                    let a2 = angle + twist;
                    let s2 = x * a2.cos() + y * a2.sin();
                    let p1 = s1 / period_px;
                    let p2 = s2 / (period_px * (1.0 + detune));
                    let p = (TAU * (p1 - p2)).cos() + 0.3 * (TAU * p1).cos();
                    for v in &mut gain {
                        *v *= 1.0 + g * p;
                    }
                }
                Texture::Fingerprint { .. } => {}
            }
        }
        for (v, g) in px.iter_mut().zip(gain) {
            *v = (f32::from(*v) * g + 0.5) as u8;
        }
    }
}

/// Encodes an RGB image (as [`render_view`] returns it) as PNG, fast compression (Up filter +
/// `fdeflate`): datasets write thousands of frames, so encoding speed matters more than the last
/// bytes of file size.
pub fn encode_png(img: &Mat) -> Result<Vec<u8>> {
    let (w, h) = (img.cols() as u32, img.rows() as u32);
    let data = img.data_bytes().map_err(cv_err("image buffer"))?;
    gelstereo_io::images::encode_png(data, (w, h), 3, png::Compression::Fastest, Some(png::Filter::Up))
        .map_err(|e| crate::error::Error::Png(e.to_string()))
}

/// Converts an RGB image to OpenCV's BGR order (for `imwrite` and friends).
pub fn rgb_to_bgr(img: &Mat) -> Result<Mat> {
    let mut out = Mat::default();
    imgproc::cvt_color_def(img, &mut out, imgproc::COLOR_RGB2BGR).map_err(cv_err("RGB to BGR"))?;
    Ok(out)
}
