//! Helpers shared by the end-to-end tests of the `gelstereo` binary (`tests/*.rs` and
//! `crates/gelstereo-cli/tests/*.rs`). Each test file uses only some of them.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `gelstereo` binary cargo built for these tests, ready for arguments.
pub fn gelstereo_command() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gelstereo"))
}

/// Runs `gelstereo ARGS...` to completion.
pub fn gelstereo(args: &[&str]) -> Output {
    gelstereo_command().args(args).output().expect("run gelstereo")
}

/// Standard output then standard error, as text (what a user sees).
pub fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// The repository root (the test binaries are built for the `gelstereo-cli` crate).
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The bundled sample recording (`data/sample/press-slide`).
pub fn sample() -> PathBuf {
    repo().join("data/sample/press-slide")
}

/// A copy of the sample's first `frames` stereo frames and its calibration in `dir/rec`, for tests
/// that spoil or overwrite a recording.
pub fn sample_copy(dir: &Path, frames: usize) -> PathBuf {
    let rec = dir.join("rec");
    for side in ["left", "right"] {
        std::fs::create_dir_all(rec.join(side)).expect("create the copy's views");
        for k in 0..frames {
            let name = format!("{k:06}.jpg");
            std::fs::copy(sample().join(side).join(&name), rec.join(side).join(&name)).expect("copy a frame");
        }
    }
    std::fs::copy(sample().join("calib.yaml"), rec.join("calib.yaml")).expect("copy the calibration");
    rec
}

/// Runs `gelstereo ARGS...`, which must fail, print every one of `needles` and not panic.
pub fn fails_with(args: &[&str], needles: &[&str]) {
    let out = gelstereo(args);
    let t = text(&out);
    assert!(!out.status.success(), "{args:?} should fail:\n{t}");
    for n in needles {
        assert!(t.contains(n), "{args:?}: '{n}' missing from:\n{t}");
    }
    assert!(!t.contains("panicked"), "{args:?} panicked:\n{t}");
}
