//! A closer look where the lattice is squeezed. At the rim of a flat or box indenter the gel pushes
//! neighbouring dots together until they touch; at the scale the network runs on (a pitch of about
//! 12 px at its input) two such dots are one blob, which it reports once, between them, or not at
//! all. The first pass still shows where this happens: its candidates there lie much closer together
//! than the pitch. Around them the network runs once more, on a window of the input at
//! [`CLOSE_LOOK_ZOOM`] times the scale, and its candidates replace the first pass's inside the
//! region; the post-processing then runs on the merged candidates as on any pass's.
//!
//! There the lattice check keeps markers off the lattice lines from a lower confidence
//! ([`crate::lattice::LatticeCheck::looked_min_confidence`]).
//!
//! Frames without contact show no squeezed candidates, so they never pay for it. What it gains:
//! `docs/experiments/localization-squeezed-dots.md`.

use gelstereo_core::{Detection, ImageSize, Point2};

use crate::layout::{InputLayout, input_per_px, layout_at_scale};
use crate::region::Region;
use crate::spacing::nearest_neighbour_distances;
use crate::window::{Window, window_of_span};

/// A candidate whose nearest other candidate lies closer than this share of the pitch is squeezed.
/// An undisturbed lattice's nearest neighbours lie a pitch apart and a sphere's press moves them by
/// a tenth or two; a flat rim squeezes them to half a pitch. So a candidate this close marks a
/// squeeze, not an undisturbed lattice, and the markers the first pass misses in contact lie mostly
/// near such candidates.
pub const SQUEEZED_NN_PITCH: f64 = 0.8;

/// ... and the network is less sure of it than this. A pair the network resolved, both sure, needs no
/// second look, so the bound saves looks and window area without losing squeezed dots.
pub const SQUEEZED_MAX_CONFIDENCE: f32 = 0.9;

/// Scale of the close look relative to the first pass's: enough to resolve squeezed dots as two;
/// a larger zoom resolves a few more, but more of what it finds then fails the checks that follow,
/// so it ends with the same markers for more pixels.
pub const CLOSE_LOOK_ZOOM: f64 = 1.5;

/// The close look's zoom stops where it would put the marker pitch beyond this at the network input,
/// px: well inside the 9-24 px the network was trained on. Zoomed past its range on scan lines and
/// glints, it finds dots in the texture.
pub const CLOSE_LOOK_MAX_INPUT_PITCH_PX: f64 = 20.0;

/// A zoom below this is not worth a pass (the first pass already ran the pitch near the top of the
/// network's range).
pub const CLOSE_LOOK_MIN_ZOOM: f64 = 1.2;

/// A region of squeezed candidates larger than this share of the image is no squeeze at an
/// indenter's rim but a lattice irregular throughout, or texture: no closer look there.
pub const CLOSE_LOOK_MAX_SHARE: f64 = 0.5;

/// Margin around the squeezed candidates, in pitches, inside which the close look's candidates
/// replace the first pass's: the dots next to a squeezed pair are often squeezed too.
pub const CLOSE_LOOK_MARGIN_PITCH: f64 = 1.5;

/// Context the network sees beyond that region, in pitches, before the window is rounded out to the
/// input multiple: a dot at the region's edge is seen whole.
pub const CLOSE_LOOK_CONTEXT_PITCH: f64 = 1.0;

/// The region worth a closer look among `kept` (a pass's de-duplicated candidates) of an image of
/// `size` with marker pitch `pitch_px`: the bounding box of the squeezed ones
/// ([`SQUEEZED_NN_PITCH`], [`SQUEEZED_MAX_CONFIDENCE`]) grown by [`CLOSE_LOOK_MARGIN_PITCH`] and clipped to the image; `None`
/// without a pitch or a squeezed candidate, or where the region is larger than
/// [`CLOSE_LOOK_MAX_SHARE`] of the image.
pub fn squeezed_region(kept: &[Detection], pitch_px: Option<f64>, size: ImageSize) -> Option<Region> {
    let points: Vec<_> = kept.iter().map(|d| d.position).collect();
    squeezed_region_of(kept, &nearest_neighbour_distances(&points), pitch_px, size)
}

/// [`squeezed_region`] given `nn`, each of `kept`'s nearest-neighbour distances among them.
pub(crate) fn squeezed_region_of(
    kept: &[Detection],
    nn: &[f64],
    pitch_px: Option<f64>,
    size: ImageSize,
) -> Option<Region> {
    let pitch = pitch_px.filter(|p| p.is_finite() && *p > 0.0)?;
    let squeezed = nn
        .iter()
        .copied()
        .zip(kept)
        .filter(|(nn, d)| *nn < SQUEEZED_NN_PITCH * pitch && d.confidence < SQUEEZED_MAX_CONFIDENCE)
        .map(|(_, d)| d.position);
    region_around(squeezed, pitch, size)
}

