//! Which detections sit on a marker lattice: the check that keeps a network pass from reporting
//! texture, noise, housing or glints as markers (`docs/localization.md`, "Lattice check"; the Python
//! twin is `lattice_members` in `train/gelstereo_train/postprocess.py`).
//!
//! A marker of a tactile sensor has neighbours at about the pitch on both sides along at least two
//! lattice directions (square, hexagonal, sheared or compressed in contact alike). So a point is a
//! *member* when
//! 1. it is on an equally spaced line of three points (it and two neighbours: `q - p` and `p - r`
//!    within [`LatticeCheck::tolerance_frac`] of their length, as the middle or at either end) in at
//!    least two directions [`LatticeCheck::min_angle_deg`] apart, and
//! 2. such points, joined by those lines, form a patch of at least [`LatticeCheck::min_patch`],
//! 3. whose spacing (median nearest-neighbour distance) is within [`LatticeCheck::patch_pitch_ratio`]
//!    of the largest patch's: dense texture (speckle on a housing, a membrane's grain) lines up by
//!    chance at its own, finer spacing, while the patches of one marker lattice (split by a contact
//!    or an occluder) share the lattice's pitch up to perspective and strain.
//!
//! A point that is no member but has at least [`LatticeCheck::adjacent_members`] members within
//! `reach_frac` x the lattice's pitch is *on the lattice* too: a marker pushed off its lines in a
//! pile-up (two dots squeezed until they touch), or next to one, breaks the lines through it and its
//! neighbours but is still surrounded by the lattice. [`keep_the_lattice`] keeps such a detection
//! only when the network is sure of it ([`LatticeCheck::adjacent_min_confidence`]): a doubtful find
//! beside the lattice is as often a membrane's rim as a marker.
//!
//! An uncertain candidate (the second tier: below the confidence the output needs, or refused by the
//! MRE) that sits at an *empty lattice site* joins the markers ([`keep_the_lattice`]): no marker within
//! half a pitch, and it lies on equally spaced lines of three with members in two directions at least
//! [`LatticeCheck::min_angle_deg`] apart, as the middle point of at least one of them. The lattice
//! itself says a marker belongs there; the network was merely unsure of it (a look it has seen
//! little of, a dot in a pile-up). Being the middle of a line keeps a rim or housing find just past
//! the lattice's edge out (it could only be the end of lines); the lines must have the lattice's own
//! spacing (0.75-1.33 pitch), or the centre of a square cell would be the middle of its diagonals.
//! Where the image's border cuts the lattice, the end of a line whose next site beyond the candidate
//! lies outside the image counts as the middle does: the lattice goes on past the border, it does not
//! end there (a faint dot of the top row, next to another the network was unsure of, on the GelSlim
//! frames). A second-tier candidate the network is sure of
//! ([`LatticeCheck::line_end_min_confidence`]) and at least [`LINE_END_INSIDE_PITCH`] inside the image
//! needs only to lie on one such line, at its end or in its middle: a marker past a part of the
//! lattice whose neighbours the network missed has lines on one side only.
//!
//! A view's detections form a *lattice* when at least [`LatticeCheck::min_support`] are members and
//! their spacing (median nearest-neighbour distance) is at least [`LatticeCheck::min_input_pitch_px`]
//! at the network input: below it the network cannot resolve markers, and what lines up there is its
//! own output grid (stride 8) on noise or banding. Without a lattice a view reports no markers.
//!
//! An *irregular* lattice (hand-placed or irregularly printed dots, each up to a quarter pitch off its
//! site) lines up too loosely for rule 1 to hold all of it. Where the lines leave more than one in 5
//! of the detections the network is sure of out, the detections are also checked by their spacing
//! ([`spaced_members`]): printed dots keep their distance from each other, and the neighbours of an
//! inner dot surround it. Patches by spacing must be mostly sure detections (the extrema of a blurred
//! texture keep a spacing too, but the network is rarely sure of them).
//!
//! Uniform random points almost never pass (rule 1 needs two lucky coincidences per point, rule 2 six
//! of those in a row); a marker lattice passes up to its corners (each the end of two lines), its
//! markers cut by the image border and its pile-ups (a marker squeezed against its neighbour still
//! lines up across the other direction).

use gelstereo_core::spatial::Buckets;
use gelstereo_core::stats::median;
use gelstereo_core::{Detection, ImageSize, Point2, TieredDetections};

use crate::edge::{inside_the_image_px, outside_the_image};
use crate::region::Region;
use crate::spacing::{median_finite, nearest_neighbour_distances};

/// Parameters of the lattice check. The defaults are what `marknet-mre` uses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LatticeCheck {
    /// Largest distance of the third point of a line from where equal spacing puts it, as a fraction
    /// of the spacing (0.2: contact strain changes the spacing by far less from one marker to the next).
    pub tolerance_frac: f64,
    /// Neighbours are searched within this many times the larger of the point's own nearest-neighbour
    /// distance and the median of them (1.6: the diagonal of a square lattice, 1.41, is inside).
    pub reach_frac: f64,
    /// Smallest angle between two lines through a member, degrees.
    pub min_angle_deg: f64,
    /// Smallest patch of members joined by lines.
    pub min_patch: usize,
    /// Largest ratio between a patch's spacing and the largest patch's (1.3: the patches of one
    /// lattice share its pitch up to perspective and strain; the speckle of a housing next to a
    /// reference-sensor lattice of pitch 16 px lined up at 7-9 px and, once those patches were
    /// gone, at 11.5 px).
    pub patch_pitch_ratio: f64,
    /// Nearest neighbours paired per point, at most (bounds the work on dense clutter).
    pub max_neighbours: usize,
    /// Members needed for a lattice (and for its pitch to steer the input layout).
    pub min_support: usize,
    /// Smallest spacing of a lattice at the network input, px.
    pub min_input_pitch_px: f64,
    /// Members within reach that put a non-member on the lattice.
    pub adjacent_members: usize,
    /// Confidence a detection on the lattice but no member needs to be kept.
    pub adjacent_min_confidence: f32,
    /// The same inside a region the closer look re-examined ([`crate::close_look`]): there the
    /// network saw the squeezed dots at a larger scale, and such a region lies inside the lattice,
    /// away from any membrane rim.
    pub looked_min_confidence: f32,
    /// Confidence a second-tier candidate needs to join at an empty site on a single line of members
    /// (its end or its middle) ([`keep_the_lattice`]; with the image's size only, and at least
    /// [`LINE_END_INSIDE_PITCH`] inside it): a marker whose neighbours on one side the network
    /// missed has lines on one side only, where a doubtful find there is as often a rim.
    pub line_end_min_confidence: f32,
}

