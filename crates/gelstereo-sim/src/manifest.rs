//! Reading what the simulator writes beside its images: a dataset's `dataset.json` and a recording's
//! `meta.json`. Readers (evaluation, tracking, reconstruction) take the grid, the image size and the
//! sensor from here; a file that is present but malformed is an error naming the file and the field,
//! never a silent fallback to the reference sensor.

use std::path::{Path, PathBuf};

use gelstereo_core::limits::{MAX_DESCRIPTION_BYTES, MAX_GRID_SIDE, read_text_at_most};
use gelstereo_core::{GridShape, ImageSize};
use serde::Deserialize;

use crate::dataset::Split;
use crate::error::{Error, Result};
use crate::sensor::SensorSpec;

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

/// What a recording's `meta.json` states: each field is `None` when absent.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingMeta {
    /// The file it was read from.
    pub path: PathBuf,
    /// The marker lattice (`grid.rows`, `grid.cols`).
    pub grid: Option<GridShape>,
    /// The image size (`image_width`, `image_height`).
    pub image_size: Option<ImageSize>,
    /// The sensor description (`sensor`), validated.
    pub sensor: Option<SensorSpec>,
    /// The frame rate (`fps`, or `frame_rate_hz`), Hz.
    pub frame_rate_hz: Option<f64>,
}

#[derive(Deserialize)]
struct RawGrid {
    rows: u16,
    cols: u16,
}

#[derive(Deserialize)]
struct RawMeta {
    grid: Option<RawGrid>,
    image_width: Option<u32>,
    image_height: Option<u32>,
    sensor: Option<serde_json::Value>,
    fps: Option<f64>,
    frame_rate_hz: Option<f64>,
}

/// Highest frame rate a recording may state, Hz (high-speed cameras reach tens of kHz).
pub const MAX_FRAME_RATE_HZ: f64 = 1e6;

impl RecordingMeta {
    /// Reads `DIR/meta.json`; `Ok(None)` when the recording has none (a real recording).
    pub fn read(dir: &Path) -> Result<Option<Self>> {
        let path = dir.join("meta.json");
        match read_text_at_most(&path, MAX_DESCRIPTION_BYTES) {
            Ok(text) => Self::parse(&path, &text).map(Some),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(Error::Io { path, error: e }),
        }
    }

    /// Parses the text of a `meta.json` read from `path` (named in errors).
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let raw: RawMeta = serde_json::from_str(text).map_err(|e| syntax(path, &e))?;
        let grid = match raw.grid {
            Some(g) if !(2..=MAX_GRID_SIDE).contains(&g.rows) || !(2..=MAX_GRID_SIDE).contains(&g.cols) => {
                return Err(field(
                    path,
                    "grid",
                    &format!("2 to {MAX_GRID_SIDE} rows and columns"),
                    &format!("{} x {}", g.rows, g.cols),
                ));
            }
            Some(g) => Some(GridShape {
                rows: g.rows,
                cols: g.cols,
            }),
            None => None,
        };
        let image_size = match (raw.image_width, raw.image_height) {
            (Some(width), Some(height)) => {
                gelstereo_core::limits::check_image_dimensions(u64::from(width), u64::from(height))
                    .and_then(|()| {
                        (width > 0 && height > 0)
                            .then_some(())
                            .ok_or_else(|| "a zero side".to_owned())
                    })
                    .map_err(|e| field(path, "image_width/image_height", "a positive image size", &e))?;
                Some(ImageSize { width, height })
            }
            (None, None) => None,
            _ => {
                return Err(field(
                    path,
                    "image_width/image_height",
                    "both or neither",
                    "only one of them",
                ));
            }
        };
        let sensor = match raw.sensor {
            Some(value) => {
                let name = format!("{} (field 'sensor')", path.display());
                let spec: SensorSpec = serde_json::from_value(value).map_err(|e| Error::SensorSyntax {
                    path: path.to_owned(),
                    message: format!("field 'sensor': {e}"),
                })?;
                spec.validate(&name)?;
                Some(spec)
            }
            None => None,
        };
        let frame_rate_hz = match (raw.fps, raw.frame_rate_hz) {
            (Some(v), _) | (None, Some(v)) if !(v.is_finite() && v > 0.0 && v <= MAX_FRAME_RATE_HZ) => {
                let name = if raw.fps.is_some() { "fps" } else { "frame_rate_hz" };
                return Err(field(
                    path,
                    name,
                    &format!("a frame rate above 0 and at most {MAX_FRAME_RATE_HZ} Hz"),
                    &v.to_string(),
                ));
            }
            (fps, rate) => fps.or(rate),
        };
        Ok(Self {
            path: path.to_owned(),
            grid,
            image_size,
            sensor,
            frame_rate_hz,
        })
    }

    /// Checks a lattice shape given on the command line against the recording's own grid: a
    /// different shape would index or track a part of the lattice, or fail later less clearly.
    pub fn check_grid(&self, given: GridShape) -> Result<()> {
        match self.grid {
            Some(own) if own != given => Err(field(
                &self.path,
                "grid",
                &format!("the grid given, {} x {} (--grid)", given.rows, given.cols),
                &format!("{} x {}: omit --grid to use the recording's", own.rows, own.cols),
            )),
            _ => Ok(()),
        }
    }
}

