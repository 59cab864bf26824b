//! `gelstereo._gelstereo._postprocess` (public as `gelstereo.postprocess`): Marknet's input layout,
//! decoding and post-processing of `gelstereo-markers`, for the trainer, which runs its own networks
//! (PyTorch, ONNX Runtime) and post-processes their output with this code instead of a copy.
//!
//! Layouts travel as tuples `(input_width, input_height, scaled_width, scaled_height, offset_x,
//! offset_y)`; markers as float64 arrays `(n, 3)` of x, y (original px, (0, 0) = centre of the
//! top-left pixel) and confidence. Configurations are read from the attributes of the objects given
//! (the trainer's `PostConfig` and `FitConfig` dataclasses).

use gelstereo::core::{Detection, ImageSize, Point2, TieredDetections};
use gelstereo::markers::contract::AutoFit;
use gelstereo::markers::edge::drop_past_the_edge;
use gelstereo::markers::finish::after_the_lattice;
use gelstereo::markers::lattice::{LatticeCheck, fit_lattice, keep_fitted_lattice};
use gelstereo::markers::layout::{
    self, InputFit, InputLayout, MAX_INPUT_SIDE_PX, decode_in_layout, layout_geometry,
};
use gelstereo::markers::marknet::{FittedCandidates, Marknet};
use gelstereo::markers::network::{self, AREA_BELOW_SCALE};
use gelstereo::markers::postprocess::{
    MISSING_DISTANCE_PITCH, MRE_FEATURES, MRE_NEIGHBOURS, PostProcess, Selection, dedup_radius_px,
    deduplicate, estimate_pitch_px,
};
use gelstereo::markers::region::Region;
use gelstereo::markers::{FILL_SAMPLE_STEP, Localizer as _, ResizeScratch, SessionOptions};
use numpy::ndarray::{Array1, Array2, Array4};
use numpy::{PyArray1, PyArray2, PyArray4, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray4};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::Mutex;

use crate::error::{GelstereoError, to_py};

/// `(input_width, input_height, scaled_width, scaled_height, offset_x, offset_y)`.
type LayoutTuple = (u32, u32, u32, u32, u32, u32);

/// A region `(x0, y0, x1, y1)`, original px.
type RegionTuple = (f64, f64, f64, f64);

/// A per-point mask.
type Mask<'py> = Bound<'py, PyArray1<bool>>;

/// One image's candidates, the layout they ran under and the region a closer look re-examined.
type Fitted<'py> = (Bound<'py, PyArray2<f64>>, LayoutTuple, Option<RegionTuple>);

fn layout_tuple(l: &InputLayout) -> LayoutTuple {
    (
        l.input_width,
        l.input_height,
        l.scaled_width,
        l.scaled_height,
        l.offset_x,
        l.offset_y,
    )
}

fn layout_of(t: LayoutTuple) -> InputLayout {
    InputLayout {
        input_width: t.0,
        input_height: t.1,
        scaled_width: t.2,
        scaled_height: t.3,
        offset_x: t.4,
        offset_y: t.5,
    }
}

/// The post-processing thresholds of a `PostConfig`-like object (attributes `conf_keep`, `conf_low`,
/// `conf_marknet_only`, `dedup_radius_frac`, `accept`, `lattice`: any true value turns the lattice
/// check on with its defaults).
struct PostArgs(PostProcess);

impl<'a, 'py> FromPyObject<'a, 'py> for PostArgs {
    type Error = PyErr;

    fn extract(ob: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        let f32_of = |name: &str| -> PyResult<f32> { ob.getattr(name)?.extract() };
        Ok(Self(PostProcess {
            conf_keep: f32_of("conf_keep")?,
            conf_low: f32_of("conf_low")?,
            conf_marknet_only: f32_of("conf_marknet_only")?,
            dedup_radius_frac: ob.getattr("dedup_radius_frac")?.extract()?,
            accept: f32_of("accept")?,
            lattice: ob.getattr("lattice")?.is_truthy()?.then(LatticeCheck::default),
        }))
    }
}