impl Default for LatticeCheck {
    fn default() -> Self {
        Self {
            tolerance_frac: 0.2,
            reach_frac: 1.6,
            min_angle_deg: 30.0,
            min_patch: 6,
            patch_pitch_ratio: 1.3,
            max_neighbours: 12,
            min_support: 8,
            min_input_pitch_px: 8.0,
            adjacent_members: 3,
            adjacent_min_confidence: 0.9,
            looked_min_confidence: 0.4,
            line_end_min_confidence: 0.7,
        }
    }
}

/// The members of a point set and what they imply.
#[derive(Debug, Clone, PartialEq)]
pub struct LatticeFit {
    /// Per point: a member.
    pub member: Vec<bool>,
    /// Per point: a member or adjacent to [`LatticeCheck::adjacent_members`] of them.
    pub on_lattice: Vec<bool>,
    /// Number of members.
    pub members: usize,
    /// Median nearest-neighbour distance of the members, original px (`None` with fewer than two).
    pub pitch_px: Option<f64>,
    /// Whether the members form a lattice (enough of them, spacing at the input large enough).
    pub is_lattice: bool,
}

/// A union-find forest whose roots are the smallest index of their set.
struct Patches(Vec<usize>);

impl Patches {
    fn root(&mut self, mut x: usize) -> usize {
        while self.0[x] != x {
            self.0[x] = self.0[self.0[x]];
            x = self.0[x];
        }
        x
    }

    fn join(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.root(a), self.root(b));
        if ra != rb {
            self.0[ra.max(rb)] = ra.min(rb);
        }
    }
}

/// Directions stored per point before it is known to lie on two lines (more, all within
/// `min_angle_deg` of each other, do not occur on a lattice; past it new ones are still compared).
const MAX_DIRECTIONS: usize = 16;

/// Whether two lines are at least an angle apart (modulo pi), from their direction vectors alone:
/// the acute angle t between lines along u and v has cos t = |u.v| / (|u| |v|), so t >= min_angle
/// exactly where (u.v)^2 <= cos^2(min_angle) |u|^2 |v|^2. Why: an arctangent per line was the
/// dearest step of the lattice check; the Python twin compares the angles themselves, which decides
/// alike up to rounding.
#[derive(Clone, Copy)]
struct MinAngle {
    cos2: f64,
    /// `min_angle_deg` <= 0: any two lines are apart; above 90: none are.
    always: Option<bool>,
}

impl MinAngle {
    fn new(min_angle_deg: f64) -> Self {
        let always = if min_angle_deg <= 0.0 {
            Some(true)
        } else if min_angle_deg > 90.0 || min_angle_deg.is_nan() {
            Some(false)
        } else {
            None
        };
        Self {
            cos2: min_angle_deg.to_radians().cos().powi(2),
            always,
        }
    }

    fn apart(&self, u: [f64; 2], v: [f64; 2]) -> bool {
        if let Some(a) = self.always {
            return a;
        }
        let dot = u[0] * v[0] + u[1] * v[1];
        dot * dot <= self.cos2 * (u[0] * u[0] + u[1] * u[1]) * (v[0] * v[0] + v[1] * v[1])
    }
}

/// The directions of the lines through one point, until two of them are far enough apart.
#[derive(Clone, Copy)]
struct Lines {
    directions: [[f64; 2]; MAX_DIRECTIONS],
    count: usize,
    two: bool,
}

impl Lines {
    const NONE: Self = Self {
        directions: [[0.0; 2]; MAX_DIRECTIONS],
        count: 0,
        two: false,
    };

    /// Adds a line along `direction` (either sense): two lines once any pair of directions is
    /// `min_angle` apart.
    fn add(&mut self, direction: [f64; 2], min_angle: &MinAngle) {
        if self.two {
            return;
        }
        self.two = self.directions[..self.count]
            .iter()
            .any(|d| min_angle.apart(*d, direction));
        if self.count < MAX_DIRECTIONS {
            self.directions[self.count] = direction;
            self.count += 1;
        }
    }
}

/// The lattice members among the `found` detections (see the module documentation); `input_per_px`
/// is the network input's scale (input px per original px) for the spacing rule. The members are
/// those of the lines (equally spaced lines in two directions) and, where those leave more than one
/// in 5 of the sure detections (confidence at least [`LatticeCheck::adjacent_min_confidence`]) out,
/// those of the spacing rule ([`spaced_members`]: an irregular lattice, hand-placed or irregularly
/// printed dots, lines up too loosely for the lines alone). Both fits at one pitch are one lattice
/// (their union); otherwise the one with the most members is.
pub fn fit_lattice(found: &[Detection], check: &LatticeCheck, input_per_px: f64) -> LatticeFit {
    let points: Vec<Point2> = found.iter().map(|d| d.position).collect();
    let nn = nearest_neighbour_distances(&points);
    fit_lattice_with_distances(found, nn, check, input_per_px)
}

