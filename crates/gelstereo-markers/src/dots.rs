//! Whether a view's markers look like dots on a gel (`docs/localization.md`, "Dots on a gel"): the
//! last say on a lattice the network found in a regular pattern that has no markers.
//!
//! The lattice check ([`crate::lattice`]) asks only where detections lie. Regular patterns that are
//! no marker gel line up as well as markers do: the squares of a checkerboard, the crests and troughs
//! of an egg-crate or a weave, the holes of a perforated plate. What every marker gel has and such
//! patterns lack are read from the image around the markers:
//! 1. **One polarity.** All markers of a gel differ from the gel between them the same way (darker,
//!    lighter, or in one hue). A checkerboard's or an egg-crate's "markers" are both its dark and its
//!    light cells. Measured as the share of markers whose colour contrast (centre against the ring
//!    half a pitch around it) points the way of the view's median contrast.
//! 2. **Gel between the dots.** A marker is a dot, and its neighbours' dots lie past a band of gel
//!    around it: going out from its centre, the colour comes back halfway to the gel's within less
//!    than half the pitch (a dot 0.75 pitch wide, the widest trained, comes back at 0.375 pitch). The
//!    cells of a checkerboard touch each other: from a cell's centre most directions run into the
//!    next cell of the same colour or along its edge, and do not come back before half a pitch.
//! 3. **Dots that look alike.** A gel's dots look like each other, where a checkerboard's
//!    neighbouring cells are dark and light. Where the cells are wider than half the pitch, the
//!    ring half a pitch out lies inside the cell, so no dot can be read at a marker at all (the first
//!    two rules then have nothing to judge); if at most a quarter of the markers show a dot and most
//!    nearest neighbours' centres differ from each other by more than each differs from its ring,
//!    the "markers" are such cells.
//! 4. **Gel between neighbours.** Halfway between a marker and its nearest neighbour lies the gel,
//!    the colour of the ring around the marker. Between a checkerboard's diagonal squares lies their
//!    shared corner, about halfway between the two colours; between a weave's crossings its dark
//!    gaps, further from the crossings' colour than the ring around them.
//!
//! All are judged over up to [`SAMPLED_MARKERS`] markers of the view and decided by the majority, so
//! markers squeezed into touching pairs at an indenter's rim, or a few glints, do not sway them. A
//! view whose markers fail loses them all (to the second tier): a view has one gel, and the markers
//! of one lattice share its look. A perforated plate whose holes are as wide as markers are (up to
//! 0.75 pitch) passes: its image is a marker lattice's, and nothing in the pixels says otherwise.
//! Weaves whose gaps are as light as the ring around a crossing, and most printed text, pass too.

use gelstereo_core::{Detection, ImageSize, Point2};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual};

use crate::spacing::{median_finite, nearest_neighbour_distances};
use crate::{Result, check_image, cv_err};

/// Markers whose look is judged, at most (spread evenly over the view's list, which is sorted by
/// position): enough for a majority, bounded work on any view.
pub const SAMPLED_MARKERS: usize = 64;

/// Fewest markers sampled (and, for the polarity and the width, read) for a verdict; with fewer the
/// view keeps its markers.
pub const MIN_JUDGED: usize = 16;

/// Smallest pitch the look is measured at, px: markers reported closer together are measured as if
/// this far apart (two pixels and a gap are the least a dot needs).
const MIN_PITCH_PX: f64 = 2.0;

/// Radius of the ring whose median colour is the gel's around a marker, in pitches: between a dot's
/// edge (at most 0.375 pitch) and its neighbour's (at least 0.625).
const RING_PITCH: f64 = 0.5;

/// Half side of the box averaged per sample, in pitches (at least 1 px): irons out pixel noise, scan
/// lines and the gel's grain, keeps a dot 0.25 pitch wide.
const BOX_HALF_PITCH: f64 = 0.05;

/// Directions sampled around a marker (the ring and the rays).
const DIRECTIONS: usize = 16;

/// Step along a ray, in pitches.
const RAY_STEP_PITCH: f64 = 0.025;

/// Smallest colour contrast (Euclidean, grey levels) between a marker's centre and its ring for the
/// marker to be judged: below it neither its polarity nor its edge can be read.
const MIN_CONTRAST: f64 = 6.0;

/// Share of judged markers whose contrast must point the way of the view's (cosine above
/// [`SAME_WAY_COSINE`]): a gel's markers share it (real sensors all of them, the widened simulator's
/// hardest views two in three); a pattern of dark and light cells splits about evenly.
pub const MIN_SAME_POLARITY: f64 = 0.66;

/// Share of the sampled markers whose nearest marker's centre differs from theirs by more than they
/// differ from their own gel, at or above which cells of two colours are taken for markers where
/// fewer than a quarter of the markers show a dot at all (the cell wider than half a pitch: its
/// centre and its ring have one colour). A gel's dots look alike; a checkerboard's neighbouring
/// cells are dark and light.
pub const MAX_UNLIKE_NEIGHBOURS: f64 = 0.75;

/// Cosine between a marker's contrast and the view's above which it points the same way.
const SAME_WAY_COSINE: f64 = 0.5;

