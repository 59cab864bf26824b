//! Calibration files: accepted and rejected inputs, and round trips.
//!
//! Fixtures in `tests/data` were written by OpenCV 4.6 (`cv2.FileStorage`) and mrcal 2.2
//! (`mrcal.cameramodel.write`) by `tests/data/generate.py`; the rejected variants below are written
//! by the tests themselves, each a small edit of an accepted file.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use gelstereo_geometry::{CalibrationPath, Error, StereoRig};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// The reference values that generate.py wrote.
const K1: [f64; 4] = [520.0, 521.5, 321.3, 238.4];
const K2: [f64; 4] = [518.6, 519.8, 318.2, 241.1];
const D8_1: [f64; 8] = [-0.065, 0.021, 0.0004, -0.0003, -0.004, 0.002, -0.001, 0.0005];
const D8_2: [f64; 8] = [-0.059, 0.018, -0.0002, 0.0005, -0.003, 0.001, 0.0007, -0.0004];

fn intrinsics(c: &gelstereo_geometry::Camera) -> [f64; 4] {
    [c.fx, c.fy, c.cx, c.cy]
}

fn max_rt_diff(a: &StereoRig, b: &StereoRig) -> (f64, f64) {
    let ra = a.right_from_left.rotation.to_rotation_matrix().into_inner();
    let rb = b.right_from_left.rotation.to_rotation_matrix().into_inner();
    let t = (a.right_from_left.translation.vector - b.right_from_left.translation.vector)
        .abs()
        .max();
    ((ra - rb).abs().max(), t)
}

#[test]
fn accepted_opencv_files() {
    let yaml = StereoRig::read_opencv(data("opencv8.yaml")).unwrap();
    assert_eq!(intrinsics(&yaml.left), K1);
    assert_eq!(intrinsics(&yaml.right), K2);
    assert_eq!(yaml.left.distortion.coeffs, D8_1);
    assert_eq!(yaml.right.distortion.coeffs, D8_2);
    assert_eq!(
        (yaml.left.image_size.width, yaml.left.image_size.height),
        (640, 480)
    );
    assert!((yaml.baseline_mm() - 10.0).abs() < 0.01, "{}", yaml.baseline_mm());

    let xml = StereoRig::read_opencv(data("opencv5.xml")).unwrap();
    assert_eq!(xml.left.distortion.coeffs, D8_1[..5]);
    assert_eq!(xml.right.distortion.coeffs, D8_2[..5]);
    let (r, t) = max_rt_diff(&xml, &yaml);
    assert!(r == 0.0 && t == 0.0, "{r} {t}");

    let m = StereoRig::read_opencv(data("stereo_calib_m1m2.yml")).unwrap();
    assert_eq!(intrinsics(&m.left), K1);
    assert_eq!(m.left.distortion.coeffs.len(), 12);
    assert_eq!(m.right.distortion.coeffs[8..], [-0.0006, 0.0003, -0.0009, 0.0001]);

    // Dispatch by extension.
    assert_eq!(
        StereoRig::load(data("opencv8.yaml").to_str().unwrap()).unwrap(),
        yaml
    );
    assert_eq!(
        StereoRig::load(data("opencv5.xml").to_str().unwrap()).unwrap(),
        xml
    );
}

/// OpenCV's stereo_calib sample writes intrinsics.yml (M1 D1 M2 D2) and extrinsics.yml (R T R1 R2
/// P1 P2 Q) and no image size: read together, with the size from a third file.
#[test]
fn stereo_calib_sample_files() {
    let (i, e) = (
        data("stereo_calib_intrinsics.yml"),
        data("stereo_calib_extrinsics.yml"),
    );
    let spec = format!("{},{}", i.display(), e.display());
    let err = StereoRig::load(&spec).unwrap_err().to_string();
    assert!(
        err.contains("image_width and image_height") && err.contains("stereo_calib"),
        "{err}"
    );
    assert!(
        err.contains("stereo_calib_intrinsics.yml") && err.contains("stereo_calib_extrinsics.yml"),
        "{err}"
    );
    let dir = tempfile::tempdir().unwrap();
    let size = dir.path().join("size.yml");
    std::fs::write(&size, "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n").unwrap();
    let rig = StereoRig::load(format!("{spec},{}", size.display())).unwrap();
    let yaml = StereoRig::read_opencv(data("opencv8.yaml")).unwrap();
    assert_eq!(intrinsics(&rig.left), K1);
    assert_eq!(rig.right.distortion.coeffs, D8_2[..5]);
    assert_eq!(rig.right_from_left, yaml.right_from_left);
    // Several OpenCV files are for reading only.
    assert!(matches!(rig.save(&spec), Err(Error::UnknownFormat { .. })));
}