/// [`fit_lattice`] given each detection's nearest-neighbour distance among `found`
/// ([`nearest_neighbour_distances`] of their positions), which the pitch estimate has already
/// measured on most frames.
pub(crate) fn fit_lattice_with_distances(
    found: &[Detection],
    nn: Vec<f64>,
    check: &LatticeCheck,
    input_per_px: f64,
) -> LatticeFit {
    let points: Vec<Point2> = found.iter().map(|d| d.position).collect();
    let n = points.len();
    let Some(hood) = Neighbourhood::of(&points, nn) else {
        return LatticeFit {
            member: vec![false; n],
            on_lattice: vec![false; n],
            members: 0,
            pitch_px: None,
            is_lattice: false,
        };
    };
    let finish = |member: Vec<bool>| finish_fit(member, &hood, check, input_per_px);
    let lined = lined_members(&points, &hood, check);
    // Spacing is weaker evidence than lines (the extrema of a blurred texture keep a spacing of
    // their own), so it is asked only where the lines leave more than one in 5 of the detections
    // the network is sure of out, and its patches must be mostly sure ones.
    let sure: Vec<bool> = found
        .iter()
        .map(|d| d.confidence >= check.adjacent_min_confidence)
        .collect();
    let sure_count = sure.iter().filter(|&&s| s).count();
    let left_out = (0..n).filter(|&i| sure[i] && !lined[i]).count();
    if left_out < 3 || (left_out as f64) <= SPACING_LEFT_OUT * sure_count as f64 {
        return finish(lined);
    }
    let spaced = spaced_members(&points, &sure, &hood, check);
    let union: Vec<bool> = lined.iter().zip(&spaced).map(|(a, b)| *a || *b).collect();
    let (lined, spaced) = (finish(lined), finish(spaced));
    let one_pitch = |a: f64, b: f64| a <= b * check.patch_pitch_ratio && b <= a * check.patch_pitch_ratio;
    match (
        lined.is_lattice,
        spaced.is_lattice,
        lined.pitch_px,
        spaced.pitch_px,
    ) {
        (_, false, ..) => lined,
        (false, true, ..) => spaced,
        // One lattice seen both ways: its regular part by the lines, the rest by spacing.
        (true, true, Some(a), Some(b)) if one_pitch(a, b) => finish(union),
        _ if spaced.members > lined.members => spaced,
        _ => lined,
    }
}

/// Cell side of the neighbourhood's grid, in median nearest-neighbour distances. The searches reach
/// `reach_frac` (1.6) x that median; cells of one median (about a point each on a lattice) let a
/// search look at fewer points than cells of the reach would, for a row of cells more (the same
/// members: every search's finds are sorted, counted or joined in a way that does not depend on the
/// order the cells give them).
const CELL_MEDIANS: f64 = 1.0;

/// Each point's nearest-neighbour distance, their median, and the points bucketed (cells of
/// [`CELL_MEDIANS`] x that median) for searches within `reach_frac` x it.
struct Neighbourhood {
    nn: Vec<f64>,
    median_nn: f64,
    grid: Buckets,
}

impl Neighbourhood {
    /// `nn`: each point's nearest-neighbour distance. `None` with fewer than three points or no
    /// finite distance.
    fn of(points: &[Point2], nn: Vec<f64>) -> Option<Self> {
        if points.len() < 3 {
            return None;
        }
        let median_nn = median_finite(&nn)?;
        let grid = Buckets::new(points, CELL_MEDIANS * median_nn);
        Some(Self { nn, median_nn, grid })
    }
}

/// The fit of the `member`s: their pitch, the points on the lattice beside them, whether they form one.
fn finish_fit(
    member: Vec<bool>,
    hood: &Neighbourhood,
    check: &LatticeCheck,
    input_per_px: f64,
) -> LatticeFit {
    let mut member_nn: Vec<f64> = (0..member.len())
        .filter(|&i| member[i])
        .map(|i| hood.nn[i])
        .collect();
    let members = member_nn.len();
    let pitch_px = if members >= 2 {
        median(&mut member_nn)
    } else {
        None
    };
    let mut on_lattice = member.clone();
    if let Some(pitch) = pitch_px {
        for (i, &p) in hood.grid.points().iter().enumerate().filter(|&(i, _)| !member[i]) {
            let mut adjacent = 0;
            hood.grid.for_each_within(p, check.reach_frac * pitch, |j, _| {
                adjacent += usize::from(member[j])
            });
            on_lattice[i] = adjacent >= check.adjacent_members;
        }
    }
    let is_lattice = members >= check.min_support
        && pitch_px.is_some_and(|p| p * input_per_px >= check.min_input_pitch_px);
    LatticeFit {
        member,
        on_lattice,
        members,
        pitch_px,
        is_lattice,
    }
}

