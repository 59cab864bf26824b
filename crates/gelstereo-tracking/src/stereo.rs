//! The stereo stages between localization and contact, each one type with one input and one output:
//!
//! - [`ViewTracking`] ("track"): both views' detections -> [`ViewTracks`], each view's markers
//!   followed by its [`Tracker`] and checked and assisted across the views;
//! - [`Triangulation`] ("triangulate"): [`ViewTracks`] -> [`Points3`], the 3-D points of the markers
//!   seen in both views, outliers of the displacement field dropped and gaps filled from the
//!   neighbours.
//!
//! The contact ([`crate::ReferenceSurface::analyze`]) and slip ([`crate::SlipDetector::update`])
//! stages follow; [`crate::StereoSession`] chains the four.

use gelstereo_core::{GridIndex, GridShape, MarkerStatus, Point2};
use gelstereo_geometry::Triangulator;
use nalgebra::{Point3, Vector3};
use rayon::iter::{IndexedParallelIterator, IntoParallelRefIterator, ParallelIterator};

use crate::error::{Result, config_err};
use crate::fit::{affine_at, quadratic_at};
use crate::session::SessionConfig;
use crate::tracker::{TrackFrame, Tracker, lattice_neighbourhood, median_in};

/// A marker's left pixel, right pixel, left status and right status in one frame.
pub type ViewPixels = (Option<Point2>, Option<Point2>, MarkerStatus, MarkerStatus);

/// What [`ViewTracking`] gives per frame.
#[derive(Debug, Clone)]
pub struct ViewTracks {
    /// Tracking in the left view.
    pub left: TrackFrame,
    /// Tracking in the right view.
    pub right: TrackFrame,
    /// Per lattice position (row-major) the marker's pixels and statuses in both views; lost where
    /// a view has no slot for it.
    pub pixels: Vec<ViewPixels>,
}

/// The "track" stage: both views' trackers, started on the reference frame's indexed markers.
#[derive(Debug, Clone)]
pub struct ViewTracking {
    shape: GridShape,
    left: Tracker,
    right: Tracker,
    /// Lattice position -> slot in the left / right tracker.
    left_slot: Vec<Option<usize>>,
    right_slot: Vec<Option<usize>>,
    /// Ids in either view, row-major.
    ids: Vec<GridIndex>,
    /// Per lattice position: the lattice positions within the tracker's support radius, weights
    /// 1/d^2 in lattice steps (the maps between the views, [`transfer`](Self::transfer)).
    around: Vec<Vec<(u32, f64)>>,
    /// [`SessionConfig::stereo_outlier_pitch`].
    stereo_outlier_pitch: f64,
    parallel: bool,
    /// The last frame number tracked: a later call with a gap (unreadable frames were not passed
    /// on) lets the trackers predict across it ([`Tracker::skip_frames`]).
    last_frame: Option<u32>,
}

impl ViewTracking {
    /// Starts both views' trackers on the reference frame's indexed markers (grid index, px).
    pub fn new(
        shape: GridShape,
        left: &[(GridIndex, Point2)],
        right: &[(GridIndex, Point2)],
        config: &SessionConfig,
    ) -> Result<Self> {
        let left = Tracker::new(shape, left, config.tracker.clone())?;
        let right = Tracker::new(shape, right, config.tracker.clone())?;
        let v = config.stereo_outlier_pitch;
        if !(v == 0.0 || (v.is_finite() && v > 0.0 && v < 1.0)) {
            return Err(config_err(
                "stereo_outlier_pitch",
                "0 (off) or a fraction of the pitch in (0, 1)",
                v,
            ));
        }
        let slot = |t: &Tracker| {
            let mut s = vec![None; shape.count()];
            for (k, id) in t.ids().iter().enumerate() {
                if let Some(lin) = shape.linear(*id) {
                    s[lin] = Some(k);
                }
            }
            s
        };
        let (left_slot, right_slot) = (slot(&left), slot(&right));
        let ids: Vec<GridIndex> = shape
            .indices()
            .filter(|i| {
                shape
                    .linear(*i)
                    .is_some_and(|l| left_slot[l].is_some() || right_slot[l].is_some())
            })
            .collect();
        let around = shape
            .indices()
            .map(|id| {
                lattice_neighbourhood(shape, id, config.tracker.support_radius)
                    .map(|(n, w)| (n as u32, w))
                    .collect()
            })
            .collect();
        Ok(Self {
            shape,
            left,
            right,
            left_slot,
            right_slot,
            ids,
            around,
            stereo_outlier_pitch: v,
            parallel: false,
            last_frame: None,
        })
    }

