//! Marker localizers behind one trait: Marknet + MRE through ONNX Runtime (the paper's method), and
//! OpenCV's SimpleBlobDetector (the paper's baseline); plus the paper's detection metrics.
//!
//! - [`Localizer`]: the trait the CLI, the evaluator and the benchmarks use; [`create_localizer`] builds
//!   one of the three [`Method`]s (`blob`, `marknet`, `marknet-mre`) from a [`LocalizerConfig`].
//! - [`marknet`]: the Marknet localizer, composed of its [`network`] (the ONNX session, its metadata
//!   contract `docs/model-contract.md`, preprocessing, batched stereo inference), the input
//!   [`layout`] and its "auto" fit, the streaming state, and the post-processing: [`postprocess`]
//!   (decoding, thresholds, de-duplication, MRE features and acceptance) and [`finish`] (the lattice
//!   check and the steps after it). Types several steps share have modules of their own ([`layout`],
//!   [`region`], [`spacing`]); no module imports one that imports it back (`tests/module_graph.rs`).
//! - [`blob`]: the SimpleBlobDetector baseline with documented, file-based parameters.
//! - [`metrics`]: one-to-one matching, precision / recall / loss and the easy / hard / contact splits
//!   (docs/design.md "Metrics").
//! - [`overlay`]: drawing detections onto images.
//!
//! # Conventions
//! - Every position is in pixels of the ORIGINAL image, (0, 0) = centre of the top-left pixel, x right,
//!   y down; never in the network's resized input.
//! - Images are 8-bit OpenCV [`Mat`]s, BGR (3 channels), BGRA (4) or grey (1). Network tensors are f32,
//!   geometry f64.
//! - Detections come out sorted by y, then x, so results are deterministic.
//!
//! # Timing
//! [`marknet::Marknet`] and its [`network`] open `tracing` spans (level TRACE, no fields) around the
//! parts of a localization call: `marknet.preprocess` (resize, f32 tensor), `marknet.network` (the
//! ONNX Runtime run) and `marknet.postprocess`, the whole call, in which the other two nest: its own
//! time is the decoding, selection, layout decisions and MRE. Without a subscriber a span costs a
//! level check.

pub mod blob;
pub mod border;
pub mod close_look;
pub mod contract;
pub mod dots;
pub mod edge;
pub mod finish;
pub mod lattice;
pub mod layout;
pub mod marknet;
pub mod metrics;
pub mod mre;
pub mod network;
pub mod onnx;
pub mod overlay;
mod pass;
pub mod postprocess;
pub mod region;
mod resize;
pub mod runtime;
pub mod self_test;
pub mod site_blobs;
pub mod spacing;
pub mod squeezed_blobs;
mod stream;
pub mod window;
pub mod yolo;

use std::path::PathBuf;

use gelstereo_core::{Detection, ImageSize, StereoPair, TieredDetections};
use opencv::core::{Mat, MatTraitConst};

pub use blob::{BlobLocalizer, BlobParams};
pub use contract::{AutoFit, MarknetContract, MreContract};
pub use layout::{InputFit, InputLayout, fit_layout, probe_layout};
pub use marknet::Marknet;
pub use mre::Mre;
pub use network::network_input;
pub use onnx::SessionOptions;
pub use postprocess::PostProcess;
pub use resize::{FILL_SAMPLE_STEP, Kernels, ResizeScratch};

