//! End-to-end reliability tests of the `gelstereo` binary (docs/reliability.md): bad paths, hostile
//! files and numbers, interruption by real signals, and outputs that are never lost or left half
//! written. Inputs are the bundled sample recording (data/sample/press-slide) and files made here.

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[path = "../../../tests/common/mod.rs"]
mod common;
use common::{fails_with, gelstereo, gelstereo_command, repo, sample, text};

use opencv::core::{CV_8UC3, Mat, Point, Scalar, Vector};
use opencv::{imgcodecs, imgproc, videoio};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 160x120 image with a few dark discs.
fn dots() -> Mat {
    let mut img = Mat::new_rows_cols_with_default(120, 160, CV_8UC3, Scalar::all(210.0)).unwrap();
    for k in 0..6 {
        let c = Point::new(20 + 24 * k, 60);
        imgproc::circle(&mut img, c, 4, Scalar::all(40.0), -1, imgproc::LINE_8, 0).unwrap();
    }
    img
}

/// Writes `image` as PNG to `path` (any path, UTF-8 or not).
fn write(path: &Path, image: &Mat) {
    let mut png = Vector::<u8>::new();
    assert!(imgcodecs::imencode(".png", image, &mut png, &Vector::new()).unwrap());
    std::fs::write(path, png.as_slice()).unwrap();
}

/// Sends `signal` (a `kill` name) to the process `child` once `ready` holds (checked every 20 ms,
/// at most 60 s), then waits for it to end; returns its stderr.
fn signal_when(mut child: std::process::Child, signal: &str, ready: impl Fn() -> bool) -> (i32, String) {
    let start = Instant::now();
    while !ready() {
        assert!(start.elapsed() < Duration::from_secs(60), "never became ready");
        assert!(child.try_wait().unwrap().is_none(), "ended before the signal");
        std::thread::sleep(Duration::from_millis(20));
    }
    let sent = Command::new("kill")
        .args([&format!("-{signal}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(sent.success());
    let out = child.wait_with_output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Issue 18 case 1: a path that is not UTF-8 is an ordinary argument.
#[test]
fn non_utf8_paths_give_errors_not_panics() {
    use std::os::unix::ffi::OsStrExt;
    let dir = tempfile::tempdir().unwrap();
    let name = std::ffi::OsStr::from_bytes(b"x\xff.png");
    let out = gelstereo_command()
        .args(["detect", "--method", "blob"])
        .arg(dir.path().join(name))
        .output()
        .unwrap();
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t.contains("x\u{FFFD}.png") && !t.contains("panicked"), "{t}");
    // A real image under such a name is read.
    write(&dir.path().join(name), &dots());
    let out = gelstereo_command()
        .args(["detect", "--method", "blob"])
        .arg(dir.path().join(name))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out));
}

/// Issue 18 case 2: a calibration nested 50,000 deep is refused before it is parsed.
#[test]
fn deeply_nested_calibrations_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let calib = dir.path().join("deep.yaml");
    let depth = 50_000;
    let text = format!("%YAML:1.0\n---\nK1: {}{}\n", "[".repeat(depth), "]".repeat(depth));
    std::fs::write(&calib, text).unwrap();
    let out = dir.path().join("out");
    fails_with(
        &[
            "reconstruct",
            "--calib",
            s(&calib),
            "--from-ground-truth",
            "--out",
            s(&out),
            s(&sample()),
        ],
        &["deep.yaml", "nested", "at most 32"],
    );
}

