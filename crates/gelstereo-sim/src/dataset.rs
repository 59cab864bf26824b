//! Recordings and datasets on disk (the layout of docs/design.md):
//!
//! ```text
//! OUT/dataset.json
//! OUT/{train,val,test}/exp_NNNN/left/NNNNNN.png, right/NNNNNN.png, markers.csv, frames.csv,
//!                               calib.yaml, left.cameramodel, right.cameramodel, meta.json
//! ```
//! Splits are 6:2:2 by experiment, deterministic from the seed. Every frame is seeded from
//! (seed, experiment, frame), so the output does not depend on how rayon schedules the work.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use gelstereo_core::table::{FRAME_COLUMNS, MARKER_COLUMNS};
use gelstereo_core::{FrameSummary, MarkerRecord, Point2};
use nalgebra::Point3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::GENERATOR_VERSION;
use crate::appearance::Appearance;
use crate::appearance::random_housing;
use crate::error::{Error, Result, io_err};
use crate::indenter::{Indenter, SHAPES};
use crate::motion::{MotionKind, Script};
use crate::physics::{Layer, SurfaceGrid, deform};
use crate::render::{MarkerTruth, Ridges, StereoOptics, ViewJob, encode_png, marker_truth, render_view};
use crate::variant::{random_gelsight_mini_like, random_variant, random_wide_variant};
use gelstereo_sensor::{Sensor, SensorSpec};

/// How much a dataset varies from the reference sensor's look and geometry.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Randomization {
    /// The sensor file exactly, with its reference look.
    Off,
    /// The sensor file's geometry, random looks (colours, polarity, lighting, marker size and
    /// contrast, blur, noise, vignetting, JPEG, dust).
    Appearance,
    /// Random looks, 30 % of the experiments on random sensor variants (grids 8-30 per side,
    /// 320x240 to 1280x720, other pitches and dot sizes) and 10 % on GelSight-Mini-like sensors
    /// with GelSight-like looks.
    Full,
    /// Wider than `full` (the sensors users have): 55 % of the experiments on
    /// [`crate::variant::random_wide_variant`] (pitch 8-100 px, images up to 1920x1080, square,
    /// hexagonal and irregular lattices, round and trapezoidal membranes in a housing, touching
    /// dots), 10 % GelSight-Mini-like, 35 % the sensor file's; looks from
    /// [`Appearance::random_wide`] (hue-only markers, scan lines, banding, moire, fingerprints,
    /// Newton rings, glints on the dots). `full` is kept as it was so that its datasets stay
    /// reproducible byte for byte.
    Wide,
    /// `wide`'s sensors and looks under flat-faced indenters only (flat punch, hexagon, box),
    /// pressed up to 1.5 x deeper into a nearly incompressible gel (Poisson ratio 0.47-0.499): the
    /// layer squeezed out from under the rims crowds the dots around them (docs/sim.md).
    Rims,
}

impl std::str::FromStr for Split {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "train" => Ok(Self::Train),
            "val" => Ok(Self::Val),
            "test" => Ok(Self::Test),
            _ => Err(Error::Parameter {
                name: "split",
                value: s.to_owned(),
                expected: "train, val or test".into(),
            }),
        }
    }
}

impl std::str::FromStr for Randomization {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "off" => Ok(Self::Off),
            "appearance" => Ok(Self::Appearance),
            "full" => Ok(Self::Full),
            "wide" => Ok(Self::Wide),
            "rims" => Ok(Self::Rims),
            _ => Err(Error::Parameter {
                name: "randomization",
                value: s.to_owned(),
                expected: "off, appearance, full, wide or rims".into(),
            }),
        }
    }
}

/// What to generate.
#[derive(Debug, Clone)]
pub struct DatasetConfig {
    /// Number of experiments (recordings), >= 1.
    pub experiments: u32,
    /// Frames per experiment, >= 2 (frame 0 is the no-contact reference).
    pub frames_per_experiment: u32,
    /// Master seed.
    pub seed: u64,
    /// The sensor.
    pub sensor: SensorSpec,
    /// Domain randomisation level.
    pub randomization: Randomization,
    /// Write only this split's experiments (the same bytes as in the whole dataset); all when
    /// `None`.
    pub only_split: Option<Split>,
    /// Every experiment uses this indenter shape (one of [`SHAPES`]) instead of cycling through
    /// them; its size is still drawn.
    pub indenter: Option<String>,
    /// Every experiment makes this motion instead of a drawn one.
    pub motion: Option<MotionKind>,
}

