//! Pseudo-labels for adapting the localizer to a user's own sensor from an unlabelled recording
//! (`gelstereo adapt`, `docs/localization.md` "Adapting to your sensor").
//!
//! The shipped model runs over the recording; a marker becomes a training label only when three
//! independent checks agree:
//! 1. the network is sure of it (confidence >= [`PseudoLabelConfig::min_confidence`]);
//! 2. it is a member of the view's marker lattice ([`gelstereo_markers::lattice`]: on equally spaced
//!    lines in two directions, in a patch of members), which a false find on texture, glare or the
//!    housing almost never is;
//! 3. it is there in the neighbouring frames too, within [`PseudoLabelConfig::track_radius_frac`] x
//!    the pitch (markers move little from one frame to the next; a flicker does not persist).
//!
//! Everything else the network found, however unsure (the rest of its accepted markers and its
//! second tier), and every confident marker of a neighbouring frame with no candidate here (a marker
//! the network may have missed), is marked *ignore*: the trainer neither rewards nor penalises a
//! detection there, so the adapted network is not taught false negatives. So is everything outside
//! the labels' convex hull grown by half a pitch (border strips and corners, where markers fade and
//! the default may see none). A view whose labels are fewer than
//! [`PseudoLabelConfig::min_frame_fraction`] x the recording's median (a frame the default struggled
//! with as a whole), or more than the grid holds, is left out.
//!
//! Frames are cut into blocks of [`PseudoLabelConfig::holdout_block`] consecutive frames and every
//! [`PseudoLabelConfig::holdout_every`]-th block is held out (the `test` split): whole blocks, so that
//! a held-out frame is not the near-copy of a training frame beside it.
//!
//! The output is a dataset in the layout `train/` reads (the simulator's, `docs/training.md`):
//!
//! ```text
//! OUT/dataset.json                      generator gelstereo-adapt, source, configuration, counts
//! OUT/{train,test}/exp_0000/left/NNNNNN.png       (right/ for stereo sources), NNNNNN = frame number
//! OUT/{train,test}/exp_0000/ignore_left/NNNNNN.png  8-bit mask, 255 = ignore
//! OUT/{train,test}/exp_0000/markers.csv           the docs/design.md columns + visible_left,
//!                                                 visible_right, in_contact; row = col = -1 (not indexed)
//! ```

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use gelstereo_core::table::MARKER_COLUMNS;
use gelstereo_core::{Point2, TieredDetections};
use gelstereo_markers::Localizer;
use gelstereo_markers::lattice::{LatticeCheck, fit_lattice};
use opencv::core::{CV_8UC1, Mat, MatTraitConst, Point, Scalar, Vector};
use opencv::imgproc;

use gelstereo::file_err;
use gelstereo::source::FrameSource;
use gelstereo::{Error, Images, Result};

/// Name of the generator in `dataset.json`, with the crate version.
pub const GENERATOR: &str = concat!("gelstereo-adapt ", env!("CARGO_PKG_VERSION"));

/// How pseudo-labels are chosen. The defaults are what `gelstereo adapt` uses.
#[derive(Debug, Clone, PartialEq)]
pub struct PseudoLabelConfig {
    /// Smallest network confidence of a label (0.6: well above the 0.4 at which `marknet-mre` accepts
    /// a marker without the MRE, so labels are the network's sure finds).
    pub min_confidence: f32,
    /// A label must have a detection within this fraction of the pitch in every neighbouring frame
    /// (0.35: a marker moves a few px per frame at 25-30 fps even in a slide; half the pitch would
    /// reach the next marker's ring).
    pub track_radius_frac: f64,
    /// Radius of an ignore disc, as a fraction of the pitch (0.5: the marker's whole cell).
    pub ignore_radius_frac: f64,
    /// A view is left out when it has fewer labels than this fraction of the recording's median.
    pub min_frame_fraction: f64,
    /// Markers of the sensor (rows x cols) when known: a view with more labels is left out.
    pub grid_markers: Option<usize>,
    /// Consecutive frames per hold-out block.
    pub holdout_block: usize,
    /// Every this many blocks, one (the middle one of each run of blocks) is held out; 0: none.
    pub holdout_every: usize,
    /// At most this many frames are used, evenly spaced over the recording (bounds the time and the
    /// disk a long recording takes).
    pub max_frames: usize,
}

