//! The part of a stream's images the network runs on. A sensor's marker lattice often fills only part
//! of its camera image (the bundled 640 x 480 sample: 365 x 397 px of it); the rest is housing and gel
//! edge, where the network only spends time. Once a stream's first frame has shown where the lattice
//! lies, later frames of that view run the network on a window of the whole image's network input
//! around it ([`window_around`]): the image is resized into its usual layout, and the window's corners
//! lie on multiples of the input multiple (the network's coarsest stride), so every convolution sees
//! the same pixels on the same grid as on the whole input, and the markers come out as they would
//! there, up to the context cut at the window's edges. A frame whose markers come
//! near an edge of the window that lies inside the input, or that shows far fewer markers than the
//! first, is run whole instead ([`LatticeWindow::holds`]): a lattice that slid out of the window, a
//! column the first frame missed, another scene. The window never changes after the first frame, so
//! every frame's markers depend on that frame and the first alone, whichever thread localized it.

use gelstereo_core::{Detection, ImageSize};

use crate::layout::InputLayout;

/// Margin around the first frame's markers, in pitches, before the window is rounded out to the
/// input multiple: room for the lattice to move before a frame falls back to the whole input, and
/// context for the outermost markers.
pub const WINDOW_MARGIN_PITCH: f64 = 2.0;

/// A frame falls back to the whole input when one of its markers lies closer than this (in pitches)
/// to an edge of the window that is not the input's own. A marker past the edge has its inner
/// neighbour about one pitch inside it, so a lattice that slides out is caught before it is lost.
pub const WINDOW_GUARD_PITCH: f64 = 1.25;

/// A frame falls back to the whole input when it finds fewer than this share of the first frame's
/// markers in the window (an indenter hides a few; another scene, most).
pub const WINDOW_MIN_SHARE: f64 = 0.75;

/// Markers the first frame needs before a window is drawn around them.
pub const WINDOW_MIN_MARKERS: usize = 16;

/// A window is used only when it is at most this share of the whole input: a larger one saves too
/// little to be worth its cost on the frames that fall back.
pub const WINDOW_MAX_INPUT_SHARE: f64 = 0.85;

/// A rectangle of the network input, px, its corners on multiples of the input multiple.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Window {
    /// Input column of the left edge.
    pub x: u32,
    /// Input row of the top edge.
    pub y: u32,
    /// Width, input px.
    pub width: u32,
    /// Height, input px.
    pub height: u32,
}

/// A view's window, the whole image's layout it is cut from and what the first frame showed there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatticeWindow {
    /// The window of the input the network runs on.
    pub window: Window,
    /// The whole image's layout (the remembered pitch's).
    pub layout: InputLayout,
    /// The marker pitch the window and its layout were made for, original px.
    pub pitch_px: f64,
    /// Markers the first frame showed.
    pub markers: usize,
}

/// Input px per original px along x and y of an image of `size` under `layout`.
fn input_scale(size: ImageSize, layout: &InputLayout) -> (f64, f64) {
    (
        f64::from(layout.scaled_width) / f64::from(size.width.max(1)),
        f64::from(layout.scaled_height) / f64::from(size.height.max(1)),
    )
}

impl LatticeWindow {
    /// Whether `accepted` (markers an image of `size` showed in the window, in the image's pixels)
    /// may stand for the whole input: enough of them, none near an edge of the window that lies
    /// inside the input.
    pub fn holds(&self, accepted: &[Detection], size: ImageSize) -> bool {
        if (accepted.len() as f64) < WINDOW_MIN_SHARE * self.markers as f64 {
            return false;
        }
        let (w, l) = (&self.window, &self.layout);
        let (sx, sy) = input_scale(size, l);
        let (left, top) = (f64::from(w.x), f64::from(w.y));
        let (right, bottom) = (left + f64::from(w.width), top + f64::from(w.height));
        let inner = [
            w.x > 0,
            w.y > 0,
            w.x + w.width < l.input_width,
            w.y + w.height < l.input_height,
        ];
        let guard = [sx, sy, sx, sy].map(|s| WINDOW_GUARD_PITCH * self.pitch_px * s);
        accepted.iter().all(|d| {
            let x = f64::from(l.offset_x) + (d.position.x + 0.5) * sx;
            let y = f64::from(l.offset_y) + (d.position.y + 0.5) * sy;
            let gaps = [x - left, y - top, right - x, bottom - y];
            (0..4).all(|k| !inner[k] || gaps[k] >= guard[k])
        })
    }
}

/// The window of `layout` (the whole input of an image of `size`) around `markers` (original px) of
/// a lattice of pitch `pitch_px`: their bounding box with [`WINDOW_MARGIN_PITCH`] pitches of margin,
/// rounded out to multiples of `multiple` and kept in the input. `None` when there are fewer than
/// [`WINDOW_MIN_MARKERS`] markers or the window would save too little ([`WINDOW_MAX_INPUT_SHARE`]).
pub fn window_around(
    markers: &[Detection],
    size: ImageSize,
    pitch_px: f64,
    layout: &InputLayout,
    multiple: u32,
) -> Option<LatticeWindow> {
    if markers.len() < WINDOW_MIN_MARKERS || pitch_px.is_nan() || pitch_px <= 0.0 {
        return None;
    }
    let span = |along: fn(&Detection) -> f64| {
        markers
            .iter()
            .map(along)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            })
    };
    let window = window_of_span(
        span(|d| d.position.x),
        span(|d| d.position.y),
        WINDOW_MARGIN_PITCH * pitch_px,
        size,
        layout,
        multiple,
    );
    let share = (f64::from(window.width) * f64::from(window.height))
        / (f64::from(layout.input_width) * f64::from(layout.input_height)).max(1.0);
    if window.width == 0 || window.height == 0 || share > WINDOW_MAX_INPUT_SHARE {
        return None;
    }
    Some(LatticeWindow {
        window,
        layout: *layout,
        pitch_px,
        markers: markers.len(),
    })
}