/// Errors of the marker localizers. Each names the file, the field or the image property concerned and
/// what was expected.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// ONNX Runtime could not be found or started.
    #[error(transparent)]
    Runtime(#[from] runtime::OnnxRuntimeError),
    /// A file could not be read at the OS level.
    #[error("cannot read {path}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error (the error's source: shown by `{:#}` / error chains).
        source: std::io::Error,
    },
    /// A model's inputs, outputs or `metadata_props` break the contract of `docs/model-contract.md`.
    #[error("{path}: model contract: '{key}': expected {expected}, found {found}")]
    Contract {
        /// The model file.
        path: PathBuf,
        /// The metadata key, or the input/output name, that does not match.
        key: String,
        /// What the contract requires.
        expected: String,
        /// What the model has.
        found: String,
    },
    /// ONNX Runtime failed while loading or running a model.
    #[error("{path}: ONNX Runtime: {what}: {message}")]
    Onnx {
        /// The model file.
        path: PathBuf,
        /// The step that failed, e.g. "loading the model", "inference".
        what: &'static str,
        /// ONNX Runtime's message.
        message: String,
    },
    /// An image cannot be localized: empty, of an unsupported type, or of an unexpected size.
    #[error("image {property}: expected {expected}, found {found}")]
    Image {
        /// The property that is wrong ("size", "type", "stereo sizes").
        property: &'static str,
        /// What is accepted.
        expected: String,
        /// What the image has.
        found: String,
    },
    /// OpenCV failed in one of our calls.
    #[error("OpenCV failed in {context}")]
    OpenCv {
        /// Which step failed (e.g. "resize", "SimpleBlobDetector::detect").
        context: &'static str,
        /// OpenCV's error.
        source: opencv::Error,
    },
    /// A configuration file (e.g. the blob parameters) has a missing or invalid field.
    #[error("{path}: '{field}': expected {expected}, found {found}")]
    Config {
        /// The file.
        path: PathBuf,
        /// The field.
        field: String,
        /// What is accepted.
        expected: String,
        /// What the file has.
        found: String,
    },
    /// A localizer failed its self-test ([`self_test::run`]).
    #[error("self-test: {0}")]
    SelfTest(String),
    /// Inputs to the metrics are inconsistent (e.g. a non-positive radius).
    #[error("metrics: {0}")]
    Metrics(String),
    /// A localization method name that is not one of [`Method::ALL`].
    #[error("unknown localization method '{0}': expected one of blob, yolo, marknet, marknet-mre")]
    UnknownMethod(String),
}

/// Result with the markers [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

pub(crate) fn cv_err(context: &'static str) -> impl FnOnce(opencv::Error) -> Error {
    move |source| Error::OpenCv { context, source }
}

/// Smallest image side a localizer accepts, px: below it no marker of any sensor we know is resolvable.
pub const MIN_IMAGE_SIDE_PX: u32 = 16;

/// A marker localizer: finds marker centres in one image, or in both views of a stereo pair.
pub trait Localizer: Send {
    /// The method's name as used on the command line and in tables (`blob`, `marknet`, `marknet-mre`).
    fn name(&self) -> &str;

    /// Markers in `image` (8-bit BGR, BGRA or grey), in pixels of `image`, sorted by y then x.
    fn detect(&mut self, image: &Mat) -> Result<Vec<Detection>>;

    /// For `marknet-mre`: the confidence at or below which a detection was accepted by MRE (its
    /// `conf_keep`), so overlays can mark those. `None` for methods without MRE.
    fn mre_band_top(&self) -> Option<f32> {
        None
    }

    /// Whether the views of a stereo pair are worked on in parallel where the method can (the
    /// learned localizers' preprocessing and post-processing; default: no). Same results: lower
    /// latency on a free core, overhead where the cores are busy.
    fn set_parallel(&mut self, parallel: bool) {
        let _ = parallel;
    }

    /// Another localizer of the same method, models and settings that goes on where this one is in
    /// a stream (Marknet's pitch remembered per image size), its network on `intra_threads` ONNX
    /// Runtime threads (0: one per core) and its views worked on one after the other: one per worker
    /// thread when frames of one stream are localized in parallel. `None`: this localizer cannot be
    /// forked (the frames are then localized one at a time).
    fn fork(&self, intra_threads: usize) -> Option<Result<Box<dyn Localizer + Send>>> {
        let _ = intra_threads;
        None
    }

    /// Markers in both views of a stereo pair. The two views must have the same size; the learned
    /// localizer runs both in one batch.
    fn detect_stereo(&mut self, pair: &StereoPair<Mat>) -> Result<StereoPair<Vec<Detection>>> {
        check_stereo_sizes(pair)?;
        Ok(StereoPair::new(
            self.detect(&pair.left)?,
            self.detect(&pair.right)?,
        ))
    }

    /// [`detect`](Self::detect) plus the candidates the method found but did not accept, for a
    /// tracker's second tier (Marknet and Marknet-MRE; others: none).
    fn detect_tiered(&mut self, image: &Mat) -> Result<TieredDetections> {
        Ok(self.detect(image)?.into())
    }

    /// [`detect_stereo`](Self::detect_stereo) with each view's second tier
    /// ([`detect_tiered`](Self::detect_tiered)).
    fn detect_stereo_tiered(&mut self, pair: &StereoPair<Mat>) -> Result<StereoPair<TieredDetections>> {
        let d = self.detect_stereo(pair)?;
        Ok(StereoPair::new(d.left.into(), d.right.into()))
    }
}

