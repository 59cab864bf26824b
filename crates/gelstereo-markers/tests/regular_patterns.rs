//! The shipped Marknet-MRE on regular patterns that are no marker gel (`docs/localization.md`,
//! "Dots on a gel"): checkerboards, egg-crates and uniform noise give at most a handful of markers;
//! a perforated plate whose holes are as wide as markers is a marker lattice to the localizer, and
//! its holes are found. Patterns are drawn here, at several sizes and phases.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: a failure is a test failure

mod shipped;
use shipped::shipped;

use gelstereo_markers::{Localizer, Marknet};
use opencv::core::{CV_8UC3, Mat, Point, Scalar};
use opencv::imgproc;
use opencv::prelude::*;

/// At most this many markers on an image without markers.
const HANDFUL: usize = 5;

/// A `w x h` BGR image whose pixel (x, y) is `grey(x, y)` (clamped to 0-255).
fn paint(w: i32, h: i32, grey: impl Fn(f64, f64) -> f64) -> Mat {
    let mut m = Mat::new_rows_cols_with_default(h, w, CV_8UC3, Scalar::all(0.0)).unwrap();
    for (i, px) in m.data_bytes_mut().unwrap().chunks_mut(3).enumerate() {
        let (x, y) = ((i % w as usize) as f64, (i / w as usize) as f64);
        px.fill(grey(x, y).round().clamp(0.0, 255.0) as u8);
    }
    m
}

fn assert_at_most_a_handful(net: &mut Marknet, what: &str, img: &Mat) {
    let n = net.detect(img).unwrap().len();
    assert!(n <= HANDFUL, "{what}: {n} markers");
}

const SIZES: [(i32, i32); 2] = [(640, 480), (320, 240)];

/// Black and white squares of 8-40 px, the squares' corners off the image's by a few px.
#[test]
fn checkerboards_give_at_most_a_handful() {
    let mut net = shipped();
    for (w, h) in SIZES {
        for side in [8.0, 12.0, 16.0, 20.0, 24.0, 30.0, 40.0] {
            let shift = side / 3.0;
            let img = paint(w, h, |x, y| {
                let cell = ((x + shift) / side).floor() + ((y + shift) / side).floor();
                if cell.rem_euclid(2.0) == 0.0 { 20.0 } else { 235.0 }
            });
            assert_at_most_a_handful(&mut net, &format!("{w}x{h}, {side} px squares"), &img);
        }
    }
}

/// `sin(u) sin(v)` over a grid of 10-36 px turned by 0 and 20 degrees: a lattice of dark and light
/// blobs, like an egg-crate or a smooth weave.
#[test]
fn egg_crates_give_at_most_a_handful() {
    let mut net = shipped();
    for period in [10.0, 16.0, 24.0, 36.0] {
        for degrees in [0.0f64, 20.0] {
            let (c, s) = (degrees.to_radians().cos(), degrees.to_radians().sin());
            let k = std::f64::consts::TAU / period;
            let img = paint(640, 480, |x, y| {
                let (u, v) = (x * c + y * s, -x * s + y * c);
                128.0 + 100.0 * (k * u).sin() * (k * v).sin()
            });
            assert_at_most_a_handful(&mut net, &format!("period {period} px at {degrees} deg"), &img);
        }
    }
}

/// Uniform random noise, per channel, at three sizes (the fine probe enlarges the smallest four
/// times, where single pixels become blobs on a regular grid).
#[test]
fn uniform_noise_gives_at_most_a_handful_at_every_size() {
    let mut net = shipped();
    for (w, h) in [(640, 480), (427, 320), (320, 240)] {
        let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC3, Scalar::all(0.0)).unwrap();
        let mut state = 7u32;
        for v in img.data_bytes_mut().unwrap() {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            *v = (state >> 24) as u8;
        }
        assert_at_most_a_handful(&mut net, &format!("noise {w}x{h}"), &img);
    }
}

/// A perforated plate whose round holes are half the pitch wide, dark holes in a light plate and
/// light holes in a dark one: its image is a marker gel's (trained markers are 0.25-0.75 pitch
/// wide), so the localizer reports its holes, every whole one on its hole.
#[test]
fn a_plate_with_marker_sized_holes_is_a_marker_lattice() {
    let mut net = shipped();
    let (pitch, radius) = (24.0, 6.0);
    for (plate, hole) in [(200.0, 25.0), (40.0, 235.0)] {
        let mut img = Mat::new_rows_cols_with_default(480, 640, CV_8UC3, Scalar::all(plate)).unwrap();
        let mut holes = Vec::new();
        for r in 0..20 {
            for c in 0..26 {
                let (x, y) = (14.3 + f64::from(c) * pitch, 12.6 + f64::from(r) * pitch);
                let centre = Point::new((x * 16.0).round() as i32, (y * 16.0).round() as i32);
                imgproc::circle(
                    &mut img,
                    centre,
                    (radius * 16.0) as i32,
                    Scalar::all(hole),
                    -1,
                    imgproc::LINE_AA,
                    4,
                )
                .unwrap();
                holes.push((x, y));
            }
        }
        let found = net.detect(&img).unwrap();
        let missed = holes
            .iter()
            .filter(|&&(x, y)| {
                !found
                    .iter()
                    .any(|d| (d.position.x - x).hypot(d.position.y - y) <= 0.1 * pitch)
            })
            .count();
        assert_eq!(
            missed,
            0,
            "plate {plate}: {missed} of {} holes missed",
            holes.len()
        );
        assert_eq!(found.len(), holes.len(), "plate {plate}");
    }
}

/// The painter draws what the tests above say they draw.
#[test]
fn the_painted_checkerboard_alternates() {
    // The painter's checkerboard: a pixel in each of two neighbouring squares.
    let img = paint(64, 48, |x, y| {
        if ((x / 16.0).floor() + (y / 16.0).floor()).rem_euclid(2.0) == 0.0 {
            20.0
        } else {
            235.0
        }
    });
    let at = |x: i32, y: i32| *img.at_2d::<opencv::core::Vec3b>(y, x).unwrap();
    assert_eq!(at(3, 3)[0], 20);
    assert_eq!(at(19, 3)[0], 235);
    assert_eq!(at(19, 19)[0], 20);
}
