//! Squeezed dots the network misses, found as blobs (`docs/localization.md`, "Blobs between squeezed
//! markers"; the Python twin is `squeezed_blobs` in `train/gelstereo_train/postprocess.py`).
//!
//! At a flat punch's or a box's rim the gel squeezes the printed dots into thin dashes side by side.
//! The network, which met such dashes rarely in training, finds one of a pair or none even at the
//! closer look's scale, while the dashes stay separate dark (or light) blobs a threshold sees. So
//! where the markers lie squeezed together (a nearest neighbour closer than
//! [`SQUEEZED_NN_PITCH`] x pitch), OpenCV's SimpleBlobDetector runs on that part of the image at
//! three grey levels between the dots' and the gel's, and a blob becomes a marker when it lies where
//! the network found none: at least [`AWAY_FROM_MARKERS_PITCH`] from every marker, surrounded by the
//! lattice, beside a squeezed marker and away from the image border (a cut dot is the edge check's). A dot that differs from the gel in hue alone
//! makes no grey blob and gains nothing.

use gelstereo_core::spatial::Buckets;
use gelstereo_core::{Detection, ImageSize, Point2};
use opencv::core::{
    CV_8UC1, KeyPointTraitConst, Mat, MatTraitConst, MatTraitConstManual, Point, Rect, Scalar, Vector,
};
use opencv::features2d::{SimpleBlobDetector, SimpleBlobDetector_Params};
use opencv::imgproc;
use opencv::prelude::Feature2DTrait;

use crate::close_look::{SQUEEZED_NN_PITCH, region_around};
use crate::edge::inside_the_image_px;
use crate::lattice::{SURROUNDED_GAP_DEG, largest_gap};
use crate::region::Region;
use crate::spacing::nearest_neighbour_distances;
use crate::{Result, cv_err};

/// Grey levels of the blob search, as shares of the way between the dots' median grey and the gel's:
/// 0.3, 0.5 and 0.7 (a blob must be seen at two of them).
pub const LEVELS: [f32; 3] = [0.3, 0.5, 0.7];

/// Dots darker or lighter than the gel by less than this (grey levels) make no blob worth trusting.
pub const MIN_CONTRAST: f32 = 12.0;

/// A blob's area, as shares of the pitch squared: a dash squeezed to a third of a dot up to a whole
/// dot (the reference sensor's dots cover about a fifth of the pitch squared).
pub const AREA_PITCH2: (f32, f32) = (0.02, 0.6);

/// Smallest ratio of a blob's short to long axis: a dash squeezed to 0.35 of its width passes.
pub const MIN_INERTIA_RATIO: f32 = 0.1;

/// Smallest convexity: two dashes merged into one peanut-shaped blob do not pass.
pub const MIN_CONVEXITY: f32 = 0.85;

/// A blob lies at least this share of the pitch from every marker.
pub const AWAY_FROM_MARKERS_PITCH: f64 = 0.3;

/// A blob has at least this many markers within [`INSIDE_REACH_PITCH`] x pitch.
pub const INSIDE_MARKERS: usize = 3;

/// See [`INSIDE_MARKERS`].
pub const INSIDE_REACH_PITCH: f64 = 1.6;

/// One of a blob's this many nearest markers is squeezed.
pub const SQUEEZED_AMONG: usize = 4;

/// A blob lies at least this share of the pitch inside the image's outermost pixel centres.
pub const EDGE_PITCH: f64 = 0.5;

/// The confidence a marker found as a blob is reported with.
pub const BLOB_CONFIDENCE: f32 = 0.5;

/// Radius of the neighbourhood of a squeezed marker that is searched, as a share of the pitch: the
/// rest of the region is painted the gel's grey, which saves the detector most of its contours.
pub const SEARCH_PITCH: f64 = 1.5;

/// The median of `values`, the mean of the middle two for an even count (0 for none), by a histogram.
pub(crate) fn median(values: impl Iterator<Item = u8>) -> f32 {
    let mut counts = [0usize; 256];
    let mut n = 0;
    for v in values {
        counts[usize::from(v)] += 1;
        n += 1;
    }
    // The value of rank k (0-based).
    let at_rank = |k: usize| -> f32 {
        let mut seen = 0;
        for (v, c) in counts.iter().enumerate() {
            seen += c;
            if seen > k {
                return v as f32;
            }
        }
        255.0
    };
    match n {
        0 => 0.0,
        _ if n % 2 == 1 => at_rank(n / 2),
        _ => 0.5 * (at_rank(n / 2 - 1) + at_rank(n / 2)),
    }
}