/// Checks that `image` is something a localizer can work on and returns its size: non-empty, at least
/// [`MIN_IMAGE_SIDE_PX`] on each side, 8-bit with 1, 3 or 4 channels.
pub fn check_image(image: &Mat) -> Result<ImageSize> {
    let (w, h) = (image.cols(), image.rows());
    if image.empty() || w < MIN_IMAGE_SIDE_PX as i32 || h < MIN_IMAGE_SIDE_PX as i32 {
        return Err(Error::Image {
            property: "size",
            expected: format!("at least {MIN_IMAGE_SIDE_PX}x{MIN_IMAGE_SIDE_PX} px"),
            found: format!("{}x{} px", w.max(0), h.max(0)),
        });
    }
    let depth = image.depth();
    let channels = image.channels();
    if depth != opencv::core::CV_8U || !matches!(channels, 1 | 3 | 4) {
        return Err(Error::Image {
            property: "type",
            expected: "8-bit grey, BGR or BGRA".into(),
            found: format!("{} channel(s) of depth code {depth}", channels),
        });
    }
    Ok(ImageSize {
        width: w as u32,
        height: h as u32,
    })
}

/// Checks both views with [`check_image`] and that they have the same size.
pub fn check_stereo_sizes(pair: &StereoPair<Mat>) -> Result<ImageSize> {
    let l = check_image(&pair.left)?;
    let r = check_image(&pair.right)?;
    if l != r {
        return Err(Error::Image {
            property: "stereo sizes",
            expected: format!("right view of the left view's size {}x{}", l.width, l.height),
            found: format!("{}x{}", r.width, r.height),
        });
    }
    Ok(l)
}

/// Sorts detections by y, then x (deterministic output order).
pub fn sort_detections(detections: &mut [Detection]) {
    detections.sort_by(detection_order);
}

/// The order of [`sort_detections`]: by y, then x.
pub(crate) fn detection_order(a: &Detection, b: &Detection) -> std::cmp::Ordering {
    a.position
        .y
        .total_cmp(&b.position.y)
        .then(a.position.x.total_cmp(&b.position.x))
}

/// The localization methods of the paper's Table I that gelstereo implements.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Method {
    /// OpenCV's SimpleBlobDetector with the sensor's tuned parameters (the paper's "OpenCV").
    Blob,
    /// The paper's YOLOv3 baseline: box centres of an anchor-based detector after threshold and NMS
    /// ([`yolo`], model `yolo.onnx` beside the Marknet model).
    Yolo,
    /// Marknet alone: candidates with c > `conf_marknet_only` (0.2) (the paper's "Marknet").
    Marknet,
    /// Marknet with MRE post-processing: c > 0.4 kept, 0.1 < c <= 0.4 kept when MRE's score > 0.99.
    MarknetMre,
}

impl Method {
    /// All methods, in the order of the paper's table.
    pub const ALL: [Method; 4] = [Method::Blob, Method::Yolo, Method::Marknet, Method::MarknetMre];

    /// The command-line name.
    pub const fn as_str(self) -> &'static str {
        match self {
            Method::Blob => "blob",
            Method::Yolo => "yolo",
            Method::Marknet => "marknet",
            Method::MarknetMre => "marknet-mre",
        }
    }

    /// Parses a comma-separated list such as `blob,marknet-mre`.
    pub fn parse_list(text: &str) -> Result<Vec<Method>> {
        let mut out = Vec::new();
        for word in text.split(',').map(str::trim).filter(|w| !w.is_empty()) {
            let m: Method = word.parse()?;
            if !out.contains(&m) {
                out.push(m);
            }
        }
        if out.is_empty() {
            return Err(Error::UnknownMethod(text.to_owned()));
        }
        Ok(out)
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Method {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Method::ALL
            .into_iter()
            .find(|m| m.as_str() == s)
            .ok_or_else(|| Error::UnknownMethod(s.to_owned()))
    }
}

/// Everything needed to build any [`Method`]'s localizer.
#[derive(Debug, Clone)]
pub struct LocalizerConfig {
    /// The Marknet model (`data/models/marknet.onnx` in a checkout).
    pub marknet_path: PathBuf,
    /// The MRE model (`data/models/mre.onnx` in a checkout).
    pub mre_path: PathBuf,
    /// SimpleBlobDetector parameters (`data/blob_params.json`, or OpenCV's defaults).
    pub blob: BlobParams,
    /// ONNX Runtime options.
    pub session: SessionOptions,
    /// How Marknet fits images to its input ([`InputFit::Auto`], the model's own, by default).
    pub fit: InputFit,
    /// Whether Marknet remembers the marker pitch per image size ([`Marknet::set_pitch_memory`]):
    /// on for streams of one sensor, off for datasets mixing sensors of one image size.
    pub remember_pitch: bool,
    /// Whether Marknet, with the pitch remembered, runs a stream's later frames on a window of its
    /// input around the lattice the first frame showed ([`Marknet::set_lattice_window`]).
    pub lattice_window: bool,
    /// Whether Marknet looks again, at a larger scale, where the lattice is squeezed, and searches
    /// for blobs between the squeezed markers ([`Marknet::set_close_look`]).
    pub close_look: bool,
}

