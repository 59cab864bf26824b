//! The paper's YOLOv3 baseline (Table I, "YOLOv3 with modified anchor size and output"): an
//! anchor-based detector whose box centres are the markers, through ONNX Runtime.
//!
//! The model (`data/models/yolo.onnx`, trained by `train/gelstereo_train/yolo_train.py`) follows the
//! contract `gelstereo-yolo/1` of `docs/model-contract.md`:
//! - input `image` `[N, 3, H, W]`, the Marknet preprocessing (whole image resized with OpenCV's bilinear
//!   `INTER_LINEAR`, RGB / 255, planar);
//! - output `raw` `[N, K, 5]` of `(tx, ty, tw, th, to)` logits, heads in ascending stride, then gy, gx,
//!   anchor: `K = sum over heads of (H / s) (W / s) A`;
//! - `metadata_props`: `strides`, `anchors_per_head`, `anchors` (input pixels), `conf_threshold`,
//!   `nms_iou`, `tw_clamp`, ...
//!
//! Post-processing of one image (the reference is `train/gelstereo_train/yolo_post.py`; the unit tests
//! check this module against values it computed):
//! 1. decode, in f64: `x_in = (sigmoid(tx) + gx) s`, `w_in = aw exp(clamp(tw, ±tw_clamp))`, likewise y
//!    and h, objectness `sigmoid(to)`;
//! 2. keep boxes with objectness > `conf_threshold`;
//! 3. map to the original image: `x = x_in W / input_width - 0.5`, `w = w_in W / input_width`;
//! 4. greedy NMS: visit in descending objectness (ties: lower flat index first), drop a box whose IoU
//!    with a box already kept is > `nms_iou`;
//! 5. markers = the kept boxes' centres, confidence = objectness; sorted by y then x.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use gelstereo_core::{Detection, ImageSize, Point2, StereoPair};
use opencv::core::Mat;
use ort::session::Session;
use ort::value::TensorRef;

use crate::contract::{TensorSpec, check_signature};
use crate::layout::InputLayout;
use crate::network::{check_aspect, write_layout};
use crate::onnx::{Opened, SessionOptions, onnx_err, open_session};
use crate::resize::ResizeScratch;
use crate::{Error, Localizer, Result, check_image, sort_detections};

/// The `contract` value of a YOLO model this loader understands.
pub const YOLO_CONTRACT: &str = "gelstereo-yolo/1";
/// The model's input name.
pub const YOLO_INPUT: &str = "image";
/// The model's output name.
pub const YOLO_OUTPUT: &str = "raw";
/// Values per anchor in `raw`: `tx, ty, tw, th, to` (one class, so no class scores).
pub const OUTPUTS_PER_ANCHOR: usize = 5;
/// Strides a head may have (those of YOLOv3's backbone).
pub const ALLOWED_STRIDES: [u32; 3] = [8, 16, 32];
/// Where the CLI looks for the model when `GELSTEREO_YOLO_MODEL` is not set: this file name in the
/// folder of the Marknet model (`data/models/` of a checkout, or the `--models` folder).
pub const DEFAULT_MODEL_FILE: &str = "yolo.onnx";
/// Environment variable that overrides the model path [`model_path`] derives.
pub const MODEL_ENV: &str = "GELSTEREO_YOLO_MODEL";

/// Post-processing thresholds. Defaults are Darknet's detector defaults (`-thresh 0.25`, NMS 0.45); a
/// model's metadata overrides them with the values chosen on the validation split.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct YoloPost {
    /// Boxes with objectness above this are candidates.
    pub conf_threshold: f64,
    /// NMS drops a box whose IoU with an already kept box is above this.
    pub nms_iou: f64,
}

impl Default for YoloPost {
    fn default() -> Self {
        Self {
            conf_threshold: 0.25,
            nms_iou: 0.45,
        }
    }
}

/// One detection head: its stride, grid and anchors.
#[derive(Debug, Clone, PartialEq)]
pub struct YoloHead {
    /// Input pixels per cell.
    pub stride: u32,
    /// Cells along x (input_width / stride).
    pub grid_x: u32,
    /// Cells along y (input_height / stride).
    pub grid_y: u32,
    /// Anchor (width, height) in input pixels.
    pub anchors: Vec<[f64; 2]>,
}

