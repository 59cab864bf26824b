//! Gel deformation under an indenter: the gel is a linear elastic layer bonded to a rigid plate
//! ([`gelstereo_mechanics`]), pressed and dragged by a rigid indenter with Coulomb friction, solved
//! per frame on a regular grid of its surface (no history: loading is monotonic within each phase
//! of a script).
//!
//! # Model
//! - **Layer response.** [`Influence`]: the exact surface response of the bonded layer (thickness,
//!   Young's modulus, Poisson ratio) to tractions `[τx, τy, p]` uniform over each grid cell, read at
//!   the nodes as `[ux, uy, w]`: the normal and tangential compliances and their coupling (a
//!   pressure on a compressible layer moves the surface sideways, a shear traction moves it up or
//!   down), applied by FFT. Built once per layer and grid and shared (see [`Layer`]).
//! - **Normal contact.** With `pen = depth - h(x)` the rigid overlap of the indenter,
//!   [`forward::indent`] (frictionless, Polonsky–Keer conjugate gradients) gives the pressure
//!   `p >= 0` with `w = C_nn p` equal to `pen` where `p > 0` and at least `pen` elsewhere: the
//!   contact is smaller than the rigid overlap and the gel around it sinks too.
//! - **Tangential contact (Cattaneo–Mindlin).** Each contact point must follow the indenter's rigid
//!   slide and twist since touch-down, `v_req`. The tractions `τ` minimise
//!   `½ τᵀ C_tt τ − v_reqᵀ τ` over `|τ| <= friction · p` at every node (accelerated projected
//!   gradients, FISTA with restarts, each step one [`Influence::apply`]): where a point sticks, its
//!   tangential displacement under `τ` is `v_req`; where it slips, `τ` is at the Coulomb limit and
//!   points along `v_req − u_t`, against the slip. The pressure vanishes at the edge of a curved
//!   contact, so the stick region shrinks from the edge as the slide grows (partial slip) until
//!   nothing sticks (gross slip).
//! - **Surface.** The markers' displacement is the layer's full response `C [τx, τy, p]`: the
//!   lateral bulge of the pressed layer and the normal displacement of the shear tractions included.
//! - **Neglected.** The tangential tractions' effect back on the pressure (the normal problem is
//!   solved first, then the tangential one with that pressure); friction during the press (the
//!   press is frictionless: the bulge under the pressure is free, friction resists only the slide
//!   and twist); the loading history (each frame is solved from its pose: right for the monotonic
//!   scripts used: press, then slide / twist, then release).
//! - **Material coordinates.** Markers are material points: all fields are functions of a point's
//!   rest position, with the indenter placed where the material under it came from: the
//!   touch-down point plus the part of the slide (and of the twist) that the material did not
//!   follow. The material follows the slide by at most what the contact carries at gross slip, the
//!   pressure-weighted mean displacement along the slide under `τ = friction · p` along it (and the
//!   twist by the torsional twin of that).

use std::sync::{Arc, Mutex, OnceLock};

use gelstereo_mechanics::{Influence, Vec3, Workspace, forward};
use nalgebra::{Point3, Rotation2, Vector2};

use crate::error::Result;
use crate::motion::{Pose, Script};
use gelstereo_core::SlipState;
use gelstereo_sensor::GelSpec;

/// Relative tolerance of the normal contact solver on the gap (of the deepest overlap).
const NORMAL_TOLERANCE: f64 = 1e-5;
/// The tangential solver stops when its stick residual falls below this fraction of the largest
/// required displacement.
const TANGENTIAL_TOLERANCE: f64 = 1e-3;
/// Iterations of the tangential solver, at most.
const TANGENTIAL_ITERS: usize = 600;
/// Influence operators kept for reuse (different layers or grids).
const CACHED_OPERATORS: usize = 8;
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

/// The gel layer's response on the physics grid: its influence operator, shared by every
/// simulator of the same layer and grid (it costs tens of milliseconds to build).
#[derive(Debug, Clone)]
pub struct Layer {
    grid: SurfaceGrid,
    facts: gelstereo_mechanics::Layer,
    op: Arc<Influence>,
}

impl Layer {
    /// The response of the layer `gel` on `grid` (an error only for facts out of range, which a
    /// validated sensor file never holds).
    pub fn new(gel: &GelSpec, grid: SurfaceGrid) -> Result<Self> {
        let facts = gel.layer();
        Ok(Self {
            grid,
            facts,
            op: influence(&facts, grid)?,
        })
    }

    /// The grid the response lives on.
    pub fn grid(&self) -> SurfaceGrid {
        self.grid
    }

    /// The influence operator.
    pub fn influence(&self) -> &Influence {
        &self.op
    }
}

