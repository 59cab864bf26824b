//! The Marker Rationality Evaluator through ONNX Runtime: the second network of `marknet-mre`, which
//! scores the feature vector of each candidate Marknet is unsure of ([`crate::postprocess`]).

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::TensorRef;

use crate::contract::{MRE_INPUT, MRE_OUTPUT};
use crate::onnx::{Opened, SessionOptions, check_finite, onnx_err, open_session};
use crate::postprocess::MRE_FEATURES;
use crate::{MreContract, Result};

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

/// The Marker Rationality Evaluator: 11 features in, the probability that a candidate is right out.
pub struct Mre {
    pub(crate) path: PathBuf,
    session: Session,
    pub(crate) contract: MreContract,
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