/// The "auto" fit of a `FitConfig`-like object (attributes `nominal_hw`, `multiple`,
/// `pitch_range_px`, `pitch_target_px`, `prefer_stretch`) and its nominal input width and height.
struct FitArgs {
    fit: AutoFit,
    nominal_width: u32,
    nominal_height: u32,
}

impl<'a, 'py> FromPyObject<'a, 'py> for FitArgs {
    type Error = PyErr;

    fn extract(ob: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        let (nominal_height, nominal_width): (u32, u32) = ob.getattr("nominal_hw")?.extract()?;
        let (pitch_min_px, pitch_max_px): (f64, f64) = ob.getattr("pitch_range_px")?.extract()?;
        Ok(Self {
            fit: AutoFit {
                multiple: ob.getattr("multiple")?.extract()?,
                pitch_min_px,
                pitch_max_px,
                pitch_target_px: ob.getattr("pitch_target_px")?.extract()?,
                prefer_stretch: ob.getattr("prefer_stretch")?.extract()?,
            },
            nominal_width,
            nominal_height,
        })
    }
}

fn size_of(width: u32, height: u32) -> PyResult<ImageSize> {
    if width == 0 || height == 0 {
        return Err(PyValueError::new_err(format!(
            "image size: expected at least 1 x 1 px, found {width} x {height}"
        )));
    }
    Ok(ImageSize { width, height })
}

fn detections_of(rows: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<Detection>> {
    let a = rows.as_array();
    if a.ncols() < 3 {
        return Err(PyValueError::new_err(format!(
            "{what}: expected an (n, 3) array of x, y, confidence, found shape {:?}",
            a.shape()
        )));
    }
    Ok(a.rows()
        .into_iter()
        .map(|r| Detection {
            position: Point2::new(r[0], r[1]),
            confidence: r[2] as f32,
        })
        .collect())
}

fn rows_of<'py>(py: Python<'py>, found: &[Detection]) -> Bound<'py, PyArray2<f64>> {
    let mut a = Array2::zeros((found.len(), 3));
    for (mut row, d) in a.rows_mut().into_iter().zip(found) {
        row[0] = d.position.x;
        row[1] = d.position.y;
        row[2] = f64::from(d.confidence);
    }
    PyArray2::from_owned_array(py, a)
}

fn region_of(region: Option<RegionTuple>) -> Option<Region> {
    region.map(|(x0, y0, x1, y1)| Region { x0, y0, x1, y1 })
}

/// The post-processing thresholds' defaults (the paper's), as a dict of `PostConfig`'s fields.
#[pyfunction]
fn default_post(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let p = PostProcess::default();
    // The f32 thresholds as the decimals they are written as (0.4, not 0.4000000059604645): they go
    // into exported models' metadata.
    let decimal = |v: f32| v.to_string().parse::<f64>().unwrap_or(f64::from(v));
    let d = PyDict::new(py);
    d.set_item("conf_keep", decimal(p.conf_keep))?;
    d.set_item("conf_low", decimal(p.conf_low))?;
    d.set_item("conf_marknet_only", decimal(p.conf_marknet_only))?;
    d.set_item("dedup_radius_frac", p.dedup_radius_frac)?;
    d.set_item("accept", decimal(p.accept))?;
    d.set_item("lattice", p.lattice.is_some())?;
    Ok(d)
}

/// The YOLO baseline's thresholds' defaults (Darknet's), as a dict of `YoloPost`'s fields.
#[pyfunction]
fn default_yolo_post(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let p = gelstereo::markers::yolo::YoloPost::default();
    let d = PyDict::new(py);
    d.set_item("conf_threshold", p.conf_threshold)?;
    d.set_item("nms_iou", p.nms_iou)?;
    Ok(d)
}

/// The "auto" layout of a `width x height` image whose marker pitch is `pitch_px` (None or NaN:
/// unknown) under `fit` (a `FitConfig`).
#[pyfunction]
#[pyo3(signature = (width, height, pitch_px, fit))]
fn fit_layout(width: u32, height: u32, pitch_px: Option<f64>, fit: FitArgs) -> PyResult<LayoutTuple> {
    let size = size_of(width, height)?;
    let l = layout::fit_layout(size, pitch_px, fit.nominal_width, fit.nominal_height, &fit.fit);
    Ok(layout_tuple(&l))
}

