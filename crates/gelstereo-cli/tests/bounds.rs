//! End-to-end tests of the `gelstereo` binary for issue 43's "resources bounded before use" and
//! "bad values" cases (docs/reliability.md): every size from a flag, a file or the environment is
//! checked before anything is allocated, broken models and malformed files are errors naming them,
//! and messages say each thing once. Inputs are the bundled sample recording, the ONNX fixtures
//! (data/fixtures/onnx, made by train/scripts/make_nan_fixture.py) and files made here in temporary
//! folders.

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

#[path = "../../../tests/common/mod.rs"]
mod common;
use common::{fails_with, gelstereo_command, repo, sample, sample_copy, text};

fn fixtures() -> PathBuf {
    repo().join("data/fixtures/onnx")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs `gelstereo ARGS...` with the environment `env`, killing it after `limit` (a hang is the
/// failure some of these cases had): the output, or a test failure when it ran past the limit.
fn run_within(args: &[&str], env: &[(&str, &str)], limit: Duration) -> Output {
    let mut command = gelstereo_command();
    command.args(args).stdout(Stdio::piped()).stderr(Stdio::piped());
    for (k, v) in env {
        command.env(k, v);
    }
    let mut child = command.spawn().unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            child.kill().unwrap();
            let out = child.wait_with_output().unwrap();
            panic!("{args:?} ran past {limit:?}:\n{}", text(&out));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// [`run_within`] that must fail within `limit`, print every one of `needles` and not panic.
fn fails_within(args: &[&str], env: &[(&str, &str)], limit: Duration, needles: &[&str]) -> String {
    let out = run_within(args, env, limit);
    let t = text(&out);
    assert!(!out.status.success(), "{args:?} should fail:\n{t}");
    for n in needles {
        assert!(t.contains(n), "{args:?}: '{n}' missing from:\n{t}");
    }
    assert!(!t.contains("panicked"), "{args:?} panicked:\n{t}");
    t
}

const MINUTE: Duration = Duration::from_secs(60);

/// Issue 43 case 1: a calibration of nested YAML aliases (10 levels of 9 copies in a few hundred
/// bytes) is refused by name, before anything expands.
#[test]
fn yaml_aliases_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let mut yaml = String::from("%YAML:1.0\n---\na0: &a0 [1, 2, 3, 4, 5, 6, 7, 8, 9]\n");
    for k in 1..=10 {
        let copies = vec![format!("*a{}", k - 1); 9].join(", ");
        yaml.push_str(&format!("a{k}: &a{k} [{copies}]\n"));
    }
    assert!(yaml.len() < 600);
    let calib = dir.path().join("laughs.yaml");
    std::fs::write(&calib, yaml).unwrap();
    let out = dir.path().join("out");
    fails_within(
        &[
            "reconstruct",
            "--calib",
            s(&calib),
            "--from-ground-truth",
            "--out",
            s(&out),
            s(&sample()),
        ],
        &[],
        MINUTE,
        &["laughs.yaml", "line 4", "alias"],
    );
}

/// Issue 43 cases 6 and 11: a model whose weights are +inf (outputs +inf, not NaN) or an MRE whose
/// weights are NaN is an error naming the model, in detect, doctor and track, with no hang.
#[test]
fn models_with_infinite_or_nan_weights_are_errors_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let image = fixtures().join("dots_64x64.png");
    fails_within(
        &[
            "detect",
            "--method",
            "marknet",
            "--marknet",
            s(&fixtures().join("marknet_inf.onnx")),
            "--fit",
            "stretch",
            s(&image),
        ],
        &[],
        MINUTE,
        &["marknet_inf.onnx", "holds inf", "expected finite"],
    );
    for (marknet, mre, needles) in [
        ("marknet_inf.onnx", "mre_tiny.onnx", ["marknet.onnx", "holds inf"]),
        ("marknet_tiny.onnx", "mre_nan.onnx", ["mre.onnx", "holds NaN"]),
    ] {
        let models = dir.path().join(marknet.replace(".onnx", "-").to_owned() + mre);
        std::fs::create_dir(&models).unwrap();
        std::fs::copy(fixtures().join(marknet), models.join("marknet.onnx")).unwrap();
        std::fs::copy(fixtures().join(mre), models.join("mre.onnx")).unwrap();
        let t = fails_within(&["doctor", "--models", s(&models)], &[], MINUTE, &needles);
        assert!(t.contains("MISSING  Marknet-MRE run"), "{t}");
        let out = dir.path().join(format!("track-{mre}"));
        fails_within(
            &[
                "track",
                "--models",
                s(&models),
                "--quiet",
                "--out",
                s(&out),
                s(&sample()),
            ],
            &[],
            MINUTE,
            &needles,
        );
        assert!(!out.join("frames.csv").exists());
    }
}

/// `doctor` runs the shipped models on a real frame, the sample's first left view.
#[test]
fn doctor_runs_the_models_on_a_real_frame() {
    let out = run_within(&["doctor"], &[], MINUTE);
    let t = text(&out);
    let line = t
        .lines()
        .find(|l| l.contains("Marknet-MRE run"))
        .unwrap_or_else(|| panic!("{t}"));
    assert!(
        line.starts_with("ok") && line.contains("markers found on") && line.contains("000000.jpg"),
        "{t}"
    );
}

/// Issue 43 case 12: a checkerboard that would allocate gigabytes is refused before anything is
/// built or written.
#[test]
fn checkerboard_sizes_are_bounded_before_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cb");
    fails_within(
        &["simulate", "--checkerboard", "100000x100000", "--out", s(&out)],
        &[],
        MINUTE,
        &["100000", "2 to 200"],
    );
    assert!(!out.exists());
    fails_with(
        &[
            "calibrate",
            "--board",
            "9x100000",
            "--square-mm",
            "1.5",
            "--out",
            s(&dir.path().join("x.yaml")),
            s(&sample().join("left")),
            s(&sample().join("right")),
        ],
        &["100000", "2 to 200"],
    );
}