/// Issue 18 cases 3 and 4: numbers that size allocations or thread pools are bounded up front.
#[test]
fn allocation_and_thread_counts_are_bounded() {
    let calib = sample().join("calib.yaml");
    fails_with(
        &[
            "reconstruct",
            "--calib",
            s(&calib),
            "--from-ground-truth",
            "--gt-dust",
            "1e10",
            "--out",
            "x",
            s(&sample()),
        ],
        &["--gt-dust", "0 to 100000"],
    );
    fails_with(
        &[
            "reconstruct",
            "--calib",
            s(&calib),
            "--from-ground-truth",
            "--gt-dust",
            "100001",
            "--out",
            "x",
            s(&sample()),
        ],
        &["--gt-dust", "0 to 100000"],
    );
    fails_with(
        &["bench", "--threads", "100000", s(&sample())],
        &["--threads", "0 (one per core) to 256"],
    );
    fails_with(&["detect", "--threads", "257", "x.png"], &["--threads", "to 256"]);
    fails_with(
        &["bench", "--pipeline", "--workers", "100000", s(&sample())],
        &["--workers", "0 (one per core) to 256"],
    );
    fails_with(
        &[
            "simulate",
            "--checkerboard",
            "9x6",
            "--poses",
            "100000000000",
            "--out",
            "cb",
        ],
        &["poses", "1 to 10000"],
    );
}

/// `simulate --force` replaces only a folder gelstereo-sim wrote, checked at every depth.
#[test]
fn simulate_force_never_removes_what_it_did_not_write() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("mine.txt"), "keep").unwrap();
    std::fs::create_dir(d.join("sub")).unwrap();
    let sim = |out: &str| {
        gelstereo_command()
            .current_dir(d)
            .args([
                "simulate",
                "--quiet",
                "--force",
                "--experiments",
                "1",
                "--frames-per-experiment",
                "2",
                "--out",
                out,
            ])
            .output()
            .unwrap()
    };
    let out = sim(".");
    assert!(
        !out.status.success() && text(&out).contains("refusing to replace it"),
        "{}",
        text(&out)
    );
    let out = sim("mine.txt");
    assert!(
        !out.status.success() && text(&out).contains("a file, not a folder"),
        "{}",
        text(&out)
    );
    assert_eq!(std::fs::read_to_string(d.join("mine.txt")).unwrap(), "keep");
    assert!(d.join("sub").is_dir());
    // A dataset it wrote is replaced; one with a file of the user's is not.
    assert!(sim("ds").status.success());
    assert!(sim("ds").status.success());
    std::fs::write(d.join("ds/notes.txt"), "mine").unwrap();
    let out = sim("ds");
    assert!(
        !out.status.success() && text(&out).contains("notes.txt"),
        "{}",
        text(&out)
    );
    assert!(d.join("ds/notes.txt").is_file());
    // Nor one with a file of the user's any number of folders down, or a link inside it.
    std::fs::remove_file(d.join("ds/notes.txt")).unwrap();
    for (nested, what) in [
        (
            "ds/train/exp_0000/left/notes.txt",
            "train/exp_0000/left/notes.txt",
        ),
        ("ds/train/exp_0000/analysis.csv", "train/exp_0000/analysis.csv"),
        ("ds/train/mine", "train/mine"),
    ] {
        std::fs::write(d.join(nested), "mine").unwrap();
        let out = sim("ds");
        assert!(
            !out.status.success() && text(&out).contains(what),
            "{}",
            text(&out)
        );
        assert_eq!(std::fs::read_to_string(d.join(nested)).unwrap(), "mine");
        std::fs::remove_file(d.join(nested)).unwrap();
    }
    std::os::unix::fs::symlink(d.join("mine.txt"), d.join("ds/train/exp_0000/left/000002.png")).unwrap();
    let out = sim("ds");
    assert!(
        !out.status.success() && text(&out).contains("000002.png"),
        "{}",
        text(&out)
    );
    assert_eq!(std::fs::read_to_string(d.join("mine.txt")).unwrap(), "keep");
    std::fs::remove_file(d.join("ds/train/exp_0000/left/000002.png")).unwrap();
    assert!(sim("ds").status.success());
    // A temporary folder left by a killed run (a process that no longer exists) is cleaned up.
    std::fs::create_dir(d.join(".fresh.partial-999999999")).unwrap();
    assert!(sim("fresh").status.success());
    assert!(!d.join(".fresh.partial-999999999").exists());
}

