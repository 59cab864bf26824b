//! The model contract of `docs/model-contract.md`: what `marknet.onnx` and `mre.onnx` must declare in
//! their `metadata_props` and in their input/output signatures. Parsing works on plain maps and
//! [`TensorSpec`]s, so it is tested without ONNX Runtime; [`crate::marknet`] feeds it from a session.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::postprocess::{MISSING_DISTANCE_PITCH, MRE_FEATURES, MRE_NEIGHBOURS, PostProcess};
use crate::{Error, Result};

/// The `contract` value of a Marknet model with a dynamic input size (what the trainer writes).
pub const MARKNET_CONTRACT: &str = "gelstereo-marknet/2";
/// The `contract` value of a fixed-input Marknet model (the first version; still loaded).
pub const MARKNET_CONTRACT_FIXED: &str = "gelstereo-marknet/1";
/// The `contract` value of an MRE model this loader understands.
pub const MRE_CONTRACT: &str = "gelstereo-mre/1";
/// Marknet's input name.
pub const MARKNET_INPUT: &str = "image";
/// Marknet's output name.
pub const MARKNET_OUTPUT: &str = "raw";
/// MRE's input name.
pub const MRE_INPUT: &str = "features";
/// MRE's output name.
pub const MRE_OUTPUT: &str = "score";

/// One input or output of a model: its name, whether it is float32, and its dimensions (-1 = dynamic).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorSpec {
    /// Input or output name.
    pub name: String,
    /// Whether the element type is float32.
    pub float32: bool,
    /// Dimensions; -1 (or any negative value) for a dynamic one.
    pub dims: Vec<i64>,
}

/// What a Marknet model declares (`metadata_props` checked against its signature).
#[derive(Debug, Clone, PartialEq)]
pub struct MarknetContract {
    /// Network input width, px.
    pub input_width: u32,
    /// Network input height, px.
    pub input_height: u32,
    /// Input pixels per grid cell.
    pub stride: u32,
    /// Grid cells along x (`grid`, S).
    pub grid_x: u32,
    /// Grid cells along y (input_height / stride).
    pub grid_y: u32,
    /// Candidate points per cell (m).
    pub candidates: u32,
    /// Post-processing defaults (metadata values where present, else the paper's).
    pub postprocess: PostProcess,
    /// The training data the model was fitted on (simulator version, seed, image count).
    pub dataset: String,
    /// When the model was trained (ISO date).
    pub trained: String,
    /// The "auto" fit of a dynamic-input model (`gelstereo-marknet/2`); `None` for a fixed input, whose
    /// width and height are `input_width` x `input_height` (then they are also nominal sizes).
    pub auto_fit: Option<AutoFit>,
}

/// How a dynamic-input model wants images scaled (`docs/model-contract.md`, "auto" fit): isotropically,
/// the image plus one marker pitch of margin fitted into the nominal `input_width x input_height`, unless
/// that puts the pitch outside `pitch_min_px..=pitch_max_px` at the input; then scaled to
/// `pitch_target_px`. The input is the smallest multiple of `multiple` px around the scaled image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutoFit {
    /// Input width and height are multiples of this (the network's largest stride).
    pub multiple: u32,
    /// Smallest marker pitch at the input the network is trained for, px.
    pub pitch_min_px: f64,
    /// Largest marker pitch at the input kept without rescaling, px.
    pub pitch_max_px: f64,
    /// Pitch at the input when the nominal fit is out of range, px.
    pub pitch_target_px: f64,
    /// The layout the network was trained on (`preferred_layout` = `stretch`): the whole-image stretch to
    /// the nominal input is kept whenever it puts the pitch within range along both axes. Otherwise
    /// (`isotropic`, the default) the isotropic fit above.
    pub prefer_stretch: bool,
}

/// What an MRE model declares.
#[derive(Debug, Clone, PartialEq)]
pub struct MreContract {
    /// Acceptance threshold on the score (the paper's 0.99).
    pub accept: f32,
    /// Lower confidence bound of the candidates MRE scores (0.1).
    pub conf_low: f32,
    /// Upper confidence bound (0.4): candidates above pass without MRE.
    pub conf_keep: f32,
    /// The training data the model was fitted on.
    pub dataset: String,
}

