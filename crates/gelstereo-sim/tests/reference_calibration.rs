//! The calibration shipped in `calib/` (OpenCV YAML and the mrcal pair) is the reference sensor's
//! (`calib/reference-sensor.json`): regenerate it with the command in `calib/README.md` when the sensor
//! file changes, and this test says so when they drift apart.
#![allow(clippy::unwrap_used)]

use std::path::Path;

use gelstereo_geometry::{Camera, StereoRig};
use gelstereo_sim::SensorSpec;

fn calib_dir() -> &'static Path {
    Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../calib"))
}

fn assert_same_camera(a: &Camera, b: &Camera, what: &str) {
    assert_eq!(a.image_size, b.image_size, "{what}: image size");
    for (x, y, name) in [
        (a.fx, b.fx, "fx"),
        (a.fy, b.fy, "fy"),
        (a.cx, b.cx, "cx"),
        (a.cy, b.cy, "cy"),
    ] {
        assert!((x - y).abs() < 1e-9, "{what}: {name} {x} vs {y}");
    }
    assert_eq!(
        a.distortion.coeffs.len(),
        b.distortion.coeffs.len(),
        "{what}: distortion length"
    );
    for (x, y) in a.distortion.coeffs.iter().zip(&b.distortion.coeffs) {
        assert!((x - y).abs() < 1e-12, "{what}: distortion {x} vs {y}");
    }
}

fn assert_same_rig(shipped: &StereoRig, truth: &StereoRig, what: &str) {
    assert_same_camera(&shipped.left, &truth.left, &format!("{what} left"));
    assert_same_camera(&shipped.right, &truth.right, &format!("{what} right"));
    let dt = (shipped.right_from_left.translation.vector - truth.right_from_left.translation.vector).norm();
    let dr = shipped
        .right_from_left
        .rotation
        .angle_to(&truth.right_from_left.rotation);
    assert!(
        dt < 1e-9 && dr < 1e-9,
        "{what}: extrinsics differ by {dt} mm, {dr} rad"
    );
}

#[test]
fn shipped_calibration_files_are_the_reference_sensors() {
    let spec = SensorSpec::load(&calib_dir().join("reference-sensor.json")).unwrap();
    let truth = spec.build().unwrap().rig;
    let yaml = StereoRig::load(calib_dir().join("reference.yaml")).unwrap();
    assert_same_rig(&yaml, &truth, "calib/reference.yaml");
    let mrcal = StereoRig::load(calib_dir()).unwrap();
    assert_same_rig(&mrcal, &truth, "calib/{left,right}.cameramodel");
}
