//! Property-based tests of the calibration readers (OpenCV FileStorage YAML / XML, mrcal
//! `.cameramodel`): whatever a file holds, the reader returns a rig or an error naming the file; it
//! never panics, aborts, crashes or overflows the stack (the nesting depth is bounded before the file
//! is parsed). Fixtures: the committed `tests/data/` files (made by `tests/data/generate.py`), mutated here.
//! Case counts are small for CI; docs/reliability.md gives a longer run (PROPTEST_CASES).

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use gelstereo_geometry::StereoRig;
use proptest::prelude::*;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// A YAML value: numbers, words, and flow sequences / maps nested up to 40 deep (past the limit).
fn yaml_value() -> impl Strategy<Value = String> {
    let leaf = prop_oneof![
        any::<f64>().prop_map(|v| v.to_string()),
        any::<i32>().prop_map(|v| v.to_string()),
        Just("!!opencv-matrix".to_owned()),
        Just("&a 1".to_owned()),
        Just("*a".to_owned()),
        "[a-z\"' :#]{0,6}",
    ];
    leaf.prop_recursive(40, 200, 4, |inner| {
        prop_oneof![
            proptest::collection::vec(inner.clone(), 0..4).prop_map(|v| format!("[{}]", v.join(", "))),
            proptest::collection::vec(("[a-z]{1,4}", inner), 0..3).prop_map(|v| {
                let items: Vec<String> = v.into_iter().map(|(k, x)| format!("{k}: {x}")).collect();
                format!("{{{}}}", items.join(", "))
            }),
        ]
    })
}

fn key() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("K1"),
        Just("D1"),
        Just("K2"),
        Just("D2"),
        Just("R"),
        Just("T"),
        Just("image_width"),
        Just("image_height"),
        Just("image_size"),
        Just("M1"),
    ]
    .prop_map(str::to_owned)
}

/// Reads `text` as a calibration file named `name` in a fresh folder; the error (if any) must name it.
fn read_as(name: &str, text: &[u8]) -> Result<(), TestCaseError> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, text).unwrap();
    if let Err(e) = StereoRig::load(path.to_str().unwrap()) {
        let message = e.to_string();
        prop_assert!(message.contains(name), "{}", message);
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// OpenCV YAML made of the real keys with random (and deeply nested) values.
    #[test]
    fn opencv_yaml_with_random_values_reads_or_names_the_file(
        entries in proptest::collection::vec((key(), yaml_value()), 0..8),
        indent in 0usize..3,
    ) {
        let mut text = String::from("%YAML:1.0\n---\n");
        for (k, v) in entries {
            text.push_str(&format!("{}{k}: {v}\n", " ".repeat(indent)));
        }
        read_as("calib.yaml", text.as_bytes())?;
    }

    /// The committed OpenCV YAML and XML calibrations with bytes replaced, inserted or cut.
    #[test]
    fn mutated_opencv_files_read_or_name_the_file(
        xml in any::<bool>(),
        edits in proptest::collection::vec((any::<usize>(), any::<u8>(), 0u8..3), 1..6),
    ) {
        let (name, mut bytes) = if xml {
            ("opencv5.xml", std::fs::read(data("opencv5.xml")).unwrap())
        } else {
            ("opencv8.yaml", std::fs::read(data("opencv8.yaml")).unwrap())
        };
        gelstereo_core::testing::mutate(&mut bytes, &edits);
        read_as(name, &bytes)?;
    }

    /// Arbitrary bytes given as an OpenCV YAML or XML calibration or as a mrcal model.
    #[test]
    fn arbitrary_bytes_read_or_name_the_file(
        kind in 0usize..3,
        bytes in proptest::collection::vec(any::<u8>(), 0..512),
    ) {
        match kind {
            0 => read_as("calib.yaml", &bytes)?,
            1 => read_as("calib.xml", &bytes)?,
            _ => {
                let dir = tempfile::tempdir().unwrap();
                let left = dir.path().join("left.cameramodel");
                std::fs::write(&left, &bytes).unwrap();
                let right = dir.path().join("right.cameramodel");
                std::fs::copy(data("opencv5_right.cameramodel"), &right).unwrap();
                if let Err(e) = StereoRig::read_mrcal(&left, &right) {
                    let message = e.to_string();
                    prop_assert!(message.contains("left.cameramodel"), "{}", message);
                }
            }
        }
    }

    /// The committed mrcal pair with the left model's bytes replaced, inserted or cut.
    #[test]
    fn mutated_mrcal_models_read_or_name_the_file(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>(), 0u8..3), 1..6),
    ) {
        let mut bytes = std::fs::read(data("opencv5_left.cameramodel")).unwrap();
        gelstereo_core::testing::mutate(&mut bytes, &edits);
        let dir = tempfile::tempdir().unwrap();
        let left = dir.path().join("left.cameramodel");
        std::fs::write(&left, &bytes).unwrap();
        std::fs::copy(data("opencv5_right.cameramodel"), dir.path().join("right.cameramodel")).unwrap();
        if let Err(e) = StereoRig::read_mrcal(&left, dir.path().join("right.cameramodel")) {
            let message = e.to_string();
            prop_assert!(message.contains("cameramodel"), "{}", message);
        }
    }
}

