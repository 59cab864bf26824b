//! `gelstereo.Pipeline`, `gelstereo.Frame`, `gelstereo.Contact`: the facade's [`Pipeline`] and its
//! [`FrameOutput`] as Python objects with numpy arrays.

use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard};

use gelstereo::core::StereoPair;
use gelstereo::gel::GelFile;
use gelstereo::sim::SensorSpec;
use gelstereo::{
    Frame, FrameOutput, GridShape, Images, MarkerRecord, Method, Pipeline, PipelineConfig, parse_grid,
};
use gelstereo::{GelFacts, GelFrame};
use numpy::ndarray::Array2;
use numpy::{PyArray1, PyArray2};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyString};

use crate::error::{GelstereoError, to_py};
use crate::image::to_mat;

/// The tracking pipeline: built once (models loaded, calibration read), then fed frame by frame.
///
/// Args:
///     calibration: stereo calibration (OpenCV YAML/XML, a folder holding a mrcal pair, or
///         "left.cameramodel,right.cameramodel"); None (default) for a mono sensor.
///     models: folder with marknet.onnx and mre.onnx for Marknet-MRE (default: the shipped
///         data/models, or the blob detector where they are not installed).
///     grid: the marker lattice, "ROWSxCOLS" or (rows, cols) (default: the sensor's, else 23x23).
///     sensor: sensor description (JSON, as `gelstereo simulate --sensor` takes): its gel's facts
///         for the contact mechanics and, for a stereo sensor whose grid overfills the cameras'
///         view, the visible markers get the sensor's own indices.
///     gel: a gel file (`gel.json` as `gelstereo track` or `calibrate-gel` write it); a keyword
///         below that is also given must agree with it.
///     gel_thickness_mm, gel_modulus_kpa, poisson, friction: the gel's facts and the friction
///         coefficient of the contact mechanics, as `gelstereo track`'s flags of the same names
///         (default: the reference sensor's 2.5 mm, 150 kPa, 0.45 and 0.6).
///     method: "marknet-mre", "marknet", "blob" or "yolo", as `gelstereo track --method`
///         (default: Marknet-MRE where its models are installed, else the blob detector).
///     pitch_mm: the marker pitch of a mono sensor, mm, so that its contact area is in mm²
///         (`--pitch-mm`); None: the area of a mono sensor is unknown (NaN).
///     threads: ONNX Runtime intra-op threads, 0 (default) one per core (`--threads`).
///     mono: track only the left view given to `process` (`--mono`).
///     pad_border: accepted and ignored with a DeprecationWarning, as `track --pad-border`: markers
///         cut by the image border are found by default.
///
/// Every other setting is `gelstereo track`'s default. The first frame that can be indexed is the
/// reference (no contact): marker ids are its grid indices, displacement is measured against it.
///
/// Raises:
///     GelstereoError: the calibration, models or sensor description cannot be used.
///     ValueError: RAYON_NUM_THREADS or OMP_NUM_THREADS asks for more than 256 threads.
#[pyclass(module = "gelstereo", name = "Pipeline", frozen)]
pub struct PyPipeline {
    /// Locked per call: Python threads sharing a pipeline take turns, frame by frame.
    inner: Mutex<Pipeline>,
    /// The last `timestamp=` given to `process`: the next must be later.
    last_timestamp_s: Mutex<Option<f64>>,
    /// Track the left view only (`mono=True`): a right view given to `process` is not used.
    mono: bool,
}

