//! The gel's facts in a file, and its modulus found from presses of known force.
//!
//! A gel file is JSON with a `gel` object (`thickness_mm`, `modulus_kpa`, `poisson`) and an
//! optional `friction`: what `gelstereo track` writes as `OUT/gel.json` and `gelstereo
//! calibrate-gel` writes, and what `--gel FILE` (and the Python `gel=`) reads.
//!
//! **Finding the modulus.** With the thickness and Poisson ratio fixed, the layer is linear: the
//! tractions that explain given displacements scale with Young's modulus, and so does every force
//! the pipeline reports. Tracking a press of known force with an assumed modulus `E0` and getting
//! forces `F̂` where the truth is `F`, the modulus is `E = E0 · Σ F F̂ / Σ F̂²` (least squares over
//! the frames in contact).

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

/// A modulus fitted to presses of known force.
#[derive(Debug, Clone, PartialEq)]
pub struct ModulusFit {
    /// The fitted Young's modulus, kPa.
    pub modulus_kpa: f64,
    /// The frames used (in contact, with a known force).
    pub frames: usize,
    /// The per-frame moduli `E0 F / F̂`: their quartiles, kPa (how well one modulus explains all).
    pub quartiles_kpa: [f64; 3],
}

/// Fits the modulus from `(known force, estimated force)` pairs, N, estimated with the modulus
/// `assumed_kpa`; pairs whose estimate or truth is not positive are skipped.
pub fn fit_modulus(assumed_kpa: f64, pairs: &[(f64, f64)]) -> Result<ModulusFit> {
    let used: Vec<(f64, f64)> = pairs
        .iter()
        .copied()
        .filter(|(f, e)| f.is_finite() && e.is_finite() && *f > 0.0 && *e > 0.0)
        .collect();
    if used.is_empty() {
        return Err(Error::Invalid(
            "no frame in contact with a known force: expected a press the pipeline sees as contact, and a positive force"
                .into(),
        ));
    }
    let (num, den) = used
        .iter()
        .fold((0.0, 0.0), |(n, d), (f, e)| (n + f * e, d + e * e));
    let mut per_frame: Vec<f64> = used.iter().map(|(f, e)| assumed_kpa * f / e).collect();
    per_frame.sort_by(f64::total_cmp);
    let at = |q: f64| per_frame[((per_frame.len() - 1) as f64 * q).round() as usize];
    Ok(ModulusFit {
        modulus_kpa: assumed_kpa * num / den,
        frames: used.len(),
        quartiles_kpa: [at(0.25), at(0.5), at(0.75)],
    })
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
    fn the_modulus_scales_the_force() {
        // Forces estimated with 100 kPa where the gel is 150 kPa come out 1.5 x too small.
        let pairs = [(0.3, 0.2), (0.6, 0.4), (0.9, 0.6), (0.0, 0.0), (0.5, 0.0)];
        let fit = fit_modulus(100.0, &pairs).unwrap();
        assert!(
            (fit.modulus_kpa - 150.0).abs() < 1e-9 && fit.frames == 3,
            "{fit:?}"
        );
        assert!(
            fit_modulus(100.0, &[(0.0, 0.1)])
                .unwrap_err()
                .to_string()
                .contains("no frame")
        );
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