/// Members by the lines: points on equally spaced lines of three in two directions, in patches of
/// at least [`LatticeCheck::min_patch`] at the lattice's pitch (module documentation, rules 1-3).
fn lined_members(points: &[Point2], hood: &Neighbourhood, check: &LatticeCheck) -> Vec<bool> {
    let Neighbourhood { nn, median_nn, grid } = hood;
    let (n, median_nn) = (points.len(), *median_nn);
    let min_angle = MinAngle::new(check.min_angle_deg);
    // The lines through each point, and the pairs each line joins.
    let mut lines = vec![Lines::NONE; n];
    let mut bonds: Vec<(usize, usize)> = Vec::new();
    let mut near: Vec<(f64, usize)> = Vec::new();
    for (i, &p) in points.iter().enumerate() {
        let reach = check.reach_frac * nn[i].max(median_nn);
        near.clear();
        grid.for_each_within(p, reach, |j, d2| {
            if j != i {
                near.push((d2, j));
            }
        });
        // By distance, then index: a total order, so an unstable sort gives the one result; squared
        // distances are never negative, so their bits order as the values do.
        near.sort_unstable_by_key(|&(d2, j)| (d2.to_bits(), j));
        near.truncate(check.max_neighbours);
        for (a, &(d2_ij, j)) in near.iter().enumerate() {
            let (vx, vy) = (points[j].x - p.x, points[j].y - p.y);
            // Where the third point of an equally spaced line with i in the middle lies.
            let (ox, oy) = (p.x - vx, p.y - vy);
            // Squared distances against the squared limit: this pair loop is the hot spot of the
            // post-processing (tens of thousands of pairs per stereo frame), and a `hypot` per pair
            // cost more than the rest of the check.
            let limit2 = check.tolerance_frac * check.tolerance_frac * d2_ij;
            // A third point within the limit of where equal spacing puts it is at most (1 + tol) x
            // the spacing from i, and `near` is sorted by distance: past that (with a margin far
            // above rounding) no later one can be.
            let beyond2 = (1.0 + check.tolerance_frac.abs()).powi(2) * d2_ij * (1.0 + 1e-6);
            for &(d2_ik, k) in &near[a + 1..] {
                if d2_ik > beyond2 {
                    break;
                }
                let (dx, dy) = (points[k].x - ox, points[k].y - oy);
                if dx * dx + dy * dy <= limit2 {
                    for q in [i, j, k] {
                        lines[q].add([vx, vy], &min_angle);
                    }
                    bonds.extend([(i, j), (i, k)]);
                }
            }
        }
    }
    let two_lines: Vec<bool> = lines.iter().map(|l| l.two).collect();
    let mut patches = Patches((0..n).collect());
    for &(i, j) in &bonds {
        if two_lines[i] && two_lines[j] {
            patches.join(i, j);
        }
    }
    let mut size = vec![0usize; n];
    for i in (0..n).filter(|&i| two_lines[i]) {
        let r = patches.root(i);
        size[r] += 1;
    }
    let patch_of: Vec<Option<usize>> = (0..n)
        .map(|i| {
            let r = patches.root(i);
            (two_lines[i] && size[r] >= check.min_patch).then_some(r)
        })
        .collect();
    let pitch_ok = patches_at_the_lattice_pitch(&patch_of, nn, check.patch_pitch_ratio);
    patch_of
        .iter()
        .map(|patch| patch.is_some_and(|r| pitch_ok[r]))
        .collect()
}

/// Share of the sure detections the lines must leave out before the spacing rule is asked: on a
/// regular lattice the lines hold nearly all (pile-ups at an indenter's rim leave some out, and
/// asking the spacing rule there changes which of them are kept, which the tracker feels); on an
/// irregular one they leave most out.
const SPACING_LEFT_OUT: f64 = 0.2;

/// Nearest-neighbour distance of a member by the spacing rule, in medians of them: printed dots keep
/// their distance (an irregular lattice's dots, moved up to 0.25 pitch per axis, stay 0.5 pitch apart),
/// where points strewn at random are often closer than 0.6 median to their nearest.
const SPACED_NN: (f64, f64) = (0.6, 1.6);

/// Neighbours of a point by spacing are searched within this many medians of the nearest-neighbour
/// distance: the median is about 0.8 pitch on an irregular lattice, so its diagonal neighbours
/// (1.41 pitch) are mostly inside.
const SPACED_REACH: f64 = 2.0;

/// Largest angle between the directions to consecutive neighbours of a point inside a lattice,
/// degrees: the six to eight neighbours of an inner dot surround it with gaps under 90, where the
/// neighbours of a point strewn at random rarely do.
pub(crate) const SURROUNDED_GAP_DEG: f64 = 120.0;

/// Members by spacing: points whose nearest neighbour lies within [`SPACED_NN`] of the median, in
/// patches of at least [`LatticeCheck::min_patch`], at least half of them `sure`, held together by
/// *inner* points (at least three such neighbours within [`SPACED_REACH`] medians, around it with no
/// gap above [`SURROUNDED_GAP_DEG`]); a sure spaced point with an inner one within reach joins its
/// patch (the lattice's edge, whose points have the lattice on one side only; a find one pitch beyond
/// the edge has no inner point within reach, and a doubtful one at the edge is as often a dot cut by
/// the image border).
fn spaced_members(points: &[Point2], sure: &[bool], hood: &Neighbourhood, check: &LatticeCheck) -> Vec<bool> {
    let Neighbourhood { nn, median_nn, grid } = hood;
    let (n, median_nn) = (points.len(), *median_nn);
    let spaced: Vec<bool> = nn
        .iter()
        .map(|&d| (SPACED_NN.0 * median_nn..=SPACED_NN.1 * median_nn).contains(&d))
        .collect();
    let reach = SPACED_REACH * median_nn;
    let mut angles = Vec::new();
    let inner: Vec<bool> = (0..n)
        .map(|i| {
            angles.clear();
            let p = points[i];
            grid.for_each_within(p, reach, |j, _| {
                if j != i && spaced[j] {
                    angles.push((points[j].y - p.y).atan2(points[j].x - p.x));
                }
            });
            spaced[i] && angles.len() >= 3 && largest_gap(&mut angles) <= SURROUNDED_GAP_DEG.to_radians()
        })
        .collect();
    let mut patches = Patches((0..n).collect());
    let mut inner_near = vec![0usize; n];
    for (i, &p) in points.iter().enumerate().filter(|&(i, _)| spaced[i]) {
        grid.for_each_within(p, reach, |j, _| {
            if j != i && inner[j] {
                inner_near[i] += 1;
                patches.join(i, j);
            }
        });
    }
    let member: Vec<bool> = (0..n)
        .map(|i| inner[i] || (spaced[i] && sure[i] && inner_near[i] >= 1))
        .collect();
    let (mut size, mut sure_size) = (vec![0usize; n], vec![0usize; n]);
    for i in (0..n).filter(|&i| member[i]) {
        let r = patches.root(i);
        size[r] += 1;
        sure_size[r] += usize::from(sure[i]);
    }
    (0..n)
        .map(|i| {
            let r = patches.root(i);
            member[i] && size[r] >= check.min_patch && 2 * sure_size[r] >= size[r]
        })
        .collect()
}

