//! What a recording's `meta.json` states about its sensor: the lattice, the image size, the sensor
//! description and the frame rate. The one parser of that file: the simulator writes it, the pipeline,
//! the evaluation and the reconstruction read it here. A file that is present but malformed is an
//! error naming the file and the field, never a silent fallback to the reference sensor.

use std::path::{Path, PathBuf};

use gelstereo_core::limits::{MAX_DESCRIPTION_BYTES, MAX_GRID_SIDE, read_text_at_most};
use gelstereo_core::{GridShape, ImageSize};
use serde::Deserialize;

use crate::error::{Error, Result, field, syntax};
use crate::spec::SensorSpec;

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

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        /// Any text gives a value or an error naming the file: never a panic.
        #[test]
        fn the_meta_parser_never_panics(text in ".{0,64}", bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let p = Path::new("x/meta.json");
            for text in [text, String::from_utf8_lossy(&bytes).into_owned()] {
                if let Err(e) = RecordingMeta::parse(p, &text) {
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
