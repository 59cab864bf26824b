//! The shipped Marknet-MRE, as the integration tests of this crate load it.

#![allow(clippy::unwrap_used, dead_code)] // test helpers: a failure is a test failure

use std::path::{Path, PathBuf};

use gelstereo_markers::{Marknet, Mre, SessionOptions};

/// The repository's root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Marknet with the MRE from data/models, one thread, no pitch remembered between images (each
/// test image is its own sensor).
pub fn shipped() -> Marknet {
    let options = SessionOptions {
        intra_threads: 1,
        use_cuda: false,
    };
    let models = root().join("data/models");
    let mre = Mre::load(&models.join("mre.onnx"), &options).unwrap();
    let mut net = Marknet::load(&models.join("marknet.onnx"), &options)
        .unwrap()
        .with_mre(mre)
        .unwrap();
    net.set_pitch_memory(false);
    net
}
