//! The "index" stage ([`Indexing`]): on the reference frame, the grid ids of the markers (and for
//! stereo the pairing of the views) that start the tracking session: the whole lattice, or the
//! visible part of a grid that overfills the view (placed by a sensor description, else from the
//! visible top-left marker).

use gelstereo_core::{Detection, GridIndex, GridShape, ImageSize, Point2, StereoPair, TieredDetections};
use gelstereo_geometry::{StereoRig, TriangulationConfig, Triangulator};
use gelstereo_matching::{IndexingConfig, ReferenceLattice, StereoConfig, StereoLattice};
use gelstereo_sensor::SensorSpec;
use gelstereo_tracking::{MonoSession, SessionConfig, StereoSession};

use crate::pipeline::Images;
use crate::{Error, PipelineConfig, Result};

/// The "index" stage: what indexing a reference frame needs (calibration, lattice, the sensor
/// description's projected lattice, settings); [`Indexing::run`] starts the tracking session.
pub(crate) struct Indexing {
    rig: Option<StereoRig>,
    expected: Option<ExpectedLattice>,
    shape: GridShape,
    config: SessionConfig,
}

impl Indexing {
    /// Loads the calibration (a mono pipeline may do without one it cannot load) and projects the
    /// sensor description's lattice through it.
    pub(crate) fn new(config: &PipelineConfig) -> Result<Self> {
        config.session.validate()?;
        let rig = match &config.calibration {
            Some(spec) => match StereoRig::load(spec) {
                Ok(rig) => Some(rig),
                Err(_) if config.mono => None,
                Err(e) => {
                    return Err(
                        Error::from(e).context(format!("cannot load the calibration {}", spec.display()))
                    );
                }
            },
            None => None,
        };
        let shape = config.grid_shape();
        // The sensor description's lattice is projected through the calibration (a mono run of a
        // stereo recording uses its left camera); only a grid that overfills the view needs it.
        let expected = match (&config.sensor, &config.recording_sensor, &rig) {
            (Some(spec), _, Some(rig)) if spec.grid_shape() == shape => Some(expected_lattice(spec, rig)?),
            (None, Some(spec), Some(rig)) if spec.grid_shape() == shape => expected_lattice(spec, rig).ok(),
            _ => None,
        };
        Ok(Self {
            rig,
            expected,
            shape,
            config: config.session.clone(),
        })
    }

    /// The calibration, when one is loaded.
    pub(crate) fn rig(&self) -> Option<&StereoRig> {
        self.rig.as_ref()
    }

    /// The lattice given.
    pub(crate) fn shape(&self) -> GridShape {
        self.shape
    }

    /// The contact mechanics' settings the session starts with.
    pub(crate) fn contact_config(&self) -> &gelstereo_tracking::ContactConfig {
        &self.config.contact
    }

    /// Indexes the reference frame (`size`: the first frame's image size): the whole lattice, else
    /// (a grid that overfills the view) the visible part, placed by the sensor description when
    /// there is one. Returns the session and the lines to log.
    pub(crate) fn run(
        &self,
        images: &Images,
        dets: &StereoPair<TieredDetections>,
        size: Option<ImageSize>,
    ) -> Result<(Session, Vec<String>)> {
        let stereo_rig = match images {
            Images::Stereo(_) => self.rig.as_ref(),
            Images::Mono(_) => None,
        };
        match start_whole(dets, stereo_rig, self.shape, &self.config) {
            Ok(s) => Ok((s, Vec::new())),
            Err(e) if e.lattice_cut() && self.expected.as_ref().is_none_or(|x| x.overfills) => {
                let size = size.unwrap_or(ImageSize { width: 0, height: 0 });
                let cut = start_cut(
                    dets,
                    stereo_rig,
                    self.shape,
                    self.expected.as_ref(),
                    self.config.planar.pitch_mm,
                    size,
                    &self.config,
                );
                match cut {
                    Ok(Some(started)) => Ok(started),
                    // Not a cut grid: the whole-lattice error stands (the next frame is tried).
                    Ok(None) => Err(e),
                    Err(cut) => Err(cut.context(format!("{}; indexing the visible part", e.full_message()))),
                }
            }
            Err(e) => Err(e),
        }
    }
}

