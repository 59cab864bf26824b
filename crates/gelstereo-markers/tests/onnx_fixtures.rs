//! Marknet + MRE through ONNX Runtime against values computed independently in Python.
//!
//! Fixtures: `data/fixtures/onnx/` (tiny random-weight models, two rendered images and
//! `expected.json`), made by `train/scripts/make_onnx_fixtures.py` with the trainer's reference
//! implementation (`train/gelstereo_train/postprocess.py`). Tolerances are the ones `expected.json`
//! states: raw logits 1e-4 for the 64x64 image (no resize), 0.05 for the resized 80x60 one; MRE
//! scores 1e-5. Post-processing run on the Python raw output must reproduce the Python result to 1e-5
//! (the file rounds to 6 decimals).

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: a failure is a test failure

use std::path::{Path, PathBuf};

use gelstereo_core::{Detection, Point2, StereoPair};
use gelstereo_markers::lattice::LatticeCheck;
use gelstereo_markers::postprocess::{Selection, decode};
use gelstereo_markers::{Error, Localizer, Marknet, Mre, PostProcess, SessionOptions};
use opencv::core::{CV_8UC3, Mat, MatTraitConst, Scalar};
use serde_json::Value;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data/fixtures/onnx")
}

fn expected() -> Value {
    let text = std::fs::read_to_string(fixtures().join("expected.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn options() -> SessionOptions {
    SessionOptions {
        intra_threads: 1,
        use_cuda: false,
    }
}

/// The fixture network under the contract's post-processing alone: its random weights give
/// candidates on no marker lattice, which the lattice check would drop (tested on its own in
/// `lattice.rs` and `tests/borders_and_clutter.rs`).
fn without_lattice_check(mut m: Marknet) -> Marknet {
    m.set_postprocess(PostProcess {
        lattice: None,
        ..*m.postprocess()
    });
    m
}

fn marknet() -> Marknet {
    without_lattice_check(Marknet::load(&fixtures().join("marknet_tiny.onnx"), &options()).unwrap())
}

fn mre() -> Mre {
    Mre::load(&fixtures().join("mre_tiny.onnx"), &options()).unwrap()
}

fn image(name: &str) -> Mat {
    let path = fixtures().join(name);
    let m = opencv::imgcodecs::imread(path.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    assert!(!opencv::core::MatTraitConst::empty(&m), "{name} unreadable");
    m
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Rows `[x, y, c]` of the file as detections.
fn rows(v: &Value) -> Vec<Detection> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let r = floats(r);
            Detection {
                position: Point2::new(r[0], r[1]),
                confidence: r[2] as f32,
            }
        })
        .collect()
}

fn post_of(e: &Value) -> PostProcess {
    let p = &e["post"];
    let f = |k: &str| p[k].as_f64().unwrap();
    PostProcess {
        conf_keep: f("conf_keep") as f32,
        conf_low: f("conf_low") as f32,
        conf_marknet_only: f("conf_marknet_only") as f32,
        dedup_radius_frac: f("dedup_radius_frac"),
        accept: f("accept") as f32,
        lattice: None,
    }
}

fn sorted(mut d: Vec<Detection>) -> Vec<Detection> {
    gelstereo_markers::sort_detections(&mut d);
    d
}

fn assert_same(got: &[Detection], want: &[Detection], tol_px: f64, tol_c: f32, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: count");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            g.position.distance(w.position) <= tol_px && (g.confidence - w.confidence).abs() <= tol_c,
            "{what}[{i}]: got {g:?}, want {w:?}"
        );
    }
}

#[test]
fn contract_is_read_from_the_fixture_metadata() {
    let m = marknet();
    let c = m.contract();
    assert_eq!(
        (
            c.input_width,
            c.input_height,
            c.stride,
            c.grid_x,
            c.grid_y,
            c.candidates
        ),
        (64, 64, 8, 8, 8, 2)
    );
    // The thresholds come from the metadata; the lattice check is the loader's default, not metadata.
    assert_eq!(
        PostProcess {
            lattice: None,
            ..c.postprocess
        },
        post_of(&expected())
    );
    assert_eq!(c.postprocess.lattice, Some(LatticeCheck::default()));
    let with = m.with_mre(mre()).unwrap();
    assert_eq!(with.name(), "marknet-mre");
}