impl YoloHead {
    /// Rows of `raw` this head contributes: `grid_y * grid_x * anchors`.
    pub fn rows(&self) -> usize {
        self.grid_y as usize * self.grid_x as usize * self.anchors.len()
    }
}

/// What a YOLO model declares (`metadata_props` checked against its signature).
#[derive(Debug, Clone, PartialEq)]
pub struct YoloContract {
    /// Network input width, px.
    pub input_width: u32,
    /// Network input height, px.
    pub input_height: u32,
    /// Heads in ascending stride (the order of their rows in `raw`).
    pub heads: Vec<YoloHead>,
    /// `|tw|`, `|th|` are clamped to this before `exp`.
    pub tw_clamp: f64,
    /// Post-processing defaults (metadata values where present, else [`YoloPost::default`]).
    pub post: YoloPost,
    /// The training data the model was fitted on.
    pub dataset: String,
    /// When the model was trained (ISO date).
    pub trained: String,
}

fn contract_err(path: &Path, key: &str, expected: impl Into<String>, found: impl Into<String>) -> Error {
    Error::Contract {
        path: path.to_path_buf(),
        key: key.to_owned(),
        expected: expected.into(),
        found: found.into(),
    }
}

impl YoloContract {
    /// Reads and checks the contract of the model at `path` from its metadata and signature.
    pub fn from_model(
        path: &Path,
        metadata: &BTreeMap<String, String>,
        inputs: &[TensorSpec],
        outputs: &[TensorSpec],
    ) -> Result<Self> {
        let get = |key: &str, expected: &str| {
            metadata
                .get(key)
                .map(|v| v.trim())
                .ok_or_else(|| contract_err(path, key, expected, "no such metadata key"))
        };
        let exact = |key: &str, value: &str| -> Result<()> {
            let found = get(key, &format!("'{value}'"))?;
            if found == value {
                Ok(())
            } else {
                Err(contract_err(
                    path,
                    key,
                    format!("'{value}'"),
                    format!("'{found}'"),
                ))
            }
        };
        let positive = |key: &str| -> Result<u32> {
            let expected = "a positive integer";
            let found = get(key, expected)?;
            match found.parse::<u32>() {
                Ok(v) if v > 0 => Ok(v),
                _ => Err(contract_err(path, key, expected, format!("'{found}'"))),
            }
        };
        let optional = |key: &str, default: f64, lo: f64, hi: f64| -> Result<f64> {
            let Some(found) = metadata.get(key) else {
                return Ok(default);
            };
            match found.trim().parse::<f64>() {
                Ok(v) if v > lo && v < hi => Ok(v),
                _ => Err(contract_err(
                    path,
                    key,
                    format!("a number strictly between {lo} and {hi}"),
                    format!("'{found}'"),
                )),
            }
        };
        exact("contract", YOLO_CONTRACT)?;
        let input_height = positive("input_height")?;
        let input_width = positive("input_width")?;
        exact("outputs_per_anchor", &OUTPUTS_PER_ANCHOR.to_string())?;
        exact("normalisation", "rgb/255")?;
        exact("layout", "NCHW")?;
        let strides_text = get("strides", "ascending strides from 8, 16, 32, comma-separated")?;
        let strides: Vec<u32> = strides_text
            .split(',')
            .map(|s| s.trim().parse::<u32>().unwrap_or(0))
            .collect();
        let ascending = strides.windows(2).all(|w| w[0] < w[1]);
        if strides.is_empty() || !ascending || strides.iter().any(|s| !ALLOWED_STRIDES.contains(s)) {
            return Err(contract_err(
                path,
                "strides",
                "ascending strides from 8, 16, 32, comma-separated",
                format!("'{strides_text}'"),
            ));
        }
        for (key, v) in [("input_width", input_width), ("input_height", input_height)] {
            if let Some(s) = strides.iter().find(|s| v % **s != 0) {
                return Err(contract_err(
                    path,
                    key,
                    format!("a multiple of stride {s}"),
                    v.to_string(),
                ));
            }
        }
        let per_head = positive("anchors_per_head")? as usize;
        let anchors_text = get("anchors", "anchor 'w,h' pairs in input pixels, space-separated")?;
        let anchors: Vec<Option<[f64; 2]>> = anchors_text
            .split_whitespace()
            .map(|pair| {
                let (w, h) = pair.split_once(',')?;
                let (w, h) = (w.trim().parse::<f64>().ok()?, h.trim().parse::<f64>().ok()?);
                (w.is_finite() && h.is_finite() && w > 0.0 && h > 0.0).then_some([w, h])
            })
            .collect();
        let expected_anchors = strides.len() * per_head;
        if anchors.len() != expected_anchors || anchors.iter().any(Option::is_none) {
            return Err(contract_err(
                path,
                "anchors",
                format!(
                    "{expected_anchors} positive 'w,h' pairs ({} heads x {per_head})",
                    strides.len()
                ),
                format!("'{anchors_text}'"),
            ));
        }
        let anchors: Vec<[f64; 2]> = anchors.into_iter().flatten().collect();
        let heads: Vec<YoloHead> = strides
            .iter()
            .zip(anchors.chunks_exact(per_head))
            .map(|(&stride, a)| YoloHead {
                stride,
                grid_x: input_width / stride,
                grid_y: input_height / stride,
                anchors: a.to_vec(),
            })
            .collect();
        let d = YoloPost::default();
        let post = YoloPost {
            conf_threshold: optional("conf_threshold", d.conf_threshold, 0.0, 1.0)?,
            nms_iou: optional("nms_iou", d.nms_iou, 0.0, 1.0)?,
        };
        let tw_clamp = optional("tw_clamp", 20.0, 0.0, 700.0)?;
        let dataset = get("dataset", "a non-empty description")?.to_owned();
        let trained = get("trained", "a non-empty description")?.to_owned();
        check_signature(
            path,
            "input",
            inputs,
            YOLO_INPUT,
            &[
                None,
                Some(3),
                Some(i64::from(input_height)),
                Some(i64::from(input_width)),
            ],
        )?;
        let rows: usize = heads.iter().map(YoloHead::rows).sum();
        check_signature(
            path,
            "output",
            outputs,
            YOLO_OUTPUT,
            &[None, Some(rows as i64), Some(OUTPUTS_PER_ANCHOR as i64)],
        )?;
        Ok(Self {
            input_width,
            input_height,
            heads,
            tw_clamp,
            post,
            dataset,
            trained,
        })
    }

