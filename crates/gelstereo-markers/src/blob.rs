//! The paper's baseline: OpenCV's SimpleBlobDetector (the real one, through the `opencv` crate).
//!
//! Parameters come from a JSON file (`data/blob_params.json` holds the ones tuned for the reference
//! sensor, with the reasons; the Python trainer reads the same keys) or are OpenCV's own defaults
//! ([`BlobParams::opencv_defaults`]). Keys are OpenCV's `SimpleBlobDetector::Params` field names
//! (`minThreshold`; the snake-case spelling `min_threshold` is accepted too). A file may give any subset;
//! the rest keep OpenCV's defaults. Keys starting with `_` are comments; any other unknown key is an
//! error, so a typo cannot silently leave a default in place.

use std::path::Path;

use gelstereo_core::{Detection, Point2};
use opencv::core::{KeyPoint, Mat, MatTraitConst, Ptr, Vector};
use opencv::features2d::{SimpleBlobDetector, SimpleBlobDetector_Params};
use opencv::imgproc;
use opencv::prelude::{Feature2DTrait, KeyPointTraitConst};

use crate::{Error, Localizer, Result, check_image, cv_err};

/// The tuned parameter file of the reference sensor, relative to the project folder.
pub const DEFAULT_PARAMS_FILE: &str = "data/blob_params.json";

/// SimpleBlobDetector's parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlobParams {
    /// The raw OpenCV parameter block.
    pub params: SimpleBlobDetector_Params,
}

/// The JSON field names (OpenCV's), in OpenCV's order.
pub const BLOB_FIELDS: [&str; 19] = [
    "thresholdStep",
    "minThreshold",
    "maxThreshold",
    "minRepeatability",
    "minDistBetweenBlobs",
    "filterByColor",
    "blobColor",
    "filterByArea",
    "minArea",
    "maxArea",
    "filterByCircularity",
    "minCircularity",
    "maxCircularity",
    "filterByInertia",
    "minInertiaRatio",
    "maxInertiaRatio",
    "filterByConvexity",
    "minConvexity",
    "maxConvexity",
];

/// `minDistBetweenBlobs` -> `min_dist_between_blobs`; snake case stays as it is.
fn snake_case(key: &str) -> String {
    let mut out = String::with_capacity(key.len() + 4);
    for ch in key.chars() {
        if ch.is_ascii_uppercase() {
            out.push('_');
            out.push(ch.to_ascii_lowercase());
        } else {
            out.push(ch);
        }
    }
    out
}

impl BlobParams {
    /// The tuned parameters of the paper's baseline, as `data/blob_params.json` holds them (a test
    /// checks the two agree): thresholds 80..160 step 20, area 15..200 px^2, circularity >= 0.6,
    /// inertia >= 0.3, convexity off; the file explains each choice.
    pub fn tuned() -> Self {
        Self {
            params: SimpleBlobDetector_Params {
                threshold_step: 20.0,
                min_threshold: 80.0,
                max_threshold: 160.0,
                min_repeatability: 2,
                min_dist_between_blobs: 10.0,
                filter_by_color: true,
                blob_color: 0,
                filter_by_area: true,
                min_area: 15.0,
                max_area: 200.0,
                filter_by_circularity: true,
                min_circularity: 0.6,
                max_circularity: f32::MAX,
                filter_by_inertia: true,
                min_inertia_ratio: 0.3,
                max_inertia_ratio: f32::MAX,
                filter_by_convexity: false,
                min_convexity: 0.95,
                max_convexity: f32::MAX,
                #[cfg(opencv_blob_collect_contours)]
                collect_contours: false,
            },
        }
    }

    /// OpenCV's defaults (`SimpleBlobDetector::Params()`), as this OpenCV build defines them.
    pub fn opencv_defaults() -> Result<Self> {
        Ok(Self {
            params: SimpleBlobDetector_Params::default().map_err(cv_err("SimpleBlobDetector::Params()"))?,
        })
    }

