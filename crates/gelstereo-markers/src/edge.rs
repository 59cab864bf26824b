//! Markers at the image border: no marker whose centre lies outside the image is reported
//! (`docs/localization.md`, "Borders"; the Python twin is `inside_the_edge` in
//! `train/gelstereo_train/postprocess.py`).
//!
//! The network places a dot cut by the border at the middle of its visible part, so a dot whose centre
//! lies just outside the image comes out just inside it, where it looks like a marker on the edge.
//! Its own position cannot tell the two apart; the lattice can. The markers one and two steps
//! inwards along a lattice line through the detection put its centre where equal spacing does
//! (`2 p1 - p2`), unbiased by what the border cut off. A detection whose extrapolated centre lies
//! outside the image (more than [`IMAGE_SPAN_PX`] beyond its outermost pixel centres) goes: a margin
//! alone cannot tell a cut dot centred just inside from one centred just outside, the lattice can.
//! A straight line ignores lens distortion, which on wide-angle sensors puts a few dots cut close to
//! their centre slightly too far out, so those few are lost (figures:
//! `docs/experiments/localization-borders.md`).
//!
//! A detection near the edge without such a line (an isolated marker, a lattice too small) falls back
//! to the margin rule: it goes when it is reported closer than [`EDGE_MARGIN_PITCH`] to the edge.

use gelstereo_core::spatial::Buckets;
use gelstereo_core::{Detection, ImageSize, Point2, TieredDetections};

/// A marker reported closer than this share of the pitch to the outermost pixel centres of its image,
/// with no lattice line inwards to check it by, is not reported: such a dot shows less than half of
/// itself and has, far more often than not, its centre outside the image.
pub const EDGE_MARGIN_PITCH: f64 = 0.02;

/// How far the image reaches beyond its outermost pixel centres, px: a marker whose centre the
/// lattice puts further out lies outside the image and is not reported.
pub const IMAGE_SPAN_PX: f64 = 0.5;

/// Detections reported within this share of the pitch of an edge are checked against it.
const NEAR_EDGE_PITCH: f64 = 0.5;

/// The first step of a line inwards, as a share of the pitch (a compressed or stretched lattice
/// included; the diagonal of a square lattice, 1.41, too).
const STEP_PITCH: (f64, f64) = (0.6, 1.5);

/// Largest distance of a line's second step from where equal spacing puts it, as a share of the
/// first step (the detection's own position is off by up to half a dot's visible part).
const LINE_TOLERANCE: f64 = 0.3;

/// Smallest cosine between a line's first step and the edge's inward normal (60 degrees): a line
/// along the edge says nothing about how far out the centre lies.
const MIN_INWARD_COSINE: f64 = 0.5;

/// One side of the image: its inward unit normal and a point's distance inside it, px.
#[derive(Debug, Clone, Copy)]
struct Side {
    normal: (f64, f64),
    /// Coordinate of the outermost pixel centres along the normal, signed so that inside is
    /// `normal . p - offset >= 0`.
    offset: f64,
}

impl Side {
    fn all(size: ImageSize) -> [Side; 4] {
        let (last_x, last_y) = (f64::from(size.width) - 1.0, f64::from(size.height) - 1.0);
        [
            Side {
                normal: (1.0, 0.0),
                offset: 0.0,
            },
            Side {
                normal: (-1.0, 0.0),
                offset: -last_x,
            },
            Side {
                normal: (0.0, 1.0),
                offset: 0.0,
            },
            Side {
                normal: (0.0, -1.0),
                offset: -last_y,
            },
        ]
    }

    fn inside_px(&self, p: Point2) -> f64 {
        self.normal.0 * p.x + self.normal.1 * p.y - self.offset
    }
}

/// How far `p` lies inside the outermost pixel centres of an image of `size`, px (negative outside):
/// its distance to the nearest side.
pub(crate) fn inside_the_image_px(p: Point2, size: ImageSize) -> f64 {
    Side::all(size)
        .iter()
        .map(|side| side.inside_px(p))
        .fold(f64::INFINITY, f64::min)
}

