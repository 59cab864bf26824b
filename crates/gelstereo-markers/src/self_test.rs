//! A localizer's self-test: one run on a synthetic marker image (a lattice of dark discs on a light
//! gel-like background), so that a broken model (NaN weights, a wrong export) is caught by
//! `gelstereo doctor` rather than by zero markers in a user's recording.

use opencv::core::{CV_8UC3, Mat, Point, Scalar};
use opencv::imgproc;

use crate::{Error, Localizer, Result};

/// Marker rows and columns of the synthetic image.
pub const SELF_TEST_GRID: i32 = 12;

/// What a self-test found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SelfTest {
    /// Markers drawn.
    pub drawn: usize,
    /// Markers the localizer found.
    pub found: usize,
}

/// The synthetic image: a 320 x 320 light background with a 12 x 12 lattice of dark discs (radius
/// 4 px, pitch 24 px), the look of the reference sensor's markers.
pub fn dot_grid() -> Result<Mat> {
    let cv = |source| Error::OpenCv {
        context: "drawing the self-test image",
        source,
    };
    let mut image = Mat::new_rows_cols_with_default(320, 320, CV_8UC3, Scalar::new(186.0, 192.0, 196.0, 0.0))
        .map_err(cv)?;
    for row in 0..SELF_TEST_GRID {
        for col in 0..SELF_TEST_GRID {
            let centre = Point::new(28 + 24 * col, 28 + 24 * row);
            imgproc::circle(&mut image, centre, 4, Scalar::all(50.0), -1, imgproc::LINE_AA, 0).map_err(cv)?;
        }
    }
    Ok(image)
}

/// Runs `localizer` once on [`dot_grid`]; an output with NaN or an infinity is an error (from the
/// localizer), and so is an image in which it finds no marker at all.
pub fn run(localizer: &mut dyn Localizer) -> Result<SelfTest> {
    let image = dot_grid()?;
    let drawn = (SELF_TEST_GRID * SELF_TEST_GRID) as usize;
    let found = run_on(
        localizer,
        &image,
        &format!("a synthetic image of {drawn} clear markers"),
    )?;
    Ok(SelfTest { drawn, found })
}

/// Runs `localizer` once on `image` (described by `what` in errors) and returns the number of
/// markers found: a non-finite network output is an error (from the localizer), and so is no
/// marker at all.
pub fn run_on(localizer: &mut dyn Localizer, image: &Mat, what: &str) -> Result<usize> {
    let found = localizer.detect(image)?.len();
    if found == 0 {
        return Err(Error::SelfTest(format!(
            "{} found no marker in {what}",
            localizer.name()
        )));
    }
    Ok(found)
}