/// Issue 18 case 6 (simulate): SIGINT and SIGTERM leave no temporary folder and no output.
#[test]
fn interrupted_simulate_leaves_nothing_behind() {
    for signal in ["INT", "TERM"] {
        let dir = tempfile::tempdir().unwrap();
        let child = gelstereo_command()
            .current_dir(dir.path())
            .args([
                "simulate",
                "--quiet",
                "--experiments",
                "2",
                "--frames-per-experiment",
                "400",
                "--out",
                "ds",
            ])
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let partial_with_frames = || {
            std::fs::read_dir(dir.path()).unwrap().flatten().any(|e| {
                e.file_name().to_string_lossy().contains(".partial-") && walk_count(&e.path(), "png") >= 4
            })
        };
        let (code, err) = signal_when(child, signal, partial_with_frames);
        assert_eq!(code, 130, "SIG{signal}: {err}");
        assert!(err.contains("interrupted"), "{err}");
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert!(left.is_empty(), "SIG{signal} left {left:?}");
    }
}

fn walk_count(dir: &Path, ext: &str) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| {
            let p = e.path();
            if p.is_dir() {
                walk_count(&p, ext)
            } else {
                usize::from(p.extension().is_some_and(|x| x == ext))
            }
        })
        .sum()
}

/// A copy of the sample recording `repeats` times over (frames renumbered), with its calibration.
fn long_recording(dir: &Path, repeats: usize) -> PathBuf {
    let rec = dir.join("long");
    let names: Vec<String> = (0..24).map(|k| format!("{k:06}.jpg")).collect();
    for side in ["left", "right"] {
        std::fs::create_dir_all(rec.join(side)).unwrap();
        for r in 0..repeats {
            for (k, name) in names.iter().enumerate() {
                let to = rec.join(side).join(format!("{:06}.jpg", r * 24 + k));
                std::fs::hard_link(sample().join(side).join(name), &to)
                    .or_else(|_| std::fs::copy(sample().join(side).join(name), &to).map(drop))
                    .unwrap();
            }
        }
    }
    std::fs::copy(sample().join("calib.yaml"), rec.join("calib.yaml")).unwrap();
    rec
}

/// Issue 18 case 6 (reconstruct): after SIGTERM, markers.csv ends at a frame boundary with whole
/// rows and a point cloud for each of its frames; an earlier run's files do not survive a new run.
#[test]
fn interrupted_reconstruct_leaves_tables_and_point_clouds_in_step() {
    let dir = tempfile::tempdir().unwrap();
    let rec = long_recording(dir.path(), 20);
    let out = dir.path().join("out");
    std::fs::create_dir_all(out.join("ply")).unwrap();
    std::fs::write(out.join("ply/999999.ply"), "stale").unwrap();
    std::fs::write(out.join("evaluation.json"), "{}").unwrap();
    // As an earlier run left them: listed in the folder's manifest.
    std::fs::write(
        out.join(".gelstereo-manifest"),
        "ply/999999.ply\nevaluation.json\n",
    )
    .unwrap();
    let child = gelstereo_command()
        .args([
            "reconstruct",
            "--method",
            "blob",
            "--calib",
            s(&rec.join("calib.yaml")),
            "--out",
            s(&out),
            s(&rec),
        ])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let ply = out.join("ply");
    let (code, err) = signal_when(child, "TERM", || {
        std::fs::read_dir(&ply).map_or(0, |d| d.count()) >= 5
    });
    assert_eq!(code, 130, "{err}");
    assert!(err.contains("interrupted after"), "{err}");
    assert!(!out.join("ply/999999.ply").exists() && !out.join("evaluation.json").exists());
    let csv = std::fs::read_to_string(out.join("markers.csv")).unwrap();
    assert!(csv.ends_with('\n'));
    let frames: std::collections::BTreeSet<u32> = csv
        .lines()
        .skip(1)
        .map(|l| {
            assert_eq!(
                l.split(',').count(),
                gelstereo::core::table::MARKER_COLUMNS.len(),
                "cut row {l}"
            );
            l.split(',').next().unwrap().parse().unwrap()
        })
        .collect();
    let plys: std::collections::BTreeSet<u32> = std::fs::read_dir(&ply)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy()[..6].parse().unwrap())
        .collect();
    assert!(
        !frames.is_empty() && frames.len() < 480,
        "{} frames",
        frames.len()
    );
    assert_eq!(frames, plys, "markers.csv and the point clouds disagree");
    assert_eq!(frames.iter().copied().max(), Some(frames.len() as u32 - 1));
}