#[test]
fn accepted_mrcal_files() {
    let yaml = StereoRig::read_opencv(data("opencv8.yaml")).unwrap();
    for (name, n) in [
        ("opencv8", 8),
        ("opencv12", 12),
        ("opencv5", 5),
        ("opencv4", 4),
        ("pinhole", 0),
    ] {
        let l = data(&format!("{name}_left.cameramodel"));
        let r = data(&format!("{name}_right.cameramodel"));
        let rig = StereoRig::read_mrcal(&l, &r).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(intrinsics(&rig.left), K1, "{name}");
        assert_eq!(intrinsics(&rig.right), K2, "{name}");
        assert_eq!(rig.left.distortion.coeffs.len(), n, "{name}");
        assert_eq!(rig.left.distortion.coeffs[..n.min(8)], D8_1[..n.min(8)], "{name}");
        // mrcal writes 10 significant digits: extrinsics agree with the full-precision YAML to that.
        let (dr, dt) = max_rt_diff(&rig, &yaml);
        assert!(dr < 1e-9 && dt < 1e-8, "{name}: {dr} {dt}");
        let spec = format!("{},{}", l.display(), r.display());
        assert_eq!(StereoRig::load(&spec).unwrap(), rig, "{name}");
    }
    // A directory holding left.cameramodel and right.cameramodel.
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(
        data("opencv8_at_ref.cameramodel"),
        dir.path().join("left.cameramodel"),
    )
    .unwrap();
    std::fs::copy(
        data("opencv8_right.cameramodel"),
        dir.path().join("right.cameramodel"),
    )
    .unwrap();
    let from_dir = StereoRig::load(dir.path().to_str().unwrap()).unwrap();
    let (dr, dt) = max_rt_diff(&from_dir, &yaml);
    assert!(dr < 1e-9 && dt < 1e-8);
}

#[test]
fn accepted_mrcal_variants() {
    let dir = tempfile::tempdir().unwrap();
    let left = std::fs::read_to_string(data("opencv4_left.cameramodel")).unwrap();
    let right = std::fs::read_to_string(data("opencv4_right.cameramodel")).unwrap();
    let base = StereoRig::read_mrcal(
        data("opencv4_left.cameramodel"),
        data("opencv4_right.cameramodel"),
    )
    .unwrap();
    let variants = [
        ("rt_cam_ref key", right.replace("'extrinsics'", "'rt_cam_ref'")),
        ("legacy distortion_model", right.replace("'lensmodel':  'LENSMODEL_OPENCV4'", "'distortion_model': 'DISTORTION_OPENCV4'")),
        (
            "optimization_inputs and valid region",
            right.replace(
                "'imagersize'",
                "'valid_intrinsics_region': [[0, 0], [639, 0], [639, 479], [0, 0]],\n 'icam_intrinsics': 1,\n \
                 'optimization_inputs': b'VI#!0fbsR'\n b'XYZ',\n 'imagersize'",
            ),
        ),
        ("tuples and double quotes", right.replace('[', "(").replace(']', ")").replace('\'', "\"")),
    ];
    let lp = dir.path().join("l.cameramodel");
    std::fs::write(&lp, &left).unwrap();
    for (what, text) in variants {
        let rp = dir.path().join("r.cameramodel");
        std::fs::write(&rp, &text).unwrap();
        let rig = StereoRig::read_mrcal(&lp, &rp).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(rig, base, "{what}");
    }
}

/// Round trip OpenCV YAML -> mrcal -> OpenCV YAML: intrinsics, distortion, image size and
/// translation are bit-identical; the rotation goes through a quaternion and a Rodrigues vector and
/// comes back to 2 ulp (measured 1.1e-16).
#[test]
fn round_trip_yaml_mrcal_yaml() {
    let dir = tempfile::tempdir().unwrap();
    for src in ["opencv8.yaml", "stereo_calib_m1m2.yml", "opencv5.xml"] {
        let a = StereoRig::read_opencv(data(src)).unwrap();
        let (l, r) = (dir.path().join("l.cameramodel"), dir.path().join("r.cameramodel"));
        a.write_mrcal(&l, &r).unwrap();
        let b = StereoRig::read_mrcal(&l, &r).unwrap();
        let y = dir.path().join("back.yaml");
        b.write_opencv_yaml(&y).unwrap();
        let c = StereoRig::read_opencv(&y).unwrap();
        for rig in [&b, &c] {
            assert_eq!(rig.left, a.left, "{src}");
            assert_eq!(rig.right, a.right, "{src}");
            assert_eq!(
                rig.right_from_left.translation, a.right_from_left.translation,
                "{src}"
            );
            let (dr, _) = max_rt_diff(rig, &a);
            assert!(dr <= 2.0 * f64::EPSILON, "{src}: rotation differs by {dr:e}");
        }
        // XML too, and a second trip is stable.
        let x = dir.path().join("back.xml");
        c.write_opencv_xml(&x).unwrap();
        let d = StereoRig::read_opencv(&x).unwrap();
        assert_eq!(d.left, a.left);
        assert_eq!(d.right, a.right);
        let (dr, dt) = max_rt_diff(&d, &a);
        assert!(dr <= 2.0 * f64::EPSILON && dt == 0.0, "{src}: {dr:e} {dt:e}");
    }
}