/// The bounding box of `points` grown by [`CLOSE_LOOK_MARGIN_PITCH`] x `pitch` and clipped to the
/// image span of `size`; `None` without points or where it covers more than [`CLOSE_LOOK_MAX_SHARE`]
/// of the image (squeezed points that spread so far are an irregular lattice, not a squeeze).
pub(crate) fn region_around(
    points: impl IntoIterator<Item = Point2>,
    pitch: f64,
    size: ImageSize,
) -> Option<Region> {
    let mut found: Option<Region> = None;
    for p in points {
        let r = found.get_or_insert(Region {
            x0: p.x,
            y0: p.y,
            x1: p.x,
            y1: p.y,
        });
        r.x0 = r.x0.min(p.x);
        r.y0 = r.y0.min(p.y);
        r.x1 = r.x1.max(p.x);
        r.y1 = r.y1.max(p.y);
    }
    let margin = CLOSE_LOOK_MARGIN_PITCH * pitch;
    found
        .map(|r| Region {
            x0: (r.x0 - margin).max(-0.5),
            y0: (r.y0 - margin).max(-0.5),
            x1: (r.x1 + margin).min(f64::from(size.width) - 0.5),
            y1: (r.y1 + margin).min(f64::from(size.height) - 0.5),
        })
        .filter(|r| r.share_of(size) <= CLOSE_LOOK_MAX_SHARE)
}

/// The close look's zoom for a first pass under `layout` of an image of `size` with marker pitch
/// `pitch_px`: [`CLOSE_LOOK_ZOOM`], or less where that would put the pitch beyond
/// [`CLOSE_LOOK_MAX_INPUT_PITCH_PX`] at the input; `None` below [`CLOSE_LOOK_MIN_ZOOM`].
pub fn close_look_zoom(size: ImageSize, layout: &InputLayout, pitch_px: f64) -> Option<f64> {
    let at_input = pitch_px * input_per_px(size, layout);
    let zoom = CLOSE_LOOK_ZOOM.min(CLOSE_LOOK_MAX_INPUT_PITCH_PX / at_input);
    (zoom >= CLOSE_LOOK_MIN_ZOOM).then_some(zoom)
}

/// Where the close look of `region` of an image of `size` (first pass under `layout`, marker pitch
/// `pitch_px`) runs: the whole image's layout at `zoom` times the scale, and the window
/// of its input around the region with [`CLOSE_LOOK_CONTEXT_PITCH`] of context, on multiples of
/// `multiple` (so that the network sees the pixels it would on the whole zoomed input).
pub fn close_look_input(
    size: ImageSize,
    layout: &InputLayout,
    region: &Region,
    pitch_px: f64,
    zoom: f64,
    multiple: u32,
) -> (InputLayout, Window) {
    let scale = zoom * input_per_px(size, layout);
    let (w, h) = (f64::from(size.width), f64::from(size.height));
    let zoomed = layout_at_scale(w, h, pitch_px, scale, multiple);
    let window = window_of_span(
        (region.x0, region.x1),
        (region.y0, region.y1),
        CLOSE_LOOK_CONTEXT_PITCH * pitch_px,
        size,
        &zoomed,
        multiple,
    );
    (zoomed, window)
}