    /// Rows K of `raw` per image.
    pub fn rows(&self) -> usize {
        self.heads.iter().map(YoloHead::rows).sum()
    }
}

/// A decoded box, in pixels of the original image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct YoloBox {
    /// Box centre (the marker position).
    pub centre: Point2,
    /// Box width, px.
    pub width_px: f64,
    /// Box height, px.
    pub height_px: f64,
    /// Objectness in (0, 1).
    pub objectness: f64,
}

impl YoloBox {
    /// Intersection over union with `other` (0 when the union is empty).
    pub fn iou(&self, other: &YoloBox) -> f64 {
        let overlap = |c1: f64, s1: f64, c2: f64, s2: f64| {
            ((c1 + s1 / 2.0).min(c2 + s2 / 2.0) - (c1 - s1 / 2.0).max(c2 - s2 / 2.0)).max(0.0)
        };
        let inter = overlap(self.centre.x, self.width_px, other.centre.x, other.width_px)
            * overlap(self.centre.y, self.height_px, other.centre.y, other.height_px);
        let union = self.width_px * self.height_px + other.width_px * other.height_px - inter;
        if union > 0.0 { inter / union } else { 0.0 }
    }
}

fn sigmoid(v: f32) -> f64 {
    1.0 / (1.0 + (-f64::from(v)).exp())
}