#[pymethods]
impl PyPipeline {
    #[new]
    #[pyo3(signature = (calibration = None, models = None, grid = None, sensor = None, *, gel = None, gel_thickness_mm = None, gel_modulus_kpa = None, poisson = None, friction = None, method = None, pitch_mm = None, threads = 0, mono = false, pad_border = None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        calibration: Option<PathBuf>,
        models: Option<PathBuf>,
        grid: Option<&Bound<'_, PyAny>>,
        sensor: Option<PathBuf>,
        gel: Option<PathBuf>,
        gel_thickness_mm: Option<f64>,
        gel_modulus_kpa: Option<f64>,
        poisson: Option<f64>,
        friction: Option<f64>,
        method: Option<&str>,
        pitch_mm: Option<f64>,
        threads: usize,
        mono: bool,
        pad_border: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        if let Some(value) = pad_border {
            // As `track --pad-border`: kept for old scripts, a value given changes nothing.
            let note = std::ffi::CString::new(format!(
                "pad_border={value} is ignored: markers cut by the image border are found and placed at their \
                 centre by default, and none whose centre lies outside the image is reported"
            ))?;
            PyErr::warn(
                py,
                &py.get_type::<pyo3::exceptions::PyDeprecationWarning>(),
                &note,
                1,
            )?;
        }
        // The thread pools start with the first pipeline; a huge count from the environment would
        // start thousands of threads.
        gelstereo::core::limits::check_thread_env().map_err(PyValueError::new_err)?;
        let mut config = PipelineConfig {
            calibration,
            grid: grid.map(grid_shape).transpose()?,
            method: method
                .map(str::parse::<Method>)
                .transpose()
                .map_err(|e| PyValueError::new_err(e.to_string()))?,
            mono,
            ..PipelineConfig::default()
        };
        let threads = gelstereo::core::limits::parse_thread_count(&threads.to_string())
            .map_err(|e| PyValueError::new_err(format!("threads: {e}")))?;
        config.localizer.session.intra_threads = threads;
        config.session.planar.pitch_mm = pitch_mm;
        let mut facts = GelFacts {
            thickness_mm: gel_thickness_mm,
            modulus_kpa: gel_modulus_kpa,
            poisson,
            friction,
        };
        if let Some(path) = &gel {
            let file = GelFile::read(path).map_err(|e| to_py(&e))?;
            facts = facts.with_file(&file, path).map_err(|e| to_py(&e))?;
        }
        if let Some(path) = &sensor {
            let spec = SensorSpec::load(path).map_err(|e| to_py(&e))?;
            facts = facts
                .with_file(&GelFile::of_sensor(&spec), path)
                .map_err(|e| to_py(&e))?;
            config.sensor = Some(spec);
        }
        config.apply_gel(&facts).map_err(|e| to_py(&e))?;
        if let Some(dir) = models {
            // Models named explicitly are used or reported, never replaced by the blob detector.
            config = config.with_models(&dir);
            config.method = config.method.or(Some(Method::MarknetMre));
        }
        let inner = py.detach(|| Pipeline::new(&config).map_err(|e| to_py(&e)))?;
        Ok(Self {
            inner: Mutex::new(inner),
            last_timestamp_s: Mutex::new(None),
            mono,
        })
    }

    /// Processes one frame and returns its `Frame`.
    ///
    /// Args:
    ///     left: the left (or only) view, numpy uint8 HxWx3 BGR (as OpenCV reads) or HxW grey.
    ///     right: the right view of a stereo sensor (same size and kind); None for mono.
    ///     timestamp: capture time in seconds (any origin), finite and later than the last one
    ///         given; None: frame number / 30 Hz.
    ///
    /// A frame that cannot be read, localized or indexed comes back flagged (`Frame.note`) with
    /// every marker lost, rather than raising, so a live loop goes on.
    ///
    /// Raises:
    ///     TypeError, ValueError: an image is not such an array, or the timestamp is not finite or
    ///         not after the previous one.
    ///     GelstereoError: the pipeline itself failed.
    #[pyo3(signature = (left, right = None, timestamp = None))]
    fn process(
        &self,
        py: Python<'_>,
        left: &Bound<'_, PyAny>,
        right: Option<&Bound<'_, PyAny>>,
        timestamp: Option<f64>,
    ) -> PyResult<PyFrame> {
        self.check_timestamp(timestamp)?;
        let left = to_mat("left", left)?;
        let images = match right.filter(|_| !self.mono) {
            Some(right) => Images::Stereo(StereoPair::new(left, to_mat("right", right)?)),
            None => Images::Mono(left),
        };
        let frame = Frame {
            images,
            time_s: timestamp,
        };
        let (output, gel) = py.detach(|| {
            let mut pipeline = self.lock()?;
            let output = pipeline.process(&frame).map_err(|e| to_py(&e))?;
            PyResult::Ok((output, pipeline.gel_frame()))
        })?;
        PyFrame::new(py, output, gel.as_ref())
    }

    /// Makes the current shape of the gel the reference from the next frame on (drift correction):
    /// displacement, contact and slip are then measured against it.
    fn rezero(&self) -> PyResult<()> {
        self.lock()?.rezero();
        Ok(())
    }

    /// The localization method in use ("marknet-mre", or "blob" without the models).
    #[getter]
    fn method(&self) -> PyResult<&'static str> {
        Ok(self.lock()?.method().as_str())
    }

    /// Whether stereo frames can be processed (a calibration is loaded).
    #[getter]
    fn is_stereo(&self) -> PyResult<bool> {
        Ok(self.lock()?.is_stereo())
    }

    /// The tracked lattice (rows, cols): the visible part once a grid that overfills the view was
    /// indexed.
    #[getter]
    fn grid(&self) -> PyResult<(u16, u16)> {
        let shape = self.lock()?.shape();
        Ok((shape.rows, shape.cols))
    }

    fn __repr__(&self) -> PyResult<String> {
        let inner = self.lock()?;
        let shape = inner.shape();
        Ok(format!(
            "gelstereo.Pipeline({}, {}, grid {}x{})",
            if inner.is_stereo() { "stereo" } else { "mono" },
            inner.method(),
            shape.rows,
            shape.cols
        ))
    }
}