    /// Frame number `frame`, given each view's [accepted, second-tier] points: associated with the
    /// trackers (side by side where parallel), then checked and assisted across the views.
    pub fn run(&mut self, frame: u32, left: [&[Point2]; 2], right: [&[Point2]; 2]) -> ViewTracks {
        let skipped = frames_skipped(&mut self.last_frame, frame);
        self.left.skip_frames(skipped);
        self.right.skip_frames(skipped);
        let (mut lf, mut rf) = if self.parallel {
            let (l, r) = (&mut self.left, &mut self.right);
            rayon::join(
                || l.update_tiered(left[0], left[1]),
                || r.update_tiered(right[0], right[1]),
            )
        } else {
            (
                self.left.update_tiered(left[0], left[1]),
                self.right.update_tiered(right[0], right[1]),
            )
        };
        self.check_and_assist_across_views(&mut lf, &mut rf);
        let pixels = self.view_pixels(&lf, &rf);
        ViewTracks {
            left: lf,
            right: rf,
            pixels,
        }
    }

    /// Whether the two views' trackers update on rayon's thread pool (default: no).
    pub fn set_parallel(&mut self, parallel: bool) {
        self.parallel = parallel;
    }

    /// Makes the latest positions each view's new reference.
    pub fn rezero(&mut self) {
        self.left.rezero();
        self.right.rezero();
    }

    /// The ids tracked (indexed in either view on the reference frame), row-major.
    pub fn ids(&self) -> &[GridIndex] {
        &self.ids
    }

    /// The lattice.
    pub fn shape(&self) -> GridShape {
        self.shape
    }

    /// The left view's tracker.
    pub fn left(&self) -> &Tracker {
        &self.left
    }

    /// The right view's tracker.
    pub fn right(&self) -> &Tracker {
        &self.right
    }

    /// Per marker (linear index) its left and right pixel and status; Lost where a view has no
    /// slot for it.
    fn view_pixels(&self, lf: &TrackFrame, rf: &TrackFrame) -> Vec<ViewPixels> {
        let mut px = vec![(None, None, MarkerStatus::Lost, MarkerStatus::Lost); self.shape.count()];
        for (lin, entry) in px.iter_mut().enumerate() {
            if let Some(k) = self.left_slot[lin] {
                entry.0 = lf.markers[k].position_px;
                entry.2 = lf.markers[k].status;
            }
            if let Some(k) = self.right_slot[lin] {
                entry.1 = rf.markers[k].position_px;
                entry.3 = rf.markers[k].status;
            }
        }
        px
    }

