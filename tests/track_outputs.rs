//! `gelstereo track`'s outputs as a user relies on them: tables byte-identical to the ones the
//! pipeline has always written on the sample, JSON lines on standard output, two cameras (video
//! files standing in) and `gelstereo capture` through the same code, outputs that survive SIGINT,
//! SIGTERM and SIGKILL, and output folders that never show an older run's files as current.
#![allow(clippy::expect_used, clippy::unwrap_used)]

mod common;

use gelstereo::core::table::{FRAME_COLUMNS, MARKER_COLUMNS};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use common::{gelstereo, gelstereo_command, repo, sample, sample_copy, text};
use sha2::Digest;

fn sha256(path: &Path) -> String {
    let bytes = std::fs::read(path).unwrap();
    format!("{:x}", sha2::Sha256::digest(&bytes))
}

/// The expected hash of markers.csv for `method` (tests/data/press-slide-markers.sha256).
fn expected_hash(method: &str) -> String {
    let text = std::fs::read_to_string(repo().join("tests/data/press-slide-markers.sha256")).unwrap();
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .find_map(|l| {
            l.split_once("  ")
                .filter(|(_, m)| *m == method)
                .map(|(h, _)| h.to_owned())
        })
        .unwrap()
}

fn track_ok(args: &[&str]) -> String {
    let out = gelstereo_command()
        .arg("track")
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap();
    let t = text(&out);
    assert!(out.status.success(), "{args:?}:\n{t}");
    t
}

#[test]
fn tables_on_the_sample_are_byte_identical_and_frames_csv_ends_with_time_and_note() {
    let dir = tempfile::tempdir().unwrap();
    // Frames localized ahead by worker threads (the default) and one at a time: the same tables.
    for (method, frames_file, workers) in [
        ("marknet-mre", "press-slide-frames.csv", "0"),
        ("marknet-mre", "press-slide-frames.csv", "1"),
        ("blob", "press-slide-frames-blob.csv", "0"),
    ] {
        let out = dir.path().join(format!("{method}-{workers}"));
        track_ok(&[
            "--method",
            method,
            "--workers",
            workers,
            "--out",
            out.to_str().unwrap(),
            sample().to_str().unwrap(),
        ]);
        assert_eq!(
            sha256(&out.join("markers.csv")),
            expected_hash(method),
            "{method}, --workers {workers}"
        );
        let expected = std::fs::read_to_string(repo().join("tests/data").join(frames_file)).unwrap();
        let written = std::fs::read_to_string(out.join("frames.csv")).unwrap();
        let lines: Vec<&str> = written.lines().collect();
        assert_eq!(lines[0], format!("{},t_s,note", expected.lines().next().unwrap()));
        for (k, (w, e)) in lines[1..].iter().zip(expected.lines().skip(1)).enumerate() {
            // The old columns unchanged, then t_s = frame / 30 Hz and an empty note.
            assert_eq!(*w, format!("{e},{:.6},", k as f64 / 30.0), "{method} frame {k}");
        }
        assert_eq!(lines.len(), expected.lines().count());
    }
    // Every frame on the whole network input: the tables of a localizer without windows.
    let whole = dir.path().join("whole-input");
    track_ok(&[
        "--whole-input",
        "--out",
        whole.to_str().unwrap(),
        sample().to_str().unwrap(),
    ]);
    assert_eq!(
        sha256(&whole.join("markers.csv")),
        expected_hash("marknet-mre --whole-input")
    );
    assert_ne!(
        expected_hash("marknet-mre --whole-input"),
        expected_hash("marknet-mre")
    );
}

#[test]
fn jsonl_to_standard_output_parses_line_by_line_and_out_dash_is_refused() {
    let cwd = tempfile::tempdir().unwrap();
    let out = gelstereo_command()
        .current_dir(cwd.path())
        .args(["track", "--quiet", "--method", "blob", "--jsonl", "-"])
        .arg(sample())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out));
    let stdout = String::from_utf8(out.stdout).unwrap();
    let expected = std::fs::read_to_string(repo().join("tests/data/press-slide-frames-blob.csv")).unwrap();
    let slips: Vec<String> = expected
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(6).unwrap().to_owned())
        .collect();
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 40);
    for (k, line) in lines.iter().enumerate() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(v["frame"], k);
        // `t_s` keeps 6 decimals, as frames.csv.
        assert!((v["t_s"].as_f64().unwrap() - k as f64 / 30.0).abs() <= 5e-7);
        assert_eq!(v["slip"], slips[k].as_str());
        assert_eq!(v["schema"], "gelstereo-frame/1");
        let markers = &v["markers"];
        assert_eq!(markers["row"].as_array().unwrap().len(), 529);
        assert!(markers["X_gel_um"][0].is_i64() && markers["lost"].is_array());
        assert!(
            v["force_N"].is_number()
                && markers["pressure_kPa"][0].is_number()
                && markers["in_contact"].is_array()
                && v["gel"]["axes"].is_array()
        );
    }
    // Nothing written beside the stream; `--out -` is refused without creating a folder `-`.
    assert_eq!(std::fs::read_dir(cwd.path()).unwrap().count(), 0);
    let refused = gelstereo_command()
        .current_dir(cwd.path())
        .args(["track", "--quiet", "--method", "blob", "--out", "-"])
        .arg(sample())
        .output()
        .unwrap();
    assert!(
        !refused.status.success() && text(&refused).contains("--jsonl -"),
        "{}",
        text(&refused)
    );
    assert!(!cwd.path().join("-").exists());
}