impl DatasetConfig {
    /// The reference sensor, `experiments` x `frames`, seed `seed`, full randomisation.
    pub fn new(experiments: u32, frames_per_experiment: u32, seed: u64) -> Self {
        Self {
            experiments,
            frames_per_experiment,
            seed,
            sensor: SensorSpec::reference(),
            randomization: Randomization::Full,
            only_split: None,
            indenter: None,
            motion: None,
        }
    }

    /// Checks the counts.
    pub fn validate(&self) -> Result<()> {
        if !(1..=100_000).contains(&self.experiments) {
            return Err(Error::Parameter {
                name: "experiments",
                value: self.experiments.to_string(),
                expected: "1 to 100000".into(),
            });
        }
        if !(2..=100_000).contains(&self.frames_per_experiment) {
            return Err(Error::Parameter {
                name: "frames_per_experiment",
                value: self.frames_per_experiment.to_string(),
                expected: "2 to 100000 (frame 0 is the no-contact reference)".into(),
            });
        }
        if let Some(name) = &self.indenter
            && !SHAPES.contains(&name.as_str())
        {
            return Err(Error::Parameter {
                name: "indenter",
                value: name.clone(),
                expected: format!("one of {}", SHAPES.join(", ")),
            });
        }
        Ok(self.sensor.validate("sensor")?)
    }
}

/// Which part of the dataset an experiment belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    /// Training (60 %).
    Train,
    /// Validation (20 %).
    Val,
    /// Test (20 %).
    Test,
}

impl Split {
    /// Folder name.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Train => "train",
            Self::Val => "val",
            Self::Test => "test",
        }
    }
}

/// Everything that defines one experiment; it alone determines the recording's bytes.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Experiment {
    /// Index in the dataset (the `NNNN` of `exp_NNNN`).
    pub index: u32,
    /// Its split.
    pub split: Split,
    /// Seed of this experiment (from the dataset seed and the index).
    pub seed: u64,
    /// The sensor it is recorded with.
    pub sensor: SensorSpec,
    /// The look.
    pub appearance: Appearance,
    /// The motion.
    pub script: Script,
    /// Its families ([`families`]; tagged by the `wide` randomisation only).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub families: Vec<String>,
}

impl Experiment {
    /// Folder name `exp_NNNN`.
    pub fn name(&self) -> String {
        format!("exp_{:04}", self.index)
    }

    /// Relative folder `split/exp_NNNN`.
    pub fn rel_dir(&self) -> PathBuf {
        Path::new(self.split.as_str()).join(self.name())
    }
}

