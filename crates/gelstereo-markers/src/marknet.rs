//! Marknet (and its MRE) through ONNX Runtime: loading with a contract check, preprocessing any image
//! size, batched inference of both stereo views, decoding and post-processing.
//!
//! Preprocessing (`docs/model-contract.md`): the image is resized with OpenCV's bilinear `INTER_LINEAR`
//! (half-pixel centres) into an [`InputLayout`], converted to planar RGB f32 in [0, 1] (grey replicated,
//! BGRA's alpha dropped). The default [`InputFit::Auto`] of a dynamic-input model scales isotropically
//! so that the marker pitch lands where the network was trained, measured on a first pass and
//! remembered per image size; a fixed-input model gets the contract's whole-image stretch.
//! Outputs are mapped back with `x_orig = (x_in - offset_x) * W / scaled_width - 0.5` (likewise y).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use gelstereo_core::{Detection, ImageSize, Point2, StereoPair, TieredDetections};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual};
use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{TensorRef, ValueType};
use rayon::iter::{IntoParallelIterator, ParallelIterator};

use crate::border::settle_the_border;
use crate::close_look::{SQUEEZED_NN_PITCH, close_look_input, close_look_zoom, merge, squeezed_region_of};
use crate::contract::AutoFit;
use crate::contract::{MARKNET_INPUT, MARKNET_OUTPUT, MRE_INPUT, MRE_OUTPUT, TensorSpec};
use crate::dots::judge_the_dots;
use crate::lattice::{
    LatticeCheck, LatticeFit, fit_lattice, fit_lattice_with_distances, keep_fitted_lattice,
};
use crate::layout::{
    COARSE_PROBE_SCALE, FINE_PROBE_SCALE, InputFit, InputLayout, MAX_INPUT_SIDE_PX, MAX_RELAYOUTS,
    MIN_PITCH_SUPPORT, PROBE_MIN_COVER, PROBE_MIN_GAIN, PROBE_SCALE, decode_in_layout, fit_layout,
    input_per_px, layout_geometry, probe_layout_at,
};
use crate::postprocess::{
    DecodeGeometry, MRE_FEATURES, Selection, dedup_radius_px, deduplicate, pitch_of_confident,
};
use crate::region::Region;
use crate::resize::{Image, ResizeScratch, resize_into_planar};
use crate::site_blobs::blobs_at_empty_sites;
use crate::spacing::nearest_neighbour_distances;
use crate::squeezed_blobs::blobs_between_squeezed;
use crate::stream::StreamState;
use crate::window::{self, LatticeWindow, WINDOW_MIN_MARKERS, Window};
use crate::{
    Error, Localizer, MarknetContract, MreContract, PostProcess, Result, check_image, cv_err, runtime,
};

/// Largest accepted ratio between an image's aspect ratio and the network input's: beyond it the resize
/// squashes markers into shapes far from anything the network was trained on.
pub const MAX_ASPECT_DISTORTION: f64 = 2.0;

/// Below this scale (output px per original px, along either axis) the image is first reduced to its
/// scaled size by area averaging (OpenCV `INTER_AREA`; `AREA_BELOW_SCALE` in the trainer), then
/// placed as usual: bilinear sampling reads 2 x 2 pixels per output pixel, so a reduction of 3x or
/// more skips most pixels, and scan lines or dots a few pixels wide alias into stripes and blobs (a
/// 1280 x 720 gel of bright 25 px dots at a 90 px pitch under scan-line banding, run at 0.13 x: 54 of
/// its 64 dots with bilinear sampling, all 64 and nothing else with area averaging;
/// `bright_dots_under_scan_lines_reduced_a_lot_are_found_and_the_banding_is_not`). Milder reductions
/// stay bilinear, as the network's training crops are: area averaging blurs small dots that
/// bilinear sampling keeps sharp (a higher threshold cost a real sensor markers in contact).
pub const AREA_BELOW_SCALE: f64 = 0.34;

/// What the passes of the "auto" fit and the closer look leave of one image, before the
/// post-processing ([`Marknet::fitted_candidates`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FittedCandidates {
    /// The candidates with c > `conf_low`, in the image's pixels, in flat order.
    pub candidates: Vec<Detection>,
    /// The layout of the pass they come from (its scale is the lattice check's).
    pub layout: InputLayout,
    /// The region a closer look re-examined, if any.
    pub looked: Option<Region>,
}

/// One image's candidates from one network pass, and what they say about its layout.
#[derive(Debug, Clone, Default)]
struct Pass {
    /// Candidates with c > the pass's threshold, in the image's pixels, flat order.
    candidates: Vec<Detection>,
    /// Post-processing step 3's output for them: de-duplicated, by descending confidence.
    kept: Vec<Detection>,
    /// Post-processing step 2's pitch of the candidates (de-duplication, MRE features).
    pitch_px: Option<f64>,
    /// How many confident candidates support `layout_pitch_px`: with the lattice check, the lattice
    /// members among the de-duplicated confident candidates (0 without a lattice); without it, every
    /// confident candidate.
    support: usize,
    /// The marker pitch the layout follows (`None`: no lattice, the layout stays).
    layout_pitch_px: Option<f64>,
    /// With the lattice check: the de-duplicated confident candidates (sorted by y then x) and their
    /// lattice fit, which the final lattice check reuses when its accepted markers are exactly these
    /// (the MRE accepted none of the rest), as it does on most frames.
    fitted: Option<FittedSet>,
    /// The region a closer look re-examined ([`crate::close_look`]), if any.
    looked: Option<Region>,
    /// Whether the closer look found every one of `kept` at least [`SQUEEZED_NN_PITCH`] x `pitch_px`
    /// from the others: the markers, a subset of them, then hold no squeezed pair either, and the
    /// blob search between squeezed markers has nothing to search.
    spread: bool,
}

/// What the lattice check and the edge margin need of an image besides its markers.
#[derive(Debug, Clone, Copy)]
struct Frame {
    size: ImageSize,
    /// Input px per original px of the final layout.
    input_per_px: f64,
    /// The candidates' pitch (post-processing step 2).
    pitch_px: Option<f64>,
    /// The region a closer look re-examined.
    looked: Option<Region>,
    /// [`Pass::spread`].
    spread: bool,
}

/// Detections and their lattice fit at one input scale.
#[derive(Debug, Clone)]
struct FittedSet {
    detections: Vec<Detection>,
    input_per_px: f64,
    fit: LatticeFit,
}

impl FittedSet {
    /// The lattice fit of `kept_confident`, the de-duplicated candidates with c > `conf_keep`, sorted
    /// by y then x as the final accepted markers are (so that their check can reuse the fit).
    /// `confident_nn`: the nearest-neighbour distances of `candidates`' confident ones (in their
    /// order), when de-duplication dropped none of them: the same points, whose distances the pitch
    /// estimate measured; kept candidates lie pairwise apart, so both orders sort alike.
    fn of_confident(
        candidates: &[Detection],
        kept_confident: &[Detection],
        confident_nn: Option<Vec<f64>>,
        conf_keep: f32,
        check: &LatticeCheck,
        input_per_px: f64,
    ) -> Self {
        let (detections, fit) = match confident_nn {
            Some(nn) => {
                let mut with_nn: Vec<(Detection, f64)> = candidates
                    .iter()
                    .filter(|d| d.confidence > conf_keep)
                    .copied()
                    .zip(nn)
                    .collect();
                with_nn.sort_by(|a, b| crate::detection_order(&a.0, &b.0));
                let (detections, nn): (Vec<Detection>, Vec<f64>) = with_nn.into_iter().unzip();
                let fit = fit_lattice_with_distances(&detections, nn, check, input_per_px);
                (detections, fit)
            }
            None => {
                let mut detections = kept_confident.to_vec();
                crate::sort_detections(&mut detections);
                let fit = fit_lattice(&detections, check, input_per_px);
                (detections, fit)
            }
        };
        Self {
            detections,
            input_per_px,
            fit,
        }
    }

    /// The fit, if it was made of exactly `accepted` at `input_per_px`.
    fn fit_of(self, accepted: &[Detection], input_per_px: f64) -> Option<LatticeFit> {
        (self.detections == accepted && self.input_per_px == input_per_px).then_some(self.fit)
    }
}