/// Issue 18 case 7: `detect --out` keeps the old file when the run fails, and leaves no temporary.
#[test]
fn detect_keeps_the_previous_csv_when_it_fails() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("old.csv");
    std::fs::write(&csv, "image,x,y,confidence\nprevious,1,2,0.9\n").unwrap();
    let good = dir.path().join("good.png");
    write(&good, &dots());
    let bad = dir.path().join("bad.png");
    std::fs::write(&bad, "not an image").unwrap();
    fails_with(
        &["detect", "--method", "blob", "--out", s(&csv), s(&good), s(&bad)],
        &["bad.png"],
    );
    assert!(
        std::fs::read_to_string(&csv)
            .unwrap()
            .contains("previous,1,2,0.9")
    );
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        3,
        "a temporary file was left"
    );
    let out = gelstereo(&["detect", "--method", "blob", "--out", s(&csv), s(&good)]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(!std::fs::read_to_string(&csv).unwrap().contains("previous"));
}

/// Truncated images and videos, and links that cannot be followed, are named (`detect` and
/// `track` warn of a video that ends before its declared length).
#[test]
fn truncated_files_and_link_loops_are_reported_with_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let jpg = dir.path().join("cut.jpg");
    let full = std::fs::read(sample().join("left/000005.jpg")).unwrap();
    std::fs::write(&jpg, &full[..full.len() / 2]).unwrap();
    fails_with(
        &["detect", "--method", "blob", s(&jpg)],
        &["cut.jpg", "truncated"],
    );
    let png = dir.path().join("cut.png");
    write(&png, &dots());
    let bytes = std::fs::read(&png).unwrap();
    std::fs::write(&png, &bytes[..bytes.len() - 20]).unwrap();
    fails_with(
        &["detect", "--method", "blob", s(&png)],
        &["cut.png", "truncated"],
    );

    // A video cut short: fewer frames than it declares, with a warning that names it.
    let video = dir.path().join("cut.avi");
    let fourcc = videoio::VideoWriter::fourcc('M', 'J', 'P', 'G').unwrap();
    let mut writer =
        videoio::VideoWriter::new(s(&video), fourcc, 10.0, opencv::core::Size::new(160, 120), true).unwrap();
    for _ in 0..40 {
        videoio::VideoWriterTrait::write(&mut writer, &dots()).unwrap();
    }
    drop(writer);
    let bytes = std::fs::read(&video).unwrap();
    std::fs::write(&video, &bytes[..bytes.len() / 2]).unwrap();
    let stream = dir.path().join("cut.jsonl");
    for args in [
        vec!["detect", "--method", "blob", s(&video)],
        vec![
            "track",
            "--quiet",
            "--method",
            "blob",
            "--jsonl",
            s(&stream),
            s(&video),
        ],
    ] {
        let out = gelstereo(&args);
        let t = text(&out);
        assert!(
            t.contains("cut.avi: only") && t.contains("of the 40 frames"),
            "{args:?}: {t}"
        );
    }

    // A link looping onto itself inside an input folder.
    let folder = dir.path().join("frames");
    std::fs::create_dir(&folder).unwrap();
    write(&folder.join("a.png"), &dots());
    std::os::unix::fs::symlink(folder.join("loop.png"), folder.join("loop.png")).unwrap();
    fails_with(&["detect", "--method", "blob", s(&folder)], &["loop.png"]);
}

