//! The "auto" fit on a stream of one sensor (`docs/model-contract.md`, Layouts): with the pitch
//! remembered, the first frame of a size runs under the layout every later frame gets, so a
//! tracker's reference frame and the frames compared with it are localized at one scale.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: a failure is a test failure

use std::path::{Path, PathBuf};

use gelstereo_core::ImageSize;
use gelstereo_markers::{Marknet, SessionOptions};
use opencv::core::{Mat, MatTraitConst};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn sample_frame(view: &str, frame: u32) -> Mat {
    let path = root().join(format!("data/sample/press-slide/{view}/{frame:06}.jpg"));
    let m = opencv::imgcodecs::imread(path.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    assert!(!m.empty(), "{} unreadable", path.display());
    m
}

/// The shipped model fits the bundled 640 x 480 sample isotropically; without a pitch its layout has no
/// margin and a slightly larger scale than the layout of the measured pitch.
#[test]
fn the_first_frame_of_a_stream_is_localized_under_the_layout_of_the_next() {
    let options = SessionOptions {
        intra_threads: 1,
        use_cuda: false,
    };
    let mut net = Marknet::load(&root().join("data/models/marknet.onnx"), &options).unwrap();
    let (left, right) = (sample_frame("left", 0), sample_frame("right", 0));
    let size = ImageSize {
        width: left.cols() as u32,
        height: left.rows() as u32,
    };
    let unmeasured = net.next_layout(size);
    let first = net.detect_batch(&[&left, &right]).unwrap();
    let remembered = net.next_layout(size);
    assert_ne!(
        unmeasured, remembered,
        "the measured pitch should change the isotropic layout"
    );
    // The same pair again, now under the remembered layout: the same markers at the same positions.
    let again = net.detect_batch(&[&left, &right]).unwrap();
    assert_eq!(net.next_layout(size), remembered);
    for (view, (a, b)) in first.iter().zip(&again).enumerate() {
        assert!(a.len() > 400, "view {view}: {} markers", a.len());
        assert_eq!(a.len(), b.len(), "view {view}");
        for (p, q) in a.iter().zip(b) {
            assert_eq!(
                (p.position.x, p.position.y),
                (q.position.x, q.position.y),
                "view {view}"
            );
        }
    }
}

fn shipped() -> Marknet {
    let options = SessionOptions {
        intra_threads: 1,
        use_cuda: false,
    };
    Marknet::load(&root().join("data/models/marknet.onnx"), &options).unwrap()
}

fn size_of(m: &Mat) -> ImageSize {
    ImageSize {
        width: m.cols() as u32,
        height: m.rows() as u32,
    }
}

/// `image` moved right by `dx` px, the uncovered columns repeating the border.
fn shifted(image: &Mat, dx: f64) -> Mat {
    let m = Mat::from_slice_2d(&[[1.0, 0.0, dx], [0.0, 1.0, 0.0]]).unwrap();
    let mut out = Mat::default();
    opencv::imgproc::warp_affine(
        image,
        &mut out,
        &m,
        image.size().unwrap(),
        opencv::imgproc::INTER_NEAREST,
        opencv::core::BORDER_REPLICATE,
        opencv::core::Scalar::default(),
    )
    .unwrap();
    out
}

/// Each marker of `found` with its distance to the nearest of `reference`, px.
fn nearest_distances(
    found: &[gelstereo_core::Detection],
    reference: &[gelstereo_core::Detection],
) -> Vec<f64> {
    found
        .iter()
        .map(|d| {
            reference
                .iter()
                .map(|r| (d.position.x - r.position.x).hypot(d.position.y - r.position.y))
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

/// The sample's lattice fills 365 x 397 px of its 640 x 480 views: after the first frame each view
/// runs on a window of the network input around its own lattice, smaller than the input. The first
/// frame is localized on that window too (the same markers when it comes again), and it finds every
/// marker the whole input does, the median one within a thousandth of a pixel of it (the window's
/// corners lie on the network's coarsest grid), the outermost within a quarter of a pixel.
#[test]
fn each_view_of_a_stream_runs_on_a_window_around_its_lattice() {
    let (left, right) = (sample_frame("left", 0), sample_frame("right", 0));
    let size = size_of(&left);
    let mut net = shipped();
    let first = net.detect_batch(&[&left, &right]).unwrap();
    let mut whole = shipped();
    whole.set_lattice_window(false);
    let reference = whole.detect_batch(&[&left, &right]).unwrap();
    let again = net.detect_batch(&[&left, &right]).unwrap();
    for slot in 0..2 {
        let r = net.lattice_window(size, slot).expect("a window for each view");
        let (w, l) = (r.window, r.layout);
        assert!(w.width * w.height < l.input_width * l.input_height, "{r:?}");
        assert_eq!(whole.lattice_window(size, slot), None);
        assert_eq!(first[slot], again[slot], "view {slot}: the first frame again");
        assert_eq!(first[slot].len(), reference[slot].len(), "view {slot}");
        let d = nearest_distances(&first[slot], &reference[slot]);
        let mut sorted = d.clone();
        sorted.sort_by(f64::total_cmp);
        let (median, worst) = (sorted[d.len() / 2], sorted[d.len() - 1]);
        assert!(
            median < 0.001 && worst < 0.25,
            "view {slot}: markers {median} px (median) and {worst} px (worst) from the whole input's"
        );
    }
}

/// A frame whose lattice has moved towards an edge of the window that lies inside the input runs on
/// the whole input: the same markers as a localizer that never uses windows.
#[test]
fn a_lattice_that_leaves_its_window_is_localized_on_the_whole_input() {
    let (left, right) = (sample_frame("left", 0), sample_frame("right", 0));
    let mut net = shipped();
    let mut whole = shipped();
    whole.set_lattice_window(false);
    net.detect_batch(&[&left, &right]).unwrap();
    whole.detect_batch(&[&left, &right]).unwrap();
    let (moved_left, moved_right) = (shifted(&left, 45.0), shifted(&right, -45.0));
    let got = net.detect_batch(&[&moved_left, &moved_right]).unwrap();
    let want = whole.detect_batch(&[&moved_left, &moved_right]).unwrap();
    assert!(
        got[0].len() > 500 && got[1].len() > 500,
        "{} and {} markers",
        got[0].len(),
        got[1].len()
    );
    assert_eq!(got, want);
}
