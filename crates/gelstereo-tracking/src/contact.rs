//! Contact geometry from the 3-D marker field: the deformed surface as a triangle mesh over the
//! marker lattice, indentation depth, contact region, area, centroid and largest depth.
//!
//! - The **reference surface** is the triangle mesh of the reference (no-contact) marker positions:
//!   each lattice cell with four markers gives two triangles (one with three). Vertex normals are the
//!   area-weighted normals of the triangles around a vertex, oriented away from the left camera
//!   (from the cameras through the gel towards the object).
//! - **Indentation depth** of a marker is its displacement against the reference along the reversed
//!   normal: positive when the surface is pushed towards the cameras.
//! - The **contact region, pressure, force and torque** come from the inverse problem of the
//!   gel, an elastic layer bonded to a rigid plate ([`gelstereo_mechanics`]): the tractions
//!   (pressure `p >= 0`, shear inside the friction cone's closure) whose exact layer response
//!   explains the markers' 3-D displacements, regularised for the frame's measured noise. The
//!   displacements enter in the **gel frame** of the reference surface: `z` along its normal
//!   (away from the cameras), `x` along the lattice's columns, `y = z × x` along its rows. The
//!   contact region is where the pressure exceeds what the noise alone puts there, its edge
//!   placed below the pitch; the area is measured on the reference (material) surface. Depth
//!   alone delimits the contact badly: the layer's response spreads the indentation well beyond
//!   the contact.
//! - The **centroid** is the pressure centroid of the deformed contact points: the markers in
//!   contact at their current positions, weighted by their pressure. (The indentation's own
//!   centre stays behind a sliding contact: the surface is dragged, the depth pattern is not.)
//! - The **largest depth** is refined below the pitch by a least-squares paraboloid over the
//!   logarithm of the 3 x 3 depths around the deepest marker (a 2-D Gaussian peak: the layer's
//!   response makes a smooth indentation peak Gaussian-like; the three-point Gaussian estimator of
//!   PIV correlation peaks, Willert & Gharib, Exp. Fluids 10, 1991), or over the depths themselves
//!   where a neighbour is below a tenth of the peak, when the fit is concave and its apex lies
//!   inside that patch.

use gelstereo_core::{GridIndex, GridShape};
use gelstereo_mechanics::inverse::{ContactLoad, InverseConfig, InverseSolver};
use gelstereo_mechanics::{Influence, Layer};
use nalgebra::{Matrix6, Point3, Vector3, Vector6};

use crate::error::{Error, Result, config_err};

/// A marker slips where its shear traction reaches this fraction of the friction cone: the
/// traction is recovered from noisy displacements, and a slipping region's sits on the cone.
const SLIP_CONE: f64 = 0.9;

/// Settings of the contact estimate. Defaults were chosen on the simulated training split
/// (`docs/tracking.md`).
#[derive(Debug, Clone, PartialEq)]
pub struct ContactConfig {
    /// A frame is in contact when the 3 x 3 mean of the depth peaks above this floor, mm, and
    /// above `contact_noise_factor` x the frame's depth noise / 3 (the noise of a 3 x 3 mean).
    /// 0.01 mm: the noise-free floor. A lower floor sees more of small shallow contacts on exact
    /// 3-D, but from images it lets isolated false contacts through in frames whose robust noise
    /// estimate is low.
    pub min_depth_mm: f64,
    /// The gel: thickness, Young's modulus and Poisson ratio ([`Layer::REFERENCE`] by default).
    pub layer: Layer,
    /// Settings of the inverse problem.
    pub inverse: InverseConfig,
    /// Coulomb friction coefficient between the gel and the object (0.6: silicone on hard
    /// plastic or metal, dry).
    pub friction: f64,
    /// A marker is in contact only where its 3 x 3 mean depth exceeds this fraction of the
    /// frame's largest: contact is where the surface is indented. Where a gel or the data depart
    /// from the ideal layer, the inverse problem spreads a faint load over the free surface to
    /// explain them, while at the edge of a real contact the surface still lies far below the
    /// rest (Hertz on a half-space: half the central depth).
    pub contact_depth_fraction: f64,
    /// Whether to refine the largest depth with a local (Gaussian or quadratic) peak fit.
    pub refine_peak: bool,
    /// The contact threshold in standard deviations of the 3 x 3 mean depth, from the frame's
    /// robust depth noise (`ContactFrame::depth_noise_mm`). 6: the largest of several hundred
    /// 3 x 3 means of noise stays below it (no false contact on the train / val splits with 0.01 and
    /// 0.02 mm of 3-D noise), while a noise-free recording is in contact from 0.01 mm.
    pub contact_noise_factor: f64,
}

impl Default for ContactConfig {
    fn default() -> Self {
        Self {
            min_depth_mm: 0.01,
            layer: Layer::REFERENCE,
            inverse: InverseConfig::default(),
            friction: 0.6,
            contact_depth_fraction: 0.2,
            refine_peak: true,
            contact_noise_factor: 6.0,
        }
    }
}