/// Decoding and post-processing alone, on the Python raw output: no ONNX Runtime in the loop.
#[test]
fn postprocessing_of_python_raw_output_matches_python() {
    let e = expected();
    let post = post_of(&e);
    let m = marknet();
    for (name, img) in e["images"].as_object().unwrap() {
        let raw: Vec<f32> = floats(&img["raw"]).into_iter().map(|v| v as f32).collect();
        let size = gelstereo_core::ImageSize {
            width: img["width"].as_u64().unwrap() as u32,
            height: img["height"].as_u64().unwrap() as u32,
        };
        let geometry = m.geometry(size);
        // Every candidate, flat order.
        let all = decode(&raw, &geometry, -1.0);
        assert_same(
            &all,
            &rows(&img["decoded"]),
            1e-4,
            1e-5,
            &format!("{name} decoded"),
        );
        let cands = decode(&raw, &geometry, post.conf_low);
        let marknet_only = Selection::new(cands.clone(), &post, false);
        let pitch = img["pitch_px"].as_f64().unwrap();
        assert!(
            (marknet_only.pitch_px.unwrap() - pitch).abs() < 1e-4,
            "{name} pitch"
        );
        assert_eq!(
            marknet_only.kept,
            img["kept"].as_array().unwrap().len(),
            "{name} kept after de-duplication"
        );
        assert_same(
            &sorted(marknet_only.accepted),
            &sorted(rows(&img["marknet"])),
            1e-4,
            1e-5,
            &format!("{name} marknet"),
        );
        let with_mre = Selection::new(cands, &post, true);
        let want_f = img["mre_features"].as_array().unwrap();
        assert_eq!(with_mre.features.len(), want_f.len(), "{name} MRE feature count");
        for (i, (g, w)) in with_mre.features.iter().zip(want_f).enumerate() {
            for (k, (a, b)) in g.iter().zip(floats(w)).enumerate() {
                assert!(
                    (f64::from(*a) - b).abs() < 1e-4,
                    "{name} feature {i}[{k}]: {a} vs {b}"
                );
            }
        }
        let scores: Vec<f32> = floats(&img["mre_scores"]).into_iter().map(|v| v as f32).collect();
        let out = with_mre.finish(&scores, post.accept);
        assert_same(
            &out,
            &sorted(rows(&img["marknet_mre"])),
            1e-4,
            1e-5,
            &format!("{name} marknet-mre"),
        );
    }
}

#[test]
fn mre_scores_match_python() {
    let e = expected();
    let mut mre = mre();
    let feats: Vec<[f32; 11]> = e["mre_rows"]["features"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let v = floats(r);
            std::array::from_fn(|k| v[k] as f32)
        })
        .collect();
    let got = mre.score(&feats).unwrap();
    for (g, w) in got.iter().zip(floats(&e["mre_rows"]["scores"])) {
        assert!((f64::from(*g) - w).abs() < 1e-5, "{g} vs {w}");
    }
    assert!(mre.score(&[]).unwrap().is_empty());
}

/// The whole path through ONNX Runtime, with and without resizing, single and batched.
#[test]
fn onnx_runtime_pipeline_matches_python() {
    let e = expected();
    let mut m = marknet().with_mre(mre()).unwrap();
    for (name, tol_raw, tol_px, tol_c) in [
        ("dots_64x64.png", 1e-4, 1e-3, 1e-4f32),
        ("dots_80x60.png", 0.05, 0.05, 0.01f32),
    ] {
        let img = image(name);
        let want = &e["images"][name];
        let (_, raw) = m.raw_output(&[&img]).unwrap();
        let want_raw = floats(&want["raw"]);
        assert_eq!(raw.len(), want_raw.len());
        let worst = raw
            .iter()
            .zip(&want_raw)
            .map(|(a, b)| (f64::from(*a) - b).abs())
            .fold(0.0, f64::max);
        eprintln!("{name}: worst raw difference {worst}");
        assert!(worst <= tol_raw, "{name}: raw differs by {worst} > {tol_raw}");
        let found = m.detect(&img).unwrap();
        assert_same(
            &found,
            &sorted(rows(&want["marknet_mre"])),
            tol_px,
            tol_c,
            &format!("{name} detect"),
        );
    }
    // A stereo pair runs as one batch of two and gives what each view gives alone.
    let a = image("dots_64x64.png");
    let mut b = Mat::default();
    opencv::core::flip(&a, &mut b, 1).unwrap();
    let pair = m.detect_stereo(&StereoPair::new(a.clone(), b.clone())).unwrap();
    assert_eq!(pair.left, m.detect(&a).unwrap());
    assert_eq!(pair.right, m.detect(&b).unwrap());
    // With the second tier: the same markers, plus only candidates of the MRE band it rejected.
    let tiered = m.detect_stereo_tiered(&StereoPair::new(a.clone(), b)).unwrap();
    assert_eq!(tiered.left, m.detect_tiered(&a).unwrap());
    assert_eq!(
        (&tiered.left.accepted, &tiered.right.accepted),
        (&pair.left, &pair.right)
    );
    let post = *m.postprocess();
    for d in tiered.left.second_tier.iter().chain(&tiered.right.second_tier) {
        assert!(
            d.confidence > post.conf_low && d.confidence <= post.conf_keep,
            "{d:?}"
        );
        assert!(!pair.left.contains(d) && !pair.right.contains(d), "{d:?}");
    }
}

