//! Contact and slip of mono sensors (one camera, e.g. a GelSight Mini) from the in-plane marker
//! displacement field, px, with the two signals of [`crate::slip`] transposed to 2-D:
//!
//! - the **contact region** is where the displacement magnitude exceeds
//!   `max(min_displacement_pitch x pitch, relative x the frame's largest displacement)`;
//! - the **stick fraction** is the share of contact markers on the plateau of the displacement
//!   projected on the mean shear direction (partial slip below `stick_fraction`);
//! - **gross slip** is a drift of the contact region in reference (material) coordinates along
//!   the shear, of more than `drift_pitch_per_frame` pitches per frame.
//!
//! Without depth, the area is counted in lattice cells (one per contact marker) and converted with
//! the marker pitch in mm when the sensor's pitch is known (`pitch_mm`); otherwise it is reported as
//! 0 and the centroid is left empty.

use gelstereo_core::{MarkerStatus, Point2, SlipState};

use crate::error::{Result, config_err};
use crate::tracker::{TrackFrame, Tracker};

/// Settings of the [`PlanarDetector`] (defaults chosen on the GelSight Mini video and the simulated
/// training split seen through the left camera only; `docs/tracking.md`).
#[derive(Debug, Clone, PartialEq)]
pub struct PlanarConfig {
    /// Smallest displacement that counts as contact, in marker pitches.
    pub min_displacement_pitch: f64,
    /// Contact threshold relative to the frame's largest displacement.
    pub relative: f64,
    /// Mean shear below which the contact sticks, in pitches.
    pub min_shear_pitch: f64,
    /// Stick fraction below which the contact is in partial slip.
    pub stick_fraction: f64,
    /// Relative tolerance of the displacement plateau.
    pub plateau_tolerance: f64,
    /// Drift of the contact region across the gel per frame above which it slides as a whole, pitches.
    pub drift_pitch_per_frame: f64,
    /// Marker pitch of the sensor, mm, to convert areas and centroids; `None` when unknown.
    pub pitch_mm: Option<f64>,
}

impl Default for PlanarConfig {
    fn default() -> Self {
        Self {
            min_displacement_pitch: 0.08,
            relative: 0.5,
            min_shear_pitch: 0.08,
            stick_fraction: 0.9,
            plateau_tolerance: 0.15,
            drift_pitch_per_frame: 0.03,
            pitch_mm: None,
        }
    }
}

impl PlanarConfig {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        for (field, v) in [
            ("min_displacement_pitch", self.min_displacement_pitch),
            ("min_shear_pitch", self.min_shear_pitch),
            ("drift_pitch_per_frame", self.drift_pitch_per_frame),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 5.0) {
                return Err(config_err(field, "a number of pitches in (0, 5)", v));
            }
        }
        for (field, v) in [
            ("relative", self.relative),
            ("stick_fraction", self.stick_fraction),
            ("plateau_tolerance", self.plateau_tolerance),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 1.0) {
                return Err(config_err(field, "a fraction in (0, 1)", v));
            }
        }
        if let Some(p) = self.pitch_mm
            && !(p.is_finite() && p > 0.0 && p < 100.0)
        {
            return Err(config_err("pitch_mm", "a pitch in (0, 100) mm", p));
        }
        Ok(())
    }
}

/// In-plane contact and slip of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanarFrame {
    /// Whether the field shows a contact.
    pub contact: bool,
    /// Contact markers x pitch^2 when `pitch_mm` is known, else 0.
    pub contact_area_mm2: f64,
    /// Contact centroid in mm of the image plane scaled by the pitch (`pitch_mm` known), else `None`.
    pub centroid_mm: Option<[f64; 2]>,
    /// Number of markers in the contact region.
    pub contact_markers: usize,
    /// Whether each marker (tracker order) lies in the contact region.
    pub in_contact: Vec<bool>,
    /// Mean displacement of the contact markers, px.
    pub shear_px: [f64; 2],
    /// Share of contact markers on the displacement plateau.
    pub stick_fraction: f64,
    /// Drift of the contact region across the gel since the previous frame, along the shear, px.
    pub drift_px: f64,
    /// Slip state.
    pub state: SlipState,
}

/// Classifies mono frames one after the other.
#[derive(Debug, Clone)]
pub struct PlanarDetector {
    config: PlanarConfig,
    pitch_px: f64,
    previous_material_px: Option<[f64; 2]>,
}