impl ContactConfig {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        if !(self.min_depth_mm.is_finite() && self.min_depth_mm > 0.0 && self.min_depth_mm < 10.0) {
            return Err(config_err(
                "min_depth_mm",
                "a depth in (0, 10) mm",
                self.min_depth_mm,
            ));
        }
        self.layer.validate()?;
        self.inverse.validate()?;
        if !(self.friction.is_finite() && self.friction > 0.0 && self.friction < self.inverse.friction_bound)
        {
            return Err(config_err(
                "friction",
                &format!("a friction coefficient in (0, {})", self.inverse.friction_bound),
                self.friction,
            ));
        }
        if !(self.contact_noise_factor.is_finite() && (0.0..1000.0).contains(&self.contact_noise_factor)) {
            return Err(config_err(
                "contact_noise_factor",
                "a number of standard deviations in [0, 1000)",
                self.contact_noise_factor,
            ));
        }
        for (field, v) in [("contact_depth_fraction", self.contact_depth_fraction)] {
            if !(v.is_finite() && (0.0..1.0).contains(&v)) {
                return Err(config_err(field, "a fraction in [0, 1)", v));
            }
        }
        Ok(())
    }
}

/// A triangle of the marker mesh: three row-major lattice positions.
pub type Triangle = [u32; 3];

/// The reference surface: marker positions of the reference frame, the mesh over them and its
/// normals, the gel frame, and the contact analysis of later frames against it.
#[derive(Debug, Clone)]
pub struct ReferenceSurface {
    shape: GridShape,
    positions_mm: Vec<Option<Point3<f64>>>,
    normals: Vec<Option<Vector3<f64>>>,
    triangles: Vec<Triangle>,
    plane_normal: Vector3<f64>,
    /// The gel frame's axes in the left camera frame: x along the columns, y along the rows, z
    /// the plane normal.
    gel_axes: [Vector3<f64>; 3],
    pitch_mm: f64,
    config: ContactConfig,
    /// The inverse problem's solver, built at the first contact (its set-up is the layer's
    /// influence operator on this lattice).
    mechanics: Option<Box<InverseSolver>>,
}

impl ReferenceSurface {
    /// Builds the surface from the reference positions, mm, dense over `shape` (row-major, `None`
    /// where a marker is missing), to analyse frames with `config`. Needs at least one triangle.
    pub fn new(shape: GridShape, positions_mm: &[Option<[f64; 3]>], config: ContactConfig) -> Result<Self> {
        config.validate()?;
        if positions_mm.len() != shape.count() {
            return Err(Error::Mismatch {
                what: "reference positions",
                expected: format!(
                    "{} entries ({}x{} lattice)",
                    shape.count(),
                    shape.rows,
                    shape.cols
                ),
                found: format!("{} entries", positions_mm.len()),
            });
        }
        let mut pos = Vec::with_capacity(positions_mm.len());
        for (k, p) in positions_mm.iter().enumerate() {
            pos.push(match p {
                Some(p) if p.iter().all(|v| v.is_finite()) => Some(Point3::from(*p)),
                Some(p) => {
                    return Err(Error::NotFinite {
                        what: format!("reference position {k}"),
                        found: format!("{p:?}"),
                    });
                }
                None => None,
            });
        }
        let triangles = mesh_triangles(shape, &pos);
        if triangles.is_empty() {
            return Err(Error::Reference {
                expected: "3-D markers forming at least one lattice triangle".into(),
                found: format!(
                    "{} marker(s) with 3-D positions, no triangle",
                    pos.iter().flatten().count()
                ),
            });
        }
        // Plane normal: mean of the triangles' normals, oriented away from the camera at the origin.
        let mut sum = Vector3::zeros();
        let mut centre = Vector3::zeros();
        let mut count = 0.0;
        for t in &triangles {
            let [a, b, c] = t.map(|i| pos[i as usize].unwrap_or(Point3::origin()));
            sum += (b - a).cross(&(c - a));
            centre += a.coords;
            count += 1.0;
        }
        let mut plane_normal = sum.try_normalize(1e-12).unwrap_or(Vector3::z());
        if plane_normal.dot(&(centre / count)) < 0.0 {
            plane_normal = -plane_normal;
        }
        let mut normals = vec![Vector3::zeros(); pos.len()];
        for t in &triangles {
            let [a, b, c] = t.map(|i| pos[i as usize].unwrap_or(Point3::origin()));
            let mut n = (b - a).cross(&(c - a));
            if n.dot(&plane_normal) < 0.0 {
                n = -n;
            }
            for &i in t {
                normals[i as usize] += n;
            }
        }
        let normals = normals
            .into_iter()
            .zip(&pos)
            .map(|(n, p)| p.map(|_| n.try_normalize(1e-12).unwrap_or(plane_normal)))
            .collect();
        let pitch_mm = lattice_pitch_mm(shape, &pos).unwrap_or(1.0);
        let gel_axes = gel_axes(shape, &pos, plane_normal);
        Ok(Self {
            shape,
            positions_mm: pos,
            normals,
            triangles,
            plane_normal,
            gel_axes,
            pitch_mm,
            config,
            mechanics: None,
        })
    }

    /// The settings frames are analysed with.
    pub fn config(&self) -> &ContactConfig {
        &self.config
    }

    /// The gel frame: origin at the centre of the reference surface (the mean of its markers),
    /// x along the lattice's columns, y along its rows, z the surface's normal away from the
    /// cameras.
    pub fn gel_frame(&self) -> GelFrame {
        let present: Vec<Point3<f64>> = self.positions_mm.iter().flatten().copied().collect();
        let sum = present.iter().fold(Vector3::zeros(), |a, p| a + p.coords);
        GelFrame {
            origin_mm: Point3::from(sum / present.len().max(1) as f64),
            axes: self.gel_axes,
            pitch_mm: self.pitch_mm(),
        }
    }

