//! The sensor description file: marker grid, gel mechanics and the two cameras.
//!
//! # Frames
//! The *sensor frame* has its origin at the centre of the gel's marker surface, x along the grid's
//! columns, y along its rows (so row grows with y, col with x, as in the left view), and z pointing
//! from the cameras out through the gel towards the object. An indenter pushes the surface towards
//! the cameras, i.e. to negative z. Each camera is placed by its centre `position_mm` and the point
//! it looks at, `look_at_mm`, both in the sensor frame; the camera's y axis is the sensor's y axis
//! made orthogonal to the viewing direction. Ground truth is written in the LEFT camera's frame.
//!
//! The reference file is `calib/reference-sensor.json`; `docs/sim.md` documents every field.

use std::path::Path;

use gelstereo_core::{GridShape, ImageSize};
use gelstereo_geometry::{Camera, Distortion, StereoRig};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// SplitMix64's output function: a stateless hash of `z`, for draws that must be the same for a
/// given key in every run (an irregular lattice's jitter per marker, the renderer's per-marker
/// looks) without carrying a random-number generator along.
pub fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A whole sensor description.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorSpec {
    /// A name written into every recording's `meta.json`.
    pub name: String,
    /// The marker lattice.
    pub grid: GridSpec,
    /// Gel mechanics.
    pub gel: GelSpec,
    /// The two cameras.
    pub cameras: CamerasSpec,
    /// The outline of the gel the markers are printed on, when it is not the whole view (a round or
    /// trapezoidal membrane in a housing); absent: the gel fills the view.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub membrane: Option<Membrane>,
}

/// How the markers are arranged on the gel.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum Lattice {
    /// Rows and columns `pitch_mm` apart.
    #[default]
    Square,
    /// Rows `pitch_mm * sqrt(3) / 2` apart, odd rows shifted by half a pitch (TacTip-like pins):
    /// every marker has six neighbours `pitch_mm` away.
    Hexagonal,
    /// The square lattice with every marker moved by up to `jitter_frac * pitch_mm` along each
    /// axis (hand-placed or irregularly printed dots), reproducibly from `seed`.
    Irregular {
        /// Largest displacement per axis, as a fraction of the pitch (0 to 0.3).
        jitter_frac: f64,
        /// Seed of the displacements.
        seed: u64,
    },
}

impl Lattice {
    fn is_square(&self) -> bool {
        *self == Self::Square
    }
}

/// The outline of a membrane in the sensor plane (rest coordinates, mm, centred on the origin).
/// Markers are printed only inside it; outside, the cameras see the housing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum Membrane {
    /// A disc (TacTip, DIGIT-like round pads).
    Circle {
        /// Radius, mm.
        radius_mm: f64,
    },
    /// A trapezoid, wider at the bottom (+y) or the top, symmetric about x = 0.
    Trapezoid {
        /// Half-width at y = -half_height_mm, mm.
        top_half_width_mm: f64,
        /// Half-width at y = +half_height_mm, mm.
        bottom_half_width_mm: f64,
        /// Half of the height, mm.
        half_height_mm: f64,
    },
}

impl Membrane {
    /// Signed distance from the outline at (`x`, `y`), mm: negative inside, positive outside
    /// (exact for the circle; for the trapezoid the largest distance to its four edge lines, which
    /// is exact inside and near the edges).
    pub fn signed_distance_mm(&self, x: f64, y: f64) -> f64 {
        match *self {
            Self::Circle { radius_mm } => x.hypot(y) - radius_mm,
            Self::Trapezoid {
                top_half_width_mm: a,
                bottom_half_width_mm: b,
                half_height_mm: h,
            } => {
                // Right edge from (a, -h) to (b, h): outward normal (2h, -(b - a)) normalised.
                let (nx, ny) = (2.0 * h, -(b - a));
                let n = nx.hypot(ny);
                let side = (nx * (x.abs() - a) + ny * (y + h)) / n;
                side.max(y.abs() - h)
            }
        }
    }

    /// Whether a dot of radius `margin_mm` centred at (`x`, `y`) lies wholly inside the outline.
    pub fn holds(&self, x: f64, y: f64, margin_mm: f64) -> bool {
        self.signed_distance_mm(x, y) <= -margin_mm
    }
}