/// The stream's schema, compiled.
fn frame_schema() -> jsonschema::Validator {
    let text = std::fs::read_to_string(repo().join("docs/schema/frame-v1.json")).unwrap();
    let schema: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(schema["properties"]["schema"]["const"], "gelstereo-frame/1");
    jsonschema::draft202012::new(&schema).unwrap()
}

/// The most bytes a line of the sample's stream may take (529 markers).
const MAX_LINE_BYTES: usize = 40_000;

/// Whether `a` and `b` agree to `tolerance` (both absent counts as agreeing).
fn close<const N: usize>(a: Option<[f64; N]>, b: Option<[f64; N]>, tolerance: f64) -> bool {
    match (a, b) {
        (None, None) => true,
        (Some(a), Some(b)) => a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= tolerance),
        _ => false,
    }
}

#[test]
fn jsonl_stream_of_the_sample_follows_its_schema_and_reads_back_as_the_tables() {
    let dir = tempfile::tempdir().unwrap();
    let (out, stream) = (dir.path().join("out"), dir.path().join("stream.jsonl"));
    track_ok(&[
        "--no-ply",
        "--overlay-every",
        "0",
        "--out",
        out.to_str().unwrap(),
        "--jsonl",
        stream.to_str().unwrap(),
        sample().to_str().unwrap(),
    ]);
    let schema = frame_schema();
    let text = std::fs::read_to_string(&stream).unwrap();
    for (k, line) in text.lines().enumerate() {
        assert!(line.len() <= MAX_LINE_BYTES, "frame {k}: {} bytes", line.len());
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        let errors: Vec<String> = schema.iter_errors(&v).map(|e| e.to_string()).collect();
        assert!(errors.is_empty(), "frame {k}: {errors:?}");
    }
    // Read back, every cell of markers.csv and frames.csv is there to the stream's precision:
    // px to 0.005, gel-frame mm to half a micrometre, camera-frame mm (through the gel frame) to
    // one micrometre, kPa to 0.005; words and flags exactly.
    let table = gelstereo::core::table::CsvTable::read(&out.join("markers.csv")).unwrap();
    let frames = gelstereo::core::table::CsvTable::read(&out.join("frames.csv")).unwrap();
    let read: Vec<_> = gelstereo::sink::read_frames(text.as_bytes(), "stream.jsonl")
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(read.len(), 40);
    let mut row = 0;
    for (k, (frame, gel)) in read.iter().enumerate() {
        assert!(gel.is_some(), "frame {k} names its gel frame");
        let summary = gelstereo::core::FrameSummary::from_table(&frames, k).unwrap();
        assert_eq!(
            (frame.summary.slip, frame.summary.contact),
            (summary.slip, summary.contact)
        );
        assert!(close(
            frame.summary.force_n.map(|f| [f]),
            summary.force_n.map(|f| [f]),
            5e-5
        ));
        let mut region = Vec::new();
        for m in &frame.markers {
            let truth = gelstereo::core::MarkerRecord::from_table(&table, row).unwrap();
            row += 1;
            if truth.in_contact == Some(true) {
                region.push(truth.index);
            }
            let at = format!("frame {k} marker {:?}", m.index);
            assert_eq!(
                (m.frame, m.index, m.status),
                (truth.frame, truth.index, truth.status),
                "{at}"
            );
            assert_eq!(
                (m.in_contact, m.slipping),
                (truth.in_contact, truth.slipping),
                "{at}"
            );
            let px = |p: Option<gelstereo::core::Point2>| p.map(|p| [p.x, p.y]);
            assert!(close(px(m.left_px), px(truth.left_px), 0.005 + 1e-9), "{at}");
            assert!(close(px(m.right_px), px(truth.right_px), 0.005 + 1e-9), "{at}");
            assert!(
                close(m.gel_position_mm, truth.gel_position_mm, 5e-4 + 1e-9),
                "{at}"
            );
            assert!(
                close(m.gel_displacement_mm, truth.gel_displacement_mm, 5e-4 + 1e-9),
                "{at}"
            );
            assert!(close(m.position_mm, truth.position_mm, 1e-3), "{at}");
            assert!(close(m.displacement_mm, truth.displacement_mm, 1e-3), "{at}");
            let kpa = |v: Option<f64>| v.map(|v| [v]);
            assert!(
                close(kpa(m.pressure_kpa), kpa(truth.pressure_kpa), 0.005 + 1e-9),
                "{at}"
            );
        }
        assert_eq!(frame.contact_region, region, "frame {k}: the contact region");
    }
    assert_eq!(row, table.len());
}