/// The largest angle between consecutive `angles` (radians, any order) around the circle.
pub(crate) fn largest_gap(angles: &mut [f64]) -> f64 {
    angles.sort_by(f64::total_cmp);
    let wrap = angles
        .first()
        .zip(angles.last())
        .map_or(0.0, |(a, b)| std::f64::consts::TAU - (b - a));
    angles.windows(2).map(|w| w[1] - w[0]).fold(wrap, f64::max)
}

/// Per patch root: whether the patch's spacing (median of its points' nearest-neighbour distances
/// `nn`) is within `ratio` of the largest patch's (ties: the one with the smallest root).
fn patches_at_the_lattice_pitch(patch_of: &[Option<usize>], nn: &[f64], ratio: f64) -> Vec<bool> {
    let mut spacing: Vec<Vec<f64>> = vec![Vec::new(); patch_of.len()];
    for (i, r) in patch_of.iter().enumerate() {
        if let Some(r) = r {
            spacing[*r].push(nn[i]);
        }
    }
    let largest = (0..spacing.len()).max_by_key(|&r| (spacing[r].len(), std::cmp::Reverse(r)));
    let pitch: Vec<Option<f64>> = spacing.iter_mut().map(|s| median(s)).collect();
    let Some(reference) = largest.and_then(|r| pitch[r]) else {
        return vec![false; patch_of.len()];
    };
    pitch
        .iter()
        .map(|p| p.is_some_and(|p| p <= reference * ratio && p * ratio >= reference))
        .collect()
}

/// The spacing, in pitches, of the lines that place an empty lattice site (contact strain changes it
/// by well under a quarter from one marker to the next).
pub(crate) const SITE_STEP: (f64, f64) = (0.75, 1.33);

/// Members searched around an empty site, in pitches: the far end of a line that ends at the site
/// lies two steps away.
const SITE_REACH: f64 = 2.2;

/// A candidate joining on a single line lies at least this many pitches inside the
/// image's outermost pixel centres: near the border, a find one step beyond the lattice is mostly a
/// dot the border cuts whose centre lies outside (the edge check's), not a marker.
pub const LINE_END_INSIDE_PITCH: f64 = 0.5;

/// The sites taken: the accepted markers (bucketed) and those moved up from the second tier so far.
struct Taken {
    accepted: Buckets,
    moved_up: Vec<Point2>,
}

impl Taken {
    fn within(&self, p: Point2, radius: f64) -> bool {
        self.accepted.any_within(p, radius)
            || self
                .moved_up
                .iter()
                .any(|q| (q.x - p.x).hypot(q.y - p.y) <= radius)
    }
}

/// Whether `p` sits at an empty lattice site of the `members` (see the module documentation):
/// no accepted marker within half a `pitch`, and on equally spaced lines of three with members in two
/// directions, the middle of at least one, or, in an image of `size`, the end of one whose next site
/// beyond `p` lies outside the image (the image's border cuts the lattice there; it does not end).
/// A candidate of confidence `confidence` >= [`LatticeCheck::line_end_min_confidence`] at least
/// [`LINE_END_INSIDE_PITCH`] inside an image of `size` needs only to lie on one such line (its end or
/// its middle).
fn at_an_empty_site(
    p: Point2,
    confidence: f32,
    members: &Buckets,
    taken: &Taken,
    pitch: f64,
    check: &LatticeCheck,
    size: Option<ImageSize>,
) -> bool {
    if taken.within(p, 0.5 * pitch) {
        return false;
    }
    let mut near: Vec<Point2> = Vec::new();
    members.for_each_within(p, SITE_REACH * pitch, |j, _| near.push(members.points()[j]));
    let min_angle = MinAngle::new(check.min_angle_deg);
    let tol2 = check.tolerance_frac * check.tolerance_frac;
    let dist2 = |u: Point2, x: f64, y: f64| (u.x - x).powi(2) + (u.y - y).powi(2);
    let (mut middle, mut any) = (Lines::NONE, Lines::NONE);
    let mut cut_by_the_border = false;
    // The site one step beyond `p` from its neighbour `near` on a line lies outside the image.
    let beyond_the_border = |near: Point2| {
        size.is_some_and(|s| outside_the_image(Point2::new(2.0 * p.x - near.x, 2.0 * p.y - near.y), s))
    };
    for (a, &q) in near.iter().enumerate() {
        for &r in &near[a + 1..] {
            let (pq2, pr2) = (dist2(p, q.x, q.y), dist2(p, r.x, r.y));
            // At the lattice's own spacing: the centre of a square cell is the middle of its
            // diagonals (0.71 pitch) and of longer chords, and no site.
            let step = pq2.min(pr2).sqrt() / pitch;
            if !(SITE_STEP.0..=SITE_STEP.1).contains(&step) {
                continue;
            }
            // p in the middle of q and r, or p at the end of the line q, r (either way round).
            let is_middle = dist2(r, 2.0 * p.x - q.x, 2.0 * p.y - q.y) <= tol2 * pq2;
            let end_beside_q = dist2(r, 2.0 * q.x - p.x, 2.0 * q.y - p.y) <= tol2 * pq2;
            let end_beside_r = dist2(q, 2.0 * r.x - p.x, 2.0 * r.y - p.y) <= tol2 * pr2;
            cut_by_the_border |=
                (end_beside_q && beyond_the_border(q)) || (end_beside_r && beyond_the_border(r));
            let is_end = end_beside_q || end_beside_r;
            if is_middle || is_end {
                let direction = [r.x - q.x, r.y - q.y];
                any.add(direction, &min_angle);
                if is_middle {
                    middle.add(direction, &min_angle);
                }
            }
        }
    }
    let line_end = confidence >= check.line_end_min_confidence
        && size.is_some_and(|s| inside_the_image_px(p, s) >= LINE_END_INSIDE_PITCH * pitch);
    ((middle.count > 0 || cut_by_the_border) && any.two) || (line_end && any.count > 0)
}

