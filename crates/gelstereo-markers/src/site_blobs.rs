//! Dots the network missed where the lattice has a site, found as blobs (`docs/localization.md`,
//! "Blobs at the lattice's empty sites"; the Python twin is `site_blobs` in
//! `train/gelstereo_train/postprocess.py`).
//!
//! A line of three equally spaced markers `c, a, b` predicts the next site `s = 2 b - a`. Where no
//! marker lies within half a pitch of `s`, and either the line goes on past `s` to another marker (a
//! hole in the lattice) or its next site past `s` lies outside the image (the image's border cuts the
//! lattice there), the lattice says a dot should be at `s`. A faint dot the network was not even
//! unsure of shows there as a blob: OpenCV's SimpleBlobDetector, with the settings of
//! [`crate::squeezed_blobs`], runs on the image around `s` at grey levels between the neighbouring
//! markers' grey and the gel's, and the blob nearest `s` (within [`SITE_REACH_PITCH`], away from every
//! marker) joins the markers. Sites past the lattice's end inside the image are not searched: there a
//! membrane's rim or the housing begins, and a full lattice has dozens of such sites per view.

use gelstereo_core::spatial::Buckets;
use gelstereo_core::{Detection, ImageSize, Point2};
use opencv::core::{KeyPointTraitConst, Mat, MatTraitConst, MatTraitConstManual, Rect, Vector};
use opencv::prelude::Feature2DTrait;

use crate::edge::{inside_the_image_px, outside_the_image};
use crate::lattice::SITE_STEP;
use crate::region::Region;
use crate::squeezed_blobs::{BLOB_CONFIDENCE, detector_for, grey_roi, median, pixels_covering};
use crate::{Result, cv_err};

/// A line's third point lies within this share of its spacing of where equal spacing puts it.
const LINE_TOLERANCE: f64 = 0.2;

/// A site is empty when no marker lies within this share of the pitch.
const EMPTY_PITCH: f64 = 0.5;

/// A site is searched when it lies at least this share of the pitch inside the image's outermost
/// pixel centres: its dot is whole there, and the blob's centre unbiased.
const INSIDE_PITCH: f64 = 0.15;

/// A blob joins when it lies within this share of the pitch of its site and at least as far from
/// every marker.
pub const SITE_REACH_PITCH: f64 = 0.3;

/// Half the side of the square searched around a site, in pitches.
const SEARCH_HALF_PITCH: f64 = 0.7;

/// The neighbouring markers whose grey gives the dots' grey.
const DOT_SAMPLES: usize = 6;

/// Each point of `grid` with its lattice steps: the points [`SITE_STEP`] pitches from it, with their
/// distance, in the grid's order; point `i`'s steps are `steps[start[i]..start[i + 1]]`.
struct Steps {
    start: Vec<usize>,
    steps: Vec<(usize, f64)>,
}

impl Steps {
    /// The steps of every point of `grid`, whose lattice is `pitch` px.
    fn of(grid: &Buckets, pitch: f64) -> Self {
        let (mut start, mut steps) = (vec![0], Vec::new());
        for &a in grid.points() {
            grid.for_each_within(a, SITE_STEP.1 * pitch, |j, d2| {
                let d = d2.sqrt();
                if (SITE_STEP.0 * pitch..=SITE_STEP.1 * pitch).contains(&d) {
                    steps.push((j, d));
                }
            });
            start.push(steps.len());
        }
        Self { start, steps }
    }

    /// Point `i`'s steps.
    fn around(&self, i: usize) -> &[(usize, f64)] {
        &self.steps[self.start[i]..self.start[i + 1]]
    }
}

/// The empty sites the lines of `grid`'s markers predict at a hole or where the border of an image of
/// `size` cuts the lattice (module doc), one per site.
fn empty_sites(grid: &Buckets, pitch: f64, size: ImageSize) -> Vec<Point2> {
    let points = grid.points();
    let inside = INSIDE_PITCH * pitch;
    let steps = Steps::of(grid, pitch);
    let empty = EMPTY_PITCH * pitch;
    // Whether a marker lies within `empty` of `s`, a step beyond marker `b`: in a whole lattice one of
    // `b`'s own steps does, which is quicker to find than by a query of the grid (asked only when
    // none does; the same test of the same squared distance, so the same answer).
    let held = |s: Point2, b: usize| {
        let near = |q: &Point2| (q.x - s.x).powi(2) + (q.y - s.y).powi(2) <= empty * empty;
        steps.around(b).iter().any(|&(k, _)| near(&points[k])) || grid.any_within(s, empty)
    };
    let mut sites: Vec<Point2> = Vec::new();
    for (i, &a) in points.iter().enumerate() {
        for &(j, d) in steps.around(i) {
            let b = points[j];
            let at = |u: Point2, v: Point2| Point2::new(2.0 * u.x - v.x, 2.0 * u.y - v.y);
            let s = at(b, a);
            let placed = !held(s, j)
                && inside_the_image_px(s, size) >= inside
                && grid.any_within(at(a, b), LINE_TOLERANCE * d);
            if !placed {
                continue;
            }
            let beyond = at(s, b);
            let hole_or_cut = grid.any_within(beyond, LINE_TOLERANCE * d) || outside_the_image(beyond, size);
            if hole_or_cut
                && sites
                    .iter()
                    .all(|t| (t.x - s.x).hypot(t.y - s.y) > SITE_REACH_PITCH * pitch)
            {
                sites.push(s);
            }
        }
    }
    sites
}

