//! Gel deformation under an indenter: an elastic-layer contact model on a regular grid of the gel
//! surface, solved per frame (no history: loading is monotonic within each phase of a script).
//!
//! # Model
//! - **Layer response.** A surface load `q` moves the surface by `K ⊗ q`, with `K` a normalised sum
//!   of two Gaussians (widths 0.35 and 1.0 times the layer thickness): the short-range response of a
//!   thin layer bonded to a rigid plate, with heavier tails than one Gaussian.
//! - **Normal contact.** With `pen = depth - h(x)` the rigid overlap of the indenter, the load `q >= 0`
//!   is found by projected Van Cittert iterations so that `w = K ⊗ q` equals `pen` where `q > 0`
//!   (Polonsky–Keer style: the contact is where the load stays positive, smaller than the rigid
//!   overlap, as for a real elastic contact). `w` is the surface's displacement towards the cameras.
//! - **Lateral spreading.** The incompressible layer squeezed under the indenter bulges outwards:
//!   `u_spread = -spreading * thickness * ∇w`.
//! - **Friction (Cattaneo–Mindlin / Ciavarella–Jäger).** Each contact point must follow the
//!   indenter's rigid slide and twist since touch-down, `v_req`. The tangential displacement a point
//!   can carry before it slips is `shear_compliance * friction * w` (the tangential problem as a
//!   difference of normal problems), so with a sliding sphere the stick region is the contact at a
//!   reduced depth: it shrinks from the edge (partial slip) until nothing sticks (gross slip). The
//!   tangential surface displacement `u_t = K ⊗ τ` matches the clamped `v_req` on the contact.
//! - **Material coordinates.** Markers are material points: all fields are functions of a point's
//!   rest position, with the indenter placed where the material under it came from (touch-down point
//!   plus the part of the slide that slipped).

use nalgebra::{Point3, Rotation2, Vector2};

use crate::motion::{Pose, Script};
use crate::sensor::GelSpec;
use gelstereo_core::SlipState;

/// Iterations of the normal and tangential solvers (projected / early-stopped Van Cittert).
const NORMAL_ITERS: usize = 10;
const TANGENTIAL_ITERS: usize = 8;

/// A square grid over the gel surface in the sensor frame: node `(i, j)` (column i, row j) lies at
/// `x = -half + i * spacing`, `y = -half + j * spacing`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceGrid {
    /// Nodes per side.
    pub n: usize,
    /// Node spacing, mm.
    pub spacing_mm: f64,
    /// Half-width of the square, mm.
    pub half_mm: f64,
}

impl SurfaceGrid {
    /// The grid of a gel description.
    pub fn new(gel: &GelSpec) -> Self {
        let n = ((2.0 * gel.half_extent_mm / gel.grid_spacing_mm).round() as usize).max(8) + 1;
        Self {
            n,
            spacing_mm: 2.0 * gel.half_extent_mm / (n - 1) as f64,
            half_mm: gel.half_extent_mm,
        }
    }

    /// Position of node (`i`, `j`), mm.
    pub fn node(&self, i: usize, j: usize) -> [f64; 2] {
        [
            -self.half_mm + i as f64 * self.spacing_mm,
            -self.half_mm + j as f64 * self.spacing_mm,
        ]
    }

    /// Bilinear interpolation of `field` at (`x`, `y`) mm, clamped to the grid.
    #[inline]
    pub fn sample(&self, field: &[f32], x: f64, y: f64) -> f64 {
        let n = self.n;
        let fx = ((x + self.half_mm) / self.spacing_mm).clamp(0.0, (n - 1) as f64 - 1e-9);
        let fy = ((y + self.half_mm) / self.spacing_mm).clamp(0.0, (n - 1) as f64 - 1e-9);
        let (i, j) = (fx as usize, fy as usize);
        let (ax, ay) = (fx - i as f64, fy - j as f64);
        let k = j * n + i;
        let top = f64::from(field[k]) * (1.0 - ax) + f64::from(field[k + 1]) * ax;
        let bot = f64::from(field[k + n]) * (1.0 - ax) + f64::from(field[k + n + 1]) * ax;
        top * (1.0 - ay) + bot * ay
    }
}