/// Largest median dot width, in pitches (twice where the rays come back halfway to the gel): trained
/// markers are up to 0.75 pitch wide, and contact spreads them a little; touching cells reach 1.
pub const MAX_DOT_WIDTH_PITCH: f64 = 0.97;

/// Largest median distance of the colour halfway between neighbouring markers from the gel's around
/// them, as a share of the markers' contrast: between two dots lies the gel; between a checkerboard's
/// diagonal squares lies their shared corner (about half way), between a weave's crossings its dark
/// gaps (beyond the gel, away from the crossings). The limit sits between the two with room on the
/// gel's side (docs/experiments/localization-regular-patterns.md).
pub const MAX_GAP: f64 = 0.4;

/// The image's pixels, read in place.
struct Pixels<'a> {
    bytes: &'a [u8],
    size: ImageSize,
    channels: usize,
    step: usize,
}

impl Pixels<'_> {
    /// Mean colour (up to 3 channels: grey, or blue-green-red) of the box of half side `half` px
    /// around `p`, `None` when it leaves the image.
    fn box_mean(&self, p: Point2, half: i64) -> Option<[f64; 3]> {
        let (cx, cy) = (p.x.round() as i64, p.y.round() as i64);
        let (w, h) = (i64::from(self.size.width), i64::from(self.size.height));
        if cx - half < 0 || cy - half < 0 || cx + half >= w || cy + half >= h {
            return None;
        }
        let used = self.channels.min(3);
        let mut sum = [0.0; 3];
        for y in cy - half..=cy + half {
            let row = y as usize * self.step;
            for x in cx - half..=cx + half {
                let px = row + x as usize * self.channels;
                for (c, s) in sum.iter_mut().enumerate().take(used) {
                    *s += f64::from(self.bytes[px + c]);
                }
            }
        }
        let n = ((2 * half + 1) * (2 * half + 1)) as f64;
        Some(sum.map(|s| s / n))
    }
}