impl Pass {
    /// The candidates of an image of `size` run under `layout`, summarised for the layout decision.
    fn new(candidates: Vec<Detection>, post: &PostProcess, size: ImageSize, layout: &InputLayout) -> Self {
        let (pitch_px, confident_nn) = pitch_of_confident(&candidates, post.conf_keep);
        let radius_px = dedup_radius_px(pitch_px, post);
        let mut kept = candidates.clone();
        deduplicate(&mut kept, radius_px);
        // Step 3 visits in descending confidence and keeps that order: the confident ones lead.
        let confident = kept.partition_point(|d| d.confidence > post.conf_keep);
        let (support, layout_pitch_px, fitted) = match &post.lattice {
            None => (confident_nn.len(), pitch_px, None),
            Some(check) => {
                let scale = input_per_px(size, layout);
                let reuse_nn = (radius_px > 0.0 && confident == confident_nn.len()).then_some(confident_nn);
                let fitted = FittedSet::of_confident(
                    &candidates,
                    &kept[..confident],
                    reuse_nn,
                    post.conf_keep,
                    check,
                    scale,
                );
                let (support, pitch) = if fitted.fit.is_lattice {
                    (fitted.fit.members, fitted.fit.pitch_px)
                } else {
                    (0, None)
                };
                (support, pitch, Some(fitted))
            }
        };
        Self {
            candidates,
            kept,
            pitch_px,
            support,
            layout_pitch_px,
            fitted,
            looked: None,
            spread: false,
        }
    }

    /// The area the supporting candidates cover (count x pitch^2, original px^2): about the gel's for a
    /// lattice and for a thinned-out one alike; a small part of it for several finds per oversized
    /// marker (the pitch then measures the spread of the duplicates).
    fn cover(&self) -> f64 {
        self.support as f64 * self.layout_pitch_px.map_or(0.0, |p| p * p)
    }
}

/// ONNX Runtime session options shared by Marknet and MRE.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SessionOptions {
    /// Intra-op threads; 0 lets ONNX Runtime choose (one per core).
    pub intra_threads: usize,
    /// Register the CUDA execution provider when this ONNX Runtime build has it (the PyPI CPU wheel
    /// does not; then the CPU provider runs).
    pub use_cuda: bool,
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            intra_threads: 0,
            use_cuda: true,
        }
    }
}

pub(crate) fn onnx_err<'a>(path: &'a Path, what: &'static str) -> impl Fn(String) -> Error + 'a {
    move |message| Error::Onnx {
        path: path.to_path_buf(),
        what,
        message,
    }
}

/// An error message when a model's output holds NaN or an infinity: broken weights (or a broken
/// export) would otherwise give no markers and no word, or infinite candidates that later stages
/// cannot place.
pub(crate) fn check_finite(data: &[f32], output: &str) -> std::result::Result<(), String> {
    match data.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(format!(
            "output '{output}' holds {} (value {i} of {}): expected finite numbers; the model's \
             weights or export are broken",
            data[i],
            data.len()
        )),
        None => Ok(()),
    }
}

/// Feature rows every healthy MRE scores with finite numbers (all zeros, all ones, a ramp): run at
/// load, they catch broken weights before any frame, since the MRE only sees the candidates Marknet
/// is unsure of and a clear image may never reach it.
#[allow(clippy::cast_precision_loss)]
const MRE_PROBE_ROWS: [[f32; MRE_FEATURES]; 3] = {
    let mut ramp = [0.0; MRE_FEATURES];
    let mut k = 0;
    while k < MRE_FEATURES {
        ramp[k] = k as f32 / MRE_FEATURES as f32;
        k += 1;
    }
    [[0.0; MRE_FEATURES], [1.0; MRE_FEATURES], ramp]
};

/// Runs Marknet once on a mid-grey input and checks every output is finite: NaN or infinite
/// weights make a model useless on every frame, so they are an error at load (naming the model)
/// rather than a flag on each frame. The input is the smallest a dynamic-input model takes (two of
/// its size multiples a side, so the probe costs little), else the declared size.
fn probe_marknet(path: &Path, session: &mut Session, contract: &MarknetContract) -> Result<()> {
    let (w, h) = match contract.auto_fit {
        Some(fit) => (2 * fit.multiple as usize, 2 * fit.multiple as usize),
        None => (contract.input_width as usize, contract.input_height as usize),
    };
    let grey = vec![0.5f32; 3 * w * h];
    let run = onnx_err(path, "a check run at load");
    let input =
        TensorRef::from_array_view(([1, 3, h, w], grey.as_slice())).map_err(|e| run(e.to_string()))?;
    let outputs = session
        .run(ort::inputs![MARKNET_INPUT => input])
        .map_err(|e| run(e.to_string()))?;
    let (_, raw) = outputs[MARKNET_OUTPUT]
        .try_extract_tensor::<f32>()
        .map_err(|e| run(e.to_string()))?;
    check_finite(raw, MARKNET_OUTPUT).map_err(|m| run(format!("{m} (on a grey image)")))
}

/// A loaded model: its session, `metadata_props`, and input / output signatures.
pub(crate) struct Opened {
    pub(crate) session: Session,
    pub(crate) metadata: BTreeMap<String, String>,
    pub(crate) inputs: Vec<TensorSpec>,
    pub(crate) outputs: Vec<TensorSpec>,
}

/// Loads a model file into a session, and reads its metadata and signature (every ONNX localizer
/// opens its model through this one function).
pub(crate) fn open_session(path: &Path, options: &SessionOptions) -> Result<Opened> {
    std::fs::metadata(path).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let load = onnx_err(path, "loading the model");
    gelstereo_core::limits::check_thread_count(options.intra_threads)
        .map_err(|e| load(format!("intra-op threads: {e}")))?;
    let rt = runtime::init()?;
    let mut builder = Session::builder(&rt.environment)
        .map_err(|e| load(e.to_string()))?
        .with_optimization_level(GraphOptimizationLevel::Level3)
        .map_err(|e| load(e.to_string()))?;
    // Idle intra-op threads block instead of busy-waiting (ONNX Runtime's default is to spin): on cores
    // shared with other work, spinning threads steal the cores the next operator needs and latency
    // gets several times worse; on an otherwise idle machine spinning would save a few percent.
    builder = builder
        .with_intra_op_spinning(false)
        .map_err(|e| load(e.to_string()))?;
    if options.intra_threads > 0 {
        builder = builder
            .with_intra_threads(options.intra_threads)
            .map_err(|e| load(e.to_string()))?;
    }
    if options.use_cuda && cuda_available() {
        builder = builder
            .with_execution_providers([ort::ep::CUDA::default().build()])
            .map_err(|e| load(e.to_string()))?;
    }
    let session = builder.commit_from_file(path).map_err(|e| load(e.to_string()))?;
    let meta_err = onnx_err(path, "reading metadata_props");
    let metadata = session.metadata().map_err(|e| meta_err(e.to_string()))?;
    let mut map = BTreeMap::new();
    for key in metadata.custom_keys().map_err(|e| meta_err(e.to_string()))? {
        if let Some(v) = metadata.custom(&key) {
            map.insert(key, v);
        }
    }
    drop(metadata);
    let spec = |o: &ort::value::Outlet| match o.dtype() {
        ValueType::Tensor { ty, shape, .. } => TensorSpec {
            name: o.name().to_owned(),
            float32: *ty == ort::value::TensorElementType::Float32,
            dims: shape.to_vec(),
        },
        _ => TensorSpec {
            name: o.name().to_owned(),
            float32: false,
            dims: Vec::new(),
        },
    };
    let inputs = session.inputs().iter().map(spec).collect();
    let outputs = session.outputs().iter().map(spec).collect();
    Ok(Opened {
        session,
        metadata: map,
        inputs,
        outputs,
    })
}

/// Checks that an image's aspect ratio is within [`MAX_ASPECT_DISTORTION`] of the network input's
/// (the contract's whole-image stretch would distort markers beyond what training covered).
pub(crate) fn check_aspect(size: ImageSize, input_width: u32, input_height: u32) -> Result<()> {
    let img = f64::from(size.width) / f64::from(size.height);
    let net = f64::from(input_width) / f64::from(input_height);
    let ratio = if img > net { img / net } else { net / img };
    if ratio > MAX_ASPECT_DISTORTION {
        return Err(Error::Image {
            property: "size",
            expected: format!(
                "an aspect ratio within {MAX_ASPECT_DISTORTION}x of the network input {input_width}x{input_height}"
            ),
            found: format!("{}x{}", size.width, size.height),
        });
    }
    Ok(())
}

