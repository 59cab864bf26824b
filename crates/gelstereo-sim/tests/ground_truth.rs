//! Ground truth against OpenCV: every frame's 3-D marker centres, projected with OpenCV's
//! `projectPoints` through the `calib.yaml` written next to them, land on the 2-D ground truth to
//! < 0.01 px; 529 markers per frame on the reference sensor; frame 0 is the no-contact reference.
//! Also: same seed gives the same bytes whatever rayon's thread count, and output folder rules.
#![allow(clippy::unwrap_used)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use gelstereo_core::CsvTable;
use gelstereo_sim::dataset::{DatasetConfig, Randomization, write_dataset};
use opencv::calib3d;
use opencv::core::{
    FileNodeTraitConst, FileStorage, FileStorageTraitConst, Mat, MatTraitConst, Point2d, Point3d, Vector,
};

struct Calib {
    k: [Mat; 2],
    d: [Mat; 2],
    r: Mat,
    t: Mat,
    size: (i32, i32),
}

fn read_calib(path: &Path) -> Calib {
    let fs = FileStorage::new_def(path.to_string_lossy().as_ref(), opencv::core::FileStorage_READ).unwrap();
    let m = |k: &str| fs.get(k).unwrap().mat().unwrap();
    let i = |k: &str| fs.get(k).unwrap().to_i32().unwrap();
    Calib {
        k: [m("K1"), m("K2")],
        d: [m("D1"), m("D2")],
        r: m("R"),
        t: m("T"),
        size: (i("image_width"), i("image_height")),
    }
}

fn recordings(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for split in ["train", "val", "test"] {
        let Ok(rd) = std::fs::read_dir(root.join(split)) else {
            continue;
        };
        for e in rd {
            out.push(e.unwrap().path());
        }
    }
    out.sort();
    out
}