    /// The lattice.
    pub fn shape(&self) -> GridShape {
        self.shape
    }

    /// Reference positions, mm, row-major.
    pub fn positions_mm(&self) -> &[Option<Point3<f64>>] {
        &self.positions_mm
    }

    /// Unit normal at each marker (away from the cameras), row-major.
    pub fn normals(&self) -> &[Option<Vector3<f64>>] {
        &self.normals
    }

    /// The mesh's triangles (row-major lattice positions), in a deterministic order.
    pub fn triangles(&self) -> &[Triangle] {
        &self.triangles
    }

    /// Median distance between lattice neighbours on the reference surface, mm.
    pub fn pitch_mm(&self) -> f64 {
        self.pitch_mm
    }

    /// Mean normal of the surface (away from the cameras).
    pub fn plane_normal(&self) -> Vector3<f64> {
        self.plane_normal
    }

    /// Per marker its position, displacement from the reference and depth along the reference
    /// normal; None where the marker is lost, not finite, or has no reference or normal.
    #[allow(clippy::type_complexity)]
    fn measure(
        &self,
        current_mm: &[Option<[f64; 3]>],
    ) -> (
        Vec<Option<Point3<f64>>>,
        Vec<Option<Vector3<f64>>>,
        Vec<Option<f64>>,
    ) {
        let n = current_mm.len();
        let mut positions = vec![None; n];
        let mut displacement = vec![None; n];
        let mut depth = vec![None; n];
        for k in 0..n {
            let (Some(r), Some(nrm), Some(c)) = (self.positions_mm[k], self.normals[k], current_mm[k]) else {
                continue;
            };
            if !c.iter().all(|v| v.is_finite()) {
                continue;
            }
            let c = Point3::from(c);
            let d = c - r;
            positions[k] = Some(c);
            displacement[k] = Some(d);
            depth[k] = Some(-d.dot(&nrm));
        }
        (positions, displacement, depth)
    }

    /// Analyses one frame: `current_mm` holds the frame's 3-D marker positions, dense over the
    /// lattice like the reference (`None` where a marker is lost).
    pub fn analyze(&mut self, current_mm: &[Option<[f64; 3]>]) -> Result<ContactFrame> {
        let config = self.config.clone();
        if current_mm.len() != self.positions_mm.len() {
            return Err(Error::Mismatch {
                what: "frame positions",
                expected: format!("{} entries like the reference", self.positions_mm.len()),
                found: format!("{} entries", current_mm.len()),
            });
        }
        let n = current_mm.len();
        let (positions, displacement, depth) = self.measure(current_mm);
        // Contact is decided on the 3 x 3 mean of the depth, so that single noisy markers do not make
        // one; the deepest point is then refined on the raw depths around the smoothed peak.
        let smooth = smooth3(self.shape, &depth);
        let (peak_index, smooth_max) = deepest(&smooth);
        let depth_noise = depth_noise_mm(self.shape, &depth);
        let contact_depth = config
            .min_depth_mm
            .max(config.contact_noise_factor * depth_noise / 3.0);
        let contact = smooth_max > contact_depth;
        let marker_max = peak_index.and_then(|k| depth[k]).unwrap_or(0.0).max(smooth_max);
        let max_depth = match (config.refine_peak, peak_index) {
            (true, Some(k)) => refine_peak(self.shape, &depth, k).map_or(marker_max, |z| z.max(smooth_max)),
            _ => marker_max,
        };
        let (load, traction) = if contact {
            let indented: Vec<bool> = smooth
                .iter()
                .map(|d| d.is_some_and(|d| d > config.contact_depth_fraction * smooth_max))
                .collect();
            let (load, traction) = self.mechanics(&displacement, depth_noise, &indented)?;
            (Some(load), traction)
        } else {
            if let Some(m) = self.mechanics.as_mut() {
                m.reset();
            }
            (None, vec![[0.0; 3]; n])
        };
        let area = load.as_ref().map_or(0.0, |l| l.area_mm2);
        let slipping: Vec<bool> = (0..n)
            .map(|k| {
                let [tx, ty, p] = traction[k];
                load.as_ref().is_some_and(|l| l.in_contact[k])
                    && tx.hypot(ty) >= SLIP_CONE * config.friction * p
            })
            .collect();
        let in_contact: Vec<bool> = match &load {
            Some(l) => (0..n).map(|k| l.in_contact[k] && depth[k].is_some()).collect(),
            None => vec![false; n],
        };
        // The contact centroid: the pressure centroid of the deformed contact points.
        let pressure: Vec<Option<f64>> = (0..n).map(|k| in_contact[k].then_some(traction[k][2])).collect();
        let centroid = (contact && area > 0.0)
            .then(|| weighted_centroid(&positions, &pressure, 0.0))
            .flatten();
        // Material centroid of the indentation: reference positions weighted by the smoothed depth
        // above half its maximum (the indentation's pattern, which a sliding contact drags across
        // the gel).
        let material_centroid = contact
            .then(|| weighted_centroid(&self.positions_mm, &smooth, 0.5 * smooth_max))
            .flatten();
        Ok(ContactFrame {
            positions_mm: positions,
            displacement_mm: displacement,
            depth_mm: depth,
            in_contact,
            contact: contact && area > 0.0,
            contact_area_mm2: if contact { area } else { 0.0 },
            max_depth_mm: max_depth.max(0.0),
            centroid_mm: centroid,
            material_centroid_mm: material_centroid,
            depth_noise_mm: depth_noise,
            force_n: load.as_ref().map_or(0.0, |l| l.force_n),
            shear_n: load.as_ref().map_or([0.0; 2], |l| l.shear_n),
            torque_nmm: load.as_ref().map_or(0.0, |l| l.torque_nmm),
            slipping,
            traction_kpa: traction,
            peak: peak_index.and_then(|k| index_of(self.shape, k)),
        })
    }