/// The probe of the "auto" fit for a `width x height` image under `fit` (a `FitConfig`): isotropic,
/// twice the nominal fit's scale, no margin.
#[pyfunction]
fn probe_layout(width: u32, height: u32, fit: FitArgs) -> PyResult<LayoutTuple> {
    let size = size_of(width, height)?;
    let l = layout::probe_layout(size, fit.nominal_width, fit.nominal_height, &fit.fit);
    Ok(layout_tuple(&l))
}

/// Input px per original px of a `width x height` image under `layout` (geometric mean of the axes).
#[pyfunction]
fn input_per_px(width: u32, height: u32, layout: LayoutTuple) -> PyResult<f64> {
    Ok(layout::input_per_px(size_of(width, height)?, &layout_of(layout)))
}

/// The network input of `image` (uint8 HxW grey or HxWx3 BGR) under `layout`, as Marknet feeds its
/// network: float32 (1, 3, input_height, input_width), RGB in [0, 1], the margin filled with the
/// resized image's median colour.
#[pyfunction]
fn network_input<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    layout: LayoutTuple,
) -> PyResult<Bound<'py, PyArray4<f32>>> {
    let image = crate::image::to_mat("image", image)?;
    let layout = layout_of(layout);
    let plane = py.detach(|| {
        let mut plane = Vec::new();
        network::network_input(&image, &layout, &mut ResizeScratch::default(), &mut plane)
            .map_err(|e| to_py(&e))?;
        PyResult::Ok(plane)
    })?;
    let shape = (1, 3, layout.input_height as usize, layout.input_width as usize);
    let array = Array4::from_shape_vec(shape, plane)
        .map_err(|e| PyValueError::new_err(format!("network input of unexpected size: {e}")))?;
    Ok(PyArray4::from_owned_array(py, array))
}

/// Every candidate of one image's raw output `raw` (float32 `(Gy, Gx, m, 3)` logits) from a
/// network of output `stride` run under `layout` on a `width x height` image: `(n, 3)` rows in flat
/// order, those in the padding around the image left out.
#[pyfunction]
fn decode<'py>(
    py: Python<'py>,
    raw: PyReadonlyArray4<'py, f32>,
    stride: u32,
    width: u32,
    height: u32,
    layout: LayoutTuple,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let size = size_of(width, height)?;
    let layout = layout_of(layout);
    let shape = raw.as_array().shape().to_vec();
    let mut geometry = layout_geometry(size, &layout, stride, shape[2] as u32);
    if shape[3] != 3 || (shape[0], shape[1]) != (geometry.grid_y, geometry.grid_x) {
        return Err(PyValueError::new_err(format!(
            "raw: expected shape ({}, {}, m, 3) for a {}x{} input at stride {stride}, found {shape:?}",
            geometry.grid_y, geometry.grid_x, layout.input_width, layout.input_height
        )));
    }
    geometry.candidates = shape[2];
    let values = raw.as_array().iter().copied().collect::<Vec<f32>>();
    let found = decode_in_layout(&values, &geometry, &layout, size, f32::NEG_INFINITY);
    Ok(rows_of(py, &found))
}

/// The candidates of step 2 on: the de-duplicated ones and the inputs of the MRE.
struct Steps {
    pitch_px: Option<f64>,
    kept: Vec<Detection>,
}

impl Steps {
    fn of(decoded: Vec<Detection>, post: &PostProcess) -> Self {
        let mut kept: Vec<Detection> = decoded
            .into_iter()
            .filter(|d| d.confidence > post.conf_low)
            .collect();
        let pitch_px = estimate_pitch_px(&kept, post.conf_keep);
        deduplicate(&mut kept, dedup_radius_px(pitch_px, post));
        Self { pitch_px, kept }
    }
}