/// Issue 43 case 13: thread counts from RAYON_NUM_THREADS and OMP_NUM_THREADS are checked before
/// any pool starts; a refused count ends the run at once.
#[test]
fn thread_counts_from_the_environment_are_bounded() {
    let image = fixtures().join("dots_160x120.png");
    let detect = ["detect", "--method", "blob", s(&image)];
    for name in ["RAYON_NUM_THREADS", "OMP_NUM_THREADS"] {
        for value in ["100000", "4,100000", "lots"] {
            let start = Instant::now();
            fails_within(&detect, &[(name, value)], MINUTE, &[name, value, "to 256"]);
            assert!(start.elapsed() < Duration::from_secs(10));
        }
    }
    // Sensible counts, OpenMP's nested form and an empty variable run as usual.
    for (name, value) in [
        ("RAYON_NUM_THREADS", "2"),
        ("OMP_NUM_THREADS", "2,1"),
        ("OMP_NUM_THREADS", ""),
    ] {
        let out = run_within(&detect, &[(name, value)], MINUTE);
        assert!(out.status.success(), "{name}={value}: {}", text(&out));
    }
}

/// Issue 43 case 15: a malformed meta.json (invalid JSON, a wrong type, NaN, a value out of range)
/// stops track and reconstruct with an error naming the file and the field.
#[test]
fn malformed_meta_json_is_an_error_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let rec = sample_copy(dir.path(), 1);
    let meta = rec.join("meta.json");
    let good: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sample().join("meta.json")).unwrap()).unwrap();
    let mut bad_poisson = good.clone();
    bad_poisson["sensor"]["gel"]["poisson"] = serde_json::json!(0.7);
    let cases = [
        ("{\"grid\": ".to_owned(), vec!["meta.json", "EOF"]),
        (
            r#"{"grid": {"rows": "many", "cols": 23}}"#.to_owned(),
            vec!["meta.json", "invalid type"],
        ),
        (
            r#"{"grid": {"rows": 23, "cols": NaN}}"#.to_owned(),
            vec!["meta.json", "column 31"],
        ),
        (
            r#"{"grid": {"rows": 1, "cols": 23}}"#.to_owned(),
            vec!["meta.json", "'grid'", "2 to 1000", "1 x 23"],
        ),
        (
            r#"{"fps": -5}"#.to_owned(),
            vec!["meta.json", "'fps'", "frame rate", "-5"],
        ),
        (
            bad_poisson.to_string(),
            vec!["meta.json", "gel.poisson", "[0, 0.5)", "0.7"],
        ),
    ];
    for (k, (content, needles)) in cases.iter().enumerate() {
        std::fs::write(&meta, content).unwrap();
        let out = dir.path().join(format!("out{k}"));
        fails_within(
            &["track", "--method", "blob", "--quiet", "--out", s(&out), s(&rec)],
            &[],
            MINUTE,
            needles,
        );
        fails_within(
            &[
                "reconstruct",
                "--method",
                "blob",
                "--calib",
                s(&rec.join("calib.yaml")),
                "--out",
                s(&out),
                s(&rec),
            ],
            &[],
            MINUTE,
            needles,
        );
    }
}