/// The grey part of `image` inside `rect`.
pub(crate) fn grey_roi(image: &Mat, rect: Rect) -> Result<Mat> {
    let roi = Mat::roi(image, rect).map_err(cv_err("the squeezed region of the image"))?;
    let mut grey = Mat::default();
    match image.channels() {
        1 => roi
            .copy_to(&mut grey)
            .map_err(cv_err("copying the squeezed region"))?,
        n => {
            let code = if n == 4 {
                imgproc::COLOR_BGRA2GRAY
            } else {
                imgproc::COLOR_BGR2GRAY
            };
            imgproc::cvt_color(&roi, &mut grey, code, 0).map_err(cv_err("cvtColor to grey"))?;
        }
    }
    Ok(grey)
}

/// The whole pixels covering `region` (finite, within the image span of `size`); `None` for a
/// region thinner than two pixels.
pub(crate) fn pixels_covering(region: &Region, size: ImageSize) -> Option<Rect> {
    let (x0, y0) = (
        region.x0.max(0.0).floor() as i32,
        region.y0.max(0.0).floor() as i32,
    );
    let x1 = (region.x1.ceil() as i32).min(size.width as i32 - 1);
    let y1 = (region.y1.ceil() as i32).min(size.height as i32 - 1);
    (x1 > x0 && y1 > y0).then(|| Rect::new(x0, y0, x1 - x0 + 1, y1 - y0 + 1))
}

/// The median grey under the markers inside `region` (each at its nearest pixel of `grey`, the part
/// of the image whose top-left pixel is `origin`) and the median grey of all of `grey`.
fn dot_and_gel_grey(
    grey: &Mat,
    points: &[Point2],
    region: &Region,
    origin: (i32, i32),
) -> Result<(f32, f32)> {
    let bytes = grey.data_bytes().map_err(cv_err("reading the squeezed region"))?;
    let (width, height) = (grey.cols().max(1) as usize, grey.rows().max(1) as usize);
    let at_markers = points
        .iter()
        .filter(|p| {
            region.contains(&Detection {
                position: **p,
                confidence: 1.0,
            })
        })
        .filter_map(|p| {
            let x = usize::try_from(p.x.round() as i32 - origin.0)
                .ok()?
                .min(width - 1);
            let y = usize::try_from(p.y.round() as i32 - origin.1)
                .ok()?
                .min(height - 1);
            bytes.get(y * width + x).copied()
        });
    Ok((median(at_markers), median(bytes.iter().copied())))
}

/// `grey` (the region whose top-left pixel is `origin` in the image) within [`SEARCH_PITCH`] x
/// `pitch` of the squeezed markers, the rest painted `gel`.
fn squeezed_neighbourhoods(
    grey: &Mat,
    points: &[Point2],
    squeezed: &[bool],
    origin: (i32, i32),
    gel: f32,
    pitch: f64,
) -> Result<Mat> {
    let (rows, cols) = (grey.rows(), grey.cols());
    let mut near = Mat::new_rows_cols_with_default(rows, cols, CV_8UC1, Scalar::all(0.0))
        .map_err(cv_err("the squeezed neighbourhoods' mask"))?;
    let radius = (SEARCH_PITCH * pitch).round() as i32;
    for p in points.iter().zip(squeezed).filter(|(_, s)| **s).map(|(p, _)| p) {
        let centre = Point::new(p.x.round() as i32 - origin.0, p.y.round() as i32 - origin.1);
        imgproc::circle(
            &mut near,
            centre,
            radius,
            Scalar::all(255.0),
            -1,
            imgproc::LINE_8,
            0,
        )
        .map_err(cv_err("drawing a squeezed neighbourhood"))?;
    }
    let mut painted =
        Mat::new_rows_cols_with_default(rows, cols, CV_8UC1, Scalar::all(f64::from(gel.round())))
            .map_err(cv_err("the painted region"))?;
    grey.copy_to_masked(&mut painted, &near)
        .map_err(cv_err("copying the squeezed neighbourhoods"))?;
    Ok(painted)
}