#[test]
fn jsonl_stream_read_by_head_ends_the_run_quietly() {
    use std::io::BufRead;
    let mut child = gelstereo_command()
        .args(["track", "--quiet", "--method", "blob", "--jsonl", "-"])
        .arg(sample())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut first = String::new();
    {
        let mut reader = std::io::BufReader::new(child.stdout.take().unwrap());
        reader.read_line(&mut first).unwrap();
    }
    // The reader is gone, as `| head -1` is after its line.
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        !stderr.contains("error") && !stderr.contains("Broken pipe"),
        "{stderr}"
    );
    assert!(stderr.contains("reader closed"), "{stderr}");
    let v: serde_json::Value = serde_json::from_str(&first).unwrap();
    assert_eq!(v["frame"], 0);
}

/// Writes the sample's `side` view as an MJPG video (a camera's stand-in).
fn video_of(side: &str, path: &Path) {
    use opencv::prelude::{VideoWriterTrait, VideoWriterTraitConst};
    let fourcc = opencv::videoio::VideoWriter::fourcc('M', 'J', 'P', 'G').unwrap();
    let size = opencv::core::Size::new(640, 480);
    let mut w = opencv::videoio::VideoWriter::new(path.to_str().unwrap(), fourcc, 30.0, size, true).unwrap();
    assert!(w.is_opened().unwrap());
    for k in 0..24 {
        let p = sample().join(side).join(format!("{k:06}.jpg"));
        let img = opencv::imgcodecs::imread(p.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
        w.write(&img).unwrap();
    }
}

#[test]
fn two_cameras_and_capture_share_one_path_and_their_frames_track_alike() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right) = (dir.path().join("left.avi"), dir.path().join("right.avi"));
    video_of("left", &left);
    video_of("right", &right);
    let cameras = format!("{},{}", left.display(), right.display());
    let calib = sample().join("calib.yaml");
    let live = dir.path().join("live");
    track_ok(&[
        "--method",
        "blob",
        "--camera",
        &cameras,
        "--calib",
        calib.to_str().unwrap(),
        "--out",
        live.to_str().unwrap(),
    ]);
    let frames = std::fs::read_to_string(live.join("frames.csv")).unwrap();
    let rows: Vec<Vec<&str>> = frames.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 24);
    // Capture time = the videos' frame times (30 Hz), from the first frame.
    assert!(
        (rows[3][11].parse::<f64>().unwrap() - 0.1).abs() < 1e-3,
        "{frames}"
    );
    assert!(rows.iter().any(|r| r[6] == "gross_slip"), "{frames}");

    let captured = dir.path().join("captured");
    let out = gelstereo(&[
        "capture",
        "--camera",
        &cameras,
        "--out",
        captured.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out));
    for side in ["left", "right"] {
        assert_eq!(std::fs::read_dir(captured.join(side)).unwrap().count(), 24);
    }
    let from_disk = dir.path().join("from-disk");
    track_ok(&[
        "--method",
        "blob",
        "--calib",
        calib.to_str().unwrap(),
        "--out",
        from_disk.to_str().unwrap(),
        captured.to_str().unwrap(),
    ]);
    // The saved pairs are the frames the cameras gave: the same markers to the last digit.
    assert_eq!(
        sha256(&from_disk.join("markers.csv")),
        sha256(&live.join("markers.csv"))
    );
}

