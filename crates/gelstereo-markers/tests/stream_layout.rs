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