fn syntax(path: &Path, e: &serde_json::Error) -> Error {
    Error::SensorSyntax {
        path: path.to_owned(),
        message: e.to_string(),
    }
}

fn field(path: &Path, name: &str, expected: &str, found: &str) -> Error {
    Error::SensorField {
        source_name: path.display().to_string(),
        field: name.to_owned(),
        expected: expected.to_owned(),
        found: found.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn the_sample_recordings_meta_reads_and_garbage_is_named() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/sample/press-slide");
        let meta = RecordingMeta::read(&dir).unwrap().unwrap();
        assert_eq!(meta.grid, Some(GridShape { rows: 23, cols: 23 }));
        assert!(meta.sensor.is_some() && meta.image_size.is_some());
        let p = Path::new("rec/meta.json");
        let err = RecordingMeta::parse(p, "garbage").unwrap_err().to_string();
        assert!(err.contains("rec/meta.json"), "{err}");
        let err = RecordingMeta::parse(p, r#"{"grid": {"rows": "x", "cols": 3}}"#)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("rec/meta.json") && err.contains("invalid type"),
            "{err}"
        );
        let err = RecordingMeta::parse(p, r#"{"grid": {"rows": 1, "cols": 3}}"#)
            .unwrap_err()
            .to_string();
        assert!(err.contains("'grid'"), "{err}");
        for bad in [r#"{"fps": -5}"#, r#"{"frame_rate_hz": 0}"#, r#"{"fps": 1e300}"#] {
            let err = RecordingMeta::parse(p, bad).unwrap_err().to_string();
            assert!(
                err.contains("rec/meta.json") && err.contains("frame rate"),
                "{bad}: {err}"
            );
        }
        let err = RecordingMeta::parse(p, r#"{"fps": "fast"}"#)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("rec/meta.json") && err.contains("invalid type"),
            "{err}"
        );
        let meta = RecordingMeta::parse(p, r#"{"fps": 60}"#).unwrap();
        assert_eq!(meta.frame_rate_hz, Some(60.0));
        let meta = RecordingMeta::parse(p, r#"{"grid": {"rows": 23, "cols": 23}}"#).unwrap();
        let err = meta
            .check_grid(GridShape { rows: 10, cols: 10 })
            .unwrap_err()
            .to_string();
        assert!(err.contains("10 x 10") && err.contains("23 x 23"), "{err}");
        assert!(meta.check_grid(GridShape { rows: 23, cols: 23 }).is_ok());
    }

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
                if let Err(e) = RecordingMeta::parse(p, &text) {
                    prop_assert!(e.to_string().contains("x/meta.json"), "{}", e);
                }
                if let Err(e) = DatasetManifest::parse(p, &text) {
                    prop_assert!(e.to_string().contains("x/meta.json"), "{}", e);
                }
            }
        }

        /// The reference sensor description with bytes replaced, inserted or cut: a sensor or an
        /// error naming the file, never a panic.
        #[test]
        fn mutated_sensor_files_load_or_name_the_file(
            edits in proptest::collection::vec((any::<usize>(), any::<u8>(), 0u8..3), 1..6),
        ) {
            let reference = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../calib/reference-sensor.json");
            let mut bytes = std::fs::read(reference).unwrap();
            gelstereo_core::testing::mutate(&mut bytes, &edits);
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("sensor.json");
            std::fs::write(&path, &bytes).unwrap();
            if let Err(e) = SensorSpec::load(&path) {
                prop_assert!(e.to_string().contains("sensor.json"), "{}", e);
            }
        }
    }
}
