//! Opening ONNX models: one session per model with the crate's session options, its
//! `metadata_props` and its input / output signatures (every ONNX localizer, Marknet, MRE and YOLO,
//! opens its model here), and the checks of a run's output.

use std::collections::BTreeMap;
use std::path::Path;

use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::ValueType;

use crate::contract::TensorSpec;
use crate::{Error, Result, runtime};

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

/// Opens an ONNX model and returns its `metadata_props`, sorted by key (what `gelstereo doctor` reports).
pub fn model_metadata(path: &Path) -> Result<BTreeMap<String, String>> {
    Ok(open_session(path, &SessionOptions::default())?.metadata)
}

/// Whether this ONNX Runtime build includes the CUDA execution provider.
pub fn cuda_available() -> bool {
    use ort::ep::ExecutionProvider as _;
    ort::ep::CUDA::is_available().unwrap_or(false)
}
