//! End-to-end: `gelstereo adapt` on the bundled simulated recording (`data/sample/press-slide`, 24
//! stereo frames) with a budget of seconds, through the project's Python environment (`.venv`, made by
//! scripts/setup.sh): the folder it writes must load with `--models` (the model contract is checked on
//! load) and find the sample's markers; the shipped models are refused as output; a missing Python
//! fails before any work and leaves nothing behind.

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

mod common;
use common::{fails_with, gelstereo, repo, text};

fn entries(dir: &std::path::Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn adapt_writes_a_model_folder_that_loads_with_models_and_finds_the_markers() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("my-sensor");
    let data = tmp.path().join("pseudo");
    let sample = repo().join("data/sample/press-slide");
    let run = gelstereo(&[
        "adapt",
        "--out",
        out.to_str().unwrap(),
        "--minutes",
        "0.05",
        "--max-frames",
        "12",
        "--grid",
        "23x23",
        "--threads",
        "1",
        "--train-threads",
        "1",
        "--keep-data",
        data.to_str().unwrap(),
        sample.to_str().unwrap(),
    ]);
    let t = text(&run);
    assert!(run.status.success(), "gelstereo adapt failed:\n{t}");
    assert_eq!(
        entries(tmp.path()),
        ["my-sensor", "pseudo"],
        "a temporary folder was left behind:\n{t}"
    );
    for f in [
        "marknet.onnx",
        "mre.onnx",
        "MODEL_CARD.md",
        "adapt.json",
        "export_report.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing from the adapted folder:\n{t}");
    }
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("adapt.json")).unwrap()).unwrap();
    let labels = manifest["train_labels"].as_u64().unwrap();
    let views = manifest["train_views"].as_u64().unwrap();
    // 12 frames x 2 views of a 23 x 23 lattice that fills the view: most of 529 markers per view.
    assert!(views >= 12 && labels >= 400 * views, "{manifest}");
    assert!(labels <= 529 * views, "more labels than markers: {manifest}");
    let card = std::fs::read_to_string(out.join("MODEL_CARD.md")).unwrap();
    assert!(
        card.contains("press-slide") && card.contains(&labels.to_string()),
        "{card}"
    );
    // The pseudo-labels are the trainer's dataset layout, with ignore masks beside the images.
    let exp = data.join("train/exp_0000");
    assert!(
        exp.join("markers.csv").is_file() && exp.join("left").is_dir() && exp.join("ignore_left").is_dir()
    );
    assert_eq!(entries(&exp.join("left")), entries(&exp.join("ignore_left")));

    // The contract is checked on load: a folder that loads and finds the markers passes it.
    let csv = tmp.path().join("found.csv");
    let detect = gelstereo(&[
        "detect",
        "--models",
        out.to_str().unwrap(),
        "--threads",
        "1",
        "--out",
        csv.to_str().unwrap(),
        sample.join("left/000000.jpg").to_str().unwrap(),
    ]);
    assert!(
        detect.status.success(),
        "detect --models failed:\n{}",
        text(&detect)
    );
    let found = std::fs::read_to_string(&csv).unwrap().lines().count() - 1;
    // The default finds all 529 on this frame; seconds of fine-tuning on its own labels keep them.
    assert!(
        (500..=529).contains(&found),
        "{found} markers with the adapted models"
    );
}

#[test]
fn adapt_refuses_the_shipped_models_and_a_missing_python_before_any_work() {
    let sample = repo().join("data/sample/press-slide");
    let shipped = repo().join("data/models");
    fails_with(
        &[
            "adapt",
            "--out",
            shipped.to_str().unwrap(),
            sample.to_str().unwrap(),
        ],
        &["--out", "shipped default models"],
    );
    fails_with(
        &[
            "adapt",
            "--out",
            shipped.join("mine").to_str().unwrap(),
            sample.to_str().unwrap(),
        ],
        &["inside the shipped models folder"],
    );
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("m");
    let missing = tmp.path().join("no-python");
    fails_with(
        &[
            "adapt",
            "--out",
            out.to_str().unwrap(),
            "--python",
            missing.to_str().unwrap(),
            sample.to_str().unwrap(),
        ],
        &["no-python", "not found", "scripts/setup.sh"],
    );
    assert!(
        entries(tmp.path()).is_empty(),
        "files left behind: {:?}",
        entries(tmp.path())
    );
    fails_with(
        &[
            "adapt",
            "--out",
            out.to_str().unwrap(),
            tmp.path().join("nothing.avi").to_str().unwrap(),
        ],
        &["nothing.avi", "no such recording"],
    );
}
