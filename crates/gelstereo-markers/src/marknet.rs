//! Marknet (and its MRE) through ONNX Runtime: loading with a contract check, preprocessing any image
//! size, batched inference of both stereo views, decoding and post-processing.
//!
//! Preprocessing (`docs/model-contract.md`): the whole image is resized with OpenCV's bilinear
//! `INTER_LINEAR` (half-pixel centres) to the network input, converted to planar RGB f32 in [0, 1]
//! (grey replicated, BGRA's alpha dropped). A frame already of the input size is not resized.
//! Outputs are mapped back with `x_orig = x_in * W / input_width - 0.5` (likewise y).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use gelstereo_core::{Detection, ImageSize, StereoPair};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Size};
use opencv::imgproc;
use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{TensorRef, ValueType};

use crate::contract::{MARKNET_INPUT, MARKNET_OUTPUT, MRE_FEATURES, MRE_INPUT, MRE_OUTPUT, TensorSpec};
use crate::postprocess::{DecodeGeometry, Selection, decode};
use crate::{
    CpuClock, Error, LocalizationTimes, Localizer, MarknetContract, MreContract, PostProcess, Result,
    check_image, cv_err, runtime,
};

/// Largest accepted ratio between an image's aspect ratio and the network input's: beyond it the resize
/// squashes markers into shapes far from anything the network was trained on.
pub const MAX_ASPECT_DISTORTION: f64 = 2.0;

/// How an image is brought to the network's input size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum InputFit {
    /// The contract's preprocessing: the whole image resized to the input size (anisotropically if
    /// the aspect ratios differ). What the model was trained and evaluated with.
    #[default]
    Stretch,
    /// Isotropic: scaled by `min(input_width / W, input_height / H, 1)` (never enlarged), centred, the
    /// rest filled by mirroring the image (OpenCV `BORDER_REFLECT_101`). For sensors whose marker
    /// pitch the stretch would push outside the range the network was trained on (e.g. a 320x240
    /// GelSight Mini video, 31 px pitch, stretched to 40 x 54 px); detections in the padding are dropped.
    Pad,
}

impl std::str::FromStr for InputFit {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "stretch" => Ok(Self::Stretch),
            "pad" => Ok(Self::Pad),
            _ => Err(Error::Config {
                path: PathBuf::from("(command line)"),
                field: "fit".into(),
                expected: "stretch or pad".into(),
                found: s.to_owned(),
            }),
        }
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
    let rt = runtime::init()?;
    let load = onnx_err(path, "loading the model");
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

/// An 8-bit pixel value as the network's [0, 1] float, `v / 255` (correctly rounded; a plain division
/// vectorises, where a lookup table does not).
#[inline(always)]
fn unit(v: u8) -> f32 {
    f32::from(v) / 255.0
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

/// Writes `src` (8-bit grey, BGR or BGRA, already of the network input size) into `plane` as planar
/// RGB f32 in [0, 1] (`plane.len()` = 3 x pixels; grey is replicated, alpha dropped).
pub(crate) fn write_planar_rgb(src: &Mat, plane: &mut [f32]) -> Result<()> {
    let owned;
    let src = if src.is_continuous() {
        src
    } else {
        owned = src
            .try_clone()
            .map_err(cv_err("copy of a non-continuous image"))?;
        &owned
    };
    let bytes = src.data_bytes().map_err(cv_err("image data"))?;
    let hw = plane.len() / 3;
    let (r, rest) = plane.split_at_mut(hw);
    let (g, b) = rest.split_at_mut(hw);
    // Index loops over slices cut to the same length: bounds checks vanish and the loops vectorise.
    match src.channels().max(1) as usize {
        1 => {
            let m = hw.min(bytes.len());
            let (r, g, b) = (&mut r[..m], &mut g[..m], &mut b[..m]);
            for (i, &v) in bytes[..m].iter().enumerate() {
                let v = unit(v);
                (r[i], g[i], b[i]) = (v, v, v);
            }
        }
        3 => {
            let m = hw.min(bytes.len() / 3);
            let (r, g, b, px) = (&mut r[..m], &mut g[..m], &mut b[..m], &bytes[..3 * m]);
            for i in 0..m {
                (b[i], g[i], r[i]) = (unit(px[3 * i]), unit(px[3 * i + 1]), unit(px[3 * i + 2]));
            }
        }
        2 => {
            return Err(Error::Image {
                property: "channels",
                expected: "1 (grey), 3 (BGR) or 4 (BGRA)".into(),
                found: "2".into(),
            });
        }
        n => {
            let m = hw.min(bytes.len() / n);
            let (r, g, b, px) = (&mut r[..m], &mut g[..m], &mut b[..m], &bytes[..n * m]);
            for i in 0..m {
                (b[i], g[i], r[i]) = (unit(px[n * i]), unit(px[n * i + 1]), unit(px[n * i + 2]));
            }
        }
    }
    Ok(())
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
        Ok(Self {
            path: path.to_path_buf(),
            session,
            contract,
            buffer: Vec::new(),
        })
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
        Ok(data.to_vec())
    }
}