    /// Stereo check and assist, after both views are associated. The local map between the views
    /// is a weighted (1/d^2) fit over a marker's lattice neighbours within the support radius that
    /// are tracked in both views in this frame ([`transfer`](Self::transfer)).
    ///
    /// 1. **Check**: a marker tracked in both views whose left position lies farther than
    ///    `stereo_outlier_pitch` x its left pitch from where the affine map puts its right one took
    ///    another marker's detection in one view: the view where it sits farther from its own
    ///    lattice ([`Tracker::lattice_residual`]) loses the association. The per-view checks
    ///    cannot see a detection that drifts with the wrong marker (a merged blob in one view's
    ///    oblique contact); the other view can. Affine, not quadratic: the quadratic map also
    ///    follows neighbours mislocalized along with the wrong detection, and lets the swap pass.
    /// 2. **Assist**: a marker tracked in one view but missed in the other is placed in the other
    ///    through the quadratic map (it follows the curved contact), not where its own
    ///    neighbours' motion carried its last position: under a sliding contact that lags by up
    ///    to a pitch within a few frames, onto a neighbour's place, and it wrecks the
    ///    triangulated point.
    fn check_and_assist_across_views(&mut self, lf: &mut TrackFrame, rf: &mut TrackFrame) {
        let limit = self.stereo_outlier_pitch;
        if limit > 0.0 {
            let both = self.tracked_in_both(lf, rf);
            let mut refuted = Vec::new();
            for (lin, pair) in both.iter().enumerate() {
                let (Some([l, r]), Some((kl, kr))) = (pair, self.slots(lin)) else {
                    continue;
                };
                let pitch = self.right.pitch_px()[kr];
                let Some(t) = self.transfer(&both, lin, *r, pitch, false, ViewMap::Affine) else {
                    continue;
                };
                if l.distance(t) <= limit * self.left.pitch_px()[kl] {
                    continue;
                }
                match (self.left.lattice_residual(kl), self.right.lattice_residual(kr)) {
                    (Some(a), Some(b)) if a >= b => refuted.push((true, kl)),
                    (Some(_), Some(_)) => refuted.push((false, kr)),
                    _ => {}
                }
            }
            for (left, k) in refuted {
                if left {
                    self.left.unassociate(k, lf);
                } else {
                    self.right.unassociate(k, rf);
                }
            }
        }
        let both = self.tracked_in_both(lf, rf);
        let mut placements = Vec::new();
        for lin in 0..self.shape.count() {
            let Some((kl, kr)) = self.slots(lin) else { continue };
            let (from_left, at, pitch) = match (tracked_px(lf, kl), tracked_px(rf, kr)) {
                (Some(p), None) => (true, p, self.left.pitch_px()[kl]),
                (None, Some(p)) => (false, p, self.right.pitch_px()[kr]),
                _ => continue,
            };
            if let Some(p) = self.transfer(&both, lin, at, pitch, from_left, ViewMap::Quadratic) {
                placements.push((from_left, kl, kr, p));
            }
        }
        for (from_left, kl, kr, p) in placements {
            if from_left {
                self.right.place(kr, p, rf);
            } else {
                self.left.place(kl, p, lf);
            }
        }
    }

    /// The slots in the left and right trackers of the marker at lattice position `lin`, when it
    /// is indexed in both views.
    fn slots(&self, lin: usize) -> Option<(usize, usize)> {
        Some((self.left_slot[lin]?, self.right_slot[lin]?))
    }

    /// Per lattice position: the [left, right] positions of the marker tracked in both views.
    fn tracked_in_both(&self, lf: &TrackFrame, rf: &TrackFrame) -> Vec<Option<[Point2; 2]>> {
        (0..self.shape.count())
            .map(|lin| {
                let (kl, kr) = self.slots(lin)?;
                Some([tracked_px(lf, kl)?, tracked_px(rf, kr)?])
            })
            .collect()
    }

    /// Where `at`, the position in one view (the left one when `from_left`; `pitch` is its local
    /// pitch there) of the marker at lattice position `lin`, lands in the other, by the weighted (1/d^2) `map` between the views of
    /// its lattice neighbours within the support radius tracked in both views (`both`, from
    /// [`tracked_in_both`](Self::tracked_in_both)); `None` when too few neighbours span the map.
    fn transfer(
        &self,
        both: &[Option<[Point2; 2]>],
        lin: usize,
        at: Point2,
        pitch: f64,
        from_left: bool,
        map: ViewMap,
    ) -> Option<Point2> {
        let (from, to) = if from_left { (0, 1) } else { (1, 0) };
        // No allocation on the check's path: it runs for every marker of every frame.
        let pairs = self.around[lin].iter().filter_map(|&(n, w)| {
            let p = both[n as usize]?;
            let (a, b) = (p[from], p[to]);
            Some(([a.x, a.y], [b.x, b.y], w))
        });
        match map {
            ViewMap::Affine => affine_at(pairs, at, pitch),
            ViewMap::Quadratic => quadratic_at(&pairs.collect::<Vec<_>>(), at, pitch),
        }
    }
}