/// The marker lattice on the gel surface, centred on the sensor frame's origin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GridSpec {
    /// Marker rows (along y).
    pub rows: u16,
    /// Marker columns (along x).
    pub cols: u16,
    /// Centre-to-centre distance, mm.
    pub pitch_mm: f64,
    /// Printed dot diameter, mm.
    pub dot_diameter_mm: f64,
    /// Arrangement of the markers (absent: square).
    #[serde(default, skip_serializing_if = "Lattice::is_square")]
    pub lattice: Lattice,
}

/// Young's modulus of the reference sensor's gel, kPa: sensor files without one have it.
pub const REFERENCE_MODULUS_KPA: f64 = gelstereo_mechanics::Layer::REFERENCE.modulus_kpa;
/// Poisson ratio of the reference sensor's gel (as [`REFERENCE_MODULUS_KPA`]).
pub const REFERENCE_POISSON: f64 = gelstereo_mechanics::Layer::REFERENCE.poisson;

fn reference_modulus_kpa() -> f64 {
    REFERENCE_MODULUS_KPA
}

fn reference_poisson() -> f64 {
    REFERENCE_POISSON
}

/// Gel layer mechanics: a linear elastic layer bonded to a rigid acrylic plate
/// (`gelstereo_mechanics::Layer`), with the simulated patch of its surface and the friction
/// against the object.
///
/// Sensor files written before the layer had a modulus and a Poisson ratio read as the reference
/// values ([`REFERENCE_MODULUS_KPA`], [`REFERENCE_POISSON`]); their `spreading` and
/// `shear_compliance` (factors of an earlier, non-physical response) are accepted and ignored: the
/// layer's exact response gives both the lateral bulge and the tangential compliance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(from = "GelFile")]
pub struct GelSpec {
    /// Thickness of the elastomer layer between the contact surface and the rigid plate, mm.
    pub thickness_mm: f64,
    /// Half-width of the simulated square of gel surface around the origin, mm (must cover what the
    /// cameras see).
    pub half_extent_mm: f64,
    /// Spacing of the physics grid, mm (the deformation is computed on it, then interpolated).
    pub grid_spacing_mm: f64,
    /// Coulomb friction coefficient between gel and object.
    pub friction: f64,
    /// Young's modulus of the elastomer, kPa.
    pub modulus_kpa: f64,
    /// Poisson ratio of the elastomer, in [0, 0.5).
    pub poisson: f64,
}

/// [`GelSpec`] as a file holds it: the modulus and Poisson ratio may be absent (older files) and
/// the obsolete `spreading` and `shear_compliance` present.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GelFile {
    thickness_mm: f64,
    half_extent_mm: f64,
    grid_spacing_mm: f64,
    friction: f64,
    #[serde(default = "reference_modulus_kpa")]
    modulus_kpa: f64,
    #[serde(default = "reference_poisson")]
    poisson: f64,
    #[serde(default, rename = "shear_compliance")]
    _shear_compliance: Option<serde::de::IgnoredAny>,
    #[serde(default, rename = "spreading")]
    _spreading: Option<serde::de::IgnoredAny>,
}

impl From<GelFile> for GelSpec {
    fn from(f: GelFile) -> Self {
        Self {
            thickness_mm: f.thickness_mm,
            half_extent_mm: f.half_extent_mm,
            grid_spacing_mm: f.grid_spacing_mm,
            friction: f.friction,
            modulus_kpa: f.modulus_kpa,
            poisson: f.poisson,
        }
    }
}

impl GelSpec {
    /// The elastic layer of the contact mechanics.
    pub fn layer(&self) -> gelstereo_mechanics::Layer {
        gelstereo_mechanics::Layer {
            thickness_mm: self.thickness_mm,
            modulus_kpa: self.modulus_kpa,
            poisson: self.poisson,
        }
    }
}

/// The stereo pair: both cameras share the image size.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CamerasSpec {
    /// Image width, px.
    pub image_width: u32,
    /// Image height, px.
    pub image_height: u32,
    /// The left camera (the reference 3-D frame of all ground truth).
    pub left: CameraSpec,
    /// The right camera.
    pub right: CameraSpec,
}

