//! End-to-end test of the pipeline benchmark, `gelstereo bench --calib FILE RECORDING`, on the
//! bundled sample recording with few frames: checks the structure of the output (every stage listed,
//! figures positive, the JSON report complete), not speed, so the command cannot silently rot.

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

mod common;

/// The number before " ms" right after `label` on the line that starts with it.
fn first_ms(text: &str, label: &str) -> f64 {
    let line = text
        .lines()
        .find(|l| l.starts_with(label))
        .unwrap_or_else(|| panic!("no line '{label}' in:\n{text}"));
    line[label.len()..]
        .split_whitespace()
        .next()
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no number on '{line}'"))
}

/// `gelstereo bench` with `args` on 4 frames of the sample, 6 timed runs: its text and JSON report.
fn pipeline_bench(args: &[&str]) -> (String, serde_json::Value) {
    let rec = common::repo().join("data/sample/press-slide");
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("bench.json");
    let common_args = ["--frames", "4", "--runs", "6", "--warmup", "1", "--json"];
    let out = common::gelstereo(
        &[
            &["bench"][..],
            args,
            &common_args,
            &[json.to_str().unwrap(), rec.to_str().unwrap()],
        ]
        .concat(),
    );
    let text = common::text(&out);
    assert!(out.status.success(), "{text}");
    let report = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    (text, report)
}

#[test]
fn pipeline_bench_lists_every_stage_with_positive_figures() {
    let calib = common::repo().join("data/sample/press-slide/calib.yaml");
    let (text, report) = pipeline_bench(&[
        "--calib",
        calib.to_str().unwrap(),
        "--method",
        "blob",
        "--workers",
        "2",
    ]);
    for stage in [
        "decode (both views, from bytes in memory)",
        "localization (both views, one batch)",
        "tracking association (2 views)",
        "triangulation",
        "outlier test + fill",
        "contact geometry",
        "track() whole (stages above + rows)",
        "reference grid indexing (once per session)",
    ] {
        assert!(first_ms(&text, stage) > 0.0, "{stage}: not positive in\n{text}");
    }
    assert!(first_ms(&text, "slip") >= 0.0, "{text}");
    assert!(
        text.contains("whole pipeline (localization + track(), decoded frames): median "),
        "{text}"
    );
    assert!(
        text.contains("stereo frames/s over 6 frames (2 workers"),
        "{text}"
    );
    assert!(text.contains("stages from their `tracing` spans"), "{text}");
    assert!(text.contains("load average"), "{text}");

    assert_eq!(report["method"], "blob");
    assert_eq!(report["frames"], 4);
    assert_eq!(report["image_size"], serde_json::json!([640, 480]));
    let stages = report["latency"]["stages"].as_array().unwrap();
    assert_eq!(stages.len(), 8);
    assert!(stages.iter().all(|s| s["median_ms"].as_f64().unwrap() >= 0.0));
    assert!(report["latency"]["whole_ms"]["median"].as_f64().unwrap() > 0.0);
    assert!(report["throughput"]["frames_per_s"].as_f64().unwrap() > 0.0);
    assert_eq!(report["tracking_stages_from"], "tracing spans (own time)");
    // The blob detector has no window around the lattice: no whole-input run beside it.
    assert!(report["throughput"]["whole_input"].is_null());
    assert!(!text.contains("--whole-input"), "{text}");
}

/// Marknet runs a stream on a window around the lattice; the throughput mode is then measured on the
/// whole input too, in the same run, with the ratio of their CPU times.
#[test]
fn pipeline_bench_measures_the_whole_input_beside_the_window() {
    let (text, report) = pipeline_bench(&["--pipeline", "--threads", "1"]);
    assert!(
        text.contains("throughput mode on the whole input of every frame (--whole-input)")
            && text.contains("the window: "),
        "{text}"
    );
    assert_eq!(report["method"], "marknet-mre");
    // Marknet's parts come from its `tracing` spans: all three rows, each positive.
    for part in [
        "  preprocess (resize, f32 tensor)",
        "  network (ONNX Runtime run)",
        "  post-process (decode, select, MRE)",
    ] {
        assert!(first_ms(&text, part) > 0.0, "{part}: not positive in\n{text}");
    }
    assert_eq!(report["latency"]["stages"].as_array().unwrap().len(), 11);
    assert!(
        report["throughput"]["whole_input"]["frames_per_s"]
            .as_f64()
            .unwrap()
            > 0.0
    );
}

/// `--repeats N`: the throughput mode runs N times; its figures are the medians of the runs, each
/// run listed in the JSON report and the range on the text line. `--repeats 0` is refused.
#[test]
fn pipeline_bench_repeats_the_throughput_mode_and_reports_medians() {
    let (text, report) = pipeline_bench(&[
        "--pipeline",
        "--method",
        "blob",
        "--workers",
        "2",
        "--repeats",
        "3",
    ]);
    let runs = report["throughput"]["repeats"].as_array().unwrap();
    assert_eq!(runs.len(), 3);
    let mut fps: Vec<f64> = runs.iter().map(|r| r["frames_per_s"].as_f64().unwrap()).collect();
    fps.sort_by(f64::total_cmp);
    assert_eq!(report["throughput"]["frames_per_s"].as_f64().unwrap(), fps[1]);
    if let Some(cpu) = report["throughput"]["cpu_ms_per_frame"].as_f64() {
        let mut each: Vec<f64> = runs
            .iter()
            .map(|r| r["cpu_ms_per_frame"].as_f64().unwrap())
            .collect();
        each.sort_by(f64::total_cmp);
        assert_eq!(cpu, each[1]);
    }
    assert!(text.contains(", the median of 3 runs ("), "{text}");
    let out = common::gelstereo(&["bench", "--pipeline", "--repeats", "0", "data/sample/press-slide"]);
    let text = common::text(&out);
    assert!(!out.status.success() && text.contains("--repeats"), "{text}");
}

#[test]
fn pipeline_bench_names_a_missing_recording() {
    let out = common::gelstereo(&["bench", "--pipeline", "/nonexistent/recording"]);
    let text = common::text(&out);
    assert!(!out.status.success());
    assert!(text.contains("/nonexistent/recording"), "{text}");
}

#[test]
fn track_bench_is_an_alias_of_the_pipeline_benchmark() {
    let rec = common::repo().join("data/sample/press-slide");
    let out = common::gelstereo(&[
        "track",
        "--bench",
        "--method",
        "blob",
        "--bench-frames",
        "3",
        rec.to_str().unwrap(),
    ]);
    let text = common::text(&out);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("stereo frames/s over 3 frames"), "{text}");
    assert!(
        first_ms(&text, "track() whole (stages above + rows)") > 0.0,
        "{text}"
    );
}