/// The local map between the views of [`ViewTracking::transfer`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ViewMap {
    Affine,
    Quadratic,
}

/// The position of slot `k` in `frame` when it is tracked there.
fn tracked_px(frame: &TrackFrame, k: usize) -> Option<Point2> {
    frame
        .markers
        .get(k)
        .filter(|m| m.status == MarkerStatus::Tracked)
        .and_then(|m| m.position_px)
}

/// The frames between the last one tracked and `frame` (0 when consecutive, or for the first, or
/// when the numbers go back); records `frame` as the last.
pub(crate) fn frames_skipped(last: &mut Option<u32>, frame: u32) -> u32 {
    let skipped = last.map_or(0, |l| frame.saturating_sub(l).saturating_sub(1));
    *last = Some(frame);
    skipped
}

/// What [`Triangulation`] gives per frame, dense over the lattice (row-major).
#[derive(Debug, Clone)]
pub struct Points3 {
    /// Every marker with a reference: triangulated, or (dropped as an outlier, or seen in one view
    /// or none) its reference plus its measured neighbours' mean displacement: the contact's input.
    pub filled: Vec<Option<[f64; 3]>>,
    /// What is written: `filled`, but an outlier within the noise floor keeps its measurement.
    pub written: Vec<Option<[f64; 3]>>,
    /// Whether `written` holds a measurement (triangulated, not dropped beyond the floor).
    pub measured: Vec<bool>,
    /// Reprojection error of each triangulated marker (the larger of the two views), px; `None`
    /// where the marker was not triangulated.
    pub reprojection_px: Vec<Option<f64>>,
}

/// The "triangulate" stage: the 3-D points of the markers seen in both views, in the left camera
/// frame, with the outlier test on the displacement field and the fill of the gaps.
#[derive(Debug, Clone)]
pub struct Triangulation {
    shape: GridShape,
    triangulator: Triangulator,
    reference_mm: Vec<Option<[f64; 3]>>,
    outlier_threshold: f64,
    outlier_noise_mm: f64,
    outlier_min_pitch: f64,
    /// A dropped marker within this residual, mm, keeps its measurement
    /// ([`SessionConfig::outlier_min_pitch`] x the reference surface's pitch).
    floor_mm: f64,
    parallel: bool,
}

impl Triangulation {
    /// The reference points of `tracking`'s reference frame (row-major): the markers indexed in both
    /// views and triangulated within the rig's bound.
    pub fn reference_points(triangulator: &Triangulator, tracking: &ViewTracking) -> Vec<Option<[f64; 3]>> {
        let mut reference_mm = vec![None; tracking.shape.count()];
        for (lin, r) in reference_mm.iter_mut().enumerate() {
            if let Some((a, b)) = tracking.slots(lin)
                && let Ok(t) = triangulator
                    .triangulate(tracking.left.reference_px()[a], tracking.right.reference_px()[b])
            {
                let p = t.p_in_left_mm;
                *r = Some([p.x, p.y, p.z]);
            }
        }
        reference_mm
    }

    /// The stage against `reference_mm` (row-major, mm), whose surface has the lattice pitch
    /// `pitch_mm`: it sets the noise floor of the outlier test.
    pub fn new(
        triangulator: Triangulator,
        shape: GridShape,
        reference_mm: Vec<Option<[f64; 3]>>,
        pitch_mm: f64,
        config: &SessionConfig,
    ) -> Self {
        Self {
            shape,
            triangulator,
            reference_mm,
            outlier_threshold: config.outlier_threshold,
            outlier_noise_mm: config.outlier_noise_mm,
            outlier_min_pitch: config.outlier_min_pitch,
            floor_mm: config.outlier_min_pitch * pitch_mm,
            parallel: false,
        }
    }