/// What one output needs of its image beyond its markers, for the lattice check and the steps after it.
struct After<'a> {
    post: &'a PostProcess,
    pitch_px: Option<f64>,
    input_per_px: Option<f64>,
    size: Option<ImageSize>,
    looked: Option<Region>,
    image: Option<&'a opencv::core::Mat>,
    close_look: bool,
}

impl After<'_> {
    /// The lattice check (with `input_per_px`), then with the image the steps after it as
    /// `marknet`/`marknet-mre` take them, or with its size only the edge rule.
    fn finish(&self, found: TieredDetections) -> PyResult<TieredDetections> {
        let (Some(check), Some(scale)) = (&self.post.lattice, self.input_per_px) else {
            return Ok(found);
        };
        let fit = fit_lattice(&found.accepted, check, scale);
        let mut found = keep_fitted_lattice(found, fit, check, self.looked.as_ref(), self.size);
        if let Some(image) = self.image {
            return after_the_lattice(found, image, self.pitch_px, self.close_look).map_err(|e| to_py(&e));
        }
        if let Some(size) = self.size {
            drop_past_the_edge(&mut found, size, self.pitch_px);
        }
        Ok(found)
    }
}

/// The MRE's scores of `features` by `mre`, a callable from an (n, 11) float32 array to n scores.
fn scores_of(py: Python<'_>, mre: &Bound<'_, PyAny>, features: &[[f32; MRE_FEATURES]]) -> PyResult<Vec<f32>> {
    let flat: Vec<f32> = features.iter().flatten().copied().collect();
    let array = Array2::from_shape_vec((features.len(), MRE_FEATURES), flat)
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let scores: Vec<f32> = mre.call1((PyArray2::from_owned_array(py, array),))?.extract()?;
    if scores.len() != features.len() {
        return Err(PyValueError::new_err(format!(
            "mre: expected {} scores, found {}",
            features.len(),
            scores.len()
        )));
    }
    Ok(scores)
}

/// Post-processing of one image's decoded candidates `decoded` (`(n, 3)`, flat order) under `post`
/// (a `PostConfig`), for `marknet` and, with `mre` (a callable from (n, 11) float32 features to
/// n scores), `marknet-mre`. With `input_per_px` (the layout's), both keep their lattice (inside
/// `looked`, the region a closer look re-examined, from the lower confidence); then with `image`
/// (uint8 grey or BGR) the steps the localizer takes after the lattice check (dots check, border,
/// blobs; between squeezed markers only with `close_look`), or with `size` (width, height) alone
/// the edge rule.
///
/// Returns a dict: `candidates` (the de-duplicated ones, by descending confidence), `pitch_px`
/// (NaN when undefined), `marknet`, `marknet_mre` (sorted by y, then x; empty without `mre`),
/// `mre_index` (rows of `candidates` scored by the MRE), `mre_features`, `mre_scores` (NaN without
/// `mre`).
#[pyfunction]
#[pyo3(signature = (decoded, post, mre = None, input_per_px = None, size = None, looked = None, image = None, close_look = true))]
#[allow(clippy::too_many_arguments)] // Python keyword arguments, each optional
fn postprocess<'py>(
    py: Python<'py>,
    decoded: PyReadonlyArray2<'py, f64>,
    post: PostArgs,
    mre: Option<Bound<'py, PyAny>>,
    input_per_px: Option<f64>,
    size: Option<(u32, u32)>,
    looked: Option<RegionTuple>,
    image: Option<Bound<'py, PyAny>>,
    close_look: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let post = post.0;
    let size = size.map(|(w, h)| size_of(w, h)).transpose()?;
    let image = image.map(|im| crate::image::to_mat("image", &im)).transpose()?;
    let steps = Steps::of(detections_of(&decoded, "decoded")?, &post);
    let after = After {
        post: &post,
        pitch_px: steps.pitch_px,
        input_per_px,
        size,
        looked: region_of(looked),
        image: image.as_ref(),
        close_look,
    };
    let only = Selection::of_deduplicated(steps.kept.clone(), steps.pitch_px, &post, false);
    let marknet = after.finish(only.finish_tiered(&[], post.accept))?;
    let with_mre = Selection::of_deduplicated(steps.kept.clone(), steps.pitch_px, &post, true);
    let features = with_mre.features.clone();
    let scores = match (&mre, features.is_empty()) {
        (Some(mre), false) => Some(scores_of(py, mre, &features)?),
        _ => None,
    };
    let marknet_mre = match (&mre, &scores) {
        (Some(_), scores) => {
            after
                .finish(with_mre.finish_tiered(scores.as_deref().unwrap_or(&[]), post.accept))?
                .accepted
        }
        (None, _) => Vec::new(),
    };
    let mre_index: Vec<i64> = (0..steps.kept.len() as i64)
        .filter(|&i| steps.kept[i as usize].confidence <= post.conf_keep)
        .collect();
    let flat: Vec<f32> = features.iter().flatten().copied().collect();
    let features = Array2::from_shape_vec((features.len(), MRE_FEATURES), flat)
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let scores: Array1<f64> = match scores {
        Some(s) => s.into_iter().map(f64::from).collect(),
        None => Array1::from_elem(mre_index.len(), f64::NAN),
    };
    let out = PyDict::new(py);
    out.set_item("candidates", rows_of(py, &steps.kept))?;
    out.set_item("pitch_px", steps.pitch_px.unwrap_or(f64::NAN))?;
    out.set_item("marknet", rows_of(py, &marknet.accepted))?;
    out.set_item("marknet_mre", rows_of(py, &marknet_mre))?;
    out.set_item("mre_index", PyArray1::from_vec(py, mre_index))?;
    out.set_item("mre_features", PyArray2::from_owned_array(py, features))?;
    out.set_item("mre_scores", PyArray1::from_owned_array(py, scores))?;
    Ok(out)
}