fn mix(a: u64, b: u64) -> u64 {
    let mut z = a ^ b.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The experiments of a dataset, in index order, with their splits (6:2:2, shuffled by the seed).
pub fn plan(config: &DatasetConfig) -> Result<Vec<Experiment>> {
    config.validate()?;
    let n = config.experiments;
    let mut order: Vec<u32> = (0..n).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(mix(config.seed, 0x5EED));
    for i in (1..order.len()).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    let n_train = (f64::from(n) * 0.6).round() as u32;
    let n_val = (f64::from(n) * 0.2).round() as u32;
    let mut split = vec![Split::Test; n as usize];
    for (rank, &e) in order.iter().enumerate() {
        let rank = rank as u32;
        split[e as usize] = if rank < n_train {
            Split::Train
        } else if rank < n_train + n_val {
            Split::Val
        } else {
            Split::Test
        };
    }
    let shape_offset = rng.random_range(0..SHAPES.len());
    let rims = config.randomization == Randomization::Rims;
    (0..n)
        .map(|index| {
            let seed = mix(config.seed, u64::from(index) + 1);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (sensor, appearance) = match config.randomization {
                Randomization::Off => (config.sensor.clone(), Appearance::reference()),
                Randomization::Appearance => (config.sensor.clone(), Appearance::random(&mut rng)),
                Randomization::Full => match rng.random_range(0..10) {
                    0 => (
                        random_gelsight_mini_like(&mut rng),
                        Appearance::random_gelsight_like(&mut rng),
                    ),
                    1..=3 => (
                        random_variant(&config.sensor, &mut rng),
                        Appearance::random(&mut rng),
                    ),
                    _ => (config.sensor.clone(), Appearance::random(&mut rng)),
                },
                Randomization::Wide => wide_look(&config.sensor, &mut rng),
                Randomization::Rims => {
                    let (mut sensor, appearance) = wide_look(&config.sensor, &mut rng);
                    sensor.gel.poisson = rng.random_range(RIM_POISSON);
                    (sensor, appearance)
                }
            };
            let ref_width = 22.0 * 0.8;
            let width = f64::from(sensor.grid.rows.min(sensor.grid.cols) - 1) * sensor.grid.pitch_mm;
            // Indenters scale with the lattice, but never below what the physics grid resolves
            // (the reference sensor's 0.4 mm cells).
            let scale = (width / ref_width)
                .max(sensor.gel.grid_spacing_mm / 0.4)
                .clamp(0.3, 3.0);
            let shapes: &[&str] = if rims { &RIM_SHAPES } else { &SHAPES };
            let shape = config
                .indenter
                .as_deref()
                .unwrap_or(shapes[(index as usize + shape_offset) % shapes.len()]);
            let indenter = Indenter::random(shape, scale, &mut rng).unwrap_or(Indenter::Sphere {
                radius_mm: 4.0 * scale,
            });
            let mut script = Script::random(
                indenter,
                config.frames_per_experiment,
                0.3 * width,
                scale,
                config.motion,
                &mut rng,
            );
            if rims {
                script.max_depth_mm *= rng.random_range(1.0..RIM_DEPTH_FACTOR);
            }
            let mut experiment = Experiment {
                index,
                split: split[index as usize],
                seed,
                sensor,
                appearance,
                script,
                families: Vec::new(),
            };
            if matches!(config.randomization, Randomization::Wide | Randomization::Rims) {
                let pitch_px = experiment.sensor.build()?.pitch_px();
                experiment.families = families(&experiment, pitch_px);
            }
            Ok(experiment)
        })
        .collect()
}

/// The flat-faced indenters of the `rims` randomisation: their rims squeeze the gel hardest.
const RIM_SHAPES: [&str; 3] = ["flat_cylinder", "hexagon", "prism"];
/// Poisson ratios of the `rims` randomisation's gels: nearly incompressible, so that the layer
/// squeezed under a flat face bulges out past its rim the most a bonded layer can.
pub const RIM_POISSON: std::ops::Range<f64> = 0.47..0.499;
/// Press depths of the `rims` randomisation: up to this many times the shape's usual range.
const RIM_DEPTH_FACTOR: f64 = 1.5;

/// Sensor and look of one experiment of the `wide` randomisation.
fn wide_look(base: &SensorSpec, rng: &mut ChaCha8Rng) -> (SensorSpec, Appearance) {
    match rng.random_range(0..20) {
        0 | 1 => {
            let sensor = random_gelsight_mini_like(rng);
            let mut app = Appearance::random_wide(rng);
            if rng.random_bool(0.5) {
                let gs = Appearance::random_gelsight_like(rng);
                app = Appearance {
                    textures: app.textures,
                    newton_rings: app.newton_rings,
                    glint: app.glint,
                    ..gs
                };
            }
            (sensor, app)
        }
        2..=12 => {
            let sensor = random_wide_variant(base, rng);
            let mut app = Appearance::random_wide(rng);
            if let Some(m) = &sensor.membrane {
                app.housing = Some(random_housing(rng, m, sensor.grid.pitch_mm));
            }
            (sensor, app)
        }
        _ => (base.clone(), Appearance::random_wide(rng)),
    }
}

/// The families an experiment belongs to, for holding whole families out of training and
/// reporting per family: `marker:dark|light|hue`, `lattice:square|hexagonal|irregular`,
/// `membrane:none|circle|trapezoid`, `res:WxH`, `pitch:<16|16-40|>40` (px, left view at rest),
/// and one `texture:...` per texture (`none`, `scanlines`, `banding`, `moire`, `fingerprint`,
/// `newton_rings`, `glint`).
pub fn families(experiment: &Experiment, pitch_px: f64) -> Vec<String> {
    use crate::appearance::{Texture, luminance};
    use gelstereo_sensor::{Lattice, Membrane};
    let app = &experiment.appearance;
    let sensor = &experiment.sensor;
    let ratio = luminance(app.marker_color) / luminance(app.background).max(1.0);
    let marker = if ratio < 0.6 {
        "dark"
    } else if ratio > 1.7 {
        "light"
    } else {
        "hue"
    };
    let lattice = match sensor.grid.lattice {
        Lattice::Square => "square",
        Lattice::Hexagonal => "hexagonal",
        Lattice::Irregular { .. } => "irregular",
    };
    let membrane = match sensor.membrane {
        None => "none",
        Some(Membrane::Circle { .. }) => "circle",
        Some(Membrane::Trapezoid { .. }) => "trapezoid",
    };
    let pitch = if pitch_px < 16.0 {
        "<16"
    } else if pitch_px <= 40.0 {
        "16-40"
    } else {
        ">40"
    };
    let mut out = vec![
        format!("marker:{marker}"),
        format!("lattice:{lattice}"),
        format!("membrane:{membrane}"),
        format!(
            "res:{}x{}",
            sensor.cameras.image_width, sensor.cameras.image_height
        ),
        format!("pitch:{pitch}"),
    ];
    for t in &app.textures {
        out.push(
            match t {
                Texture::Bands { period_px, .. } if *period_px < 8.0 => "texture:scanlines",
                Texture::Bands { .. } => "texture:banding",
                Texture::Moire { .. } => "texture:moire",
                Texture::Fingerprint { .. } => "texture:fingerprint",
            }
            .to_owned(),
        );
    }
    if app.newton_rings.is_some() {
        out.push("texture:newton_rings".into());
    }
    if app.glint.is_some() {
        out.push("texture:glint".into());
    }
    if !out.iter().any(|f| f.starts_with("texture:")) {
        out.push("texture:none".into());
    }
    out.dedup();
    out
}

/// One frame's ground truth and images.
pub struct Frame {
    /// Marker ground truth.
    pub markers: Vec<MarkerTruth>,
    /// The frame summary.
    pub summary: FrameSummary,
    /// Left and right BGR images.
    pub images: [opencv::core::Mat; 2],
}

/// Everything needed to simulate the frames of one experiment.
pub struct Simulator {
    /// The experiment.
    pub experiment: Experiment,
    /// Its sensor, built.
    pub sensor: Sensor,
    optics: Arc<StereoOptics>,
    layer: Layer,
    rest_left: Vec<Point3<f64>>,
}

impl Simulator {
    /// Prepares an experiment (camera lookups, the layer's influence operator).
    pub fn new(experiment: Experiment) -> Result<Self> {
        Self::with_optics(experiment, None)
    }

    /// Like [`Simulator::new`], reusing camera lookups already built for the same sensor.
    pub fn with_optics(experiment: Experiment, optics: Option<Arc<StereoOptics>>) -> Result<Self> {
        let sensor = experiment.sensor.build()?;
        let optics = optics.unwrap_or_else(|| Arc::new(StereoOptics::new(&sensor)));
        let grid = SurfaceGrid::new(&sensor.spec.gel);
        let layer = Layer::new(&sensor.spec.gel, grid)?;
        let rest_left = sensor
            .spec
            .grid_shape()
            .indices()
            .map(|i| {
                let [x, y] = sensor.spec.marker_rest_mm(i.row, i.col);
                sensor.left_from_sensor * Point3::new(x, y, 0.0)
            })
            .collect();
        Ok(Self {
            experiment,
            sensor,
            optics,
            layer,
            rest_left,
        })
    }

    /// Simulates frame `frame`: deformation, ground truth, both images.
    pub fn frame(&self, frame: u32) -> Result<Frame> {
        let exp = &self.experiment;
        let pose = exp.script.pose(frame);
        let def = deform(&self.sensor.spec.gel, &self.layer, &exp.script, &pose);
        let markers = marker_truth(&self.sensor, &self.optics, &def);
        let seed = mix(exp.seed, u64::from(frame) + 0x1000);
        let radius = 0.5 * self.sensor.spec.grid.dot_diameter_mm * exp.appearance.dot_scale;
        let radius = radius.min(0.42 * self.sensor.spec.grid.pitch_mm);
        let lattice_half = 0.5
            * f64::from(self.sensor.spec.grid.cols.max(self.sensor.spec.grid.rows) - 1)
            * self.sensor.spec.grid.pitch_mm;
        // The exposure is centred on the frame's time, so a moving marker's truth is the middle of
        // its smear: the one place an image shows it at, whichever way it moved.
        let exposure_start = if exp.appearance.motion_blur > 0.0 && frame > 0 {
            let before = exp
                .script
                .pose_at(f64::from(frame) - 0.5 * exp.appearance.motion_blur);
            let def0 = deform(&self.sensor.spec.gel, &self.layer, &exp.script, &before);
            Some(marker_truth(&self.sensor, &self.optics, &def0))
        } else {
            None
        };
        let ridges = match (&exp.script.indenter, def.indenter_frame) {
            (Indenter::Fingertip { rx_mm, ry_mm }, Some([x, y, a])) => Some(Ridges {
                centre: [x as f32, y as f32],
                angle: a as f32,
                aspect: (ry_mm / rx_mm) as f32,
                period_mm: 0.3 + 0.15 * ((exp.seed >> 11) % 1000) as f32 / 1000.0,
            }),
            _ => None,
        };
        let render = |view: usize| {
            render_view(&ViewJob {
                optics: if view == 0 {
                    &self.optics.left
                } else {
                    &self.optics.right
                },
                view,
                def: &def,
                markers: &markers,
                appearance: &exp.appearance,
                dot_radius_mm: radius,
                lattice_half_mm: lattice_half,
                seed: mix(seed, view as u64),
                exposure_start: exposure_start.as_deref(),
                ridges,
                membrane: self.sensor.spec.membrane,
            })
        };
        let images = [render(0)?, render(1)?];
        let centroid = def.centroid_mm.map(|c| {
            let p = self.sensor.left_from_sensor * Point3::new(c[0], c[1], c[2]);
            [p.x, p.y]
        });
        let summary = FrameSummary {
            frame,
            contact: def.contact_area_mm2 > 0.0,
            contact_area_mm2: Some(def.contact_area_mm2),
            max_depth_mm: Some(def.max_depth_mm),
            centroid_mm: centroid,
            slip: def.slip,
            force_n: Some(def.force_n),
            shear_n: Some(def.shear_n),
            torque_nmm: Some(def.torque_nmm),
            measured: true,
        };
        Ok(Frame {
            markers,
            summary,
            images,
        })
    }

    /// The rows of `markers.csv` for one frame (with the ground-truth columns), appended to `out`.
    pub fn marker_rows(&self, frame: u32, markers: &[MarkerTruth], out: &mut String) {
        let cams = [&self.sensor.rig.left, &self.sensor.rig.right];
        for (k, m) in markers.iter().enumerate() {
            let p = self.sensor.left_from_sensor * m.position_sensor;
            let rest = self.rest_left[k];
            let rec = MarkerRecord {
                frame,
                index: m.index,
                left_px: m.px[0],
                right_px: m.px[1],
                position_mm: Some([p.x, p.y, p.z]),
                displacement_mm: Some([p.x - rest.x, p.y - rest.y, p.z - rest.z]),
                pressure_kpa: Some(m.pressure_kpa),
                in_contact: Some(m.in_contact),
                slipping: Some(m.slipping),
                ..Default::default()
            };
            rec.write_csv(out);
            let vis = |v: usize| u8::from(m.printed && m.px[v].is_some_and(|q: Point2| cams[v].contains(q)));
            let _ = writeln!(out, ",{},{}", vis(0), vis(1));
        }
    }
}

/// Header of `markers.csv`: the docs/design.md columns (with the truth's `in_contact`) and the
/// simulator's visibility flags.
pub fn markers_header() -> String {
    format!("{},visible_left,visible_right\n", MARKER_COLUMNS.join(","))
}

/// Writes one recording into `dir` (which must exist); `progress` is called once per frame.
pub fn write_recording(dir: &Path, experiment: &Experiment, progress: &(dyn Fn() + Sync)) -> Result<()> {
    write_recording_with(dir, experiment, None, progress)
}

fn write_recording_with(
    dir: &Path,
    experiment: &Experiment,
    optics: Option<Arc<StereoOptics>>,
    progress: &(dyn Fn() + Sync),
) -> Result<()> {
    let sim = Simulator::with_optics(experiment.clone(), optics)?;
    for v in ["left", "right"] {
        std::fs::create_dir_all(dir.join(v)).map_err(io_err(dir.join(v)))?;
    }
    let frames = experiment.script.frames;
    let rows: Vec<(String, FrameSummary)> = (0..frames)
        .into_par_iter()
        .map(|f| -> Result<(String, FrameSummary)> {
            if gelstereo_core::interrupt::requested() {
                return Err(Error::Interrupted);
            }
            let fr = sim.frame(f)?;
            for (v, name) in ["left", "right"].iter().enumerate() {
                let png = encode_png(&fr.images[v])?;
                let path = dir.join(name).join(format!("{f:06}.png"));
                std::fs::write(&path, png).map_err(io_err(path))?;
            }
            let mut text = String::with_capacity(fr.markers.len() * 120);
            sim.marker_rows(f, &fr.markers, &mut text);
            progress();
            Ok((text, fr.summary))
        })
        .collect::<Result<_>>()?;
    let mut markers = markers_header();
    let mut frames_csv = FRAME_COLUMNS.join(",");
    frames_csv.push('\n');
    for (text, summary) in &rows {
        markers.push_str(text);
        summary.write_csv(&mut frames_csv);
        frames_csv.push('\n');
    }
    let write = |name: &str, text: &str| std::fs::write(dir.join(name), text).map_err(io_err(dir.join(name)));
    write("markers.csv", &markers)?;
    write("frames.csv", &frames_csv)?;
    crate::calibration::write_calibration(&sim.sensor.rig, dir)?;
    let meta = serde_json::json!({
        "generator": GENERATOR_VERSION,
        "experiment": experiment.name(),
        "split": experiment.split,
        "seed": experiment.seed,
        "frames": frames,
        "image_width": experiment.sensor.cameras.image_width,
        "image_height": experiment.sensor.cameras.image_height,
        "grid": { "rows": experiment.sensor.grid.rows, "cols": experiment.sensor.grid.cols },
        "indenter": experiment.script.indenter,
        "motion": experiment.script,
        "appearance": experiment.appearance,
        "sensor": experiment.sensor,
    });
    let mut meta = meta;
    if !experiment.families.is_empty() {
        // Only the `wide` randomisation tags families: older datasets' meta.json stay unchanged.
        meta["families"] = serde_json::json!(experiment.families);
    }
    write("meta.json", &pretty(&meta))?;
    Ok(())
}

fn pretty(v: &serde_json::Value) -> String {
    let mut s = serde_json::to_string_pretty(v).unwrap_or_else(|_| v.to_string());
    s.push('\n');
    s
}

/// What a dataset run produced.
#[derive(Debug, Clone, Serialize)]
pub struct DatasetSummary {
    /// Experiments per split (train, val, test).
    pub experiments: [u32; 3],
    /// Stereo frames in all.
    pub frames: u64,
}

/// What gelstereo-sim writes, as a tree: a dataset is `dataset.json` and `SPLIT/exp_NNNN/` folders
/// (each with `left/` and `right/` frames and the experiment's tables, calibration and meta.json); a
/// checkerboard set is `poses.json`, `left/`, `right/`, its corners and calibration. The first file
/// is the manifest. `--force` replaces only a folder whose manifest gelstereo-sim wrote and whose
/// every entry, at every depth, is one of these: a file of the user's anywhere inside is kept.
#[derive(Clone, Copy)]
enum OutputLayout {
    Dataset,
    Checkerboard,
}

/// The files of one experiment folder beside its `left/` and `right/` frames.
const EXPERIMENT_FILES: [&str; 6] = [
    "markers.csv",
    "frames.csv",
    "meta.json",
    "calib.yaml",
    "left.cameramodel",
    "right.cameramodel",
];

impl OutputLayout {
    const ALL: [OutputLayout; 2] = [OutputLayout::Dataset, OutputLayout::Checkerboard];

    fn manifest(self) -> &'static str {
        match self {
            OutputLayout::Dataset => "dataset.json",
            OutputLayout::Checkerboard => "poses.json",
        }
    }

    /// Whether an entry at `rel` (path components below the output folder) is one this layout
    /// writes; `is_dir` says whether the entry is a folder.
    fn holds(self, rel: &[&str], is_dir: bool) -> bool {
        let frame = |name: &str| {
            name.strip_suffix(".png")
                .is_some_and(|n| n.len() == 6 && n.bytes().all(|b| b.is_ascii_digit()))
        };
        let view = |name: &str| name == "left" || name == "right";
        match (self, rel, is_dir) {
            (OutputLayout::Dataset, [m], false) => *m == "dataset.json",
            (OutputLayout::Dataset, [split], true) => ["train", "val", "test"].contains(split),
            (OutputLayout::Dataset, [_, exp], true) => exp
                .strip_prefix("exp_")
                .is_some_and(|n| n.len() >= 4 && n.bytes().all(|b| b.is_ascii_digit())),
            (OutputLayout::Dataset, [_, _, v], true) => view(v),
            (OutputLayout::Dataset, [_, _, f], false) => EXPERIMENT_FILES.contains(f),
            (OutputLayout::Dataset, [_, _, _, f], false) => frame(f),
            (OutputLayout::Checkerboard, [v], true) => view(v),
            (OutputLayout::Checkerboard, [f], false) => [
                "poses.json",
                "corners.csv",
                "calib.yaml",
                "left.cameramodel",
                "right.cameramodel",
            ]
            .contains(f),
            (OutputLayout::Checkerboard, [_, f], false) => frame(f),
            _ => false,
        }
    }
}

