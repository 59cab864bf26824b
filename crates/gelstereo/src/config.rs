//! How a [`crate::Pipeline`] is built: [`PipelineConfig`], with the defaults of `gelstereo track`,
//! and [`PipelineConfig::for_recording`], which adds what a recording folder says about its sensor.

use std::path::{Path, PathBuf};

use gelstereo_core::GridShape;
use gelstereo_core::limits::{ECHO_CHARS, MAX_GRID_SIDE, shorten};
use gelstereo_markers::{Localizer, LocalizerConfig, Method};
use gelstereo_sensor::{RecordingMeta, SensorSpec};
use gelstereo_tracking::SessionConfig;

use crate::{Error, Result};

/// Everything a [`crate::Pipeline`] is built from. `Default` is `gelstereo track`'s defaults for a
/// mono sensor: no calibration, the shipped models, the reference sensor's 23 x 23 grid.
#[derive(Debug, Clone)]
pub struct PipelineConfig {
    /// Stereo calibration: an OpenCV YAML/XML file, a folder holding a mrcal pair, or
    /// `left.cameramodel,right.cameramodel`. Stereo frames need one; `None` for a mono sensor.
    pub calibration: Option<PathBuf>,
    /// Track the left view only (a mono sensor, or a stereo recording's left camera). A calibration
    /// then only projects a sensor description's grid, and one that cannot be loaded is ignored.
    pub mono: bool,
    /// Localization method; `None`: Marknet-MRE when its models are installed, else the blob detector.
    pub method: Option<Method>,
    /// Model paths, blob parameters and ONNX Runtime options (default: the shipped `data/models`).
    pub localizer: LocalizerConfig,
    /// The marker lattice; `None`: the sensor description's grid, else 23 x 23 (the reference sensor).
    pub grid: Option<GridShape>,
    /// A sensor description whose grid overfills the cameras' view: its lattice, projected through
    /// the calibration, places the visible markers on the sensor's own grid indices. An error building
    /// it is reported.
    pub sensor: Option<SensorSpec>,
    /// A recording's own sensor description (its `meta.json`, validated when read): used like
    /// [`Self::sensor`] when it builds, ignored when it does not.
    pub recording_sensor: Option<SensorSpec>,
    /// Tracking, contact and slip settings (gel thickness, marker pitch of a mono sensor, ...).
    pub session: SessionConfig,
    /// Frame rate for timestamps of frames given without one, Hz (30: a typical USB camera).
    pub frame_rate_hz: f64,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self {
            calibration: None,
            mono: false,
            method: None,
            localizer: crate::models::localizer_config(),
            grid: None,
            sensor: None,
            recording_sensor: None,
            session: SessionConfig::default(),
            frame_rate_hz: 30.0,
        }
    }
}

impl PipelineConfig {
    /// The defaults plus what the recording folder `dir` describes: its `calib.yaml`, and from its
    /// `meta.json` the grid, the gel's facts and the sensor description (each only when present:
    /// real recordings lack them). A malformed `meta.json` is an error naming it and the field.
    pub fn for_recording(dir: &Path) -> Result<Self> {
        let mut config = Self::default();
        config.apply_recording(dir)?;
        Ok(config)
    }

    /// Fills what [`Self::for_recording`] reads from `dir` into `self`.
    pub fn apply_recording(&mut self, dir: &Path) -> Result<()> {
        let calib = dir.join("calib.yaml");
        if calib.is_file() {
            self.calibration = Some(calib);
        }
        let Some(meta) = RecordingMeta::read(dir)? else {
            return Ok(());
        };
        self.grid = meta.grid;
        if let Some(gel) = meta.sensor.as_ref().map(|s| &s.gel) {
            let layer = &mut self.session.contact.layer;
            (layer.thickness_mm, layer.modulus_kpa, layer.poisson) =
                (gel.thickness_mm, gel.modulus_kpa, gel.poisson);
        }
        self.recording_sensor = meta.sensor;
        Ok(())
    }

    /// The method [`Self::method`] names, else Marknet-MRE when both its models exist, else blob.
    pub fn chosen_method(&self) -> Method {
        self.method.unwrap_or_else(|| {
            if self.localizer.marknet_path.is_file() && self.localizer.mre_path.is_file() {
                Method::MarknetMre
            } else {
                Method::Blob
            }
        })
    }

    /// The lattice tracked when nothing else says: [`Self::grid`], else the sensor description's.
    pub fn grid_shape(&self) -> GridShape {
        self.grid
            .or_else(|| self.sensor.as_ref().map(SensorSpec::grid_shape))
            .unwrap_or(GridShape::REFERENCE)
    }