/// Steps 1-3 of the module docs for one image: the boxes with objectness > `conf_threshold`, in flat
/// order, mapped with `scale_x` = W / input_width, `scale_y` = H / input_height. An output shorter than
/// the contract's `K x 5` gives no boxes.
pub fn decode(
    raw: &[f32],
    contract: &YoloContract,
    scale_x: f64,
    scale_y: f64,
    conf_threshold: f64,
) -> Vec<YoloBox> {
    let mut out = Vec::new();
    if raw.len() < contract.rows() * OUTPUTS_PER_ANCHOR {
        return out;
    }
    let clamp = contract.tw_clamp;
    let mut rows = raw.chunks_exact(OUTPUTS_PER_ANCHOR);
    for head in &contract.heads {
        let s = f64::from(head.stride);
        for gy in 0..head.grid_y {
            for gx in 0..head.grid_x {
                for anchor in &head.anchors {
                    let Some(r) = rows.next() else { return out };
                    let objectness = sigmoid(r[4]);
                    if objectness.partial_cmp(&conf_threshold) != Some(std::cmp::Ordering::Greater) {
                        continue;
                    }
                    let x_in = (sigmoid(r[0]) + f64::from(gx)) * s;
                    let y_in = (sigmoid(r[1]) + f64::from(gy)) * s;
                    let w_in = anchor[0] * f64::from(r[2]).clamp(-clamp, clamp).exp();
                    let h_in = anchor[1] * f64::from(r[3]).clamp(-clamp, clamp).exp();
                    out.push(YoloBox {
                        centre: Point2::new(x_in * scale_x - 0.5, y_in * scale_y - 0.5),
                        width_px: w_in * scale_x,
                        height_px: h_in * scale_y,
                        objectness,
                    });
                }
            }
        }
    }
    out
}

/// Step 4: greedy NMS. Returns the kept boxes in visiting order (descending objectness, ties: lower
/// index first); a box is dropped when its IoU with a kept box is > `iou_threshold`.
pub fn nms(boxes: &[YoloBox], iou_threshold: f64) -> Vec<YoloBox> {
    let mut order: Vec<usize> = (0..boxes.len()).collect();
    order.sort_by(|&a, &b| {
        boxes[b]
            .objectness
            .total_cmp(&boxes[a].objectness)
            .then(a.cmp(&b))
    });
    // Boxes overlap only if their centres are closer than the largest box side along both axes, so
    // kept boxes are bucketed on a grid of that cell size and only the 3x3 neighbourhood is checked.
    let cell = boxes
        .iter()
        .flat_map(|b| [b.width_px, b.height_px])
        .filter(|v| v.is_finite())
        .fold(0.0f64, f64::max)
        .max(1e-6);
    let key = |b: &YoloBox| {
        (
            (b.centre.x / cell).floor() as i64,
            (b.centre.y / cell).floor() as i64,
        )
    };
    let mut grid: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    let mut kept = Vec::new();
    for i in order {
        let b = &boxes[i];
        let (cx, cy) = key(b);
        let clash = (cx - 1..=cx + 1).any(|nx| {
            (cy - 1..=cy + 1).any(|ny| {
                grid.get(&(nx, ny))
                    .is_some_and(|ks| ks.iter().any(|&k| boxes[k].iou(b) > iou_threshold))
            })
        });
        if !clash {
            grid.entry((cx, cy)).or_default().push(i);
            kept.push(*b);
        }
    }
    kept
}

/// The path of the YOLO model for a [`crate::LocalizerConfig`]: `$GELSTEREO_YOLO_MODEL` when set, else
/// `yolo.onnx` in the folder of the Marknet model (the CLI's `--models` folder, `data/models` by
/// default).
pub fn model_path(config: &crate::LocalizerConfig) -> PathBuf {
    match std::env::var_os(MODEL_ENV).filter(|v| !v.is_empty()) {
        Some(p) => PathBuf::from(p),
        None => config.marknet_path.with_file_name(DEFAULT_MODEL_FILE),
    }
}

/// The YOLOv3 localizer (`yolo`).
pub struct YoloLocalizer {
    path: PathBuf,
    options: SessionOptions,
    session: Session,
    contract: YoloContract,
    post: YoloPost,
    resize: ResizeScratch,
    input: Vec<f32>,
}

impl std::fmt::Debug for YoloLocalizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("YoloLocalizer")
            .field("path", &self.path)
            .field("contract", &self.contract)
            .field("post", &self.post)
            .finish()
    }
}

