//! Stereo checkerboard calibration from two folders of images (`gelstereo calibrate`): pairs the
//! images by file name, finds the board in both views in parallel, calibrates with OpenCV
//! ([`gelstereo_geometry::checkerboard`]).

use std::path::{Path, PathBuf};

use gelstereo_core::{ImageSize, Point2};
use gelstereo_geometry::checkerboard::{CalibrationReport, calibrate_stereo, find_corners};
use gelstereo_geometry::{Board, CalibrationOptions, StereoCorners};
use opencv::core::MatTraitConst;
use rayon::prelude::*;

use crate::{Error, Result};

/// A calibration from two folders, with what was left out.
#[derive(Debug, Clone)]
pub struct FolderCalibration {
    /// OpenCV's result: the rig, RMS and epipolar errors, per-pair errors.
    pub report: CalibrationReport,
    /// The images' size.
    pub image_size: ImageSize,
    /// Image pairs found (same file name in both folders).
    pub pairs: usize,
    /// Pairs whose board was not found: `NAME (left|right|both)`.
    pub not_found: Vec<String>,
    /// Images without a counterpart in the other folder.
    pub unpaired: Vec<String>,
}

/// One detected pair: file name, image size, left and right corners (`None`: board not found).
type Detected = (String, ImageSize, Option<Vec<Point2>>, Option<Vec<Point2>>);

fn size_of(m: &opencv::core::Mat) -> ImageSize {
    ImageSize {
        width: u32::try_from(m.cols()).unwrap_or(0),
        height: u32::try_from(m.rows()).unwrap_or(0),
    }
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// A file name and the left and right images of that name.
type NamedPair = (String, PathBuf, PathBuf);

/// Pairs `left_dir` and `right_dir` by file name.
fn pair_images(left_dir: &Path, right_dir: &Path) -> Result<(Vec<NamedPair>, Vec<String>)> {
    let left = gelstereo_io::images::list_images(left_dir)?;
    let right = gelstereo_io::images::list_images(right_dir)?;
    let mut unpaired = Vec::new();
    let mut pairs = Vec::new();
    for l in &left {
        let name = file_name(l);
        match right.iter().find(|r| file_name(r) == name) {
            Some(r) => pairs.push((name, l.clone(), r.clone())),
            None => unpaired.push(format!("{} (no right image)", l.display())),
        }
    }
    for r in &right {
        if !left.iter().any(|l| file_name(l) == file_name(r)) {
            unpaired.push(format!("{} (no left image)", r.display()));
        }
    }
    if pairs.is_empty() {
        return Err(Error::Invalid(format!(
            "no image pairs: {} and {} share no image file names ({} and {} images)",
            left_dir.display(),
            right_dir.display(),
            left.len(),
            right.len()
        )));
    }
    Ok((pairs, unpaired))
}

fn detect(name: &str, l: &Path, r: &Path, board: &Board, options: &CalibrationOptions) -> Result<Detected> {
    let li = gelstereo_io::images::read_image(l)?;
    let ri = gelstereo_io::images::read_image(r)?;
    let (ls, rs) = (size_of(&li), size_of(&ri));
    if ls != rs {
        return Err(Error::Invalid(format!(
            "{}: {}x{} but {}: {}x{}; both cameras must have the same image size",
            l.display(),
            ls.width,
            ls.height,
            r.display(),
            rs.width,
            rs.height
        )));
    }
    let lc =
        find_corners(&li, board, options).map_err(|e| Error::from(e).context(l.display().to_string()))?;
    let rc =
        find_corners(&ri, board, options).map_err(|e| Error::from(e).context(r.display().to_string()))?;
    Ok((name.to_owned(), ls, lc, rc))
}

/// Calibrates a stereo rig from the checkerboard images of `left_dir` and `right_dir` (paired by file
/// name; all of one size).
pub fn calibrate_folders(
    left_dir: &Path,
    right_dir: &Path,
    board: &Board,
    options: &CalibrationOptions,
) -> Result<FolderCalibration> {
    options.validate()?;
    let (pairs, unpaired) = pair_images(left_dir, right_dir)?;
    // Detect in parallel; keep the file order.
    let detected: Vec<Result<Detected>> = pairs
        .par_iter()
        .map(|(name, l, r)| detect(name, l, r, board, options))
        .collect();
    let mut size: Option<(ImageSize, String)> = None;
    let mut views = Vec::new();
    let mut not_found = Vec::new();
    for d in detected {
        let (name, s, lc, rc) = d?;
        match &size {
            None => size = Some((s, name.clone())),
            Some((first, first_name)) if *first != s => {
                return Err(Error::Invalid(format!(
                    "{name} is {}x{} but {first_name} is {}x{}: all images must have one size",
                    s.width, s.height, first.width, first.height
                )));
            }
            _ => {}
        }
        match (lc, rc) {
            (Some(left), Some(right)) => views.push(StereoCorners { name, left, right }),
            (None, Some(_)) => not_found.push(format!("{name} (left)")),
            (Some(_), None) => not_found.push(format!("{name} (right)")),
            (None, None) => not_found.push(format!("{name} (both)")),
        }
    }
    let Some((image_size, _)) = size else {
        return Err(Error::Invalid("no images read".into()));
    };
    let report = calibrate_stereo(board, image_size, &views, options).map_err(|e| {
        Error::from(e).context(format!(
            "calibrating from {} and {}",
            left_dir.display(),
            right_dir.display()
        ))
    })?;
    Ok(FolderCalibration {
        report,
        image_size,
        pairs: pairs.len(),
        not_found,
        unpaired,
    })
}
