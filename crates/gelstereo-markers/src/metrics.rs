//! The paper's detection metrics, as docs/design.md "Metrics" defines them for gelstereo (one definition,
//! shared with the Python trainer):
//!
//! - A prediction is correct when it is matched one-to-one, nearest pairs first, to a visible
//!   ground-truth marker within `r = 0.25 x pitch_px`; `pitch_px` is estimated from the ground truth of
//!   the same image (median nearest-neighbour distance between its visible markers).
//! - precision = PT / (PT + PF), recall = PT / T, loss = D / PT with D the sum of squared distances
//!   (px^2 of the original image) of the correct predictions.
//! - Splits: `hard` = ground-truth markers the tuned blob baseline misses or places farther than r (i.e.
//!   that the same matching leaves unmatched for the blob detections); `easy` = the rest; `contact` =
//!   markers whose ground truth says in_contact (they are also easy or hard); `border` = markers whose
//!   centre lies within one pitch of the image's border (where dots are cut by it and a margin
//!   replaces the rest of the image). An unmatched prediction counts as PF towards the split(s) of its
//!   nearest visible ground-truth marker.
//! - `all` adds up every marker and prediction (a prediction in an image without visible markers counts
//!   only there).

use gelstereo_core::{Detection, Point2};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use serde::Serialize;

use crate::spacing::median_nearest_neighbour_px;
use crate::{Error, Result};

/// r as a fraction of the marker pitch.
pub const RADIUS_PITCH_FRACTION: f64 = 0.25;

/// One visible ground-truth marker of one view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GroundTruth {
    /// Its true position, px of the original image.
    pub position: Point2,
    /// Whether the ground truth says it is in contact with the object.
    pub in_contact: bool,
}

/// The match radius for an image from its ground truth: `0.25 x` median nearest-neighbour distance.
pub fn radius_from_ground_truth(gt: &[GroundTruth]) -> Option<f64> {
    let pts: Vec<Point2> = gt.iter().map(|g| g.position).collect();
    median_nearest_neighbour_px(&pts).map(|pitch| RADIUS_PITCH_FRACTION * pitch)
}

/// The result of one-to-one matching.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Matching {
    /// For each prediction, the ground-truth index it is matched to and the distance, px.
    pub prediction_match: Vec<Option<(usize, f64)>>,
    /// For each ground-truth marker, the matched prediction's index.
    pub ground_truth_match: Vec<Option<usize>>,
}