/// Issue 43 case 18: a camera model past the size limit is refused before it is read whole, and
/// a long string in one is echoed cut short.
#[test]
fn camera_models_are_capped_and_long_strings_cut_short() {
    let dir = tempfile::tempdir().unwrap();
    let model = std::fs::read_to_string(sample().join("left.cameramodel")).unwrap();
    let right = sample().join("right.cameramodel");
    let big = dir.path().join("big.cameramodel");
    let mut text = model.clone();
    text.push('#');
    text.push_str(&"x".repeat(5 << 20));
    std::fs::write(&big, &text).unwrap();
    let out = dir.path().join("out");
    let calib = format!("{},{}", s(&big), s(&right));
    let recording = sample();
    let args = [
        "reconstruct",
        "--calib",
        &calib,
        "--from-ground-truth",
        "--out",
        s(&out),
        s(&recording),
    ];
    fails_within(
        &args,
        &[],
        MINUTE,
        &["big.cameramodel", "larger than 4194304 bytes"],
    );
    let long = model.replace("LENSMODEL_OPENCV5", &format!("LENSMODEL_{}", "Q".repeat(1 << 20)));
    std::fs::write(&big, long).unwrap();
    let t = fails_within(
        &args,
        &[],
        MINUTE,
        &["big.cameramodel", "unsupported lens model", "characters in all"],
    );
    assert!(
        t.len() < 2_000,
        "the error echoes the whole string: {} bytes",
        t.len()
    );
}

/// Issue 43 case 21: NaN and out-of-range numbers are refused with the option and the range.
#[test]
fn nan_and_out_of_range_numbers_are_refused() {
    let calib = sample().join("calib.yaml");
    for (flag, value, range) in [
        ("--gt-missing", "2", "from 0 to 1"),
        ("--gt-missing", "NaN", "from 0 to 1"),
        ("--gt-noise-px", "-1", "from 0 to 1000"),
        ("--gt-noise-px", "inf", "from 0 to 1000"),
    ] {
        // `--flag=VALUE`: clap would take a separate "-1" for an option of its own.
        let given = format!("{flag}={value}");
        fails_with(
            &[
                "reconstruct",
                "--calib",
                s(&calib),
                "--from-ground-truth",
                &given,
                "--out",
                "x",
                s(&sample()),
            ],
            &[flag, value, range],
        );
    }
    for value in ["NaN", "-3", "1e9"] {
        let given = format!("--arrow-scale={value}");
        fails_with(
            &["track", &given, "--out", "x", s(&sample())],
            &["--arrow-scale", value, "from 0 to 1000"],
        );
    }
}

/// Issue 43's unclear messages: each says the file, the field and the range once.
#[test]
fn messages_say_each_thing_once() {
    let dir = tempfile::tempdir().unwrap();
    // The OS error text once, not twice.
    let missing = dir.path().join("missing.yaml");
    let t = fails_within(
        &[
            "track",
            "--method",
            "blob",
            "--calib",
            s(&missing),
            "--out",
            "x",
            s(&sample()),
        ],
        &[],
        MINUTE,
        &["missing.yaml", "No such file or directory"],
    );
    assert_eq!(t.matches("No such file or directory").count(), 1, "{t}");
    // A lattice too large says the range, not "must be a number".
    fails_with(
        &["track", "--grid", "100000x100000", "--out", "x", s(&sample())],
        &["--grid", "100000", "from 2 to 1000"],
    );
    // A binary file given as a calibration says so, with no "line 0".
    let binary = dir.path().join("binary.yaml");
    let mut bytes = b"\x7fELF\x02\x01\x01\0".to_vec();
    bytes.extend((0..=255u8).cycle().take(4096));
    std::fs::write(&binary, bytes).unwrap();
    let t = fails_within(
        &[
            "reconstruct",
            "--calib",
            s(&binary),
            "--from-ground-truth",
            "--out",
            "x",
            s(&sample()),
        ],
        &[],
        MINUTE,
        &["binary.yaml", "binary data"],
    );
    assert!(!t.contains("line 0"), "{t}");
    // eval names --sensor only when it was given.
    let dataset = dir.path().join("dataset");
    std::fs::create_dir_all(dataset.join("test/exp_0000")).unwrap();
    std::fs::write(dataset.join("dataset.json"), "{\"experiments\": 3}").unwrap();
    let t = fails_within(
        &["eval", "--dataset", s(&dataset), "--methods", "blob"],
        &[],
        MINUTE,
        &["dataset.json"],
    );
    assert!(!t.contains("--sensor"), "{t}");
}