/// The lattice fit of `points` (`(n, 2)`) with confidences `confidence` (None: all sure) at
/// `input_per_px`: (member mask, on-lattice mask, pitch_px or NaN, whether they form a lattice).
#[pyfunction]
#[pyo3(signature = (points, confidence = None, input_per_px = 1.0))]
fn lattice_fit<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f64>,
    confidence: Option<PyReadonlyArray1<'py, f64>>,
    input_per_px: f64,
) -> PyResult<(Mask<'py>, Mask<'py>, f64, bool)> {
    let p = points.as_array();
    let conf: Vec<f32> = match &confidence {
        Some(c) => c.as_array().iter().map(|&v| v as f32).collect(),
        None => vec![1.0; p.nrows()],
    };
    if p.ncols() < 2 || conf.len() != p.nrows() {
        return Err(PyValueError::new_err(format!(
            "points: expected an (n, 2) array and n confidences, found shape {:?} and {} confidences",
            p.shape(),
            conf.len()
        )));
    }
    let found: Vec<Detection> = p
        .rows()
        .into_iter()
        .zip(conf)
        .map(|(r, confidence)| Detection {
            position: Point2::new(r[0], r[1]),
            confidence,
        })
        .collect();
    let fit = fit_lattice(&found, &LatticeCheck::default(), input_per_px);
    Ok((
        PyArray1::from_vec(py, fit.member),
        PyArray1::from_vec(py, fit.on_lattice),
        fit.pitch_px.unwrap_or(f64::NAN),
        fit.is_lattice,
    ))
}