/// The blob detector for dots of median grey `dot` on a gel of median grey `gel`, `pitch` px apart;
/// `None` when the two differ by less than [`MIN_CONTRAST`].
pub(crate) fn detector_for(
    dot: f32,
    gel: f32,
    pitch: f64,
) -> Result<Option<opencv::core::Ptr<SimpleBlobDetector>>> {
    let (lo, hi) = (dot.min(gel), dot.max(gel));
    let span = hi - lo;
    if span < MIN_CONTRAST {
        return Ok(None);
    }
    let pitch2 = (pitch * pitch) as f32;
    let params = SimpleBlobDetector_Params {
        threshold_step: (LEVELS[1] - LEVELS[0]) * span,
        min_threshold: lo + LEVELS[0] * span,
        // SimpleBlobDetector's levels run while below the maximum: the last one included.
        max_threshold: lo + LEVELS[2] * span + 0.5,
        min_repeatability: 2,
        min_dist_between_blobs: (0.25 * pitch) as f32,
        filter_by_color: true,
        blob_color: if dot < gel { 0 } else { 255 },
        filter_by_area: true,
        min_area: AREA_PITCH2.0 * pitch2,
        max_area: AREA_PITCH2.1 * pitch2,
        filter_by_circularity: false,
        // Unused with the filter off; newer OpenCV versions reject a bound that is not positive even so.
        min_circularity: f32::MIN_POSITIVE,
        max_circularity: f32::MAX,
        filter_by_inertia: true,
        min_inertia_ratio: MIN_INERTIA_RATIO,
        max_inertia_ratio: f32::MAX,
        filter_by_convexity: true,
        min_convexity: MIN_CONVEXITY,
        max_convexity: f32::MAX,
        #[cfg(opencv_blob_collect_contours)]
        collect_contours: false,
    };
    Ok(Some(
        SimpleBlobDetector::create(params).map_err(cv_err("SimpleBlobDetector::create"))?,
    ))
}

/// Whether a blob at `p` is a marker the network missed (module doc): away from every marker,
/// surrounded by the lattice (at least [`INSIDE_MARKERS`] markers within [`INSIDE_REACH_PITCH`],
/// no gap between their directions wider than [`SURROUNDED_GAP_DEG`]: a blob past the lattice's
/// edge, where housing, a groove's shadow or a membrane's rim lie, has markers on one side only),
/// beside a squeezed marker.
fn missed_marker(p: Point2, markers: &Buckets, squeezed: &[bool], pitch: f64) -> bool {
    let reach = INSIDE_REACH_PITCH * pitch;
    let points = markers.points();
    let mut within: Vec<(f64, usize)> = Vec::new();
    markers.for_each_within(p, reach, |i, d2| {
        if d2 < reach * reach {
            within.push((d2.sqrt(), i));
        }
    });
    within.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut angles: Vec<f64> = within
        .iter()
        .map(|(_, i)| (points[*i].y - p.y).atan2(points[*i].x - p.x))
        .collect();
    within
        .first()
        .is_some_and(|(d, _)| *d > AWAY_FROM_MARKERS_PITCH * pitch)
        && angles.len() >= INSIDE_MARKERS
        && largest_gap(&mut angles) <= SURROUNDED_GAP_DEG.to_radians()
        && within.iter().take(SQUEEZED_AMONG).any(|(_, i)| squeezed[*i])
}

