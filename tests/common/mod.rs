//! Helpers shared by the end-to-end tests of the `gelstereo` binary (`tests/*.rs` and
//! `crates/gelstereo-cli/tests/*.rs`). Each test file uses only some of them.
#![allow(dead_code)]

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