    /// The tractions on the gel that explain the frame's displacements (gel frame, kPa per
    /// marker cell) and what the cells in contact among the `indented` ones add up to.
    fn mechanics(
        &mut self,
        displacement: &[Option<Vector3<f64>>],
        depth_noise: f64,
        indented: &[bool],
    ) -> Result<(ContactLoad, Vec<[f64; 3]>)> {
        let (rows, cols) = (usize::from(self.shape.rows), usize::from(self.shape.cols));
        let solver = match &mut self.mechanics {
            Some(s) => s,
            None => {
                let op = Influence::new(&self.config.layer, rows, cols, self.pitch_mm)?;
                self.mechanics
                    .insert(Box::new(InverseSolver::new(op, self.config.inverse.clone())?))
            }
        };
        let [ex, ey, ez] = self.gel_axes;
        // Into the gel is towards the cameras: −z.
        let gel: Vec<Option<[f64; 3]>> = displacement
            .iter()
            .map(|d| d.map(|d| [d.dot(&ex), d.dot(&ey), -d.dot(&ez)]))
            .collect();
        let component = |c: usize| -> Vec<Option<f64>> { gel.iter().map(|d| d.map(|d| d[c])).collect() };
        let tangential_noise = depth_noise_mm(self.shape, &component(0))
            .hypot(depth_noise_mm(self.shape, &component(1)))
            / std::f64::consts::SQRT_2;
        let t = solver.solve(&gel, [tangential_noise, depth_noise])?;
        let load = ContactLoad::new(&t, rows, cols, self.pitch_mm, Some(indented));
        Ok((load, t.traction_kpa))
    }
}

/// The gel frame's axes in the camera frame: z the plane normal, x the mean step along the
/// lattice's rows (from one column to the next) made normal to z, y = z × x (down the rows).
fn gel_axes(shape: GridShape, pos: &[Option<Point3<f64>>], normal: Vector3<f64>) -> [Vector3<f64>; 3] {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let mut along = Vector3::zeros();
    for r in 0..rows {
        for c in 0..cols.saturating_sub(1) {
            if let (Some(a), Some(b)) = (pos[r * cols + c], pos[r * cols + c + 1]) {
                along += b - a;
            }
        }
    }
    let x = (along - normal * along.dot(&normal))
        .try_normalize(1e-12)
        .unwrap_or_else(|| {
            (Vector3::x() - normal * normal.x)
                .try_normalize(1e-12)
                .unwrap_or(Vector3::y())
        });
    [x, normal.cross(&x), normal]
}

/// The gel frame of a stereo sensor in the left camera frame, mm: origin at the centre of the
/// reference surface, `x` along the lattice's columns, `y` along its rows, `z` the surface's normal
/// away from the cameras; `p_gel = [x; y; z] (p_left − origin)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GelFrame {
    /// The origin, mm.
    pub origin_mm: Point3<f64>,
    /// The axes `[x, y, z]`, unit vectors.
    pub axes: [Vector3<f64>; 3],
    /// The marker pitch on the reference surface, mm.
    pub pitch_mm: f64,
}

impl GelFrame {
    /// A point of the left camera frame in the gel frame, mm.
    pub fn to_gel(&self, p: Point3<f64>) -> [f64; 3] {
        self.vector_to_gel(p - self.origin_mm)
    }

    /// A vector of the left camera frame (a displacement) in the gel frame.
    pub fn vector_to_gel(&self, v: Vector3<f64>) -> [f64; 3] {
        self.axes.map(|a| a.dot(&v))
    }

    /// A gel-frame point in the left camera frame, mm: the inverse of [`Self::to_gel`] (the axes
    /// are orthonormal).
    pub fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        let c = self.origin_mm + Vector3::from(self.vector_to_camera(p));
        [c.x, c.y, c.z]
    }

    /// A gel-frame vector in the left camera frame: the inverse of [`Self::vector_to_gel`].
    pub fn vector_to_camera(&self, v: [f64; 3]) -> [f64; 3] {
        let c = self.axes[0] * v[0] + self.axes[1] * v[1] + self.axes[2] * v[2];
        [c.x, c.y, c.z]
    }
}

