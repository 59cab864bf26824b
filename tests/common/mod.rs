//! Helpers shared by the end-to-end tests of the `gelstereo` binary (`tests/*.rs` and
//! `crates/gelstereo-cli/tests/*.rs`). Each test file uses only some of them.
#![allow(dead_code)]

use std::path::PathBuf;
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