/// A recording of `n` frames walking the sample forth and back (long enough to interrupt).
fn long_recording(dir: &Path, n: usize) -> PathBuf {
    let rec = dir.join("long");
    for side in ["left", "right"] {
        std::fs::create_dir_all(rec.join(side)).unwrap();
        for k in 0..n {
            let j = if (k / 23) % 2 == 0 { k % 23 } else { 23 - k % 23 };
            std::fs::copy(
                sample().join(side).join(format!("{j:06}.jpg")),
                rec.join(side).join(format!("{k:06}.jpg")),
            )
            .unwrap();
        }
    }
    std::fs::copy(sample().join("calib.yaml"), rec.join("calib.yaml")).unwrap();
    rec
}

/// Frames in markers.csv (with their row counts) and in frames.csv; panics on a cut line.
fn table_frames(out: &Path) -> (BTreeMap<u32, usize>, BTreeSet<u32>) {
    let markers = std::fs::read_to_string(out.join("markers.csv")).unwrap();
    let frames = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    for (name, text, cells) in [
        ("markers.csv", &markers, MARKER_COLUMNS.len()),
        ("frames.csv", &frames, FRAME_COLUMNS.len() + 2),
    ] {
        assert!(text.ends_with('\n'), "{name} ends mid-line");
        for line in text.lines() {
            assert_eq!(line.split(',').count(), cells, "{name}: cut line '{line}'");
        }
    }
    let mut per_frame = BTreeMap::new();
    for line in markers.lines().skip(1) {
        *per_frame
            .entry(line.split(',').next().unwrap().parse().unwrap())
            .or_insert(0) += 1;
    }
    let in_frames = frames
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    (per_frame, in_frames)
}