/// One camera: OpenCV intrinsics and its placement in the sensor frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Focal length along x, px.
    pub fx: f64,
    /// Focal length along y, px.
    pub fy: f64,
    /// Principal point x, px ((0, 0) = centre of the top-left pixel).
    pub cx: f64,
    /// Principal point y, px.
    pub cy: f64,
    /// OpenCV distortion `k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]]`: 0, 4, 5, 8 or 12 values.
    pub distortion: Vec<f64>,
    /// Camera centre in the sensor frame, mm (z < 0: behind the gel).
    pub position_mm: [f64; 3],
    /// The point the optical axis goes through, sensor frame, mm.
    pub look_at_mm: [f64; 3],
}

fn field_err(source_name: &str, field: &str, expected: &str, found: impl std::fmt::Display) -> Error {
    Error::SensorField {
        source_name: source_name.to_owned(),
        field: field.to_owned(),
        expected: expected.to_owned(),
        found: found.to_string(),
    }
}

fn positive(src: &str, field: &str, v: f64) -> Result<()> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(field_err(src, field, "a finite number > 0", v))
    }
}

fn in_range(src: &str, field: &str, v: f64, lo: f64, hi: f64) -> Result<()> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        Err(field_err(src, field, &format!("a number in [{lo}, {hi}]"), v))
    }
}

/// The sensor-frame pose of a simulated sensor: cameras, lattice and mechanics, ready to use.
#[derive(Debug, Clone)]
pub struct Sensor {
    /// The description it was built from.
    pub spec: SensorSpec,
    /// The calibrated rig (exactly what is written to `calib.yaml` and the `.cameramodel` files).
    pub rig: StereoRig,
    /// Left camera frame from sensor frame.
    pub left_from_sensor: Isometry3<f64>,
    /// Right camera frame from sensor frame.
    pub right_from_sensor: Isometry3<f64>,
}

impl SensorSpec {
    /// Reads and validates a sensor description (JSON). Errors name the file and the field.
    pub fn load(path: &Path) -> Result<Self> {
        let text =
            gelstereo_core::limits::read_text_at_most(path, gelstereo_core::limits::MAX_DESCRIPTION_BYTES)
                .map_err(crate::error::io_err(path))?;
        let spec: SensorSpec = serde_json::from_str(&text).map_err(|e| Error::SensorSyntax {
            path: path.to_owned(),
            message: e.to_string(),
        })?;
        spec.validate(&path.display().to_string())?;
        Ok(spec)
    }

    /// The reference GelStereo sensor (the same numbers as `calib/reference-sensor.json`).
    pub fn reference() -> Self {
        // Compiled in so the library works without the repository checkout; a test checks that the
        // file in calib/ is identical.
        let text = include_str!("../../../calib/reference-sensor.json");
        match serde_json::from_str(text) {
            Ok(spec) => spec,
            Err(e) => unreachable!("calib/reference-sensor.json is checked by a test: {e}"),
        }
    }

    /// The marker lattice's shape.
    pub fn grid_shape(&self) -> GridShape {
        GridShape {
            rows: self.grid.rows,
            cols: self.grid.cols,
        }
    }

    /// Image size of both cameras.
    pub fn image_size(&self) -> ImageSize {
        ImageSize {
            width: self.cameras.image_width,
            height: self.cameras.image_height,
        }
    }

    /// Rest position of marker (`row`, `col`) in the sensor frame, mm (z = 0), per the lattice.
    pub fn marker_rest_mm(&self, row: u16, col: u16) -> [f64; 2] {
        let p = self.grid.pitch_mm;
        let x = f64::from(col) - 0.5 * f64::from(self.grid.cols - 1);
        let y = f64::from(row) - 0.5 * f64::from(self.grid.rows - 1);
        match self.grid.lattice {
            Lattice::Square => [x * p, y * p],
            Lattice::Hexagonal => {
                let shift = if row % 2 == 1 { 0.25 } else { -0.25 };
                [(x + shift) * p, y * p * 0.75f64.sqrt()]
            }
            Lattice::Irregular { jitter_frac, seed } => {
                let key = seed ^ (u64::from(row) << 32) ^ u64::from(col);
                let h = splitmix64(key);
                // Two uniform numbers in [-1, 1) from the hash's halves.
                let u = |bits: u64| (bits & 0xFFFF_FFFF) as f64 / 2_147_483_648.0 - 1.0;
                [(x + jitter_frac * u(h)) * p, (y + jitter_frac * u(h >> 32)) * p]
            }
        }
    }