/// Matches `predictions` to `ground_truth` one-to-one, nearest pairs first, within `radius_px`
/// (inclusive). Ties are broken by prediction then ground-truth index, so the result is deterministic.
pub fn match_one_to_one(predictions: &[Point2], ground_truth: &[Point2], radius_px: f64) -> Result<Matching> {
    if !(radius_px.is_finite() && radius_px > 0.0) {
        return Err(Error::Metrics(format!(
            "match radius must be a positive number of px, found {radius_px}"
        )));
    }
    let mut out = Matching {
        prediction_match: vec![None; predictions.len()],
        ground_truth_match: vec![None; ground_truth.len()],
    };
    if predictions.is_empty() || ground_truth.is_empty() {
        return Ok(out);
    }
    let coords: Vec<[f64; 2]> = ground_truth.iter().map(|p| [p.x, p.y]).collect();
    let tree: ImmutableKdTree<f64, 2> = ImmutableKdTree::new_from_slice(&coords)
        .map_err(|e| Error::Metrics(format!("k-d tree of the ground truth: {e:?}")))?;
    let r2 = radius_px * radius_px;
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (i, p) in predictions.iter().enumerate() {
        // Exact distances decide; the tree only proposes neighbours (a slightly larger radius guards
        // against rounding in its squared distances).
        for r in tree
            .query(&[p.x, p.y])
            .within::<SquaredEuclidean<f64>>(r2 * (1.0 + 1e-9) + 1e-12)
            .execute()
        {
            let j = r.item as usize;
            let d = p.distance(ground_truth[j]);
            if d <= radius_px {
                pairs.push((d, i, j));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    for (d, i, j) in pairs {
        if out.prediction_match[i].is_none() && out.ground_truth_match[j].is_none() {
            out.prediction_match[i] = Some((j, d));
            out.ground_truth_match[j] = Some(i);
        }
    }
    Ok(out)
}

/// Counts of one split, accumulated over images.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct SplitCounts {
    /// T: ground-truth markers in the split.
    pub markers: usize,
    /// PT: correct predictions (matched to a marker of the split).
    pub correct: usize,
    /// PF: wrong predictions attributed to the split.
    pub wrong: usize,
    /// D: sum of squared distances of the correct predictions, px^2.
    pub sq_dist_sum_px2: f64,
}

impl SplitCounts {
    /// PT / (PT + PF); `None` without predictions.
    pub fn precision(&self) -> Option<f64> {
        let n = self.correct + self.wrong;
        (n > 0).then(|| self.correct as f64 / n as f64)
    }

    /// PT / T; `None` without markers.
    pub fn recall(&self) -> Option<f64> {
        (self.markers > 0).then(|| self.correct as f64 / self.markers as f64)
    }

    /// D / PT, px^2; `None` without correct predictions.
    pub fn loss_px2(&self) -> Option<f64> {
        (self.correct > 0).then(|| self.sq_dist_sum_px2 / self.correct as f64)
    }

    fn add(&mut self, other: &SplitCounts) {
        self.markers += other.markers;
        self.correct += other.correct;
        self.wrong += other.wrong;
        self.sq_dist_sum_px2 += other.sq_dist_sum_px2;
    }
}

/// The split names, in table order.
pub const SPLITS: [&str; 5] = ["easy", "hard", "contact", "border", "all"];

/// Counts of every split for one method.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct SplitTable {
    /// Markers the blob baseline finds within r.
    pub easy: SplitCounts,
    /// Markers the blob baseline misses or places farther than r.
    pub hard: SplitCounts,
    /// Markers in contact (ground truth).
    pub contact: SplitCounts,
    /// Markers within one pitch of the image border.
    pub border: SplitCounts,
    /// Everything.
    pub all: SplitCounts,
}

impl SplitTable {
    /// The split called `name` (one of [`SPLITS`]).
    pub fn get(&self, name: &str) -> Option<&SplitCounts> {
        match name {
            "easy" => Some(&self.easy),
            "hard" => Some(&self.hard),
            "contact" => Some(&self.contact),
            "border" => Some(&self.border),
            "all" => Some(&self.all),
            _ => None,
        }
    }

    /// Adds another table's counts (e.g. another image's).
    pub fn add(&mut self, other: &SplitTable) {
        self.easy.add(&other.easy);
        self.hard.add(&other.hard);
        self.contact.add(&other.contact);
        self.border.add(&other.border);
        self.all.add(&other.all);
    }
}

/// Which ground-truth markers of one view are hard: those the blob detections leave unmatched.
pub fn hard_markers(blob: &[Detection], gt: &[GroundTruth], radius_px: f64) -> Result<Vec<bool>> {
    let pred: Vec<Point2> = blob.iter().map(|d| d.position).collect();
    let gts: Vec<Point2> = gt.iter().map(|g| g.position).collect();
    Ok(match_one_to_one(&pred, &gts, radius_px)?
        .ground_truth_match
        .iter()
        .map(Option::is_none)
        .collect())
}

/// Which ground-truth markers of a `width x height` view lie within one pitch (`radius_px /`
/// [`RADIUS_PITCH_FRACTION`]) of its border; the image spans -0.5..width-0.5 (pixel-centre convention).
pub fn border_markers(gt: &[GroundTruth], width: u32, height: u32, radius_px: f64) -> Vec<bool> {
    let pitch = radius_px / RADIUS_PITCH_FRACTION;
    let (w, h) = (f64::from(width), f64::from(height));
    gt.iter()
        .map(|g| {
            let p = g.position;
            (p.x + 0.5).min(p.y + 0.5).min(w - 0.5 - p.x).min(h - 0.5 - p.y) < pitch
        })
        .collect()
}

/// The splits of one view's ground-truth markers that the ground truth alone does not give: which
/// are hard ([`hard_markers`]), which lie near the border ([`border_markers`]), and the match radius.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewSplits {
    /// Per ground-truth marker: missed by the blob baseline.
    pub hard: Vec<bool>,
    /// Per ground-truth marker: within one pitch of the image border.
    pub border: Vec<bool>,
    /// r, px.
    pub radius_px: f64,
}