impl PlanarDetector {
    /// A detector for the markers of `tracker` (its median reference pitch sets the scale).
    pub fn new(config: PlanarConfig, tracker: &Tracker) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            config,
            pitch_px: tracker.median_pitch_px(),
            previous_material_px: None,
        })
    }

    /// Forgets the history (after re-zeroing).
    pub fn reset(&mut self) {
        self.previous_material_px = None;
    }

    /// Classifies the frame `track` that `tracker` just produced.
    pub fn update(&mut self, tracker: &Tracker, track: &TrackFrame) -> Result<PlanarFrame> {
        let c = &self.config;
        let previous = self.previous_material_px.take();
        let reference = tracker.reference_px();
        let disp: Vec<Option<[f64; 2]>> = track
            .markers
            .iter()
            .enumerate()
            .map(|(k, m)| match (m.status, m.position_px) {
                (MarkerStatus::Lost, _) | (_, None) => None,
                (_, Some(p)) => Some([p.x - reference[k].x, p.y - reference[k].y]),
            })
            .collect();
        let mut mags: Vec<f64> = disp.iter().flatten().map(|d| d[0].hypot(d[1])).collect();
        mags.sort_by(f64::total_cmp);
        let top = mags
            .get(((mags.len().max(1) - 1) as f64 * 0.98).round() as usize)
            .copied()
            .unwrap_or(0.0);
        let min_disp = c.min_displacement_pitch * self.pitch_px;
        let none = PlanarFrame {
            contact: false,
            contact_area_mm2: 0.0,
            centroid_mm: None,
            contact_markers: 0,
            in_contact: vec![false; disp.len()],
            shear_px: [0.0; 2],
            stick_fraction: 1.0,
            drift_px: 0.0,
            state: SlipState::NoContact,
        };
        if top <= min_disp {
            return Ok(none);
        }
        let threshold = min_disp.max(c.relative * top);
        let (mut sx, mut sy, mut n) = (0.0, 0.0, 0usize);
        let (mut mx, mut my, mut mw) = (0.0, 0.0, 0.0);
        let (mut cx, mut cy) = (0.0, 0.0);
        let mut members = Vec::new();
        let mut in_contact = vec![false; disp.len()];
        for (k, d) in disp.iter().enumerate() {
            let Some(d) = d else { continue };
            let m = d[0].hypot(d[1]);
            if m <= threshold {
                continue;
            }
            in_contact[k] = true;
            members.push(*d);
            sx += d[0];
            sy += d[1];
            n += 1;
            let w = m - threshold;
            mx += w * reference[k].x;
            my += w * reference[k].y;
            mw += w;
            cx += reference[k].x + d[0];
            cy += reference[k].y + d[1];
        }
        if n == 0 {
            return Ok(none);
        }
        let shear = [sx / n as f64, sy / n as f64];
        let material = [mx / mw, my / mw];
        self.previous_material_px = Some(material);
        let scale = c.pitch_mm.map(|p| p / self.pitch_px);
        let mut frame = PlanarFrame {
            contact: true,
            contact_area_mm2: c.pitch_mm.map_or(0.0, |p| n as f64 * p * p),
            centroid_mm: scale.map(|s| [s * cx / n as f64, s * cy / n as f64]),
            contact_markers: n,
            in_contact,
            shear_px: shear,
            stick_fraction: 1.0,
            drift_px: 0.0,
            state: SlipState::Stick,
        };
        let norm = shear[0].hypot(shear[1]);
        if norm < c.min_shear_pitch * self.pitch_px {
            return Ok(frame);
        }
        let dir = [shear[0] / norm, shear[1] / norm];
        let mut along: Vec<f64> = members.iter().map(|d| d[0] * dir[0] + d[1] * dir[1]).collect();
        along.sort_by(f64::total_cmp);
        let p90 = along[((along.len() - 1) as f64 * 0.9).round() as usize];
        let tol = c.plateau_tolerance * p90.abs();
        frame.stick_fraction = along.iter().filter(|&&p| p >= p90 - tol).count() as f64 / along.len() as f64;
        frame.drift_px = previous.map_or(0.0, |p| {
            (material[0] - p[0]) * dir[0] + (material[1] - p[1]) * dir[1]
        });
        frame.state = if frame.drift_px > c.drift_pitch_per_frame * self.pitch_px {
            SlipState::GrossSlip
        } else if frame.stick_fraction < c.stick_fraction {
            SlipState::PartialSlip
        } else {
            SlipState::Stick
        };
        Ok(frame)
    }
}

/// Positions of the tracked and predicted markers of `track`, px (for overlays).
pub fn positions(track: &TrackFrame) -> Vec<Point2> {
    track.markers.iter().filter_map(|m| m.position_px).collect()
}