/// `found` with its accepted markers moved to the second tier unless they are members, or on the
/// lattice with a confidence of at least [`LatticeCheck::adjacent_min_confidence`] (all of them when
/// the accepted markers form no lattice), and second-tier candidates at empty lattice sites moved up
/// (most confident first), both tiers sorted by y then x.
pub fn keep_the_lattice(
    found: TieredDetections,
    check: &LatticeCheck,
    input_per_px: f64,
) -> TieredDetections {
    let fit = fit_lattice(&found.accepted, check, input_per_px);
    keep_fitted_lattice(found, fit, check, None, None)
}

/// [`keep_the_lattice`] with `fit`, the [`fit_lattice`] of `found.accepted` already made (a localizer
/// that fitted the same markers to choose its input layout reuses that fit), and inside `looked` (the
/// region a closer look re-examined) [`LatticeCheck::looked_min_confidence`] for the markers on the
/// lattice; with the image's `size`, empty sites where its border cuts the lattice count too (see
/// the module documentation).
pub fn keep_fitted_lattice(
    found: TieredDetections,
    fit: LatticeFit,
    check: &LatticeCheck,
    looked: Option<&Region>,
    size: Option<ImageSize>,
) -> TieredDetections {
    let needs = |d: &Detection| match looked {
        Some(r) if r.contains(d) => check.looked_min_confidence,
        _ => check.adjacent_min_confidence,
    };
    let (mut accepted, mut second_tier): (Vec<Detection>, Vec<Detection>) = (Vec::new(), found.second_tier);
    let mut member_points = Vec::new();
    for ((d, on), member) in found.accepted.into_iter().zip(fit.on_lattice).zip(fit.member) {
        if member {
            member_points.push(d.position);
        }
        if fit.is_lattice && (member || (on && d.confidence >= needs(&d))) {
            accepted.push(d);
        } else {
            second_tier.push(d);
        }
    }
    if let (true, Some(pitch)) = (fit.is_lattice, fit.pitch_px) {
        second_tier.sort_by(|a, b| b.confidence.total_cmp(&a.confidence));
        let members = Buckets::new(&member_points, check.reach_frac * pitch);
        let mut taken = Taken {
            accepted: Buckets::new(&accepted.iter().map(|a| a.position).collect::<Vec<_>>(), pitch),
            moved_up: Vec::new(),
        };
        let mut unsure = Vec::new();
        for d in second_tier {
            if at_an_empty_site(d.position, d.confidence, &members, &taken, pitch, check, size) {
                taken.moved_up.push(d.position);
                accepted.push(d);
            } else {
                unsure.push(d);
            }
        }
        second_tier = unsure;
    }
    crate::sort_detections(&mut accepted);
    crate::sort_detections(&mut second_tier);
    TieredDetections {
        accepted,
        second_tier,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square(cols: usize, rows: usize, pitch: f64) -> Vec<Point2> {
        (0..rows)
            .flat_map(|r| {
                (0..cols).map(move |c| Point2::new(c as f64 * pitch + 10.0, r as f64 * pitch + 10.0))
            })
            .collect()
    }

    /// Detections the network is sure of at `points`.
    fn sure(points: &[Point2]) -> Vec<Detection> {
        points
            .iter()
            .map(|&position| Detection {
                position,
                confidence: 0.99,
            })
            .collect()
    }

    /// Uniform random points from a fixed linear congruential sequence (no dependency for a test).
    fn scattered(n: usize, side: f64, mut state: u64) -> Vec<Point2> {
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64 * side
        };
        (0..n).map(|_| Point2::new(next(), next())).collect()
    }

    #[test]
    fn every_point_of_a_square_lattice_is_a_member_corners_included() {
        let fit = fit_lattice(&sure(&square(10, 8, 20.0)), &LatticeCheck::default(), 1.0);
        assert_eq!(fit.members, 80);
        assert!(fit.is_lattice);
        assert_eq!(fit.pitch_px, Some(20.0));
    }

    #[test]
    fn texture_lined_up_at_a_finer_spacing_beside_the_lattice_is_no_member() {
        // A 12 x 10 marker lattice (pitch 16) and, well apart, a 5 x 5 patch at pitch 7: the speckle
        // of a housing that the network took for dots and that lines up by chance.
        let mut pts = square(12, 10, 16.0);
        let speckle: Vec<Point2> = square(5, 5, 7.0)
            .into_iter()
            .map(|p| Point2::new(p.x + 300.0, p.y + 200.0))
            .collect();
        pts.extend(&speckle);
        let fit = fit_lattice(&sure(&pts), &LatticeCheck::default(), 1.0);
        assert_eq!(fit.members, 120, "only the marker lattice");
        assert!(fit.member[..120].iter().all(|&m| m));
        assert!(fit.on_lattice[120..].iter().all(|&m| !m));
        // Two patches of one lattice (split by an occluder) at the same pitch both stay.
        let mut split = square(12, 4, 16.0);
        split.extend(
            square(12, 4, 16.0)
                .into_iter()
                .map(|p| Point2::new(p.x, p.y + 120.0)),
        );
        assert_eq!(
            fit_lattice(&sure(&split), &LatticeCheck::default(), 1.0).members,
            96
        );
    }

    fn tiers(accepted: &[Point2], second_tier: &[(Point2, f32)]) -> TieredDetections {
        let det = |position: Point2, confidence: f32| Detection { position, confidence };
        TieredDetections {
            accepted: accepted.iter().map(|&p| det(p, 0.99)).collect(),
            second_tier: second_tier.iter().map(|&(p, c)| det(p, c)).collect(),
        }
    }

    #[test]
    fn an_unsure_candidate_at_an_empty_lattice_site_joins_and_others_stay_unsure() {
        // A 10 x 8 lattice (pitch 20, origin 10) without the markers at column 4, row 3 and at
        // column 9 (the right edge), row 3.
        let holes = [Point2::new(90.0, 70.0), Point2::new(190.0, 70.0)];
        let lattice: Vec<Point2> = square(10, 8, 20.0)
            .into_iter()
            .filter(|p| !holes.contains(p))
            .collect();
        let unsure = [
            (Point2::new(91.0, 69.0), 0.3),  // at the empty site
            (Point2::new(189.0, 71.0), 0.3), // at the empty edge site: the middle of the edge
            (Point2::new(88.0, 71.0), 0.2),  // the same site again: taken by now
            (Point2::new(52.0, 50.0), 0.35), // 2 px from a marker: its site is taken
            (Point2::new(210.0, 50.0), 0.3), // one pitch past the right edge: only the end of a line
            (Point2::new(100.0, 80.0), 0.3), // between four markers: no line through it
        ];
        let out = keep_the_lattice(tiers(&lattice, &unsure), &LatticeCheck::default(), 1.0);
        assert_eq!(out.accepted.len(), lattice.len() + 2);
        for site in [Point2::new(91.0, 69.0), Point2::new(189.0, 71.0)] {
            assert!(out.accepted.iter().any(|d| d.position == site), "{site:?}");
        }
        assert_eq!(out.second_tier.len(), 4);
    }

    #[test]
    fn a_sure_find_one_step_past_the_lattice_joins_inside_the_image_and_no_further() {
        // A 10 x 8 lattice (pitch 20, x 10-190, y 10-150) whose network missed the column after its
        // last: sure finds one step past it end one line each (their row).
        let lattice = square(10, 8, 20.0);
        let second = [
            (Point2::new(210.5, 70.0), 0.8),  // one step past the last column: joins
            (Point2::new(209.5, 90.0), 0.3),  // the same, unsure: stays
            (Point2::new(230.0, 110.0), 0.9), // two steps past: no line ends there
            (Point2::new(100.0, 80.0), 0.9),  // between four markers: no line through it
        ];
        let check = LatticeCheck::default();
        let tiered = tiers(&lattice, &second);
        let fit = fit_lattice(&tiered.accepted, &check, 1.0);
        let roomy = ImageSize {
            width: 300,
            height: 200,
        };
        let out = keep_fitted_lattice(tiered.clone(), fit.clone(), &check, None, Some(roomy));
        assert_eq!(out.accepted.len(), lattice.len() + 1);
        assert!(
            out.accepted
                .iter()
                .any(|d| d.position == Point2::new(210.5, 70.0))
        );
        assert_eq!(out.second_tier.len(), 3);
        // Within half a pitch of the border (an image 218 px wide: 6.5 px inside) a find past the
        // lattice is mostly a dot the border cuts: it stays, and so without the image's size.
        let narrow = ImageSize {
            width: 218,
            height: 200,
        };
        let cut = keep_fitted_lattice(tiered.clone(), fit.clone(), &check, None, Some(narrow));
        assert_eq!(cut.accepted.len(), lattice.len());
        let blind = keep_fitted_lattice(tiered, fit, &check, None, None);
        assert_eq!(blind.accepted.len(), lattice.len());
    }

    #[test]
    fn unsure_dots_the_image_border_cuts_the_lattice_at_join_and_those_past_its_end_do_not() {
        // A 10 x 8 lattice (pitch 20) whose top row lies 6 px below the top of a 200 x 170 image; the
        // network was unsure of three of its dots: the corner and two side by side (columns 0, 3, 4).
        // Each ends a column whose next site up lies outside the image, and a row: not the middle of
        // any line. One pitch past the bottom row (y = 166, inside the image) and one past the right
        // column (x = 206, in a wider image) the lattice ends, with nothing there: unsure finds
        // there stay unsure.
        let lattice = |x0: f64| -> Vec<Point2> {
            (0..8)
                .flat_map(|r| (0..10).map(move |c| Point2::new(x0 + c as f64 * 20.0, 6.0 + r as f64 * 20.0)))
                .collect()
        };
        let all = lattice(6.0);
        let missed = [
            Point2::new(6.0, 6.0),
            Point2::new(66.0, 6.0),
            Point2::new(86.0, 6.0),
        ];
        let found: Vec<Point2> = all.iter().copied().filter(|p| !missed.contains(p)).collect();
        let unsure: Vec<(Point2, f32)> = missed
            .iter()
            .map(|&p| (Point2::new(p.x + 0.5, p.y - 0.5), 0.3))
            .collect();
        let size = ImageSize {
            width: 200,
            height: 170,
        };
        let check = LatticeCheck::default();
        let tiered = tiers(&found, &unsure);
        let fit = fit_lattice(&tiered.accepted, &check, 1.0);
        let out = keep_fitted_lattice(tiered.clone(), fit.clone(), &check, None, Some(size));
        assert_eq!(out.accepted.len(), all.len(), "the three unsure dots join");
        assert!(out.second_tier.is_empty());
        // Without the image (no border known) only the middle-of-a-line rule applies: none joins.
        let blind = keep_fitted_lattice(tiered, fit, &check, None, None);
        assert_eq!(blind.accepted.len(), found.len());
        // Past the lattice's end inside the image: a row below the last and a column right of the
        // last, in an image wide enough that the site beyond the column lies inside it.
        let past: Vec<(Point2, f32)> = (0..10)
            .map(|c| (Point2::new(6.0 + c as f64 * 20.0, 166.0), 0.3))
            .chain((1..7).map(|r| (Point2::new(206.0, 6.0 + r as f64 * 20.0), 0.3)))
            .collect();
        let wide = ImageSize {
            width: 260,
            height: 200,
        };
        let found = tiers(&all, &past);
        let fit = fit_lattice(&found.accepted, &check, 1.0);
        let out = keep_fitted_lattice(found, fit, &check, None, Some(wide));
        assert_eq!(
            out.accepted.len(),
            all.len(),
            "nothing past the lattice's end joins"
        );
    }

    #[test]
    fn a_hexagonal_lattice_is_a_lattice() {
        let pts: Vec<Point2> = (0..12)
            .flat_map(|r| {
                (0..14).map(move |c| {
                    let shift = if r % 2 == 1 { 10.0 } else { 0.0 };
                    Point2::new(c as f64 * 20.0 + shift, r as f64 * 20.0 * 3f64.sqrt() / 2.0)
                })
            })
            .collect();
        let fit = fit_lattice(&sure(&pts), &LatticeCheck::default(), 1.0);
        assert_eq!(fit.members, pts.len());
    }

    /// A 12 x 10 lattice (pitch 20) whose markers are moved up to `jitter` pitch per axis, as
    /// hand-placed dots are.
    fn jittered(jitter: f64, seed: u64) -> Vec<Point2> {
        let offsets = scattered(240, 2.0 * jitter * 20.0, seed);
        square(12, 10, 20.0)
            .into_iter()
            .zip(offsets.chunks(2))
            .map(|(p, o)| Point2::new(p.x + o[0].x - jitter * 20.0, p.y + o[1].y - jitter * 20.0))
            .collect()
    }

    #[test]
    fn an_irregular_lattice_the_network_is_sure_of_is_a_lattice() {
        for seed in 1..=5 {
            let pts = jittered(0.25, seed);
            let fit = fit_lattice(&sure(&pts), &LatticeCheck::default(), 1.0);
            assert!(fit.is_lattice, "seed {seed}");
            assert!(fit.members >= 108, "seed {seed}: {} of 120 members", fit.members);
            // The pitch is the members' median nearest-neighbour distance: under 20 px with jitter.
            assert!(
                (15.0..21.0).contains(&fit.pitch_px.unwrap_or(0.0)),
                "{:?}",
                fit.pitch_px
            );
            // Doubtful detections in the same places: the spacing alone does not make them markers.
            let doubtful: Vec<Detection> = sure(&pts)
                .into_iter()
                .map(|d| Detection { confidence: 0.6, ..d })
                .collect();
            let fit = fit_lattice(&doubtful, &LatticeCheck::default(), 1.0);
            assert!(fit.members < 60, "seed {seed}: {} doubtful members", fit.members);
        }
    }

    #[test]
    fn random_points_are_not_a_lattice() {
        for (n, seed) in [(200, 1), (2000, 2), (5000, 3)] {
            let fit = fit_lattice(&sure(&scattered(n, 640.0, seed)), &LatticeCheck::default(), 1.0);
            assert!(fit.members <= n / 100, "{n} points: {} members", fit.members);
        }
    }

    /// Outliers beside a lattice (a rim, glints) are dropped, the lattice is kept; so is a pair of
    /// touching markers squeezed together in a row.
    #[test]
    fn outliers_go_and_squeezed_pairs_stay() {
        let mut pts = square(10, 8, 20.0);
        // two markers of row 3 squeezed towards each other by 5 px each (touching dots)
        let (a, b) = (3 * 10 + 4, 3 * 10 + 5);
        pts[a].x += 5.0;
        pts[b].x -= 5.0;
        let lattice = pts.len();
        pts.extend([
            Point2::new(260.0, 40.0),
            Point2::new(-40.0, 97.0),
            Point2::new(120.0, 200.0),
        ]);
        let fit = fit_lattice(&sure(&pts), &LatticeCheck::default(), 1.0);
        assert!(
            fit.on_lattice[..lattice].iter().all(|m| *m),
            "{:?}",
            fit.on_lattice
        );
        assert!(fit.on_lattice[lattice..].iter().all(|m| !*m));
    }

    /// A squeezed pair the network is unsure of (pushed off its lines, so on the lattice but no
    /// member) is kept inside a region the closer look re-examined, and only there.
    #[test]
    fn unsure_squeezed_markers_are_kept_inside_a_looked_region_only() {
        let mut pts = square(10, 8, 20.0);
        let (a, b) = (3 * 10 + 4, 3 * 10 + 5);
        pts[a].x += 5.0;
        pts[a].y += 3.0;
        pts[b].x -= 5.0;
        pts[b].y -= 3.0;
        let mut found = sure(&pts);
        found[a].confidence = 0.6;
        found[b].confidence = 0.6;
        let check = LatticeCheck::default();
        let fit = fit_lattice(&found, &check, 1.0);
        assert!(fit.on_lattice[a] && fit.on_lattice[b] && !fit.member[a] && !fit.member[b]);
        let tiers = || TieredDetections {
            accepted: found.clone(),
            second_tier: Vec::new(),
        };
        let kept = |d: &Detection, t: &TieredDetections| t.accepted.contains(d);
        let plain = keep_fitted_lattice(tiers(), fit_lattice(&found, &check, 1.0), &check, None, None);
        assert!(!kept(&found[a], &plain) && !kept(&found[b], &plain));
        let around = Region {
            x0: 60.0,
            y0: 40.0,
            x1: 120.0,
            y1: 80.0,
        };
        let looked = keep_fitted_lattice(
            tiers(),
            fit_lattice(&found, &check, 1.0),
            &check,
            Some(&around),
            None,
        );
        assert!(kept(&found[a], &looked) && kept(&found[b], &looked));
        let elsewhere = Region {
            x0: 140.0,
            y0: 100.0,
            x1: 180.0,
            y1: 140.0,
        };
        let far = keep_fitted_lattice(
            tiers(),
            fit_lattice(&found, &check, 1.0),
            &check,
            Some(&elsewhere),
            None,
        );
        assert!(!kept(&found[a], &far) && !kept(&found[b], &far));
    }

    #[test]
    fn a_lattice_finer_than_the_network_resolves_is_none() {
        let fit = fit_lattice(&sure(&square(10, 8, 20.0)), &LatticeCheck::default(), 0.3);
        assert_eq!(fit.members, 80);
        assert!(!fit.is_lattice, "6 px at the input");
        let few = fit_lattice(&sure(&square(3, 2, 20.0)), &LatticeCheck::default(), 1.0);
        assert!(!few.is_lattice, "{} members", few.members);
    }
}