/// Starts `track` on `rec`, waits until a few frames are written, sends `signal`, waits for the end.
fn interrupted_run(rec: &Path, out: &Path, signal: &str) -> String {
    let child = gelstereo_command()
        .args([
            "track",
            "--quiet",
            "--method",
            "blob",
            "--overlay-every",
            "2",
            "--ply-every",
            "3",
            "--out",
        ])
        .arg(out)
        .arg(rec)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while std::fs::read_to_string(out.join("frames.csv")).map_or(0, |t| t.lines().count()) < 6 {
        assert!(started.elapsed() < Duration::from_secs(60), "no frames written");
        std::thread::sleep(Duration::from_millis(20));
    }
    let kill = std::process::Command::new("kill")
        .args([signal, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let output = child.wait_with_output().unwrap();
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn interrupted_runs_leave_whole_tables_and_a_new_run_replaces_every_file_of_the_old() {
    let dir = tempfile::tempdir().unwrap();
    let rec = long_recording(dir.path(), 400);
    for signal in ["-INT", "-TERM"] {
        let out = dir.path().join(format!("out{signal}"));
        let err = interrupted_run(&rec, &out, signal);
        assert!(err.contains("interrupted"), "{signal}: {err}");
        let (markers, frames) = table_frames(&out);
        assert!(frames.len() < 400, "{signal}: the run was not interrupted");
        assert_eq!(
            markers.keys().copied().collect::<BTreeSet<_>>(),
            frames,
            "{signal}"
        );
        assert!(markers.values().all(|n| *n == 529), "{signal}");
        for plot in ["contact_area", "max_depth", "slip"] {
            assert!(
                out.join(format!("plots/{plot}.png")).is_file(),
                "{signal}: {plot} missing"
            );
        }
    }
    let out = dir.path().join("out-KILL");
    interrupted_run(&rec, &out, "-KILL");
    let (markers, frames) = table_frames(&out);
    let marker_frames: BTreeSet<u32> = markers.keys().copied().collect();
    assert!(frames.is_subset(&marker_frames) && marker_frames.len() <= frames.len() + 1);
    // Every overlay under its final name decodes (written whole, then renamed).
    for entry in std::fs::read_dir(out.join("overlays")).unwrap() {
        let path = entry.unwrap().path();
        if !path.file_name().unwrap().to_str().unwrap().starts_with('.') {
            let img =
                opencv::imgcodecs::imread(path.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
            assert!(
                opencv::core::MatTraitConst::rows(&img) > 0,
                "{} cut",
                path.display()
            );
        }
    }
    // A shorter run into the same folder leaves none of the killed run's files.
    track_ok(&[
        "--method",
        "blob",
        "--max-frames",
        "3",
        "--out",
        out.to_str().unwrap(),
        sample().to_str().unwrap(),
    ]);
    let (markers, frames) = table_frames(&out);
    assert_eq!(frames, (0..3).collect());
    assert_eq!(markers.len(), 3);
    let overlays: Vec<String> = std::fs::read_dir(out.join("overlays"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert!(overlays.iter().all(|n| n.ends_with("000000.png")), "{overlays:?}");
    assert!(!out.join("ply/cloud_000003.ply").exists());
}

#[test]
fn a_folder_gelstereo_did_not_write_is_refused_and_force_keeps_the_users_files() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("mine");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("notes.txt"), "keep me").unwrap();
    let args = [
        "--method",
        "blob",
        "--max-frames",
        "2",
        "--out",
        out.to_str().unwrap(),
    ];
    let refused = gelstereo_command()
        .args(["track", "--quiet"])
        .args(args)
        .arg(sample())
        .output()
        .unwrap();
    assert!(
        !refused.status.success() && text(&refused).contains("--force"),
        "{}",
        text(&refused)
    );
    assert!(!out.join("markers.csv").exists());
    let sample = sample();
    let mut forced: Vec<&str> = args.to_vec();
    forced.push("--force");
    forced.push(sample.to_str().unwrap());
    track_ok(&forced);
    assert!(out.join("markers.csv").is_file());
    assert_eq!(std::fs::read_to_string(out.join("notes.txt")).unwrap(), "keep me");
}

/// `track` into `out` with tables and plots only.
fn track_into(out: &Path, input: &Path) -> std::process::Output {
    gelstereo(&[
        "track",
        "--quiet",
        "--no-ply",
        "--overlay-every",
        "0",
        "--out",
        out.to_str().unwrap(),
        input.to_str().unwrap(),
    ])
}

#[test]
fn outputs_never_clobber_inputs_linked_folders_special_files_or_a_running_run() {
    let dir = tempfile::tempdir().unwrap();
    // A copy of the sample as the recording, with its truth table (a file outputs must not touch).
    let rec = sample_copy(dir.path(), 40);
    std::fs::copy(sample().join("markers.csv"), rec.join("markers.csv")).unwrap();
    let truth = std::fs::read(rec.join("markers.csv")).unwrap();
    // An output folder that is, or lies inside, the input is refused, even with --force.
    for out in [rec.clone(), rec.join("track")] {
        let run = gelstereo(&[
            "track",
            "--quiet",
            "--force",
            "--out",
            out.to_str().unwrap(),
            rec.to_str().unwrap(),
        ]);
        assert!(
            !run.status.success() && text(&run).contains("overlaps the input"),
            "{}",
            text(&run)
        );
    }
    assert_eq!(
        std::fs::read(rec.join("markers.csv")).unwrap(),
        truth,
        "the recording is intact"
    );

    // A folder linked from inside the output folder is not written through, and its files stay.
    let out = dir.path().join("out");
    assert!(track_into(&out, &rec).status.success());
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir_all(&elsewhere).unwrap();
    std::fs::write(elsewhere.join("slip.png"), "the user's").unwrap();
    std::fs::remove_dir_all(out.join("plots")).unwrap();
    std::os::unix::fs::symlink(&elsewhere, out.join("plots")).unwrap();
    let run = track_into(&out, &rec);
    assert!(
        !run.status.success() && text(&run).contains("symbolic link"),
        "{}",
        text(&run)
    );
    assert_eq!(
        std::fs::read_to_string(elsewhere.join("slip.png")).unwrap(),
        "the user's"
    );
    std::fs::remove_file(out.join("plots")).unwrap();

    // A second run into a folder another run is writing is refused (the lock is held here as a
    // running track would hold it).
    let lock = std::fs::File::open(out.join(".gelstereo-lock")).unwrap();
    lock.lock().unwrap();
    let run = track_into(&out, &rec);
    assert!(
        !run.status.success() && text(&run).contains("another gelstereo run"),
        "{}",
        text(&run)
    );
    drop(lock);
    assert!(
        track_into(&out, &rec).status.success(),
        "the lock goes with the run"
    );

    // A file output that is a device or a link is not replaced; a stream that fails names its file.
    let link = dir.path().join("detections.csv");
    std::os::unix::fs::symlink(rec.join("markers.csv"), &link).unwrap();
    let image = rec.join("left/000000.jpg");
    for target in [link.as_path(), Path::new("/dev/null")] {
        let run = gelstereo(&[
            "detect",
            "--out",
            target.to_str().unwrap(),
            image.to_str().unwrap(),
        ]);
        assert!(
            !run.status.success() && text(&run).contains("not a regular file"),
            "{}",
            text(&run)
        );
    }
    assert_eq!(std::fs::read(rec.join("markers.csv")).unwrap(), truth);
    let run = gelstereo(&[
        "track",
        "--quiet",
        "--no-ply",
        "--jsonl",
        "/dev/full",
        rec.to_str().unwrap(),
    ]);
    assert!(
        !run.status.success() && text(&run).contains("/dev/full"),
        "{}",
        text(&run)
    );
}
