//! The gel's facts in a file. A gel file is JSON with a `gel` object (`thickness_mm`,
//! `modulus_kpa`, `poisson`) and an optional `friction`: what `gelstereo track` writes as
//! `OUT/gel.json` and `gelstereo calibrate-gel` writes (the modulus it finds:
//! `gelstereo_apps::calibrate_gel`), and what `--gel FILE` (and the Python `gel=`) reads.

use std::path::Path;

use gelstereo_core::limits::{ECHO_CHARS, shorten};
use gelstereo_mechanics::Layer;
use serde_json::Value;

use crate::error::{Error, Result};

/// The facts a gel file holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GelFile {
    /// Thickness, Young's modulus and Poisson ratio.
    pub layer: Layer,
    /// The friction coefficient, when the file gives one.
    pub friction: Option<f64>,
}

/// Largest gel file read, bytes (a gel file is a few hundred).
const MAX_GEL_FILE_BYTES: u64 = 1 << 20;

impl GelFile {
    /// The gel's facts of a sensor description (`gelstereo simulate --sensor`, `track --sensor`).
    pub fn of_sensor(sensor: &crate::sim::SensorSpec) -> Self {
        let gel = &sensor.gel;
        Self {
            layer: Layer {
                thickness_mm: gel.thickness_mm,
                modulus_kpa: gel.modulus_kpa,
                poisson: gel.poisson,
            },
            friction: Some(gel.friction),
        }
    }

    /// Reads and checks `path`; an error names the file, the field and what was expected.
    pub fn read(path: &Path) -> Result<Self> {
        let invalid = |what: String| Error::Invalid(format!("{}: {what}", path.display()));
        let size = std::fs::metadata(path)
            .map_err(|e| invalid(format!("cannot read: {e}")))?
            .len();
        if size > MAX_GEL_FILE_BYTES {
            return Err(invalid(format!(
                "expected a gel file of at most 1 MiB, found {size} bytes"
            )));
        }
        let text = std::fs::read_to_string(path).map_err(|e| invalid(format!("cannot read: {e}")))?;
        let v: Value = serde_json::from_str(&text).map_err(|e| invalid(format!("expected JSON: {e}")))?;
        let gel = v.get("gel").filter(|g| g.is_object()).ok_or_else(|| {
            invalid("expected an object `gel` with thickness_mm, modulus_kpa and poisson".into())
        })?;
        let number = |field: &str| {
            gel.get(field)
                .and_then(Value::as_f64)
                .ok_or_else(|| invalid(format!("gel.{field}: expected a number")))
        };
        let layer = Layer {
            thickness_mm: number("thickness_mm")?,
            modulus_kpa: number("modulus_kpa")?,
            poisson: number("poisson")?,
        };
        layer.validate().map_err(|e| invalid(format!("gel.{e}")))?;
        let friction = match v.get("friction") {
            None | Some(Value::Null) => None,
            Some(f) => Some(f.as_f64().filter(|f| f.is_finite() && *f > 0.0).ok_or_else(|| {
                let found = f.to_string();
                let found = shorten(&found, ECHO_CHARS);
                invalid(format!("friction: expected a positive number, found {found}"))
            })?),
        };
        Ok(Self { layer, friction })
    }

    /// The file's JSON (`extra` adds top-level fields, e.g. how a modulus was found).
    pub fn to_json(&self, extra: serde_json::Map<String, Value>) -> Value {
        let mut v = serde_json::json!({
            "gel": {
                "thickness_mm": self.layer.thickness_mm,
                "modulus_kpa": self.layer.modulus_kpa,
                "poisson": self.layer.poisson,
            },
        });
        if let (Some(f), Some(map)) = (self.friction, v.as_object_mut()) {
            map.insert("friction".into(), f.into());
        }
        if let Some(map) = v.as_object_mut() {
            map.extend(extra);
        }
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        /// A gel file with bytes replaced, inserted or cut: facts or an error naming the file,
        /// never a panic, and never a whole long value echoed back.
        #[test]
        fn mutated_gel_files_read_or_name_the_file(
            edits in proptest::collection::vec((any::<usize>(), any::<u8>(), 0u8..3), 1..6),
            long in proptest::option::of("[a-z]{200,400}"),
        ) {
            let good = GelFile {
                layer: Layer { thickness_mm: 1.5, modulus_kpa: 150.0, poisson: 0.49 },
                friction: Some(0.8),
            };
            let mut text = good.to_json(serde_json::Map::new()).to_string();
            if let Some(long) = &long {
                text = text.replace("0.8", &format!("\"{long}\""));
            }
            let mut bytes = text.into_bytes();
            gelstereo_core::testing::mutate(&mut bytes, &edits);
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("gel.json");
            std::fs::write(&path, &bytes).unwrap();
            if let Err(e) = GelFile::read(&path) {
                let message = e.to_string();
                prop_assert!(message.contains("gel.json"), "{}", message);
                prop_assert!(message.len() < 400, "{}", message);
            }
        }
    }

    #[test]
    fn a_gel_file_round_trips_and_bad_facts_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gel.json");
        let file = GelFile {
            layer: Layer {
                thickness_mm: 3.0,
                modulus_kpa: 210.0,
                poisson: 0.48,
            },
            friction: Some(0.8),
        };
        std::fs::write(&path, file.to_json(Default::default()).to_string()).unwrap();
        assert_eq!(GelFile::read(&path).unwrap(), file);
        for (text, field) in [
            (
                r#"{"gel": {"thickness_mm": 2, "modulus_kpa": -5, "poisson": 0.4}}"#,
                "modulus_kpa",
            ),
            (
                r#"{"gel": {"thickness_mm": 2, "modulus_kpa": 5, "poisson": 0.5}}"#,
                "poisson",
            ),
            (
                r#"{"gel": {"thickness_mm": 2, "poisson": 0.4}}"#,
                "gel.modulus_kpa",
            ),
            (
                r#"{"gel": {"thickness_mm": 2, "modulus_kpa": 5, "poisson": 0.4}, "friction": 0}"#,
                "friction",
            ),
            ("{}", "`gel`"),
            ("not json", "JSON"),
        ] {
            std::fs::write(&path, text).unwrap();
            let e = GelFile::read(&path).unwrap_err().to_string();
            assert!(e.contains(field) && e.contains("gel.json"), "{text}: {e}");
        }
    }
}