/// Contact geometry of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ContactFrame {
    /// Deformed marker positions, mm, row-major (`None` where lost).
    pub positions_mm: Vec<Option<Point3<f64>>>,
    /// 3-D displacement against the reference, mm, row-major.
    pub displacement_mm: Vec<Option<Vector3<f64>>>,
    /// Indentation depth (positive towards the cameras), mm, row-major.
    pub depth_mm: Vec<Option<f64>>,
    /// Whether each marker lies in the contact region.
    pub in_contact: Vec<bool>,
    /// Whether anything touches the gel.
    pub contact: bool,
    /// Contact area on the reference (material) surface, mm^2.
    pub contact_area_mm2: f64,
    /// Largest indentation depth, mm (refined below the pitch; 0 without any depth).
    pub max_depth_mm: f64,
    /// Area centroid of the contact region on the deformed surface, left camera frame, mm.
    pub centroid_mm: Option<Point3<f64>>,
    /// Centroid of the indentation in material (reference) coordinates: the reference positions
    /// weighted by the 3 x 3 smoothed depth above half its maximum, mm. It stays put while the
    /// contact sticks and moves when the object slides across the gel.
    pub material_centroid_mm: Option<Point3<f64>>,
    /// The frame's depth noise, mm: 1.4826 x the median absolute difference between each marker's
    /// depth and the mean of its 8-neighbours' (over sqrt(1 + 1/8)); robust, since most of the
    /// lattice lies outside the contact where the depth field is smooth.
    pub depth_noise_mm: f64,
    /// Total normal force on the gel, N (0 without contact).
    pub force_n: f64,
    /// Total tangential force on the gel along the gel frame's `[x, y]` (the lattice's columns
    /// and rows), N.
    pub shear_n: [f64; 2],
    /// Torque of the tangential tractions about the normal through the pressure centroid, N mm.
    pub torque_nmm: f64,
    /// Traction on each marker's cell `[τx, τy, p]` in the gel frame, kPa (row-major; zeros
    /// without contact): `p` the pressure into the gel.
    pub traction_kpa: Vec<[f64; 3]>,
    /// Whether each marker in contact slips: its shear traction lies on the friction cone
    /// (`|τ| >= SLIP_CONE x friction x p`).
    pub slipping: Vec<bool>,
    /// The deepest marker.
    pub peak: Option<GridIndex>,
}

/// Centroid of `points` weighted by how far their weight (a smoothed depth, a pressure) exceeds
/// `level`, mm; `None` when no point's does.
fn weighted_centroid(
    points: &[Option<Point3<f64>>],
    depth: &[Option<f64>],
    level: f64,
) -> Option<Point3<f64>> {
    let (mut sum, mut wsum) = (Vector3::zeros(), 0.0);
    for (p, d) in points.iter().zip(depth) {
        if let (Some(p), Some(d)) = (p, d)
            && *d > level
        {
            sum += (d - level) * p.coords;
            wsum += d - level;
        }
    }
    (wsum > 0.0).then(|| Point3::from(sum / wsum))
}

fn index_of(shape: GridShape, k: usize) -> Option<GridIndex> {
    let cols = usize::from(shape.cols);
    (k < shape.count()).then(|| GridIndex::new((k / cols) as u16, (k % cols) as u16))
}

/// The deepest of the smoothed depths: its index (None where none is positive) and depth (zero
/// where none is positive); the lowest index among equals.
fn deepest(smooth: &[Option<f64>]) -> (Option<usize>, f64) {
    smooth
        .iter()
        .enumerate()
        .filter_map(|(k, d)| d.map(|d| (k, d)))
        .fold(
            (None, 0.0f64),
            |(bk, bd), (k, d)| if d > bd { (Some(k), d) } else { (bk, bd) },
        )
}

/// Mean of each marker's value and its present 8-neighbours' (`None` where the marker has none).
pub(crate) fn smooth3(shape: GridShape, v: &[Option<f64>]) -> Vec<Option<f64>> {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let mut out = vec![None; v.len()];
    for r in 0..rows {
        for c in 0..cols {
            if v[r * cols + c].is_none() {
                continue;
            }
            let (mut sum, mut n) = (0.0, 0.0);
            for rr in r.saturating_sub(1)..=(r + 1).min(rows - 1) {
                for cc in c.saturating_sub(1)..=(c + 1).min(cols - 1) {
                    if let Some(x) = v[rr * cols + cc] {
                        sum += x;
                        n += 1.0;
                    }
                }
            }
            out[r * cols + c] = Some(sum / n);
        }
    }
    out
}

/// Robust depth noise of a frame: 1.4826 x the median absolute difference between each marker's
/// depth and the mean of its 8-neighbours' (all 8 present), divided by sqrt(1 + 1/8), mm. Most
/// of the lattice lies outside the contact, where the depth field is smooth, so the median sees
/// the noise and not the indentation.
fn depth_noise_mm(shape: GridShape, depth: &[Option<f64>]) -> f64 {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let mut residuals = Vec::with_capacity(depth.len());
    for r in 1..rows.saturating_sub(1) {
        for c in 1..cols.saturating_sub(1) {
            let Some(d) = depth[r * cols + c] else { continue };
            let mut sum = 0.0;
            let mut n = 0;
            for rr in r - 1..=r + 1 {
                for cc in c - 1..=c + 1 {
                    if (rr, cc) != (r, c)
                        && let Some(x) = depth[rr * cols + cc]
                    {
                        sum += x;
                        n += 1;
                    }
                }
            }
            if n == 8 {
                residuals.push((d - sum / 8.0).abs());
            }
        }
    }
    crate::tracker::median(residuals).map_or(0.0, |m| 1.4826 * m / (1.0f64 + 1.0 / 8.0).sqrt())
}

/// Median distance between 4-connected lattice neighbours, mm.
fn lattice_pitch_mm(shape: GridShape, pos: &[Option<Point3<f64>>]) -> Option<f64> {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let mut d = Vec::new();
    for r in 0..rows {
        for c in 0..cols {
            let Some(p) = pos[r * cols + c] else { continue };
            if c + 1 < cols
                && let Some(q) = pos[r * cols + c + 1]
            {
                d.push((q - p).norm());
            }
            if r + 1 < rows
                && let Some(q) = pos[(r + 1) * cols + c]
            {
                d.push((q - p).norm());
            }
        }
    }
    crate::tracker::median(d).filter(|p| *p > 0.0)
}

