//! End-to-end tests of `gelstereo reconstruct` on a small recording made here by `gelstereo simulate`
//! (reference look, 6 frames): ground-truth 2-D positions through indexing, pairing and
//! triangulation, checked against the simulator's 3-D truth; the blob localizer on one stereo pair;
//! and the errors a user meets (missing calibration key, image size, zero baseline, empty views).

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::path::{Path, PathBuf};

#[path = "../../../tests/common/mod.rs"]
mod common;
use common::{fails_with, gelstereo, text};

fn ok(args: &[&str]) -> String {
    let out = gelstereo(args);
    let t = text(&out);
    assert!(out.status.success(), "{args:?} failed:\n{t}");
    t
}

/// Simulates one 6-frame experiment into `root` and returns its recording folder.
fn simulate(root: &Path) -> PathBuf {
    let out = root.join("sim");
    let s = out.to_str().unwrap();
    ok(&[
        "simulate",
        "--out",
        s,
        "--experiments",
        "1",
        "--frames-per-experiment",
        "6",
        "--randomization",
        "off",
        "--quiet",
    ]);
    for split in ["train", "val", "test"] {
        let dir = out.join(split).join("exp_0000");
        if dir.is_dir() {
            return dir;
        }
    }
    panic!("no exp_0000 in {}", out.display());
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn reconstruct_from_ground_truth_matches_the_simulator_and_reports_bad_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = simulate(tmp.path());
    let calib = rec.join("calib.yaml");
    let out = tmp.path().join("out");
    let log = ok(&[
        "reconstruct",
        "--calib",
        s(&calib),
        "--out",
        s(&out),
        "--from-ground-truth",
        "--evaluate",
        s(&rec),
    ]);
    assert!(log.contains("23x23 lattice"), "{log}");

    // markers.csv: the docs/design.md header and one row per marker and frame, displacement and
    // contact mechanics empty.
    let csv = std::fs::read_to_string(out.join("markers.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "frame,row,col,x_left,y_left,x_right,y_right,X_mm,Y_mm,Z_mm,dX_mm,dY_mm,dZ_mm,status,pressure_kPa,in_contact,slipping,\
         X_gel_mm,Y_gel_mm,Z_gel_mm,dX_gel_mm,dY_gel_mm,dZ_gel_mm"
    );
    let rows: Vec<&str> = lines.collect();
    assert_eq!(rows.len(), 6 * 529);
    assert!(
        rows[0].starts_with("0,0,0,") && rows[0].ends_with(",,,,"),
        "{}",
        rows[0]
    );

    // Against the truth: the done-when figures (the truth's own 2-D positions are exact, so the
    // 3-D error is the geometry's numerical error).
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("evaluation.json")).unwrap()).unwrap();
    let all = &eval["all"];
    assert!(all["rmse_mm"].as_f64().unwrap() <= 0.02, "{all}");
    assert!(all["coverage"].as_f64().unwrap() >= 0.99, "{all}");
    assert_eq!(all["wrong_pairs"], 0, "{all}");
    assert!(all["index_consistency"].as_f64().unwrap() >= 0.995, "{all}");

    // No pair was rejected: the rejection table has its header only.
    let rejected = std::fs::read_to_string(out.join("rejected_pairs.csv")).unwrap();
    assert_eq!(rejected, "frame,row,col,reason\n");

    // One PLY per frame with every marker of its markers.csv rows, readable back with its ids
    // (under the gross slip of frame 4, 0.9 mm deep, the surface dragged 2 mm, a marker or two of
    // the contact may go unindexed: coverage is checked above).
    for f in 0..6 {
        let cloud = gelstereo::io::ply::read_marker_cloud(&out.join(format!("ply/{f:06}.ply"))).unwrap();
        let placed = rows
            .iter()
            .filter(|r| r.starts_with(&format!("{f},")) && !r.split(',').nth(7).unwrap_or("").is_empty())
            .count();
        assert_eq!(cloud.len(), placed);
        assert!(cloud.len() >= 527, "frame {f}: {}", cloud.len());
        assert!(
            cloud
                .iter()
                .all(|p| p.position_mm[2] > 0.0 && p.reprojection_error_px < 0.01)
        );
    }

    // The same with a localizer's imperfections simulated: 0.3 px noise, 10% misses, 5 dust points
    // per view. Coverage drops to about 0.9^2 (a marker must be seen in both views), the 3-D error
    // grows with the noise (~0.2 mm per px on this rig), ids and pairs stay right.
    let noisy = tmp.path().join("noisy");
    let args = [
        "--gt-noise-px",
        "0.3",
        "--gt-missing",
        "0.1",
        "--gt-dust",
        "5",
        "--seed",
        "3",
        "--no-ply",
    ];
    let mut cmd = vec![
        "reconstruct",
        "--calib",
        s(&calib),
        "--out",
        s(&noisy),
        "--from-ground-truth",
        "--evaluate",
    ];
    cmd.extend(args);
    cmd.push(s(&rec));
    ok(&cmd);
    let eval: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(noisy.join("evaluation.json")).unwrap()).unwrap();
    let all = &eval["all"];
    let coverage = all["coverage"].as_f64().unwrap();
    assert!((0.7..0.9).contains(&coverage), "{all}");
    let rmse = all["rmse_mm"].as_f64().unwrap();
    assert!((0.01..0.2).contains(&rmse), "{all}");
    assert!(all["index_consistency"].as_f64().unwrap() >= 0.995, "{all}");
    assert!(all["wrong_pair_rate"].as_f64().unwrap() <= 0.005, "{all}");

    // A tight reprojection bound rejects noisy pairs: flagged with their reason, no 3-D position.
    let tight = tmp.path().join("tight");
    let mut cmd = vec![
        "reconstruct",
        "--calib",
        s(&calib),
        "--out",
        s(&tight),
        "--from-ground-truth",
    ];
    cmd.extend([
        "--gt-noise-px",
        "0.3",
        "--max-reprojection-px",
        "0.2",
        "--no-ply",
        s(&rec),
    ]);
    ok(&cmd);
    let rejected = std::fs::read_to_string(tight.join("rejected_pairs.csv")).unwrap();
    let first = rejected.lines().nth(1).expect("some pairs rejected");
    assert!(
        first.contains("triangulation: reprojection error") && first.split(',').count() == 4,
        "{first}"
    );
    let (frame, row, col) = {
        let c: Vec<&str> = first.split(',').collect();
        (c[0].to_owned(), c[1].to_owned(), c[2].to_owned())
    };
    let csv = std::fs::read_to_string(tight.join("markers.csv")).unwrap();
    let line = csv
        .lines()
        .find(|l| l.starts_with(&format!("{frame},{row},{col},")))
        .unwrap();
    let cells: Vec<&str> = line.split(',').collect();
    assert!(
        !cells[3].is_empty() && !cells[5].is_empty() && cells[7].is_empty(),
        "{line}"
    );

    // A missing calibration key is named.
    let yaml = std::fs::read_to_string(&calib).unwrap();
    let t_at = yaml.find("\nT:").unwrap();
    let no_t = tmp.path().join("no_t.yaml");
    let size_at = yaml.find("image_width").unwrap();
    std::fs::write(&no_t, format!("{}{}", &yaml[..t_at + 1], &yaml[size_at..])).unwrap();
    fails_with(
        &[
            "reconstruct",
            "--calib",
            s(&no_t),
            "--out",
            s(&out),
            "--from-ground-truth",
            s(&rec),
        ],
        &["'T'"],
    );

    // A calibration for another image size.
    let wide = tmp.path().join("wide.yaml");
    std::fs::write(&wide, yaml.replace("image_width: 640", "image_width: 800")).unwrap();
    fails_with(
        &[
            "reconstruct",
            "--calib",
            s(&wide),
            "--out",
            s(&out),
            "--from-ground-truth",
            s(&rec),
        ],
        &["image size mismatch", "800x480", "640x480"],
    );

    // Degenerate geometry: zero baseline.
    let t_block = &yaml[t_at..];
    let data_at = t_block.find("data:").unwrap();
    let zero_t = format!(
        "{}{}data: [ 0., 0., 0. ]\n{}",
        &yaml[..t_at],
        &t_block[..data_at],
        {
            let rest = &t_block[data_at..];
            &rest[rest.find(']').unwrap() + 2..]
        }
    );
    let flat = tmp.path().join("flat.yaml");
    std::fs::write(&flat, zero_t).unwrap();
    fails_with(
        &[
            "reconstruct",
            "--calib",
            s(&flat),
            "--out",
            s(&out),
            "--from-ground-truth",
            s(&rec),
        ],
        &["baseline"],
    );

    // Empty views: two blank images of the right size give a clear error, not NaN rows.
    let blank = |name: &str| {
        let p = tmp.path().join(name);
        let img = opencv::core::Mat::new_rows_cols_with_default(
            480,
            640,
            opencv::core::CV_8UC3,
            opencv::core::Scalar::all(255.0),
        )
        .unwrap();
        opencv::imgcodecs::imwrite(s(&p), &img, &opencv::core::Vector::new()).unwrap();
        p
    };
    let (l, r) = (blank("blank_l.png"), blank("blank_r.png"));
    fails_with(
        &[
            "reconstruct",
            "--method",
            "blob",
            "--calib",
            s(&calib),
            "--out",
            s(&out),
            s(&l),
            s(&r),
        ],
        &["reference frame", "no detections"],
    );
}