/// Resizes `image` into `layout` (OpenCV bilinear `INTER_LINEAR` on the 8-bit pixels: half-pixel
/// centres, no antialiasing; the margin filled with the resized image's median colour) and writes it
/// into `plane` as planar RGB f32 in [0, 1] (grey replicated, alpha dropped), in one pass
/// bit-identical to OpenCV's resize + copyMakeBorder with that constant ([`crate::resize`]); with
/// `window`, only that rectangle of the input (`plane` holds 3 x its pixels). `scratch` is kept
/// between calls.
pub(crate) fn write_layout(
    image: &Mat,
    layout: &InputLayout,
    window: Option<&Window>,
    scratch: &mut ResizeScratch,
    plane: &mut [f32],
) -> Result<()> {
    let owned;
    let image = if image.is_continuous() {
        image
    } else {
        owned = image
            .try_clone()
            .map_err(cv_err("copy of a non-continuous image"))?;
        &owned
    };
    let size = check_image(image)?;
    let reduced;
    let image = if f64::from(layout.scaled_width) < AREA_BELOW_SCALE * f64::from(size.width)
        || f64::from(layout.scaled_height) < AREA_BELOW_SCALE * f64::from(size.height)
    {
        let mut out = Mat::default();
        let to = opencv::core::Size::new(layout.scaled_width as i32, layout.scaled_height as i32);
        opencv::imgproc::resize(image, &mut out, to, 0.0, 0.0, opencv::imgproc::INTER_AREA)
            .map_err(cv_err("area reduction of a large image"))?;
        reduced = out;
        &reduced
    } else {
        image
    };
    let view = Image {
        bytes: image.data_bytes().map_err(cv_err("image data"))?,
        width: image.cols() as usize,
        height: image.rows() as usize,
        channels: image.channels() as usize,
    };
    resize_into_planar(&view, layout, window, scratch, plane);
    Ok(())
}

/// The network input of `image` under `layout`, as Marknet feeds its network: the image resized
/// (OpenCV's `INTER_LINEAR` bit for bit, area averaging first below 0.34 x), the rest of the input
/// filled with its median colour, planar RGB f32 in [0, 1] (3 x input pixels) in `plane`. `scratch`
/// is kept between calls and chooses the kernels ([`ResizeScratch::with_kernels`]); every kernel set
/// gives the same bits. For looking at what the network sees and for timing the kernels
/// (`gelstereo bench`).
pub fn network_input(
    image: &Mat,
    layout: &InputLayout,
    scratch: &mut ResizeScratch,
    plane: &mut Vec<f32>,
) -> Result<()> {
    // The image itself is checked by `write_layout`.
    let l = layout;
    let fits = |offset: u32, scaled: u32, input: u32| {
        scaled >= 1
            && input <= MAX_INPUT_SIDE_PX
            && offset.checked_add(scaled).is_some_and(|end| end <= input)
    };
    if !fits(l.offset_x, l.scaled_width, l.input_width) || !fits(l.offset_y, l.scaled_height, l.input_height)
    {
        return Err(Error::Image {
            property: "layout",
            expected: format!(
                "a resized image of at least 1 x 1 px inside a network input of at most {MAX_INPUT_SIDE_PX} px a side"
            ),
            found: format!("{l:?}"),
        });
    }
    plane.clear();
    plane.resize(3 * l.input_width as usize * l.input_height as usize, 0.0);
    write_layout(image, layout, None, scratch, plane)
}

/// Checks `image` and writes it into `plane` under `layout` ([`write_layout`]); `stretch_to`: the
/// network input a whole-image stretch must keep the aspect ratio of ([`check_aspect`]).
///
/// The trainer divides by 255 before resizing; resizing the 8-bit image first differs by at most
/// half a grey level (rounding), which `docs/model-contract.md` allows, and halves the cost.
fn preprocess(
    image: &Mat,
    layout: &InputLayout,
    window: Option<&Window>,
    stretch_to: Option<(u32, u32)>,
    scratch: &mut ResizeScratch,
    plane: &mut [f32],
) -> Result<()> {
    let size = check_image(image)?;
    if let Some((w, h)) = stretch_to {
        check_aspect(size, w, h)?;
    }
    write_layout(image, layout, window, scratch, plane)
}

/// The input size an image runs at: its layout's, or its window's.
fn input_dims(layout: &InputLayout, window: Option<&Window>) -> (u32, u32) {
    window.map_or((layout.input_width, layout.input_height), |w| (w.width, w.height))
}

/// `items` mapped by `f`, in order: on rayon's thread pool when `parallel` and there are several
/// (the images of a batch), else on the calling thread.
fn map_images<T: Send, R: Send>(parallel: bool, items: Vec<T>, f: impl Fn(T) -> R + Sync + Send) -> Vec<R> {
    if parallel && items.len() > 1 {
        items.into_par_iter().map(f).collect()
    } else {
        items.into_iter().map(f).collect()
    }
}

/// Opens an ONNX model and returns its `metadata_props`, sorted by key (what `gelstereo doctor` reports).
pub fn model_metadata(path: &Path) -> Result<BTreeMap<String, String>> {
    Ok(open_session(path, &SessionOptions::default())?.metadata)
}

/// Whether this ONNX Runtime build includes the CUDA execution provider.
pub fn cuda_available() -> bool {
    use ort::ep::ExecutionProvider as _;
    ort::ep::CUDA::is_available().unwrap_or(false)
}

/// The Marker Rationality Evaluator: 11 features in, the probability that a candidate is right out.
pub struct Mre {
    path: PathBuf,
    session: Session,
    contract: MreContract,
    buffer: Vec<f32>,
}

impl std::fmt::Debug for Mre {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mre")
            .field("path", &self.path)
            .field("contract", &self.contract)
            .finish()
    }
}

impl Mre {
    /// Loads `path` and checks its contract.
    pub fn load(path: &Path, options: &SessionOptions) -> Result<Self> {
        let Opened {
            session,
            metadata: meta,
            inputs,
            outputs,
        } = open_session(path, options)?;
        let contract = MreContract::from_model(path, &meta, &inputs, &outputs)?;
        let mut mre = Self {
            path: path.to_path_buf(),
            session,
            contract,
            buffer: Vec::new(),
        };
        mre.score(&MRE_PROBE_ROWS)?;
        Ok(mre)
    }

    /// The model's declared contract.
    pub fn contract(&self) -> &MreContract {
        &self.contract
    }

    /// Scores a batch of feature vectors (one run); an empty batch gives an empty result.
    pub fn score(&mut self, features: &[[f32; MRE_FEATURES]]) -> Result<Vec<f32>> {
        if features.is_empty() {
            return Ok(Vec::new());
        }
        self.buffer.clear();
        self.buffer.extend(features.iter().flatten());
        let run = onnx_err(&self.path, "inference");
        let input = TensorRef::from_array_view(([features.len(), MRE_FEATURES], self.buffer.as_slice()))
            .map_err(|e| run(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs![MRE_INPUT => input])
            .map_err(|e| run(e.to_string()))?;
        let (shape, data) = outputs[MRE_OUTPUT]
            .try_extract_tensor::<f32>()
            .map_err(|e| run(e.to_string()))?;
        if data.len() != features.len() {
            return Err(run(format!(
                "output '{MRE_OUTPUT}' has shape {shape}, expected [{}, 1]",
                features.len()
            )));
        }
        check_finite(data, MRE_OUTPUT).map_err(run)?;
        Ok(data.to_vec())
    }
}

/// The Marknet localizer: `marknet` (c > `conf_marknet_only`) or, with an [`Mre`], `marknet-mre`.
pub struct Marknet {
    path: PathBuf,
    options: SessionOptions,
    session: Session,
    contract: MarknetContract,
    post: PostProcess,
    mre: Option<Mre>,
    fit: InputFit,
    /// The remembered pitches and lattice windows of the stream being localized.
    stream: StreamState,
    /// Whether squeezed parts of the lattice get a closer look ([`crate::close_look`]).
    close_look: bool,
    /// Scratch of each batch slot's preprocessing.
    resize: Vec<ResizeScratch>,
    /// Work on the images of a batch in parallel ([`set_parallel`](Self::set_parallel)).
    parallel: bool,
    input: Vec<f32>,
}

impl std::fmt::Debug for Marknet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Marknet")
            .field("path", &self.path)
            .field("contract", &self.contract)
            .field("post", &self.post)
            .field("fit", &self.fit)
            .field("mre", &self.mre)
            .finish()
    }
}