/// Triangles over the lattice cells whose corners are present: two per full cell (split along the
/// diagonal from top-left to bottom-right), one when exactly three corners are present.
pub fn mesh_triangles<T>(shape: GridShape, present: &[Option<T>]) -> Vec<Triangle> {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let mut out = Vec::new();
    if present.len() != rows * cols {
        return out;
    }
    for r in 0..rows.saturating_sub(1) {
        for c in 0..cols.saturating_sub(1) {
            let tl = r * cols + c;
            let (tr, bl, br) = (tl + 1, tl + cols, tl + cols + 1);
            let has = |k: usize| present[k].is_some();
            match (has(tl), has(tr), has(bl), has(br)) {
                (true, true, true, true) => {
                    out.push([tl as u32, tr as u32, br as u32]);
                    out.push([tl as u32, br as u32, bl as u32]);
                }
                (true, true, true, false) => out.push([tl as u32, tr as u32, bl as u32]),
                (true, true, false, true) => out.push([tl as u32, tr as u32, br as u32]),
                (true, false, true, true) => out.push([tl as u32, br as u32, bl as u32]),
                (false, true, true, true) => out.push([tr as u32, br as u32, bl as u32]),
                _ => {}
            }
        }
    }
    out
}

/// The peak depth over the 3 x 3 lattice neighbourhood of `k` (u, v in lattice steps): the apex
/// of a least-squares paraboloid `a + b u + c v + d u^2 + e uv + f v^2` fitted to the logarithm of
/// the depths (all above a tenth of the centre's), else to the depths, when all nine depths exist,
/// the fit is concave and its apex lies within one step; `None` otherwise.
fn refine_peak(shape: GridShape, depth: &[Option<f64>], k: usize) -> Option<f64> {
    let cols = usize::from(shape.cols);
    let (r, c) = (k / cols, k % cols);
    if r == 0 || c == 0 || r + 1 >= usize::from(shape.rows) || c + 1 >= cols {
        return None;
    }
    let mut patch = [0.0; 9];
    for (i, z) in patch.iter_mut().enumerate() {
        let (du, dv) = (i % 3, i / 3);
        *z = depth.get((r + dv - 1) * cols + c + du - 1).copied().flatten()?;
    }
    // The layer's response makes a smooth indentation peak Gaussian-like: its logarithm is a
    // paraboloid (the three-point Gaussian peak estimator of PIV, Willert & Gharib 1991, in 2-D).
    // Where the patch is not clearly positive, the depth itself is fitted.
    let floor = GAUSSIAN_PEAK_FLOOR * patch[4];
    if patch.iter().all(|z| *z > floor && *z > 0.0) {
        let logs = patch.map(f64::ln);
        if let Some(z) = fit_apex(&logs) {
            return Some(z.exp());
        }
    }
    fit_apex(&patch)
}

/// Smallest neighbour depth, as a fraction of the peak marker's, for the Gaussian peak fit.
const GAUSSIAN_PEAK_FLOOR: f64 = 0.1;