    /// Points the localizer at the models in `dir` (`marknet.onnx`, `mre.onnx`).
    pub fn with_models(mut self, dir: &Path) -> Self {
        self.localizer.marknet_path = dir.join("marknet.onnx");
        self.localizer.mre_path = dir.join("mre.onnx");
        self
    }
}

/// The gel's facts and friction coefficient a user gives (`gelstereo track --gel-thickness-mm
/// --gel-modulus-kpa --poisson --friction`, the Python `Pipeline`'s keywords of the same names);
/// `None` keeps what the configuration holds.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GelFacts {
    /// Thickness between the contact surface and the rigid window, mm.
    pub thickness_mm: Option<f64>,
    /// Young's modulus, kPa.
    pub modulus_kpa: Option<f64>,
    /// Poisson ratio, in [0, 0.5).
    pub poisson: Option<f64>,
    /// Coulomb friction coefficient between gel and object.
    pub friction: Option<f64>,
}

impl GelFacts {
    /// These facts completed by a gel file's (`path` names it in errors): a fact given both here
    /// and in the file must agree with it.
    pub fn with_file(self, file: &crate::gel::GelFile, path: &Path) -> crate::Result<Self> {
        let agree = |given: Option<f64>, name: &str, filed: f64| -> crate::Result<Option<f64>> {
            match given {
                Some(v) if (v - filed).abs() > 1e-9 * filed.abs().max(1.0) => {
                    Err(crate::Error::Invalid(format!(
                        "{name} {v} disagrees with {} (gel.{name} {filed}): give one of them, or make them agree",
                        path.display()
                    )))
                }
                _ => Ok(Some(filed)),
            }
        };
        Ok(Self {
            thickness_mm: agree(self.thickness_mm, "thickness_mm", file.layer.thickness_mm)?,
            modulus_kpa: agree(self.modulus_kpa, "modulus_kpa", file.layer.modulus_kpa)?,
            poisson: agree(self.poisson, "poisson", file.layer.poisson)?,
            friction: match file.friction {
                Some(f) => agree(self.friction, "friction", f)?,
                None => self.friction,
            },
        })
    }
}

impl PipelineConfig {
    /// Writes the given facts into the contact settings and checks them all; an error names the
    /// fact, the range expected and the value.
    pub fn apply_gel(&mut self, facts: &GelFacts) -> crate::Result<()> {
        let contact = &mut self.session.contact;
        for (value, fact) in [
            (facts.thickness_mm, &mut contact.layer.thickness_mm),
            (facts.modulus_kpa, &mut contact.layer.modulus_kpa),
            (facts.poisson, &mut contact.layer.poisson),
            (facts.friction, &mut contact.friction),
        ] {
            if let Some(v) = value {
                *fact = v;
            }
        }
        contact.validate()?;
        Ok(())
    }
}

/// Builds the localizer of `method`; an error names the method (and, for the learned ones, where
/// the models are looked for).
pub fn localizer(method: Method, config: &LocalizerConfig) -> Result<Box<dyn Localizer + Send>> {
    gelstereo_markers::create_localizer(method, config).map_err(|e| {
        let what = match method {
            Method::Blob => format!("cannot set up method '{method}'"),
            _ => format!("cannot set up method '{method}' (models: --models DIR, default data/models)"),
        };
        Error::from(e).context(what)
    })
}

/// Parses a lattice `ROWSxCOLS` (e.g. `23x23`); `what` names the option in errors.
pub fn parse_grid(text: &str, what: &str) -> Result<GridShape> {
    let invalid = |why: &str| Error::Invalid(format!("{what} '{}': {why}", shorten(text, ECHO_CHARS)));
    let (r, c) = text
        .split_once(['x', 'X'])
        .ok_or_else(|| invalid("expected ROWSxCOLS, e.g. 23x23"))?;
    let side = |s: &str, name: &str| match s.trim().parse::<u16>() {
        Ok(n) if (2..=MAX_GRID_SIDE).contains(&n) => Ok(n),
        _ => Err(invalid(&format!(
            "{name} '{}': expected a whole number from 2 to {MAX_GRID_SIDE} (at least 2x2 markers)",
            shorten(s.trim(), ECHO_CHARS)
        ))),
    };
    Ok(GridShape {
        rows: side(r, "rows")?,
        cols: side(c, "columns")?,
    })
}

/// The folder holding the shipped `data/` and `calib/`: `GELSTEREO_HOME` when set, else the checkout
/// this library was built from, else the folder of the executable.
pub fn project_home() -> PathBuf {
    gelstereo_markers::project_home()
}