impl Default for PseudoLabelConfig {
    fn default() -> Self {
        Self {
            min_confidence: 0.6,
            track_radius_frac: 0.35,
            ignore_radius_frac: 0.5,
            min_frame_fraction: 0.5,
            grid_markers: None,
            holdout_block: 10,
            holdout_every: 5,
            max_frames: 600,
        }
    }
}

/// One view's detections, split the way pseudo-labelling needs them.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ViewCandidates {
    /// Confident lattice members: label candidates.
    pub confident: Vec<Point2>,
    /// Every accepted marker (the confident ones included).
    pub accepted: Vec<Point2>,
    /// Every candidate the network found but did not accept.
    pub second_tier: Vec<Point2>,
    /// The lattice's pitch, px; `None` when the accepted markers form no lattice.
    pub pitch_px: Option<f64>,
}

impl ViewCandidates {
    /// Splits a localizer's output (see the module documentation).
    pub fn new(found: &TieredDetections, config: &PseudoLabelConfig) -> Self {
        let accepted: Vec<Point2> = found.accepted.iter().map(|d| d.position).collect();
        // Original pixels: the spacing rule is about what the network resolves, and the default
        // already ran at its own scale; 1 px per px keeps only the rule's meaning for real markers.
        let fit = fit_lattice(&found.accepted, &LatticeCheck::default(), 1.0);
        let confident = found
            .accepted
            .iter()
            .zip(&fit.member)
            .filter(|(d, member)| **member && d.confidence >= config.min_confidence)
            .map(|(d, _)| d.position)
            .collect();
        Self {
            confident,
            accepted,
            second_tier: found.second_tier.iter().map(|d| d.position).collect(),
            pitch_px: fit.pitch_px.filter(|_| fit.is_lattice),
        }
    }
}

/// A view's pseudo-labels.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewLabels {
    /// Marker centres taught as markers, px.
    pub labels: Vec<Point2>,
    /// Centres of ignore discs, px.
    pub ignore: Vec<Point2>,
    /// Radius of the ignore discs, px.
    pub ignore_radius_px: f64,
    /// The labels' convex hull grown by half a pitch; outside it is ignored.
    pub hull: Vec<Point2>,
    /// The lattice's pitch, px.
    pub pitch_px: f64,
}

/// Why a view gave no pseudo-labels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum SkipReason {
    /// The frame could not be read.
    Unreadable,
    /// The default found no marker lattice.
    NoLattice,
    /// No readable neighbouring frame to check the markers against.
    NoNeighbour,
    /// Fewer labels than [`PseudoLabelConfig::min_frame_fraction`] x the median.
    FewLabels,
    /// More labels than the sensor's grid holds.
    TooManyLabels,
}

impl SkipReason {
    /// A short name for tables and `dataset.json`.
    pub fn as_str(self) -> &'static str {
        match self {
            SkipReason::Unreadable => "unreadable",
            SkipReason::NoLattice => "no_lattice",
            SkipReason::NoNeighbour => "no_neighbour",
            SkipReason::FewLabels => "few_labels",
            SkipReason::TooManyLabels => "too_many_labels",
        }
    }
}

fn near_any(p: Point2, points: &[Point2], radius: f64) -> bool {
    points.iter().any(|q| q.distance(p) <= radius)
}