/// With the two views worked on in parallel, a stereo pair gives exactly the sequential results,
/// under the fixed input and under the auto fit (probe and relayout passes, then from memory).
#[test]
fn parallel_views_give_the_same_detections() {
    let a = image("dots_160x120.png");
    let mut b = Mat::default();
    opencv::core::flip(&a, &mut b, 1).unwrap();
    let pair = StereoPair::new(a, b);
    let post = post_of(&expected());
    let fixed = || marknet().with_mre(mre()).unwrap();
    let auto = || {
        let mut m = without_lattice_check(
            Marknet::load(&fixtures().join("marknet_tiny_auto.onnx"), &options()).unwrap(),
        );
        m.set_postprocess(post);
        m
    };
    for make in [&fixed as &dyn Fn() -> Marknet, &auto] {
        let (mut sequential, mut parallel) = (make(), make());
        parallel.set_parallel(true);
        for pass in 0..2 {
            let want = sequential.detect_stereo_tiered(&pair).unwrap();
            let got = parallel.detect_stereo_tiered(&pair).unwrap();
            assert!(!want.left.accepted.is_empty(), "pass {pass}");
            assert_eq!((&got.left, &got.right), (&want.left, &want.right), "pass {pass}");
        }
    }
}

#[test]
fn bad_inputs_give_clear_errors() {
    let mut m = marknet();
    let thin = Mat::new_rows_cols_with_default(20, 200, CV_8UC3, Scalar::all(128.0)).unwrap();
    let err = m.detect(&thin).unwrap_err().to_string();
    assert!(err.contains("200x20") && err.contains("aspect ratio"), "{err}");
    assert!(matches!(m.detect(&Mat::default()), Err(Error::Image { .. })));
    let a = Mat::new_rows_cols_with_default(64, 64, CV_8UC3, Scalar::all(128.0)).unwrap();
    let b = Mat::new_rows_cols_with_default(60, 80, CV_8UC3, Scalar::all(128.0)).unwrap();
    let err = m.detect_stereo(&StereoPair::new(a, b)).unwrap_err().to_string();
    assert!(err.contains("stereo sizes"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nothing.onnx");
    let err = Marknet::load(&missing, &options()).unwrap_err().to_string();
    assert!(err.contains("nothing.onnx"), "{err}");
    let junk = dir.path().join("junk.onnx");
    std::fs::write(&junk, b"not a model at all").unwrap();
    let err = Marknet::load(&junk, &options()).unwrap_err().to_string();
    assert!(
        err.contains("junk.onnx") && err.contains("loading the model"),
        "{err}"
    );
}

/// The fixture model with one metadata value or key changed in place (same length, so the protobuf
/// stays valid): the loader must name the key.
#[test]
fn wrong_metadata_is_named() {
    let bytes = std::fs::read(fixtures().join("marknet_tiny.onnx")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    for (from, to, key) in [
        (
            &b"gelstereo-marknet/1"[..],
            &b"gelstereo-marknet/7"[..],
            "'contract'",
        ),
        (b"candidates", b"candidatez", "'candidates'"),
        (b"rgb/255", b"bgr/255", "'normalisation'"),
    ] {
        let at = bytes
            .windows(from.len())
            .position(|w| w == from)
            .expect("key in fixture");
        let mut edited = bytes.clone();
        edited[at..at + from.len()].copy_from_slice(to);
        let path = dir.path().join("edited.onnx");
        std::fs::write(&path, &edited).unwrap();
        let err = Marknet::load(&path, &options()).unwrap_err().to_string();
        assert!(err.contains(key) && err.contains("edited.onnx"), "{key}: {err}");
    }
    // An MRE file where a Marknet is expected, and the reverse.
    let err = Marknet::load(&fixtures().join("mre_tiny.onnx"), &options())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("'contract'") && err.contains("gelstereo-mre/1"),
        "{err}"
    );
    let err = Mre::load(&fixtures().join("marknet_tiny.onnx"), &options())
        .unwrap_err()
        .to_string();
    assert!(err.contains("'contract'"), "{err}");
}

/// `InputFit::Pad`: isotropic scale, centred, mirrored border; the mapping back puts the input's centre
/// on the image's centre, and nothing is reported in the padding.
#[test]
fn padded_fit_maps_back_to_the_image() {
    let mut m = marknet().with_mre(mre()).unwrap();
    m.set_fit(gelstereo_markers::InputFit::Pad);
    // 80x60 into 64x64: scale 0.8 -> 64x48, 8 rows of padding above and below.
    let g = m.geometry(gelstereo_core::ImageSize {
        width: 80,
        height: 60,
    });
    assert_eq!(
        (g.scale_x, g.scale_y, g.offset_x, g.offset_y),
        (1.25, 1.25, 0.0, 8.0)
    );
    let centre = Point2::new(
        (32.0 - g.offset_x) * g.scale_x - 0.5,
        (32.0 - g.offset_y) * g.scale_y - 0.5,
    );
    assert_eq!(centre, Point2::new(39.5, 29.5));
    // Small images are never enlarged: 40x30 sits at scale 1 in the middle.
    let g = m.geometry(gelstereo_core::ImageSize {
        width: 40,
        height: 30,
    });
    assert_eq!(
        (g.scale_x, g.scale_y, g.offset_x, g.offset_y),
        (1.0, 1.0, 12.0, 17.0)
    );
    let img = image("dots_80x60.png");
    let found = m.detect(&img).unwrap();
    assert!(
        found
            .iter()
            .all(|d| (-0.5..=79.5).contains(&d.position.x) && (-0.5..=59.5).contains(&d.position.y))
    );
    // A shape the stretch rejects is fine when padded.
    let wide = Mat::new_rows_cols_with_default(20, 200, CV_8UC3, Scalar::all(128.0)).unwrap();
    assert!(m.detect(&wide).is_ok());
    assert!("squash".parse::<gelstereo_markers::InputFit>().is_err());
}

/// How many of `want` have no detection of `got` of their own within the tolerances.
fn unmatched(got: &[Detection], want: &[Detection], tol_px: f64, tol_c: f32) -> usize {
    let mut used = vec![false; got.len()];
    want.iter()
        .filter(|w| {
            let close = |g: &Detection| {
                g.position.distance(w.position) <= tol_px && (g.confidence - w.confidence).abs() <= tol_c
            };
            match (0..got.len()).find(|&i| !used[i] && close(&got[i])) {
                Some(i) => {
                    used[i] = true;
                    false
                }
                None => true,
            }
        })
        .count()
}

fn expected_auto() -> Value {
    let text = std::fs::read_to_string(fixtures().join("expected_auto.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn layout_of(v: &Value) -> gelstereo_markers::InputLayout {
    let u = |k: &str| v[k].as_u64().unwrap() as u32;
    gelstereo_markers::InputLayout {
        input_width: u("input_w"),
        input_height: u("input_h"),
        scaled_width: u("scaled_w"),
        scaled_height: u("scaled_h"),
        offset_x: u("ox"),
        offset_y: u("oy"),
    }
}

/// The "auto" layout for a table of image sizes and pitches equals the trainer's `fit_layout`
/// (nominal 416 x 416, multiple 32, pitch range 9-24, target 12), isotropic and preferring the stretch.
#[test]
fn auto_layout_matches_the_trainer() {
    let e = expected_auto();
    let table = |key: &str| e[key].as_array().unwrap().clone();
    let (isotropic, stretch) = (
        table("fit_layout_nominal_416"),
        table("fit_layout_nominal_416_prefer_stretch"),
    );
    assert!(isotropic.len() >= 30 && stretch.len() >= 20);
    let cases = isotropic
        .into_iter()
        .map(|c| (c, false))
        .chain(stretch.into_iter().map(|c| (c, true)));
    for (case, prefer_stretch) in cases {
        let fit = gelstereo_markers::AutoFit {
            multiple: 32,
            pitch_min_px: 9.0,
            pitch_max_px: 24.0,
            pitch_target_px: 12.0,
            prefer_stretch,
        };
        let size = gelstereo_core::ImageSize {
            width: case["width"].as_u64().unwrap() as u32,
            height: case["height"].as_u64().unwrap() as u32,
        };
        let got = gelstereo_markers::fit_layout(size, case["pitch_px"].as_f64(), 416, 416, &fit);
        assert_eq!(got, layout_of(&case["layout"]), "{case}");
    }
}

/// The probe layout (twice the nominal scale, isotropic, no margin) for a table of image sizes equals
/// the trainer's `probe_layout`.
#[test]
fn probe_layout_matches_the_trainer() {
    let e = expected_auto();
    let cases = e["probe_layout_nominal_416"].as_array().unwrap();
    assert!(cases.len() >= 5);
    let fit = gelstereo_markers::AutoFit {
        multiple: 32,
        pitch_min_px: 9.0,
        pitch_max_px: 24.0,
        pitch_target_px: 12.0,
        prefer_stretch: false,
    };
    for case in cases {
        let size = gelstereo_core::ImageSize {
            width: case["width"].as_u64().unwrap() as u32,
            height: case["height"].as_u64().unwrap() as u32,
        };
        let got = gelstereo_markers::probe_layout(size, 416, 416, &fit);
        assert_eq!(got, layout_of(&case["layout"]), "{case}");
    }
}

/// A dynamic-input model (`gelstereo-marknet/2`) under the default fit: a first pass without a pitch
/// (probed at twice the scale when it finds few confident markers, as on these sparse dot images),
/// then a pass at the scale the measured pitch asks for, detections as the trainer's MarknetRunner
/// finds them; with the pitch remembered, the next image of that size starts from the final layout.
#[test]
fn auto_fit_passes_match_the_trainer() {
    let e = expected_auto();
    let path = fixtures().join("marknet_tiny_auto.onnx");
    let post = post_of(&expected());
    for name in ["dots_80x60.png", "dots_160x120.png"] {
        let want = &e["images"][name];
        let img = image(name);
        let size = gelstereo_core::ImageSize {
            width: img.cols() as u32,
            height: img.rows() as u32,
        };
        let mut m = Marknet::load(&path, &options()).unwrap();
        assert!(m.contract().auto_fit.is_some());
        m.set_postprocess(post);
        assert_eq!(m.next_layout(size), layout_of(&want["first_layout"]), "{name}");
        let got = sorted(m.detect(&img).unwrap());
        // At the final scale the random network leaves ~900 candidates on this small image: a few
        // near-ties (de-duplication between neighbours of equal confidence within the resize rounding,
        // the cut at the image border) may go the other way; the layouts above and below are exact.
        let want_rows = rows(&want["marknet"]);
        assert!(want_rows.len() > 100, "{name}: {} rows", want_rows.len());
        let unmatched = unmatched(&got, &want_rows, 0.05, 0.01);
        assert!(
            got.len().abs_diff(want_rows.len()) * 100 <= want_rows.len(),
            "{name}: {} vs {}",
            got.len(),
            want_rows.len()
        );
        assert!(
            unmatched * 100 <= want_rows.len(),
            "{name}: {unmatched} of {} unmatched",
            want_rows.len()
        );
        // Remembered: the next frame of this size starts at the final layout. (A random network has no
        // stable pitch, so what it measures there is not checked.)
        assert_eq!(m.next_layout(size), layout_of(&want["final_layout"]), "{name}");
        // Not remembered: every image starts from the first layout again.
        m.set_pitch_memory(false);
        assert_eq!(m.next_layout(size), layout_of(&want["first_layout"]), "{name}");
        assert_same(&sorted(m.detect(&img).unwrap()), &got, 1e-9, 0.0, name);
    }
}