impl Marknet {
    /// Loads `path` and checks its contract; the localizer is `marknet` until [`with_mre`](Self::with_mre).
    pub fn load(path: &Path, options: &SessionOptions) -> Result<Self> {
        let Opened {
            mut session,
            metadata: meta,
            inputs,
            outputs,
        } = open_session(path, options)?;
        let contract = MarknetContract::from_model(path, &meta, &inputs, &outputs)?;
        probe_marknet(path, &mut session, &contract)?;
        Ok(Self {
            path: path.to_path_buf(),
            options: *options,
            session,
            post: contract.postprocess,
            contract,
            mre: None,
            fit: InputFit::Auto,
            stream: StreamState::default(),
            close_look: true,
            resize: Vec::new(),
            parallel: false,
            input: Vec::new(),
        })
    }

    /// Adds MRE post-processing (`marknet-mre`); MRE's confidence band must match Marknet's, and its
    /// acceptance threshold replaces the default.
    pub fn with_mre(mut self, mre: Mre) -> Result<Self> {
        mre.contract.check_compatible(&mre.path, &self.post)?;
        self.post.accept = mre.contract.accept;
        self.mre = Some(mre);
        Ok(self)
    }

    /// The model's declared contract.
    pub fn contract(&self) -> &MarknetContract {
        &self.contract
    }

    /// The post-processing thresholds in use.
    pub fn postprocess(&self) -> &PostProcess {
        &self.post
    }

    /// Replaces the post-processing thresholds (e.g. for a threshold sweep).
    pub fn set_postprocess(&mut self, post: PostProcess) {
        self.post = post;
    }

    /// Chooses how images are fitted to the network input ([`InputFit::Auto`] by default).
    pub fn set_fit(&mut self, fit: InputFit) {
        self.fit = fit;
    }

    /// Whether the "auto" fit remembers the marker pitch measured per image size (default: yes, for
    /// streams of one sensor: one pass per image). Off, every image starts without a pitch (a first
    /// pass, and a second when the pitch asks for another scale), as the trainer's evaluation does.
    pub fn set_pitch_memory(&mut self, remember: bool) {
        self.stream.set_remember_pitch(remember);
    }

    /// Whether, with the pitch remembered, each view of a stream runs on a window around the
    /// lattice its first frame showed ([`crate::window`]; default: yes). Off, every frame runs whole.
    /// Windows are kept per image size and batch slot (a stereo pair's left and right), so the images
    /// given to one slot must come from one camera: a second camera's images interleaved through
    /// [`Localizer::detect`] would each fall back to the whole input after trying the first's window
    /// (use `detect_stereo`, one localizer per camera, or turn windows off).
    pub fn set_lattice_window(&mut self, on: bool) {
        self.stream.set_lattice_window(on);
    }

    /// Whether the network looks again, at a larger scale, where the first pass's candidates lie
    /// squeezed together ([`crate::close_look`]), and blobs between the squeezed markers it still
    /// missed join them ([`crate::squeezed_blobs`]; default: yes). It needs the "auto" fit and the
    /// lattice check (it is beyond the model contract's steps, as they are).
    pub fn set_close_look(&mut self, on: bool) {
        self.close_look = on;
    }

    /// The window view `slot` (index in the batch: 0 = left, 1 = right) of images of `size` runs
    /// on, if it has one.
    pub fn lattice_window(&self, size: ImageSize, slot: usize) -> Option<LatticeWindow> {
        self.stream.window(size, slot)
    }

    /// [`Localizer::fork`]: the models loaded again with `intra_threads`, the thresholds, the fit
    /// and the remembered pitches copied.
    fn forked(&self, intra_threads: usize) -> Result<Self> {
        let options = SessionOptions {
            intra_threads,
            ..self.options
        };
        let mut net = Marknet::load(&self.path, &options)?;
        if let Some(mre) = &self.mre {
            net = net.with_mre(Mre::load(&mre.path, &options)?)?;
        }
        net.post = self.post;
        net.fit = self.fit;
        net.stream = self.stream.clone();
        net.close_look = self.close_look;
        Ok(net)
    }

    /// Whether the "auto" fit applies (an [`InputFit::Auto`] localizer on a dynamic-input model).
    fn auto_fit(&self) -> Option<&AutoFit> {
        match self.fit {
            InputFit::Auto => self.contract.auto_fit.as_ref(),
            InputFit::Stretch | InputFit::Pad => None,
        }
    }

    /// The layout of an image of `size` given its marker pitch (used by the "auto" fit only).
    pub fn layout(&self, size: ImageSize, pitch_px: Option<f64>) -> InputLayout {
        let (iw, ih) = (self.contract.input_width, self.contract.input_height);
        if let Some(fit) = self.auto_fit() {
            return fit_layout(size, pitch_px, iw, ih, fit);
        }
        match self.fit {
            InputFit::Pad => {
                let (w, h) = (f64::from(size.width), f64::from(size.height));
                let scale = (f64::from(iw) / w).min(f64::from(ih) / h).min(1.0);
                let nw = ((w * scale).round() as u32).clamp(1, iw);
                let nh = ((h * scale).round() as u32).clamp(1, ih);
                InputLayout {
                    input_width: iw,
                    input_height: ih,
                    scaled_width: nw,
                    scaled_height: nh,
                    offset_x: (iw - nw) / 2,
                    offset_y: (ih - nh) / 2,
                }
            }
            InputFit::Auto | InputFit::Stretch => InputLayout::stretch(iw, ih),
        }
    }

    /// The layout the next image of `size` gets (with the remembered pitch, if any).
    pub fn next_layout(&self, size: ImageSize) -> InputLayout {
        self.layout(size, self.stream.pitch(size))
    }

    /// Whether the images of a batch (the two views of a stereo pair) are preprocessed, decoded and
    /// post-processed in parallel on rayon's thread pool (default: no). Same results; it lowers the
    /// latency of one pair where a core is free, and only adds overhead where the cores are already
    /// busy (e.g. several localizers working on frames in parallel).
    pub fn set_parallel(&mut self, parallel: bool) {
        self.parallel = parallel;
    }

    /// Whether MRE post-processing is on (`marknet-mre`).
    pub fn has_mre(&self) -> bool {
        self.mre.is_some()
    }