/// The window of `layout` (the whole input of an image of `size`) around the original pixels
/// `xs` x `ys` (first and last, pixel-centre convention) with `margin_px` original px of margin,
/// rounded out to multiples of `multiple` and kept in the input.
pub(crate) fn window_of_span(
    xs: (f64, f64),
    ys: (f64, f64),
    margin_px: f64,
    size: ImageSize,
    layout: &InputLayout,
    multiple: u32,
) -> Window {
    let (sx, sy) = input_scale(size, layout);
    let m = f64::from(multiple.max(1));
    let axis = |(lo, hi): (f64, f64), offset: u32, s: f64, input: u32| -> (u32, u32) {
        let to_input = |v: f64| f64::from(offset) + (v + 0.5) * s;
        let first = ((to_input(lo) - margin_px * s) / m).floor().max(0.0) * m;
        let last = (((to_input(hi) + margin_px * s) / m).ceil() * m).min(f64::from(input));
        (first as u32, (last - first).max(0.0) as u32)
    };
    let (x, width) = axis(xs, layout.offset_x, sx, layout.input_width);
    let (y, height) = axis(ys, layout.offset_y, sy, layout.input_height);
    Window { x, y, width, height }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::layout_at_scale;
    use gelstereo_core::Point2;

    fn lattice(x0: f64, y0: f64, (nx, ny): (usize, usize), pitch: f64) -> Vec<Detection> {
        (0..nx * ny)
            .map(|k| Detection {
                position: Point2::new(x0 + (k % nx) as f64 * pitch, y0 + (k / nx) as f64 * pitch),
                confidence: 0.9,
            })
            .collect()
    }

    const SIZE: ImageSize = ImageSize {
        width: 640,
        height: 480,
    };

    /// The bundled sample's geometry: a 23 x 23 lattice of 16.5 px pitch in the middle of 640 x 480,
    /// at its layout (416 x 320 input). The window lies on multiples of 32, holds every marker with
    /// at least the margin, and is narrower than the input.
    #[test]
    fn the_window_holds_the_lattice_with_its_margin_on_the_input_multiple() {
        let pitch = 16.5;
        let layout = layout_at_scale(640.0, 480.0, pitch, 416.0 / 656.5, 32);
        assert_eq!((layout.input_width, layout.input_height), (416, 320));
        let markers = lattice(125.0, 40.0, (23, 23), pitch);
        let r = window_around(&markers, SIZE, pitch, &layout, 32).expect("a window");
        let w = r.window;
        assert_eq!(
            (w.x % 32, w.y % 32, w.width % 32, w.height % 32),
            (0, 0, 0, 0),
            "{w:?}"
        );
        assert!(
            w.width < 416 && w.x + w.width <= 416 && w.y + w.height <= 320,
            "{w:?}"
        );
        let s = f64::from(layout.scaled_width) / 640.0;
        let margin = WINDOW_MARGIN_PITCH * pitch * s;
        for d in &markers {
            let x = f64::from(layout.offset_x) + (d.position.x + 0.5) * s;
            assert!(
                x - f64::from(w.x) >= margin && f64::from(w.x + w.width) - x >= margin,
                "{w:?} at {x}"
            );
        }
        // The markers of the frame that made it pass its own check.
        assert!(r.holds(&markers, SIZE));
    }

    /// A lattice that slides towards an inner edge, or loses most of its markers, falls back to the
    /// whole input; one moving a little inside the window does not.
    #[test]
    fn a_lattice_near_an_inner_edge_or_thinned_out_falls_back() {
        let pitch = 16.5;
        let layout = layout_at_scale(640.0, 480.0, pitch, 416.0 / 656.5, 32);
        let markers = lattice(125.0, 40.0, (23, 23), pitch);
        let r = window_around(&markers, SIZE, pitch, &layout, 32).expect("a window");
        let shifted = |dx: f64| -> Vec<Detection> {
            markers
                .iter()
                .map(|d| Detection {
                    position: Point2::new(d.position.x + dx, d.position.y),
                    ..*d
                })
                .collect()
        };
        assert!(r.holds(&shifted(0.5 * pitch), SIZE));
        assert!(r.holds(&shifted(-0.5 * pitch), SIZE));
        assert!(!r.holds(&shifted(4.5 * pitch), SIZE));
        assert!(!r.holds(&shifted(-4.5 * pitch), SIZE));
        assert!(!r.holds(&markers[..markers.len() / 2], SIZE));
    }

    /// A lattice that fills the image, or too few markers, gives no window.
    #[test]
    fn no_window_where_it_would_not_save_or_could_not_be_trusted() {
        let layout = layout_at_scale(640.0, 480.0, 29.0, 0.5, 32);
        let full = lattice(12.0, 10.0, (22, 16), 29.0);
        assert!(window_around(&full, SIZE, 29.0, &layout, 32).is_none());
        let few = lattice(300.0, 200.0, (3, 3), 16.5);
        let sample = layout_at_scale(640.0, 480.0, 16.5, 416.0 / 656.5, 32);
        assert!(window_around(&few, SIZE, 16.5, &sample, 32).is_none());
    }
}