    /// The reference points (row-major; `None` where a marker has none).
    pub fn reference_mm(&self) -> &[Option<[f64; 3]>] {
        &self.reference_mm
    }

    /// Whether triangulation runs on rayon's thread pool (default: no).
    pub fn set_parallel(&mut self, parallel: bool) {
        self.parallel = parallel;
    }

    /// Makes `positions` (row-major, mm) the reference points, their surface's pitch `pitch_mm`
    /// (drift correction).
    pub fn rezero(&mut self, positions: Vec<Option<[f64; 3]>>, pitch_mm: f64) {
        self.reference_mm = positions;
        self.floor_mm = self.outlier_min_pitch * pitch_mm;
    }

    /// One frame's tracks -> its 3-D points.
    pub fn run(&self, tracks: &ViewTracks) -> Points3 {
        let points = {
            let _span = tracing::trace_span!("triangulate").entered();
            self.triangulate_all(&tracks.pixels)
        };
        let _span = tracing::trace_span!("outliers").entered();
        let mut current: Vec<Option<[f64; 3]>> = points.iter().map(|t| t.map(|(p, _)| p)).collect();
        let reprojection_px = points.iter().map(|t| t.map(|(_, e)| e)).collect();
        let dropped = reject_outliers(
            self.shape,
            &self.reference_mm,
            &mut current,
            self.outlier_threshold,
            self.outlier_noise_mm,
        );
        let mut measured: Vec<bool> = current.iter().map(Option::is_some).collect();
        // Markers without a 3-D point take their reference plus the mean 3-D displacement of their
        // measured 8-neighbours.
        let filled = fill_from_neighbours(self.shape, &self.reference_mm, &current);
        let written = self.restore_within_floor(filled.clone(), &mut measured, dropped);
        Points3 {
            filled,
            written,
            measured,
            reprojection_px,
        }
    }

    /// Triangulates every marker seen in both views: its 3-D point in the left camera frame and
    /// its largest reprojection error.
    fn triangulate_all(&self, px: &[ViewPixels]) -> Vec<Option<([f64; 3], f64)>> {
        let triangulator = &self.triangulator;
        let triangulate = |&(l, r, _, _): &ViewPixels| {
            let t = triangulator.triangulate(l?, r?).ok()?;
            let p = t.p_in_left_mm;
            Some(([p.x, p.y, p.z], t.max_reprojection_error_px()))
        };
        if self.parallel {
            // One piece per thread: a piece more costs a wake-up (rayon halves a range while each
            // half keeps at least `piece`).
            let piece = (px.len() / rayon::current_num_threads()).max(1);
            px.par_iter().with_min_len(piece).map(triangulate).collect()
        } else {
            px.iter().map(triangulate).collect()
        }
    }

    /// What is written: outliers within the noise floor keep their measurement (and count as
    /// measured) in place of the filled-in value.
    fn restore_within_floor(
        &self,
        filled: Vec<Option<[f64; 3]>>,
        measured: &mut [bool],
        dropped: Vec<(usize, [f64; 3], f64)>,
    ) -> Vec<Option<[f64; 3]>> {
        let mut written = filled;
        let floor_mm = self.floor_mm;
        for (k, p, residual_mm) in dropped {
            if residual_mm <= floor_mm {
                written[k] = Some(p);
                measured[k] = true;
            }
        }
        written
    }
}

