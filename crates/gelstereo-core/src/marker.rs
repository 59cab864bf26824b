use serde::{Deserialize, Serialize};

use crate::Error;

/// A point in an image, in pixels of the original image ((0, 0) = centre of the top-left pixel).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Point2 {
    /// Pixels to the right of the top-left pixel's centre.
    pub x: f64,
    /// Pixels below the top-left pixel's centre.
    pub y: f64,
}

impl Point2 {
    /// The point (`x`, `y`).
    pub const fn new(x: f64, y: f64) -> Self {
        Self { x, y }
    }

    /// Euclidean distance to `other`, in pixels.
    pub fn distance(&self, other: Point2) -> f64 {
        (self.x - other.x).hypot(self.y - other.y)
    }
}

/// Width and height of an image in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ImageSize {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
}

/// One marker found by a localizer in one view.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Detection {
    /// Marker centre, pixels of the original image.
    pub position: Point2,
    /// The localizer's confidence in (0, 1]; 1 for detectors without a score (blob baseline).
    pub confidence: f32,
}

/// A localizer's output for one view with the candidates it found but did not accept: a tracker
/// may give one of those to a marker it expects there and finds nothing else for
/// (`docs/tracking.md`, "Second-tier candidates"). Localizers without such candidates leave
/// `second_tier` empty.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TieredDetections {
    /// The markers (what the localizer's `detect` returns).
    pub accepted: Vec<Detection>,
    /// Candidates not accepted (Marknet-MRE: `conf_low < c <= conf_keep` with an MRE score at or
    /// below its threshold; Marknet: `conf_low < c <= conf_marknet_only`), with Marknet's
    /// confidence.
    pub second_tier: Vec<Detection>,
}

impl From<Vec<Detection>> for TieredDetections {
    fn from(accepted: Vec<Detection>) -> Self {
        Self {
            accepted,
            second_tier: Vec::new(),
        }
    }
}

/// Which camera of the stereo pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub enum View {
    /// The left camera: its frame is the reference 3-D frame.
    Left,
    /// The right camera.
    Right,
}

/// The same kind of thing for the left and the right view (images, detections, cameras).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct StereoPair<T> {
    /// Left view.
    pub left: T,
    /// Right view.
    pub right: T,
}

impl<T> StereoPair<T> {
    /// The pair (`left`, `right`).
    pub fn new(left: T, right: T) -> Self {
        Self { left, right }
    }

    /// The member for `view`.
    pub fn get(&self, view: View) -> &T {
        match view {
            View::Left => &self.left,
            View::Right => &self.right,
        }
    }

    /// Applies `f` to both views.
    pub fn map<U>(self, mut f: impl FnMut(T) -> U) -> StereoPair<U> {
        StereoPair {
            left: f(self.left),
            right: f(self.right),
        }
    }
}

macro_rules! named_enum {
    ($(#[$doc:meta])* $name:ident, $what:literal, { $($(#[$vdoc:meta])* $variant:ident => $text:literal),+ $(,)? }) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
        #[serde(rename_all = "snake_case")]
        pub enum $name {
            $($(#[$vdoc])* $variant),+
        }

        impl $name {
            /// The word used for this value in tables and on the command line.
            pub const fn as_str(self) -> &'static str {
                match self { $(Self::$variant => $text),+ }
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.as_str())
            }
        }

        impl std::str::FromStr for $name {
            type Err = Error;
            fn from_str(s: &str) -> Result<Self, Error> {
                match s {
                    $($text => Ok(Self::$variant),)+
                    _ => Err(Error::UnknownName {
                        what: $what,
                        found: s.to_owned(),
                        expected: concat!($($text, " "),+),
                    }),
                }
            }
        }
    };
}

named_enum!(
    /// How a marker's position in a frame was obtained.
    MarkerStatus, "marker status", {
        /// Detected and associated in this frame.
        Tracked => "tracked",
        /// Not detected; position predicted from its neighbours' motion.
        Predicted => "predicted",
        /// Neither detected nor predictable.
        Lost => "lost",
    }
);

named_enum!(
    /// Per-frame slip state of the contact.
    SlipState, "slip state", {
        /// Nothing touches the gel.
        NoContact => "no_contact",
        /// Contact, the whole contact region sticks to the object.
        Stick => "stick",
        /// The stick region shrinks from the edge: part of the contact slides.
        PartialSlip => "partial_slip",
        /// The whole contact region slides.
        GrossSlip => "gross_slip",
    }
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_names_are_reported() {
        for s in [
            SlipState::NoContact,
            SlipState::Stick,
            SlipState::PartialSlip,
            SlipState::GrossSlip,
        ] {
            assert_eq!(s.as_str().parse::<SlipState>().unwrap(), s);
        }
        for s in [MarkerStatus::Tracked, MarkerStatus::Predicted, MarkerStatus::Lost] {
            assert_eq!(s.to_string().parse::<MarkerStatus>().unwrap(), s);
        }
        let err = "sliding".parse::<SlipState>().unwrap_err().to_string();
        assert!(err.contains("sliding") && err.contains("gross_slip"), "{err}");
    }
}