/// Prepares an output folder: refuses a non-empty one unless `force`, and with `force` refuses
/// anything gelstereo-sim did not write (a regular file, a link, the current folder, a folder
/// without a manifest or with files of its own); removes temporary folders left by earlier runs
/// that were killed. Returns the temporary sibling to write into.
pub fn begin_output(out: &Path, force: bool) -> Result<PendingOutput> {
    let not_ours = |why: &str| Error::OutputNotOurs {
        path: out.to_owned(),
        why: why.to_owned(),
    };
    // `.` or `dir/..` name a folder through its parent: resolve them to a real name.
    let out = match std::fs::symlink_metadata(out) {
        Ok(meta) if meta.file_type().is_symlink() => return Err(not_ours("a symbolic link")),
        Ok(meta) if !meta.is_dir() => return Err(not_ours("a file, not a folder")),
        Ok(_) => {
            let resolved = std::fs::canonicalize(out).map_err(io_err(out))?;
            if let Ok(cwd) = std::env::current_dir()
                && cwd.starts_with(&resolved)
            {
                return Err(not_ours("the current folder or one of its parents"));
            }
            if std::fs::read_dir(&resolved)
                .map_err(io_err(&resolved))?
                .next()
                .is_some()
            {
                if !force {
                    return Err(Error::OutputNotEmpty { path: out.to_owned() });
                }
                check_written_by_us(&resolved).map_err(|why| not_ours(&why))?;
            }
            resolved
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => out.to_owned(),
        Err(e) => {
            return Err(Error::Io {
                path: out.to_owned(),
                error: e,
            });
        }
    };
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| not_ours("not a folder with a name"))?;
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_owned(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(io_err(&parent))?;
    remove_stale_partials(&parent, &name);
    let tmp = parent.join(format!(".{name}.partial-{}", std::process::id()));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(io_err(&tmp))?;
    }
    std::fs::create_dir(&tmp).map_err(io_err(&tmp))?;
    Ok(PendingOutput { tmp, out })
}

