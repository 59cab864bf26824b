//! Where `gelstereo detect` places markers under textures that multiply the whole image, as the
//! widened simulator's banding does (docs/experiments/localization-placement.md): the shipped model,
//! every default, dots drawn at known sub-pixel centres.

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::f64::consts::TAU;
use std::path::Path;

#[path = "../../../tests/common/mod.rs"]
mod common;
use common::{gelstereo, text};

use opencv::core::{CV_8UC3, Mat, MatTrait, Point, Scalar, Vector};
use opencv::{imgcodecs, imgproc};

const PITCH_PX: f64 = 29.0;
const BOUND_PX: f64 = 0.3;

/// Stripes across `angle` (0: vertical stripes, pi/2: horizontal ones) of `period` pitches,
/// multiplying every pixel by `1 + gain * sin`.
struct Bands {
    name: &'static str,
    angle: f64,
    period: f64,
    gain: f64,
}

/// A 320 x 240 gel, 10 x 7 dark dots of radius 5.5 px at sub-pixel centres (drawn at 1/16 px), the
/// lattice slightly sheared so that no two dots sit alike on the pixel grid, under `bands`.
fn banded_gel(bands: &Bands) -> (Mat, Vec<(f64, f64)>) {
    let centres: Vec<(f64, f64)> = (0..7)
        .flat_map(|r| {
            (0..10).map(move |c| {
                let (r, c) = (f64::from(r), f64::from(c));
                (20.3 + PITCH_PX * c + 0.37 * r, 18.6 + PITCH_PX * r + 0.21 * c)
            })
        })
        .collect();
    let mut img =
        Mat::new_rows_cols_with_default(240, 320, CV_8UC3, Scalar::new(190.0, 180.0, 170.0, 0.0)).unwrap();
    for &(x, y) in &centres {
        let at = Point::new((x * 16.0).round() as i32, (y * 16.0).round() as i32);
        imgproc::circle(&mut img, at, 88, Scalar::all(45.0), -1, imgproc::LINE_AA, 4).unwrap();
    }
    let (sin, cos) = bands.angle.sin_cos();
    for y in 0..240 {
        for x in 0..320 {
            let s = f64::from(x) * cos + f64::from(y) * sin;
            let g = 1.0 + bands.gain * (TAU * s / (bands.period * PITCH_PX)).sin();
            let px = img.at_2d_mut::<opencv::core::Vec3b>(y, x).unwrap();
            for v in px.iter_mut() {
                *v = (f64::from(*v) * g).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    (img, centres)
}

/// Banding of the simulator's kind (a sine of 20 % gain, periods that are no multiple of the pitch,
/// horizontal, vertical and oblique stripes) neither misses a dot nor pulls the dots of an image by
/// more than 0.3 px on average along either axis, and each axis's RMS error stays that of a plain gel.
#[test]
fn banding_does_not_pull_marker_positions() {
    let cases = [
        Bands {
            name: "plain",
            angle: 0.0,
            period: 1.0,
            gain: 0.0,
        },
        Bands {
            name: "rows-1.37",
            angle: TAU / 4.0,
            period: 1.37,
            gain: 0.2,
        },
        Bands {
            name: "rows-0.61",
            angle: TAU / 4.0,
            period: 0.61,
            gain: 0.2,
        },
        Bands {
            name: "rows-2.45",
            angle: TAU / 4.0,
            period: 2.45,
            gain: 0.2,
        },
        Bands {
            name: "columns-1.37",
            angle: 0.0,
            period: 1.37,
            gain: 0.2,
        },
        Bands {
            name: "oblique-1.9",
            angle: 0.6,
            period: 1.9,
            gain: 0.2,
        },
    ];
    let dir = tempfile::tempdir().unwrap();
    let mut truth = Vec::new();
    for case in &cases {
        let (img, centres) = banded_gel(case);
        let path = dir.path().join(format!("{}.png", case.name));
        assert!(imgcodecs::imwrite(path.to_str().unwrap(), &img, &Vector::new()).unwrap());
        truth.push((case.name, centres));
    }
    let out = gelstereo(&["detect", "--threads", "1", dir.path().to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    let found: Vec<(String, f64, f64)> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let stem = Path::new(f[0])
                .file_stem()
                .unwrap()
                .to_string_lossy()
                .into_owned();
            (stem, f[1].parse().unwrap(), f[2].parse().unwrap())
        })
        .collect();
    for (name, centres) in &truth {
        let mine: Vec<(f64, f64)> = found
            .iter()
            .filter(|d| d.0 == *name)
            .map(|d| (d.1, d.2))
            .collect();
        let errors: Vec<(f64, f64)> = centres
            .iter()
            .map(|c| {
                let nearest = mine
                    .iter()
                    .min_by(|a, b| {
                        (a.0 - c.0)
                            .hypot(a.1 - c.1)
                            .total_cmp(&(b.0 - c.0).hypot(b.1 - c.1))
                    })
                    .unwrap_or_else(|| panic!("{name}: no marker found"));
                (nearest.0 - c.0, nearest.1 - c.1)
            })
            .collect();
        assert!(
            errors.iter().all(|e| e.0.hypot(e.1) <= 0.25 * PITCH_PX),
            "{name}: a dot is missed: {errors:?}"
        );
        let n = errors.len() as f64;
        let mean = |k: fn(&(f64, f64)) -> f64| errors.iter().map(k).sum::<f64>() / n;
        let rms = |k: fn(&(f64, f64)) -> f64| (errors.iter().map(|e| k(e).powi(2)).sum::<f64>() / n).sqrt();
        let (mx, my) = (mean(|e| e.0), mean(|e| e.1));
        assert!(
            mx.abs() <= BOUND_PX && my.abs() <= BOUND_PX,
            "{name}: bias ({mx:+.3}, {my:+.3}) px"
        );
        let (rx, ry) = (rms(|e| e.0), rms(|e| e.1));
        assert!(
            rx <= 0.75 && ry <= 0.75,
            "{name}: RMS error ({rx:.2}, {ry:.2}) px"
        );
    }
}