/// Whether `p` lies outside the image span of `size` (more than [`IMAGE_SPAN_PX`] beyond its outermost
/// pixel centres).
pub(crate) fn outside_the_image(p: Point2, size: ImageSize) -> bool {
    inside_the_image_px(p, size) < -IMAGE_SPAN_PX
}

/// How far inside `side` (px; negative outside) the line inwards from `p` most nearly along the
/// side's normal puts `p`'s centre: `2 p1 - p2` for lattice points `p1` one step and `p2` two steps
/// from `p`. `None` without such a line.
fn extrapolated_inside_px(p: Point2, side: &Side, lattice: &Buckets, pitch_px: f64) -> Option<f64> {
    let points = lattice.points();
    let (min_step, max_step) = (STEP_PITCH.0 * pitch_px, STEP_PITCH.1 * pitch_px);
    let mut best: Option<(f64, f64)> = None; // (cosine, inside px)
    lattice.for_each_within(p, max_step, |j, d2| {
        let step = d2.sqrt();
        let p1 = points[j];
        let cosine = (side.normal.0 * (p1.x - p.x) + side.normal.1 * (p1.y - p.y)) / step;
        if step < min_step || cosine < MIN_INWARD_COSINE || best.is_some_and(|(c, _)| c >= cosine) {
            return;
        }
        let want = Point2::new(2.0 * p1.x - p.x, 2.0 * p1.y - p.y);
        let tolerance = LINE_TOLERANCE * step;
        let mut second: Option<(f64, Point2)> = None;
        lattice.for_each_within(want, tolerance, |k, e2| {
            if second.is_none_or(|(b, _)| e2 < b) {
                second = Some((e2, points[k]));
            }
        });
        if let Some((_, p2)) = second {
            let centre = Point2::new(2.0 * p1.x - p2.x, 2.0 * p1.y - p2.y);
            best = Some((cosine, side.inside_px(centre)));
        }
    });
    best.map(|(_, inside)| inside)
}

/// Whether a detection at `p` stays: for every side it lies within [`NEAR_EDGE_PITCH`] of, the
/// lattice puts its centre inside the image, or, without a line to tell, it is reported at least
/// [`EDGE_MARGIN_PITCH`] inside the outermost pixel centres.
fn stays(p: Point2, sides: &[Side; 4], lattice: &Buckets, pitch_px: f64) -> bool {
    sides.iter().all(|side| {
        let inside = side.inside_px(p);
        if inside >= NEAR_EDGE_PITCH * pitch_px {
            return true;
        }
        match extrapolated_inside_px(p, side, lattice, pitch_px) {
            Some(centre) => centre >= -IMAGE_SPAN_PX,
            None => inside >= EDGE_MARGIN_PITCH * pitch_px,
        }
    })
}

/// Keeps the markers of an image of `size` (px), accepted and second tier, whose centre lies inside
/// it, judged by the lines of the accepted markers (`pitch_px` apart) and, where no line reaches a
/// marker, by the edge margin; all of them without a pitch.
pub fn drop_past_the_edge(found: &mut TieredDetections, size: ImageSize, pitch_px: Option<f64>) {
    drop_past_the_edge_except(found, size, pitch_px, &[]);
}