impl YoloLocalizer {
    /// Loads `path` into ONNX Runtime and checks its contract.
    pub fn load(path: &Path, options: &SessionOptions) -> Result<Self> {
        let Opened {
            session,
            metadata: map,
            inputs,
            outputs,
        } = open_session(path, options)?;
        let contract = YoloContract::from_model(path, &map, &inputs, &outputs)?;
        Ok(Self {
            path: path.to_path_buf(),
            options: *options,
            session,
            post: contract.post,
            contract,
            resize: ResizeScratch::default(),
            input: Vec::new(),
        })
    }

    /// The model's declared contract.
    pub fn contract(&self) -> &YoloContract {
        &self.contract
    }

    /// The thresholds in use.
    pub fn postprocess(&self) -> &YoloPost {
        &self.post
    }

    /// Replaces the thresholds (e.g. for a sweep).
    pub fn set_postprocess(&mut self, post: YoloPost) {
        self.post = post;
    }

    /// Resizes and converts `image` into batch slot `slot` of the input buffer (the Marknet
    /// preprocessing of `docs/model-contract.md`).
    fn preprocess(&mut self, image: &Mat, slot: usize) -> Result<ImageSize> {
        let size = check_image(image)?;
        let (iw, ih) = (self.contract.input_width, self.contract.input_height);
        check_aspect(size, iw, ih)?;
        let layout = InputLayout::stretch(iw, ih);
        let hw = (iw * ih) as usize;
        let plane = &mut self.input[slot * 3 * hw..(slot + 1) * 3 * hw];
        write_layout(image, &layout, None, &mut self.resize, plane)?;
        Ok(size)
    }

    /// Runs the network on `images` (one batch) and returns each image's boxes above the threshold,
    /// before NMS (steps 1-3 of the module docs), in that image's pixels.
    pub fn boxes(&mut self, images: &[&Mat]) -> Result<Vec<Vec<YoloBox>>> {
        if images.is_empty() {
            return Ok(Vec::new());
        }
        let (iw, ih) = (
            self.contract.input_width as usize,
            self.contract.input_height as usize,
        );
        self.input.resize(images.len() * 3 * iw * ih, 0.0);
        let mut sizes = Vec::with_capacity(images.len());
        for (slot, image) in images.iter().enumerate() {
            sizes.push(self.preprocess(image, slot)?);
        }
        let run = onnx_err(&self.path, "inference");
        let input = TensorRef::from_array_view(([images.len(), 3, ih, iw], self.input.as_slice()))
            .map_err(|e| run(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs![YOLO_INPUT => input])
            .map_err(|e| run(e.to_string()))?;
        let (shape, raw) = outputs[YOLO_OUTPUT]
            .try_extract_tensor::<f32>()
            .map_err(|e| run(e.to_string()))?;
        let per_image = self.contract.rows() * OUTPUTS_PER_ANCHOR;
        if raw.len() != per_image * images.len() {
            return Err(run(format!(
                "output '{YOLO_OUTPUT}' has shape {shape}, expected [{}, {}, {OUTPUTS_PER_ANCHOR}]",
                images.len(),
                self.contract.rows()
            )));
        }
        crate::onnx::check_finite(raw, YOLO_OUTPUT).map_err(run)?;
        let c = &self.contract;
        Ok(sizes
            .iter()
            .zip(raw.chunks_exact(per_image))
            .map(|(size, r)| {
                let sx = f64::from(size.width) / f64::from(c.input_width);
                let sy = f64::from(size.height) / f64::from(c.input_height);
                decode(r, c, sx, sy, self.post.conf_threshold)
            })
            .collect())
    }

    /// Full localization of a batch of images: network, decoding, threshold, NMS; markers sorted by
    /// y then x.
    pub fn detect_batch(&mut self, images: &[&Mat]) -> Result<Vec<Vec<Detection>>> {
        let iou = self.post.nms_iou;
        Ok(self
            .boxes(images)?
            .into_iter()
            .map(|b| {
                let mut d: Vec<Detection> = nms(&b, iou)
                    .into_iter()
                    .map(|k| Detection {
                        position: k.centre,
                        confidence: k.objectness as f32,
                    })
                    .collect();
                sort_detections(&mut d);
                d
            })
            .collect())
    }
}

impl Localizer for YoloLocalizer {
    fn name(&self) -> &str {
        "yolo"
    }