/// Scores one view's `predictions` against its visible ground truth, split by `splits` (of the
/// same view).
pub fn score_view(predictions: &[Detection], gt: &[GroundTruth], splits: &ViewSplits) -> Result<SplitTable> {
    let ViewSplits {
        hard,
        border,
        radius_px,
    } = splits;
    for (name, mask) in [("hard", hard), ("border", border)] {
        if mask.len() != gt.len() {
            return Err(Error::Metrics(format!(
                "{name} mask has {} entries for {} ground-truth markers",
                mask.len(),
                gt.len()
            )));
        }
    }
    let radius_px = *radius_px;
    let pred: Vec<Point2> = predictions.iter().map(|d| d.position).collect();
    let gts: Vec<Point2> = gt.iter().map(|g| g.position).collect();
    let m = match_one_to_one(&pred, &gts, radius_px)?;
    let mut t = SplitTable::default();
    let splits_of = |j: usize| -> [bool; 4] { [!hard[j], hard[j], gt[j].in_contact, border[j]] };
    for j in 0..gt.len() {
        for (on, s) in splits_of(j)
            .into_iter()
            .zip([&mut t.easy, &mut t.hard, &mut t.contact, &mut t.border])
        {
            if on {
                s.markers += 1;
            }
        }
        t.all.markers += 1;
    }
    let tree: Option<ImmutableKdTree<f64, 2>> = if gts.is_empty() {
        None
    } else {
        let coords: Vec<[f64; 2]> = gts.iter().map(|p| [p.x, p.y]).collect();
        ImmutableKdTree::new_from_slice(&coords).ok()
    };
    for (i, p) in pred.iter().enumerate() {
        let (j, correct, d) = match m.prediction_match[i] {
            Some((j, d)) => (Some(j), true, d),
            None => {
                let nearest = tree.as_ref().map(|t| {
                    t.query(&[p.x, p.y])
                        .nearest_one::<SquaredEuclidean<f64>>()
                        .execute()
                        .item as usize
                });
                (nearest, false, 0.0)
            }
        };
        let count = |s: &mut SplitCounts| {
            if correct {
                s.correct += 1;
                s.sq_dist_sum_px2 += d * d;
            } else {
                s.wrong += 1;
            }
        };
        count(&mut t.all);
        if let Some(j) = j {
            for (on, s) in
                splits_of(j)
                    .into_iter()
                    .zip([&mut t.easy, &mut t.hard, &mut t.contact, &mut t.border])
            {
                if on {
                    count(s);
                }
            }
        }
    }
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(x: f64, y: f64) -> Point2 {
        Point2::new(x, y)
    }

    fn det(x: f64, y: f64) -> Detection {
        Detection {
            position: p(x, y),
            confidence: 1.0,
        }
    }

    fn gt(x: f64, y: f64, in_contact: bool) -> GroundTruth {
        GroundTruth {
            position: p(x, y),
            in_contact,
        }
    }

    #[test]
    fn nearest_pairs_are_matched_first_and_one_to_one() {
        // Prediction 0 is 1.0 from gt 0 and 0.5 from gt 1; prediction 1 is 0.6 from gt 1.
        // Nearest first: (pred 0, gt 1, 0.5), then pred 1 cannot take gt 1, and gt 0 is 2.5 from it.
        let preds = [p(1.0, 0.0), p(2.1, 0.0)];
        let gts = [p(0.0, 0.0), p(1.5, 0.0)];
        let m = match_one_to_one(&preds, &gts, 2.0).unwrap();
        assert_eq!(m.prediction_match[0], Some((1, 0.5)));
        assert_eq!(m.prediction_match[1], None);
        assert_eq!(m.ground_truth_match, [None, Some(0)]);
        // The radius is inclusive.
        let m = match_one_to_one(&[p(3.0, 4.0)], &[p(0.0, 0.0)], 5.0).unwrap();
        assert!(m.prediction_match[0].is_some());
        assert!(match_one_to_one(&preds, &gts, 0.0).is_err());
    }

    #[test]
    fn splits_precision_recall_and_loss_by_hand() {
        // Four markers on a pitch-10 line; the blob baseline finds 0 and 1, so 2 and 3 are hard;
        // 3 is in contact.
        let gts = [
            gt(0.0, 0.0, false),
            gt(10.0, 0.0, false),
            gt(20.0, 0.0, false),
            gt(30.0, 0.0, true),
        ];
        let r = radius_from_ground_truth(&gts).unwrap();
        assert_eq!(r, 2.5);
        let hard = hard_markers(&[det(0.5, 0.0), det(10.0, 1.0), det(23.0, 0.0)], &gts, r).unwrap();
        assert_eq!(hard, [false, false, true, true]);
        // Predictions: 1 px off marker 0, 2 px off marker 3, a duplicate near marker 3, one far off
        // near marker 1.
        let preds = [det(1.0, 0.0), det(30.0, 2.0), det(29.0, -1.8), det(14.0, 0.0)];
        let splits = ViewSplits {
            hard,
            border: vec![false; 4],
            radius_px: r,
        };
        let t = score_view(&preds, &gts, &splits).unwrap();
        assert_eq!(
            t.easy,
            SplitCounts {
                markers: 2,
                correct: 1,
                wrong: 1,
                sq_dist_sum_px2: 1.0
            }
        );
        // (30, 2) is 2.0 px from marker 3, nearer than (29, -1.8) at 2.06 px: it is the match.
        let d2 = 4.0;
        assert_eq!((t.hard.markers, t.hard.correct, t.hard.wrong), (2, 1, 1));
        assert!((t.hard.sq_dist_sum_px2 - d2).abs() < 1e-9);
        assert_eq!((t.contact.markers, t.contact.correct, t.contact.wrong), (1, 1, 1));
        assert_eq!((t.all.markers, t.all.correct, t.all.wrong), (4, 2, 2));
        assert_eq!(t.easy.precision(), Some(0.5));
        assert_eq!(t.hard.recall(), Some(0.5));
        assert_eq!(t.easy.loss_px2(), Some(1.0));
        assert_eq!(SplitCounts::default().precision(), None);
        assert_eq!(t.border, SplitCounts::default());
    }

    #[test]
    fn border_markers_lie_within_one_pitch_of_an_edge_and_phantoms_there_count_against_them() {
        // A pitch-10 row across a 45 x 60 image: x = 5, 15, 25, 35 at y = 30. The image spans
        // -0.5..44.5, so 5 (5.5 from the left edge) and 35 (9.5 from the right) are near the border and
        // 15 and 25 (15.5 and 19.5 away) are not; y = 30 is 30.5 from the top.
        let gts = [
            gt(5.0, 30.0, false),
            gt(15.0, 30.0, false),
            gt(25.0, 30.0, false),
            gt(35.0, 30.0, false),
        ];
        let r = radius_from_ground_truth(&gts).unwrap();
        let border = border_markers(&gts, 45, 60, r);
        assert_eq!(border, [true, false, false, true]);
        // Found: 5 (pulled 2 px onto the edge, still within r), 15, 25; a phantom on the right edge
        // nearest 35, and 35 itself missed.
        let preds = [det(3.0, 30.0), det(15.0, 30.0), det(25.0, 30.0), det(44.0, 30.0)];
        let splits = ViewSplits {
            hard: vec![false; 4],
            border,
            radius_px: r,
        };
        let t = score_view(&preds, &gts, &splits).unwrap();
        assert_eq!((t.border.markers, t.border.correct, t.border.wrong), (2, 1, 1));
        assert_eq!(t.border.loss_px2(), Some(4.0));
        assert_eq!((t.all.markers, t.all.correct, t.all.wrong), (4, 3, 1));
        // An image too small for any marker to be a pitch away from every edge: all are near it.
        assert!(border_markers(&gts, 20, 20, r).iter().all(|&b| b));
    }
}