/// A view's labels from its candidates and those of the same view in the neighbouring frames (the
/// frames just before and after; see the module documentation).
pub fn label_view(
    current: &ViewCandidates,
    neighbours: &[&ViewCandidates],
    config: &PseudoLabelConfig,
) -> std::result::Result<ViewLabels, SkipReason> {
    let pitch = current.pitch_px.ok_or(SkipReason::NoLattice)?;
    if neighbours.is_empty() {
        return Err(SkipReason::NoNeighbour);
    }
    let track_px = config.track_radius_frac * pitch;
    let (labels, dropped): (Vec<Point2>, Vec<Point2>) = current.confident.iter().partition(|&&p| {
        neighbours
            .iter()
            .all(|n| near_any(p, &n.accepted, track_px) || near_any(p, &n.second_tier, track_px))
    });
    let mut ignore: Vec<Point2> = dropped;
    ignore.extend(
        current
            .accepted
            .iter()
            .chain(&current.second_tier)
            .filter(|&&p| !near_any(p, &labels, track_px)),
    );
    // A marker the neighbours are sure of and this frame has no candidate for: missed here, perhaps.
    let here: Vec<Point2> = current
        .accepted
        .iter()
        .chain(&current.second_tier)
        .copied()
        .collect();
    for n in neighbours {
        ignore.extend(n.confident.iter().filter(|&&p| !near_any(p, &here, track_px)));
    }
    // An ignore disc on a label would hide the label's own cell.
    let keep_clear = config.ignore_radius_frac * pitch;
    ignore.retain(|&p| !near_any(p, &labels, keep_clear));
    ignore.sort_by(|a, b| a.y.total_cmp(&b.y).then(a.x.total_cmp(&b.x)));
    ignore.dedup_by(|a, b| a.distance(*b) < 0.5);
    let hull = grown_hull(&labels, 0.5 * pitch);
    Ok(ViewLabels {
        labels,
        ignore,
        ignore_radius_px: config.ignore_radius_frac * pitch,
        hull,
        pitch_px: pitch,
    })
}