    /// Reads a parameter file (see the module docs); `path` names it in errors.
    pub fn from_json_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_json(path, &text)
    }

    /// Parses parameter-file text; `path` names it in errors.
    pub fn from_json(path: &Path, text: &str) -> Result<Self> {
        let err = |field: &str, expected: &str, found: String| Error::Config {
            path: path.to_path_buf(),
            field: field.to_owned(),
            expected: expected.to_owned(),
            found,
        };
        let value: serde_json::Value =
            serde_json::from_str(text).map_err(|e| err("(file)", "a JSON object", e.to_string()))?;
        let serde_json::Value::Object(map) = value else {
            return Err(err("(file)", "a JSON object", "another JSON value".into()));
        };
        let mut p = Self::opencv_defaults()?.params;
        for (key, v) in &map {
            if key.starts_with('_') {
                continue;
            }
            let num = || -> Result<f32> {
                v.as_f64()
                    .filter(|x| x.is_finite() && *x >= 0.0)
                    .map(|x| x as f32)
                    .ok_or_else(|| err(key, "a non-negative number", v.to_string()))
            };
            let flag = || {
                v.as_bool()
                    .ok_or_else(|| err(key, "true or false", v.to_string()))
            };
            match snake_case(key).as_str() {
                "threshold_step" => p.threshold_step = num()?,
                "min_threshold" => p.min_threshold = num()?,
                "max_threshold" => p.max_threshold = num()?,
                "min_repeatability" => {
                    p.min_repeatability = v
                        .as_u64()
                        .filter(|n| *n >= 1)
                        .map(|n| n as usize)
                        .ok_or_else(|| err(key, "a positive integer", v.to_string()))?
                }
                "min_dist_between_blobs" => p.min_dist_between_blobs = num()?,
                "filter_by_color" => p.filter_by_color = flag()?,
                "blob_color" => {
                    p.blob_color = v
                        .as_u64()
                        .and_then(|n| u8::try_from(n).ok())
                        .ok_or_else(|| err(key, "0 (dark blobs) or 255 (bright blobs)", v.to_string()))?
                }
                "filter_by_area" => p.filter_by_area = flag()?,
                "min_area" => p.min_area = num()?,
                "max_area" => p.max_area = num()?,
                "filter_by_circularity" => p.filter_by_circularity = flag()?,
                "min_circularity" => p.min_circularity = num()?,
                "max_circularity" => p.max_circularity = num()?,
                "filter_by_inertia" => p.filter_by_inertia = flag()?,
                "min_inertia_ratio" => p.min_inertia_ratio = num()?,
                "max_inertia_ratio" => p.max_inertia_ratio = num()?,
                "filter_by_convexity" => p.filter_by_convexity = flag()?,
                "min_convexity" => p.min_convexity = num()?,
                "max_convexity" => p.max_convexity = num()?,
                _ => {
                    return Err(err(
                        key,
                        &format!("one of {} (or a key starting with _)", BLOB_FIELDS.join(", ")),
                        "an unknown key".into(),
                    ));
                }
            }
        }
        if p.threshold_step <= 0.0 {
            return Err(err(
                "thresholdStep",
                "a positive step",
                p.threshold_step.to_string(),
            ));
        }
        if p.min_threshold >= p.max_threshold {
            return Err(err(
                "maxThreshold",
                &format!("more than minThreshold ({})", p.min_threshold),
                p.max_threshold.to_string(),
            ));
        }
        for (field, lo, hi) in [
            ("maxArea", p.min_area, p.max_area),
            ("maxCircularity", p.min_circularity, p.max_circularity),
            ("maxInertiaRatio", p.min_inertia_ratio, p.max_inertia_ratio),
            ("maxConvexity", p.min_convexity, p.max_convexity),
        ] {
            if hi < lo {
                return Err(err(
                    field,
                    &format!("at least its minimum ({lo})"),
                    hi.to_string(),
                ));
            }
        }
        Ok(Self { params: p })
    }

    /// The parameters as a JSON object with every field (for reports and `--blob-params` round trips).
    pub fn to_json(&self) -> serde_json::Value {
        let p = &self.params;
        let f = |v: f32| {
            serde_json::json!(if v >= f32::MAX {
                f64::from(f32::MAX)
            } else {
                f64::from(v)
            })
        };
        serde_json::json!({
            "thresholdStep": f(p.threshold_step),
            "minThreshold": f(p.min_threshold),
            "maxThreshold": f(p.max_threshold),
            "minRepeatability": p.min_repeatability,
            "minDistBetweenBlobs": f(p.min_dist_between_blobs),
            "filterByColor": p.filter_by_color,
            "blobColor": p.blob_color,
            "filterByArea": p.filter_by_area,
            "minArea": f(p.min_area),
            "maxArea": f(p.max_area),
            "filterByCircularity": p.filter_by_circularity,
            "minCircularity": f(p.min_circularity),
            "maxCircularity": f(p.max_circularity),
            "filterByInertia": p.filter_by_inertia,
            "minInertiaRatio": f(p.min_inertia_ratio),
            "maxInertiaRatio": f(p.max_inertia_ratio),
            "filterByConvexity": p.filter_by_convexity,
            "minConvexity": f(p.min_convexity),
            "maxConvexity": f(p.max_convexity),
        })
    }
}