/// Starts a session on the whole lattice: stereo when `rig` is given, else mono on the left view.
fn start_whole(
    dets: &StereoPair<TieredDetections>,
    rig: Option<&StereoRig>,
    shape: GridShape,
    config: &SessionConfig,
) -> Result<Session> {
    match rig {
        Some(rig) => {
            let lat = StereoLattice::from_reference(
                rig,
                &dets.left.accepted,
                &dets.right.accepted,
                shape,
                StereoConfig::default(),
            )?;
            Session::stereo(rig, &lat, shape, config)
        }
        None => {
            let lat =
                ReferenceLattice::from_detections(&dets.left.accepted, shape, IndexingConfig::default())?;
            Session::mono(&lat, shape, config)
        }
    }
}

/// A running session, stereo or mono.
pub(crate) enum Session {
    Stereo(Box<StereoSession>),
    Mono(Box<MonoSession>),
}

impl Session {
    pub(crate) fn ids(&self) -> &[GridIndex] {
        match self {
            Session::Stereo(s) => s.ids(),
            Session::Mono(s) => s.tracker().ids(),
        }
    }

    pub(crate) fn shape(&self) -> GridShape {
        match self {
            Session::Stereo(s) => s.shape(),
            Session::Mono(s) => s.tracker().shape(),
        }
    }

    fn stereo(
        rig: &StereoRig,
        lat: &StereoLattice,
        shape: GridShape,
        config: &SessionConfig,
    ) -> Result<Self> {
        let l: Vec<(GridIndex, Point2)> = lat.left().reference_view().markers().collect();
        let r: Vec<(GridIndex, Point2)> = lat.right().reference_view().markers().collect();
        let tri = Triangulator::new(rig.clone(), TriangulationConfig::default())?;
        let mut session = StereoSession::new(shape, &l, &r, tri, config.clone())?;
        // The two views' tracker updates and the triangulation on both cores (one frame at a time).
        session.set_parallel(true);
        Ok(Session::Stereo(Box::new(session)))
    }

    fn mono(lat: &ReferenceLattice, shape: GridShape, config: &SessionConfig) -> Result<Self> {
        let l: Vec<(GridIndex, Point2)> = lat.reference_view().markers().collect();
        Ok(Session::Mono(Box::new(MonoSession::new(
            shape,
            &l,
            config.clone(),
        )?)))
    }
}

/// The rest positions of a sensor description's markers in both views (row-major; `None` where a
/// marker does not project), with the calibrated rig; and whether every one falls inside the image.
fn expected_lattice(spec: &SensorSpec, rig: &StereoRig) -> Result<ExpectedLattice> {
    let sensor = spec
        .build()
        .map_err(|e| Error::from(e).context("the sensor description"))?;
    let size = rig.left.image_size;
    let inside = |q: &Point2| {
        q.x >= 0.0 && q.y >= 0.0 && q.x <= f64::from(size.width) - 1.0 && q.y <= f64::from(size.height) - 1.0
    };
    let (mut left, mut right) = (Vec::new(), Vec::new());
    for i in spec.grid_shape().indices() {
        let [x, y] = spec.marker_rest_mm(i.row, i.col);
        let p = rig.project(&(sensor.left_from_sensor * nalgebra::Point3::new(x, y, 0.0)));
        left.push(p.map(|p| p.0));
        right.push(p.map(|p| p.1));
    }
    let overfills = left.iter().chain(&right).any(|q| !q.as_ref().is_some_and(inside));
    Ok(ExpectedLattice {
        left,
        right,
        overfills,
    })
}

struct ExpectedLattice {
    /// Rest positions in the left view (row-major; `None` where a marker does not project).
    left: Vec<Option<Point2>>,
    right: Vec<Option<Point2>>,
    /// Some marker falls outside a view at rest.
    overfills: bool,
}