/// Issue 18 case 10: silent wrong results become errors naming the file and the field.
#[test]
fn absurd_inputs_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    // D1 = 1e300.
    let calib = std::fs::read_to_string(sample().join("calib.yaml")).unwrap();
    let d1 = calib.find("D1:").unwrap();
    let data = d1 + calib[d1..].find("data: [").unwrap() + "data: [".len();
    let absurd = format!(
        "{} 1e300,{}",
        &calib[..data],
        &calib[data..].split_once(',').unwrap().1
    );
    let bad_calib = dir.path().join("absurd.yaml");
    std::fs::write(&bad_calib, absurd).unwrap();
    fails_with(
        &[
            "reconstruct",
            "--calib",
            s(&bad_calib),
            "--from-ground-truth",
            "--out",
            "x",
            s(&sample()),
        ],
        &["absurd.yaml", "'D1'", "no ray"],
    );
    // A garbage meta.json, and a --grid other than the recording's.
    let rec = dir.path().join("rec");
    for side in ["left", "right"] {
        std::fs::create_dir_all(rec.join(side)).unwrap();
        std::fs::copy(
            sample().join(side).join("000000.jpg"),
            rec.join(side).join("000000.jpg"),
        )
        .unwrap();
    }
    std::fs::write(rec.join("meta.json"), r#"{"grid": {"rows": "many", "cols": 23}}"#).unwrap();
    let calib = sample().join("calib.yaml");
    fails_with(
        &[
            "reconstruct",
            "--method",
            "blob",
            "--calib",
            s(&calib),
            "--out",
            "x",
            s(&rec),
        ],
        &["meta.json", "invalid type"],
    );
    std::fs::copy(sample().join("meta.json"), rec.join("meta.json")).unwrap();
    fails_with(
        &[
            "reconstruct",
            "--method",
            "blob",
            "--calib",
            s(&calib),
            "--grid",
            "10x10",
            "--out",
            "x",
            s(&rec),
        ],
        &["meta.json", "'grid'", "10 x 10", "23 x 23"],
    );
    // Without meta.json, a 10x10 lattice on a 23x23 view is refused by the indexing.
    std::fs::remove_file(rec.join("meta.json")).unwrap();
    fails_with(
        &[
            "reconstruct",
            "--method",
            "blob",
            "--calib",
            s(&calib),
            "--grid",
            "10x10",
            "--out",
            "x",
            s(&rec),
        ],
        &["more than the 10 x 10 lattice"],
    );
    // eval: --frame-step 0 and a garbage dataset.json.
    fails_with(
        &["eval", "--dataset", s(dir.path()), "--frame-step", "0"],
        &["--frame-step", "0"],
    );
    std::fs::create_dir_all(dir.path().join("test/exp_0000")).unwrap();
    std::fs::write(dir.path().join("dataset.json"), "{\"experiments\": 3}").unwrap();
    fails_with(
        &["eval", "--dataset", s(dir.path()), "--methods", "blob"],
        &["dataset.json"],
    );
}

/// Issue 18 case 10: a model whose weights are NaN is an error, not zero markers.
#[test]
fn a_model_with_nan_weights_is_an_error() {
    let fixtures = repo().join("data/fixtures/onnx");
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("dots.png");
    write(&img, &dots());
    fails_with(
        &[
            "detect",
            "--method",
            "marknet",
            "--marknet",
            s(&fixtures.join("marknet_nan.onnx")),
            "--fit",
            "stretch",
            s(&img),
        ],
        &["marknet_nan.onnx", "NaN"],
    );
    // doctor runs the models once on a synthetic marker image and reports the broken one.
    let models = dir.path().join("models");
    std::fs::create_dir(&models).unwrap();
    std::fs::copy(fixtures.join("marknet_nan.onnx"), models.join("marknet.onnx")).unwrap();
    std::fs::copy(fixtures.join("mre_tiny.onnx"), models.join("mre.onnx")).unwrap();
    let out = gelstereo(&["doctor", "--models", s(&models)]);
    let t = text(&out);
    assert!(
        !out.status.success() && t.contains("Marknet-MRE run") && t.contains("NaN"),
        "{t}"
    );
}