/// The influence operator of `facts` on `grid`, from a small cache (the same operator for the same
/// layer and grid: the result does not depend on which simulator built it first).
fn influence(facts: &gelstereo_mechanics::Layer, grid: SurfaceGrid) -> Result<Arc<Influence>> {
    type Key = [u64; 5];
    type Cache = Mutex<Vec<(Key, Arc<Influence>)>>;
    static CACHE: OnceLock<Cache> = OnceLock::new();
    let key = [
        facts.thickness_mm.to_bits(),
        facts.modulus_kpa.to_bits(),
        facts.poisson.to_bits(),
        grid.n as u64,
        grid.spacing_mm.to_bits(),
    ];
    let cache = CACHE.get_or_init(Mutex::default);
    let hit = cache
        .lock()
        .ok()
        .and_then(|c| c.iter().find(|(k, _)| *k == key).map(|(_, op)| Arc::clone(op)));
    if let Some(op) = hit {
        return Ok(op);
    }
    let op = Arc::new(Influence::new(facts, grid.n, grid.n, grid.spacing_mm)?);
    if let Ok(mut c) = cache.lock() {
        if c.len() >= CACHED_OPERATORS {
            c.remove(0);
        }
        c.push((key, Arc::clone(&op)));
    }
    Ok(op)
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
    /// Contact pressure, kPa (> 0 in contact).
    pub pressure: Vec<f32>,
    /// Tangential traction of the object on the gel along x and y, kPa.
    pub traction: [Vec<f32>; 2],
    /// The contact load as a length, mm: pressure x thickness / Young's modulus (the compression it
    /// would make of an unconfined layer). Contact where it exceeds 1e-4 mm; it drives the
    /// renderer's fading of the markers.
    pub load: Vec<f32>,
    /// 1 where a loaded point sticks to the indenter, 0 elsewhere (slipping or unloaded).
    pub stick: Vec<f32>,
    /// Contact area, mm^2: the cells where the pressure is positive (rest positions).
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
    /// Total normal force on the gel, N.
    pub force_n: f64,
    /// Total tangential force on the gel along the sensor frame's x and y, N.
    pub shear_n: [f64; 2],
    /// Torque of the tangential tractions about the normal through the pressure centroid (rest
    /// positions), N mm, positive from x towards y.
    pub torque_nmm: f64,
}

/// Whether a load (mm) marks contact.
const LOADED_MM: f32 = 1e-4;