/// The Marknet localizer: `marknet` (c > `conf_marknet_only`) or, with an [`Mre`], `marknet-mre`.
pub struct Marknet {
    path: PathBuf,
    session: Session,
    contract: MarknetContract,
    post: PostProcess,
    mre: Option<Mre>,
    fit: InputFit,
    resized: Mat,
    padded: Mat,
    input: Vec<f32>,
    times: LocalizationTimes,
    clock: Option<CpuClock>,
    /// CPU time at the start of the latest batch, after preprocessing and after the network, ns.
    cpu_marks: [Option<u64>; 3],
}

impl std::fmt::Debug for Marknet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Marknet")
            .field("path", &self.path)
            .field("contract", &self.contract)
            .field("post", &self.post)
            .field("mre", &self.mre)
            .finish()
    }
}

impl Marknet {
    /// Loads `path` and checks its contract; the localizer is `marknet` until [`with_mre`](Self::with_mre).
    pub fn load(path: &Path, options: &SessionOptions) -> Result<Self> {
        let Opened {
            session,
            metadata: meta,
            inputs,
            outputs,
        } = open_session(path, options)?;
        let contract = MarknetContract::from_model(path, &meta, &inputs, &outputs)?;
        Ok(Self {
            path: path.to_path_buf(),
            session,
            post: contract.postprocess,
            contract,
            mre: None,
            fit: InputFit::Stretch,
            resized: Mat::default(),
            padded: Mat::default(),
            input: Vec::new(),
            times: LocalizationTimes::default(),
            clock: None,
            cpu_marks: [None; 3],
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

    /// Chooses how images are fitted to the network input ([`InputFit::Stretch`] by default).
    pub fn set_fit(&mut self, fit: InputFit) {
        self.fit = fit;
    }

    /// The padded layout of an image of `size` ([`InputFit::Pad`]): scaled size and offsets in input px.
    fn pad_layout(&self, size: ImageSize) -> (i32, i32, i32, i32) {
        let (iw, ih) = (
            f64::from(self.contract.input_width),
            f64::from(self.contract.input_height),
        );
        let (w, h) = (f64::from(size.width), f64::from(size.height));
        let scale = (iw / w).min(ih / h).min(1.0);
        let nw = ((w * scale).round() as i32).clamp(1, iw as i32);
        let nh = ((h * scale).round() as i32).clamp(1, ih as i32);
        (nw, nh, (iw as i32 - nw) / 2, (ih as i32 - nh) / 2)
    }

    /// Whether MRE post-processing is on (`marknet-mre`).
    pub fn has_mre(&self) -> bool {
        self.mre.is_some()
    }

    /// Resizes `image` to the network input (OpenCV bilinear `INTER_LINEAR` on the 8-bit pixels: half-pixel
    /// centres, no antialiasing) and writes it as planar RGB f32 in [0, 1] into batch slot `slot`.
    ///
    /// The trainer divides by 255 before resizing; resizing the 8-bit image first differs by at most
    /// half a grey level (rounding), which `docs/model-contract.md` allows, and halves the cost.
    fn preprocess(&mut self, image: &Mat, slot: usize) -> Result<ImageSize> {
        let size = check_image(image)?;
        let (iw, ih) = (
            self.contract.input_width as i32,
            self.contract.input_height as i32,
        );
        let src: &Mat = match self.fit {
            InputFit::Stretch => {
                check_aspect(size, self.contract.input_width, self.contract.input_height)?;
                if image.cols() == iw && image.rows() == ih {
                    image
                } else {
                    imgproc::resize(
                        image,
                        &mut self.resized,
                        Size::new(iw, ih),
                        0.0,
                        0.0,
                        imgproc::INTER_LINEAR,
                    )
                    .map_err(cv_err("resize to the network input"))?;
                    &self.resized
                }
            }
            InputFit::Pad => {
                let (nw, nh, ox, oy) = self.pad_layout(size);
                let scaled: &Mat = if nw == image.cols() && nh == image.rows() {
                    image
                } else {
                    imgproc::resize(
                        image,
                        &mut self.resized,
                        Size::new(nw, nh),
                        0.0,
                        0.0,
                        imgproc::INTER_LINEAR,
                    )
                    .map_err(cv_err("resize to the network input"))?;
                    &self.resized
                };
                let (top, left) = (oy, ox);
                let (bottom, right) = (ih - nh - oy, iw - nw - ox);
                // Mirroring needs a border smaller than the image; tiny images repeat their edge instead.
                let mode = if top.max(bottom) < nh && left.max(right) < nw {
                    opencv::core::BORDER_REFLECT_101
                } else {
                    opencv::core::BORDER_REPLICATE
                };
                opencv::core::copy_make_border(
                    scaled,
                    &mut self.padded,
                    top,
                    bottom,
                    left,
                    right,
                    mode,
                    opencv::core::Scalar::default(),
                )
                .map_err(cv_err("padding to the network input"))?;
                &self.padded
            }
        };
        let hw = (iw * ih) as usize;
        write_planar_rgb(src, &mut self.input[slot * 3 * hw..(slot + 1) * 3 * hw])?;
        Ok(size)
    }

    /// Runs the network on `images` (one batch): each image's size and its raw output (`[Gy, Gx, m, 3]`
    /// logits, row-major, `Gy * Gx * m * 3` values per image, concatenated).
    pub fn raw_output(&mut self, images: &[&Mat]) -> Result<(Vec<ImageSize>, Vec<f32>)> {
        if images.is_empty() {
            return Ok((Vec::new(), Vec::new()));
        }
        let (iw, ih) = (
            self.contract.input_width as usize,
            self.contract.input_height as usize,
        );
        self.cpu_marks[0] = self.clock.and_then(|c| c());
        let t0 = std::time::Instant::now();
        self.input.resize(images.len() * 3 * iw * ih, 0.0);
        let mut sizes = Vec::with_capacity(images.len());
        for (slot, image) in images.iter().enumerate() {
            sizes.push(self.preprocess(image, slot)?);
        }
        let t1 = std::time::Instant::now();
        self.cpu_marks[1] = self.clock.and_then(|c| c());
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
        let per_image = (c.grid_y * c.grid_x * c.candidates * 3) as usize;
        if raw.len() != per_image * images.len() {
            return Err(run(format!(
                "output '{MARKNET_OUTPUT}' has shape {shape}, expected [{}, {}, {}, {}, 3]",
                images.len(),
                c.grid_y,
                c.grid_x,
                c.candidates
            )));
        }
        let raw = raw.to_vec();
        self.times.preprocess_ms = (t1 - t0).as_secs_f64() * 1e3;
        self.times.network_ms = t1.elapsed().as_secs_f64() * 1e3;
        self.cpu_marks[2] = self.clock.and_then(|c| c());
        Ok((sizes, raw))
    }

    /// The decoding geometry for an image of `size` under this model's contract and the input fit.
    pub fn geometry(&self, size: ImageSize) -> DecodeGeometry {
        let c = &self.contract;
        let (scale_x, scale_y, offset_x, offset_y) = match self.fit {
            InputFit::Stretch => (
                f64::from(size.width) / f64::from(c.input_width),
                f64::from(size.height) / f64::from(c.input_height),
                0.0,
                0.0,
            ),
            InputFit::Pad => {
                let (nw, nh, ox, oy) = self.pad_layout(size);
                (
                    f64::from(size.width) / f64::from(nw),
                    f64::from(size.height) / f64::from(nh),
                    f64::from(ox),
                    f64::from(oy),
                )
            }
        };
        DecodeGeometry {
            grid_y: c.grid_y as usize,
            grid_x: c.grid_x as usize,
            candidates: c.candidates as usize,
            stride: f64::from(c.stride),
            scale_x,
            scale_y,
            offset_x,
            offset_y,
        }
    }

    /// Runs the network on `images` (one batch) and returns each image's candidates with
    /// c > `min_confidence`, in that image's pixels, in flat order (step 1 of [`crate::postprocess`]).
    pub fn candidates(&mut self, images: &[&Mat], min_confidence: f32) -> Result<Vec<Vec<Detection>>> {
        let (sizes, raw) = self.raw_output(images)?;
        let per_image = raw.len() / sizes.len().max(1);
        let pad = self.fit == InputFit::Pad;
        Ok(sizes
            .iter()
            .enumerate()
            .map(|(i, size)| {
                let mut found = decode(
                    &raw[i * per_image..(i + 1) * per_image],
                    &self.geometry(*size),
                    min_confidence,
                );
                if pad {
                    // Candidates in the mirrored padding are reflections, not markers of the image.
                    let (w, h) = (f64::from(size.width) - 0.5, f64::from(size.height) - 0.5);
                    found
                        .retain(|d| (-0.5..=w).contains(&d.position.x) && (-0.5..=h).contains(&d.position.y));
                }
                found
            })
            .collect())
    }

    /// Full localization of a batch of images: network, post-processing and (with MRE) one MRE run
    /// for all images' pending candidates.
    pub fn detect_batch(&mut self, images: &[&Mat]) -> Result<Vec<Vec<Detection>>> {
        let started = std::time::Instant::now();
        self.times = LocalizationTimes::default();
        self.cpu_marks = [None; 3];
        let found = self.detect_batch_untimed(images)?;
        let end = self.clock.and_then(|c| c());
        let t = &mut self.times;
        t.postprocess_ms = (started.elapsed().as_secs_f64() * 1e3 - t.preprocess_ms - t.network_ms).max(0.0);
        if let ([Some(a), Some(b), Some(c)], Some(d)) = (self.cpu_marks, end) {
            let ms = |x: u64, y: u64| y.saturating_sub(x) as f64 * 1e-6;
            t.cpu_ms = Some([ms(a, b), ms(b, c), ms(c, d)]);
        }
        Ok(found)
    }

    fn detect_batch_untimed(&mut self, images: &[&Mat]) -> Result<Vec<Vec<Detection>>> {
        let with_mre = self.mre.is_some();
        let post = self.post;
        let candidates = self.candidates(images, post.conf_low)?;
        let selections: Vec<Selection> = candidates
            .into_iter()
            .map(|c| Selection::new(c, &post, with_mre))
            .collect();
        let Some(mre) = self.mre.as_mut() else {
            return Ok(selections
                .into_iter()
                .map(|s| s.finish(&[], post.accept))
                .collect());
        };
        let features: Vec<[f32; MRE_FEATURES]> = selections
            .iter()
            .flat_map(|s| s.features.iter().copied())
            .collect();
        let scores = mre.score(&features)?;
        let mut offset = 0;
        Ok(selections
            .into_iter()
            .map(|s| {
                let n = s.pending.len();
                let mine = scores.get(offset..offset + n).unwrap_or(&[]);
                offset += n;
                s.finish(mine, post.accept)
            })
            .collect())
    }
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

    fn last_times(&self) -> Option<LocalizationTimes> {
        Some(self.times)
    }

    fn set_cpu_clock(&mut self, clock: CpuClock) {
        self.clock = Some(clock);
    }

    fn detect_stereo(&mut self, pair: &StereoPair<Mat>) -> Result<StereoPair<Vec<Detection>>> {
        crate::check_stereo_sizes(pair)?;
        let mut out = self.detect_batch(&[&pair.left, &pair.right])?;
        let right = out.pop().unwrap_or_default();
        let left = out.pop().unwrap_or_default();
        Ok(StereoPair::new(left, right))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_8UC1, CV_8UC3, CV_8UC4, Scalar};
    use opencv::prelude::*;

    /// Every pixel value at every channel position, converted exactly as `v / 255` into the right
    /// plane (B, G, R swapped to R, G, B; grey replicated; alpha dropped).
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
            write_planar_rgb(&m, &mut plane)?;
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
}