#[test]
fn save_dispatches_by_path() {
    let a = StereoRig::read_opencv(data("opencv8.yaml")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mdir = dir.path().join("models");
    a.save(mdir.to_str().unwrap()).unwrap();
    assert!(mdir.join("left.cameramodel").is_file() && mdir.join("right.cameramodel").is_file());
    assert_eq!(StereoRig::load(mdir.to_str().unwrap()).unwrap().left, a.left);
    let y = dir.path().join("x.YML");
    a.save(y.to_str().unwrap()).unwrap();
    assert_eq!(StereoRig::load(y.to_str().unwrap()).unwrap().right, a.right);
    for bad in ["a.json", "l.cameramodel,r.yaml", "x.cameramodel"] {
        assert!(
            matches!(CalibrationPath::parse(bad), Err(Error::UnknownFormat { .. })),
            "{bad}"
        );
    }
}

fn cv_mat(name: &str, rows: usize, cols: usize, data: &[f64]) -> String {
    let d: Vec<String> = data.iter().map(|v| format!("{v:?}")).collect();
    format!(
        "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n",
        d.join(", ")
    )
}

/// An OpenCV YAML file from the reference values with `edit` applied to its list of entries.
fn yaml_with(edit: impl FnOnce(&mut Vec<(&'static str, String)>)) -> String {
    let rig = StereoRig::read_opencv(data("opencv8.yaml")).unwrap();
    let r = rig
        .right_from_left
        .rotation
        .to_rotation_matrix()
        .into_inner()
        .transpose();
    let t = rig.right_from_left.translation.vector;
    let k = |c: [f64; 4]| [c[0], 0.0, c[2], 0.0, c[1], c[3], 0.0, 0.0, 1.0];
    let mut entries: Vec<(&'static str, String)> = vec![
        ("K1", cv_mat("K1", 3, 3, &k(K1))),
        ("D1", cv_mat("D1", 1, 8, &D8_1)),
        ("K2", cv_mat("K2", 3, 3, &k(K2))),
        ("D2", cv_mat("D2", 1, 8, &D8_2)),
        ("R", cv_mat("R", 3, 3, r.as_slice())),
        ("T", cv_mat("T", 3, 1, t.as_slice())),
        ("image_width", "image_width: 640\n".to_owned()),
        ("image_height", "image_height: 480\n".to_owned()),
    ];
    edit(&mut entries);
    let mut s = "%YAML:1.0\n---\n".to_owned();
    for (_, e) in entries {
        s.push_str(&e);
    }
    s
}

fn replace(entries: &mut [(&'static str, String)], key: &str, text: String) {
    for e in entries.iter_mut() {
        if e.0 == key {
            e.1 = text.clone();
        }
    }
}

#[test]
fn rejected_opencv_files() {
    let dir = tempfile::tempdir().unwrap();
    // The table itself is checked: the unedited file must be accepted.
    let ok = dir.path().join("ok.yaml");
    std::fs::write(&ok, yaml_with(|_| {})).unwrap();
    StereoRig::read_opencv(&ok).unwrap();

    type Edit = Box<dyn FnOnce(&mut Vec<(&'static str, String)>)>;
    let cases: Vec<(&str, Edit, &[&str])> = vec![
        (
            "missing K2",
            Box::new(|e| e.retain(|x| x.0 != "K2")),
            &["missing key 'K2 or M2'", "3x3 camera matrix"],
        ),
        (
            "missing D1",
            Box::new(|e| e.retain(|x| x.0 != "D1")),
            &["missing key 'D1'"],
        ),
        (
            "missing R",
            Box::new(|e| e.retain(|x| x.0 != "R")),
            &["missing key 'R'"],
        ),
        (
            "missing T",
            Box::new(|e| e.retain(|x| x.0 != "T")),
            &["missing key 'T'"],
        ),
        (
            "missing size",
            Box::new(|e| e.retain(|x| x.0 != "image_height")),
            &["missing key 'image_width and image_height'"],
        ),
        (
            "K1 2x3",
            Box::new(|e| replace(e, "K1", cv_mat("K1", 2, 3, &[1.0; 6]))),
            &["key 'K1'", "3x3 camera matrix", "2x3"],
        ),
        (
            "K1 skew",
            Box::new(|e| {
                replace(
                    e,
                    "K1",
                    cv_mat("K1", 3, 3, &[520.0, 0.5, 320.0, 0.0, 520.0, 240.0, 0.0, 0.0, 1.0]),
                )
            }),
            &["key 'K1'", "skew", "0.5"],
        ),
        (
            "K2 negative focal",
            Box::new(|e| {
                replace(
                    e,
                    "K2",
                    cv_mat(
                        "K2",
                        3,
                        3,
                        &[-520.0, 0.0, 320.0, 0.0, 520.0, 240.0, 0.0, 0.0, 1.0],
                    ),
                )
            }),
            &["key 'K2'", "positive focal"],
        ),
        (
            "D1 six",
            Box::new(|e| replace(e, "D1", cv_mat("D1", 1, 6, &[0.0; 6]))),
            &["key 'D1'", "1x6", "0, 4, 5, 8 or 12"],
        ),
        (
            "D2 tilted",
            Box::new(|e| replace(e, "D2", cv_mat("D2", 14, 1, &[0.0; 14]))),
            &["key 'D2'", "14x1", "tilted"],
        ),
        (
            "D1 matrix",
            Box::new(|e| replace(e, "D1", cv_mat("D1", 2, 4, &[0.0; 8]))),
            &["key 'D1'", "2x4"],
        ),
        (
            "R 2x2",
            Box::new(|e| replace(e, "R", cv_mat("R", 2, 2, &[1.0, 0.0, 0.0, 1.0]))),
            &["key 'R'", "3x3 rotation", "2x2"],
        ),
        (
            "R not a rotation",
            Box::new(|e| {
                replace(
                    e,
                    "R",
                    cv_mat("R", 3, 3, &[1.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0]),
                )
            }),
            &["key 'R'", "orthonormal"],
        ),
        (
            "T 1x2",
            Box::new(|e| replace(e, "T", cv_mat("T", 1, 2, &[1.0, 2.0]))),
            &["key 'T'", "3x1", "1x2"],
        ),
        (
            "T zero",
            Box::new(|e| replace(e, "T", cv_mat("T", 3, 1, &[0.0; 3]))),
            &["baseline"],
        ),
        (
            "width not a number",
            Box::new(|e| replace(e, "image_width", "image_width: \"wide\"\n".to_owned())),
            &["key 'image_width'", "numeric", "the string 'wide'"],
        ),
        (
            "width zero",
            Box::new(|e| replace(e, "image_width", "image_width: 0\n".to_owned())),
            &["key 'image_width'", "positive whole number"],
        ),
        (
            "width fractional",
            Box::new(|e| replace(e, "image_width", "image_width: 640.5\n".to_owned())),
            &["key 'image_width'", "640.5"],
        ),
    ];
    for (what, edit, needles) in cases {
        let p = dir.path().join("bad.yaml");
        std::fs::write(&p, yaml_with(edit)).unwrap();
        let e = StereoRig::read_opencv(&p)
            .err()
            .unwrap_or_else(|| panic!("{what}: accepted"));
        let msg = e.to_string();
        assert!(msg.contains("bad.yaml"), "{what}: no file name in '{msg}'");
        for n in needles {
            assert!(msg.contains(n), "{what}: '{n}' not in '{msg}'");
        }
    }
    // Not a FileStorage file at all, and a file that does not exist.
    let p = dir.path().join("garbage.yaml");
    std::fs::write(&p, "this: [is not: {valid").unwrap();
    let e = StereoRig::read_opencv(&p).unwrap_err();
    assert!(
        matches!(e, Error::Syntax { .. }) && e.to_string().contains("garbage.yaml"),
        "{e}"
    );
    let e = StereoRig::read_opencv(dir.path().join("absent.yaml")).unwrap_err();
    assert!(
        matches!(e, Error::Io { .. }) && e.to_string().contains("absent.yaml"),
        "{e}"
    );
}

#[test]
fn rejected_mrcal_files() {
    let dir = tempfile::tempdir().unwrap();
    let left = data("opencv8_left.cameramodel");
    let right = std::fs::read_to_string(data("opencv8_right.cameramodel")).unwrap();
    // The mrcal-written CAHVOR model.
    let e = StereoRig::read_mrcal(&left, data("rejected_cahvor.cameramodel")).unwrap_err();
    assert!(matches!(e, Error::UnsupportedLensModel { .. }), "{e}");
    assert!(
        e.to_string().contains("LENSMODEL_CAHVOR") && e.to_string().contains("rejected_cahvor.cameramodel")
    );

    let cases: Vec<(&str, String, &[&str])> = vec![
        (
            "splined",
            right.replace(
                "LENSMODEL_OPENCV8",
                "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=100",
            ),
            &[
                "lensmodel",
                "LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=16_Ny=12_fov_x_deg=100",
            ],
        ),
        (
            "opencv14",
            right.replace("LENSMODEL_OPENCV8", "LENSMODEL_OPENCV14"),
            &["LENSMODEL_OPENCV14"],
        ),
        (
            "stereographic",
            right.replace("LENSMODEL_OPENCV8", "LENSMODEL_STEREOGRAPHIC"),
            &["LENSMODEL_STEREOGRAPHIC"],
        ),
        (
            "intrinsics short",
            right.replace("LENSMODEL_OPENCV8", "LENSMODEL_OPENCV12"),
            &[
                "key 'intrinsics'",
                "list of 16 numbers",
                "found a list of 12 numbers",
            ],
        ),
        (
            "intrinsics text",
            right.replace("'intrinsics': [", "'intrinsics': [ 'a',"),
            &["key 'intrinsics'", "not all numbers"],
        ),
        (
            "no lensmodel",
            right.replace("'lensmodel'", "'lensmode'"),
            &["missing key 'lensmodel or distortion_model or lens_model'"],
        ),
        (
            "no imagersize",
            right.replace("'imagersize'", "'imagesize'"),
            &["missing key 'imagersize'"],
        ),
        (
            "no extrinsics",
            right.replace("'extrinsics'", "'extrinsic'"),
            &["missing key 'extrinsics or rt_cam_ref'"],
        ),
        (
            "imagersize 3",
            right.replace("'imagersize': [", "'imagersize': [ 1,"),
            &["key 'imagersize'", "2 integers", "3 numbers"],
        ),
        (
            "imagersize zero",
            right.replace("'imagersize': [ 640", "'imagersize': [ 0"),
            &["key 'imagersize'", "positive"],
        ),
        (
            "fx negative",
            right.replace("'intrinsics': [ ", "'intrinsics': [ -"),
            &["key 'intrinsics'", "fx"],
        ),
        (
            "unclosed",
            right.replace("'imagersize': [ 640, 480,],", "'imagersize': [ 640, 480,"),
            &["line"],
        ),
        ("not a dict", "[1, 2, 3]\n".to_owned(), &["expected a dict"]),
        (
            "nan",
            right.replace("'intrinsics': [ ", "'intrinsics': [ nan, "),
            &["line 5", "'nan' is not a Python literal"],
        ),
    ];
    for (what, text, needles) in cases {
        let p = dir.path().join("bad.cameramodel");
        std::fs::write(&p, &text).unwrap();
        let e = StereoRig::read_mrcal(&left, &p)
            .err()
            .unwrap_or_else(|| panic!("{what}: accepted"));
        let msg = e.to_string();
        assert!(msg.contains("bad.cameramodel"), "{what}: no file name in '{msg}'");
        for n in needles {
            assert!(msg.contains(n), "{what}: '{n}' not in '{msg}'");
        }
    }
    // Extrinsics of 5 numbers.
    let p = dir.path().join("ext5.cameramodel");
    let five = with_zero_extrinsics(&right, 5);
    std::fs::write(&p, five).unwrap();
    let msg = StereoRig::read_mrcal(&left, &p).unwrap_err().to_string();
    assert!(
        msg.contains("key 'extrinsics'") && msg.contains("6 numbers") && msg.contains("list of 5 numbers"),
        "{msg}"
    );
}

/// Rewrites the `'extrinsics'` line with `n` zeros.
fn with_zero_extrinsics(text: &str, n: usize) -> String {
    text.lines()
        .map(|l| {
            if l.trim_start().starts_with("'extrinsics'") {
                format!("    'extrinsics': [{}],", " 0.0,".repeat(n))
            } else {
                l.to_owned()
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}