impl PyPipeline {
    /// Refuses a `timestamp=` that is not finite or not after the last one given: speeds, slip and
    /// the frame times written out all assume time goes forward.
    fn check_timestamp(&self, timestamp: Option<f64>) -> PyResult<()> {
        let Some(t) = timestamp else {
            return Ok(());
        };
        if !t.is_finite() {
            return Err(PyValueError::new_err(format!(
                "timestamp={t}: expected a finite number of seconds"
            )));
        }
        let mut last = self
            .last_timestamp_s
            .lock()
            .map_err(|_| GelstereoError::new_err("the pipeline failed in another thread"))?;
        if let Some(previous) = *last
            && t <= previous
        {
            return Err(PyValueError::new_err(format!(
                "timestamp={t}: expected a time after the previous frame's {previous} s (timestamps must increase)"
            )));
        }
        *last = Some(t);
        Ok(())
    }

    fn lock(&self) -> PyResult<MutexGuard<'_, Pipeline>> {
        self.inner
            .lock()
            .map_err(|_| GelstereoError::new_err("the pipeline failed in another thread"))
    }
}

/// `grid=`: "ROWSxCOLS" or (rows, cols).
fn grid_shape(grid: &Bound<'_, PyAny>) -> PyResult<GridShape> {
    let text = if let Ok(text) = grid.cast::<PyString>() {
        text.to_string()
    } else if let Ok((rows, cols)) = grid.extract::<(i64, i64)>() {
        format!("{rows}x{cols}")
    } else {
        return Err(PyTypeError::new_err(
            "grid: expected \"ROWSxCOLS\" (e.g. \"23x23\") or a (rows, cols) tuple",
        ));
    };
    parse_grid(&text, "grid").map_err(|e| to_py(&e))
}

/// One processed frame.
///
/// Attributes:
///     frame: frame number, from 0 (flagged frames count).
///     timestamp: seconds from the first frame.
///     markers: dict of equal-length numpy arrays, one entry per tracked marker in id order:
///         row, col (int64 grid index), status ("tracked", "predicted", "lost"), x_left, y_left,
///         x_right, y_right (px), X_mm, Y_mm, Z_mm (3-D, left camera frame), dX_mm, dY_mm, dZ_mm
///         (displacement against the reference); NaN where a view or the 3-D stages lack a value;
///         pressure_kPa (contact pressure on the marker's cell), in_contact and slipping (bool);
///         X_gel_mm, Y_gel_mm, Z_gel_mm, dX_gel_mm, dY_gel_mm, dZ_gel_mm (the same in the gel frame).
///     contact: the `Contact` (area, depth, centroid, region); NaN figures for a frame whose
///         contact is unknown (flagged: unreadable, or no usable markers).
///     slip: "no_contact", "stick", "partial_slip" or "gross_slip"; None when the contact is unknown.
///     note: why the frame is flagged (unreadable, not localized, reference not yet indexed...);
///         None for a frame processed normally.
///     log: informational lines (how the reference lattice was indexed, re-zeroing).
///     earlier: frames flagged before the reference was indexed, returned again now with a lost
///         row per marker (they precede this frame).
///     camera_from_gel: (4, 4) float64 homogeneous transform taking gel-frame points (mm) to the
///         left camera frame (the gel's x, y, z axes as columns, its origin as the translation);
///         None for a mono sensor or before the reference frame.
#[pyclass(module = "gelstereo", name = "Frame", frozen)]
pub struct PyFrame {
    #[pyo3(get)]
    frame: u32,
    #[pyo3(get)]
    timestamp: f64,
    #[pyo3(get)]
    markers: Py<PyDict>,
    #[pyo3(get)]
    contact: Py<PyContact>,
    #[pyo3(get)]
    slip: Option<&'static str>,
    #[pyo3(get)]
    note: Option<String>,
    #[pyo3(get)]
    log: Vec<String>,
    #[pyo3(get)]
    earlier: Vec<Py<PyFrame>>,
    #[pyo3(get)]
    camera_from_gel: Option<Py<PyArray2<f64>>>,
}

