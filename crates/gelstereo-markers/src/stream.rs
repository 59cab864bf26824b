//! What Marknet keeps from one frame of a stream to the next: the marker pitch measured per image
//! size (the "auto" fit's layout of the next image of that size) and each view's lattice window
//! ([`crate::window`]), with the two switches that allow them. Everything a later frame's result
//! depends on besides the model and the thresholds lives here, so a forked localizer that copies it
//! localizes the stream's next frames as the original would.

use std::collections::HashMap;

use gelstereo_core::ImageSize;

use crate::window::LatticeWindow;

/// The state a stream of frames leaves in a localizer. The memories stay empty while their switch
/// is off: turning pitch memory off forgets the pitches and the windows (a window belongs to a
/// remembered pitch), turning windows off forgets the windows.
#[derive(Debug, Clone)]
pub(crate) struct StreamState {
    remember_pitch: bool,
    lattice_window: bool,
    /// Marker pitch (original px) measured per image size.
    pitch: HashMap<ImageSize, f64>,
    /// Per image size and view (index in the batch): the window of the input the view runs on, or
    /// `None` where its first frame showed that a window would not save enough or not hold.
    windows: HashMap<(ImageSize, usize), Option<LatticeWindow>>,
}

impl Default for StreamState {
    /// Pitch memory and windows on, nothing remembered yet.
    fn default() -> Self {
        Self {
            remember_pitch: true,
            lattice_window: true,
            pitch: HashMap::new(),
            windows: HashMap::new(),
        }
    }
}

impl StreamState {
    /// Turns pitch memory on or off; off forgets every pitch and window.
    pub(crate) fn set_remember_pitch(&mut self, remember: bool) {
        self.remember_pitch = remember;
        if !remember {
            self.pitch.clear();
            self.windows.clear();
        }
    }

    /// Turns lattice windows on or off; off forgets every window.
    pub(crate) fn set_lattice_window(&mut self, on: bool) {
        self.lattice_window = on;
        if !on {
            self.windows.clear();
        }
    }

    /// The pitch remembered for images of `size`, original px.
    pub(crate) fn pitch(&self, size: ImageSize) -> Option<f64> {
        self.pitch.get(&size).copied()
    }

    /// Remembers `pitch_px` for images of `size` (with pitch memory on): the first one measured, or a
    /// later one where `replace` (a pass that asked for another layout).
    pub(crate) fn learn_pitch(&mut self, size: ImageSize, pitch_px: f64, replace: bool) {
        if self.remember_pitch && (replace || !self.pitch.contains_key(&size)) {
            self.pitch.insert(size, pitch_px);
        }
    }

    /// The window view `slot` of images of `size` runs on, as remembered.
    pub(crate) fn window(&self, size: ImageSize, slot: usize) -> Option<LatticeWindow> {
        self.windows.get(&(size, slot)).copied().flatten()
    }

    /// [`window`](Self::window), while it still belongs to the remembered pitch: a window made for
    /// another pitch (a relayout changed it) is forgotten, so the view learns a new one.
    pub(crate) fn current_window(&mut self, size: ImageSize, slot: usize) -> Option<LatticeWindow> {
        let entry = self.windows.get(&(size, slot)).copied()?;
        match entry {
            Some(w) if Some(w.pitch_px) != self.pitch(size) => {
                self.windows.remove(&(size, slot));
                None
            }
            w => w,
        }
    }

    /// Whether view `slot` of images of `size` may learn a window: windows and pitch memory on, a
    /// pitch remembered, nothing learnt yet.
    pub(crate) fn may_learn_window(&self, size: ImageSize, slot: usize) -> bool {
        self.remember_pitch
            && self.lattice_window
            && self.pitch.contains_key(&size)
            && !self.windows.contains_key(&(size, slot))
    }

    /// Remembers what view `slot` of images of `size` learnt (`None`: no window to run on).
    pub(crate) fn learn_window(&mut self, size: ImageSize, slot: usize, window: Option<LatticeWindow>) {
        self.windows.insert((size, slot), window);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::InputLayout;
    use crate::window::Window;

    const SIZE: ImageSize = ImageSize {
        width: 640,
        height: 480,
    };

    fn window_for(pitch_px: f64) -> LatticeWindow {
        LatticeWindow {
            window: Window {
                x: 32,
                y: 32,
                width: 256,
                height: 256,
            },
            layout: InputLayout::stretch(416, 320),
            pitch_px,
            markers: 100,
        }
    }

    #[test]
    fn the_first_pitch_is_kept_until_a_relayout_replaces_it() {
        let mut s = StreamState::default();
        s.learn_pitch(SIZE, 20.0, false);
        s.learn_pitch(SIZE, 21.0, false);
        assert_eq!(s.pitch(SIZE), Some(20.0));
        s.learn_pitch(SIZE, 22.0, true);
        assert_eq!(s.pitch(SIZE), Some(22.0));
        assert_eq!(
            s.pitch(ImageSize {
                width: 320,
                height: 240
            }),
            None
        );
    }

    #[test]
    fn a_window_is_learnt_once_per_view_and_dropped_when_the_pitch_moves() {
        let mut s = StreamState::default();
        assert!(!s.may_learn_window(SIZE, 0), "no pitch yet");
        s.learn_pitch(SIZE, 20.0, false);
        assert!(s.may_learn_window(SIZE, 0));
        s.learn_window(SIZE, 0, Some(window_for(20.0)));
        s.learn_window(SIZE, 1, None);
        assert!(!s.may_learn_window(SIZE, 0) && !s.may_learn_window(SIZE, 1));
        assert_eq!(s.current_window(SIZE, 0), Some(window_for(20.0)));
        assert_eq!(s.current_window(SIZE, 1), None);
        s.learn_pitch(SIZE, 25.0, true);
        assert_eq!(s.current_window(SIZE, 0), None);
        assert!(
            s.may_learn_window(SIZE, 0),
            "the view learns again at the new pitch"
        );
    }

    #[test]
    fn switching_off_forgets_what_the_switch_allowed() {
        let mut s = StreamState::default();
        s.learn_pitch(SIZE, 20.0, false);
        s.learn_window(SIZE, 0, Some(window_for(20.0)));
        s.set_lattice_window(false);
        assert_eq!((s.pitch(SIZE), s.window(SIZE, 0)), (Some(20.0), None));
        assert!(!s.may_learn_window(SIZE, 0));
        s.set_lattice_window(true);
        s.learn_window(SIZE, 0, Some(window_for(20.0)));
        s.set_remember_pitch(false);
        assert_eq!((s.pitch(SIZE), s.window(SIZE, 0)), (None, None));
        s.learn_pitch(SIZE, 20.0, false);
        assert_eq!(s.pitch(SIZE), None, "nothing is remembered while memory is off");
    }
}