/// The pixels within `half` px of `p` in an image of `size`; `None` when thinner than five pixels.
fn square_around(p: Point2, half: f64, size: ImageSize) -> Option<Rect> {
    let square = Region {
        x0: p.x - half,
        y0: p.y - half,
        x1: p.x + half,
        y1: p.y + half,
    };
    pixels_covering(&square, size).filter(|r| r.width >= 5 && r.height >= 5)
}

/// The median grey of `image` at `points` (nearest pixels inside it).
fn median_grey_at(image: &Mat, points: &[Point2], size: ImageSize) -> Result<f32> {
    let pixels: Vec<(i32, i32)> = points
        .iter()
        .map(|p| (p.x.round() as i32, p.y.round() as i32))
        .filter(|&(x, y)| x >= 0 && y >= 0 && x < size.width as i32 && y < size.height as i32)
        .collect();
    let (Some(x0), Some(y0)) = (pixels.iter().map(|p| p.0).min(), pixels.iter().map(|p| p.1).min()) else {
        return Ok(0.0);
    };
    let x1 = pixels.iter().map(|p| p.0).max().unwrap_or(x0);
    let y1 = pixels.iter().map(|p| p.1).max().unwrap_or(y0);
    let grey = grey_roi(image, Rect::new(x0, y0, x1 - x0 + 1, y1 - y0 + 1))?;
    let bytes = grey.data_bytes().map_err(cv_err("reading the markers' grey"))?;
    let width = (x1 - x0 + 1) as usize;
    Ok(median(pixels.iter().filter_map(|&(x, y)| {
        bytes.get((y - y0) as usize * width + (x - x0) as usize).copied()
    })))
}

/// The blob at site `s` (module doc), if any.
fn blob_at(image: &Mat, s: Point2, grid: &Buckets, pitch: f64, size: ImageSize) -> Result<Option<Point2>> {
    let Some(rect) = square_around(s, SEARCH_HALF_PITCH * pitch, size) else {
        return Ok(None);
    };
    let mut nearest: Vec<(f64, Point2)> = Vec::new();
    grid.for_each_within(s, 2.0 * pitch, |j, d2| nearest.push((d2, grid.points()[j])));
    nearest.sort_by(|a, b| a.0.total_cmp(&b.0));
    let samples: Vec<Point2> = nearest.iter().take(DOT_SAMPLES).map(|n| n.1).collect();
    let dot = median_grey_at(image, &samples, size)?;
    let grey = grey_roi(image, rect)?;
    let gel = median(
        grey.data_bytes()
            .map_err(cv_err("reading a site's grey"))?
            .iter()
            .copied(),
    );
    let Some(mut detector) = detector_for(dot, gel, pitch)? else {
        return Ok(None);
    };
    let mut keypoints = Vector::new();
    detector
        .detect(&grey, &mut keypoints, &opencv::core::no_array())
        .map_err(cv_err("SimpleBlobDetector::detect"))?;
    let reach = SITE_REACH_PITCH * pitch;
    Ok(keypoints
        .iter()
        .map(|k| {
            Point2::new(
                f64::from(k.pt().x) + f64::from(rect.x),
                f64::from(k.pt().y) + f64::from(rect.y),
            )
        })
        .map(|b| ((b.x - s.x).hypot(b.y - s.y), b))
        .filter(|(e, b)| *e <= reach && !grid.any_within(*b, reach))
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, b)| b))
}

