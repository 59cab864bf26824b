//! Contact and slip of mono sensors (one camera, e.g. a GelSight Mini) from the in-plane marker
//! displacement field, px:
//!
//! - the **contact region** is where the displacement magnitude exceeds
//!   `max(min_displacement_pitch x pitch, relative x the frame's largest displacement)`;
//! - **slip** shows as a strain concentration: while the contact sticks, the gel surface follows
//!   the object and the displacement field stays smooth (neighbouring markers move alike, the
//!   surface strain is that of the elastic layer); at a slip front the surface is torn along by
//!   the object on one side and left behind on the other, and neighbouring markers' displacements
//!   differ by a sizeable part of the pitch (the displacement discontinuity at the stick/slip
//!   boundary that Yuan et al., ICRA 2015, use to detect slip with a GelSight). The slip measure is
//!   the largest displacement difference between tracked 4-neighbours, in pitches (a surface
//!   strain); above `slip_strain` the frame is `partial_slip`. Without depth the contact cannot be
//!   told to slide as a whole, so mono sensors report `stick` or `partial_slip`, never
//!   `gross_slip`.
//!
//! Without depth, the area is counted in lattice cells (one per contact marker) and converted with
//! the marker pitch in mm when the sensor's pitch is known (`pitch_mm`); otherwise it is reported as
//! 0 and the centroid is left empty.

use gelstereo_core::{GridIndex, MarkerStatus, Point2, SlipState};

use crate::error::{Result, config_err};
use crate::tracker::{TrackFrame, Tracker};

/// Settings of the [`PlanarDetector`] (defaults chosen on the GelSight Mini video and the simulated
/// training split seen through the left camera only; `docs/tracking.md`).
#[derive(Debug, Clone, PartialEq)]
pub struct PlanarConfig {
    /// Smallest displacement that counts as contact, in marker pitches (0.08: ten times the
    /// frame-to-frame jitter of blob centres on the GelSight Mini video).
    pub min_displacement_pitch: f64,
    /// Contact threshold relative to the frame's largest displacement.
    pub relative: f64,
    /// Largest displacement difference between tracked neighbours, in pitches, above which the
    /// contact slips (0.2: the press of the GelSight Mini video stays below 0.17, its hard slide
    /// reaches 0.24-0.5).
    pub slip_strain: f64,
    /// Marker pitch of the sensor, mm, to convert areas and centroids; `None` when unknown.
    pub pitch_mm: Option<f64>,
}

impl Default for PlanarConfig {
    fn default() -> Self {
        Self {
            min_displacement_pitch: 0.08,
            relative: 0.5,
            slip_strain: 0.2,
            pitch_mm: None,
        }
    }
}

impl PlanarConfig {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        for (field, v) in [
            ("min_displacement_pitch", self.min_displacement_pitch),
            ("slip_strain", self.slip_strain),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 5.0) {
                return Err(config_err(field, "a number of pitches in (0, 5)", v));
            }
        }
        if !(self.relative.is_finite() && self.relative > 0.0 && self.relative < 1.0) {
            return Err(config_err("relative", "a fraction in (0, 1)", self.relative));
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
    /// Contact markers x pitch^2, mm^2 (0 without contact); `None` when `pitch_mm` is not known
    /// (the image gives no scale).
    pub contact_area_mm2: Option<f64>,
    /// Contact centroid in mm of the image plane scaled by the pitch (`pitch_mm` known), else `None`.
    pub centroid_mm: Option<[f64; 2]>,
    /// Number of markers in the contact region.
    pub contact_markers: usize,
    /// Whether each marker (tracker order) lies in the contact region.
    pub in_contact: Vec<bool>,
    /// Mean displacement of the contact markers, px.
    pub shear_px: [f64; 2],
    /// Largest displacement difference between tracked 4-neighbours, in pitches.
    pub strain: f64,
    /// Slip state (`no_contact`, `stick` or `partial_slip`).
    pub state: SlipState,
}

/// Classifies mono frames.
#[derive(Debug, Clone)]
pub struct PlanarDetector {
    config: PlanarConfig,
    pitch_px: f64,
    /// Per tracker slot, the slots of its right and lower lattice neighbours.
    edges: Vec<(usize, usize)>,
}

impl PlanarDetector {
    /// A detector for the markers of `tracker` (its median reference pitch sets the scale).
    pub fn new(config: PlanarConfig, tracker: &Tracker) -> Result<Self> {
        config.validate()?;
        let shape = tracker.shape();
        let mut slot = vec![usize::MAX; shape.count()];
        for (k, id) in tracker.ids().iter().enumerate() {
            if let Some(l) = shape.linear(*id) {
                slot[l] = k;
            }
        }
        let mut edges = Vec::new();
        for (k, id) in tracker.ids().iter().enumerate() {
            for n in [
                GridIndex::new(id.row, id.col + 1),
                GridIndex::new(id.row + 1, id.col),
            ] {
                if let Some(l) = shape.linear(n)
                    && slot[l] != usize::MAX
                {
                    edges.push((k, slot[l]));
                }
            }
        }
        Ok(Self {
            config,
            pitch_px: tracker.median_pitch_px(),
            edges,
        })
    }