/// Issue 18 case 11: calibration numbers out of range are refused before OpenCV sees them.
#[test]
fn calibrate_ranges_are_checked_before_opencv() {
    let views = sample();
    for (square, window, needle) in [
        ("1e308", "5", "--square-mm"),
        ("1.5", "100000", "--subpix-window"),
    ] {
        let out = gelstereo(&[
            "calibrate",
            "--board",
            "9x6",
            "--square-mm",
            square,
            "--subpix-window",
            window,
            "--out",
            "x.yaml",
            s(&views.join("left")),
            s(&views.join("right")),
        ]);
        let t = text(&out);
        assert!(
            !out.status.success() && t.contains(needle) && !t.contains("OpenCV(") && !t.contains("panicked"),
            "{t}"
        );
    }
}

/// Issue 18 case 12: an image larger than the limit is refused from its header, before decoding.
#[test]
fn huge_images_are_refused_from_their_header() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("huge.png");
    // A valid PNG header (IHDR 20000 x 20000) with no pixel data: decoding would need 1.2 GB.
    let mut bytes = b"\x89PNG\r\n\x1a\n\0\0\0\x0dIHDR".to_vec();
    bytes.extend_from_slice(&20_000u32.to_be_bytes());
    bytes.extend_from_slice(&20_000u32.to_be_bytes());
    bytes.extend_from_slice(&[8, 2, 0, 0, 0, 0, 0, 0, 0]);
    bytes.extend_from_slice(b"\0\0\0\0IEND\xae\x42\x60\x82");
    std::fs::write(&png, bytes).unwrap();
    fails_with(
        &["detect", "--method", "blob", s(&png)],
        &["huge.png", "20000x20000", "16384"],
    );
}

/// Issue 43 case 22: `detect` stopped by SIGTERM leaves the existing --out file as it was and no
/// temporary file; one killed outright (SIGKILL runs no destructor) leaves a temporary file that the
/// next run into the same place removes.
#[test]
fn a_stopped_or_killed_detect_leaves_no_temporary_file() {
    let dir = tempfile::tempdir().unwrap();
    let rec = long_recording(dir.path(), 4);
    let out = dir.path().join("det.csv");
    std::fs::write(&out, "image,x,y,confidence\n").unwrap();
    let overlays = dir.path().join("overlays");
    std::fs::create_dir_all(&overlays).unwrap();
    let child = gelstereo_command()
        .args([
            "detect",
            "--method",
            "blob",
            "--out",
            s(&out),
            "--overlay",
            s(&overlays),
        ])
        .arg(rec.join("left"))
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (code, err) = signal_when(child, "TERM", || {
        std::fs::read_dir(&overlays).map_or(0, |d| d.count()) >= 3
    });
    assert_eq!(code, 130, "{err}");
    assert!(err.contains("interrupted"), "{err}");
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "image,x,y,confidence\n");
    let leftovers = |dir: &Path| -> Vec<String> {
        std::fs::read_dir(dir)
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".partial"))
            .collect()
    };
    assert!(leftovers(dir.path()).is_empty(), "{:?}", leftovers(dir.path()));
    // What a killed run leaves (its process id is no running process's), removed by the next run.
    let stale = dir.path().join(".det.csv.4194303.a1b2c3.partial");
    std::fs::write(&stale, "cut").unwrap();
    let image = rec.join("left/000000.jpg");
    let run = gelstereo_command()
        .args(["detect", "--method", "blob", "--out", s(&out)])
        .arg(&image)
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", text(&run));
    assert!(leftovers(dir.path()).is_empty(), "{:?}", leftovers(dir.path()));
}

