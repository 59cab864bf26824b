//! Reading a dataset's `dataset.json`, which the simulator writes beside its recordings (a recording's
//! `meta.json` is read by [`gelstereo_sensor::RecordingMeta`]). A file that is present but malformed
//! is an error naming the file and the field.

use std::path::Path;

use gelstereo_core::limits::{MAX_DESCRIPTION_BYTES, read_text_at_most};
use serde::Deserialize;

use crate::dataset::Split;
use crate::error::{Error, Result};

/// One experiment listed in `dataset.json`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct ManifestExperiment {
    /// Its name, e.g. `exp_0003`.
    pub name: String,
    /// Its folder relative to the dataset, e.g. `train/exp_0003`.
    pub path: String,
    /// The split it belongs to.
    pub split: Split,
    /// Its number of stereo frames.
    pub frames: u32,
    /// The name of its sensor description.
    pub sensor: String,
}

/// The parts of `dataset.json` that readers use.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct DatasetManifest {
    /// The generator that wrote it (`gelstereo-sim VERSION`).
    pub generator: String,
    /// Every experiment of the dataset.
    pub experiments: Vec<ManifestExperiment>,
}

impl DatasetManifest {
    /// Reads `DIR/dataset.json`.
    pub fn read(dataset: &Path) -> Result<Self> {
        let path = dataset.join("dataset.json");
        let text = read_text_at_most(&path, MAX_DESCRIPTION_BYTES).map_err(crate::error::io_err(&path))?;
        Self::parse(&path, &text)
    }

    /// Parses the text of a `dataset.json` read from `path` (named in errors).
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let manifest: Self = serde_json::from_str(text).map_err(|e| syntax(path, &e))?;
        if let Some(e) = manifest.experiments.iter().find(|e| !is_relative_folder(&e.path)) {
            return Err(field(
                path,
                "experiments[].path",
                "a folder inside the dataset",
                &e.path,
            ));
        }
        Ok(manifest)
    }
}

/// Whether `path` names a folder below the dataset (no `..`, not absolute).
fn is_relative_folder(path: &str) -> bool {
    let p = Path::new(path);
    !path.is_empty()
        && p.components()
            .all(|c| matches!(c, std::path::Component::Normal(_)))
}

fn syntax(path: &Path, e: &serde_json::Error) -> Error {
    gelstereo_sensor::error::syntax(path, e).into()
}

fn field(path: &Path, name: &str, expected: &str, found: &str) -> Error {
    gelstereo_sensor::error::field(path, name, expected, found).into()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn garbage_dataset_manifests_are_named() {
        let p = Path::new("ds/dataset.json");
        for text in [
            "",
            "[]",
            r#"{"generator": "x"}"#,
            r#"{"generator": "x", "experiments": [{"name": 3}]}"#,
        ] {
            let err = DatasetManifest::parse(p, text).unwrap_err().to_string();
            assert!(err.contains("ds/dataset.json"), "{err}");
        }
        let escape = r#"{"generator": "x", "experiments": [{"name": "e", "path": "../../etc", "split": "train", "frames": 2, "sensor": "s"}]}"#;
        let err = DatasetManifest::parse(p, escape).unwrap_err().to_string();
        assert!(err.contains("experiments[].path"), "{err}");
    }

    /// A small JSON value generator: scalars, and arrays / objects of them a few levels deep, with
    /// the keys the readers look for among the random ones.
    fn json_value() -> impl Strategy<Value = serde_json::Value> {
        let leaf = prop_oneof![
            Just(serde_json::Value::Null),
            any::<bool>().prop_map(serde_json::Value::from),
            any::<i64>().prop_map(serde_json::Value::from),
            any::<f64>().prop_map(serde_json::Value::from),
            "[a-z_]{0,8}".prop_map(serde_json::Value::from),
        ];
        leaf.prop_recursive(4, 32, 6, |inner| {
            let key = prop_oneof![
                Just("grid".to_owned()),
                Just("rows".to_owned()),
                Just("cols".to_owned()),
                Just("image_width".to_owned()),
                Just("image_height".to_owned()),
                Just("sensor".to_owned()),
                Just("experiments".to_owned()),
                Just("generator".to_owned()),
                Just("path".to_owned()),
                "[a-z]{1,6}",
            ];
            prop_oneof![
                proptest::collection::vec(inner.clone(), 0..4).prop_map(serde_json::Value::from),
                proptest::collection::btree_map(key, inner, 0..6)
                    .prop_map(|m| serde_json::Value::Object(m.into_iter().collect())),
            ]
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        /// Any JSON text, or any bytes, gives a value or an error naming the file: never a panic.
        #[test]
        fn meta_and_manifest_parsers_never_panic(value in json_value(), bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let p = Path::new("x/meta.json");
            for text in [value.to_string(), String::from_utf8_lossy(&bytes).into_owned()] {
                if let Err(e) = gelstereo_sensor::RecordingMeta::parse(p, &text) {
                    prop_assert!(e.to_string().contains("x/meta.json"), "{}", e);
                }
                if let Err(e) = DatasetManifest::parse(p, &text) {
                    prop_assert!(e.to_string().contains("x/meta.json"), "{}", e);
                }
            }
        }
    }
}