impl PyFrame {
    /// The frame of `output`; `gel` is the pipeline's gel frame (`None` for a mono sensor or
    /// before the reference frame).
    pub(crate) fn new(py: Python<'_>, output: FrameOutput, gel: Option<&GelFrame>) -> PyResult<Self> {
        let summary = &output.summary;
        let region: Vec<[i64; 2]> = output
            .contact_region
            .iter()
            .map(|id| [i64::from(id.row), i64::from(id.col)])
            .collect();
        let contact = PyContact {
            in_contact: summary.contact,
            area_mm2: summary.contact_area_mm2.unwrap_or(f64::NAN),
            max_depth_mm: summary.max_depth_mm.unwrap_or(f64::NAN),
            centroid_mm: summary.centroid_mm.map(|[x, y]| (x, y)),
            force_n: summary.force_n.unwrap_or(f64::NAN),
            shear_n: summary.shear_n.map_or((f64::NAN, f64::NAN), |[x, y]| (x, y)),
            torque_nmm: summary.torque_nmm.unwrap_or(f64::NAN),
            region: PyArray2::from_owned_array(py, Array2::from(region)).unbind(),
        };
        let earlier = output
            .earlier
            .into_iter()
            .map(|f| Py::new(py, PyFrame::new(py, f, gel)?))
            .collect::<PyResult<Vec<_>>>()?;
        Ok(Self {
            frame: output.frame,
            timestamp: output.t_s,
            markers: markers_dict(py, &output.markers)?.unbind(),
            contact: Py::new(py, contact)?,
            slip: output.summary.measured.then_some(output.summary.slip.as_str()),
            note: output.note,
            log: output.log,
            earlier,
            camera_from_gel: gel.map(|g| PyArray2::from_owned_array(py, camera_from_gel(g)).unbind()),
        })
    }
}

/// The 4 x 4 homogeneous transform taking gel-frame points (mm) to the left camera frame: the
/// axes as columns, the origin as the translation.
fn camera_from_gel(gel: &GelFrame) -> Array2<f64> {
    let mut m = Array2::eye(4);
    for (c, axis) in gel.axes.iter().enumerate() {
        for r in 0..3 {
            m[[r, c]] = axis[r];
        }
    }
    for r in 0..3 {
        m[[r, 3]] = gel.origin_mm[r];
    }
    m
}

#[pymethods]
impl PyFrame {
    fn __repr__(&self, py: Python<'_>) -> String {
        let count = self
            .markers
            .bind(py)
            .get_item("row")
            .ok()
            .flatten()
            .map_or(0, |a| a.len().unwrap_or(0));
        format!(
            "gelstereo.Frame(frame={}, timestamp={:.3}, {count} markers, slip={}{})",
            self.frame,
            self.timestamp,
            self.slip.unwrap_or("unknown"),
            self.note
                .as_ref()
                .map(|n| format!(", note={n:?}"))
                .unwrap_or_default()
        )
    }
}