    /// Whether marker (`row`, `col`) is printed: inside the membrane with its whole dot (always
    /// without a membrane). Unprinted markers are never drawn and never visible.
    pub fn marker_printed(&self, row: u16, col: u16) -> bool {
        let Some(membrane) = &self.membrane else {
            return true;
        };
        let [x, y] = self.marker_rest_mm(row, col);
        membrane.holds(x, y, 0.5 * self.grid.dot_diameter_mm)
    }

    /// Checks every field's range; `src` names the file in errors. The sections are checked in
    /// file order, so the first offending field is the one reported.
    pub fn validate(&self, src: &str) -> Result<()> {
        self.validate_grid(src)?;
        self.validate_membrane(src)?;
        self.validate_gel(src)?;
        self.validate_cameras(src)
    }

    /// The marker lattice: size, pitch, dot size and irregularity.
    fn validate_grid(&self, src: &str) -> Result<()> {
        let g = &self.grid;
        if !(2..=200).contains(&g.rows) {
            return Err(field_err(src, "grid.rows", "an integer in [2, 200]", g.rows));
        }
        if !(2..=200).contains(&g.cols) {
            return Err(field_err(src, "grid.cols", "an integer in [2, 200]", g.cols));
        }
        positive(src, "grid.pitch_mm", g.pitch_mm)?;
        positive(src, "grid.dot_diameter_mm", g.dot_diameter_mm)?;
        if g.dot_diameter_mm >= g.pitch_mm {
            return Err(field_err(
                src,
                "grid.dot_diameter_mm",
                &format!("less than grid.pitch_mm ({})", g.pitch_mm),
                g.dot_diameter_mm,
            ));
        }
        if let Lattice::Irregular { jitter_frac, .. } = g.lattice {
            in_range(src, "grid.lattice.jitter_frac", jitter_frac, 0.0, 0.3)?;
        }
        Ok(())
    }

    /// The membrane's outline, where it does not fill the view.
    fn validate_membrane(&self, src: &str) -> Result<()> {
        match self.membrane {
            None => {}
            Some(Membrane::Circle { radius_mm }) => positive(src, "membrane.radius_mm", radius_mm)?,
            Some(Membrane::Trapezoid {
                top_half_width_mm,
                bottom_half_width_mm,
                half_height_mm,
            }) => {
                positive(src, "membrane.top_half_width_mm", top_half_width_mm)?;
                positive(src, "membrane.bottom_half_width_mm", bottom_half_width_mm)?;
                positive(src, "membrane.half_height_mm", half_height_mm)?;
            }
        }
        Ok(())
    }

    /// The gel layer: thickness, extent against the lattice, physics grid and material.
    fn validate_gel(&self, src: &str) -> Result<()> {
        let gel = &self.gel;
        let g = &self.grid;
        positive(src, "gel.thickness_mm", gel.thickness_mm)?;
        positive(src, "gel.grid_spacing_mm", gel.grid_spacing_mm)?;
        let span = 0.5 * f64::from(g.rows.max(g.cols) - 1) * g.pitch_mm;
        if !(gel.half_extent_mm.is_finite() && gel.half_extent_mm > span + g.pitch_mm) {
            return Err(field_err(
                src,
                "gel.half_extent_mm",
                &format!(
                    "more than the lattice's half-width plus one pitch ({:.3} mm)",
                    span + g.pitch_mm
                ),
                gel.half_extent_mm,
            ));
        }
        let cells = 2.0 * gel.half_extent_mm / gel.grid_spacing_mm;
        if !(8.0..=512.0).contains(&cells) {
            return Err(field_err(
                src,
                "gel.grid_spacing_mm",
                "a spacing giving 8 to 512 physics cells across 2 * gel.half_extent_mm",
                gel.grid_spacing_mm,
            ));
        }
        in_range(src, "gel.friction", gel.friction, 0.05, 5.0)?;
        positive(src, "gel.modulus_kpa", gel.modulus_kpa)?;
        if !(gel.poisson.is_finite() && (0.0..0.5).contains(&gel.poisson)) {
            // 0.5, the incompressible limit, makes a bonded layer rigid under a uniform load.
            return Err(field_err(src, "gel.poisson", "a number in [0, 0.5)", gel.poisson));
        }
        Ok(())
    }