/// An output folder being written: everything goes into [`PendingOutput::tmp`], which
/// [`PendingOutput::finish`] moves onto the output; dropped unfinished (an error, an interruption),
/// the temporary folder is removed.
#[derive(Debug)]
pub struct PendingOutput {
    /// The temporary sibling folder to write into.
    pub tmp: PathBuf,
    out: PathBuf,
}

impl PendingOutput {
    /// Moves the finished temporary folder onto the output (replacing it when it exists:
    /// [`begin_output`] checked that it is a folder gelstereo-sim wrote).
    pub fn finish(self) -> Result<()> {
        if self.out.is_dir() {
            std::fs::remove_dir_all(&self.out).map_err(io_err(&self.out))?;
        }
        std::fs::rename(&self.tmp, &self.out).map_err(io_err(&self.out))
    }
}

impl Drop for PendingOutput {
    fn drop(&mut self) {
        // After `finish` the temporary folder is gone and this does nothing.
        let _ = std::fs::remove_dir_all(&self.tmp);
    }
}

/// Whether `dir` holds a gelstereo-sim manifest and, at every depth, only the entries of its
/// layout; `Err(why)` naming the first entry that is not.
fn check_written_by_us(dir: &Path) -> std::result::Result<(), String> {
    for layout in OutputLayout::ALL {
        let manifest = dir.join(layout.manifest());
        let ours = std::fs::read_to_string(&manifest)
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| {
                v.get("generator")?
                    .as_str()
                    .map(|g| g.starts_with("gelstereo-sim "))
            })
            .unwrap_or(false);
        if ours {
            return check_tree(dir, &mut Vec::new(), layout);
        }
    }
    Err("holds no dataset.json or poses.json written by gelstereo-sim".to_owned())
}

