//! Experiment scripts: how an indenter moves over the frames of one recording (press, hold, slide,
//! twist, release), and the pose it has in each frame.

use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::indenter::Indenter;

/// What the indenter does after pressing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionKind {
    /// Press, change depth, release.
    Press,
    /// Press, then slide along a direction.
    PressSlide,
    /// Press, then twist about the pressing axis.
    PressTwist,
    /// Press, then slide and twist together.
    PressSlideTwist,
}

impl MotionKind {
    /// The names [`MotionKind::from_str`](std::str::FromStr) takes, as written in `meta.json`.
    pub const NAMES: [&'static str; 4] = ["press", "press_slide", "press_twist", "press_slide_twist"];
}

impl std::str::FromStr for MotionKind {
    type Err = crate::error::Error;
    /// Accepts the `meta.json` names, with `-` for `_` as on a command line.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.replace('-', "_").as_str() {
            "press" => Ok(Self::Press),
            "press_slide" => Ok(Self::PressSlide),
            "press_twist" => Ok(Self::PressTwist),
            "press_slide_twist" => Ok(Self::PressSlideTwist),
            _ => Err(crate::error::Error::Parameter {
                name: "motion",
                value: s.to_owned(),
                expected: format!("one of {}", Self::NAMES.join(", ")),
            }),
        }
    }
}

/// One experiment's motion: an indenter, where it touches down and how it moves afterwards.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Script {
    /// The object.
    pub indenter: Indenter,
    /// What happens after the press.
    pub kind: MotionKind,
    /// Touch-down point in the sensor frame, mm.
    pub centre_mm: [f64; 2],
    /// Orientation of the indenter's local x axis at touch-down, degrees from the sensor's x.
    pub angle_deg: f64,
    /// Deepest press, mm.
    pub max_depth_mm: f64,
    /// Total slide of the indenter (sensor frame), mm.
    pub slide_mm: [f64; 2],
    /// Total twist, degrees (positive: from +x towards +y).
    pub twist_deg: f64,
    /// Number of frames.
    pub frames: u32,
    /// Fraction of the recording at which the press reaches full depth.
    pub press_end: f64,
    /// Fraction at which the slide / twist ends (and the release starts).
    pub shear_end: f64,
    /// Whether the object is lifted off at the end (else the recording ends in contact).
    pub release: bool,
}

/// The indenter's state in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Depth of the lowest point below the undeformed surface, mm (<= 0: not touching).
    pub depth_mm: f64,
    /// Slide since touch-down, sensor frame, mm.
    pub slide_mm: [f64; 2],
    /// Twist since touch-down, degrees.
    pub twist_deg: f64,
}

fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

impl Script {
    /// A random script for `indenter` over `frames` frames, touching down within `reach_mm` of the
    /// gel centre; depths and slides are multiplied by `scale` (1 for a gel about 18 mm wide).
    /// `kind` fixes the motion; the draw is made either way, so that the other draws of a seed do
    /// not depend on it.
    pub fn random(
        indenter: Indenter,
        frames: u32,
        reach_mm: f64,
        scale: f64,
        kind: Option<MotionKind>,
        rng: &mut impl Rng,
    ) -> Self {
        let drawn = match rng.random_range(0..10) {
            0..=1 => MotionKind::Press,
            2..=6 => MotionKind::PressSlide,
            7..=8 => MotionKind::PressTwist,
            _ => MotionKind::PressSlideTwist,
        };
        let kind = kind.unwrap_or(drawn);
        let (dlo, dhi) = indenter.depth_range_mm();
        let max_depth_mm = rng.random_range(dlo..dhi) * scale;
        let r = reach_mm * rng.random_range(0.0f64..1.0).sqrt();
        let a = rng.random_range(0.0..std::f64::consts::TAU);
        let centre_mm = [r * a.cos(), r * a.sin()];
        let slides = matches!(kind, MotionKind::PressSlide | MotionKind::PressSlideTwist);
        let twists = matches!(kind, MotionKind::PressTwist | MotionKind::PressSlideTwist);
        let slide_len = if slides {
            rng.random_range(0.3..3.5) * scale
        } else {
            0.0
        };
        let dir = rng.random_range(0.0..std::f64::consts::TAU);
        let twist_deg = if twists {
            rng.random_range(4.0..25.0) * if rng.random_bool(0.5) { 1.0 } else { -1.0 }
        } else {
            0.0
        };
        let press_end = rng.random_range(0.25..0.45);
        let release = rng.random_bool(0.7);
        let shear_end = if release {
            rng.random_range(press_end + 0.25..0.85)
        } else {
            1.0
        };
        Self {
            indenter,
            kind,
            centre_mm,
            angle_deg: rng.random_range(0.0..360.0),
            max_depth_mm,
            slide_mm: [slide_len * dir.cos(), slide_len * dir.sin()],
            twist_deg,
            frames,
            press_end,
            shear_end,
            release,
        }
    }

    /// The pose in frame `frame` (frame 0 never touches).
    pub fn pose(&self, frame: u32) -> Pose {
        self.pose_at(f64::from(frame))
    }

    /// The pose at a fractional frame time (for motion blur); frame 0 and earlier never touch.
    pub fn pose_at(&self, frame: f64) -> Pose {
        if frame <= 0.0 || self.frames < 2 {
            return Pose {
                depth_mm: -0.3,
                slide_mm: [0.0; 2],
                twist_deg: 0.0,
            };
        }
        let t = frame / f64::from(self.frames - 1);
        // Touch-down a little after the start; the press follows a smooth (varying speed) ramp.
        let t0 = 0.06;
        let press = smoothstep((t - t0) / (self.press_end - t0));
        let mut depth = -0.05 + (self.max_depth_mm + 0.05) * press;
        if self.kind == MotionKind::Press {
            // Breathe: ease off to 60 % and press again during the hold.
            let h = ((t - self.press_end) / (self.shear_end - self.press_end)).clamp(0.0, 1.0);
            depth *= 1.0 - 0.4 * (std::f64::consts::PI * h).sin().powi(2);
        }
        let shear = ((t - self.press_end) / (self.shear_end - self.press_end)).clamp(0.0, 1.0);
        if self.release && t > self.shear_end {
            let r = smoothstep((t - self.shear_end) / (0.95 - self.shear_end).max(1e-3));
            depth = depth * (1.0 - r) - 0.2 * r;
        }
        Pose {
            depth_mm: depth,
            slide_mm: [self.slide_mm[0] * shear, self.slide_mm[1] * shear],
            twist_deg: self.twist_deg * shear,
        }
    }
}
