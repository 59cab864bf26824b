//! Reconstruction metrics against a simulated recording's ground truth (docs/design.md "Metrics"):
//! 3-D RMSE over the reconstructed markers, coverage = reconstructed / visible in both views, wrong
//! pairs = pairs whose right-view point is farther than r from the marker's own, and grid-index
//! consistency. r = 0.25 x the marker pitch in pixels of each view.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use gelstereo_core::{CsvTable, GridIndex, MarkerRecord, Point2, StereoPair, View};

use crate::Result;
use crate::lattice::IndexedView;
use crate::reconstruct::FrameReconstruction;

/// Ground truth of one marker in one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthMarker {
    /// Left view position, px, when the marker is visible there.
    pub left_px: Option<Point2>,
    /// Right view position, px, when visible there.
    pub right_px: Option<Point2>,
    /// 3-D position in the left camera frame, mm.
    pub position_mm: Option<[f64; 3]>,
    /// Whether the marker is in contact with the indenter.
    pub in_contact: bool,
}

/// A simulated recording's ground truth (`markers.csv` with the simulator's `visible_left`,
/// `visible_right`, `in_contact` columns, and `frames.csv`).
#[derive(Debug, Clone, Default)]
pub struct GroundTruth {
    /// Per frame, per marker.
    pub frames: BTreeMap<u32, BTreeMap<GridIndex, TruthMarker>>,
    /// Per frame, whether anything touches the gel.
    pub contact: BTreeMap<u32, bool>,
}

impl GroundTruth {
    /// Reads `dir/markers.csv` and, if present, `dir/frames.csv`.
    pub fn read(dir: &Path) -> Result<Self> {
        let table = CsvTable::read(&dir.join("markers.csv"))?;
        table.require(&["visible_left", "visible_right", "in_contact"])?;
        let mut frames: BTreeMap<u32, BTreeMap<GridIndex, TruthMarker>> = BTreeMap::new();
        for row in 0..table.len() {
            let rec = MarkerRecord::from_table(&table, row)?;
            let flag = |c: &str| -> Result<bool> { Ok(table.value::<u8>(row, c, "0 or 1")? == 1) };
            let (vis_left, vis_right) = (flag("visible_left")?, flag("visible_right")?);
            let m = TruthMarker {
                left_px: rec.left_px.filter(|_| vis_left),
                right_px: rec.right_px.filter(|_| vis_right),
                position_mm: rec.position_mm,
                in_contact: flag("in_contact")?,
            };
            frames.entry(rec.frame).or_default().insert(rec.index, m);
        }
        let mut contact = BTreeMap::new();
        let fpath = dir.join("frames.csv");
        if fpath.exists() {
            let ft = CsvTable::read(&fpath)?;
            for row in 0..ft.len() {
                let frame: u32 = ft.value(row, "frame", "a frame number")?;
                let c: u8 = ft.value(row, "contact", "0 or 1")?;
                contact.insert(frame, c == 1);
            }
        }
        Ok(Self { frames, contact })
    }
}

/// Counts behind the metrics of one group of markers.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Counts {
    /// Ground-truth markers visible in the left view.
    pub visible_left: usize,
    /// Left detections that are true markers (within r of one, matched one-to-one).
    pub detected_left: usize,
    /// Of those, given their true index.
    pub index_correct: usize,
    /// Left detections given a wrong index (true markers with another's index, and spurious
    /// detections that received one).
    pub index_wrong: usize,
    /// Ground-truth markers visible in both views.
    pub visible_both: usize,
    /// Ground-truth markers the localizer found in both views (a true detection within r in each).
    pub detected_both: usize,
    /// Reconstructed markers among those.
    pub reconstructed_of_detected_both: usize,
    /// Markers with a 3-D position.
    pub reconstructed: usize,
    /// Reconstructed markers that are visible in both views.
    pub reconstructed_of_visible_both: usize,
    /// Reconstructed markers whose right-view point is farther than r from the marker's own.
    pub wrong_pairs: usize,
    /// Sum of squared 3-D errors, mm².
    pub sq_error_mm2: f64,
    /// Largest 3-D error, mm.
    pub max_error_mm: f64,
}

fn ratio(a: usize, b: usize) -> Option<f64> {
    (b > 0).then(|| a as f64 / b as f64)
}

impl Counts {
    /// Fraction of true left detections given their true index.
    pub fn index_consistency(&self) -> Option<f64> {
        ratio(self.index_correct, self.detected_left)
    }

    /// Reconstructed / visible in both views.
    pub fn coverage(&self) -> Option<f64> {
        ratio(self.reconstructed_of_visible_both, self.visible_both)
    }

    /// Reconstructed / found by the localizer in both views: the coverage of indexing, pairing
    /// and triangulation alone.
    pub fn matching_coverage(&self) -> Option<f64> {
        ratio(self.reconstructed_of_detected_both, self.detected_both)
    }

    /// Wrong pairs / reconstructed.
    pub fn wrong_pair_rate(&self) -> Option<f64> {
        ratio(self.wrong_pairs, self.reconstructed)
    }

    /// 3-D RMSE over the reconstructed markers, mm.
    pub fn rmse_mm(&self) -> Option<f64> {
        (self.reconstructed > 0).then(|| (self.sq_error_mm2 / self.reconstructed as f64).sqrt())
    }
}

/// Metrics of a recording: all markers, markers of contact frames, and markers in contact.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Evaluation {
    /// Frames evaluated.
    pub frames: usize,
    /// All markers.
    pub all: Counts,
    /// Markers of frames with contact.
    pub contact_frames: Counts,
    /// Markers the ground truth says are in contact.
    pub in_contact_markers: Counts,
}