/// Walks the folder at `dir` (`rel` below the output folder) and refuses the first entry the
/// layout does not write: a link, a special file, or a file or folder of another name or depth.
fn check_tree(dir: &Path, rel: &mut Vec<String>, layout: OutputLayout) -> std::result::Result<(), String> {
    let entries = std::fs::read_dir(dir).map_err(|e| format!("cannot be read ({e})"))?;
    for entry in entries {
        let entry = entry.map_err(|e| format!("cannot be read ({e})"))?;
        rel.push(entry.file_name().to_string_lossy().into_owned());
        let kind = entry.file_type().map_err(|e| format!("cannot be read ({e})"))?;
        let parts: Vec<&str> = rel.iter().map(String::as_str).collect();
        let written = (kind.is_dir() || kind.is_file()) && layout.holds(&parts, kind.is_dir());
        if !written {
            return Err(format!(
                "holds '{}', which gelstereo-sim does not write",
                rel.join("/")
            ));
        }
        if kind.is_dir() {
            check_tree(&entry.path(), rel, layout)?;
        }
        rel.pop();
    }
    Ok(())
}

/// Removes `.NAME.partial-PID` folders in `parent` whose process no longer runs (left by a run that
/// was killed). Only on Linux, where a process's liveness is visible in /proc.
fn remove_stale_partials(parent: &Path, name: &str) {
    if !cfg!(target_os = "linux") {
        return;
    }
    let prefix = format!(".{name}.partial-");
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    for entry in entries.flatten() {
        let file_name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = file_name
            .strip_prefix(&prefix)
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

/// Writes a whole dataset to `out` (see the module docs). Refuses a non-empty `out` unless
/// `force`; writes into a temporary sibling and renames it at the end, so an interrupted run never
/// leaves a complete-looking dataset. `progress` is called once per stereo frame.
pub fn write_dataset(
    out: &Path,
    config: &DatasetConfig,
    force: bool,
    progress: &(dyn Fn() + Sync),
) -> Result<DatasetSummary> {
    let mut experiments = plan(config)?;
    if let Some(split) = config.only_split {
        experiments.retain(|e| e.split == split);
    }
    let pending = begin_output(out, force)?;
    let summary = write_into(&pending.tmp, config, &experiments, progress)?;
    pending.finish()?;
    Ok(summary)
}

fn write_into(
    tmp: &Path,
    config: &DatasetConfig,
    experiments: &[Experiment],
    progress: &(dyn Fn() + Sync),
) -> Result<DatasetSummary> {
    // Experiments on the dataset's own sensor share its camera lookups.
    let shared = Arc::new(StereoOptics::new(&config.sensor.build()?));
    experiments.par_iter().try_for_each(|e| {
        let dir = tmp.join(e.rel_dir());
        std::fs::create_dir_all(&dir).map_err(io_err(&dir))?;
        let optics = (e.sensor == config.sensor).then(|| Arc::clone(&shared));
        write_recording_with(&dir, e, optics, progress)
    })?;
    let mut counts = [0u32; 3];
    let mut frames = [0u64; 3];
    for e in experiments {
        let k = e.split as usize;
        counts[k] += 1;
        frames[k] += u64::from(e.script.frames);
    }
    let list: Vec<_> = experiments
        .iter()
        .map(|e| {
            serde_json::json!({
                "name": e.name(),
                "path": e.rel_dir().to_string_lossy(),
                "split": e.split,
                "seed": e.seed,
                "frames": e.script.frames,
                "indenter": e.script.indenter.name(),
                "motion": e.script.kind,
                "sensor": e.sensor.name,
                "image_width": e.sensor.cameras.image_width,
                "image_height": e.sensor.cameras.image_height,
                "grid_rows": e.sensor.grid.rows,
                "grid_cols": e.sensor.grid.cols,
            })
        })
        .collect();
    let json = serde_json::json!({
        "generator": GENERATOR_VERSION,
        "seed": config.seed,
        "randomization": config.randomization,
        "frames_per_experiment": config.frames_per_experiment,
        "sensor": config.sensor,
        "counts": {
            "train": { "experiments": counts[0], "frames": frames[0] },
            "val": { "experiments": counts[1], "frames": frames[1] },
            "test": { "experiments": counts[2], "frames": frames[2] },
        },
        "experiments": list,
    });
    let path = tmp.join("dataset.json");
    std::fs::write(&path, pretty(&json)).map_err(io_err(&path))?;
    Ok(DatasetSummary {
        experiments: counts,
        frames: frames.iter().sum(),
    })
}