/// Apex of the least-squares paraboloid through a 3 x 3 patch (row-major, unit spacing), when it
/// is concave and lies inside the patch.
fn fit_apex(patch: &[f64; 9]) -> Option<f64> {
    let mut ata = Matrix6::<f64>::zeros();
    let mut atb = Vector6::<f64>::zeros();
    for (i, &z) in patch.iter().enumerate() {
        let (u, v) = ((i % 3) as f64 - 1.0, (i / 3) as f64 - 1.0);
        let row = Vector6::new(1.0, u, v, u * u, u * v, v * v);
        ata += row * row.transpose();
        atb += row * z;
    }
    let s = ata.cholesky()?.solve(&atb);
    let (a, b, cc, d, e, f) = (s[0], s[1], s[2], s[3], s[4], s[5]);
    // Apex: gradient zero: [2d e; e 2f] [u v]^T = -[b c]^T.
    let det = 4.0 * d * f - e * e;
    if !(d < 0.0 && det > 0.0) {
        return None;
    }
    let u = (-2.0 * f * b + e * cc) / det;
    let v = (-2.0 * d * cc + e * b) / det;
    if u.abs() > 1.0 || v.abs() > 1.0 {
        return None;
    }
    let z = a + b * u + cc * v + d * u * u + e * u * v + f * v * v;
    z.is_finite().then_some(z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_mechanics::Influence;

    type Positions = Vec<Option<[f64; 3]>>;

    /// A flat 23 x 23 lattice, pitch 0.8 mm, 24 mm in front of the camera, and the same lattice
    /// pressed by a spherical cap of radius `radius_mm` to `depth_mm` at (`cx`, `cy`): depth
    /// `d - r^2 / 2R` inside the cap (towards the camera, i.e. -z), 0 outside.
    fn lattice(radius_mm: f64, depth_mm: f64, cx: f64, cy: f64) -> (GridShape, Positions, Positions) {
        let shape = GridShape::REFERENCE;
        let mut rest = Vec::new();
        let mut pressed = Vec::new();
        for i in shape.indices() {
            let (x, y) = ((f64::from(i.col) - 11.0) * 0.8, (f64::from(i.row) - 11.0) * 0.8);
            let r2 = (x - cx).powi(2) + (y - cy).powi(2);
            let w = (depth_mm - r2 / (2.0 * radius_mm)).max(0.0);
            rest.push(Some([x, y, 24.0]));
            pressed.push(Some([x, y, 24.0 - w]));
        }
        (shape, rest, pressed)
    }

    #[test]
    fn spherical_cap_centroid_and_depth_resolve_below_the_pitch() {
        // Apex between markers.
        let (shape, rest, pressed) = lattice(4.0, 0.6, 0.33, -0.21);
        let mut surface = ReferenceSurface::new(shape, &rest, ContactConfig::default()).unwrap();
        assert!(
            (surface.plane_normal() - Vector3::z()).norm() < 1e-9,
            "normal points away from the camera"
        );
        assert!((surface.pitch_mm() - 0.8).abs() < 1e-9);
        let f = surface.analyze(&pressed).unwrap();
        assert!(f.contact);
        // The contact lies inside the cap (r^2 < 2 R d).
        let cap = std::f64::consts::PI * 2.0 * 4.0 * 0.6;
        assert!(
            f.contact_area_mm2 > 0.1 * cap && f.contact_area_mm2 < cap,
            "area {} vs cap {cap}",
            f.contact_area_mm2
        );
        let c = f.centroid_mm.unwrap();
        assert!(
            (c.x - 0.33).abs() < 0.05 && (c.y + 0.21).abs() < 0.05,
            "centroid {c:?}"
        );
        // The deepest marker is 0.01-0.05 mm shallower than the apex; the peak fit recovers it to
        // 0.02 mm (a rigid cap is a paraboloid, the fit assumes the Gaussian-like peak of an
        // elastic layer, see `gaussian_peak_is_recovered_between_markers`).
        assert!(
            (f.max_depth_mm - 0.6).abs() < 0.02,
            "max depth {}",
            f.max_depth_mm
        );
        let unrefined = ReferenceSurface::new(
            shape,
            &rest,
            ContactConfig {
                refine_peak: false,
                ..Default::default()
            },
        )
        .unwrap()
        .analyze(&pressed)
        .unwrap();
        assert!(unrefined.max_depth_mm < 0.6 - 0.005);
        assert_eq!(surface.triangles().len(), 2 * 22 * 22);
    }

    #[test]
    fn gaussian_peak_is_recovered_between_markers() {
        // The indentation of an elastic layer is the load blurred by the layer's response: near
        // its peak, Gaussian-like. Width 1 mm (1.25 pitches), apex 0.5 mm between markers.
        let shape = GridShape::REFERENCE;
        let (rest, pressed): (Positions, Positions) = shape
            .indices()
            .map(|i| {
                let (x, y) = ((f64::from(i.col) - 11.0) * 0.8, (f64::from(i.row) - 11.0) * 0.8);
                let w = 0.5 * (-((x - 0.37).powi(2) + (y + 0.29).powi(2)) / 2.0).exp();
                (Some([x, y, 24.0]), Some([x, y, 24.0 - w]))
            })
            .unzip();
        let mut surface = ReferenceSurface::new(shape, &rest, ContactConfig::default()).unwrap();
        let f = surface.analyze(&pressed).unwrap();
        assert!(
            (f.max_depth_mm - 0.5).abs() < 1e-6,
            "max depth {}",
            f.max_depth_mm
        );
    }

    /// The flat 23 x 23 lattice (pitch 0.8 mm, 24 mm in front of the camera) and the same lattice
    /// pressed into the reference gel by a rigid flat punch of radius `radius_mm`, `depth_mm` deep
    /// at (`cx`, `cy`) (the layer's exact response): (rest, pressed, pressure per marker, kPa).
    fn flat_punch(depth_mm: f64, radius_mm: f64, cx: f64, cy: f64) -> (Positions, Positions, Vec<f64>) {
        let shape = GridShape::REFERENCE;
        let xy = |i: GridIndex| ((f64::from(i.col) - 11.0) * 0.8, (f64::from(i.row) - 11.0) * 0.8);
        let pen: Vec<f64> = shape
            .indices()
            .map(|i| {
                let (x, y) = xy(i);
                if (x - cx).hypot(y - cy) < radius_mm {
                    depth_mm
                } else {
                    -1.0
                }
            })
            .collect();
        let op = Influence::new(&Layer::REFERENCE, 23, 23, 0.8).unwrap();
        let sol = gelstereo_mechanics::forward::indent(&op, &pen, 1e-8);
        let rest: Positions = shape.indices().map(|i| Some([xy(i).0, xy(i).1, 24.0])).collect();
        // Gel frame = camera frame here, but for z: into the gel is towards the camera (−z).
        let pressed: Positions = rest
            .iter()
            .zip(&sol.displacement_mm)
            .map(|(p, d)| p.map(|p| [p[0] + d[0], p[1] + d[1], p[2] - d[2]]))
            .collect();
        (rest, pressed, sol.pressure_kpa)
    }

    /// A deterministic uniform generator on [-1, 1) (xorshift), for reproducible noise.
    fn uniform_noise(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            2.0 * ((state >> 11) as f64 / (1u64 << 53) as f64) - 1.0
        }
    }

    #[test]
    fn a_flat_punch_is_recovered() {
        // A flat punch of radius 2.4 mm (3 pitches), 0.1 mm deep at (0.4, 0) mm: its region, area
        // and force come back from the markers' displacements.
        let shape = GridShape::REFERENCE;
        let (rest, pressed, pressure) = flat_punch(0.1, 2.4, 0.4, 0.0);
        let mut surface = ReferenceSurface::new(shape, &rest, ContactConfig::default()).unwrap();
        let f = surface.analyze(&pressed).unwrap();
        let inside = pressure.iter().filter(|p| **p > 0.0).count() as f64 * 0.64;
        assert!(
            (f.contact_area_mm2 - inside).abs() < 0.1 * inside,
            "area {} vs {inside}",
            f.contact_area_mm2
        );
        let force: f64 = pressure.iter().sum::<f64>() * 0.64e-3;
        assert!(
            (f.force_n / force - 1.0).abs() < 0.05,
            "force {} vs {force}",
            f.force_n
        );
        let c = f.centroid_mm.unwrap();
        assert!((c.x - 0.4).abs() < 0.1 && c.y.abs() < 0.1, "{c:?}");
        let wrong = (0..529)
            .filter(|&k| f.in_contact[k] != (pressure[k] > 0.0))
            .count();
        assert!(wrong <= 4, "{wrong} markers misclassified");
    }

    #[test]
    fn no_press_is_no_contact_and_missing_markers_are_tolerated() {
        let (shape, rest, _) = lattice(4.0, 0.0, 0.0, 0.0);
        let mut surface = ReferenceSurface::new(shape, &rest, ContactConfig::default()).unwrap();
        let f = surface.analyze(&rest).unwrap();
        assert!(!f.contact && f.contact_area_mm2 == 0.0 && f.centroid_mm.is_none() && f.max_depth_mm == 0.0);
        let (_, _, mut pressed) = lattice(4.0, 0.5, 0.0, 0.0);
        pressed[11 * 23 + 11] = None;
        pressed[5] = None;
        let f = surface.analyze(&pressed).unwrap();
        assert!(f.contact && f.depth_mm[5].is_none());
        let short = surface.analyze(&pressed[..10]).unwrap_err().to_string();
        assert!(
            short.contains("frame positions") && short.contains("529"),
            "{short}"
        );
        let none = ReferenceSurface::new(shape, &vec![None; 529], ContactConfig::default())
            .unwrap_err()
            .to_string();
        assert!(none.contains("no triangle"), "{none}");
    }

    #[test]
    fn contact_threshold_follows_the_depth_noise() {
        // A noise-free press 0.03 mm deep by a wide cap (3 x 3 mean 0.019 mm) is a contact (floor
        // 0.01 mm).
        let (shape, rest, shallow) = lattice(40.0, 0.03, 0.0, 0.0);
        let mut surface = ReferenceSurface::new(shape, &rest, ContactConfig::default()).unwrap();
        let f = surface.analyze(&shallow).unwrap();
        assert!(f.contact && f.depth_noise_mm < 1e-6, "{}", f.depth_noise_mm);
        // No press, 0.01 mm of depth noise (uniform, deterministic): estimated, and no contact.
        let mut u = uniform_noise(0x2545_F491_4F6C_DD1D);
        let noisy: Positions = rest
            .iter()
            .map(|p| p.map(|[x, y, z]| [x, y, z + 0.01 * 3f64.sqrt() * u()]))
            .collect();
        let f = surface.analyze(&noisy).unwrap();
        assert!((f.depth_noise_mm - 0.01).abs() < 0.003, "{}", f.depth_noise_mm);
        assert!(!f.contact);
    }

    #[test]
    fn the_centroid_of_a_noisy_flat_press_stays_within_the_target() {
        // A flat punch of radius 2.4 mm pressed 0.25 mm at (0.5, −0.3) mm, seen with 0.03 mm of
        // depth noise and 0.005 mm in the plane, as the images give a contact: the depth-weighted
        // centroid stays within the target. Truth: the mean of the loaded markers (the
        // simulator's definition, on the lattice).
        let shape = GridShape::REFERENCE;
        let (rest, pressed, load) = flat_punch(0.25, 2.4, 0.5, -0.3);
        let loaded: Vec<[f64; 3]> = rest
            .iter()
            .zip(&load)
            .filter(|(_, q)| **q > 0.0)
            .filter_map(|(p, _)| *p)
            .collect();
        let truth = loaded
            .iter()
            .fold([0.0, 0.0], |a, p| [a[0] + p[0], a[1] + p[1]])
            .map(|v| v / loaded.len() as f64);
        let mut surface = ReferenceSurface::new(shape, &rest, ContactConfig::default()).unwrap();
        let mut u = uniform_noise(0x9E37_79B9_7F4A_7C15);
        let s3 = 3f64.sqrt();
        let mut errors: Vec<f64> = (0..40)
            .map(|_| {
                let noisy: Positions = pressed
                    .iter()
                    .map(|p| {
                        p.map(|[x, y, z]| [x + 0.005 * s3 * u(), y + 0.005 * s3 * u(), z + 0.03 * s3 * u()])
                    })
                    .collect();
                let f = surface.analyze(&noisy).unwrap();
                f.centroid_mm
                    .map_or(f64::INFINITY, |c| (c.x - truth[0]).hypot(c.y - truth[1]))
            })
            .collect();
        errors.sort_by(f64::total_cmp);
        // 30 of the 40 draws within the 0.2 mm target, the median well inside it.
        assert!(errors[29] < 0.2 && errors[20] < 0.12, "{errors:?}");
    }
}