/// The true index of every detection of `view`: the nearest visible ground-truth marker within
/// `r_px`, matched one-to-one nearest pairs first; `None` for spurious detections.
fn true_indices(
    view: &IndexedView,
    gt: &BTreeMap<GridIndex, TruthMarker>,
    r_px: f64,
    side: View,
) -> Vec<Option<GridIndex>> {
    let mut cand: Vec<(f64, usize, GridIndex)> = Vec::new();
    let truth: Vec<(GridIndex, Point2)> = gt
        .iter()
        .filter_map(|(i, t)| {
            match side {
                View::Left => t.left_px,
                View::Right => t.right_px,
            }
            .map(|p| (*i, p))
        })
        .collect();
    for d in 0..view.detection_count() {
        let Some(p) = view.detection_position(d) else {
            continue;
        };
        for &(idx, q) in &truth {
            let dist = p.distance(q);
            if dist <= r_px {
                cand.push((dist, d, idx));
            }
        }
    }
    cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut out = vec![None; view.detection_count()];
    let mut used = BTreeSet::new();
    for (_, d, idx) in cand {
        if out[d].is_none() && used.insert(idx) {
            out[d] = Some(idx);
        }
    }
    out
}

impl Evaluation {
    /// Adds frame `frame` of `truth` reconstructed as `rec`, with r = `r_px` per view.
    pub fn add_frame(
        &mut self,
        truth: &GroundTruth,
        frame: u32,
        rec: &FrameReconstruction,
        r_px: &StereoPair<f64>,
    ) {
        let empty = BTreeMap::new();
        let gt = truth.frames.get(&frame).unwrap_or(&empty);
        let contact_frame = truth.contact.get(&frame).copied().unwrap_or(false);
        self.frames += 1;
        let mut add = |in_contact: bool, f: &dyn Fn(&mut Counts)| {
            f(&mut self.all);
            if contact_frame {
                f(&mut self.contact_frames);
            }
            if in_contact {
                f(&mut self.in_contact_markers);
            }
        };
        let left = &rec.matched.left;
        let left_truth = true_indices(left, gt, r_px.left, View::Left);
        // Markers the localizer found in both views (a true detection within r in each).
        let found_right: BTreeSet<GridIndex> = true_indices(&rec.matched.right, gt, r_px.right, View::Right)
            .into_iter()
            .flatten()
            .collect();
        let found_both: BTreeSet<GridIndex> = left_truth
            .iter()
            .flatten()
            .filter(|i| found_right.contains(i))
            .copied()
            .collect();
        for (d, t) in left_truth.into_iter().enumerate() {
            let in_contact = t.and_then(|t| gt.get(&t)).is_some_and(|m| m.in_contact);
            match (t, left.index_of(d)) {
                (Some(t), Some(g)) => add(in_contact, &|c| {
                    c.detected_left += 1;
                    if t == g {
                        c.index_correct += 1;
                    } else {
                        c.index_wrong += 1;
                    }
                }),
                (Some(_), None) => add(in_contact, &|c| c.detected_left += 1),
                (None, Some(_)) => add(false, &|c| c.index_wrong += 1),
                (None, None) => {}
            }
        }
        for m in &rec.markers {
            let t = gt.get(&m.index);
            let in_contact = t.is_some_and(|t| t.in_contact);
            let (t_left, t_right) = (t.and_then(|t| t.left_px), t.and_then(|t| t.right_px));
            let both = t_left.is_some() && t_right.is_some();
            if t_left.is_some() {
                add(in_contact, &|c| c.visible_left += 1);
            }
            if both {
                add(in_contact, &|c| c.visible_both += 1);
            }
            let detected_both = found_both.contains(&m.index);
            if detected_both {
                add(in_contact, &|c| c.detected_both += 1);
            }
            let (Some(pos), Some(right)) = (m.position_mm, m.right_px) else {
                continue;
            };
            // docs/design.md: a pair is wrong when its right-view point is farther than r from the
            // marker's own (a misplaced left point shows in the index consistency instead).
            let pair_ok = t_right.is_some_and(|q| right.distance(q) <= r_px.right);
            let err = t.and_then(|t| t.position_mm).map(|g| {
                ((pos[0] - g[0]).powi(2) + (pos[1] - g[1]).powi(2) + (pos[2] - g[2]).powi(2)).sqrt()
            });
            add(in_contact, &|c| {
                c.reconstructed += 1;
                if both {
                    c.reconstructed_of_visible_both += 1;
                }
                if detected_both {
                    c.reconstructed_of_detected_both += 1;
                }
                if !pair_ok {
                    c.wrong_pairs += 1;
                }
                if let Some(e) = err {
                    c.sq_error_mm2 += e * e;
                    c.max_error_mm = c.max_error_mm.max(e);
                }
            });
        }
    }

    /// Sums two evaluations (e.g. of several recordings).
    pub fn merge(&mut self, other: &Evaluation) {
        self.frames += other.frames;
        for (a, b) in [
            (&mut self.all, &other.all),
            (&mut self.contact_frames, &other.contact_frames),
            (&mut self.in_contact_markers, &other.in_contact_markers),
        ] {
            a.visible_left += b.visible_left;
            a.detected_left += b.detected_left;
            a.index_correct += b.index_correct;
            a.index_wrong += b.index_wrong;
            a.visible_both += b.visible_both;
            a.reconstructed += b.reconstructed;
            a.reconstructed_of_visible_both += b.reconstructed_of_visible_both;
            a.detected_both += b.detected_both;
            a.reconstructed_of_detected_both += b.reconstructed_of_detected_both;
            a.wrong_pairs += b.wrong_pairs;
            a.sq_error_mm2 += b.sq_error_mm2;
            a.max_error_mm = a.max_error_mm.max(b.max_error_mm);
        }
    }
}