    /// Runs the network once on `images` under `layouts` (each on the whole input, or on the window
    /// `windows` gives), all of one input size; returns the raw output (`[Gy, Gx, m, 3]` logits per
    /// image, row-major, concatenated), in the spans `marknet.preprocess` and `marknet.network` (a
    /// batch may take several passes under the "auto" fit).
    fn run_batch(
        &mut self,
        images: &[&Mat],
        windows: &[Option<Window>],
        layouts: &[InputLayout],
    ) -> Result<Vec<f32>> {
        let Some(first) = layouts.first() else {
            return Ok(Vec::new());
        };
        let (iw, ih) = input_dims(first, windows.first().and_then(Option::as_ref));
        let (iw, ih) = (iw as usize, ih as usize);
        let preprocessing = tracing::trace_span!("marknet.preprocess").entered();
        self.input.resize(images.len() * 3 * iw * ih, 0.0);
        if self.resize.len() < images.len() {
            self.resize.resize_with(images.len(), ResizeScratch::default);
        }
        // A stretch must keep the aspect ratio within bounds (the "auto" and "pad" layouts keep it).
        let stretch =
            self.fit == InputFit::Stretch || (self.fit == InputFit::Auto && self.contract.auto_fit.is_none());
        let stretch_to = stretch.then_some((self.contract.input_width, self.contract.input_height));
        let slots = images
            .iter()
            .zip(windows)
            .zip(layouts)
            .zip(self.input.chunks_exact_mut(3 * iw * ih))
            .zip(self.resize.iter_mut())
            .collect();
        map_images(
            self.parallel,
            slots,
            |((((image, window), layout), plane), scratch)| {
                preprocess(image, layout, window.as_ref(), stretch_to, scratch, plane)
            },
        )
        .into_iter()
        .collect::<Result<()>>()?;
        drop(preprocessing);
        let _network = tracing::trace_span!("marknet.network").entered();
        let run = onnx_err(&self.path, "inference");
        let input = TensorRef::from_array_view(([images.len(), 3, ih, iw], self.input.as_slice()))
            .map_err(|e| run(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs![MARKNET_INPUT => input])
            .map_err(|e| run(e.to_string()))?;
        let (shape, raw) = outputs[MARKNET_OUTPUT]
            .try_extract_tensor::<f32>()
            .map_err(|e| run(e.to_string()))?;
        let c = &self.contract;
        let (gy, gx) = (ih / c.stride as usize, iw / c.stride as usize);
        let per_image = gy * gx * c.candidates as usize * 3;
        if raw.len() != per_image * images.len() {
            return Err(run(format!(
                "output '{MARKNET_OUTPUT}' has shape {shape}, expected [{}, {gy}, {gx}, {}, 3]",
                images.len(),
                c.candidates
            )));
        }
        check_finite(raw, MARKNET_OUTPUT).map_err(run)?;
        Ok(raw.to_vec())
    }

    /// Runs the network on `images` as one batch under the layouts the next images of their sizes get
    /// ([`next_layout`](Self::next_layout)): each image's size and its raw output (`[Gy, Gx, m, 3]`
    /// logits, row-major, concatenated). The images must share one input size (e.g. a stereo pair).
    pub fn raw_output(&mut self, images: &[&Mat]) -> Result<(Vec<ImageSize>, Vec<f32>)> {
        let sizes = images
            .iter()
            .map(|im| check_image(im))
            .collect::<Result<Vec<_>>>()?;
        let layouts: Vec<InputLayout> = sizes.iter().map(|s| self.next_layout(*s)).collect();
        if let Some(other) = layouts
            .iter()
            .find(|l| (l.input_width, l.input_height) != (layouts[0].input_width, layouts[0].input_height))
        {
            return Err(Error::Image {
                property: "size",
                expected: format!(
                    "one network input size for the whole batch ({}x{})",
                    layouts[0].input_width, layouts[0].input_height
                ),
                found: format!("{}x{}", other.input_width, other.input_height),
            });
        }
        let raw = self.run_batch(images, &vec![None; images.len()], &layouts)?;
        Ok((sizes, raw))
    }

    /// The decoding geometry of an image of `size` under `layout`.
    pub fn geometry_for(&self, size: ImageSize, layout: &InputLayout) -> DecodeGeometry {
        layout_geometry(size, layout, self.contract.stride, self.contract.candidates)
    }

    /// [`geometry_for`](Self::geometry_for) of the network run on `window` of the layout's input.
    fn window_geometry(
        &self,
        size: ImageSize,
        layout: &InputLayout,
        window: Option<&Window>,
    ) -> DecodeGeometry {
        let whole = self.geometry_for(size, layout);
        let Some(w) = window else { return whole };
        let stride = self.contract.stride;
        DecodeGeometry {
            grid_y: (w.height / stride) as usize,
            grid_x: (w.width / stride) as usize,
            offset_x: whole.offset_x - f64::from(w.x),
            offset_y: whole.offset_y - f64::from(w.y),
            ..whole
        }
    }

    /// The decoding geometry the next image of `size` gets ([`next_layout`](Self::next_layout)).
    pub fn geometry(&self, size: ImageSize) -> DecodeGeometry {
        self.geometry_for(size, &self.next_layout(size))
    }

    /// Runs `images` under `layouts` (grouped into one batch per input size) and decodes each image's
    /// candidates with c > `min_confidence`, in its own pixels; candidates in the padding are dropped
    /// (a marker whose centre lies outside the image is not reported). An image with a window in
    /// `windows` runs on that window of its layout's input. Each image's [`Pass`].
    fn decode_pass(
        &mut self,
        images: &[&Mat],
        windows: &[Option<Window>],
        sizes: &[ImageSize],
        layouts: &[InputLayout],
        min_confidence: f32,
    ) -> Result<Vec<Pass>> {
        let post = self.post;
        self.decode_each(images, windows, sizes, layouts, min_confidence, |i, dets| {
            Pass::new(dets, &post, sizes[i], &layouts[i])
        })
    }

    /// [`decode_pass`](Self::decode_pass) with `finish` (index into `images`, its candidates) making
    /// each image's result.
    fn decode_each<T: Default + Send>(
        &mut self,
        images: &[&Mat],
        windows: &[Option<Window>],
        sizes: &[ImageSize],
        layouts: &[InputLayout],
        min_confidence: f32,
        finish: impl Fn(usize, Vec<Detection>) -> T + Sync + Send,
    ) -> Result<Vec<T>> {
        let mut found: Vec<T> = (0..images.len()).map(|_| T::default()).collect();
        let mut pending: Vec<usize> = (0..images.len()).collect();
        let dims = |i: usize| input_dims(&layouts[i], windows[i].as_ref());
        while let Some(&lead) = pending.first() {
            let key = dims(lead);
            let (group, rest): (Vec<usize>, Vec<usize>) = pending.iter().partition(|&&i| dims(i) == key);
            pending = rest;
            let batch_images: Vec<&Mat> = group.iter().map(|&i| images[i]).collect();
            let batch_windows: Vec<Option<Window>> = group.iter().map(|&i| windows[i]).collect();
            let batch_layouts: Vec<InputLayout> = group.iter().map(|&i| layouts[i]).collect();
            let raw = self.run_batch(&batch_images, &batch_windows, &batch_layouts)?;
            let per_image = raw.len() / group.len().max(1);
            let jobs = group
                .iter()
                .map(|&i| {
                    (
                        i,
                        self.window_geometry(sizes[i], &layouts[i], windows[i].as_ref()),
                    )
                })
                .zip(raw.chunks(per_image.max(1)))
                .collect();
            let decoded = map_images(self.parallel, jobs, |((i, geometry), raw)| {
                let dets = decode_in_layout(raw, &geometry, &layouts[i], sizes[i], min_confidence);
                (i, finish(i, dets))
            });
            for (i, d) in decoded {
                found[i] = d;
            }
        }
        Ok(found)
    }

    /// Runs the network on `images` and returns each image's candidates with c > `min_confidence`, in
    /// that image's pixels, in flat order (step 1 of [`crate::postprocess`]). Under the "auto" fit an
    /// image whose measured pitch asks for another scale is run again at that scale, and the pitch is
    /// remembered for its size.
    pub fn candidates(&mut self, images: &[&Mat], min_confidence: f32) -> Result<Vec<Vec<Detection>>> {
        let found = self.candidates_with_pitch(images, &vec![None; images.len()], min_confidence)?;
        Ok(found.into_iter().map(|(pass, _)| pass.candidates).collect())
    }

    /// Each image's [`FittedCandidates`]: the network passes [`Localizer::detect`] runs before its
    /// post-processing (probes, relayouts, the closer look), for a caller that post-processes the
    /// candidates itself (the trainer's evaluation scores them with and without its own MRE).
    pub fn fitted_candidates(&mut self, images: &[&Mat]) -> Result<Vec<FittedCandidates>> {
        let found = self.candidates_with_pitch(images, &vec![None; images.len()], self.post.conf_low)?;
        Ok(found
            .into_iter()
            .map(|(pass, layout)| FittedCandidates {
                candidates: pass.candidates,
                layout,
                looked: pass.looked,
            })
            .collect())
    }

    /// [`candidates`](Self::candidates), each image's as a [`Pass`] (with its pitch estimate,
    /// post-processing step 2, computed once for both the layout decision and the post-processing)
    /// and the layout it ran under. An image with a remembered window in `learnt` runs once, on
    /// that window of its layout's input.
    fn candidates_with_pitch(
        &mut self,
        images: &[&Mat],
        learnt: &[Option<LatticeWindow>],
        min_confidence: f32,
    ) -> Result<Vec<(Pass, InputLayout)>> {
        let sizes = images
            .iter()
            .map(|im| check_image(im))
            .collect::<Result<Vec<_>>>()?;
        let mut layouts: Vec<InputLayout> = sizes
            .iter()
            .zip(learnt)
            .map(|(s, r)| r.map_or_else(|| self.next_layout(*s), |r| r.layout))
            .collect();
        let windows: Vec<Option<Window>> = learnt.iter().map(|r| r.map(|r| r.window)).collect();
        let mut found = self.decode_pass(images, &windows, &sizes, &layouts, min_confidence)?;
        let Some(fit) = self.auto_fit().copied() else {
            return Ok(found.into_iter().zip(layouts).collect());
        };
        let (iw, ih) = (self.contract.input_width, self.contract.input_height);
        let whole_images: Vec<usize> = (0..images.len()).filter(|&i| learnt[i].is_none()).collect();
        let unknown: Vec<usize> = whole_images
            .iter()
            .copied()
            .filter(|&i| self.stream.pitch(sizes[i]).is_none())
            .collect();
        for scale in [PROBE_SCALE, FINE_PROBE_SCALE, COARSE_PROBE_SCALE] {
            // The fine and coarse probes only where no pass so far found a lattice; the fine one also
            // where the lattice found (with the lattice check) lies below the network's range at its
            // input: its dots barely resolved, it may be a thinned-out part of a finer lattice, whose
            // few finds lie a multiple of its pitch apart.
            let with_lattice = self.post.lattice.is_some();
            let probes: Vec<(usize, InputLayout)> = unknown
                .iter()
                .filter(|&&i| {
                    let unresolved = || {
                        let pitch = found[i].layout_pitch_px.unwrap_or(f64::INFINITY);
                        pitch * input_per_px(sizes[i], &layouts[i]) < fit.pitch_min_px
                    };
                    scale == PROBE_SCALE
                        || found[i].support < MIN_PITCH_SUPPORT
                        || (scale == FINE_PROBE_SCALE && with_lattice && unresolved())
                })
                .map(|&i| (i, probe_layout_at(sizes[i], iw, ih, &fit, scale)))
                .filter(|&(i, probe)| probe != layouts[i])
                .collect();
            let probed = self.decode_subset(images, &sizes, &probes, min_confidence)?;
            for ((i, layout), probe) in probes.into_iter().zip(probed) {
                let n = probe.support;
                let gain = n >= MIN_PITCH_SUPPORT && n as f64 >= PROBE_MIN_GAIN * found[i].support as f64;
                if gain && probe.cover() >= PROBE_MIN_COVER * found[i].cover() {
                    found[i] = probe;
                    layouts[i] = layout;
                }
            }
        }
        // Without the lattice check a pitch is any candidates' spacing (a random network's lies at its
        // output stride at every scale), and repeating would only zoom in: one relayout, as before.
        let rounds = if self.post.lattice.is_some() {
            MAX_RELAYOUTS
        } else {
            1
        };
        let mut todo = whole_images;
        for _ in 0..rounds {
            let redo = self.relayouts(&todo, &found, &sizes, &mut layouts);
            let again = self.decode_subset(images, &sizes, &redo, min_confidence)?;
            todo = redo.iter().map(|&(i, _)| i).collect();
            for ((i, _), d) in redo.into_iter().zip(again) {
                found[i] = d;
            }
            if todo.is_empty() {
                break;
            }
        }
        if self.close_look && self.post.lattice.is_some() {
            self.look_closer(images, &sizes, &layouts, &mut found, fit.multiple, min_confidence)?;
        }
        Ok(found.into_iter().zip(layouts).collect())
    }

    /// Runs the network once more where an image's pass in `found` shows squeezed candidates, on a
    /// window of its input at a larger scale ([`crate::close_look`]), and makes its pass of the
    /// merged candidates, still under its layout in `layouts` (whose scale the lattice check uses).
    fn look_closer(
        &mut self,
        images: &[&Mat],
        sizes: &[ImageSize],
        layouts: &[InputLayout],
        found: &mut [Pass],
        multiple: u32,
        min_confidence: f32,
    ) -> Result<()> {
        struct Look {
            image: usize,
            region: Region,
            zoomed: InputLayout,
            window: Window,
        }
        let mut looks = Vec::new();
        for (image, pass) in found.iter_mut().enumerate() {
            let points: Vec<Point2> = pass.kept.iter().map(|d| d.position).collect();
            let nn = nearest_neighbour_distances(&points);
            pass.spread = pass
                .pitch_px
                .is_some_and(|p| nn.iter().all(|&d| d >= SQUEEZED_NN_PITCH * p));
            let (Some(region), Some(pitch)) = (
                squeezed_region_of(&pass.kept, &nn, pass.pitch_px, sizes[image]),
                pass.pitch_px,
            ) else {
                continue;
            };
            let Some(zoom) = close_look_zoom(sizes[image], &layouts[image], pitch) else {
                continue;
            };
            let (zoomed, window) =
                close_look_input(sizes[image], &layouts[image], &region, pitch, zoom, multiple);
            if window.width > 0 && window.height > 0 {
                looks.push(Look {
                    image,
                    region,
                    zoomed,
                    window,
                });
            }
        }
        if looks.is_empty() {
            return Ok(());
        }
        let picked: Vec<&Mat> = looks.iter().map(|l| images[l.image]).collect();
        let picked_sizes: Vec<ImageSize> = looks.iter().map(|l| sizes[l.image]).collect();
        let zoomed: Vec<InputLayout> = looks.iter().map(|l| l.zoomed).collect();
        let windows: Vec<Option<Window>> = looks.iter().map(|l| Some(l.window)).collect();
        let closer = self.decode_each(
            &picked,
            &windows,
            &picked_sizes,
            &zoomed,
            min_confidence,
            |_, dets| dets,
        )?;
        let post = self.post;
        for (look, closer) in looks.into_iter().zip(closer) {
            let i = look.image;
            let first = std::mem::take(&mut found[i].candidates);
            found[i] = Pass::new(merge(first, closer, &look.region), &post, sizes[i], &layouts[i]);
            found[i].looked = Some(look.region);
        }
        Ok(())
    }

    /// The images of `todo` to run again and their new layouts (set in `layouts`): those whose pass
    /// measured a pitch (with enough support) that asks for a layout more than
    /// [`RELAYOUT_SCALE_CHANGE`] away and, with the pitch remembered, every image of a size under the
    /// layout the next one gets; the remembered pitch follows the measured one.
    fn relayouts(
        &mut self,
        todo: &[usize],
        found: &[Pass],
        sizes: &[ImageSize],
        layouts: &mut [InputLayout],
    ) -> Vec<(usize, InputLayout)> {
        let mut wanted: Vec<Option<InputLayout>> = vec![None; found.len()];
        for &i in todo {
            let pass = &found[i];
            // Too few markers to trust a pitch (an empty or unusual frame): keep the layout.
            let Some(pitch) = pass.layout_pitch_px.filter(|_| pass.support >= MIN_PITCH_SUPPORT) else {
                continue;
            };
            let layout = self.layout(sizes[i], Some(pitch));
            let relayout = layouts[i].needs_relayout(&layout);
            if relayout {
                wanted[i] = Some(layout);
            }
            self.stream.learn_pitch(sizes[i], pitch, relayout);
        }
        // With the pitch remembered, every image of a size runs under the layout the next one gets,
        // including the first (measured under the layout without a pitch, a few % off in scale): a
        // tracker's reference frame localized at another scale than the frames compared with it
        // carries a per-marker bias into every displacement.
        let mut redo = Vec::new();
        for &i in todo {
            let target = if self.stream.pitch(sizes[i]).is_some() {
                Some(self.next_layout(sizes[i]))
            } else {
                wanted[i]
            };
            if let Some(target) = target.filter(|t| *t != layouts[i]) {
                layouts[i] = target;
                redo.push((i, target));
            }
        }
        redo
    }

    /// [`decode_pass`](Self::decode_pass) over the whole images picked by `subset` (index into
    /// `images` and `sizes`, layout to run it at), in the order of `subset`; nothing runs for an empty
    /// one.
    fn decode_subset(
        &mut self,
        images: &[&Mat],
        sizes: &[ImageSize],
        subset: &[(usize, InputLayout)],
        min_confidence: f32,
    ) -> Result<Vec<Pass>> {
        if subset.is_empty() {
            return Ok(Vec::new());
        }
        let picked: Vec<&Mat> = subset.iter().map(|&(i, _)| images[i]).collect();
        let picked_sizes: Vec<ImageSize> = subset.iter().map(|&(i, _)| sizes[i]).collect();
        let layouts: Vec<InputLayout> = subset.iter().map(|&(_, l)| l).collect();
        self.decode_pass(
            &picked,
            &vec![None; picked.len()],
            &picked_sizes,
            &layouts,
            min_confidence,
        )
    }

    /// Full localization of a batch of images: network, post-processing and (with MRE) one MRE run
    /// for all images' pending candidates.
    pub fn detect_batch(&mut self, images: &[&Mat]) -> Result<Vec<Vec<Detection>>> {
        Ok(self
            .detect_batch_tiered(images)?
            .into_iter()
            .map(|t| t.accepted)
            .collect())
    }

    /// [`detect_batch`](Self::detect_batch) with each image's rejected candidates as second tier
    /// ([`Selection::finish_tiered`]); same accepted markers, same cost.
    /// The call runs in the span `marknet.postprocess`, the network passes' spans nested in it
    /// (crate docs, "Timing").
    pub fn detect_batch_tiered(&mut self, images: &[&Mat]) -> Result<Vec<TieredDetections>> {
        let _postprocess = tracing::trace_span!("marknet.postprocess").entered();
        self.localize_batch(images)
    }

    /// Localizes a batch: each image on its view's remembered window ([`crate::window`]) where it
    /// has one and the window holds the frame's lattice, else whole. A view's first frame with a
    /// lattice (and a remembered pitch) gives the view its window, and is then localized on it, as
    /// every later frame of the view will be (one scale and sampling for a tracker's reference frame
    /// and the frames compared with it).
    fn localize_batch(&mut self, images: &[&Mat]) -> Result<Vec<TieredDetections>> {
        let sizes = images
            .iter()
            .map(|im| check_image(im))
            .collect::<Result<Vec<_>>>()?;
        let learnt: Vec<Option<LatticeWindow>> = sizes
            .iter()
            .enumerate()
            .map(|(slot, &size)| self.stream.current_window(size, slot))
            .collect();
        let mut found = self.detect_in(images, &learnt)?;
        let fallen: Vec<(usize, Option<LatticeWindow>)> = (0..images.len())
            .filter(|&i| learnt[i].is_some_and(|r| !r.holds(&found[i].accepted, sizes[i])))
            .map(|i| (i, None))
            .collect();
        for (i, again) in self.detect_subset(images, &fallen)? {
            found[i] = again;
        }
        self.learn_windows(images, &sizes, &learnt, &mut found)?;
        Ok(found)
    }

    /// Gives each view without a window (`learnt`) one around the lattice of its markers in `found`,
    /// where it may learn one, and localizes its image again on it, as every later frame of the view
    /// will be; a window that does not hold even there is remembered as none.
    fn learn_windows(
        &mut self,
        images: &[&Mat],
        sizes: &[ImageSize],
        learnt: &[Option<LatticeWindow>],
        found: &mut [TieredDetections],
    ) -> Result<()> {
        let fresh: Vec<(usize, Option<LatticeWindow>)> = (0..images.len())
            .filter(|&i| learnt[i].is_none() && self.may_learn_window(sizes[i], i, found[i].accepted.len()))
            .map(|i| (i, self.window_around(sizes[i], &found[i].accepted)))
            .collect();
        let tried: Vec<(usize, Option<LatticeWindow>)> =
            fresh.iter().copied().filter(|(_, r)| r.is_some()).collect();
        let mut kept = vec![false; images.len()];
        for ((i, window), (_, again)) in tried.iter().zip(self.detect_subset(images, &tried)?) {
            if window.is_some_and(|r| r.holds(&again.accepted, sizes[*i])) {
                kept[*i] = true;
                found[*i] = again;
            }
        }
        for (i, r) in fresh {
            self.stream.learn_window(sizes[i], i, r.filter(|_| kept[i]));
        }
        Ok(())
    }

    /// [`detect_in`](Self::detect_in) over the images picked by `subset` (index into `images`, the
    /// window to run it on, if any): each picked index with its markers.
    fn detect_subset(
        &mut self,
        images: &[&Mat],
        subset: &[(usize, Option<LatticeWindow>)],
    ) -> Result<Vec<(usize, TieredDetections)>> {
        if subset.is_empty() {
            return Ok(Vec::new());
        }
        let picked: Vec<&Mat> = subset.iter().map(|&(i, _)| images[i]).collect();
        let learnt: Vec<Option<LatticeWindow>> = subset.iter().map(|&(_, r)| r).collect();
        let found = self.detect_in(&picked, &learnt)?;
        Ok(subset.iter().map(|&(i, _)| i).zip(found).collect())
    }

    /// Whether view `slot` of images of `size` may learn its window from a frame with `markers`
    /// markers: windows on, the isotropic "auto" fit, a remembered pitch, nothing learnt yet.
    fn may_learn_window(&self, size: ImageSize, slot: usize, markers: usize) -> bool {
        markers >= WINDOW_MIN_MARKERS
            && self.auto_fit().is_some_and(|f| !f.prefer_stretch)
            && self.stream.may_learn_window(size, slot)
    }

    /// The window around `markers` of an image of `size` in the input of the remembered pitch's
    /// layout ([`window::window_around`]).
    fn window_around(&self, size: ImageSize, markers: &[Detection]) -> Option<LatticeWindow> {
        let pitch = self.stream.pitch(size)?;
        let multiple = self.auto_fit()?.multiple;
        window::window_around(markers, size, pitch, &self.next_layout(size), multiple)
    }

    /// Localizes `images` (each whole, or on its remembered window in `learnt`).
    fn detect_in(
        &mut self,
        images: &[&Mat],
        learnt: &[Option<LatticeWindow>],
    ) -> Result<Vec<TieredDetections>> {
        let with_mre = self.mre.is_some();
        let post = self.post;
        let candidates = self.candidates_with_pitch(images, learnt, post.conf_low)?;
        // Per image: its size, the input px per original px of its final layout (for the lattice
        // check) and its candidates' pitch (for the edge margin).
        let frames: Vec<Frame> = candidates
            .iter()
            .zip(images)
            .map(|((pass, layout), image)| {
                let size = ImageSize {
                    width: image.cols().max(0) as u32,
                    height: image.rows().max(0) as u32,
                };
                Frame {
                    size,
                    input_per_px: input_per_px(size, layout),
                    pitch_px: pass.pitch_px,
                    looked: pass.looked,
                    spread: pass.spread,
                }
            })
            .collect();
        let (selections, fitted): (Vec<Selection>, Vec<Option<FittedSet>>) =
            map_images(self.parallel, candidates, |(pass, _)| {
                let selection = Selection::of_deduplicated(pass.kept, pass.pitch_px, &post, with_mre);
                (selection, pass.fitted)
            })
            .into_iter()
            .unzip();
        let finish = |found: TieredDetections, fitted: Option<FittedSet>, frame: Frame| {
            // The lattice check, beyond the model contract's steps (the border is settled after it).
            let Some(check) = &post.lattice else {
                return found;
            };
            let scale = frame.input_per_px;
            let fit = fitted
                .and_then(|f| f.fit_of(&found.accepted, scale))
                .unwrap_or_else(|| fit_lattice(&found.accepted, check, scale));
            keep_fitted_lattice(found, fit, check, frame.looked.as_ref(), Some(frame.size))
        };
        let pitch_and_spread: Vec<(Option<f64>, bool)> =
            frames.iter().map(|f| (f.pitch_px, f.spread)).collect();
        let found: Vec<TieredDetections> = match self.mre.as_mut() {
            None => selections
                .into_iter()
                .zip(fitted)
                .zip(frames)
                .map(|((s, fitted), frame)| finish(s.finish_tiered(&[], post.accept), fitted, frame))
                .collect(),
            Some(mre) => {
                let features: Vec<[f32; MRE_FEATURES]> = selections
                    .iter()
                    .flat_map(|s| s.features.iter().copied())
                    .collect();
                let scores = mre.score(&features)?;
                let mut offset = 0;
                selections
                    .into_iter()
                    .zip(fitted)
                    .zip(frames)
                    .map(|((s, fitted), frame)| {
                        let n = s.pending.len();
                        let mine = scores.get(offset..offset + n).unwrap_or(&[]);
                        offset += n;
                        finish(s.finish_tiered(mine, post.accept), fitted, frame)
                    })
                    .collect()
            }
        };
        if post.lattice.is_none() {
            return Ok(found);
        }
        // Dots the network missed, found as blobs: between squeezed markers (part of the closer
        // look), then where the lattice's lines put a site at a hole or at the border.
        let close_look = self.close_look;
        found
            .into_iter()
            .zip(images)
            .zip(pitch_and_spread)
            .map(|((found, image), (pitch, spread))| {
                after_the_lattice(found, image, pitch, close_look && !spread)
            })
            .collect()
    }
}

/// The steps after the lattice check on one image: the dots-on-a-gel check, the border, and the
/// dots the network missed, found as blobs (between squeezed markers when `between_squeezed`, then
/// at the lattice's empty sites). `pitch`: the candidates' pitch (post-processing step 2).
pub fn after_the_lattice(
    mut found: TieredDetections,
    image: &Mat,
    pitch: Option<f64>,
    between_squeezed: bool,
) -> Result<TieredDetections> {
    // A regular pattern that is no marker gel (a checkerboard, a weave) can pass the lattice
    // check; its "markers" then lose the look of dots on a gel.
    if judge_the_dots(image, &found.accepted)?.is_some_and(|v| !v.dots()) {
        let rejected = std::mem::take(&mut found.accepted);
        found.second_tier.extend(rejected);
        return Ok(found);
    }
    settle_the_border(&mut found, image, pitch)?;
    let before = found.accepted.len();
    if between_squeezed {
        let blobs = blobs_between_squeezed(image, &found.accepted, pitch)?;
        found.accepted.extend(blobs);
    }
    let at_sites = blobs_at_empty_sites(image, &found.accepted, pitch)?;
    found.accepted.extend(at_sites);
    if found.accepted.len() > before {
        crate::sort_detections(&mut found.accepted);
    }
    Ok(found)
}

impl Localizer for Marknet {
    fn name(&self) -> &str {
        if self.mre.is_some() {
            "marknet-mre"
        } else {
            "marknet"
        }
    }