/// The YOLO baseline's post-processing (`gelstereo_markers::yolo`) of one image's raw output `raw`
/// (float32 `(K, 5)`) from a network of input `input_hw` with heads of `strides` and `anchors`
/// (`(heads, anchors per head, 2)`, input px; `|tw|`, `|th|` clamped to `tw_clamp`) on an image of
/// `image_wh`: a dict of `candidates` (`(n, 5)` x, y, width, height, objectness above
/// `conf_threshold`, original px, flat order) and `markers` (`(k, 3)` x, y, objectness of the boxes
/// NMS at `nms_iou` keeps, in its visiting order).
#[pyfunction]
#[pyo3(signature = (raw, input_hw, strides, anchors, tw_clamp, image_wh, conf_threshold, nms_iou))]
#[allow(clippy::too_many_arguments)] // the contract's values, each named as in the metadata
fn yolo_postprocess<'py>(
    py: Python<'py>,
    raw: PyReadonlyArray2<'py, f32>,
    input_hw: (u32, u32),
    strides: Vec<u32>,
    anchors: Vec<Vec<[f64; 2]>>,
    tw_clamp: f64,
    image_wh: (u32, u32),
    conf_threshold: f64,
    nms_iou: f64,
) -> PyResult<Bound<'py, PyDict>> {
    use gelstereo::markers::yolo::{self, YoloContract, YoloHead, YoloPost};
    let (input_height, input_width) = input_hw;
    if strides.len() != anchors.len() || strides.contains(&0) {
        return Err(PyValueError::new_err(format!(
            "strides, anchors: expected one non-zero stride per head's anchors, found {} strides and {} heads",
            strides.len(),
            anchors.len()
        )));
    }
    let heads = strides
        .iter()
        .zip(anchors)
        .map(|(&stride, anchors)| YoloHead {
            stride,
            grid_x: input_width / stride,
            grid_y: input_height / stride,
            anchors,
        })
        .collect();
    let contract = YoloContract {
        input_width,
        input_height,
        heads,
        tw_clamp,
        post: YoloPost {
            conf_threshold,
            nms_iou,
        },
        dataset: String::new(),
        trained: String::new(),
    };
    let array = raw.as_array();
    if array.ncols() != yolo::OUTPUTS_PER_ANCHOR || array.nrows() != contract.rows() {
        return Err(PyValueError::new_err(format!(
            "raw: expected shape ({}, {}) for these heads, found {:?}",
            contract.rows(),
            yolo::OUTPUTS_PER_ANCHOR,
            array.shape()
        )));
    }
    let values: Vec<f32> = array.iter().copied().collect();
    let scale_x = f64::from(image_wh.0) / f64::from(input_width.max(1));
    let scale_y = f64::from(image_wh.1) / f64::from(input_height.max(1));
    let boxes = yolo::decode(&values, &contract, scale_x, scale_y, conf_threshold);
    let kept = yolo::nms(&boxes, nms_iou);
    let table = |rows: Vec<Vec<f64>>, width: usize| {
        let flat: Vec<f64> = rows.into_iter().flatten().collect();
        Array2::from_shape_vec((flat.len() / width, width), flat)
            .map(|a| PyArray2::from_owned_array(py, a))
            .map_err(|e| PyValueError::new_err(e.to_string()))
    };
    let out = PyDict::new(py);
    let candidates = boxes
        .iter()
        .map(|b| vec![b.centre.x, b.centre.y, b.width_px, b.height_px, b.objectness])
        .collect();
    out.set_item("candidates", table(candidates, 5)?)?;
    let markers = kept
        .iter()
        .map(|b| vec![b.centre.x, b.centre.y, b.objectness])
        .collect();
    out.set_item("markers", table(markers, 3)?)?;
    Ok(out)
}

/// A Marknet ONNX model run by `gelstereo-markers` up to its post-processing: the passes of the
/// "auto" fit (probes, relayouts; each image on its own, no pitch remembered) and the closer look.
#[pyclass(module = "gelstereo.postprocess", name = "Marknet", frozen)]
struct PyMarknet {
    inner: Mutex<Marknet>,
    #[pyo3(get)]
    stride: u32,
    #[pyo3(get)]
    input_width: u32,
    #[pyo3(get)]
    input_height: u32,
}