struct Meta<'a> {
    path: &'a Path,
    map: &'a BTreeMap<String, String>,
}

impl Meta<'_> {
    fn err(&self, key: &str, expected: impl Into<String>, found: impl Into<String>) -> Error {
        Error::Contract {
            path: self.path.to_path_buf(),
            key: key.to_owned(),
            expected: expected.into(),
            found: found.into(),
        }
    }

    fn required(&self, key: &str, expected: &str) -> Result<&str> {
        self.map
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| self.err(key, expected, "no such metadata key"))
    }

    fn exact(&self, key: &str, value: &str) -> Result<()> {
        let found = self.required(key, &format!("'{value}'"))?;
        if found.trim() == value {
            Ok(())
        } else {
            Err(self.err(key, format!("'{value}'"), format!("'{found}'")))
        }
    }

    fn positive(&self, key: &str) -> Result<u32> {
        let expected = "a positive integer";
        let found = self.required(key, expected)?;
        match found.trim().parse::<u32>() {
            Ok(v) if v > 0 => Ok(v),
            _ => Err(self.err(key, expected, format!("'{found}'"))),
        }
    }

    fn fraction(&self, key: &str, default: f64) -> Result<f64> {
        let Some(found) = self.map.get(key) else {
            return Ok(default);
        };
        match found.trim().parse::<f64>() {
            Ok(v) if v > 0.0 && v < 1.0 => Ok(v),
            _ => Err(self.err(key, "a number strictly between 0 and 1", format!("'{found}'"))),
        }
    }

    fn number(&self, key: &str) -> Result<f64> {
        let expected = "a positive number";
        let found = self.required(key, expected)?;
        match found.trim().parse::<f64>() {
            Ok(v) if v > 0.0 && v.is_finite() => Ok(v),
            _ => Err(self.err(key, expected, format!("'{found}'"))),
        }
    }

    /// `"lo,hi"` with 0 < lo < hi.
    fn range(&self, key: &str) -> Result<(f64, f64)> {
        let expected = "'lo,hi' with 0 < lo < hi";
        let found = self.required(key, expected)?;
        let parsed: Vec<Option<f64>> = found.split(',').map(|v| v.trim().parse::<f64>().ok()).collect();
        match parsed.as_slice() {
            [Some(lo), Some(hi)] if *lo > 0.0 && lo < hi && hi.is_finite() => Ok((*lo, *hi)),
            _ => Err(self.err(key, expected, format!("'{found}'"))),
        }
    }

    fn text(&self, key: &str) -> Result<String> {
        Ok(self.required(key, "a non-empty description")?.to_owned())
    }
}

pub(crate) fn dims_text(dims: &[i64]) -> String {
    let parts: Vec<String> = dims
        .iter()
        .map(|d| if *d < 0 { "N".to_owned() } else { d.to_string() })
        .collect();
    format!("[{}]", parts.join(", "))
}