/// [`drop_past_the_edge`], leaving alone the markers at `judged` (already placed inside the image by
/// [`crate::border`]).
pub(crate) fn drop_past_the_edge_except(
    found: &mut TieredDetections,
    size: ImageSize,
    pitch_px: Option<f64>,
    judged: &[Point2],
) {
    let Some(pitch) = pitch_px.filter(|p| p.is_finite() && *p > 0.0) else {
        return;
    };
    let sides = Side::all(size);
    let near_edge = |d: &Detection| {
        sides
            .iter()
            .any(|s| s.inside_px(d.position) < NEAR_EDGE_PITCH * pitch)
    };
    if !found.accepted.iter().chain(&found.second_tier).any(near_edge) {
        return;
    }
    let points: Vec<Point2> = found.accepted.iter().map(|d| d.position).collect();
    let grid = Buckets::new(&points, pitch);
    let keep = |d: &Detection| judged.contains(&d.position) || stays(d.position, &sides, &grid, pitch);
    found.accepted.retain(keep);
    found.second_tier.retain(keep);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn det(x: f64, y: f64) -> Detection {
        Detection {
            position: Point2::new(x, y),
            confidence: 1.0,
        }
    }

    const SIZE: ImageSize = ImageSize {
        width: 320,
        height: 240,
    };

    /// A square lattice of pitch 25 px, 12 columns by 9 rows, the first at (`x0`, `y0`).
    fn lattice(x0: f64, y0: f64) -> Vec<Detection> {
        (0..9)
            .flat_map(|r| (0..12).map(move |c| det(x0 + 25.0 * f64::from(c), y0 + 25.0 * f64::from(r))))
            .collect()
    }

    /// Runs the check on `accepted` (no second tier), which are their own lattice.
    fn checked(accepted: Vec<Detection>) -> Vec<Detection> {
        let mut found = TieredDetections {
            accepted,
            second_tier: Vec::new(),
        };
        drop_past_the_edge(&mut found, SIZE, Some(25.0));
        found.accepted
    }

    /// A cut dot reported 2 px inside the left edge goes when its row's lattice puts its centre 1.5 px
    /// outside the outermost pixel centres (1 px outside the image), and stays when it puts it 0.3 px
    /// beyond them (inside the image's half pixel) or on them.
    #[test]
    fn a_cut_dot_goes_where_the_lattice_puts_its_centre_outside() {
        for (x0, stays) in [(23.5, false), (24.7, true), (25.0, true)] {
            let inner = lattice(x0, 12.0);
            let mut found = inner.clone();
            found.push(det(2.0, 112.0));
            let kept = checked(found.clone());
            assert_eq!(
                kept,
                if stays { found } else { inner.clone() },
                "first column at {x0}"
            );

            // The same dot in the second tier is judged by the accepted markers' lines.
            let mut tiered = TieredDetections {
                accepted: inner.clone(),
                second_tier: vec![det(2.0, 112.0)],
            };
            drop_past_the_edge(&mut tiered, SIZE, Some(25.0));
            assert_eq!(tiered.accepted, inner);
            assert_eq!(
                tiered.second_tier.len(),
                usize::from(stays),
                "first column at {x0}"
            );
        }
    }

    /// On the right and bottom sides: a dot whose lattice centre lies 0.3 px inside the edge stays
    /// though it is reported within the margin; one whose centre lies 2 px outside goes.
    #[test]
    fn every_side_is_checked_by_its_own_normal() {
        // The next column lies at 318.7 and the next row at 238.7: 0.3 px inside.
        let inner = lattice(18.7, 13.7);
        let mut found = inner.clone();
        found.push(det(318.9, 113.7));
        found.push(det(118.7, 238.9));
        assert_eq!(checked(found.clone()), found);

        // The next column lies at 321 and the next row at 241: 2 px outside.
        let inner = lattice(21.0, 16.0);
        let mut found = inner.clone();
        found.push(det(318.5, 116.0));
        found.push(det(121.0, 238.5));
        assert_eq!(checked(found), inner);
    }

    /// Without a line inwards (a lone detection) the margin decides: 0.5 px at pitch 25.
    #[test]
    fn without_a_line_the_margin_decides() {
        let found = checked(vec![det(0.3, 100.0), det(0.6, 150.0), det(150.0, -0.2)]);
        assert_eq!(found, vec![det(0.6, 150.0)]);
        let mut kept: TieredDetections = vec![det(0.3, 100.0)].into();
        drop_past_the_edge(&mut kept, SIZE, None);
        assert_eq!(kept.accepted, vec![det(0.3, 100.0)]);
    }
}
