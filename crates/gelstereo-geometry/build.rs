//! Which OpenCV headers the `opencv` crate binds, where its generated API differs between the
//! versions gelstereo builds against (Debian's 4.6, the minimal static build of
//! scripts/build-wheel-minimal.sh): a cfg for each difference, found in the headers themselves.
//! The headers are looked up as the `opencv` crate looks them up through its environment variable
//! `OPENCV_INCLUDE_PATHS`, else in the system's include folders. gelstereo-markers shares this script.

use std::path::{Path, PathBuf};

/// (cfg, header, text): the cfg is set when the header holds the text.
const DIFFERENCES: [(&str, &str, &str); 2] = [
    // An overload with per-view rotations and translations: the bindings then name the
    // per-view-errors overload `stereo_calibrate_1` instead of `stereo_calibrate_extended`.
    (
        "opencv_stereo_calibrate_rvecs",
        "calib3d.hpp",
        "OutputArrayOfArrays rvecs, OutputArrayOfArrays tvecs, OutputArray perViewErrors",
    ),
    // SimpleBlobDetector::Params gains a field `collect_contours`.
    (
        "opencv_blob_collect_contours",
        "features2d.hpp",
        "bool collectContours;",
    ),
];

fn main() {
    println!("cargo::rerun-if-env-changed=OPENCV_INCLUDE_PATHS");
    let include = include_folder();
    for (cfg, header, text) in DIFFERENCES {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
        let Some(folder) = &include else { continue };
        let path = folder.join("opencv2").join(header);
        println!("cargo::rerun-if-changed={}", path.display());
        if std::fs::read_to_string(&path).is_ok_and(|source| source.contains(text)) {
            println!("cargo::rustc-cfg={cfg}");
        }
    }
}

/// The first folder holding `opencv2/core/version.hpp`.
fn include_folder() -> Option<PathBuf> {
    let from_env = std::env::var("OPENCV_INCLUDE_PATHS").unwrap_or_default();
    let from_env: Vec<String> = from_env
        .trim_start_matches('+')
        .split(',')
        .filter(|dir| !dir.is_empty())
        .map(String::from)
        .collect();
    from_env
        .iter()
        .map(String::as_str)
        .chain(["/usr/include/opencv4", "/usr/local/include/opencv4"])
        .map(PathBuf::from)
        .find(|dir| Path::new(dir).join("opencv2/core/version.hpp").is_file())
}