/// The normalised median test of particle image velocimetry (Westerweel & Scarano, "Universal outlier
/// detection for PIV data", Exp. Fluids 39, 2005) on the 3-D displacement field: a marker whose
/// displacement differs from the median of its measured 8-neighbours by more than `threshold` x
/// (the neighbours' median residual + the noise level) is dropped. The noise level is `noise_mm` or,
/// when larger, the median residual over the lattice (then predicted from its neighbours).
/// Needs at least 3 measured neighbours. Returns the dropped markers: lattice position, position
/// and residual, mm.
pub fn reject_outliers(
    shape: GridShape,
    reference: &[Option<[f64; 3]>],
    current: &mut [Option<[f64; 3]>],
    threshold: f64,
    noise_mm: f64,
) -> Vec<(usize, [f64; 3], f64)> {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let disp: Vec<Option<Vector3<f64>>> = current
        .iter()
        .zip(reference)
        .map(|(c, r)| match (c, r) {
            (Some(c), Some(r)) => Some(Vector3::from(*c) - Vector3::from(*r)),
            _ => None,
        })
        .collect();
    // Per marker: (lattice position, |residual|, neighbours' median residual).
    let mut tests: Vec<(usize, f64, f64)> = Vec::new();
    let mut neigh: Vec<Vector3<f64>> = Vec::with_capacity(8);
    let mut scratch = Vec::with_capacity(8);
    for r in 0..rows {
        for c in 0..cols {
            let k = r * cols + c;
            let Some(d) = disp[k] else { continue };
            neigh.clear();
            for dr in -1i64..=1 {
                for dc in -1i64..=1 {
                    let (rr, cc) = (r as i64 + dr, c as i64 + dc);
                    if (dr == 0 && dc == 0) || rr < 0 || cc < 0 || rr >= rows as i64 || cc >= cols as i64 {
                        continue;
                    }
                    if let Some(v) = disp[rr as usize * cols + cc as usize] {
                        neigh.push(v);
                    }
                }
            }
            if neigh.len() < 3 {
                continue;
            }
            let med =
                Vector3::from_fn(|i, _| median_in(neigh.iter().map(|v| v[i]), &mut scratch).unwrap_or(0.0));
            let residual = (d - med).norm();
            // Within `threshold` (>= 0) x the noise floor a marker stays whatever its neighbours' spread
            // (the noise level is at least the floor): most markers, whose spread is not needed.
            let spread = if threshold >= 0.0 && residual <= threshold * noise_mm {
                0.0
            } else {
                median_in(neigh.iter().map(|v| (v - med).norm()), &mut scratch).unwrap_or(0.0)
            };
            tests.push((k, residual, spread));
        }
    }
    // The noise level: the configured floor, or the median residual over the whole lattice when the
    // rig is noisier (a calibration with longer range or a noisier localizer).
    let noise = crate::tracker::median(tests.iter().map(|t| t.1).collect())
        .unwrap_or(0.0)
        .max(noise_mm);
    let mut dropped = Vec::new();
    for &(k, residual, spread) in &tests {
        if residual > threshold * (spread + noise)
            && let Some(p) = current[k].take()
        {
            dropped.push((k, p, residual));
        }
    }
    dropped
}

/// Dense positions where missing entries with a reference take the reference plus the mean
/// displacement of their present 8-neighbours (that have a reference).
pub fn fill_from_neighbours(
    shape: GridShape,
    reference: &[Option<[f64; 3]>],
    current: &[Option<[f64; 3]>],
) -> Vec<Option<[f64; 3]>> {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    let mut out = current.to_vec();
    for r in 0..rows {
        for c in 0..cols {
            let k = r * cols + c;
            let (None, Some(rk)) = (current[k], reference[k]) else {
                continue;
            };
            let mut sum = Vector3::zeros();
            let mut count = 0.0;
            for dr in -1i64..=1 {
                for dc in -1i64..=1 {
                    let (rr, cc) = (r as i64 + dr, c as i64 + dc);
                    if (dr == 0 && dc == 0) || rr < 0 || cc < 0 || rr >= rows as i64 || cc >= cols as i64 {
                        continue;
                    }
                    let j = rr as usize * cols + cc as usize;
                    if let (Some(p), Some(q)) = (current[j], reference[j]) {
                        sum += Vector3::from(p) - Vector3::from(q);
                        count += 1.0;
                    }
                }
            }
            if count > 0.0 {
                let p = Point3::from(rk) + sum / count;
                out[k] = Some([p.x, p.y, p.z]);
            }
        }
    }
    out
}
