//! End-to-end tests of `gelstereo detect`, `eval` and `bench` on small images drawn here (dark discs
//! at known centres) and the tiny ONNX fixtures of `data/fixtures/onnx/` (random weights: these tests
//! check plumbing, formats and errors; accuracy is checked in gelstereo-markers against Python values).

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::path::{Path, PathBuf};

#[path = "../../../tests/common/mod.rs"]
mod common;
use common::{fails_with, gelstereo, text};

use opencv::core::{CV_8UC3, Mat, Point, Scalar, Vector};
use opencv::{imgcodecs, imgproc};

const PITCH_PX: i32 = 20;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/fixtures/onnx")
}

/// A 160x120 bright image with dark discs (radius 4) at `centres`.
fn dots(centres: &[(i32, i32)]) -> Mat {
    let mut img =
        Mat::new_rows_cols_with_default(120, 160, CV_8UC3, Scalar::new(200.0, 210.0, 220.0, 0.0)).unwrap();
    for &(x, y) in centres {
        imgproc::circle(
            &mut img,
            Point::new(x, y),
            4,
            Scalar::all(40.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
    }
    img
}

/// The 7 x 5 lattice of the test images, pitch 20 px, starting at (20, 20).
fn lattice() -> Vec<(i32, i32)> {
    (0..5)
        .flat_map(|r| (0..7).map(move |c| (20 + c * PITCH_PX, 20 + r * PITCH_PX)))
        .collect()
}

fn write(path: &Path, img: &Mat) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    assert!(imgcodecs::imwrite(path.to_str().unwrap(), img, &Vector::new()).unwrap());
}

fn marknet_args(fx: &Path) -> Vec<String> {
    vec![
        "--marknet".into(),
        fx.join("marknet_tiny.onnx").display().to_string(),
        "--mre".into(),
        fx.join("mre_tiny.onnx").display().to_string(),
    ]
}

#[test]
fn detect_writes_the_csv_contract_and_overlays() {
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("a.png");
    write(&img, &dots(&lattice()));
    let csv = dir.path().join("out/found.csv");
    let ov = dir.path().join("ov");
    let img_s = img.display().to_string();
    let out = gelstereo(&[
        "detect",
        "--method",
        "blob",
        "--out",
        csv.to_str().unwrap(),
        "--overlay",
        ov.to_str().unwrap(),
        &img_s,
    ]);
    assert!(out.status.success(), "{}", text(&out));
    let body = std::fs::read_to_string(&csv).unwrap();
    let mut lines = body.lines();
    assert_eq!(lines.next(), Some("image,x,y,confidence"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), lattice().len(), "one row per disc:\n{body}");
    for r in &rows {
        assert_eq!(r[0], img_s, "image column is the path as given");
        let (x, y): (f64, f64) = (r[1].parse().unwrap(), r[2].parse().unwrap());
        let near = lattice()
            .iter()
            .any(|&(cx, cy)| (x - f64::from(cx)).hypot(y - f64::from(cy)) < 0.5);
        assert!(near, "({x}, {y}) is not at a disc centre");
    }
    assert!(ov.join("a.png").is_file(), "overlay written");

    // A stereo recording: rows for both views, named by their files.
    let rec = dir.path().join("rec");
    write(&rec.join("left/000000.png"), &dots(&lattice()));
    write(&rec.join("right/000000.png"), &dots(&lattice()[..10]));
    let mut args: Vec<String> = vec!["detect".into()];
    args.extend(marknet_args(&fixtures()));
    args.push(rec.display().to_string());
    let out = gelstereo(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.status.success(), "{}", text(&out));
    let t = String::from_utf8_lossy(&out.stdout);
    assert!(t.starts_with("image,x,y,confidence\n"), "{t}");
    for line in t.lines().skip(1) {
        assert!(
            line.contains("left/000000.png,") || line.contains("right/000000.png,"),
            "{line}"
        );
    }
}

#[test]
fn bad_inputs_fail_with_clear_messages() {
    let dir = tempfile::tempdir().unwrap();
    let fx = fixtures();
    fails_with(&["detect", "--method", "blob"], &["no input images"]);
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    fails_with(
        &["detect", "--method", "blob", empty.to_str().unwrap()],
        &["folder holds no images"],
    );

    let corrupt = dir.path().join("corrupt.png");
    std::fs::write(&corrupt, b"\x89PNG\r\n\x1a\n garbage").unwrap();
    fails_with(
        &["detect", "--method", "blob", corrupt.to_str().unwrap()],
        &["corrupt.png", "cannot decode"],
    );
    fails_with(
        &["detect", "--method", "blob", "/no/such/image.png"],
        &["/no/such/image.png"],
    );

    let thin = dir.path().join("thin.png");
    write(
        &thin,
        &Mat::new_rows_cols_with_default(20, 200, CV_8UC3, Scalar::all(90.0)).unwrap(),
    );
    let mut args: Vec<String> = vec!["detect".into()];
    args.extend(marknet_args(&fx));
    args.push(thin.display().to_string());
    fails_with(
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        &["thin.png", "200x20", "aspect ratio"],
    );
    let tiny = dir.path().join("tiny.png");
    write(
        &tiny,
        &Mat::new_rows_cols_with_default(8, 8, CV_8UC3, Scalar::all(90.0)).unwrap(),
    );
    fails_with(
        &["detect", "--method", "blob", tiny.to_str().unwrap()],
        &["tiny.png", "at least 16x16"],
    );

    // A model whose metadata breaks the contract, and a missing model.
    let mut bytes = std::fs::read(fx.join("marknet_tiny.onnx")).unwrap();
    let at = bytes
        .windows(19)
        .position(|w| w == b"gelstereo-marknet/1")
        .unwrap();
    bytes[at + 18] = b'9';
    let bad = dir.path().join("bad_meta.onnx");
    std::fs::write(&bad, &bytes).unwrap();
    let img = dir.path().join("ok.png");
    write(&img, &dots(&lattice()));
    fails_with(
        &[
            "detect",
            "--method",
            "marknet",
            "--marknet",
            bad.to_str().unwrap(),
            img.to_str().unwrap(),
        ],
        &["bad_meta.onnx", "'contract'", "gelstereo-marknet/1"],
    );
    fails_with(
        &[
            "detect",
            "--models",
            dir.path().to_str().unwrap(),
            img.to_str().unwrap(),
        ],
        &["mre.onnx", "marknet-mre"],
    );
    fails_with(
        &["detect", "--method", "yolo3", img.to_str().unwrap()],
        &["yolo3"],
    );
}

/// A two-frame dataset in the layout of `gelstereo simulate`: the lattice is drawn except for two
/// markers (the blob baseline cannot find them: they are the hard split), and the bottom row is in
/// contact.
fn tiny_dataset(root: &Path) {
    let exp = root.join("test/exp_0000");
    let all = lattice();
    let missing = [all[8], all[20]];
    let drawn: Vec<(i32, i32)> = all.iter().copied().filter(|p| !missing.contains(p)).collect();
    let mut csv = String::from(
        "frame,row,col,x_left,y_left,x_right,y_right,X_mm,Y_mm,Z_mm,dX_mm,dY_mm,dZ_mm,status,visible_left,visible_right,in_contact\n",
    );
    for frame in 0..2 {
        for side in ["left", "right"] {
            write(&exp.join(side).join(format!("{frame:06}.png")), &dots(&drawn));
        }
        for (k, &(x, y)) in all.iter().enumerate() {
            let (row, col) = (k / 7, k % 7);
            let contact = u8::from(row == 4);
            csv.push_str(&format!(
                "{frame},{row},{col},{x},{y},{x},{y},,,,,,,,1,1,{contact}\n"
            ));
        }
    }
    std::fs::write(exp.join("markers.csv"), csv).unwrap();
}

#[test]
fn eval_prints_and_writes_table_one() {
    let dir = tempfile::tempdir().unwrap();
    tiny_dataset(dir.path());
    let out_dir = dir.path().join("eval");
    let mut args: Vec<String> = vec![
        "eval".into(),
        "--dataset".into(),
        dir.path().display().to_string(),
        "--methods".into(),
        "blob,marknet-mre".into(),
        "--out".into(),
        out_dir.display().to_string(),
    ];
    args.extend(marknet_args(&fixtures()));
    let out = gelstereo(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let t = text(&out);
    assert!(out.status.success(), "{t}");
    // r = 0.25 x pitch 20 = 5 px.
    assert!(t.contains("median 5.00 px"), "{t}");
    let csv = std::fs::read_to_string(out_dir.join("table1.csv")).unwrap();
    let row = |split: &str, method: &str| -> Vec<String> {
        csv.lines()
            .find(|l| l.starts_with(&format!("{split},{method},")))
            .unwrap_or_else(|| panic!("no {split},{method} row in\n{csv}"))
            .split(',')
            .map(str::to_owned)
            .collect()
    };
    // 2 frames x 2 views: 33 found markers each are easy, the 2 undrawn ones hard, 7 in contact.
    let easy = row("easy", "blob");
    assert_eq!(
        (easy[3].as_str(), easy[5].as_str(), easy[6].as_str()),
        ("1.000000", "132", "132"),
        "{csv}"
    );
    let hard = row("hard", "blob");
    assert_eq!((hard[3].as_str(), hard[5].as_str()), ("0.000000", "8"), "{csv}");
    assert_eq!(row("contact", "blob")[5], "28");
    assert_eq!(row("all", "marknet-mre")[5], "140");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("table1.json")).unwrap()).unwrap();
    assert_eq!(json["views"], 4);
    assert_eq!(json["radius_px"]["median"], 5.0);

    fails_with(
        &[
            "eval",
            "--dataset",
            dir.path().to_str().unwrap(),
            "--split",
            "val",
        ],
        &["val"],
    );
}