    /// The cameras: image size, each camera's intrinsics and pose, and a non-zero baseline.
    fn validate_cameras(&self, src: &str) -> Result<()> {
        let c = &self.cameras;
        if !(16..=8192).contains(&c.image_width) {
            return Err(field_err(
                src,
                "cameras.image_width",
                "an integer in [16, 8192]",
                c.image_width,
            ));
        }
        if !(16..=8192).contains(&c.image_height) {
            return Err(field_err(
                src,
                "cameras.image_height",
                "an integer in [16, 8192]",
                c.image_height,
            ));
        }
        for (name, cam) in [("left", &c.left), ("right", &c.right)] {
            validate_camera(src, name, cam, c)?;
        }
        if c.left.position_mm == c.right.position_mm {
            return Err(field_err(
                src,
                "cameras.right.position_mm",
                "a position different from the left camera's (non-zero baseline)",
                format!("{:?}", c.right.position_mm),
            ));
        }
        Ok(())
    }

    /// Builds the cameras and their poses. Call [`SensorSpec::validate`] first (loading does).
    pub fn build(&self) -> Result<Sensor> {
        self.validate("sensor")?;
        let size = self.image_size();
        let camera = |c: &CameraSpec| -> Result<Camera> {
            let cam = Camera {
                image_size: size,
                fx: c.fx,
                fy: c.fy,
                cx: c.cx,
                cy: c.cy,
                distortion: Distortion::new(c.distortion.clone())?,
            };
            cam.validate()?;
            Ok(cam)
        };
        let left_from_sensor = camera_from_sensor(&self.cameras.left);
        let right_from_sensor = camera_from_sensor(&self.cameras.right);
        let rig = StereoRig {
            left: camera(&self.cameras.left)?,
            right: camera(&self.cameras.right)?,
            right_from_left: right_from_sensor * left_from_sensor.inverse(),
        };
        rig.validate()?;
        Ok(Sensor {
            spec: self.clone(),
            rig,
            left_from_sensor,
            right_from_sensor,
        })
    }
}

/// `camera_from_sensor` of a camera at `position_mm` looking at `look_at_mm`, y axis as close to
/// the sensor's +y as possible.
fn camera_from_sensor(c: &CameraSpec) -> Isometry3<f64> {
    let pos = Vector3::from(c.position_mm);
    let z = (Vector3::from(c.look_at_mm) - pos).normalize();
    let x = Vector3::y().cross(&z).normalize();
    let y = z.cross(&x);
    // Columns = camera axes in the sensor frame: sensor_from_camera rotation.
    let sensor_from_cam = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    let rot = UnitQuaternion::from_rotation_matrix(&sensor_from_cam).inverse();
    let t = -(rot * pos);
    Isometry3::from_parts(Translation3::from(t), rot)
}

impl Sensor {
    /// The sensor-frame point `p` (mm) in the left and right camera frames.
    pub fn to_cameras(&self, p: &Point3<f64>) -> (Point3<f64>, Point3<f64>) {
        (self.left_from_sensor * p, self.right_from_sensor * p)
    }

    /// Whether every marker of the lattice at rest projects inside both images with `margin_px`
    /// to spare.
    pub fn all_markers_visible_at_rest(&self, margin_px: f64) -> bool {
        self.visible_fraction_at_rest(margin_px) >= 1.0
    }

