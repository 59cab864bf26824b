//! Overlays: detections drawn onto a copy of the image.
//!
//! Each marker is a circle coloured by confidence, from red (c = 0.1) through yellow to green (c = 1);
//! blob detections (no score) are green. Markers that MRE accepted (confidence at or below the
//! method's `conf_keep`) also get a small cross, so the ones rescued by MRE stand out.

use gelstereo_core::Detection;
use opencv::core::{Mat, MatTraitConst, Point, Scalar};
use opencv::imgproc;

use crate::{Result, cv_err};

/// BGR colour for `confidence`: red at 0.1 or below, yellow at 0.55, green at 1.
pub fn confidence_colour(confidence: f32) -> Scalar {
    let t = f64::from(((confidence - 0.1) / 0.9).clamp(0.0, 1.0));
    let (r, g) = if t < 0.5 {
        (255.0, 510.0 * t)
    } else {
        (510.0 * (1.0 - t), 255.0)
    };
    Scalar::new(0.0, g, r, 0.0)
}

/// Draws `detections` onto a BGR copy of `image` (grey and BGRA images are converted). Markers with
/// confidence at or below `mre_band_top` are marked as MRE-accepted (pass `None` for methods without
/// MRE). `radius_px` is the circle radius.
pub fn draw(image: &Mat, detections: &[Detection], mre_band_top: Option<f32>, radius_px: i32) -> Result<Mat> {
    let mut canvas = Mat::default();
    match image.channels() {
        1 => imgproc::cvt_color(image, &mut canvas, imgproc::COLOR_GRAY2BGR, 0)
            .map_err(cv_err("grey to BGR"))?,
        4 => imgproc::cvt_color(image, &mut canvas, imgproc::COLOR_BGRA2BGR, 0)
            .map_err(cv_err("BGRA to BGR"))?,
        _ => canvas = image.try_clone().map_err(cv_err("copy of the image"))?,
    }
    // Sub-pixel centres: OpenCV's drawing takes fixed-point coordinates with `shift` fractional bits.
    const SHIFT: i32 = 4;
    let scale = f64::from(1 << SHIFT);
    for d in detections {
        let colour = confidence_colour(d.confidence);
        let centre = Point::new(
            (d.position.x * scale).round() as i32,
            (d.position.y * scale).round() as i32,
        );
        imgproc::circle(
            &mut canvas,
            centre,
            radius_px.max(1) << SHIFT,
            colour,
            1,
            imgproc::LINE_AA,
            SHIFT,
        )
        .map_err(cv_err("circle"))?;
        if mre_band_top.is_some_and(|top| d.confidence <= top) {
            let c = Point::new(d.position.x.round() as i32, d.position.y.round() as i32);
            imgproc::draw_marker(
                &mut canvas,
                c,
                Scalar::new(255.0, 255.0, 0.0, 0.0),
                imgproc::MARKER_CROSS,
                radius_px.max(2),
                1,
                imgproc::LINE_8,
            )
            .map_err(cv_err("drawMarker"))?;
        }
    }
    Ok(canvas)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_core::Point2;
    use opencv::core::{CV_8UC1, Vec3b};

    #[test]
    fn draws_coloured_circles_at_the_markers() {
        let grey = Mat::new_rows_cols_with_default(40, 40, CV_8UC1, Scalar::all(0.0)).unwrap();
        let dets = [Detection {
            position: Point2::new(20.0, 20.0),
            confidence: 1.0,
        }];
        let out = draw(&grey, &dets, None, 5).unwrap();
        assert_eq!(out.channels(), 3);
        let on_circle = *out.at_2d::<Vec3b>(20, 25).unwrap();
        assert!(
            on_circle[1] > 100 && on_circle[2] < 50,
            "green circle expected, got {on_circle:?}"
        );
        assert_eq!(
            *out.at_2d::<Vec3b>(20, 20).unwrap(),
            Vec3b::from([0, 0, 0]),
            "centre untouched"
        );
        let low = draw(
            &grey,
            &[Detection {
                confidence: 0.3,
                ..dets[0]
            }],
            Some(0.4),
            5,
        )
        .unwrap();
        assert_ne!(
            *low.at_2d::<Vec3b>(20, 20).unwrap(),
            Vec3b::from([0, 0, 0]),
            "MRE cross at the centre"
        );
    }
}