/// `detect` keeps names that are not UTF-8 apart (in the CSV and in overlay names), and writes
/// overlays only into a folder of its own: a folder of the user's needs --force, and files there
/// that detect does not write are never touched.
#[test]
fn detect_keeps_odd_names_apart_and_overlays_only_its_own_folder() {
    use std::os::unix::ffi::OsStrExt;
    let dir = tempfile::tempdir().unwrap();
    let inputs = dir.path().join("in");
    std::fs::create_dir(&inputs).unwrap();
    for byte in [0xffu8, 0xfe] {
        let name = [b'a', byte, b'.', b'p', b'n', b'g'];
        write(&inputs.join(std::ffi::OsStr::from_bytes(&name)), &dots());
    }
    let csv = dir.path().join("found.csv");
    let overlays = dir.path().join("overlays");
    let detect = |overlay: &Path, extra: &[&str]| {
        let mut args = vec![
            "detect",
            "--method",
            "blob",
            "--out",
            s(&csv),
            "--overlay",
            s(overlay),
        ];
        args.extend_from_slice(extra);
        args.push(s(&inputs));
        gelstereo(&args)
    };
    let out = detect(&overlays, &[]);
    assert!(out.status.success(), "{}", text(&out));
    let table = std::fs::read_to_string(&csv).unwrap();
    assert!(
        table.contains("a\\xff.png,") && table.contains("a\\xfe.png,"),
        "{table}"
    );
    assert!(overlays.join("a\\xff.png").is_file() && overlays.join("a\\xfe.png").is_file());

    // A folder of the user's: refused without --force; with it, only detect's own names are written.
    let user = dir.path().join("user");
    std::fs::create_dir(&user).unwrap();
    std::fs::write(user.join("a\\xff.png"), "mine").unwrap();
    std::fs::write(user.join("notes.txt"), "mine").unwrap();
    let out = detect(&user, &[]);
    assert!(
        !out.status.success() && text(&out).contains("--force"),
        "{}",
        text(&out)
    );
    assert_eq!(std::fs::read_to_string(user.join("a\\xff.png")).unwrap(), "mine");
    assert!(detect(&user, &["--force"]).status.success());
    assert_eq!(std::fs::read_to_string(user.join("notes.txt")).unwrap(), "mine");
    // detect's own folder is reused without --force; an overlay folder inside the input is refused.
    assert!(detect(&overlays, &[]).status.success());
    let out = detect(&inputs.join("ov"), &["--force"]);
    assert!(!out.status.success(), "{}", text(&out));
    assert!(!inputs.join("ov").exists());
}

/// A recording whose folder name is not UTF-8 is tracked with its own calib.yaml, and its outputs
/// go where asked.
#[test]
fn a_recording_named_in_bytes_that_are_not_utf8_is_tracked() {
    use std::os::unix::ffi::OsStrExt;
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join(std::ffi::OsStr::from_bytes(b"rec\xff"));
    std::fs::rename(common::sample_copy(dir.path(), 3), &rec).unwrap();
    let out = gelstereo_command()
        .arg("track")
        .arg("--quiet")
        .arg(&rec)
        .arg("--out")
        .arg(dir.path().join(std::ffi::OsStr::from_bytes(b"out\xfe")))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out));
    let frames = dir
        .path()
        .join(std::ffi::OsStr::from_bytes(b"out\xfe/frames.csv"));
    assert_eq!(std::fs::read_to_string(frames).unwrap().lines().count(), 4);
}

/// Frame files read in natural order (`2` before `10`), with a warning where two names carry the
/// same number written differently (`1.png` and `01.png`).
#[test]
fn frame_names_that_do_not_settle_their_order_are_warned_about() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    for name in ["1.png", "01.png", "2.png", "10.png"] {
        write(&frames.join(name), &dots());
    }
    let stream = dir.path().join("s.jsonl");
    let track = || {
        let args = [
            "track",
            "--quiet",
            "--method",
            "blob",
            "--jsonl",
            s(&stream),
            s(&frames),
        ];
        text(&gelstereo(&args))
    };
    let t = track();
    assert!(t.contains("1.png and 01.png") && t.contains("same number"), "{t}");
    std::fs::remove_file(frames.join("01.png")).unwrap();
    let t = track();
    assert!(!t.contains("same number"), "{t}");
}