    /// Fraction of the lattice's markers that, at rest, project inside both images with
    /// `margin_px` to spare.
    pub fn visible_fraction_at_rest(&self, margin_px: f64) -> f64 {
        let size = self.spec.image_size();
        let inside = |q: gelstereo_core::Point2| {
            q.x >= margin_px
                && q.y >= margin_px
                && q.x <= f64::from(size.width) - 1.0 - margin_px
                && q.y <= f64::from(size.height) - 1.0 - margin_px
        };
        let grid = self.spec.grid_shape();
        let seen = grid
            .indices()
            .filter(|i| {
                if !self.spec.marker_printed(i.row, i.col) {
                    return false;
                }
                let [x, y] = self.spec.marker_rest_mm(i.row, i.col);
                let (l, r) = self.to_cameras(&Point3::new(x, y, 0.0));
                matches!((self.rig.left.project(&l), self.rig.right.project(&r)),
                    (Some(a), Some(b)) if inside(a) && inside(b))
            })
            .count();
        seen as f64 / grid.count() as f64
    }

    /// Marker pitch in the left image at the centre of the lattice, px.
    pub fn pitch_px(&self) -> f64 {
        let p = self.spec.grid.pitch_mm;
        let a = self
            .rig
            .left
            .project(&(self.left_from_sensor * Point3::new(-0.5 * p, 0.0, 0.0)));
        let b = self
            .rig
            .left
            .project(&(self.left_from_sensor * Point3::new(0.5 * p, 0.0, 0.0)));
        match (a, b) {
            (Some(a), Some(b)) => a.distance(b),
            _ => f64::NAN,
        }
    }
}

