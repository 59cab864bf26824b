//! A reconstruction compared with the ground truth of a simulated recording (docs/design.md
//! "Metrics", 3-D): the figures as JSON (`evaluation.json`) and as one line per group of markers.

use std::fmt::Write as _;

use gelstereo_core::StereoPair;
use gelstereo_matching::eval::{Counts, Evaluation};
use serde_json::{Value, json};

/// The evaluation's figures: `json` as written to `evaluation.json`, `text` a line per group.
#[derive(Debug, Clone)]
pub struct EvaluationReport {
    /// Frames, match radii, time per frame and the counts of each group.
    pub json: Value,
    /// 3-D RMSE, coverage, wrong pairs and index consistency of each group, a line each.
    pub text: String,
}

impl EvaluationReport {
    /// The report of `evaluation`, whose match radii were `r_px` and matching time `match_ms` per frame.
    pub fn new(evaluation: &Evaluation, r_px: &StereoPair<f64>, match_ms: f64) -> Self {
        let json = json!({
            "frames": evaluation.frames,
            "r_px": { "left": r_px.left, "right": r_px.right },
            "matching_ms_per_frame": match_ms,
            "all": counts_json(&evaluation.all),
            "contact_frames": counts_json(&evaluation.contact_frames),
            "in_contact_markers": counts_json(&evaluation.in_contact_markers),
        });
        let text = summary_text(&json);
        Self { json, text }
    }
}

fn counts_json(c: &Counts) -> Value {
    json!({
        "markers_visible_left": c.visible_left,
        "markers_detected_left": c.detected_left,
        "index_correct": c.index_correct,
        "index_wrong": c.index_wrong,
        "index_consistency": c.index_consistency(),
        "markers_visible_both": c.visible_both,
        "reconstructed": c.reconstructed,
        "coverage": c.coverage(),
        "markers_detected_both": c.detected_both,
        "matching_coverage": c.matching_coverage(),
        "wrong_pairs": c.wrong_pairs,
        "wrong_pair_rate": c.wrong_pair_rate(),
        "rmse_mm": c.rmse_mm(),
        "max_error_mm": c.max_error_mm,
    })
}

fn summary_text(v: &Value) -> String {
    let mut s = String::new();
    for key in ["all", "contact_frames", "in_contact_markers"] {
        let g = &v[key];
        let pct = |k: &str| {
            g[k].as_f64()
                .map_or("-".to_owned(), |x| format!("{:.3}%", 100.0 * x))
        };
        let mm = |k: &str| g[k].as_f64().map_or("-".to_owned(), |x| format!("{x:.2e} mm"));
        let _ = writeln!(
            s,
            "{key}: 3-D RMSE {} (max {}), coverage {} (of the markers found in both views: {}), wrong pairs {} ({}), index consistency {} ({} wrong of {} detected)",
            mm("rmse_mm"),
            mm("max_error_mm"),
            pct("coverage"),
            pct("matching_coverage"),
            g["wrong_pairs"],
            pct("wrong_pair_rate"),
            pct("index_consistency"),
            g["index_wrong"],
            g["markers_detected_left"],
        );
    }
    s.trim_end().to_owned()
}