/// The blob baseline as a [`Localizer`]. Every detection has confidence 1.
pub struct BlobLocalizer {
    params: BlobParams,
    detector: Ptr<SimpleBlobDetector>,
    grey: Mat,
    keypoints: Vector<KeyPoint>,
}

impl std::fmt::Debug for BlobLocalizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlobLocalizer")
            .field("params", &self.params)
            .finish()
    }
}

impl BlobLocalizer {
    /// A detector with `params`.
    pub fn new(params: BlobParams) -> Result<Self> {
        let detector =
            SimpleBlobDetector::create(params.params).map_err(cv_err("SimpleBlobDetector::create"))?;
        Ok(Self {
            params,
            detector,
            grey: Mat::default(),
            keypoints: Vector::new(),
        })
    }

    /// The parameters in use.
    pub fn params(&self) -> &BlobParams {
        &self.params
    }
}

impl Localizer for BlobLocalizer {
    fn name(&self) -> &str {
        "blob"
    }

    fn fork(&self, _intra_threads: usize) -> Option<Result<Box<dyn Localizer + Send>>> {
        Some(BlobLocalizer::new(self.params).map(|b| Box::new(b) as Box<dyn Localizer + Send>))
    }

    fn detect(&mut self, image: &Mat) -> Result<Vec<Detection>> {
        check_image(image)?;
        let grey: &Mat = match image.channels() {
            1 => image,
            n => {
                let code = if n == 4 {
                    imgproc::COLOR_BGRA2GRAY
                } else {
                    imgproc::COLOR_BGR2GRAY
                };
                imgproc::cvt_color(image, &mut self.grey, code, 0).map_err(cv_err("cvtColor to grey"))?;
                &self.grey
            }
        };
        self.keypoints.clear();
        self.detector
            .detect(grey, &mut self.keypoints, &opencv::core::no_array())
            .map_err(cv_err("SimpleBlobDetector::detect"))?;
        let mut out: Vec<Detection> = self
            .keypoints
            .iter()
            .map(|k| {
                let p = k.pt();
                Detection {
                    position: Point2::new(f64::from(p.x), f64::from(p.y)),
                    confidence: 1.0,
                }
            })
            .collect();
        crate::sort_detections(&mut out);
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_8UC3, Point, Scalar};

    #[test]
    fn tuned_parameters_are_those_of_the_shipped_file() {
        let path = crate::project_home().join(DEFAULT_PARAMS_FILE);
        assert_eq!(BlobParams::tuned(), BlobParams::from_json_file(&path).unwrap());
    }