/// The candidates of an image after a close look at `region`: the first pass's outside it, in their
/// order, then the close look's inside it, in theirs.
pub fn merge(first: Vec<Detection>, closer: Vec<Detection>, region: &Region) -> Vec<Detection> {
    first
        .into_iter()
        .filter(|d| !region.contains(d))
        .chain(closer.into_iter().filter(|d| region.contains(d)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_core::Point2;

    const SIZE: ImageSize = ImageSize {
        width: 640,
        height: 480,
    };

    fn at(x: f64, y: f64) -> Detection {
        Detection {
            position: Point2::new(x, y),
            confidence: 0.6,
        }
    }

    fn lattice(pitch: f64) -> Vec<Detection> {
        (0..20 * 15)
            .map(|k| at(30.0 + (k % 20) as f64 * pitch, 30.0 + (k / 20) as f64 * pitch))
            .collect()
    }

    /// The zoom keeps the pitch inside the network's range at the input, and a pass already near its
    /// top gets none.
    #[test]
    fn the_zoom_stays_in_the_networks_range() {
        let at_pitch = |p: f64| layout_at_scale(640.0, 480.0, p, 12.0 / p, 32);
        let zoom = |input_pitch: f64| close_look_zoom(SIZE, &at_pitch(20.0), input_pitch * 20.0 / 12.0);
        assert_eq!(zoom(12.0), Some(CLOSE_LOOK_ZOOM));
        let capped = zoom(16.0).expect("a zoom");
        assert!(
            (capped * 16.0 - CLOSE_LOOK_MAX_INPUT_PITCH_PX).abs() < 0.2,
            "{capped}"
        );
        assert_eq!(zoom(18.0), None);
    }

    /// A region of squeezed candidates over most of the image (an irregular lattice) is no squeeze.
    #[test]
    fn squeezed_candidates_all_over_the_image_ask_for_no_look() {
        let pitch = 20.0;
        let mut pairs = lattice(pitch);
        for k in [0, 18, 280, 298] {
            pairs[k + 1].position.x = pairs[k].position.x + 0.5 * pitch;
        }
        // the lattice (30..410 x 30..310) fills a 440 x 340 image
        let size = ImageSize {
            width: 440,
            height: 340,
        };
        assert_eq!(squeezed_region(&pairs, Some(pitch), size), None);
        assert!(squeezed_region(&pairs[..40], Some(pitch), size).is_some());
    }

    /// An undisturbed lattice, or one a press moves by a fifth of the pitch, asks for no closer look.
    #[test]
    fn an_undisturbed_or_gently_pressed_lattice_is_not_looked_at() {
        let pitch = 20.0;
        assert_eq!(squeezed_region(&lattice(pitch), Some(pitch), SIZE), None);
        let mut pressed = lattice(pitch);
        pressed[100].position.x += 0.19 * pitch;
        assert_eq!(squeezed_region(&pressed, Some(pitch), SIZE), None);
        assert_eq!(squeezed_region(&lattice(pitch), None, SIZE), None);
    }

    /// Two dots squeezed to half a pitch, the network unsure of them, give the box around them with
    /// the margin (none when it is sure of both); a pair near the image's edge gives a box clipped to
    /// the image.
    #[test]
    fn squeezed_dots_give_their_box_with_the_margin_inside_the_image() {
        let pitch = 20.0;
        let mut pressed = lattice(pitch);
        // dots 125 (x 130, y 150) and 126 (x 150, y 150): the second pushed to half a pitch away
        pressed[126].position.x -= 0.5 * pitch;
        let r = squeezed_region(&pressed, Some(pitch), SIZE).expect("a region");
        let m = CLOSE_LOOK_MARGIN_PITCH * pitch;
        assert_eq!(
            (r.x0, r.x1, r.y0, r.y1),
            (130.0 - m, 140.0 + m, 150.0 - m, 150.0 + m)
        );
        // dots 0 and 1 (y 30) squeezed against the left edge: the box stops at the image's edge
        pressed[0].position.x = 2.0;
        pressed[1].position.x = 10.0;
        let r = squeezed_region(&pressed, Some(pitch), SIZE).expect("a region");
        assert_eq!((r.x0, r.y0), (-0.5, 30.0 - m));
        assert!(r.x1 >= 140.0 + m && r.y1 >= 150.0 + m);
    }

    /// The merge keeps the first pass's candidates outside the region and the close look's inside it.
    #[test]
    fn the_close_look_replaces_the_first_pass_inside_its_region_only() {
        let region = Region {
            x0: 100.0,
            y0: 100.0,
            x1: 200.0,
            y1: 200.0,
        };
        let first = vec![at(50.0, 50.0), at(150.0, 150.0), at(250.0, 150.0)];
        let closer = vec![at(140.0, 150.0), at(160.0, 150.0), at(260.0, 150.0)];
        let merged = merge(first, closer, &region);
        let xs: Vec<f64> = merged.iter().map(|d| d.position.x).collect();
        assert_eq!(xs, vec![50.0, 250.0, 140.0, 160.0]);
    }

    /// The window lies on the input multiple, covers the region with its context, and the zoomed
    /// layout is 1.5 x the first's scale.
    #[test]
    fn the_window_covers_the_region_at_the_zoomed_scale() {
        let pitch = 19.0;
        let first = layout_at_scale(640.0, 480.0, pitch, 416.0 / 659.0, 32);
        let region = Region {
            x0: 200.0,
            y0: 150.0,
            x1: 300.0,
            y1: 220.0,
        };
        let zoom = close_look_zoom(SIZE, &first, pitch).expect("a zoom");
        assert_eq!(zoom, CLOSE_LOOK_ZOOM);
        let (zoomed, w) = close_look_input(SIZE, &first, &region, pitch, zoom, 32);
        let ratio = input_per_px(SIZE, &zoomed) / input_per_px(SIZE, &first);
        assert!((ratio - CLOSE_LOOK_ZOOM).abs() < 0.01, "{ratio}");
        assert_eq!((w.x % 32, w.y % 32, w.width % 32, w.height % 32), (0, 0, 0, 0));
        let s = f64::from(zoomed.scaled_width) / 640.0;
        let to_input = |v: f64, o: u32| f64::from(o) + (v + 0.5) * s;
        let context = CLOSE_LOOK_CONTEXT_PITCH * pitch * s;
        assert!(f64::from(w.x) <= to_input(region.x0, zoomed.offset_x) - context);
        assert!(f64::from(w.x + w.width) >= to_input(region.x1, zoomed.offset_x) + context);
        assert!(f64::from(w.y) <= to_input(region.y0, zoomed.offset_y) - context);
        assert!(f64::from(w.y + w.height) >= to_input(region.y1, zoomed.offset_y) + context);
        assert!(w.width < zoomed.input_width && w.height < zoomed.input_height);
    }
}