/// The convex hull of `points` (Andrew's monotone chain), each vertex moved `grow_px` away from the
/// centroid.
fn grown_hull(points: &[Point2], grow_px: f64) -> Vec<Point2> {
    let mut pts: Vec<Point2> = points.to_vec();
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    pts.dedup_by(|a, b| a.x == b.x && a.y == b.y);
    if pts.len() < 3 {
        return pts;
    }
    let cross = |o: Point2, a: Point2, b: Point2| (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x);
    let mut hull: Vec<Point2> = Vec::with_capacity(2 * pts.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &Point2>> = if pass == 0 {
            Box::new(pts.iter())
        } else {
            Box::new(pts.iter().rev())
        };
        for &p in iter {
            while hull.len() >= start + 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0 {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    let n = hull.len() as f64;
    let cx = hull.iter().map(|p| p.x).sum::<f64>() / n;
    let cy = hull.iter().map(|p| p.y).sum::<f64>() / n;
    hull.iter()
        .map(|p| {
            let (dx, dy) = (p.x - cx, p.y - cy);
            let d = dx.hypot(dy).max(1e-9);
            Point2::new(p.x + dx / d * grow_px, p.y + dy / d * grow_px)
        })
        .collect()
}

/// The ignore mask of a view (8-bit, 255 = ignore): outside the hull, and the ignore discs.
pub fn ignore_mask(labels: &ViewLabels, width: i32, height: i32) -> Result<Mat> {
    let mut mask = Mat::new_rows_cols_with_default(height, width, CV_8UC1, Scalar::all(255.0))?;
    let px = |p: &Point2| Point::new(p.x.round() as i32, p.y.round() as i32);
    if labels.hull.len() >= 3 {
        let hull: Vector<Point> = labels.hull.iter().map(px).collect();
        imgproc::fill_convex_poly(&mut mask, &hull, Scalar::all(0.0), imgproc::LINE_8, 0)?;
    }
    let r = labels.ignore_radius_px.round().max(1.0) as i32;
    for p in &labels.ignore {
        imgproc::circle(&mut mask, px(p), r, Scalar::all(255.0), -1, imgproc::LINE_8, 0)?;
    }
    Ok(mask)
}

/// What pseudo-labelling produced.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PseudoLabelSummary {
    /// Frames of the source looked at (after the even spacing of [`PseudoLabelConfig::max_frames`]).
    pub frames_used: usize,
    /// Views per frame (1 mono, 2 stereo).
    pub views: usize,
    /// Labelled views in the training split, and their labels and ignore discs.
    pub train_views: usize,
    /// Labels in the training split.
    pub train_labels: usize,
    /// Ignore discs in the training split.
    pub train_ignored: usize,
    /// Labelled views held out (the `test` split) and their labels.
    pub heldout_views: usize,
    /// Labels in the held-out split.
    pub heldout_labels: usize,
    /// Detections the default accepted over all views used.
    pub accepted: usize,
    /// Source frame numbers held out (whole blocks, whether labelled or not).
    pub heldout_frames: Vec<usize>,
    /// Views left out, per reason.
    pub skipped: BTreeMap<&'static str, usize>,
    /// Median pitch of the labelled views, px.
    pub pitch_px: Option<f64>,
}

impl PseudoLabelSummary {
    /// `L labels in V training views (and I ignore discs), L labels in V held-out views; views left
    /// out: ...`, for a log line.
    pub fn counts_text(&self) -> String {
        format!(
            "{} labels in {} training views (and {} ignore discs), {} labels in {} held-out views; \
             views left out: {}",
            self.train_labels,
            self.train_views,
            self.train_ignored,
            self.heldout_labels,
            self.heldout_views,
            skipped_text(&self.skipped)
        )
    }
}

/// Whether the frame at position `k` of the frames used is held out.
pub fn held_out(k: usize, config: &PseudoLabelConfig) -> bool {
    config.holdout_every > 0
        && config.holdout_block > 0
        && (k / config.holdout_block) % config.holdout_every == config.holdout_every / 2
}

const VIEW_NAMES: [&str; 2] = ["left", "right"];

struct FrameRecord {
    index: usize,
    /// Per view: candidates and image size; `None` when unreadable.
    views: Option<Vec<(ViewCandidates, i32, i32)>>,
}

/// Runs `localizer` over `input` (a stereo recording, a folder of images or a video; `side_by_side`:
/// a stereo video) and writes the pseudo-label dataset into `out` (an existing, empty folder; see the
/// module documentation). Stops with an error when `stop` is set (checked per frame); `progress` is
/// called once per frame read.
pub fn write_pseudo_labels(
    input: &Path,
    side_by_side: bool,
    localizer: &mut dyn Localizer,
    config: &PseudoLabelConfig,
    out: &Path,
    stop: &AtomicBool,
    progress: &dyn Fn(usize, Option<usize>),
) -> Result<PseudoLabelSummary> {
    let mut source = FrameSource::open_path(input, side_by_side)?;
    let views = if source.is_stereo() { 2 } else { 1 };
    let total = source.len_hint();
    let step = total.map_or(1, |n| n.div_ceil(config.max_frames.max(1)).max(1));
    let staging = out.join("frames");
    std::fs::create_dir_all(&staging).map_err(file_err(&staging))?;
    let mut records: Vec<FrameRecord> = Vec::new();
    let mut seen = 0usize;
    while let Some(frame) = source.next_frame() {
        if stop.load(Ordering::SeqCst) {
            return Err(Error::Invalid("interrupted".into()));
        }
        seen += 1;
        progress(seen, total);
        if frame.index % step != 0 {
            continue;
        }
        if records.len() >= config.max_frames {
            break;
        }
        let index = frame.index;
        let images: Vec<Mat> = match frame.images {
            Ok(Images::Mono(m)) => vec![m],
            Ok(Images::Stereo(p)) => vec![p.left, p.right],
            Err(_) => {
                records.push(FrameRecord { index, views: None });
                continue;
            }
        };
        let mut per_view = Vec::with_capacity(images.len());
        for (v, image) in images.iter().enumerate() {
            let found = localizer
                .detect_tiered(image)
                .map_err(|e| Error::from(e).context(format!("{}: frame {index}", input.display())))?;
            let path = staging.join(format!("{index:06}_{}.png", VIEW_NAMES[v]));
            gelstereo_io::images::write_image(&path, image)?;
            per_view.push((ViewCandidates::new(&found, config), image.cols(), image.rows()));
        }
        records.push(FrameRecord {
            index,
            views: Some(per_view),
        });
    }
    if records.is_empty() {
        return Err(Error::Invalid(format!("{}: holds no frames", input.display())));
    }

    // Labels per frame and view.
    let mut summary = PseudoLabelSummary {
        frames_used: records.len(),
        views,
        ..Default::default()
    };
    let mut labelled: Vec<Vec<std::result::Result<ViewLabels, SkipReason>>> = Vec::new();
    for (k, rec) in records.iter().enumerate() {
        let Some(current) = &rec.views else {
            labelled.push(vec![Err(SkipReason::Unreadable); views]);
            continue;
        };
        let mut row = Vec::with_capacity(views);
        for (v, (cand, _, _)) in current.iter().enumerate() {
            summary.accepted += cand.accepted.len();
            // Neighbours in the same split only: a held-out block stays unseen by training labels.
            let neighbours: Vec<&ViewCandidates> = [k.checked_sub(1), Some(k + 1)]
                .into_iter()
                .flatten()
                .filter(|&j| held_out(j, config) == held_out(k, config))
                .filter_map(|j| records.get(j)?.views.as_ref()?.get(v).map(|c| &c.0))
                .collect();
            row.push(label_view(cand, &neighbours, config));
        }
        labelled.push(row);
    }
    let mut counts: Vec<usize> = labelled
        .iter()
        .flatten()
        .filter_map(|l| l.as_ref().ok().map(|l| l.labels.len()))
        .collect();
    counts.sort_unstable();
    let median = counts.get(counts.len() / 2).copied().unwrap_or(0);
    for l in labelled.iter_mut().flatten() {
        let n = match l {
            Ok(v) => v.labels.len(),
            Err(_) => continue,
        };
        if (n as f64) < config.min_frame_fraction * median as f64 || n == 0 {
            *l = Err(SkipReason::FewLabels);
        } else if config.grid_markers.is_some_and(|g| n > g) {
            *l = Err(SkipReason::TooManyLabels);
        }
    }

    // Write the splits.
    let mut pitches = Vec::new();
    let mut csv: [String; 2] = [marker_header(), marker_header()];
    for (k, (rec, row)) in records.iter().zip(&labelled).enumerate() {
        let test = held_out(k, config);
        if test {
            summary.heldout_frames.push(rec.index);
        }
        let split = usize::from(test);
        let exp = out.join(if test { "test" } else { "train" }).join("exp_0000");
        for (v, l) in row.iter().enumerate() {
            let l = match l {
                Ok(l) => l,
                Err(why) => {
                    *summary.skipped.entry(why.as_str()).or_insert(0) += 1;
                    continue;
                }
            };
            let Some(Some((_, w, h))) = rec.views.as_ref().map(|vs| vs.get(v)) else {
                continue;
            };
            let name = format!("{:06}.png", rec.index);
            let image_dir = exp.join(VIEW_NAMES[v]);
            std::fs::create_dir_all(&image_dir).map_err(file_err(&image_dir))?;
            let staged = staging.join(format!("{:06}_{}.png", rec.index, VIEW_NAMES[v]));
            let dest = image_dir.join(&name);
            std::fs::rename(&staged, &dest).map_err(file_err(&dest))?;
            let mask = ignore_mask(l, *w, *h)?;
            gelstereo_io::images::write_image(
                &exp.join(format!("ignore_{}", VIEW_NAMES[v])).join(&name),
                &mask,
            )?;
            for p in &l.labels {
                write_label(&mut csv[split], rec.index, v, *p);
            }
            pitches.push(l.pitch_px);
            if test {
                summary.heldout_views += 1;
                summary.heldout_labels += l.labels.len();
            } else {
                summary.train_views += 1;
                summary.train_labels += l.labels.len();
                summary.train_ignored += l.ignore.len();
            }
        }
    }
    std::fs::remove_dir_all(&staging).map_err(file_err(&staging))?;
    if summary.train_views == 0 {
        return Err(Error::Invalid(format!(
            "{}: no frame could be pseudo-labelled ({} frames; views left out: {}); the default finds no \
             marker lattice it is sure of in them",
            input.display(),
            records.len(),
            skipped_text(&summary.skipped)
        )));
    }
    for (split, text) in ["train", "test"].iter().zip(&csv) {
        let dir = out.join(split).join("exp_0000");
        if dir.is_dir() {
            let path = dir.join("markers.csv");
            std::fs::write(&path, text).map_err(file_err(&path))?;
        }
    }
    pitches.sort_by(f64::total_cmp);
    summary.pitch_px = pitches.get(pitches.len() / 2).copied();
    let manifest = dataset_json(input, config, &summary);
    let path = out.join("dataset.json");
    std::fs::write(&path, manifest).map_err(file_err(&path))?;
    Ok(summary)
}

/// `reason count, ...` of the views left out.
pub fn skipped_text(skipped: &BTreeMap<&'static str, usize>) -> String {
    if skipped.is_empty() {
        return "none".into();
    }
    skipped
        .iter()
        .map(|(k, n)| format!("{k} {n}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn marker_header() -> String {
    format!("{},visible_left,visible_right\n", MARKER_COLUMNS.join(","))
}

/// One label row: the docs/design.md columns (row = col = -1: pseudo-labels are not indexed;
/// `in_contact` 0) and the visibility flags of its view.
fn write_label(out: &mut String, frame: usize, view: usize, p: Point2) {
    let mut cells = vec![String::new(); MARKER_COLUMNS.len() + 2];
    let mut set = |column: &str, value: String| {
        if let Some(i) = MARKER_COLUMNS.iter().position(|c| *c == column) {
            cells[i] = value;
        }
    };
    set("frame", frame.to_string());
    set("row", "-1".into());
    set("col", "-1".into());
    let (x, y) = if view == 0 {
        ("x_left", "y_left")
    } else {
        ("x_right", "y_right")
    };
    set(x, format!("{:.3}", p.x));
    set(y, format!("{:.3}", p.y));
    set("in_contact", "0".into());
    let n = MARKER_COLUMNS.len();
    cells[n] = u8::from(view == 0).to_string();
    cells[n + 1] = u8::from(view == 1).to_string();
    let _ = writeln!(out, "{}", cells.join(","));
}

fn dataset_json(input: &Path, config: &PseudoLabelConfig, s: &PseudoLabelSummary) -> String {
    let json = serde_json::json!({
        "generator": GENERATOR,
        "source": input.display().to_string(),
        "views": s.views,
        "config": {
            "min_confidence": config.min_confidence,
            "track_radius_frac": config.track_radius_frac,
            "ignore_radius_frac": config.ignore_radius_frac,
            "min_frame_fraction": config.min_frame_fraction,
            "grid_markers": config.grid_markers,
            "holdout_block": config.holdout_block,
            "holdout_every": config.holdout_every,
            "max_frames": config.max_frames,
        },
        "pseudo_labels": {
            "frames_used": s.frames_used,
            "default_accepted": s.accepted,
            "train_views": s.train_views,
            "train_labels": s.train_labels,
            "train_ignored": s.train_ignored,
            "heldout_views": s.heldout_views,
            "heldout_labels": s.heldout_labels,
            "heldout_frames": s.heldout_frames,
            "skipped": s.skipped,
            "pitch_px": s.pitch_px,
        },
    });
    let mut text = serde_json::to_string_pretty(&json).unwrap_or_default();
    text.push('\n');
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_core::Detection;

    fn lattice(rows: usize, cols: usize, pitch: f64, shift: f64) -> Vec<Detection> {
        (0..rows)
            .flat_map(|r| {
                (0..cols).map(move |c| Detection {
                    position: Point2::new(20.0 + c as f64 * pitch + shift, 20.0 + r as f64 * pitch),
                    confidence: 0.95,
                })
            })
            .collect()
    }

    fn found(accepted: Vec<Detection>) -> TieredDetections {
        TieredDetections {
            accepted,
            second_tier: Vec::new(),
        }
    }

    #[test]
    fn markers_off_the_lattice_are_no_labels_but_ignored() {
        let cfg = PseudoLabelConfig::default();
        let mut here = lattice(8, 10, 30.0, 0.0);
        // Confident finds that sit on no lattice line: in the middle of a cell, and far outside.
        // 4 px beside a cell's centre (the centre itself is the midpoint of both diagonals, on two
        // lines), more than half a pitch from every marker; and one far outside.
        let off = [
            Point2::new(20.0 + 4.5 * 30.0 + 4.0, 20.0 + 3.5 * 30.0),
            Point2::new(400.0, 330.0),
        ];
        for p in off {
            here.push(Detection {
                position: p,
                confidence: 0.99,
            });
        }
        let mut before = lattice(8, 10, 30.0, -1.0);
        let mut after = lattice(8, 10, 30.0, 1.0);
        // The same finds persist in the neighbours: time alone would keep them.
        for d in [&mut before, &mut after] {
            d.extend(off.iter().map(|&p| Detection {
                position: p,
                confidence: 0.99,
            }));
        }
        let c = ViewCandidates::new(&found(here), &cfg);
        let n = [
            ViewCandidates::new(&found(before), &cfg),
            ViewCandidates::new(&found(after), &cfg),
        ];
        let l = label_view(&c, &[&n[0], &n[1]], &cfg).expect("a lattice");
        assert_eq!(l.labels.len(), 80, "every lattice marker is a label");
        for p in off {
            assert!(
                !near_any(p, &l.labels, 1.0),
                "{p:?} is off the lattice but labelled"
            );
            assert!(near_any(p, &l.ignore, 1e-9), "{p:?} is not marked ignore");
        }
        assert!((l.pitch_px - 30.0).abs() < 1e-9);
    }

    #[test]
    fn a_marker_missing_in_a_neighbour_is_ignored_and_one_missing_here_too() {
        let cfg = PseudoLabelConfig::default();
        let here = lattice(6, 6, 25.0, 0.0);
        let mut before = lattice(6, 6, 25.0, 0.5);
        let flicker = before.remove(14).position; // seen here, not in the frame before
        let after = lattice(6, 6, 25.0, 0.5);
        let mut here_less = here.clone();
        let missed = here_less.remove(20).position; // seen in both neighbours, not here
        let c = ViewCandidates::new(&found(here_less), &cfg);
        let n0 = ViewCandidates::new(&found(before), &cfg);
        let n1 = ViewCandidates::new(&found(after), &cfg);
        let l = label_view(&c, &[&n0, &n1], &cfg).expect("a lattice");
        assert_eq!(l.labels.len(), 34);
        assert!(!near_any(flicker, &l.labels, 1.0) && near_any(flicker, &l.ignore, 1.0));
        assert!(
            near_any(missed, &l.ignore, 1.0),
            "a marker only the neighbours see is not ignored"
        );
    }

    #[test]
    fn no_lattice_and_no_neighbour_give_no_labels() {
        let cfg = PseudoLabelConfig::default();
        let scattered: Vec<Detection> = [(10.0, 10.0), (80.0, 13.0), (33.0, 71.0), (140.0, 90.0)]
            .iter()
            .map(|&(x, y)| Detection {
                position: Point2::new(x, y),
                confidence: 0.99,
            })
            .collect();
        let c = ViewCandidates::new(&found(scattered), &cfg);
        assert_eq!(label_view(&c, &[&c], &cfg), Err(SkipReason::NoLattice));
        let c = ViewCandidates::new(&found(lattice(5, 5, 20.0, 0.0)), &cfg);
        assert_eq!(label_view(&c, &[], &cfg), Err(SkipReason::NoNeighbour));
    }

    #[test]
    fn the_hull_encloses_the_labels_and_the_mask_ignores_outside_it() {
        let cfg = PseudoLabelConfig::default();
        let c = ViewCandidates::new(&found(lattice(4, 5, 30.0, 0.0)), &cfg);
        let l = label_view(&c, &[&c], &cfg).expect("a lattice");
        let mask = ignore_mask(&l, 200, 160).expect("mask");
        let at = |x: i32, y: i32| *mask.at_2d::<u8>(y, x).expect("pixel");
        assert_eq!(at(20, 20), 0, "a label's pixel is taught, not ignored");
        assert_eq!(at(65, 65), 0, "inside the lattice is taught");
        assert_eq!(at(199, 159), 255, "the corner outside the lattice is ignored");
    }

    #[test]
    fn held_out_blocks_are_whole_and_spread() {
        let cfg = PseudoLabelConfig::default();
        let held: Vec<usize> = (0..100).filter(|&k| held_out(k, &cfg)).collect();
        assert_eq!(held, (20..30).chain(70..80).collect::<Vec<_>>());
    }
}