/// What one marker's surroundings say.
struct MarkerLook {
    /// Centre colour minus the ring's median, per channel; `None` when fainter than
    /// [`MIN_CONTRAST`].
    contrast: Option<[f64; 3]>,
    /// Median over the rays of where they come back halfway to the ring's colour, in pitches (the
    /// ring's radius where they do not come back before it); 0 for a faint marker.
    edge_pitch: f64,
    /// Where the colour halfway to the nearest marker lies between the gel's (0) and this marker's
    /// centre's (1); 0 for a faint marker.
    gap: f64,
    /// Whether the nearest marker's centre differs from this one's by more than this one differs
    /// from its gel.
    unlike_neighbour: bool,
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn median_of(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// The look of the marker at `p` whose nearest marker lies at `neighbour` (`None` where its ring
/// leaves the image).
fn look_at(pixels: &Pixels, p: Point2, neighbour: Point2, pitch: f64) -> Option<MarkerLook> {
    let half = (BOX_HALF_PITCH * pitch).round().max(1.0) as i64;
    let ray = |k: usize| {
        let a = std::f64::consts::TAU * k as f64 / DIRECTIONS as f64;
        (a.cos(), a.sin())
    };
    let at = |(dx, dy): (f64, f64), r: f64| Point2 {
        x: p.x + dx * r,
        y: p.y + dy * r,
    };
    let centre = pixels.box_mean(p, half)?;
    let mut ring = Vec::with_capacity(DIRECTIONS);
    for k in 0..DIRECTIONS {
        ring.push(pixels.box_mean(at(ray(k), RING_PITCH * pitch), half)?);
    }
    let gel: [f64; 3] =
        std::array::from_fn(|c| median_of(&mut ring.iter().map(|v| v[c]).collect::<Vec<_>>()));
    let contrast: [f64; 3] = std::array::from_fn(|c| centre[c] - gel[c]);
    let strength = norm(contrast);
    let unlike_neighbour = pixels
        .box_mean(neighbour, half)
        .is_some_and(|n| norm(std::array::from_fn(|c| centre[c] - n[c])) > strength.max(MIN_CONTRAST));
    if strength < MIN_CONTRAST {
        return Some(MarkerLook {
            contrast: None,
            edge_pitch: 0.0,
            gap: 0.0,
            unlike_neighbour,
        });
    }
    let steps = (RING_PITCH / RAY_STEP_PITCH).round() as usize;
    let mut edges: Vec<f64> = (0..DIRECTIONS)
        .map(|k| {
            (1..=steps)
                .map(|s| s as f64 * RAY_STEP_PITCH)
                .find(|&r| {
                    pixels.box_mean(at(ray(k), r * pitch), half).is_some_and(|v| {
                        let d: [f64; 3] = std::array::from_fn(|c| v[c] - gel[c]);
                        dot(d, contrast) < 0.5 * strength * strength
                    })
                })
                .unwrap_or(RING_PITCH)
        })
        .collect();
    let halfway = Point2 {
        x: 0.5 * (p.x + neighbour.x),
        y: 0.5 * (p.y + neighbour.y),
    };
    let gap = pixels.box_mean(halfway, half).map_or(0.0, |v| {
        let d: [f64; 3] = std::array::from_fn(|c| v[c] - gel[c]);
        dot(d, contrast) / (strength * strength)
    });
    Some(MarkerLook {
        contrast: Some(contrast),
        edge_pitch: median_of(&mut edges),
        gap,
        unlike_neighbour,
    })
}

/// The verdict on a view's markers, with the measures it rests on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DotsVerdict {
    /// Markers sampled whose ring lies inside the image.
    pub sampled: usize,
    /// Share of the sampled markers whose nearest marker's centre differs from theirs by more than
    /// they differ from their gel.
    pub unlike_neighbours: f64,
    /// Markers judged (whole rings inside the image, contrast readable).
    pub judged: usize,
    /// Share of them whose contrast points the view's way.
    pub same_polarity: f64,
    /// Their median dot width, in pitches.
    pub dot_width_pitch: f64,
    /// Median of where the colour halfway to the nearest marker lies between the gel's (0) and the
    /// marker's (1).
    pub gap: f64,
}

impl DotsVerdict {
    /// Whether the markers look like dots on a gel (module documentation; too few sampled: yes).
    pub fn dots(&self) -> bool {
        if self.sampled < MIN_JUDGED {
            return true;
        }
        let no_dot_at_the_centres = 4 * self.judged < self.sampled;
        if no_dot_at_the_centres && self.unlike_neighbours >= MAX_UNLIKE_NEIGHBOURS {
            return false;
        }
        self.judged < MIN_JUDGED
            || (self.same_polarity >= MIN_SAME_POLARITY
                && self.dot_width_pitch <= MAX_DOT_WIDTH_PITCH
                && self.gap.abs() <= MAX_GAP)
    }
}

/// Judges the `markers` of `image` (module documentation). `None` with fewer than [`MIN_JUDGED`]
/// markers or no pitch.
pub fn judge_the_dots(image: &Mat, markers: &[Detection]) -> Result<Option<DotsVerdict>> {
    if markers.len() < MIN_JUDGED {
        return Ok(None);
    }
    let points: Vec<Point2> = markers.iter().map(|d| d.position).collect();
    let Some(pitch) = median_finite(&nearest_neighbour_distances(&points)) else {
        return Ok(None);
    };
    let pitch = pitch.max(MIN_PITCH_PX);
    let size = check_image(image)?;
    let continuous;
    let image = if image.is_continuous() {
        image
    } else {
        continuous = image.try_clone().map_err(cv_err("copy of the image"))?;
        &continuous
    };
    let channels = image.channels().max(1) as usize;
    let pixels = Pixels {
        bytes: image.data_bytes().map_err(cv_err("reading the image"))?,
        size,
        channels,
        step: size.width as usize * channels,
    };
    let stride = points.len().div_ceil(SAMPLED_MARKERS);
    let nearest = |i: usize| {
        let p = points[i];
        points
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .min_by(|a, b| {
                let da = (a.1.x - p.x).hypot(a.1.y - p.y);
                let db = (b.1.x - p.x).hypot(b.1.y - p.y);
                da.total_cmp(&db)
            })
            .map_or(p, |(_, q)| *q)
    };
    let seen: Vec<MarkerLook> = (0..points.len())
        .step_by(stride)
        .filter_map(|i| look_at(&pixels, points[i], nearest(i), pitch))
        .collect();
    let sampled = seen.len();
    let unlike = seen.iter().filter(|l| l.unlike_neighbour).count();
    let looks: Vec<(&MarkerLook, [f64; 3])> =
        seen.iter().filter_map(|l| l.contrast.map(|c| (l, c))).collect();
    let unlike_neighbours = if sampled == 0 {
        0.0
    } else {
        unlike as f64 / sampled as f64
    };
    if looks.len() < MIN_JUDGED {
        return Ok(Some(DotsVerdict {
            sampled,
            judged: looks.len(),
            unlike_neighbours,
            same_polarity: 1.0,
            dot_width_pitch: 0.0,
            gap: 0.0,
        }));
    }
    let unit: Vec<[f64; 3]> = looks.iter().map(|(_, c)| c.map(|v| v / norm(*c))).collect();
    let way: [f64; 3] =
        std::array::from_fn(|c| median_of(&mut unit.iter().map(|u| u[c]).collect::<Vec<_>>()));
    let way_norm = norm(way).max(f64::MIN_POSITIVE);
    let same = unit
        .iter()
        .filter(|u| dot(**u, way) / way_norm > SAME_WAY_COSINE)
        .count();
    let mut widths: Vec<f64> = looks.iter().map(|(l, _)| 2.0 * l.edge_pitch).collect();
    let mut gaps: Vec<f64> = looks.iter().map(|(l, _)| l.gap).collect();
    Ok(Some(DotsVerdict {
        gap: median_of(&mut gaps),
        sampled,
        judged: looks.len(),
        unlike_neighbours,
        same_polarity: same as f64 / looks.len() as f64,
        dot_width_pitch: median_of(&mut widths),
    }))
}