    fn detect(&mut self, image: &Mat) -> Result<Vec<Detection>> {
        Ok(self.detect_batch(&[image])?.pop().unwrap_or_default())
    }

    fn mre_band_top(&self) -> Option<f32> {
        self.mre.is_some().then_some(self.post.conf_keep)
    }

    fn set_parallel(&mut self, parallel: bool) {
        Marknet::set_parallel(self, parallel);
    }

    fn fork(&self, intra_threads: usize) -> Option<Result<Box<dyn Localizer + Send>>> {
        Some(
            self.forked(intra_threads)
                .map(|n| Box::new(n) as Box<dyn Localizer + Send>),
        )
    }

    fn detect_stereo(&mut self, pair: &StereoPair<Mat>) -> Result<StereoPair<Vec<Detection>>> {
        let t = self.detect_stereo_tiered(pair)?;
        Ok(StereoPair::new(t.left.accepted, t.right.accepted))
    }

    fn detect_tiered(&mut self, image: &Mat) -> Result<TieredDetections> {
        Ok(self.detect_batch_tiered(&[image])?.pop().unwrap_or_default())
    }

    fn detect_stereo_tiered(&mut self, pair: &StereoPair<Mat>) -> Result<StereoPair<TieredDetections>> {
        crate::check_stereo_sizes(pair)?;
        let mut out = self.detect_batch_tiered(&[&pair.left, &pair.right])?;
        let right = out.pop().unwrap_or_default();
        let left = out.pop().unwrap_or_default();
        Ok(StereoPair::new(left, right))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Kernels;
    use opencv::core::{CV_8UC1, CV_8UC3, CV_8UC4, Scalar};
    use opencv::prelude::*;

    /// A jittered 14 x 11 lattice (pitch 20 px) of confident candidates in a scrambled order, with
    /// doubtful ones between its dots, a row of 8 confident ones 45 px apart below it, and
    /// `duplicates` confident near-copies of its dots.
    fn lattice_candidates(duplicates: usize) -> Vec<Detection> {
        let jitter = |k: usize| ((k * 7919 + 13) % 1000) as f64 / 1000.0 - 0.5;
        let mut out = Vec::new();
        for k in 0..154 {
            let site = (k * 37) % 154;
            let (col, row) = ((site % 14) as f64, (site / 14) as f64);
            let (x, y) = (30.0 + 20.0 * col + jitter(k), 30.0 + 20.0 * row + jitter(k + 500));
            let c = 0.45 + 0.5 * (jitter(k + 900) + 0.5) as f32;
            let at = |x: f64, y: f64, confidence: f32| Detection {
                position: gelstereo_core::Point2::new(x, y),
                confidence,
            };
            out.push(at(x, y, c));
            if k % 3 == 0 {
                out.push(at(x + 10.0, y + 10.0, 0.25));
            }
            if k < duplicates {
                out.push(at(x + 1.0, y - 1.0, c - 0.01));
            }
            // Confident finds off the lattice, far apart: their distances must stay theirs.
            if k < 8 {
                out.push(at(30.0 + 45.0 * k as f64, 310.0, 0.9));
            }
        }
        out
    }

    /// The pass de-duplicates all candidates once and reuses the pitch estimate's nearest-neighbour
    /// distances for the lattice check when no confident candidate was dropped: among the confident
    /// ones it keeps exactly what de-duplicating them alone keeps, and its fit is the one
    /// `fit_lattice` makes of them, with and without dropped duplicates.
    #[test]
    fn one_deduplication_and_reused_distances_leave_the_fit_as_it_was() {
        let post = PostProcess::default();
        let check = post.lattice.expect("the default has the lattice check");
        let size = ImageSize {
            width: 340,
            height: 340,
        };
        for duplicates in [0, 5] {
            let candidates = lattice_candidates(duplicates);
            let pass = Pass::new(candidates.clone(), &post, size, &InputLayout::stretch(340, 340));
            let radius = dedup_radius_px(pass.pitch_px, &post);
            let mut alone: Vec<Detection> = candidates
                .iter()
                .filter(|d| d.confidence > post.conf_keep)
                .copied()
                .collect();
            deduplicate(&mut alone, radius);
            assert_eq!(alone.len(), 162, "{duplicates} duplicates");
            assert_eq!(&pass.kept[..alone.len()], &alone[..]);
            assert!(
                pass.kept[alone.len()..]
                    .iter()
                    .all(|d| d.confidence <= post.conf_keep)
            );
            crate::sort_detections(&mut alone);
            let fitted = pass.fitted.expect("the lattice check runs");
            assert_eq!(fitted.detections, alone);
            assert_eq!(fitted.fit, fit_lattice(&alone, &check, 1.0));
            assert!(fitted.fit.is_lattice && (150..=154).contains(&fitted.fit.members));
        }
    }

    /// Every pixel value at every channel position, converted exactly as `v / 255` into the right
    /// plane (B, G, R swapped to R, G, B; grey replicated; alpha dropped) when the image is the
    /// input's size.
    #[test]
    fn planar_rgb_is_exact_for_grey_bgr_and_bgra() -> Result<()> {
        for (typ, n) in [(CV_8UC1, 1usize), (CV_8UC3, 3), (CV_8UC4, 4)] {
            let (w, h) = (37, 29);
            let mut m =
                Mat::new_rows_cols_with_default(h, w, typ, Scalar::all(0.0)).map_err(cv_err("test"))?;
            for (i, v) in m.data_bytes_mut().map_err(cv_err("test"))?.iter_mut().enumerate() {
                *v = (i * 7 % 256) as u8;
            }
            let bytes = m.data_bytes().map_err(cv_err("test"))?.to_vec();
            let hw = (w * h) as usize;
            let mut plane = vec![-1.0f32; 3 * hw];
            let same = InputLayout::stretch(w as u32, h as u32);
            write_layout(&m, &same, None, &mut ResizeScratch::default(), &mut plane)?;
            for p in 0..hw {
                let px = &bytes[n * p..n * p + n];
                let (r, g, b) = if n == 1 {
                    (px[0], px[0], px[0])
                } else {
                    (px[2], px[1], px[0])
                };
                for (c, v) in [r, g, b].into_iter().enumerate() {
                    assert_eq!(
                        plane[c * hw + p].to_bits(),
                        (v as f32 / 255.0).to_bits(),
                        "{n} channels, px {p}"
                    );
                }
            }
        }
        Ok(())
    }

    /// `network_input` gives the same bits with every kernel set and refuses a layout whose resized
    /// image does not fit its input, naming the layout.
    #[test]
    fn the_network_input_is_the_same_with_every_kernel_set_and_a_bad_layout_is_refused() -> Result<()> {
        let mut m =
            Mat::new_rows_cols_with_default(480, 640, CV_8UC3, Scalar::all(0.0)).map_err(cv_err("test"))?;
        for (i, v) in m.data_bytes_mut().map_err(cv_err("test"))?.iter_mut().enumerate() {
            *v = (i * 31 % 253) as u8;
        }
        let layout = InputLayout {
            input_width: 416,
            input_height: 320,
            scaled_width: 406,
            scaled_height: 304,
            offset_x: 5,
            offset_y: 8,
        };
        let mut inputs = Vec::new();
        for kernels in [Kernels::Avx512, Kernels::Sse, Kernels::Scalar] {
            let mut plane = Vec::new();
            network_input(&m, &layout, &mut ResizeScratch::with_kernels(kernels), &mut plane)?;
            assert_eq!(plane.len(), 3 * 416 * 320);
            inputs.push(plane.iter().map(|v| v.to_bits()).collect::<Vec<u32>>());
        }
        assert!(inputs.windows(2).all(|w| w[0] == w[1]));
        let too_wide = InputLayout {
            offset_x: 20,
            ..layout
        };
        let err = network_input(&m, &too_wide, &mut ResizeScratch::default(), &mut Vec::new())
            .expect_err("a resized image past the input's edge");
        assert!(err.to_string().contains("image layout"), "{err}");
        Ok(())
    }
}