/// The contact of one frame.
///
/// Attributes:
///     in_contact: whether anything touches the gel.
///     area_mm2: contact area, mm^2 (0 without contact; NaN when the sensor's scale is unknown).
///     max_depth_mm: largest indentation depth, mm (0 without contact; NaN for a mono sensor).
///     centroid_mm: contact centroid (X, Y) in the left camera frame, mm; None without contact.
///     force_n: total normal force on the gel, N (0 without contact; NaN for a mono sensor).
///     shear_n: total tangential force (x, y) along the gel frame's axes (the lattice's columns
///         and rows), N.
///     torque_nmm: torque of the shear about the normal through the pressure centroid, N mm.
///     region: (K, 2) int64 array of the (row, col) ids of the markers in contact.
#[pyclass(module = "gelstereo", name = "Contact", frozen)]
pub struct PyContact {
    #[pyo3(get)]
    in_contact: bool,
    #[pyo3(get)]
    area_mm2: f64,
    #[pyo3(get)]
    max_depth_mm: f64,
    #[pyo3(get)]
    centroid_mm: Option<(f64, f64)>,
    #[pyo3(get)]
    force_n: f64,
    #[pyo3(get)]
    shear_n: (f64, f64),
    #[pyo3(get)]
    torque_nmm: f64,
    #[pyo3(get)]
    region: Py<PyArray2<i64>>,
}

#[pymethods]
impl PyContact {
    fn __repr__(&self) -> String {
        format!(
            "gelstereo.Contact(area_mm2={:.3}, max_depth_mm={:.3}, force_n={:.4}, centroid_mm={})",
            self.area_mm2,
            self.max_depth_mm,
            self.force_n,
            self.centroid_mm
                .map_or("None".into(), |(x, y)| format!("({x:.3}, {y:.3})"))
        )
    }
}

/// The per-marker columns as numpy arrays (the keys of `Frame.markers`, in `markers.csv` order).
fn markers_dict<'py>(py: Python<'py>, rows: &[MarkerRecord]) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    let ints = |f: fn(&MarkerRecord) -> u16| PyArray1::from_iter(py, rows.iter().map(|m| i64::from(f(m))));
    let floats = |f: &dyn Fn(&MarkerRecord) -> Option<f64>| {
        PyArray1::from_iter(py, rows.iter().map(|m| f(m).unwrap_or(f64::NAN)))
    };
    dict.set_item("row", ints(|m| m.index.row))?;
    dict.set_item("col", ints(|m| m.index.col))?;
    let status = PyList::new(py, rows.iter().map(|m| m.status.map_or("", |s| s.as_str())))?;
    let numpy = py.import("numpy")?;
    let kwargs = PyDict::new(py);
    kwargs.set_item("dtype", "U")?;
    dict.set_item("status", numpy.getattr("array")?.call((status,), Some(&kwargs))?)?;
    for (name, view) in [("left", 0), ("right", 1)] {
        let px = move |m: &MarkerRecord| if view == 0 { m.left_px } else { m.right_px };
        dict.set_item(format!("x_{name}"), floats(&|m| px(m).map(|p| p.x)))?;
        dict.set_item(format!("y_{name}"), floats(&|m| px(m).map(|p| p.y)))?;
    }
    for (k, axis) in ["X", "Y", "Z"].into_iter().enumerate() {
        dict.set_item(format!("{axis}_mm"), floats(&|m| m.position_mm.map(|v| v[k])))?;
    }
    for (k, axis) in ["X", "Y", "Z"].into_iter().enumerate() {
        dict.set_item(
            format!("d{axis}_mm"),
            floats(&|m| m.displacement_mm.map(|v| v[k])),
        )?;
    }
    dict.set_item("pressure_kPa", floats(&|m| m.pressure_kpa))?;
    let flags = |f: fn(&MarkerRecord) -> Option<bool>| {
        PyArray1::from_iter(py, rows.iter().map(|m| f(m).unwrap_or(false)))
    };
    dict.set_item("in_contact", flags(|m| m.in_contact))?;
    dict.set_item("slipping", flags(|m| m.slipping))?;
    // In markers.csv's column order: positions, then displacements.
    for (prefix, vector) in [
        (
            "",
            (|m| m.gel_position_mm) as fn(&MarkerRecord) -> Option<[f64; 3]>,
        ),
        ("d", |m| m.gel_displacement_mm),
    ] {
        for (k, axis) in ["X", "Y", "Z"].into_iter().enumerate() {
            dict.set_item(
                format!("{prefix}{axis}_gel_mm"),
                floats(&|m| vector(m).map(|v| v[k])),
            )?;
        }
    }
    Ok(dict)
}