/// One camera of `cameras` (named `name`): intrinsics inside the image, distortion of a known
/// length and sane size, and a finite pose behind the gel looking at it.
fn validate_camera(src: &str, name: &str, cam: &CameraSpec, c: &CamerasSpec) -> Result<()> {
    let f = |k: &str| format!("cameras.{name}.{k}");
    positive(src, &f("fx"), cam.fx)?;
    positive(src, &f("fy"), cam.fy)?;
    in_range(src, &f("cx"), cam.cx, -0.5, f64::from(c.image_width) - 0.5)?;
    in_range(src, &f("cy"), cam.cy, -0.5, f64::from(c.image_height) - 0.5)?;
    if !matches!(cam.distortion.len(), 0 | 4 | 5 | 8 | 12) {
        return Err(field_err(
            src,
            &f("distortion"),
            "0, 4, 5, 8 or 12 OpenCV coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]])",
            format!("{} values", cam.distortion.len()),
        ));
    }
    if let Some(v) = cam.distortion.iter().find(|v| !v.is_finite() || v.abs() > 10.0) {
        return Err(field_err(
            src,
            &f("distortion"),
            "finite coefficients of magnitude <= 10",
            v,
        ));
    }
    for (k, v) in cam.position_mm.iter().chain(&cam.look_at_mm).enumerate() {
        if !v.is_finite() {
            let key = if k < 3 { "position_mm" } else { "look_at_mm" };
            return Err(field_err(src, &f(key), "finite coordinates", v));
        }
    }
    if cam.position_mm[2] >= 0.0 {
        return Err(field_err(
            src,
            &f("position_mm"),
            "a camera behind the gel (z < 0 in the sensor frame)",
            format!("{:?}", cam.position_mm),
        ));
    }
    let dir = Vector3::from(cam.look_at_mm) - Vector3::from(cam.position_mm);
    if dir.z <= 0.2 * dir.norm() {
        return Err(field_err(
            src,
            &f("look_at_mm"),
            "a point in front of the camera, towards the gel (+z)",
            format!("{:?}", cam.look_at_mm),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_file_is_valid_and_all_markers_are_seen_at_rest() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../calib/reference-sensor.json");
        let spec = SensorSpec::load(&path).unwrap();
        assert_eq!(spec, SensorSpec::reference());
        assert_eq!(spec.grid_shape().count(), 529);
        let s = spec.build().unwrap();
        assert!(s.all_markers_visible_at_rest(5.0));
        let pitch = s.pitch_px();
        assert!((15.0..=25.0).contains(&pitch), "pitch {pitch} px");
        // Camera y is the sensor's y: rows grow downwards in the left image.
        let a = s
            .rig
            .left
            .project(&(s.left_from_sensor * Point3::new(0.0, 0.0, 0.0)))
            .unwrap();
        let b = s
            .rig
            .left
            .project(&(s.left_from_sensor * Point3::new(0.0, 1.0, 0.0)))
            .unwrap();
        assert!(b.y > a.y + 10.0);
    }

    /// A file written before the gel had a modulus and a Poisson ratio (and with the factors of
    /// the earlier response, `shear_compliance` and `spreading`) reads as the reference gel.
    #[test]
    fn older_gel_fields_read_as_the_reference_layer() {
        let reference = SensorSpec::reference();
        assert_eq!(reference.gel.modulus_kpa, REFERENCE_MODULUS_KPA);
        assert_eq!(reference.gel.poisson, REFERENCE_POISSON);
        let mut value = serde_json::to_value(&reference).unwrap();
        let gel = value["gel"].as_object_mut().unwrap();
        gel.remove("modulus_kpa");
        gel.remove("poisson");
        gel.insert("shear_compliance".into(), 1.33.into());
        gel.insert("spreading".into(), 0.15.into());
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("old.json");
        std::fs::write(&f, value.to_string()).unwrap();
        let old = SensorSpec::load(&f).unwrap();
        assert_eq!(old, reference);
        // Written back, the file holds the layer's facts and not the obsolete factors.
        let text = serde_json::to_string(&old).unwrap();
        assert!(
            text.contains("\"modulus_kpa\":150.0") && !text.contains("spreading"),
            "{text}"
        );
        // Unknown fields of the gel are still refused.
        let mut value = serde_json::to_value(&reference).unwrap();
        value["gel"]["modulus"] = 1.0.into();
        std::fs::write(&f, value.to_string()).unwrap();
        let e = SensorSpec::load(&f).unwrap_err().to_string();
        assert!(e.contains("old.json") && e.contains("modulus"), "{e}");
    }

    #[test]
    fn bad_fields_are_named() {
        let mut spec = SensorSpec::reference();
        spec.grid.pitch_mm = -1.0;
        let e = spec.validate("x.json").unwrap_err().to_string();
        assert!(
            e.contains("x.json") && e.contains("grid.pitch_mm") && e.contains("-1"),
            "{e}"
        );
        let mut spec = SensorSpec::reference();
        spec.cameras.right.distortion = vec![0.0; 3];
        let e = spec.validate("x.json").unwrap_err().to_string();
        assert!(
            e.contains("cameras.right.distortion") && e.contains("3 values"),
            "{e}"
        );
        let mut spec = SensorSpec::reference();
        spec.cameras.left.position_mm[2] = 5.0;
        let e = spec.validate("x.json").unwrap_err().to_string();
        assert!(e.contains("cameras.left.position_mm"), "{e}");
        for (modulus, poisson, field, found) in [
            (0.0, 0.45, "gel.modulus_kpa", "0"),
            (f64::INFINITY, 0.45, "gel.modulus_kpa", "inf"),
            (150.0, 0.5, "gel.poisson", "0.5"),
            (150.0, -0.1, "gel.poisson", "-0.1"),
            (150.0, f64::NAN, "gel.poisson", "NaN"),
        ] {
            let mut spec = SensorSpec::reference();
            spec.gel.modulus_kpa = modulus;
            spec.gel.poisson = poisson;
            let e = spec.validate("x.json").unwrap_err().to_string();
            assert!(
                e.contains("x.json") && e.contains(field) && e.contains(found),
                "{e}"
            );
            if field == "gel.poisson" {
                assert!(e.contains("[0, 0.5)"), "{e}");
            }
        }

        let dir = std::env::temp_dir().join(format!("gs-sensor-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("bad.json");
        std::fs::write(&f, r#"{"name": "x", "grid": {"rows": 3}}"#).unwrap();
        let e = SensorSpec::load(&f).unwrap_err().to_string();
        assert!(e.contains("bad.json") && e.contains("cols"), "{e}");
        std::fs::write(&f, "{\"name\": \"x\", \"gird\": 1}").unwrap();
        let e = SensorSpec::load(&f).unwrap_err().to_string();
        assert!(e.contains("gird"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