    fn fork(&self, intra_threads: usize) -> Option<Result<Box<dyn Localizer + Send>>> {
        let options = SessionOptions {
            intra_threads,
            ..self.options
        };
        Some(YoloLocalizer::load(&self.path, &options).map(|mut y| {
            y.post = self.post;
            Box::new(y) as Box<dyn Localizer + Send>
        }))
    }

    fn detect(&mut self, image: &Mat) -> Result<Vec<Detection>> {
        Ok(self.detect_batch(&[image])?.pop().unwrap_or_default())
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

    const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../data/fixtures/onnx");

    fn meta() -> BTreeMap<String, String> {
        [
            ("contract", YOLO_CONTRACT),
            ("input_height", "416"),
            ("input_width", "416"),
            ("strides", "8,16"),
            ("anchors_per_head", "3"),
            ("anchors", "5,6 5.5,7 6,7.5 6.5,8 7,9 8,10"),
            ("outputs_per_anchor", "5"),
            ("tw_clamp", "20"),
            ("normalisation", "rgb/255"),
            ("layout", "NCHW"),
            ("conf_threshold", "0.3"),
            ("nms_iou", "0.45"),
            ("dataset", "sim v1"),
            ("trained", "2026-11-22"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v.to_owned()))
        .collect()
    }

    fn spec(name: &str, dims: &[i64]) -> Vec<TensorSpec> {
        vec![TensorSpec {
            name: name.into(),
            float32: true,
            dims: dims.to_vec(),
        }]
    }

    // 52*52*3 + 26*26*3 rows for 416x416 with strides 8 and 16.
    const ROWS_416: i64 = 52 * 52 * 3 + 26 * 26 * 3;

    fn parse(meta: &BTreeMap<String, String>) -> Result<YoloContract> {
        YoloContract::from_model(
            Path::new("y.onnx"),
            meta,
            &spec("image", &[-1, 3, 416, 416]),
            &spec("raw", &[-1, ROWS_416, 5]),
        )
    }

    #[test]
    fn a_conforming_model_is_accepted() {
        let c = parse(&meta()).unwrap();
        assert_eq!(c.heads.len(), 2);
        assert_eq!(
            (c.heads[0].stride, c.heads[0].grid_x, c.heads[1].grid_y),
            (8, 52, 26)
        );
        assert_eq!(c.heads[1].anchors, vec![[6.5, 8.0], [7.0, 9.0], [8.0, 10.0]]);
        assert_eq!(c.rows() as i64, ROWS_416);
        assert_eq!(
            c.post,
            YoloPost {
                conf_threshold: 0.3,
                nms_iou: 0.45
            }
        );
        let mut m = meta();
        m.remove("conf_threshold");
        m.remove("nms_iou");
        assert_eq!(parse(&m).unwrap().post, YoloPost::default());
    }

    /// Table of broken contracts: each must be reported by the key at fault.
    #[test]
    fn each_contract_violation_is_named() {
        let cases: Vec<(&str, Option<&str>)> = vec![
            ("contract", Some("gelstereo-marknet/1")),
            ("contract", None),
            ("strides", Some("16,8")),
            ("strides", Some("8,12")),
            ("strides", Some("")),
            ("input_width", Some("420")),
            ("anchors", Some("5,6 5.5,7")),
            ("anchors", Some("5,6 5.5,7 6,7.5 6.5,8 7,9 8,-1")),
            ("anchors", Some("5;6 5.5,7 6,7.5 6.5,8 7,9 8,10")),
            ("anchors_per_head", Some("0")),
            ("outputs_per_anchor", Some("6")),
            ("normalisation", Some("imagenet")),
            ("layout", Some("NHWC")),
            ("conf_threshold", Some("1.5")),
            ("nms_iou", Some("zero")),
            ("dataset", None),
        ];
        for (key, value) in cases {
            let mut m = meta();
            match value {
                Some(v) => m.insert(key.to_owned(), v.to_owned()),
                None => m.remove(key),
            };
            let err = parse(&m).unwrap_err().to_string();
            assert!(
                err.contains(&format!("'{key}'")) && err.contains("y.onnx"),
                "{key}={value:?}: {err}"
            );
        }
        let p = Path::new("y.onnx");
        let err = YoloContract::from_model(
            p,
            &meta(),
            &spec("image", &[-1, 3, 416, 416]),
            &spec("raw", &[-1, 100, 5]),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("'raw'") && err.contains(&format!("[N, {ROWS_416}, 5]")),
            "{err}"
        );
        let err = YoloContract::from_model(
            p,
            &meta(),
            &spec("input", &[-1, 3, 416, 416]),
            &spec("raw", &[-1, ROWS_416, 5]),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("'image'") && err.contains("input 'input'"), "{err}");
    }

    fn bx(x: f64, y: f64, w: f64, h: f64, objectness: f64) -> YoloBox {
        YoloBox {
            centre: Point2::new(x, y),
            width_px: w,
            height_px: h,
            objectness,
        }
    }

    #[test]
    fn iou_and_nms_on_hand_made_boxes() {
        // Two boxes of 4x4 shifted by 1 px: inter 12, union 20, IoU 0.6.
        let a = bx(10.0, 10.0, 4.0, 4.0, 0.9);
        let b = bx(11.0, 10.0, 4.0, 4.0, 0.8);
        assert!((a.iou(&b) - 0.6).abs() < 1e-12);
        assert_eq!(a.iou(&bx(20.0, 10.0, 4.0, 4.0, 0.5)), 0.0);
        assert_eq!(bx(0.0, 0.0, 0.0, 0.0, 0.5).iou(&bx(0.0, 0.0, 0.0, 0.0, 0.5)), 0.0);
        // b is suppressed by a at 0.45 but not at 0.7; a far box survives; visiting order = objectness.
        let far = bx(30.0, 30.0, 4.0, 4.0, 0.95);
        let kept = nms(&[b, a, far], 0.45);
        assert_eq!(kept, vec![far, a]);
        assert_eq!(nms(&[b, a, far], 0.7), vec![far, a, b]);
        // Ties: the lower index is visited first and wins.
        let t1 = bx(10.0, 10.0, 4.0, 4.0, 0.5);
        let t2 = bx(10.5, 10.0, 4.0, 4.0, 0.5);
        assert_eq!(nms(&[t2, t1], 0.45), vec![t2]);
        // A big box is checked against neighbours however far its centre is in grid cells.
        let big = bx(50.0, 50.0, 60.0, 60.0, 0.9);
        let inside = bx(52.0, 50.0, 58.0, 60.0, 0.6);
        assert_eq!(nms(&[inside, big], 0.45), vec![big]);
        assert!(nms(&[], 0.45).is_empty());
    }

    fn fixture() -> serde_json::Value {
        let text = std::fs::read_to_string(Path::new(FIXTURES).join("yolo_tiny_expected.json")).unwrap();
        serde_json::from_str(&text).unwrap()
    }

    fn floats(v: &serde_json::Value) -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    }

