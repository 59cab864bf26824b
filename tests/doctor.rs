//! End-to-end: `gelstereo doctor` and `gelstereo --version` against the real ONNX Runtime library
//! that scripts/setup.sh installs.

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::path::PathBuf;
use std::process::Output;

mod common;
use common::{gelstereo_command, text};

fn gelstereo(args: &[&str], ort_dylib: Option<&PathBuf>) -> Output {
    let mut cmd = gelstereo_command();
    cmd.args(args);
    match ort_dylib {
        Some(p) => cmd.env("ORT_DYLIB_PATH", p),
        None => cmd.env_remove("ORT_DYLIB_PATH"),
    };
    cmd.output().expect("run gelstereo")
}

#[test]
fn doctor_passes_after_setup_without_any_environment_variable() {
    let out = gelstereo(&["doctor"], None);
    let t = text(&out);
    assert!(out.status.success(), "doctor failed after setup:\n{t}");
    assert!(t.contains("ok       ONNX Runtime") && t.contains("1.31.1"), "{t}");
    assert!(t.contains("ok       OpenCV") && t.contains("4."), "{t}");
}

#[test]
fn doctor_fails_with_a_fix_when_the_onnxruntime_library_is_removed() {
    let installed = gelstereo::markers::runtime::locate().expect("setup installed ONNX Runtime");
    let dir = tempfile::tempdir().unwrap();
    let copy = dir.path().join("libonnxruntime.so");
    std::fs::copy(&installed, &copy).unwrap();

    let present = gelstereo(&["doctor"], Some(&copy));
    assert!(
        present.status.success(),
        "doctor with a copied library:\n{}",
        text(&present)
    );

    std::fs::remove_file(&copy).unwrap();
    let removed = gelstereo(&["doctor"], Some(&copy));
    let t = text(&removed);
    assert!(
        !removed.status.success(),
        "doctor passed without ONNX Runtime:\n{t}"
    );
    assert!(t.contains("MISSING  ONNX Runtime"), "{t}");
    assert!(
        t.contains(&copy.display().to_string()) && t.contains("scripts/setup.sh"),
        "{t}"
    );
}

#[test]
fn version_names_opencv_and_onnxruntime() {
    let out = gelstereo(&["--version"], None);
    let t = text(&out);
    assert!(out.status.success(), "{t}");
    assert!(
        t.contains(env!("CARGO_PKG_VERSION")) && t.contains("OpenCV 4.") && t.contains("ONNX Runtime 1.31.1"),
        "{t}"
    );
}

#[test]
fn doctor_away_from_the_project_passes_with_the_models_compiled_in() {
    let home = tempfile::tempdir().unwrap();
    let cache = tempfile::tempdir().unwrap();
    let out = gelstereo_command()
        .arg("doctor")
        .env("GELSTEREO_HOME", home.path())
        .env("XDG_CACHE_HOME", cache.path())
        .output()
        .expect("run gelstereo");
    let t = text(&out);
    assert!(out.status.success(), "doctor without the project's files:\n{t}");
    let unpacked = cache.path().join("gelstereo");
    assert!(
        t.contains("ok       Marknet model") && t.contains(&unpacked.display().to_string()),
        "{t}"
    );
    let models = std::fs::read_dir(&unpacked)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let shipped = common::repo().join("data/models");
    for name in ["marknet.onnx", "mre.onnx"] {
        assert_eq!(
            std::fs::read(models.join(name)).unwrap(),
            std::fs::read(shipped.join(name)).unwrap(),
            "{name}"
        );
    }
}