/// Returns the largest reprojection error (px) over the recording, and checks the table's shape.
fn check_recording(dir: &Path, expect_markers: Option<usize>) -> f64 {
    let c = read_calib(&dir.join("calib.yaml"));
    let table = CsvTable::read(&dir.join("markers.csv")).unwrap();
    let frames_table = CsvTable::read(&dir.join("frames.csv")).unwrap();
    assert_eq!(
        frames_table.cell(0, "slip").unwrap(),
        "no_contact",
        "{}: frame 0 must be no-contact",
        dir.display()
    );
    let mut by_frame: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
    for r in 0..table.len() {
        by_frame
            .entry(table.value(r, "frame", "frame").unwrap())
            .or_default()
            .push(r);
    }
    assert_eq!(by_frame.len(), frames_table.len());
    let mut rvec_r = Mat::default();
    calib3d::rodrigues_def(&c.r, &mut rvec_r).unwrap();
    let zero = Mat::from_slice(&[0.0f64, 0.0, 0.0]).unwrap().try_clone().unwrap();
    let mut worst: f64 = 0.0;
    for (frame, rows) in &by_frame {
        if let Some(n) = expect_markers {
            assert_eq!(rows.len(), n, "frame {frame}");
        }
        let mut obj = Vector::<Point3d>::new();
        let mut gt: [Vec<(f64, f64)>; 2] = [Vec::new(), Vec::new()];
        for &r in rows {
            let v = |k: &str| table.opt_f64(r, k).unwrap().unwrap();
            obj.push(Point3d::new(v("X_mm"), v("Y_mm"), v("Z_mm")));
            gt[0].push((v("x_left"), v("y_left")));
            gt[1].push((v("x_right"), v("y_right")));
            if *frame == 0 {
                for k in ["dX_mm", "dY_mm", "dZ_mm"] {
                    assert_eq!(v(k), 0.0);
                }
                if expect_markers.is_some() {
                    // The reference sensor sees every marker at rest (variants may overfill).
                    assert_eq!(table.cell(r, "visible_left").unwrap(), "1");
                    assert_eq!(table.cell(r, "visible_right").unwrap(), "1");
                }
                assert_eq!(table.cell(r, "in_contact").unwrap(), "0");
            }
        }
        for (view, truth) in gt.iter().enumerate() {
            let (rv, tv) = if view == 0 {
                (&zero, &zero)
            } else {
                (&rvec_r, &c.t)
            };
            let mut img = Vector::<Point2d>::new();
            calib3d::project_points_def(&obj, rv, tv, &c.k[view], &c.d[view], &mut img).unwrap();
            for (p, g) in img.iter().zip(truth) {
                worst = worst.max((p.x - g.0).hypot(p.y - g.1));
            }
        }
    }
    // Images match the calibration's size.
    let png = dir.join("left").join("000000.png");
    let im =
        opencv::imgcodecs::imread(png.to_string_lossy().as_ref(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    assert_eq!((im.cols(), im.rows()), c.size);
    worst
}

#[test]
fn ground_truth_reprojects_through_the_written_calibration() {
    let tmp = tempfile::tempdir().unwrap();
    // Reference sensor, reference look.
    let out = tmp.path().join("ref");
    let mut cfg = DatasetConfig::new(5, 12, 3);
    cfg.randomization = Randomization::Off;
    write_dataset(&out, &cfg, false, &|| {}).unwrap();
    let recs = recordings(&out);
    assert_eq!(recs.len(), 5);
    for r in &recs {
        let err = check_recording(r, Some(529));
        assert!(err < 0.01, "{}: reprojection error {err} px", r.display());
    }
    // Full randomisation: sensor variants with other grids and resolutions.
    let out = tmp.path().join("full");
    let cfg = DatasetConfig::new(6, 6, 5);
    write_dataset(&out, &cfg, false, &|| {}).unwrap();
    for r in &recordings(&out) {
        let err = check_recording(r, None);
        assert!(err < 0.01, "{}: reprojection error {err} px", r.display());
    }
}

fn digest(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

#[test]
fn same_seed_same_bytes_whatever_the_thread_count() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = DatasetConfig::new(3, 5, 42);
    let a = tmp.path().join("a");
    let b = tmp.path().join("b");
    write_dataset(&a, &cfg, false, &|| {}).unwrap();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    pool.install(|| write_dataset(&b, &cfg, false, &|| {})).unwrap();
    let (da, db) = (digest(&a), digest(&b));
    assert_eq!(da.keys().collect::<Vec<_>>(), db.keys().collect::<Vec<_>>());
    for (k, v) in &da {
        assert!(v == &db[k], "{} differs", k.display());
    }
    // Another seed gives other images.
    let c = tmp.path().join("c");
    write_dataset(&c, &DatasetConfig::new(3, 5, 43), false, &|| {}).unwrap();
    assert_ne!(
        digest(&c).get(Path::new("dataset.json")),
        da.get(Path::new("dataset.json"))
    );
}

#[test]
fn output_folder_rules() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("keep.txt"), "x").unwrap();
    let cfg = DatasetConfig::new(1, 2, 1);
    let e = write_dataset(&out, &cfg, false, &|| {}).unwrap_err().to_string();
    assert!(e.contains("not empty") && e.contains("--force"), "{e}");
    assert!(out.join("keep.txt").exists());
    // --force replaces only what gelstereo-sim wrote: a folder with a file of the user's is kept.
    let e = write_dataset(&out, &cfg, true, &|| {}).unwrap_err().to_string();
    assert!(e.contains("refusing to replace it"), "{e}");
    assert!(out.join("keep.txt").exists());
    std::fs::remove_file(out.join("keep.txt")).unwrap();
    write_dataset(&out, &cfg, true, &|| {}).unwrap();
    write_dataset(&out, &cfg, true, &|| {}).unwrap();
    assert!(out.join("dataset.json").exists());
    // Nothing half-written is left beside it.
    let leftovers: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(leftovers.len(), 1, "{leftovers:?}");
    // Impossible parameters.
    let e = write_dataset(&tmp.path().join("p"), &DatasetConfig::new(1, 1, 1), false, &|| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("frames_per_experiment"), "{e}");
    assert!(!tmp.path().join("p").exists());
    // Unwritable output (a path under a file).
    let e = write_dataset(&out.join("dataset.json").join("x"), &cfg, false, &|| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("dataset.json"), "{e}");
}