impl Deformation {
    /// The undeformed gel.
    pub fn rest(grid: SurfaceGrid) -> Self {
        let z = vec![0.0; grid.n * grid.n];
        Self {
            grid,
            w: z.clone(),
            ux: z.clone(),
            uy: z.clone(),
            pressure: z.clone(),
            traction: [z.clone(), z.clone()],
            load: z.clone(),
            stick: z,
            contact_area_mm2: 0.0,
            max_depth_mm: 0.0,
            centroid_mm: None,
            slip: SlipState::NoContact,
            indenter_frame: None,
            force_n: 0.0,
            shear_n: [0.0; 2],
            torque_nmm: 0.0,
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
        let loaded = f64::from(LOADED_MM);
        self.grid.sample(&self.load, x, y) > loaded && self.nearest(&self.load, x, y) > LOADED_MM
    }

    /// Contact pressure at rest position (`x`, `y`), kPa (bilinear over the grid).
    pub fn pressure_kpa(&self, x: f64, y: f64) -> f64 {
        self.grid.sample(&self.pressure, x, y).max(0.0)
    }

    /// Whether the material point at rest position (`x`, `y`) touches the object and its cell (the
    /// nearest node's) slips: its traction is at the friction limit.
    pub fn slipping(&self, x: f64, y: f64) -> bool {
        self.in_contact(x, y) && self.nearest(&self.stick, x, y) == 0.0
    }

    fn nearest(&self, field: &[f32], x: f64, y: f64) -> f32 {
        let g = &self.grid;
        let i = (((x + g.half_mm) / g.spacing_mm).round() as isize).clamp(0, g.n as isize - 1) as usize;
        let j = (((y + g.half_mm) / g.spacing_mm).round() as isize).clamp(0, g.n as isize - 1) as usize;
        field[j * g.n + i]
    }
}

/// The contact of the layer with a rigid indenter on the grid: pressure, tangential tractions,
/// which loaded nodes slip, and the surface displacement.
#[derive(Debug, Clone)]
struct Contact {
    /// Pressure per node, kPa.
    pressure: Vec<f64>,
    /// Tangential traction per node, kPa.
    traction: Vec<[f64; 2]>,
    /// Whether a loaded node's traction is at the friction limit.
    slipping: Vec<bool>,
    /// Surface displacement `[ux, uy, w]` per node, mm.
    displacement: Vec<Vec3>,
}

/// The frictionless press of the rigid overlap `pen` (per node, mm). Gaps wider than the deepest
/// overlap are clamped to it: no bulge of the gel closes them, and [`forward::indent`] measures its
/// tolerance against the largest overlap in magnitude (an indenter's infinite height far away
/// would stop it at once).
fn press(layer: &Layer, pen: &[f64]) -> forward::Indentation {
    let deepest = pen.iter().fold(0.0f64, |m, &v| m.max(v));
    let pen: Vec<f64> = pen.iter().map(|&v| v.max(-deepest)).collect();
    forward::indent(&layer.op, &pen, NORMAL_TOLERANCE)
}

/// Adds the tangential contact to the press `normal`: `required(k)` is the rigid tangential
/// displacement (mm) that loaded node `k` must follow where it sticks; `None` leaves the press
/// alone (no slide, no twist).
fn drag(
    layer: &Layer,
    friction: f64,
    normal: forward::Indentation,
    required: Option<&dyn Fn(usize) -> [f64; 2]>,
) -> Contact {
    let nn = normal.pressure_kpa.len();
    let p = normal.pressure_kpa;
    let Some(required) = required else {
        return Contact {
            pressure: p,
            traction: vec![[0.0; 2]; nn],
            slipping: vec![false; nn],
            displacement: normal.displacement_mm,
        };
    };
    let contact: Vec<usize> = (0..nn).filter(|&k| p[k] > 0.0).collect();
    let req: Vec<[f64; 2]> = contact.iter().map(|&k| required(k)).collect();
    let limit: Vec<f64> = contact.iter().map(|&k| friction * p[k]).collect();
    let mut work = Workspace::default();
    let (tau, active) = tangential(&layer.op, &mut work, &contact, &limit, &req);
    let mut traction = vec![[0.0; 2]; nn];
    let mut slipping = vec![false; nn];
    for (j, &k) in contact.iter().enumerate() {
        traction[k] = tau[j];
        slipping[k] = active[j];
    }
    let t: Vec<Vec3> = (0..nn).map(|k| [traction[k][0], traction[k][1], p[k]]).collect();
    let mut displacement = vec![[0.0; 3]; nn];
    layer.op.apply(&t, &mut displacement, &mut work);
    Contact {
        pressure: p,
        traction,
        slipping,
        displacement,
    }
}

/// The tangential tractions on the nodes `contact`: the minimum of `½ τᵀ C_tt τ − reqᵀ τ` over
/// `|τ_j| <= limit_j`, by FISTA with adaptive restarts (O'Donoghue & Candès, 2015) and the step
/// `1 / ‖C‖`. Returns the tractions and whether each node's limit is active (it slips).
fn tangential(
    op: &Influence,
    work: &mut Workspace,
    contact: &[usize],
    limit: &[f64],
    req: &[[f64; 2]],
) -> (Vec<[f64; 2]>, Vec<bool>) {
    let nn = op.rows() * op.cols();
    let m = contact.len();
    let step = 1.0 / op.norm();
    let scale = req.iter().fold(0.0f64, |a, r| a.max(r[0].hypot(r[1])));
    let mut x = vec![[0.0; 2]; m];
    let mut active = vec![false; m];
    if m == 0 || scale <= 0.0 {
        return (x, active);
    }
    let tolerance = TANGENTIAL_TOLERANCE * scale;
    let mut y = x.clone();
    let mut next = x.clone();
    let mut t_k = 1.0f64;
    let mut load = vec![[0.0; 3]; nn];
    let mut u = vec![[0.0; 3]; nn];
    for _ in 0..TANGENTIAL_ITERS {
        for (j, &k) in contact.iter().enumerate() {
            load[k] = [y[j][0], y[j][1], 0.0];
        }
        op.apply(&load, &mut u, work);
        // One projected gradient step from y; the gradient mapping (y - next) / step is the stick
        // residual where the step stays inside the friction disc, and vanishes at the optimum.
        let (mut residual, mut progress) = (0.0f64, 0.0f64);
        for j in 0..m {
            let k = contact[j];
            let z = [
                y[j][0] - step * (u[k][0] - req[j][0]),
                y[j][1] - step * (u[k][1] - req[j][1]),
            ];
            let size = z[0].hypot(z[1]);
            active[j] = size > limit[j];
            next[j] = if active[j] {
                let f = limit[j] / size;
                [z[0] * f, z[1] * f]
            } else {
                z
            };
            let g = [y[j][0] - next[j][0], y[j][1] - next[j][1]];
            residual = residual.max(g[0].hypot(g[1]) / step);
            progress += g[0] * (next[j][0] - x[j][0]) + g[1] * (next[j][1] - x[j][1]);
        }
        if residual <= tolerance {
            std::mem::swap(&mut x, &mut next);
            break;
        }
        // Restart the momentum when it points against the descent.
        let beta = if progress > 0.0 {
            t_k = 1.0;
            0.0
        } else {
            let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t_k * t_k).sqrt());
            let b = (t_k - 1.0) / t_next;
            t_k = t_next;
            b
        };
        for j in 0..m {
            for c in 0..2 {
                y[j][c] = next[j][c] + beta * (next[j][c] - x[j][c]);
            }
        }
        std::mem::swap(&mut x, &mut next);
    }
    (x, active)
}