/// The dots `image` shows at the empty sites of the lattice of `markers` (`pitch_px` apart) where a
/// line predicts one at a hole or at the border (module doc), with [`BLOB_CONFIDENCE`].
pub fn blobs_at_empty_sites(
    image: &Mat,
    markers: &[Detection],
    pitch_px: Option<f64>,
) -> Result<Vec<Detection>> {
    let Some(pitch) = pitch_px.filter(|p| p.is_finite() && *p > 0.0) else {
        return Ok(Vec::new());
    };
    let size = ImageSize {
        width: image.cols().max(0) as u32,
        height: image.rows().max(0) as u32,
    };
    let points: Vec<Point2> = markers.iter().map(|d| d.position).collect();
    let grid = Buckets::new(&points, pitch);
    let mut found = Vec::new();
    for s in empty_sites(&grid, pitch, size) {
        if let Some(position) = blob_at(image, s, &grid, pitch, size)? {
            found.push(Detection {
                position,
                confidence: BLOB_CONFIDENCE,
            });
        }
    }
    Ok(found)
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_8UC3, Point, Scalar};
    use opencv::imgproc;

    const PITCH: f64 = 20.0;

    fn det(p: Point2) -> Detection {
        Detection {
            position: p,
            confidence: 1.0,
        }
    }

    /// A 320 x 240 gel with faint dark dots of radius 4 (30 grey levels below the gel) every 20 px,
    /// the top row 6 px below the image's top (x = 20, 40, ... 300; y = 6, 26, ... 226).
    fn faint_gel() -> (Mat, Vec<Point2>) {
        let mut img =
            Mat::new_rows_cols_with_default(240, 320, CV_8UC3, Scalar::new(150.0, 155.0, 160.0, 0.0))
                .unwrap();
        let mut dots = Vec::new();
        for r in 0..12 {
            for c in 0..15 {
                let (x, y) = (20 + 20 * c, 6 + 20 * r);
                imgproc::circle(
                    &mut img,
                    Point::new(x, y),
                    4,
                    Scalar::all(125.0),
                    -1,
                    imgproc::LINE_AA,
                    0,
                )
                .unwrap();
                dots.push(Point2::new(f64::from(x), f64::from(y)));
            }
        }
        (img, dots)
    }

    /// A dot missing from the markers inside the lattice (a hole) and one of the top row (whose next
    /// site up lies outside the image) are found where they are; with every dot found nothing is
    /// added, and no site past the lattice's last column (inside the image, no dot) is searched.
    #[test]
    fn dots_at_a_hole_and_at_the_border_are_found_and_nothing_past_the_lattice() {
        let (img, dots) = faint_gel();
        let missing = [Point2::new(160.0, 106.0), Point2::new(100.0, 6.0)];
        let found: Vec<Detection> = dots
            .iter()
            .copied()
            .filter(|p| !missing.contains(p))
            .map(det)
            .collect();
        let added = blobs_at_empty_sites(&img, &found, Some(PITCH)).unwrap();
        assert_eq!(added.len(), 2, "{added:?}");
        for m in missing {
            assert!(
                added
                    .iter()
                    .any(|d| (d.position.x - m.x).hypot(d.position.y - m.y) < 0.5),
                "{m:?} in {added:?}"
            );
        }
        assert!(added.iter().all(|d| d.confidence == BLOB_CONFIDENCE));
        let all: Vec<Detection> = dots.iter().copied().map(det).collect();
        assert!(blobs_at_empty_sites(&img, &all, Some(PITCH)).unwrap().is_empty());
        let size = ImageSize {
            width: 320,
            height: 240,
        };
        let grid = Buckets::new(&dots, PITCH);
        assert!(
            empty_sites(&grid, PITCH, size).is_empty(),
            "a whole lattice has no site to search"
        );
    }

    /// Where the lattice's last column ends 80 px inside the image and a dark spot lies one pitch past
    /// it, the spot is not taken: a site past the lattice's end is no hole, and the border does not
    /// cut the lattice there.
    #[test]
    fn a_spot_past_the_lattice_end_inside_the_image_is_not_taken() {
        let (img, dots) = faint_gel();
        let mut img = img;
        // Gel over the last three columns (x = 260-300), then one spot at x = 260.
        imgproc::rectangle(
            &mut img,
            opencv::core::Rect::new(250, 0, 70, 240),
            Scalar::new(150.0, 155.0, 160.0, 0.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
        imgproc::circle(
            &mut img,
            Point::new(260, 106),
            4,
            Scalar::all(125.0),
            -1,
            imgproc::LINE_AA,
            0,
        )
        .unwrap();
        let lattice: Vec<Detection> = dots.iter().copied().filter(|p| p.x < 250.0).map(det).collect();
        let added = blobs_at_empty_sites(&img, &lattice, Some(PITCH)).unwrap();
        assert!(added.is_empty(), "{added:?}");
    }
}