#[test]
fn reconstruct_runs_the_blob_localizer_on_one_stereo_pair() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = simulate(tmp.path());
    let out = tmp.path().join("blob");
    let (l, r) = (rec.join("left/000000.png"), rec.join("right/000000.png"));
    ok(&[
        "reconstruct",
        "--method",
        "blob",
        "--calib",
        s(&rec.join("calib.yaml")),
        "--out",
        s(&out),
        s(&l),
        s(&r),
    ]);
    let cloud = gelstereo::io::ply::read_marker_cloud(&out.join("ply/000000.ply")).unwrap();
    // The tuned blob detector on the reference look finds nearly every marker (>= 95%).
    assert!(cloud.len() >= 500, "{} markers", cloud.len());
    assert!(cloud.iter().all(|p| p.reprojection_error_px <= 2.0));
}

#[test]
fn reconstruct_reads_a_side_by_side_stereo_video() {
    use opencv::core::{Mat, Size, Vector};
    use opencv::prelude::*;
    use opencv::{core, imgcodecs, videoio};
    let tmp = tempfile::tempdir().unwrap();
    let rec = simulate(tmp.path());
    let video = tmp.path().join("sbs.avi");
    let fourcc = videoio::VideoWriter::fourcc('M', 'J', 'P', 'G').unwrap();
    let mut writer = videoio::VideoWriter::new(s(&video), fourcc, 10.0, Size::new(1280, 480), true).unwrap();
    assert!(writer.is_opened().unwrap());
    for f in 0..3 {
        let read = |side: &str| {
            imgcodecs::imread(
                s(&rec.join(format!("{side}/{f:06}.png"))),
                imgcodecs::IMREAD_COLOR,
            )
            .unwrap()
        };
        let mut both = Mat::default();
        let halves: Vector<Mat> = Vector::from_iter([read("left"), read("right")]);
        core::hconcat(&halves, &mut both).unwrap();
        writer.write(&both).unwrap();
    }
    writer.release().unwrap();
    let out = tmp.path().join("video");
    ok(&[
        "reconstruct",
        "--method",
        "blob",
        "--calib",
        s(&rec.join("calib.yaml")),
        "--out",
        s(&out),
        s(&video),
    ]);
    let csv = std::fs::read_to_string(out.join("markers.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 3 * 529);
    // MJPG compression moves the blobs a little; nearly every marker is still reconstructed.
    let cloud = gelstereo::io::ply::read_marker_cloud(&out.join("ply/000002.ply")).unwrap();
    assert!(cloud.len() >= 500, "{} markers", cloud.len());
}

#[test]
fn reconstruct_writes_only_into_its_own_folder_apart_from_the_recording() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = simulate(tmp.path());
    let calib = rec.join("calib.yaml");
    let truth = std::fs::read(rec.join("markers.csv")).unwrap();
    let run = |out: &Path, force: bool| {
        let mut args = vec![
            "reconstruct",
            "--calib",
            s(&calib),
            "--out",
            s(out),
            "--from-ground-truth",
        ];
        if force {
            args.push("--force");
        }
        args.push(s(&rec));
        gelstereo(&args)
    };
    // The recording itself, or a folder inside it: refused, the recording's truth intact.
    for out in [rec.clone(), rec.join("reconstructed")] {
        let r = run(&out, true);
        assert!(
            !r.status.success() && text(&r).contains("overlaps the input"),
            "{}",
            text(&r)
        );
    }
    assert_eq!(std::fs::read(rec.join("markers.csv")).unwrap(), truth);
    // A folder holding a user's markers.csv: refused without --force, the file untouched.
    let mine = tmp.path().join("mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("markers.csv"), "the user's").unwrap();
    let r = run(&mine, false);
    assert!(
        !r.status.success() && text(&r).contains("--force"),
        "{}",
        text(&r)
    );
    assert_eq!(
        std::fs::read_to_string(mine.join("markers.csv")).unwrap(),
        "the user's"
    );
    // Its own folder: written again and again without --force.
    let out = tmp.path().join("out");
    assert!(run(&out, false).status.success());
    assert!(run(&out, false).status.success());
}
