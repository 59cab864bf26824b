//! Criterion benches of marker localization on a 640x480 view (the reference sensor's size):
//! the blob baseline (tuned and OpenCV-default parameters), Marknet + MRE per view and per stereo pair,
//! and the post-processing alone.
//!
//! `cargo bench -p gelstereo-markers --bench localize`. Models: `$GELSTEREO_BENCH_MODELS/{marknet,mre}.onnx`,
//! else `data/models/`; without them the Marknet benches are skipped (with a note). The image is drawn
//! here: a lattice of ~1,000 dark dots (pitch 16 px, radius 3.5 px) on a shaded background, which is
//! the kind of image the blob detector's parameters were tuned on.
//! `gelstereo bench` measures the same code side by side on real dataset images.

use std::hint::black_box;
use std::path::{Path, PathBuf};

use criterion::{Criterion, criterion_group, criterion_main};
use gelstereo_core::{Detection, Point2, StereoPair};
use gelstereo_markers::postprocess::{DecodeGeometry, PostProcess, Selection, decode};
use gelstereo_markers::{BlobLocalizer, BlobParams, Localizer, Marknet, Mre, SessionOptions};
use opencv::core::{CV_8UC3, Mat, Point, Scalar};
use opencv::imgproc;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// 640x480, ~1,000 dark dots; returns `None` if OpenCV fails (then the benches are skipped).
fn view(shift_px: i32) -> Option<Mat> {
    let mut img =
        Mat::new_rows_cols_with_default(480, 640, CV_8UC3, Scalar::new(190.0, 200.0, 215.0, 0.0)).ok()?;
    for r in 0..28 {
        for c in 0..38 {
            let centre = Point::new((20 + c * 16 + shift_px) * 16 + 8, (24 + r * 16) * 16 + 8);
            imgproc::circle(&mut img, centre, 56, Scalar::all(45.0), -1, imgproc::LINE_AA, 4).ok()?;
        }
    }
    let mut blurred = Mat::default();
    imgproc::gaussian_blur_def(&img, &mut blurred, opencv::core::Size::new(3, 3), 0.8).ok()?;
    Some(blurred)
}

fn bench_blob(c: &mut Criterion, image: &Mat) {
    let tuned = BlobParams::from_json_file(&root().join(gelstereo_markers::blob::DEFAULT_PARAMS_FILE));
    for (name, params) in [
        ("blob tuned, 640x480 view", tuned.ok()),
        (
            "blob OpenCV defaults, 640x480 view",
            BlobParams::opencv_defaults().ok(),
        ),
    ] {
        let Some(mut blob) = params.and_then(|p| BlobLocalizer::new(p).ok()) else {
            eprintln!("skipping {name}: parameters unavailable");
            continue;
        };
        c.bench_function(name, |b| {
            b.iter(|| black_box(blob.detect(black_box(image)).map(|d| d.len())))
        });
    }
}

fn bench_marknet(c: &mut Criterion, pair: &StereoPair<Mat>) {
    let dir =
        std::env::var_os("GELSTEREO_BENCH_MODELS").map_or_else(|| root().join("data/models"), PathBuf::from);
    let options = SessionOptions::default();
    let loaded = Mre::load(&dir.join("mre.onnx"), &options)
        .and_then(|mre| Marknet::load(&dir.join("marknet.onnx"), &options)?.with_mre(mre));
    let mut net = match loaded {
        Ok(n) => n,
        Err(e) => {
            eprintln!("skipping the Marknet benches: {e}");
            return;
        }
    };
    c.bench_function("marknet network only (resize + inference), 640x480 view", |b| {
        b.iter(|| black_box(net.raw_output(&[black_box(&pair.left)]).map(|r| r.1.len())))
    });
    c.bench_function("marknet-mre, 640x480 view", |b| {
        b.iter(|| black_box(net.detect(black_box(&pair.left)).map(|d| d.len())))
    });
    c.bench_function("marknet-mre, 640x480 stereo pair (batch 2)", |b| {
        b.iter(|| black_box(net.detect_stereo(black_box(pair)).map(|d| d.left.len())))
    });
}

/// Decoding a 52 x 52 x 5 output and post-processing what a trained net gives on the reference sensor:
/// ~530 confident markers (slot 0 of every fifth cell) plus ~200 weak candidates.
fn bench_postprocess(c: &mut Criterion) {
    let g = DecodeGeometry {
        grid_y: 52,
        grid_x: 52,
        candidates: 5,
        stride: 8.0,
        scale_x: 640.0 / 416.0,
        scale_y: 480.0 / 416.0,
        offset_x: 0.0,
        offset_y: 0.0,
    };
    // Deterministic pseudo-random logits.
    let mut raw = vec![0f32; g.values_per_image()];
    let mut state = 12345u32;
    let mut rnd = || {
        state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (state >> 8) as f32 / (1u32 << 24) as f32
    };
    for (i, v) in raw.iter_mut().enumerate() {
        let (cell, slot, value) = (i / 15, (i % 15) / 3, i % 3);
        *v = match (value, slot) {
            (2, 0) if cell % 5 == 0 => 1.0 + 3.0 * rnd(),
            (2, _) => -12.0 + 10.0 * rnd(),
            _ => 4.0 * rnd() - 2.0,
        };
    }
    let post = PostProcess::default();
    c.bench_function("decode 52x52x5 + post-process (marknet-mre, before MRE)", |b| {
        b.iter(|| {
            let cands: Vec<Detection> = decode(black_box(&raw), &g, post.conf_low);
            black_box(Selection::new(cands, &post, true).features.len())
        })
    });
    let lattice: Vec<Detection> = (0..1000)
        .map(|i| Detection {
            position: Point2::new(f64::from(i % 40) * 16.0, f64::from(i / 40) * 16.0),
            confidence: 0.9,
        })
        .collect();
    let coords: Vec<[f64; 2]> = lattice.iter().map(|d| [d.position.x, d.position.y]).collect();
    c.bench_function("kiddo tree of 1,000 points", |b| {
        b.iter(|| {
            let t: Option<kiddo::ImmutableKdTree<f64, 2>> =
                kiddo::ImmutableKdTree::new_from_slice(black_box(&coords)).ok();
            black_box(t.map(|t| t.size()))
        })
    });
    c.bench_function("pitch of 1,000 candidates", |b| {
        b.iter(|| {
            black_box(gelstereo_markers::postprocess::estimate_pitch_px(
                black_box(&lattice),
                0.4,
            ))
        })
    });
    c.bench_function("pitch + de-duplication of 1,000 candidates", |b| {
        b.iter(|| black_box(Selection::new(black_box(lattice.clone()), &post, false).kept))
    });
}

fn benches(c: &mut Criterion) {
    let (Some(left), Some(right)) = (view(0), view(3)) else {
        eprintln!("skipping: OpenCV could not draw the bench image");
        return;
    };
    bench_blob(c, &left);
    bench_marknet(c, &StereoPair::new(left, right));
    bench_postprocess(c);
}

criterion_group!(localize, benches);
criterion_main!(localize);