/// A 1-D normalised Gaussian.
#[derive(Debug, Clone)]
struct Gauss {
    taps: Vec<f32>,
}

impl Gauss {
    fn new(sigma_cells: f64) -> Self {
        let r = (3.0 * sigma_cells).ceil().max(1.0) as usize;
        let mut taps: Vec<f32> = (0..=2 * r)
            .map(|k| {
                let d = k as f64 - r as f64;
                (-0.5 * d * d / (sigma_cells * sigma_cells)).exp() as f32
            })
            .collect();
        let s: f32 = taps.iter().sum();
        taps.iter_mut().for_each(|t| *t /= s);
        Self { taps }
    }

    /// `dst += weight * (G ⊗ src)` with zero padding (nothing outside the simulated gel).
    fn blur_add(&self, src: &[f32], n: usize, weight: f32, tmp: &mut Vec<f32>, dst: &mut [f32]) {
        let r = self.taps.len() / 2;
        tmp.clear();
        tmp.resize(n * n, 0.0);
        // Horizontal.
        for y in 0..n {
            let row = &src[y * n..(y + 1) * n];
            let out = &mut tmp[y * n..(y + 1) * n];
            for (k, &t) in self.taps.iter().enumerate() {
                // out[x] += t * row[x + k - r]
                let off = k as isize - r as isize;
                let (x0, x1) = (
                    (-off).max(0) as usize,
                    (n as isize - off).min(n as isize) as usize,
                );
                if x0 >= x1 {
                    continue;
                }
                let src_slice = &row[(x0 as isize + off) as usize..(x1 as isize + off) as usize];
                for (o, s) in out[x0..x1].iter_mut().zip(src_slice) {
                    *o += t * s;
                }
            }
        }
        // Vertical, row by row (vectorises).
        for y in 0..n {
            let out = &mut dst[y * n..(y + 1) * n];
            for (k, &t) in self.taps.iter().enumerate() {
                let yy = y as isize + k as isize - r as isize;
                if yy < 0 || yy >= n as isize {
                    continue;
                }
                let tw = t * weight;
                let srow = &tmp[yy as usize * n..(yy as usize + 1) * n];
                for (o, s) in out.iter_mut().zip(srow) {
                    *o += tw * s;
                }
            }
        }
    }
}

/// The layer's response kernel `K` (two Gaussians) with scratch space.
#[derive(Debug, Clone)]
pub struct Layer {
    grid: SurfaceGrid,
    narrow: Gauss,
    wide: Gauss,
    narrow_weight: f32,
}

impl Layer {
    /// The response of the layer `gel` on `grid`.
    pub fn new(gel: &GelSpec, grid: SurfaceGrid) -> Self {
        let cells = |mm: f64| mm / grid.spacing_mm;
        Self {
            grid,
            narrow: Gauss::new(cells(0.35 * gel.thickness_mm)),
            wide: Gauss::new(cells(1.0 * gel.thickness_mm)),
            narrow_weight: 0.65,
        }
    }

    /// `K ⊗ src` into `dst`.
    fn apply(&self, src: &[f32], tmp: &mut Vec<f32>, dst: &mut [f32]) {
        dst.iter_mut().for_each(|d| *d = 0.0);
        let n = self.grid.n;
        self.narrow.blur_add(src, n, self.narrow_weight, tmp, dst);
        self.wide.blur_add(src, n, 1.0 - self.narrow_weight, tmp, dst);
    }
}

/// The deformed gel surface of one frame, as fields over the rest (material) positions.
#[derive(Debug, Clone)]
pub struct Deformation {
    /// The grid the fields live on.
    pub grid: SurfaceGrid,
    /// Displacement towards the cameras (indentation), mm.
    pub w: Vec<f32>,
    /// Tangential displacement along x, mm.
    pub ux: Vec<f32>,
    /// Tangential displacement along y, mm.
    pub uy: Vec<f32>,
    /// Contact load (`q` of the model, in mm of indentation it supports); > 0 in contact.
    pub load: Vec<f32>,
    /// 1 where the contact point sticks to the indenter, 0 elsewhere.
    pub stick: Vec<f32>,
    /// Contact area, mm^2.
    pub contact_area_mm2: f64,
    /// Largest indentation, mm.
    pub max_depth_mm: f64,
    /// Contact centroid (deformed positions), sensor frame, mm.
    pub centroid_mm: Option<[f64; 3]>,
    /// Slip state.
    pub slip: SlipState,
    /// Where the indenter sits in material coordinates: centre x, y (mm) and the angle of its
    /// local x axis (radians); `None` without contact.
    pub indenter_frame: Option<[f64; 3]>,
}