impl Default for LocalizerConfig {
    /// The shipped models (`data/models` of [`project_home`]), the tuned blob parameters of
    /// `data/blob_params.json` ([`BlobParams::tuned`]), ONNX Runtime's defaults, the model's own
    /// input layout, the pitch remembered per image size (one sensor per stream), a stream's
    /// frames run on a window around its lattice, and a closer look where the lattice is squeezed.
    fn default() -> Self {
        let models = project_home().join("data/models");
        Self {
            marknet_path: models.join("marknet.onnx"),
            mre_path: models.join("mre.onnx"),
            blob: BlobParams::tuned(),
            session: SessionOptions::default(),
            fit: InputFit::Auto,
            remember_pitch: true,
            lattice_window: true,
            close_look: true,
        }
    }
}

/// The folder holding the shipped `data/` and `calib/`: `GELSTEREO_HOME` when set, else the checkout
/// this library was built from (not in a `relocatable` build), else the folder of the running
/// executable.
pub fn project_home() -> PathBuf {
    if let Some(p) = std::env::var_os("GELSTEREO_HOME").filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    #[cfg(not(feature = "relocatable"))]
    {
        let checkout = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."));
        if checkout.join("data").is_dir() {
            return checkout.canonicalize().unwrap_or(checkout);
        }
    }
    std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from("."))
}

/// Builds the localizer for `method`. Models are loaded (and their contract checked) only for the
/// learned methods, so `blob` works without ONNX Runtime.
pub fn create_localizer(method: Method, config: &LocalizerConfig) -> Result<Box<dyn Localizer + Send>> {
    Ok(match method {
        Method::Blob => Box::new(BlobLocalizer::new(config.blob)?),
        Method::Yolo => Box::new(yolo::YoloLocalizer::load(
            &yolo::model_path(config),
            &config.session,
        )?),
        Method::Marknet => {
            let mut net = Marknet::load(&config.marknet_path, &config.session)?;
            net.set_fit(config.fit);
            net.set_pitch_memory(config.remember_pitch);
            net.set_lattice_window(config.lattice_window);
            net.set_close_look(config.close_look);
            Box::new(net)
        }
        Method::MarknetMre => {
            let mre = Mre::load(&config.mre_path, &config.session)?;
            let mut net = Marknet::load(&config.marknet_path, &config.session)?.with_mre(mre)?;
            net.set_fit(config.fit);
            net.set_pitch_memory(config.remember_pitch);
            net.set_lattice_window(config.lattice_window);
            net.set_close_look(config.close_look);
            Box::new(net)
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_8UC3, CV_16UC1, Scalar};

    #[test]
    fn methods_parse_and_unknown_names_are_reported() {
        assert_eq!(
            Method::parse_list("blob, marknet-mre,blob").unwrap(),
            [Method::Blob, Method::MarknetMre]
        );
        for m in Method::ALL {
            assert_eq!(m.as_str().parse::<Method>().unwrap(), m);
        }
        let err = Method::parse_list("blob,ssd").unwrap_err().to_string();
        assert!(err.contains("'ssd'") && err.contains("marknet-mre"), "{err}");
        assert!(Method::parse_list(" , ").is_err());
    }

    #[test]
    fn images_of_unusable_size_or_type_are_rejected() {
        let tiny = Mat::new_rows_cols_with_default(8, 640, CV_8UC3, Scalar::all(0.0)).unwrap();
        let err = check_image(&tiny).unwrap_err().to_string();
        assert!(err.contains("640x8") && err.contains("at least 16x16"), "{err}");
        let deep = Mat::new_rows_cols_with_default(32, 32, CV_16UC1, Scalar::all(0.0)).unwrap();
        assert!(check_image(&deep).unwrap_err().to_string().contains("8-bit"));
        assert!(check_image(&Mat::default()).is_err());
        let a = Mat::new_rows_cols_with_default(48, 64, CV_8UC3, Scalar::all(0.0)).unwrap();
        let b = Mat::new_rows_cols_with_default(48, 60, CV_8UC3, Scalar::all(0.0)).unwrap();
        let err = check_stereo_sizes(&StereoPair::new(a, b))
            .unwrap_err()
            .to_string();
        assert!(err.contains("64x48") && err.contains("60x48"), "{err}");
    }
}