    /// Kept for symmetry with the stereo detector: the mono detector has no history.
    pub fn reset(&mut self) {}

    /// Classifies the frame `track` that `tracker` just produced.
    pub fn update(&mut self, tracker: &Tracker, track: &TrackFrame) -> Result<PlanarFrame> {
        let c = &self.config;
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
        let mut frame = PlanarFrame {
            contact: false,
            // Without the pitch no area is measurable, not even a zero one.
            contact_area_mm2: c.pitch_mm.map(|_| 0.0),
            centroid_mm: None,
            contact_markers: 0,
            in_contact: vec![false; disp.len()],
            shear_px: [0.0; 2],
            strain: 0.0,
            state: SlipState::NoContact,
        };
        if top <= min_disp {
            return Ok(frame);
        }
        let threshold = min_disp.max(c.relative * top);
        let (mut sx, mut sy, mut cx, mut cy, mut n) = (0.0, 0.0, 0.0, 0.0, 0usize);
        for (k, d) in disp.iter().enumerate() {
            let Some(d) = d else { continue };
            if d[0].hypot(d[1]) <= threshold {
                continue;
            }
            frame.in_contact[k] = true;
            sx += d[0];
            sy += d[1];
            cx += reference[k].x + d[0];
            cy += reference[k].y + d[1];
            n += 1;
        }
        if n == 0 {
            return Ok(frame);
        }
        let tracked = |k: usize| track.markers[k].status == MarkerStatus::Tracked;
        frame.strain = self
            .edges
            .iter()
            .filter(|(a, b)| tracked(*a) && tracked(*b))
            .filter_map(|(a, b)| match (disp[*a], disp[*b]) {
                (Some(u), Some(v)) => Some((u[0] - v[0]).hypot(u[1] - v[1]) / self.pitch_px),
                _ => None,
            })
            .fold(0.0, f64::max);
        let scale = c.pitch_mm.map(|p| p / self.pitch_px);
        frame.contact = true;
        frame.contact_markers = n;
        frame.contact_area_mm2 = c.pitch_mm.map(|p| n as f64 * p * p);
        frame.centroid_mm = scale.map(|s| [s * cx / n as f64, s * cy / n as f64]);
        frame.shear_px = [sx / n as f64, sy / n as f64];
        frame.state = if frame.strain > c.slip_strain {
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

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_core::GridShape;

    #[test]
    fn smooth_shear_sticks_and_a_torn_field_slips() {
        // An 8 x 10 lattice, pitch 30 px.
        let shape = GridShape { rows: 8, cols: 10 };
        let rest: Vec<(GridIndex, Point2)> = shape
            .indices()
            .map(|i| {
                (
                    i,
                    Point2::new(20.0 + 30.0 * f64::from(i.col), 15.0 + 30.0 * f64::from(i.row)),
                )
            })
            .collect();
        let mut tracker = Tracker::new(shape, &rest, crate::TrackerConfig::default()).unwrap();
        let mut det = PlanarDetector::new(PlanarConfig::default(), &tracker).unwrap();
        let mut run = |f: &dyn Fn(GridIndex) -> [f64; 2]| {
            let pts: Vec<Point2> = rest
                .iter()
                .map(|(i, p)| Point2::new(p.x + f(*i)[0], p.y + f(*i)[1]))
                .collect();
            let t = tracker.update(&pts);
            det.update(&tracker, &t).unwrap()
        };
        let still = run(&|_| [0.1, -0.1]);
        assert_eq!(still.state, SlipState::NoContact);
        // A smooth bump of shear, up to 6 px: neighbours differ by at most ~2 px (0.07 pitch).
        let bump = |i: GridIndex| {
            let (dx, dy) = (f64::from(i.col) - 4.5, f64::from(i.row) - 3.5);
            let w = (-(dx * dx + dy * dy) / 8.0).exp();
            [6.0 * w, 2.0 * w]
        };
        let stick = run(&bump);
        assert_eq!(stick.state, SlipState::Stick, "strain {}", stick.strain);
        assert!(stick.contact_markers > 4 && stick.contact_area_mm2.is_none() && stick.centroid_mm.is_none());
        // Columns 5.. carried 9 px further than the rest: a slip front between columns 4 and 5.
        let torn = run(&|i| {
            let b = bump(i);
            [b[0] + if i.col >= 5 { 9.0 } else { 0.0 }, b[1]]
        });
        assert_eq!(torn.state, SlipState::PartialSlip, "strain {}", torn.strain);
        assert!(torn.strain > 0.25);
        let bad = PlanarConfig {
            slip_strain: -1.0,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("slip_strain"));
    }
}