impl Deformation {
    /// The undeformed gel.
    pub fn rest(grid: SurfaceGrid) -> Self {
        let z = vec![0.0; grid.n * grid.n];
        Self {
            grid,
            w: z.clone(),
            ux: z.clone(),
            uy: z.clone(),
            load: z.clone(),
            stick: z,
            contact_area_mm2: 0.0,
            max_depth_mm: 0.0,
            centroid_mm: None,
            slip: SlipState::NoContact,
            indenter_frame: None,
        }
    }

    /// Deformed position (sensor frame, mm) of the material point at rest position (`x`, `y`, 0).
    #[inline]
    pub fn deformed(&self, x: f64, y: f64) -> Point3<f64> {
        let g = &self.grid;
        Point3::new(
            x + g.sample(&self.ux, x, y),
            y + g.sample(&self.uy, x, y),
            -g.sample(&self.w, x, y),
        )
    }

    /// Whether the material point at rest position (`x`, `y`) touches the object.
    pub fn in_contact(&self, x: f64, y: f64) -> bool {
        self.grid.sample(&self.load, x, y) > 1e-4 && self.nearest(&self.load, x, y) > 1e-4
    }

    fn nearest(&self, field: &[f32], x: f64, y: f64) -> f32 {
        let g = &self.grid;
        let i = (((x + g.half_mm) / g.spacing_mm).round() as isize).clamp(0, g.n as isize - 1) as usize;
        let j = (((y + g.half_mm) / g.spacing_mm).round() as isize).clamp(0, g.n as isize - 1) as usize;
        field[j * g.n + i]
    }
}