    fn fixture_contract(fx: &serde_json::Value) -> YoloContract {
        let strides: Vec<u32> = floats(&fx["strides"]).into_iter().map(|s| s as u32).collect();
        let anchors: Vec<[f64; 2]> = fx["anchors"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| [a[0].as_f64().unwrap(), a[1].as_f64().unwrap()])
            .collect();
        let per_head = anchors.len() / strides.len();
        let (iw, ih) = (
            fx["input_width"].as_u64().unwrap() as u32,
            fx["input_height"].as_u64().unwrap() as u32,
        );
        YoloContract {
            input_width: iw,
            input_height: ih,
            heads: strides
                .iter()
                .zip(anchors.chunks_exact(per_head))
                .map(|(&s, a)| YoloHead {
                    stride: s,
                    grid_x: iw / s,
                    grid_y: ih / s,
                    anchors: a.to_vec(),
                })
                .collect(),
            tw_clamp: 20.0,
            post: YoloPost {
                conf_threshold: fx["conf_threshold"].as_f64().unwrap(),
                nms_iou: fx["nms_iou"].as_f64().unwrap(),
            },
            dataset: "fixture".into(),
            trained: "fixture".into(),
        }
    }

    /// Decoding + threshold + NMS of the fixture's raw output against the Python reference
    /// (`yolo_post.py`); both compute in f64 from the same f32 logits, so the tolerance is 1e-9.
    #[test]
    fn decoding_and_nms_match_the_python_reference() {
        let fx = fixture();
        let c = fixture_contract(&fx);
        let raw: Vec<f32> = floats(&fx["raw"]).into_iter().map(|v| v as f32).collect();
        assert_eq!(raw.len(), c.rows() * OUTPUTS_PER_ANCHOR);
        let sx = fx["image_width"].as_f64().unwrap() / f64::from(c.input_width);
        let sy = fx["image_height"].as_f64().unwrap() / f64::from(c.input_height);
        let boxes = decode(&raw, &c, sx, sy, c.post.conf_threshold);
        let want = fx["candidates"].as_array().unwrap();
        assert_eq!(boxes.len(), want.len());
        for (b, w) in boxes.iter().zip(want) {
            let w = floats(w);
            let got = [b.centre.x, b.centre.y, b.width_px, b.height_px, b.objectness];
            for (g, e) in got.iter().zip(&w) {
                assert!((g - e).abs() < 1e-9, "candidate {got:?} vs {w:?}");
            }
        }
        let kept = nms(&boxes, c.post.nms_iou);
        let want = fx["markers"].as_array().unwrap();
        assert!(kept.len() < boxes.len(), "the fixture must exercise NMS");
        assert_eq!(kept.len(), want.len());
        for (k, w) in kept.iter().zip(want) {
            let w = floats(w);
            assert!(
                (k.centre.x - w[0]).abs() < 1e-9 && (k.centre.y - w[1]).abs() < 1e-9,
                "{k:?} vs {w:?}"
            );
            assert!((k.objectness - w[2]).abs() < 1e-9);
        }
        // A truncated output decodes to nothing rather than panicking.
        assert!(decode(&raw[..raw.len() - 1], &c, sx, sy, 0.0).is_empty());
    }