#[pymethods]
impl PyMarknet {
    /// Loads `path` (checking its contract) with `threads` intra-op threads; `fit`: "auto" (the
    /// model's layout) or "stretch" (the whole image resized to the nominal input); `post`: a
    /// `PostConfig` (None: the model's); `close_look`: whether squeezed parts get a closer look.
    #[new]
    #[pyo3(signature = (path, threads = 1, fit = "auto", post = None, close_look = true))]
    fn new(
        py: Python<'_>,
        path: std::path::PathBuf,
        threads: usize,
        fit: &str,
        post: Option<PostArgs>,
        close_look: bool,
    ) -> PyResult<Self> {
        let fit: InputFit = fit
            .parse()
            .map_err(|e: gelstereo::markers::Error| PyValueError::new_err(e.to_string()))?;
        let options = SessionOptions {
            intra_threads: threads,
            use_cuda: false,
        };
        let mut net = py.detach(|| Marknet::load(&path, &options).map_err(|e| to_py(&e)))?;
        net.set_fit(fit);
        net.set_pitch_memory(false);
        net.set_lattice_window(false);
        net.set_close_look(close_look);
        if let Some(post) = post {
            net.set_postprocess(post.0);
        }
        let c = net.contract();
        Ok(Self {
            stride: c.stride,
            input_width: c.input_width,
            input_height: c.input_height,
            inner: Mutex::new(net),
        })
    }

    /// The name of the localizer (`marknet`).
    #[getter]
    fn name(&self) -> PyResult<String> {
        Ok(self.lock()?.name().to_string())
    }

    /// Each image's (uint8 grey or BGR) candidates with c > `conf_low` after the passes
    /// (`(n, 3)`, flat order), the layout of the pass they come from, and the region
    /// (x0, y0, x1, y1) a closer look re-examined, or None.
    fn fitted<'py>(&self, py: Python<'py>, images: Vec<Bound<'py, PyAny>>) -> PyResult<Vec<Fitted<'py>>> {
        let mats = images
            .iter()
            .map(|im| crate::image::to_mat("image", im))
            .collect::<PyResult<Vec<_>>>()?;
        let found: Vec<FittedCandidates> = py.detach(|| {
            let refs: Vec<&opencv::core::Mat> = mats.iter().collect();
            self.lock()?.fitted_candidates(&refs).map_err(|e| to_py(&e))
        })?;
        Ok(found
            .into_iter()
            .map(|f| {
                (
                    rows_of(py, &f.candidates),
                    layout_tuple(&f.layout),
                    f.looked.map(|r| (r.x0, r.y0, r.x1, r.y1)),
                )
            })
            .collect())
    }
}

impl PyMarknet {
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, Marknet>> {
        self.inner
            .lock()
            .map_err(|_| GelstereoError::new_err("the model failed in another thread"))
    }
}

/// The submodule `_postprocess` of the extension, with the constants the trainer shares.
pub fn module(py: Python<'_>) -> PyResult<Bound<'_, PyModule>> {
    let m = PyModule::new(py, "_postprocess")?;
    m.add_function(wrap_pyfunction!(default_post, &m)?)?;
    m.add_function(wrap_pyfunction!(default_yolo_post, &m)?)?;
    m.add_function(wrap_pyfunction!(fit_layout, &m)?)?;
    m.add_function(wrap_pyfunction!(probe_layout, &m)?)?;
    m.add_function(wrap_pyfunction!(input_per_px, &m)?)?;
    m.add_function(wrap_pyfunction!(network_input, &m)?)?;
    m.add_function(wrap_pyfunction!(decode, &m)?)?;
    m.add_function(wrap_pyfunction!(postprocess, &m)?)?;
    m.add_function(wrap_pyfunction!(lattice_fit, &m)?)?;
    m.add_function(wrap_pyfunction!(yolo_postprocess, &m)?)?;
    m.add_class::<PyMarknet>()?;
    m.add("MRE_NEIGHBOURS", MRE_NEIGHBOURS)?;
    m.add("MRE_FEATURES", MRE_FEATURES)?;
    m.add("MISSING_DISTANCE", MISSING_DISTANCE_PITCH)?;
    m.add("AREA_BELOW_SCALE", AREA_BELOW_SCALE)?;
    m.add("FILL_SAMPLE_STEP", FILL_SAMPLE_STEP)?;
    m.add("MAX_INPUT_SIDE_PX", MAX_INPUT_SIDE_PX)?;
    Ok(m)
}