/// Whether the left view's markers come within a pitch of the image border (on a side where the
/// lattice could be cut off) in a direction where fewer rows / columns than `full`'s are visible.
fn touches_border(dets: &[Detection], visible: GridShape, full: GridShape, size: ImageSize) -> bool {
    let pts: Vec<Point2> = dets.iter().map(|d| d.position).collect();
    let mut nn: Vec<f64> = pts
        .iter()
        .enumerate()
        .filter_map(|(i, p)| {
            pts.iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, q)| p.distance(*q))
                .min_by(f64::total_cmp)
        })
        .collect();
    nn.sort_by(f64::total_cmp);
    let Some(&pitch) = nn.get(nn.len() / 2) else {
        return false;
    };
    let (w, h) = (f64::from(size.width) - 1.0, f64::from(size.height) - 1.0);
    let near = |f: &dyn Fn(&Point2) -> bool| pts.iter().any(f);
    (visible.cols < full.cols && near(&|p| p.x < pitch || p.x > w - pitch))
        || (visible.rows < full.rows && near(&|p| p.y < pitch || p.y > h - pitch))
}

/// Starts a session on a reference frame whose view shows only part of the `full` lattice: on the
/// sensor's own grid indices when a sensor description places it, else from the visible top-left
/// marker (with a warning; `pitch_mm`, the marker pitch, can settle the right view's column
/// offset). Returns the session and the lines to log; `None` when the view does not look cut off
/// (no description, and no fewer rows or columns than the grid's near the image border).
fn start_cut(
    dets: &StereoPair<TieredDetections>,
    rig: Option<&StereoRig>,
    full: GridShape,
    expected: Option<&ExpectedLattice>,
    pitch_mm: Option<f64>,
    size: ImageSize,
    config: &SessionConfig,
) -> Result<Option<(Session, Vec<String>)>> {
    let (left, right) = (&dets.left.accepted, &dets.right.accepted);
    if let Some(x) = expected {
        let (session, line) = match rig {
            Some(rig) => {
                let (lat, p) = StereoLattice::from_reference_placed(
                    rig,
                    left,
                    right,
                    full,
                    (&x.left, &x.right),
                    StereoConfig::default(),
                )?;
                let line = format!(
                    "the {}x{} grid overfills the view: placed by the sensor description; left view {}, right view {}; \
                     {} of {} markers seen in both views pair within {} px of the epipolar lines",
                    full.rows,
                    full.cols,
                    p.left,
                    p.right,
                    p.within_epipolar,
                    p.paired,
                    StereoConfig::default().max_epipolar_px
                );
                (Session::stereo(rig, &lat, full, config)?, line)
            }
            None => {
                let (lat, p) =
                    ReferenceLattice::from_detections_placed(left, full, &x.left, IndexingConfig::default())?;
                let line = format!(
                    "the {}x{} grid overfills the view: placed by the sensor description on {p}",
                    full.rows, full.cols
                );
                (Session::mono(&lat, full, config)?, line)
            }
        };
        return Ok(Some((session, vec![line])));
    }
    let visible = ReferenceLattice::visible_shape(left, full, &IndexingConfig::default())?;
    if !touches_border(left, visible, full, size) {
        return Ok(None);
    }
    let session = match rig {
        Some(rig) => {
            let lat = StereoLattice::from_visible_reference(
                rig,
                left,
                right,
                visible,
                full,
                pitch_mm,
                StereoConfig::default(),
            )
            .map_err(|e| {
                Error::from(e).context(
                    "give the sensor description (--sensor FILE) to place the grid, or the marker pitch (--pitch-mm)",
                )
            })?;
            Session::stereo(rig, &lat, visible, config)?
        }
        None => Session::mono(
            &ReferenceLattice::from_detections(left, visible, IndexingConfig::default())?,
            visible,
            config,
        )?,
    };
    let line = format!(
        "warning: the {}x{} grid overfills the view and no sensor description places it: indexing the visible \
         {}x{} markers with the visible top-left marker as (0, 0); ids are not the sensor's grid indices",
        full.rows, full.cols, visible.rows, visible.cols
    );
    Ok(Some((session, vec![line])))
}