    /// The fixture model through ONNX Runtime, OpenCV's resize and the whole localizer, against the
    /// Python pipeline (cv2 resize + onnxruntime + yolo_post). Tolerance 1e-3 px / 1e-4 in confidence:
    /// ONNX Runtime may pick other kernels than in Python; the resize is the same integer arithmetic.
    #[test]
    fn the_fixture_model_localizes_like_the_python_pipeline() {
        let fx = fixture();
        let dir = Path::new(FIXTURES);
        let mut yolo = YoloLocalizer::load(
            &dir.join("yolo_tiny.onnx"),
            &SessionOptions {
                intra_threads: 1,
                use_cuda: false,
            },
        )
        .unwrap();
        assert_eq!(
            yolo.contract().post.conf_threshold,
            fx["conf_threshold"].as_f64().unwrap()
        );
        assert_eq!(yolo.contract().heads, fixture_contract(&fx).heads);
        let image = opencv::imgcodecs::imread(
            dir.join(fx["image"].as_str().unwrap()).to_str().unwrap(),
            opencv::imgcodecs::IMREAD_COLOR,
        )
        .unwrap();
        let mut want: Vec<Vec<f64>> = fx["markers"].as_array().unwrap().iter().map(floats).collect();
        want.sort_by(|a, b| a[1].total_cmp(&b[1]).then(a[0].total_cmp(&b[0])));
        let got = yolo.detect(&image).unwrap();
        assert_eq!(got.len(), want.len());
        for (g, w) in got.iter().zip(&want) {
            assert!(
                (g.position.x - w[0]).abs() < 1e-3 && (g.position.y - w[1]).abs() < 1e-3,
                "{g:?} vs {w:?}"
            );
            assert!((f64::from(g.confidence) - w[2]).abs() < 1e-4);
        }
        // Stereo runs both views in one batch and gives each view the single-image result.
        let pair = StereoPair::new(image.clone(), image);
        let both = yolo.detect_stereo(&pair).unwrap();
        assert_eq!(both.left, got);
        assert_eq!(both.right, got);
        // A too-elongated image is refused by name.
        let strip =
            Mat::new_rows_cols_with_default(20, 200, opencv::core::CV_8UC3, opencv::core::Scalar::all(0.0))
                .unwrap();
        assert!(
            yolo.detect(&strip)
                .unwrap_err()
                .to_string()
                .contains("aspect ratio")
        );
    }
}