/// Checks that `specs` is exactly one tensor named `name`, float32, whose dims match `expected`
/// (`None` = any size, dynamic included; `Some(n)` = n, or dynamic).
pub(crate) fn check_signature(
    path: &Path,
    role: &str,
    specs: &[TensorSpec],
    name: &str,
    expected: &[Option<i64>],
) -> Result<()> {
    let exp_text = format!(
        "one float32 {role} '{name}' of shape [{}]",
        expected
            .iter()
            .map(|d| d.map_or("N".to_owned(), |v| v.to_string()))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let err = |found: String| Error::Contract {
        path: path.to_path_buf(),
        key: name.to_owned(),
        expected: exp_text.clone(),
        found,
    };
    let [spec] = specs else {
        let names: Vec<&str> = specs.iter().map(|s| s.name.as_str()).collect();
        return Err(err(format!("{} {role}s ({})", specs.len(), names.join(", "))));
    };
    if spec.name != name {
        return Err(err(format!("{role} '{}'", spec.name)));
    }
    let shape_ok = spec.dims.len() == expected.len()
        && spec
            .dims
            .iter()
            .zip(expected)
            .all(|(d, e)| *d < 0 || e.is_none_or(|e| e == *d));
    if !spec.float32 || !shape_ok {
        return Err(err(format!(
            "{} of shape {}",
            if spec.float32 {
                "float32"
            } else {
                "a non-float32 tensor"
            },
            dims_text(&spec.dims)
        )));
    }
    Ok(())
}

impl MarknetContract {
    /// Reads and checks the contract of the Marknet model at `path` from its metadata and signature.
    pub fn from_model(
        path: &Path,
        metadata: &BTreeMap<String, String>,
        inputs: &[TensorSpec],
        outputs: &[TensorSpec],
    ) -> Result<Self> {
        let m = Meta { path, map: metadata };
        let dynamic = match metadata.get("contract").map(|c| c.trim()) {
            Some(MARKNET_CONTRACT) => true,
            Some(MARKNET_CONTRACT_FIXED) => false,
            other => {
                return Err(m.err(
                    "contract",
                    format!("'{MARKNET_CONTRACT}' or '{MARKNET_CONTRACT_FIXED}'"),
                    other.map_or("no such metadata key".to_owned(), |c| format!("'{c}'")),
                ));
            }
        };
        let input_height = m.positive("input_height")?;
        let input_width = m.positive("input_width")?;
        let stride = m.positive("stride")?;
        for (key, v) in [("input_width", input_width), ("input_height", input_height)] {
            if v % stride != 0 {
                return Err(m.err(key, format!("a multiple of stride {stride}"), v.to_string()));
            }
        }
        let grid_x = m.positive("grid")?;
        if grid_x != input_width / stride {
            return Err(m.err(
                "grid",
                format!("input_width / stride = {}", input_width / stride),
                grid_x.to_string(),
            ));
        }
        let grid_y = input_height / stride;
        let candidates = m.positive("candidates")?;
        m.exact("normalisation", "rgb/255")?;
        m.exact("layout", "NCHW")?;
        let dataset = m.text("dataset")?;
        let trained = m.text("trained")?;
        let d = PostProcess::default();
        let postprocess = PostProcess {
            conf_keep: m.fraction("conf_keep", f64::from(d.conf_keep))? as f32,
            conf_low: m.fraction("conf_low", f64::from(d.conf_low))? as f32,
            conf_marknet_only: m.fraction("conf_marknet_only", f64::from(d.conf_marknet_only))? as f32,
            dedup_radius_frac: m.fraction("dedup_radius_frac", d.dedup_radius_frac)?,
            accept: d.accept,
            lattice: d.lattice,
        };
        if postprocess.conf_low >= postprocess.conf_keep {
            return Err(m.err(
                "conf_low",
                format!("less than conf_keep ({})", postprocess.conf_keep),
                postprocess.conf_low.to_string(),
            ));
        }
        let auto_fit = if dynamic {
            m.exact("input_size", "dynamic")?;
            let multiple = m.positive("input_multiple")?;
            if multiple % stride != 0 {
                return Err(m.err(
                    "input_multiple",
                    format!("a multiple of stride {stride}"),
                    multiple.to_string(),
                ));
            }
            let (pitch_min_px, pitch_max_px) = m.range("pitch_range_px")?;
            let pitch_target_px = m.number("pitch_target_px")?;
            if !(pitch_min_px..=pitch_max_px).contains(&pitch_target_px) {
                return Err(m.err(
                    "pitch_target_px",
                    format!("within pitch_range_px {pitch_min_px}..{pitch_max_px}"),
                    pitch_target_px.to_string(),
                ));
            }
            let prefer_stretch = match metadata.get("preferred_layout").map(|v| v.trim()) {
                None | Some("isotropic") => false,
                Some("stretch") => true,
                Some(other) => {
                    return Err(m.err(
                        "preferred_layout",
                        "'stretch' or 'isotropic'",
                        format!("'{other}'"),
                    ));
                }
            };
            Some(AutoFit {
                multiple,
                pitch_min_px,
                pitch_max_px,
                pitch_target_px,
                prefer_stretch,
            })
        } else {
            None
        };
        // A dynamic model's height, width and grid may be anything; a fixed one's are declared.
        let fixed = |v: u32| (!dynamic).then_some(i64::from(v));
        check_signature(
            path,
            "input",
            inputs,
            MARKNET_INPUT,
            &[None, Some(3), fixed(input_height), fixed(input_width)],
        )?;
        check_signature(
            path,
            "output",
            outputs,
            MARKNET_OUTPUT,
            &[
                None,
                fixed(grid_y),
                fixed(grid_x),
                Some(i64::from(candidates)),
                Some(3),
            ],
        )?;
        Ok(Self {
            input_width,
            input_height,
            stride,
            grid_x,
            grid_y,
            candidates,
            postprocess,
            dataset,
            trained,
            auto_fit,
        })
    }
}

impl MreContract {
    /// Reads and checks the contract of the MRE model at `path` from its metadata and signature.
    pub fn from_model(
        path: &Path,
        metadata: &BTreeMap<String, String>,
        inputs: &[TensorSpec],
        outputs: &[TensorSpec],
    ) -> Result<Self> {
        let m = Meta { path, map: metadata };
        m.exact("contract", MRE_CONTRACT)?;
        m.exact("features", &MRE_FEATURES.to_string())?;
        m.exact("neighbours", &MRE_NEIGHBOURS.to_string())?;
        m.exact("distance_unit", "pitch")?;
        if let Some(found) = m.map.get("missing_distance") {
            let v: Option<f32> = found.trim().parse().ok();
            if v != Some(MISSING_DISTANCE_PITCH) {
                let expected = MISSING_DISTANCE_PITCH.to_string();
                return Err(m.err("missing_distance", expected, format!("'{found}'")));
            }
        }
        let d = PostProcess::default();
        let accept = m.fraction("accept", f64::from(d.accept))? as f32;
        for key in ["conf_low", "conf_keep"] {
            m.required(key, "a number strictly between 0 and 1")?;
        }
        let conf_low = m.fraction("conf_low", 0.0)? as f32;
        let conf_keep = m.fraction("conf_keep", 0.0)? as f32;
        let dataset = m.text("dataset")?;
        check_signature(
            path,
            "input",
            inputs,
            MRE_INPUT,
            &[None, Some(MRE_FEATURES as i64)],
        )?;
        check_signature(path, "output", outputs, MRE_OUTPUT, &[None, Some(1)])?;
        Ok(Self {
            accept,
            conf_low,
            conf_keep,
            dataset,
        })
    }

    /// Checks that this MRE was trained on the confidence band Marknet's post-processing will give it.
    pub fn check_compatible(&self, mre_path: &Path, post: &PostProcess) -> Result<()> {
        for (key, mine, theirs) in [
            ("conf_low", self.conf_low, post.conf_low),
            ("conf_keep", self.conf_keep, post.conf_keep),
        ] {
            if (mine - theirs).abs() > 1e-6 {
                return Err(Error::Contract {
                    path: PathBuf::from(mre_path),
                    key: key.to_owned(),
                    expected: format!("the Marknet model's {key} = {theirs}"),
                    found: mine.to_string(),
                });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn marknet_meta() -> BTreeMap<String, String> {
        [
            ("contract", MARKNET_CONTRACT_FIXED),
            ("input_height", "416"),
            ("input_width", "416"),
            ("stride", "8"),
            ("grid", "52"),
            ("candidates", "5"),
            ("normalisation", "rgb/255"),
            ("layout", "NCHW"),
            ("dataset", "gelstereo-sim/1 seed 1 n 100"),
            ("trained", "2026-11-22"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v.to_owned()))
        .collect()
    }

    fn spec(name: &str, dims: &[i64]) -> Vec<TensorSpec> {
        vec![TensorSpec {
            name: name.into(),
            float32: true,
            dims: dims.to_vec(),
        }]
    }

    fn parse(
        meta: &BTreeMap<String, String>,
        inp: &[TensorSpec],
        out: &[TensorSpec],
    ) -> Result<MarknetContract> {
        MarknetContract::from_model(Path::new("m.onnx"), meta, inp, out)
    }

    /// The error `parse` reports for `meta` with `key` set to `value` (removed for `None`).
    fn error_with(
        mut meta: BTreeMap<String, String>,
        key: &str,
        value: Option<&str>,
        inp: &[TensorSpec],
        out: &[TensorSpec],
    ) -> String {
        match value {
            Some(v) => meta.insert(key.to_owned(), v.to_owned()),
            None => meta.remove(key),
        };
        parse(&meta, inp, out).unwrap_err().to_string()
    }

    #[test]
    fn a_conforming_marknet_is_accepted_with_default_thresholds() {
        let c = parse(
            &marknet_meta(),
            &spec("image", &[-1, 3, 416, 416]),
            &spec("raw", &[-1, 52, 52, 5, 3]),
        )
        .unwrap();
        assert_eq!((c.grid_x, c.grid_y, c.candidates, c.stride), (52, 52, 5, 8));
        assert_eq!(c.postprocess, PostProcess::default());
    }

    fn dynamic_meta() -> BTreeMap<String, String> {
        let mut meta = marknet_meta();
        for (k, v) in [
            ("contract", MARKNET_CONTRACT),
            ("input_size", "dynamic"),
            ("input_multiple", "32"),
            ("pitch_range_px", "9,24"),
            ("pitch_target_px", "12"),
        ] {
            meta.insert(k.to_owned(), v.to_owned());
        }
        meta
    }

    #[test]
    fn a_dynamic_marknet_declares_its_auto_fit() {
        let (inp, out) = (spec("image", &[-1, 3, -1, -1]), spec("raw", &[-1, -1, -1, 5, 3]));
        let c = parse(&dynamic_meta(), &inp, &out).unwrap();
        let fit = c.auto_fit.unwrap();
        assert_eq!(fit.multiple, 32);
        assert_eq!(
            (fit.pitch_min_px, fit.pitch_max_px, fit.pitch_target_px),
            (9.0, 24.0, 12.0)
        );
        assert!(!fit.prefer_stretch);
        let mut meta = dynamic_meta();
        meta.insert("preferred_layout".into(), "stretch".into());
        assert!(parse(&meta, &inp, &out).unwrap().auto_fit.unwrap().prefer_stretch);
        // The fixed contract has none.
        let c = parse(
            &marknet_meta(),
            &spec("image", &[-1, 3, 416, 416]),
            &spec("raw", &[-1, 52, 52, 5, 3]),
        )
        .unwrap();
        assert!(c.auto_fit.is_none());
        let cases: Vec<(&str, Option<&str>, &str)> = vec![
            ("input_size", Some("fixed"), "'input_size'"),
            ("input_multiple", None, "'input_multiple'"),
            ("input_multiple", Some("12"), "'input_multiple'"),
            ("pitch_range_px", Some("24,9"), "'pitch_range_px'"),
            ("pitch_range_px", Some("9"), "'pitch_range_px'"),
            ("pitch_target_px", Some("30"), "'pitch_target_px'"),
            ("pitch_target_px", Some("-1"), "'pitch_target_px'"),
            ("preferred_layout", Some("squash"), "'preferred_layout'"),
        ];
        for (key, value, needle) in cases {
            let err = error_with(dynamic_meta(), key, value, &inp, &out);
            assert!(err.contains(needle), "{key}={value:?}: {err}");
        }
    }

    /// Table of broken contracts: each must be reported by the key at fault.
    #[test]
    fn each_contract_violation_is_named() {
        let good_in = spec("image", &[-1, 3, 416, 416]);
        let good_out = spec("raw", &[-1, 52, 52, 5, 3]);
        let cases: Vec<(&str, Option<&str>, &str)> = vec![
            ("contract", Some("gelstereo-marknet/0"), "'contract'"),
            ("contract", None, "'contract'"),
            ("stride", Some("0"), "'stride'"),
            ("stride", Some("eight"), "'stride'"),
            ("grid", Some("26"), "'grid'"),
            ("input_width", Some("420"), "'input_width'"),
            ("normalisation", Some("imagenet"), "'normalisation'"),
            ("layout", Some("NHWC"), "'layout'"),
            ("candidates", None, "'candidates'"),
            ("conf_keep", Some("1.5"), "'conf_keep'"),
            ("conf_low", Some("0.6"), "'conf_low'"),
            ("dataset", None, "'dataset'"),
        ];
        for (key, value, needle) in cases {
            let err = error_with(marknet_meta(), key, value, &good_in, &good_out);
            assert!(
                err.contains(needle) && err.contains("m.onnx"),
                "{key}={value:?}: {err}"
            );
        }
        let err = parse(&marknet_meta(), &spec("input", &[-1, 3, 416, 416]), &good_out)
            .unwrap_err()
            .to_string();
        assert!(err.contains("'image'") && err.contains("input 'input'"), "{err}");
        let err = parse(&marknet_meta(), &spec("image", &[1, 3, 320, 320]), &good_out)
            .unwrap_err()
            .to_string();
        assert!(err.contains("[1, 3, 320, 320]"), "{err}");
        let err = parse(&marknet_meta(), &good_in, &spec("raw", &[-1, 52, 52, 3, 3]))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("'raw'") && err.contains("[N, 52, 52, 5, 3]"),
            "{err}"
        );
    }

    #[test]
    fn mre_contract_and_band_compatibility() {
        let meta: BTreeMap<String, String> = [
            ("contract", MRE_CONTRACT),
            ("features", "11"),
            ("neighbours", "10"),
            ("distance_unit", "pitch"),
            ("accept", "0.99"),
            ("conf_low", "0.1"),
            ("conf_keep", "0.4"),
            ("dataset", "x"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v.to_owned()))
        .collect();
        let p = Path::new("mre.onnx");
        let c = MreContract::from_model(p, &meta, &spec("features", &[-1, 11]), &spec("score", &[-1, 1]))
            .unwrap();
        assert!((c.accept - 0.99).abs() < 1e-7);
        c.check_compatible(p, &PostProcess::default()).unwrap();
        let other = PostProcess {
            conf_keep: 0.5,
            ..PostProcess::default()
        };
        assert!(
            c.check_compatible(p, &other)
                .unwrap_err()
                .to_string()
                .contains("'conf_keep'")
        );
        let mut bad = meta.clone();
        bad.insert("distance_unit".into(), "px".into());
        let err = MreContract::from_model(p, &bad, &spec("features", &[-1, 11]), &spec("score", &[-1, 1]));
        assert!(err.unwrap_err().to_string().contains("'distance_unit'"));
        let err = MreContract::from_model(p, &meta, &spec("features", &[-1, 12]), &spec("score", &[-1, 1]));
        assert!(err.unwrap_err().to_string().contains("'features'"));
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        /// A metadata value: a number-like word, a list of them, or any short text.
        fn value() -> impl Strategy<Value = String> {
            prop_oneof![
                any::<i64>().prop_map(|v| v.to_string()),
                any::<f64>().prop_map(|v| v.to_string()),
                proptest::collection::vec(any::<f64>(), 0..4).prop_map(|v| format!("{v:?}")),
                ".{0,12}",
            ]
        }

        fn dims() -> impl Strategy<Value = Vec<i64>> {
            proptest::collection::vec(prop_oneof![Just(-1i64), 0i64..600, any::<i64>()], 0..6)
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(256))]

            /// Metadata with random values under the real keys (and random extra keys), and random
            /// tensor shapes: a contract or an error naming the model file, never a panic.
            #[test]
            fn contract_parsing_never_panics(
                changes in proptest::collection::vec(
                    (prop_oneof![
                        Just("contract".to_owned()), Just("input_height".to_owned()),
                        Just("input_width".to_owned()), Just("stride".to_owned()),
                        Just("grid".to_owned()), Just("candidates".to_owned()),
                        Just("conf_keep".to_owned()), Just("conf_low".to_owned()),
                        Just("input_size".to_owned()), Just("input_multiple".to_owned()),
                        Just("pitch_range_px".to_owned()), Just("features".to_owned()),
                        Just("neighbours".to_owned()), Just("missing_distance".to_owned()),
                        "[a-z_]{1,10}",
                    ], proptest::option::of(value())),
                    0..6,
                ),
                input in dims(),
                output in dims(),
            ) {
                let mut meta = marknet_meta();
                for (key, v) in changes {
                    match v {
                        Some(v) => meta.insert(key, v),
                        None => meta.remove(&key),
                    };
                }
                let p = Path::new("m.onnx");
                if let Err(e) = MarknetContract::from_model(p, &meta, &spec("image", &input), &spec("out", &output)) {
                    prop_assert!(e.to_string().contains("m.onnx"), "{}", e);
                }
                if let Err(e) = MreContract::from_model(p, &meta, &spec("features", &input), &spec("score", &output)) {
                    prop_assert!(e.to_string().contains("m.onnx"), "{}", e);
                }
            }
        }
    }
}