    #[test]
    fn parameter_files_override_defaults_and_reject_mistakes() {
        let p = BlobParams::from_json(
            Path::new("b.json"),
            r#"{"_why": "test", "minThreshold": 80, "max_threshold": 160, "filterByConvexity": false}"#,
        )
        .unwrap();
        let d = BlobParams::opencv_defaults().unwrap();
        assert_eq!((p.params.min_threshold, p.params.max_threshold), (80.0, 160.0));
        assert!(!p.params.filter_by_convexity);
        assert_eq!(
            p.params.min_area, d.params.min_area,
            "unset fields keep OpenCV's defaults"
        );
        for (text, field) in [
            (r#"{"minTreshold": 80}"#, "'minTreshold'"),
            (r#"{"minArea": "big"}"#, "'minArea'"),
            (r#"{"minThreshold": 200, "maxThreshold": 100}"#, "'maxThreshold'"),
            (r#"{"blobColor": 300}"#, "'blobColor'"),
            (r#"[1, 2]"#, "'(file)'"),
        ] {
            let err = BlobParams::from_json(Path::new("b.json"), text)
                .unwrap_err()
                .to_string();
            assert!(err.contains(field) && err.contains("b.json"), "{text}: {err}");
        }
        let round = BlobParams::from_json(Path::new("r.json"), &p.to_json().to_string()).unwrap();
        assert_eq!(round, p);
    }

    /// The shipped parameter file parses, and the trainer's copy (if present) holds the same values.
    #[test]
    fn shipped_parameter_files_agree() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let shipped = BlobParams::from_json_file(&root.join(crate::blob::DEFAULT_PARAMS_FILE)).unwrap();
        assert_eq!(
            (shipped.params.min_threshold, shipped.params.max_area),
            (80.0, 200.0)
        );
        let any = BlobParams::from_json_file(&root.join("data/blob_params_any_polarity.json")).unwrap();
        assert!(!any.params.filter_by_color && shipped.params.filter_by_color);
        let same_otherwise = BlobParams {
            params: SimpleBlobDetector_Params {
                filter_by_color: true,
                ..any.params
            },
        };
        assert_eq!(
            same_otherwise, shipped,
            "the any-polarity file differs only in filterByColor"
        );
        let train = root.join("train/gelstereo_train/blob_params.json");
        if train.exists() {
            assert_eq!(
                BlobParams::from_json_file(&train).unwrap(),
                shipped,
                "{} differs",
                train.display()
            );
        }
    }

    /// Dark discs of radius 5 on a bright background, centres known: the detector finds each within
    /// 0.5 px (disc rasterisation is symmetric about integer centres).
    #[test]
    fn finds_drawn_discs_at_their_centres() {
        let mut img = Mat::new_rows_cols_with_default(120, 160, CV_8UC3, Scalar::all(220.0)).unwrap();
        let centres = [(30, 30), (80, 30), (130, 30), (30, 90), (80, 90), (130, 90)];
        for (x, y) in centres {
            imgproc::circle(
                &mut img,
                Point::new(x, y),
                5,
                Scalar::all(40.0),
                -1,
                imgproc::LINE_8,
                0,
            )
            .unwrap();
        }
        let params = BlobParams::from_json(
            Path::new("t"),
            r#"{"minThreshold": 80, "maxThreshold": 160, "thresholdStep": 20, "minArea": 15, "maxArea": 200,
                "filterByCircularity": true, "minCircularity": 0.6, "minInertiaRatio": 0.3, "filterByConvexity": false}"#,
        )
        .unwrap();
        let mut blob = BlobLocalizer::new(params).unwrap();
        let found = blob.detect(&img).unwrap();
        assert_eq!(found.len(), centres.len(), "{found:?}");
        for (x, y) in centres {
            let near = found
                .iter()
                .any(|d| d.position.distance(Point2::new(f64::from(x), f64::from(y))) < 0.5);
            assert!(near, "({x}, {y}) not found in {found:?}");
        }
        assert!(blob.detect(&Mat::default()).is_err());
    }
}