#[test]
fn bench_reports_the_ratio_to_blob() {
    let dir = tempfile::tempdir().unwrap();
    let img = dir.path().join("a.png");
    write(&img, &dots(&lattice()));
    let json = dir.path().join("bench.json");
    let out = gelstereo(&[
        "bench",
        "--methods",
        "blob",
        "--runs",
        "3",
        "--warmup",
        "1",
        "--out",
        json.to_str().unwrap(),
        img.to_str().unwrap(),
    ]);
    let t = text(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains("blob") && t.contains("1.00x"), "{t}");
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["results"][0]["markers_per_image"], 35.0);
    fails_with(&["bench", "--methods", "blob"], &["no images to benchmark"]);
}

/// How far `p` lies inside the outermost pixel centres of a 320 x 240 image, px (negative outside).
fn inside_px(p: (f64, f64)) -> f64 {
    p.0.min(p.1).min(319.0 - p.0).min(239.0 - p.1)
}

/// 320 x 240 gels whose lattices (pitch 29 px, dots of radius 5.5) the border cuts on every side at
/// another depth: left columns centred 0.3-3 px inside or 1-2 px outside, top rows likewise, right
/// columns and bottom rows cut or past the edge. By default, with no option, `detect` reports every dot
/// whose centre lies inside the image, those the border cuts within 0.5 px of their centre however
/// much of them it cuts off (whole dots within 1.5 px), and none whose centre lies outside (more than 0.75 px beyond the outermost pixel centres: the
/// image span ends 0.5 px beyond them). `--pad-border 8`, kept for old scripts, changes nothing.
#[test]
fn detect_places_dots_cut_by_the_border_and_reports_none_centred_outside() {
    let (pitch, radius) = (29.0, 5.5);
    let origins = [
        (1.5, -2.0),
        (0.3, 3.0),
        (-1.0, 1.0),
        (3.0, 0.6),
        (-2.0, -1.2),
        (2.2, 2.0),
    ];
    let dir = tempfile::tempdir().unwrap();
    let mut truth = Vec::new();
    for (k, &(x0, y0)) in origins.iter().enumerate() {
        let centres: Vec<(f64, f64)> = (0..10)
            .flat_map(|r| (0..13).map(move |c| (x0 + pitch * f64::from(c), y0 + pitch * f64::from(r))))
            .filter(|&p| inside_px(p) > -radius)
            .collect();
        let mut img =
            Mat::new_rows_cols_with_default(240, 320, CV_8UC3, Scalar::new(190.0, 180.0, 170.0, 0.0))
                .unwrap();
        for &(x, y) in &centres {
            // Drawn at 1/16 px, as the dots of the borders test.
            let at = Point::new((x * 16.0).round() as i32, (y * 16.0).round() as i32);
            imgproc::circle(&mut img, at, 88, Scalar::all(45.0), -1, imgproc::LINE_AA, 4).unwrap();
        }
        let name = format!("gel{k}.png");
        write(&dir.path().join(&name), &img);
        truth.push((name, centres));
    }
    let found = |extra: &[&str]| -> Vec<(String, f64, f64)> {
        let mut args = vec!["detect", "--threads", "1"];
        args.extend_from_slice(extra);
        args.push(dir.path().to_str().unwrap());
        let out = gelstereo(&args);
        assert!(out.status.success(), "{}", text(&out));
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .skip(1)
            .map(|l| {
                let f: Vec<&str> = l.split(',').collect();
                let name = Path::new(f[0])
                    .file_name()
                    .unwrap()
                    .to_string_lossy()
                    .into_owned();
                (name, f[1].parse().unwrap(), f[2].parse().unwrap())
            })
            .collect()
    };
    let plain = found(&[]);
    let (mut cut, mut outside) = (0, 0);
    for (name, centres) in &truth {
        let mine: Vec<(f64, f64)> = plain
            .iter()
            .filter(|d| &d.0 == name)
            .map(|d| (d.1, d.2))
            .collect();
        let nearest = |c: (f64, f64)| {
            mine.iter()
                .map(|p| (p.0 - c.0).hypot(p.1 - c.1))
                .fold(f64::INFINITY, f64::min)
        };
        for &c in centres {
            let inside = inside_px(c);
            if inside >= 0.0 {
                // Whole dots are the network's to place (within 1.5 px, as in the borders test).
                let tolerance = if inside < radius { 0.5 } else { 1.5 };
                cut += usize::from(inside < radius);
                assert!(
                    nearest(c) <= tolerance,
                    "{name}: dot {c:?} ({inside:.1} px inside) missed: {mine:?}"
                );
            } else if inside < -0.75 {
                outside += 1;
                assert!(
                    nearest(c) > 0.25 * pitch,
                    "{name}: dot {c:?} centred {:.1} px outside reported: {mine:?}",
                    -inside
                );
            }
        }
        // Nothing else: every report is a dot of the lattice.
        for p in &mine {
            assert!(
                centres.iter().any(|c| (p.0 - c.0).hypot(p.1 - c.1) <= 1.5),
                "{name}: {p:?} is no dot"
            );
        }
    }
    assert!(
        cut >= 60 && outside >= 60,
        "{cut} cut dots inside, {outside} outside"
    );
    let old = gelstereo(&[
        "detect",
        "--threads",
        "1",
        "--pad-border",
        "8",
        dir.path().to_str().unwrap(),
    ]);
    assert!(old.status.success(), "{}", text(&old));
    assert!(text(&old).contains("--pad-border 8 is ignored"), "{}", text(&old));
    let padded = found(&["--pad-border", "8"]);
    assert_eq!(padded, plain);
    fails_with(
        &["detect", "--pad-border", "1000", dir.path().to_str().unwrap()],
        &["--pad-border", "0..=256"],
    );
}