/// Solves the gel's deformation for one pose of a script.
pub fn deform(gel: &GelSpec, layer: &Layer, script: &Script, pose: &Pose) -> Deformation {
    let grid = layer.grid;
    if pose.depth_mm <= 0.0 {
        return Deformation::rest(grid);
    }
    let n = grid.n;
    let nn = n * n;
    let limit_per_mm = gel.shear_compliance * gel.friction;
    let slide = Vector2::from(pose.slide_mm);
    let twist = pose.twist_deg.to_radians();
    let depth = pose.depth_mm;

    // Where the material under the indenter came from: the stuck part of the slide moved with it.
    let slide_len = slide.norm();
    let stuck = slide_len.min(limit_per_mm * depth);
    let c_ind = Vector2::from(script.centre_mm) + slide;
    let c_mat = if slide_len > 0.0 {
        c_ind - slide * (stuck / slide_len)
    } else {
        c_ind
    };
    // Elastic twist of the contact centre, limited by friction over a typical contact radius.
    let overlap_radius = {
        let mut count = 0usize;
        let angle = (script.angle_deg + pose.twist_deg).to_radians();
        let rot = Rotation2::new(-angle);
        for j in 0..n {
            for i in 0..n {
                let [x, y] = grid.node(i, j);
                let l = rot * (Vector2::new(x, y) - c_ind);
                if script.indenter.height(l.x, l.y) < depth {
                    count += 1;
                }
            }
        }
        (count as f64 * grid.spacing_mm * grid.spacing_mm / std::f64::consts::PI)
            .sqrt()
            .max(grid.spacing_mm)
    };
    let twist_el = twist.signum() * twist.abs().min(limit_per_mm * depth / overlap_radius);
    let mat_angle = (script.angle_deg + pose.twist_deg).to_radians() - twist_el;
    let rot = Rotation2::new(-mat_angle);

    // Rigid overlap.
    let mut pen = vec![0.0f32; nn];
    for j in 0..n {
        for i in 0..n {
            let [x, y] = grid.node(i, j);
            let l = rot * (Vector2::new(x, y) - c_mat);
            pen[j * n + i] = (depth - script.indenter.height(l.x, l.y)) as f32;
        }
    }

    // Normal contact: projected Van Cittert.
    let mut tmp = Vec::with_capacity(nn);
    let mut q: Vec<f32> = pen.iter().map(|&p| p.max(0.0)).collect();
    let mut w = vec![0.0f32; nn];
    for _ in 0..NORMAL_ITERS {
        layer.apply(&q, &mut tmp, &mut w);
        for k in 0..nn {
            q[k] = if pen[k] > 0.0 {
                (q[k] + pen[k] - w[k]).max(0.0)
            } else {
                0.0
            };
        }
    }
    layer.apply(&q, &mut tmp, &mut w);

    // Friction: each contact point must follow the indenter's rigid slide and twist (`v_req`); the
    // tangential load tau (in the units of q) may not exceed friction * q there (Coulomb). Projected
    // Van Cittert on `shear_compliance * K ⊗ tau = v_req` with |tau| <= friction * q.
    let (s, c) = twist.sin_cos();
    let rho = gel.shear_compliance as f32;
    let mu = gel.friction as f32;
    let mut reqx = vec![0.0f32; nn];
    let mut reqy = vec![0.0f32; nn];
    let mut contact = 0usize;
    let mut any_motion = false;
    for j in 0..n {
        for i in 0..n {
            let k = j * n + i;
            if q[k] <= 1e-4 {
                continue;
            }
            contact += 1;
            let [x, y] = grid.node(i, j);
            let (dx, dy) = (x - c_mat.x, y - c_mat.y);
            let req = Vector2::new(
                slide.x + (c - 1.0) * dx - s * dy,
                slide.y + s * dx + (c - 1.0) * dy,
            );
            any_motion |= req.norm() > 1e-9;
            reqx[k] = req.x as f32;
            reqy[k] = req.y as f32;
        }
    }
    let mut ux = vec![0.0f32; nn];
    let mut uy = vec![0.0f32; nn];
    let mut stick: Vec<f32> = q.iter().map(|&v| if v > 1e-4 { 1.0 } else { 0.0 }).collect();
    let mut stuck_count = contact;
    if any_motion {
        let mut tx = vec![0.0f32; nn];
        let mut ty = vec![0.0f32; nn];
        for it in 0..=TANGENTIAL_ITERS {
            layer.apply(&tx, &mut tmp, &mut ux);
            layer.apply(&ty, &mut tmp, &mut uy);
            if it == TANGENTIAL_ITERS {
                break;
            }
            stuck_count = 0;
            for k in 0..nn {
                if q[k] <= 1e-4 {
                    continue;
                }
                let nx = tx[k] + (reqx[k] - rho * ux[k]) / rho;
                let ny = ty[k] + (reqy[k] - rho * uy[k]) / rho;
                let lim = mu * q[k];
                let norm = (nx * nx + ny * ny).sqrt();
                if norm > lim {
                    tx[k] = nx * lim / norm;
                    ty[k] = ny * lim / norm;
                    stick[k] = 0.0;
                } else {
                    tx[k] = nx;
                    ty[k] = ny;
                    stick[k] = 1.0;
                    stuck_count += 1;
                }
            }
        }
        for u in ux.iter_mut().chain(uy.iter_mut()) {
            *u *= rho;
        }
    }

    // Lateral spreading, outwards from the indentation.
    let kspread = (gel.spreading * gel.thickness_mm / (2.0 * grid.spacing_mm)) as f32;
    for j in 0..n {
        for i in 0..n {
            let k = j * n + i;
            let gx = if i > 0 && i + 1 < n {
                w[k + 1] - w[k - 1]
            } else {
                0.0
            };
            let gy = if j > 0 && j + 1 < n {
                w[k + n] - w[k - n]
            } else {
                0.0
            };
            ux[k] -= kspread * gx;
            uy[k] -= kspread * gy;
        }
    }

    // Summary.
    let cell = grid.spacing_mm * grid.spacing_mm;
    let mut max_depth = 0.0f64;
    let mut sum = Vector2::zeros();
    let mut sum_z = 0.0;
    for j in 0..n {
        for i in 0..n {
            let k = j * n + i;
            max_depth = max_depth.max(f64::from(w[k]));
            if q[k] > 1e-4 {
                let [x, y] = grid.node(i, j);
                sum += Vector2::new(x + f64::from(ux[k]), y + f64::from(uy[k]));
                sum_z -= f64::from(w[k]);
            }
        }
    }
    let (slip, centroid) = if contact == 0 {
        (SlipState::NoContact, None)
    } else {
        let ratio = stuck_count as f64 / contact as f64;
        let slip = if ratio >= 0.9 {
            SlipState::Stick
        } else if ratio > 0.03 {
            SlipState::PartialSlip
        } else {
            SlipState::GrossSlip
        };
        let m = sum / contact as f64;
        (slip, Some([m.x, m.y, sum_z / contact as f64]))
    };
    Deformation {
        grid,
        w,
        ux,
        uy,
        load: q,
        stick,
        contact_area_mm2: contact as f64 * cell,
        max_depth_mm: if contact == 0 { 0.0 } else { max_depth },
        centroid_mm: centroid,
        slip,
        indenter_frame: (contact > 0).then_some([c_mat.x, c_mat.y, mat_angle]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::indenter::Indenter;
    use crate::motion::MotionKind;
    use crate::sensor::SensorSpec;

    fn script(indenter: Indenter, slide: [f64; 2], twist: f64) -> Script {
        Script {
            indenter,
            kind: MotionKind::PressSlide,
            centre_mm: [0.0, 0.0],
            angle_deg: 0.0,
            max_depth_mm: 1.0,
            slide_mm: slide,
            twist_deg: twist,
            frames: 10,
            press_end: 0.3,
            shear_end: 0.8,
            release: false,
        }
    }

    #[test]
    fn sphere_press_is_hertz_like_and_sliding_goes_stick_partial_gross() {
        let spec = SensorSpec::reference();
        let grid = SurfaceGrid::new(&spec.gel);
        let layer = Layer::new(&spec.gel, grid);
        let s = script(Indenter::Sphere { radius_mm: 4.0 }, [0.0, 0.0], 0.0);
        let d = deform(
            &spec.gel,
            &layer,
            &s,
            &Pose {
                depth_mm: 0.8,
                slide_mm: [0.0, 0.0],
                twist_deg: 0.0,
            },
        );
        assert_eq!(d.slip, SlipState::Stick);
        // The surface follows the sphere at the centre, within 5 %.
        assert!((d.max_depth_mm - 0.8).abs() < 0.04, "{}", d.max_depth_mm);
        // Contact smaller than the rigid overlap (pi * 2 R d), but not tiny.
        let overlap = std::f64::consts::PI * 2.0 * 4.0 * 0.8;
        assert!(
            d.contact_area_mm2 < overlap && d.contact_area_mm2 > 0.3 * overlap,
            "{}",
            d.contact_area_mm2
        );
        // Surface outside the contact is depressed too (elastic, not a rigid copy).
        assert!(d.grid.sample(&d.w, 3.5, 0.0) > 0.02);
        // Lateral spreading pushes material outwards.
        assert!(d.grid.sample(&d.ux, 3.0, 0.0) > 0.0 && d.grid.sample(&d.ux, -3.0, 0.0) < 0.0);

        let lim = spec.gel.shear_compliance * spec.gel.friction * 0.8;
        let mut states = Vec::new();
        for f in [0.02, 0.3, 0.6, 0.9, 1.2] {
            let slide = [lim * f, 0.0];
            let d = deform(
                &spec.gel,
                &layer,
                &s,
                &Pose {
                    depth_mm: 0.8,
                    slide_mm: slide,
                    twist_deg: 0.0,
                },
            );
            states.push(d.slip);
            if f < 0.9 {
                // Centre sticks: moves with the indenter (the regularised solve overshoots a little).
                let c = d.deformed(0.0, 0.0);
                assert!(
                    (c.x - slide[0]).abs() < 0.2 * slide[0] + 0.01,
                    "f {f}: {} vs {}",
                    c.x,
                    slide[0]
                );
            }
        }
        assert_eq!(
            states,
            [
                SlipState::Stick,
                SlipState::PartialSlip,
                SlipState::PartialSlip,
                SlipState::PartialSlip,
                SlipState::GrossSlip
            ]
        );
    }
}