/// How far the contact with pressure `p` carries the material at gross slip: the pressure-weighted
/// mean displacement along the unit `direction` under the tractions `friction · p` along it, mm,
/// and the twist (radians) under `friction · p` turning about `centre` (rest coordinates, mm), the
/// pressure- and radius²-weighted mean rotation. `None` for a motion that is absent.
fn carried(
    layer: &Layer,
    friction: f64,
    p: &[f64],
    direction: Option<Vector2<f64>>,
    centre: Option<Vector2<f64>>,
) -> (f64, f64) {
    let grid = layer.grid;
    let n = grid.n;
    let nn = n * n;
    let node = |k: usize| Vector2::from(grid.node(k % n, k / n));
    let mut work = Workspace::default();
    let mut u = vec![[0.0; 3]; nn];
    let along = direction.map_or(0.0, |d| {
        let t: Vec<Vec3> = p
            .iter()
            .map(|&v| [friction * v * d.x, friction * v * d.y, 0.0])
            .collect();
        layer.op.apply(&t, &mut u, &mut work);
        let (num, den) = (0..nn).fold((0.0, 0.0), |(a, b), k| {
            (a + p[k] * (u[k][0] * d.x + u[k][1] * d.y), b + p[k])
        });
        if den > 0.0 { num / den } else { 0.0 }
    });
    let turn = centre.map_or(0.0, |c| {
        let t: Vec<Vec3> = (0..nn)
            .map(|k| {
                let r = node(k) - c;
                let len = r.norm();
                if len > 0.0 {
                    let s = friction * p[k] / len;
                    [-r.y * s, r.x * s, 0.0]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        layer.op.apply(&t, &mut u, &mut work);
        let (num, den) = (0..nn).fold((0.0, 0.0), |(a, b), k| {
            let r = node(k) - c;
            (
                a + p[k] * (r.x * u[k][1] - r.y * u[k][0]),
                b + p[k] * r.norm_squared(),
            )
        });
        if den > 0.0 { num / den } else { 0.0 }
    });
    (along.max(0.0), turn.max(0.0))
}

/// Rounds of the alternation between the normal and the tangential contact problem in a moving
/// contact (the first solve neglects the shear's normal motion).
const COUPLING_ROUNDS: usize = 2;

/// The normal displacement (mm, into the gel positive as the pressure's) that the tangential
/// tractions `traction` (kPa) alone cause.
fn normal_motion_of_shear(layer: &Layer, traction: &[[f64; 2]]) -> Vec<f64> {
    let t: Vec<Vec3> = traction.iter().map(|t| [t[0], t[1], 0.0]).collect();
    let mut u = vec![[0.0; 3]; t.len()];
    layer.op.apply(&t, &mut u, &mut Workspace::default());
    u.iter().map(|u| u[2]).collect()
}

/// Solves the gel's deformation for one pose of a script.
pub fn deform(gel: &GelSpec, layer: &Layer, script: &Script, pose: &Pose) -> Deformation {
    let grid = layer.grid;
    if pose.depth_mm <= 0.0 {
        return Deformation::rest(grid);
    }
    let n = grid.n;
    let nn = n * n;
    let slide = Vector2::from(pose.slide_mm);
    let twist = pose.twist_deg.to_radians();
    let depth = pose.depth_mm;
    let overlap = |c_mat: Vector2<f64>, angle: f64| -> Vec<f64> {
        let rot = Rotation2::new(-angle);
        (0..nn)
            .map(|k| {
                let l = rot * (Vector2::from(grid.node(k % n, k / n)) - c_mat);
                depth - script.indenter.height(l.x, l.y)
            })
            .collect()
    };
    let (c_mat, mat_angle, normal) = place_material(gel, layer, script, slide, twist, &overlap);
    let sol = solve_shear(gel, layer, normal, slide, twist, c_mat, || {
        overlap(c_mat, mat_angle)
    });
    summarize(layer, &sol, [c_mat.x, c_mat.y, mat_angle])
}

/// Where the material under the indenter came from: first where it sticks (the touch-down
/// place), then, if the contact cannot carry the whole slide or twist, moved by the part that
/// slipped. Returns that place, the material angle and the press there; `overlap(centre,
/// angle)` is the indenter's overlap with the rest surface placed so.
fn place_material(
    gel: &GelSpec,
    layer: &Layer,
    script: &Script,
    slide: Vector2<f64>,
    twist: f64,
    overlap: &dyn Fn(Vector2<f64>, f64) -> Vec<f64>,
) -> (Vector2<f64>, f64, forward::Indentation) {
    let slide_len = slide.norm();
    let touch_down = Vector2::from(script.centre_mm);
    let c_ind = touch_down + slide;
    let base_angle = script.angle_deg.to_radians();
    let (mut c_mat, mut mat_angle) = (touch_down, base_angle);
    let mut normal = press(layer, &overlap(c_mat, mat_angle));
    let moving = slide_len > 0.0 || twist != 0.0;
    if moving && normal.pressure_kpa.iter().any(|&v| v > 0.0) {
        let (along, turn) = carried(
            layer,
            gel.friction,
            &normal.pressure_kpa,
            (slide_len > 0.0).then(|| slide / slide_len),
            (twist != 0.0).then_some(touch_down),
        );
        let stuck = slide_len.min(along);
        let twist_el = twist.signum() * twist.abs().min(turn);
        if stuck < slide_len || twist_el != twist {
            c_mat = if slide_len > 0.0 {
                c_ind - slide * (stuck / slide_len)
            } else {
                c_ind
            };
            mat_angle = base_angle + twist - twist_el;
            normal = press(layer, &overlap(c_mat, mat_angle));
        }
    }
    (c_mat, mat_angle, normal)
}

/// Friction: each loaded point must follow the indenter's rigid slide and twist about `c_mat`.
/// The shear also moves the surface along its normal (the layer's normal–tangential coupling),
/// which lifts the surface into the indenter on one side and away on the other: press again with
/// that motion taken from the overlap (`overlap_now`), then drag again, so that pressure and
/// shear are solved together (alternating the normal and the tangential problem, as Kalker's
/// Panagiotopoulos process does).
fn solve_shear(
    gel: &GelSpec,
    layer: &Layer,
    normal: forward::Indentation,
    slide: Vector2<f64>,
    twist: f64,
    c_mat: Vector2<f64>,
    overlap_now: impl Fn() -> Vec<f64>,
) -> Contact {
    let grid = layer.grid;
    let n = grid.n;
    let moving = slide.norm() > 0.0 || twist != 0.0;
    let (s, c) = twist.sin_cos();
    let required = |k: usize| -> [f64; 2] {
        let [x, y] = grid.node(k % n, k / n);
        let (dx, dy) = (x - c_mat.x, y - c_mat.y);
        [
            slide.x + (c - 1.0) * dx - s * dy,
            slide.y + s * dx + (c - 1.0) * dy,
        ]
    };
    let required = moving.then_some(&required as &dyn Fn(usize) -> [f64; 2]);
    let mut sol = drag(layer, gel.friction, normal, required);
    if moving {
        let overlap_now = overlap_now();
        for _ in 0..COUPLING_ROUNDS {
            let lift = normal_motion_of_shear(layer, &sol.traction);
            let pen: Vec<f64> = overlap_now.iter().zip(&lift).map(|(o, l)| o - l).collect();
            sol = drag(layer, gel.friction, press(layer, &pen), required);
        }
    }
    sol
}

/// Sums over the loaded nodes of a solved contact.
struct ContactTotals {
    /// Deepest indentation over all nodes, mm.
    max_depth: f64,
    /// Loaded nodes, and of those the ones that stick.
    contact: usize,
    stuck_count: usize,
    /// Sum of the loaded nodes' displaced in-plane positions and of their depths (negated).
    sum: Vector2<f64>,
    sum_z: f64,
    /// Sum of pressures, of tangential tractions and of pressure-weighted rest positions.
    force: f64,
    shear: [f64; 2],
    moment: Vector2<f64>,
}

impl ContactTotals {
    fn of(grid: SurfaceGrid, sol: &Contact) -> Self {
        let n = grid.n;
        let mut s = Self {
            max_depth: 0.0,
            contact: 0,
            stuck_count: 0,
            sum: Vector2::zeros(),
            sum_z: 0.0,
            force: 0.0,
            shear: [0.0; 2],
            moment: Vector2::zeros(),
        };
        for (k, &pk) in sol.pressure.iter().enumerate().take(n * n) {
            let u = sol.displacement[k];
            s.max_depth = s.max_depth.max(u[2]);
            if pk > 0.0 {
                let r = Vector2::from(grid.node(k % n, k / n));
                s.contact += 1;
                s.stuck_count += usize::from(!sol.slipping[k]);
                s.sum += Vector2::new(r.x + u[0], r.y + u[1]);
                s.sum_z -= u[2];
                s.force += pk;
                s.moment += r * pk;
                s.shear[0] += sol.traction[k][0];
                s.shear[1] += sol.traction[k][1];
            }
        }
        s
    }

    /// The contact's slip state by its share of sticking nodes, and its displaced centroid.
    fn slip_and_centroid(&self) -> (SlipState, Option<[f64; 3]>) {
        if self.contact == 0 {
            return (SlipState::NoContact, None);
        }
        let ratio = self.stuck_count as f64 / self.contact as f64;
        let slip = if ratio >= 0.9 {
            SlipState::Stick
        } else if ratio > 0.03 {
            SlipState::PartialSlip
        } else {
            SlipState::GrossSlip
        };
        let m = self.sum / self.contact as f64;
        (slip, Some([m.x, m.y, self.sum_z / self.contact as f64]))
    }
}

/// The per-node fields and the summary of a solved contact; `indenter_frame` is the material
/// place and angle it was solved at.
fn summarize(layer: &Layer, sol: &Contact, indenter_frame: [f64; 3]) -> Deformation {
    let grid = layer.grid;
    let n = grid.n;
    let nn = n * n;
    let cell = grid.spacing_mm * grid.spacing_mm;
    let load_per_kpa = layer.facts.thickness_mm / layer.facts.modulus_kpa;
    let p = &sol.pressure;
    let totals = ContactTotals::of(grid, sol);
    let (contact, force) = (totals.contact, totals.force);
    // Torque about the pressure centroid: Σ (r − c) × τ = Σ r × τ − c × Σ τ.
    let centre = if force > 0.0 {
        totals.moment / force
    } else {
        Vector2::zeros()
    };
    let torque: f64 = (0..nn)
        .filter(|&k| p[k] > 0.0)
        .map(|k| {
            let r = Vector2::from(grid.node(k % n, k / n)) - centre;
            r.x * sol.traction[k][1] - r.y * sol.traction[k][0]
        })
        .sum();
    let (slip, centroid) = totals.slip_and_centroid();
    let field = |f: &dyn Fn(usize) -> f64| -> Vec<f32> { (0..nn).map(|k| f(k) as f32).collect() };
    Deformation {
        grid,
        w: field(&|k| sol.displacement[k][2]),
        ux: field(&|k| sol.displacement[k][0]),
        uy: field(&|k| sol.displacement[k][1]),
        pressure: field(&|k| p[k]),
        traction: [field(&|k| sol.traction[k][0]), field(&|k| sol.traction[k][1])],
        load: field(&|k| p[k] * load_per_kpa),
        stick: field(&|k| f64::from(u8::from(p[k] > 0.0 && !sol.slipping[k]))),
        contact_area_mm2: contact as f64 * cell,
        max_depth_mm: if contact == 0 { 0.0 } else { totals.max_depth },
        centroid_mm: centroid,
        slip,
        indenter_frame: (contact > 0).then_some(indenter_frame),
        force_n: force * cell * 1e-3,
        shear_n: [totals.shear[0] * cell * 1e-3, totals.shear[1] * cell * 1e-3],
        torque_nmm: torque * cell * 1e-3,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::indenter::Indenter;
    use crate::motion::MotionKind;
    use gelstereo_sensor::SensorSpec;

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

    fn pose(depth_mm: f64, slide_mm: [f64; 2], twist_deg: f64) -> Pose {
        Pose {
            depth_mm,
            slide_mm,
            twist_deg,
        }
    }

    /// The finite-element reference of the bonded layer (data/fixtures/elastic-fe, scikit-fem,
    /// converged to 0.3 % in force): its gel, and the truth of one of its cases.
    fn fe_case(name: &str) -> (GelSpec, serde_json::Value) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../data/fixtures/elastic-fe/bonded-layer.json");
        let fe: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let layer = &fe["layer"];
        let gel = GelSpec {
            thickness_mm: layer["thickness_mm"].as_f64().unwrap(),
            half_extent_mm: 14.0,
            grid_spacing_mm: 0.2,
            friction: 5.0,
            modulus_kpa: layer["modulus_kpa"].as_f64().unwrap(),
            poisson: layer["poisson"].as_f64().unwrap(),
        };
        let case = fe["cases"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["name"] == name)
            .unwrap();
        (gel, case.clone())
    }

    fn close(got: f64, want: f64, rel: f64) -> bool {
        (got / want - 1.0).abs() < rel
    }

    /// A sharp flat punch (radius 2.5 mm, 0.12 mm deep) on the finite-element reference's layer
    /// (3.2 mm, 150 kPa, 0.42): the force of the bonded layer's flat-punch stiffness as the FE
    /// solution gives it, within 3 % (the grid's 0.2 mm cells resolve the edge singularity).
    #[test]
    fn a_sharp_flat_punch_presses_with_the_finite_element_force() {
        let (gel, case) = fe_case("flat-punch");
        let layer = Layer::new(&gel, SurfaceGrid::new(&gel)).unwrap();
        let grid = layer.grid();
        let (radius, depth) = (2.5, 0.12);
        let pen: Vec<f64> = (0..grid.n * grid.n)
            .map(|k| {
                let [x, y] = grid.node(k % grid.n, k / grid.n);
                if x.hypot(y) < radius { depth } else { -1.0 }
            })
            .collect();
        let sol = press(&layer, &pen);
        let force = sol.force_n(grid.spacing_mm);
        let want = case["truth"]["force_N"].as_f64().unwrap();
        assert!(close(force, want, 0.03), "force {force} N, FE {want} N");
    }

    /// The same punch bonded to the gel (full stick: friction far above the traction's ratio) and
    /// moved sideways by (0.05, 0.02) mm: the shear of the FE solution within 3 %. The FE keeps the
    /// gel under the punch from bulging during the press too; those tractions are radial and sum to
    /// no shear, so the totals compare.
    #[test]
    fn the_sheared_bonded_punch_carries_the_finite_element_shear() {
        let (gel, case) = fe_case("flat-punch-sheared");
        let layer = Layer::new(&gel, SurfaceGrid::new(&gel)).unwrap();
        let grid = layer.grid();
        let n = grid.n;
        let pen: Vec<f64> = (0..n * n)
            .map(|k| {
                let [x, y] = grid.node(k % n, k / n);
                if x.hypot(y) < 2.5 { 0.12 } else { -1.0 }
            })
            .collect();
        let shift = [0.05, 0.02];
        let required = |_k: usize| shift;
        let sol = drag(&layer, gel.friction, press(&layer, &pen), Some(&required));
        let cell = grid.spacing_mm * grid.spacing_mm * 1e-3;
        let shear = sol
            .traction
            .iter()
            .fold([0.0; 2], |s, t| [s[0] + t[0] * cell, s[1] + t[1] * cell]);
        let truth = &case["truth"];
        let want = [
            truth["shear_x_N"].as_f64().unwrap(),
            truth["shear_y_N"].as_f64().unwrap(),
        ];
        assert!(
            close(shear[0], want[0], 0.03) && close(shear[1], want[1], 0.03),
            "shear {shear:?} N, FE {want:?} N"
        );
        // It sticks: under the punch the surface moved with it.
        let loaded = sol.pressure.iter().filter(|&&v| v > 0.0).count();
        let slipping = sol.slipping.iter().filter(|&&s| s).count();
        assert!(slipping * 50 < loaded, "{slipping} of {loaded} nodes slip");
        let centre = sol.displacement[(n / 2) * n + n / 2];
        assert!(
            (centre[0] - shift[0]).abs() < 2e-3 && (centre[1] - shift[1]).abs() < 2e-3,
            "{centre:?}"
        );
    }

    /// The simulator's flat cylinder has a 0.25 mm edge fillet: its force lies between the sharp
    /// punches of its flat face and of its outline, so the FE's sharp 2.5 mm punch falls between
    /// the filleted 2.5 mm cylinder and the filleted 2.75 mm one (a contact force grows with the
    /// rigid overlap).
    #[test]
    fn filleted_cylinders_bracket_the_finite_element_punch() {
        let (gel, case) = fe_case("flat-punch");
        let layer = Layer::new(&gel, SurfaceGrid::new(&gel)).unwrap();
        let want = case["truth"]["force_N"].as_f64().unwrap();
        let force = |radius_mm: f64| {
            let s = script(Indenter::FlatCylinder { radius_mm }, [0.0; 2], 0.0);
            deform(&gel, &layer, &s, &pose(0.12, [0.0; 2], 0.0)).force_n
        };
        let (inner, outer) = (force(2.5), force(2.75));
        assert!(inner < want && want < outer, "{inner} < {want} < {outer} N");
    }

    /// A sphere pressed through the simulator (geometry, placement, solver): the FE sphere's force
    /// within 3 % and its contact area within 6 % (the area counts whole 0.2 mm cells).
    #[test]
    fn a_pressed_sphere_matches_the_finite_element_sphere() {
        let (gel, case) = fe_case("sphere-deep");
        let layer = Layer::new(&gel, SurfaceGrid::new(&gel)).unwrap();
        let sphere = &case["indenter"]["spheres"][0];
        let radius_mm = sphere["radius_mm"].as_f64().unwrap();
        let depth = sphere["depth_mm"].as_f64().unwrap();
        let s = script(Indenter::Sphere { radius_mm }, [0.0; 2], 0.0);
        let d = deform(&gel, &layer, &s, &pose(depth, [0.0; 2], 0.0));
        let truth = &case["truth"];
        let (force, area) = (
            truth["force_N"].as_f64().unwrap(),
            truth["contact_area_mm2"].as_f64().unwrap(),
        );
        assert!(close(d.force_n, force, 0.03), "{} vs {force} N", d.force_n);
        assert!(
            close(d.contact_area_mm2, area, 0.06),
            "{} vs {area} mm2",
            d.contact_area_mm2
        );
        assert!(d.shear_n == [0.0; 2] && d.torque_nmm == 0.0);
        assert_eq!(d.slip, SlipState::Stick);
    }

    #[test]
    fn sphere_press_then_slide_goes_stick_partial_gross_within_the_friction_cone() {
        let spec = SensorSpec::reference();
        let grid = SurfaceGrid::new(&spec.gel);
        let layer = Layer::new(&spec.gel, grid).unwrap();
        let s = script(Indenter::Sphere { radius_mm: 4.0 }, [0.0, 0.0], 0.0);
        let d = deform(&spec.gel, &layer, &s, &pose(0.8, [0.0; 2], 0.0));
        assert_eq!(d.slip, SlipState::Stick);
        // The surface follows the sphere at the centre, within 1 % (the solver's tolerance is far
        // below; the rest is the cell's size).
        assert!((d.max_depth_mm - 0.8).abs() < 0.008, "{}", d.max_depth_mm);
        // Contact smaller than the rigid overlap (pi * 2 R d), but not tiny.
        let overlap = std::f64::consts::PI * 2.0 * 4.0 * 0.8;
        assert!(
            d.contact_area_mm2 < overlap && d.contact_area_mm2 > 0.3 * overlap,
            "{}",
            d.contact_area_mm2
        );
        // The squeezed, nearly incompressible layer bulges outwards around the contact.
        assert!(d.grid.sample(&d.ux, 3.0, 0.0) > 0.0 && d.grid.sample(&d.ux, -3.0, 0.0) < 0.0);
        // Pressure at the centre, none far away; the load marks the contact.
        assert!(d.pressure_kpa(0.0, 0.0) > 10.0 && d.pressure_kpa(8.0, 0.0) == 0.0);
        assert!(d.in_contact(0.0, 0.0) && !d.in_contact(8.0, 0.0) && !d.slipping(0.0, 0.0));
        let press_force = d.force_n;

        // The slide the contact carries at gross slip.
        let p: Vec<f64> = d.pressure.iter().map(|&v| f64::from(v)).collect();
        let (lim, _) = carried(&layer, spec.gel.friction, &p, Some(Vector2::x()), None);
        assert!(lim > 0.0);
        let mut states = Vec::new();
        for f in [0.02, 0.3, 0.6, 0.9, 1.5] {
            let slide = [lim * f, 0.0];
            let d = deform(&spec.gel, &layer, &s, &pose(0.8, slide, 0.0));
            states.push(d.slip);
            // The press does not change (the shear's effect on the pressure is neglected, and the
            // sphere is the same wherever the material under it came from).
            assert!(
                close(d.force_n, press_force, 0.01),
                "{} vs {press_force}",
                d.force_n
            );
            // Coulomb: the shear never exceeds friction x force, and it drags along the slide.
            let shear = d.shear_n[0].hypot(d.shear_n[1]);
            assert!(shear <= spec.gel.friction * d.force_n * (1.0 + 1e-9), "f {f}");
            assert!(
                d.shear_n[0] > 0.0 && d.shear_n[1].abs() < 1e-6 * shear,
                "{:?}",
                d.shear_n
            );
            if f < 0.9 {
                // The centre sticks: it moves with the indenter.
                let c = d.deformed(0.0, 0.0);
                assert!(
                    (c.x - slide[0]).abs() < 0.01 * slide[0] + 1e-4,
                    "f {f}: {} vs {}",
                    c.x,
                    slide[0]
                );
                assert!(!d.slipping(0.0, 0.0));
            } else if f > 1.0 {
                // Gross slip: the whole friction cone.
                assert!(close(shear, spec.gel.friction * d.force_n, 1e-3), "f {f}");
                // The indenter sits where the material under it came from: the touch-down point
                // plus the part of the slide the contact could not carry (`lim`, from the
                // pressure in f32 here, so to 1e-4).
                let [x, _, _] = d.indenter_frame.unwrap();
                assert!(close(x, slide[0] - lim, 1e-4), "{x} vs {}", slide[0] - lim);
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

    /// A twist turns the tractions the same way (positive torque from x towards y) and never
    /// beyond what friction allows: |torque| <= friction x the largest radius x force.
    #[test]
    fn a_twist_gives_a_torque_of_its_sign_within_friction() {
        let spec = SensorSpec::reference();
        let layer = Layer::new(&spec.gel, SurfaceGrid::new(&spec.gel)).unwrap();
        let s = script(Indenter::FlatCylinder { radius_mm: 2.0 }, [0.0; 2], 10.0);
        for twist in [2.0, -20.0] {
            let d = deform(&spec.gel, &layer, &s, &pose(0.3, [0.0; 2], twist));
            assert!(d.torque_nmm * twist > 0.0, "{twist}: {}", d.torque_nmm);
            assert!(d.torque_nmm.abs() <= spec.gel.friction * 2.0 * d.force_n);
            assert!(
                d.shear_n[0].hypot(d.shear_n[1]) < 1e-3 * d.force_n,
                "{:?}",
                d.shear_n
            );
        }
    }

    #[test]
    fn the_same_pose_gives_the_same_bits() {
        let spec = SensorSpec::reference();
        let layer = Layer::new(&spec.gel, SurfaceGrid::new(&spec.gel)).unwrap();
        let s = script(Indenter::Sphere { radius_mm: 5.0 }, [1.0, 0.5], 8.0);
        let p = pose(0.5, [0.6, 0.3], 5.0);
        let (a, b) = (
            deform(&spec.gel, &layer, &s, &p),
            deform(&spec.gel, &layer, &s, &p),
        );
        assert!(a.w == b.w && a.ux == b.ux && a.uy == b.uy && a.pressure == b.pressure);
        assert_eq!(a.force_n.to_bits(), b.force_n.to_bits());
        assert_eq!(a.torque_nmm.to_bits(), b.torque_nmm.to_bits());
    }
}