/// The markers `image` shows between the squeezed ones of `markers` (`pitch_px` apart) that the
/// network missed (module doc), with [`BLOB_CONFIDENCE`]; none without a squeeze.
pub fn blobs_between_squeezed(
    image: &Mat,
    markers: &[Detection],
    pitch_px: Option<f64>,
) -> Result<Vec<Detection>> {
    let Some(pitch) = pitch_px.filter(|p| p.is_finite() && *p > 0.0) else {
        return Ok(Vec::new());
    };
    let points: Vec<Point2> = markers.iter().map(|d| d.position).collect();
    let squeezed: Vec<bool> = nearest_neighbour_distances(&points)
        .into_iter()
        .map(|nn| nn < SQUEEZED_NN_PITCH * pitch)
        .collect();
    let size = ImageSize {
        width: image.cols().max(0) as u32,
        height: image.rows().max(0) as u32,
    };
    let around = points.iter().zip(&squeezed).filter(|(_, s)| **s).map(|(p, _)| *p);
    let Some(region) = region_around(around, pitch, size) else {
        return Ok(Vec::new());
    };
    let Some(rect) = pixels_covering(&region, size) else {
        return Ok(Vec::new());
    };
    let grey = grey_roi(image, rect)?;
    let (dot, gel) = dot_and_gel_grey(&grey, &points, &region, (rect.x, rect.y))?;
    let Some(mut detector) = detector_for(dot, gel, pitch)? else {
        return Ok(Vec::new());
    };
    let (x0, y0) = (rect.x, rect.y);
    let searched = squeezed_neighbourhoods(&grey, &points, &squeezed, (x0, y0), gel, pitch)?;
    let mut keypoints = Vector::new();
    detector
        .detect(&searched, &mut keypoints, &opencv::core::no_array())
        .map_err(cv_err("SimpleBlobDetector::detect"))?;
    let edge = EDGE_PITCH * pitch;
    let grid = Buckets::new(&points, pitch);
    Ok(keypoints
        .iter()
        .map(|k| {
            Point2::new(
                f64::from(k.pt().x) + f64::from(x0),
                f64::from(k.pt().y) + f64::from(y0),
            )
        })
        .filter(|p| inside_the_image_px(*p, size) >= edge)
        .filter(|p| missed_marker(*p, &grid, &squeezed, pitch))
        .map(|position| Detection {
            position,
            confidence: BLOB_CONFIDENCE,
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_8UC3, Size};

    const PITCH: f64 = 20.0;

    fn det(x: f64, y: f64) -> Detection {
        Detection {
            position: Point2::new(x, y),
            confidence: 1.0,
        }
    }

    /// A 320 x 240 gel with dark dots of radius 4 every 20 px from (20, 20), where rows 120 and 140
    /// have their dots at x = 140 and 160 squeezed into vertical dashes 10 px apart (x = 145, 155).
    fn squeezed_gel() -> (Mat, Vec<Detection>) {
        let mut img =
            Mat::new_rows_cols_with_default(240, 320, CV_8UC3, Scalar::new(200.0, 205.0, 210.0, 0.0))
                .unwrap();
        let mut truth = Vec::new();
        for r in 0..11 {
            for c in 0..15 {
                let (x, y) = (20 + 20 * c, 20 + 20 * r);
                let dash = (y == 120 || y == 140) && (x == 140 || x == 160);
                if dash {
                    let xd = if x == 140 { 145 } else { 155 };
                    imgproc::ellipse(
                        &mut img,
                        Point::new(xd, y),
                        Size::new(2, 5),
                        0.0,
                        0.0,
                        360.0,
                        Scalar::all(40.0),
                        -1,
                        imgproc::LINE_AA,
                        0,
                    )
                    .unwrap();
                    truth.push(det(f64::from(xd), f64::from(y)));
                } else {
                    imgproc::circle(
                        &mut img,
                        Point::new(x, y),
                        4,
                        Scalar::all(40.0),
                        -1,
                        imgproc::LINE_AA,
                        0,
                    )
                    .unwrap();
                    truth.push(det(f64::from(x), f64::from(y)));
                }
            }
        }
        (img, truth)
    }

    /// The dash the network missed beside its squeezed neighbour is found where it is; nothing else
    /// is, and with every marker found nothing is added.
    #[test]
    fn a_missed_dash_beside_a_squeezed_marker_is_found() {
        let (img, truth) = squeezed_gel();
        let missing = Point2::new(155.0, 140.0);
        let found: Vec<Detection> = truth.iter().copied().filter(|d| d.position != missing).collect();
        let added = blobs_between_squeezed(&img, &found, Some(PITCH)).unwrap();
        assert_eq!(added.len(), 1, "{added:?}");
        let p = added[0].position;
        assert!((p.x - missing.x).hypot(p.y - missing.y) < 0.5, "{p:?}");
        assert_eq!(added[0].confidence, BLOB_CONFIDENCE);
        assert!(
            blobs_between_squeezed(&img, &truth, Some(PITCH))
                .unwrap()
                .is_empty()
        );
    }

    /// Without a squeeze (no marker nearer its neighbour than 0.8 pitch), or without a pitch, the
    /// image is not searched: a dot the network missed in an even lattice is the lattice check's.
    #[test]
    fn an_even_lattice_is_not_searched() {
        let (img, truth) = squeezed_gel();
        let even: Vec<Detection> = truth
            .iter()
            .copied()
            .filter(|d| !(d.position.y == 120.0 || d.position.y == 140.0) || d.position.x < 100.0)
            .filter(|d| d.position != Point2::new(60.0, 60.0))
            .collect();
        assert!(
            blobs_between_squeezed(&img, &even, Some(PITCH))
                .unwrap()
                .is_empty()
        );
        assert!(
            blobs_between_squeezed(&img, &truth[1..], None)
                .unwrap()
                .is_empty()
        );
    }
}