#[test]
fn deeply_nested_calibrations_are_refused_before_they_are_parsed() {
    let depth = 50_000;
    let yaml = format!("%YAML:1.0\n---\nK1: {}{}\n", "[".repeat(depth), "]".repeat(depth));
    let xml = format!(
        "<?xml version=\"1.0\"?>\n<opencv_storage>\n<K1>{}{}</K1>\n</opencv_storage>\n",
        "<a>".repeat(depth),
        "</a>".repeat(depth)
    );
    for (name, text) in [("deep.yaml", yaml), ("deep.xml", xml)] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        let err = StereoRig::load(path.to_str().unwrap()).unwrap_err().to_string();
        assert!(
            err.contains(name) && err.contains("nested") && err.contains("at most 32"),
            "{err}"
        );
    }
}

/// Issue 43 case 1: nested aliases (10 levels of 9 copies, a few hundred bytes that a loader would
/// expand to 9^10 values) are refused before anything is expanded.
#[test]
fn yaml_aliases_are_refused_before_they_expand() {
    let mut yaml = String::from("%YAML:1.0\n---\na0: &a0 [1, 2, 3, 4, 5, 6, 7, 8, 9]\n");
    for k in 1..=10 {
        let p = k - 1;
        yaml.push_str(&format!(
            "a{k}: &a{k} [*a{p}, *a{p}, *a{p}, *a{p}, *a{p}, *a{p}, *a{p}, *a{p}, *a{p}]\n"
        ));
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("laughs.yaml");
    std::fs::write(&path, &yaml).unwrap();
    let err = StereoRig::load(path.to_str().unwrap()).unwrap_err().to_string();
    assert!(
        err.contains("laughs.yaml") && err.contains("line 4") && err.contains("alias"),
        "{err}"
    );
    // One alias is refused as well: the calibration keys are written out.
    let calib = std::fs::read_to_string(data("opencv8.yaml")).unwrap();
    let aliased = calib
        .replacen("K2:", "K2: *k1\nunused:", 1)
        .replacen("K1:", "K1: &k1", 1);
    std::fs::write(&path, aliased).unwrap();
    let err = StereoRig::load(path.to_str().unwrap()).unwrap_err().to_string();
    assert!(err.contains("laughs.yaml") && err.contains("alias"), "{err}");
}

/// A binary file given as a calibration says so, with no "line 0".
#[test]
fn binary_calibrations_are_named_as_binary() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("calib.yaml");
    let mut bytes = b"\x7fELF\x02\x01\x01".to_vec();
    bytes.extend((0..=255u8).cycle().take(4096));
    std::fs::write(&path, &bytes).unwrap();
    let err = StereoRig::load(path.to_str().unwrap()).unwrap_err().to_string();
    assert!(
        err.contains("calib.yaml") && err.contains("binary") && !err.contains("line 0"),
        "{err}"
    );
}
