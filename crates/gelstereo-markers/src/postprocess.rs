//! From Marknet's raw output to markers (paper Sec. II-B, `docs/model-contract.md`; the reference
//! implementation is `train/gelstereo_train/postprocess.py`, and the fixtures it writes check this one):
//!
//! 1. decode every slot (`x_in = (sigmoid(tx) + gx) * stride`, `x = x_in * W / input_width - 0.5`, likewise
//!    y, `c = sigmoid(tc)`) and keep the candidates with c > `conf_low`, in flat order
//!    `(gy * Gx + gx) * m + k`;
//! 2. `pitch_px` = median nearest-neighbour distance between candidates with c > `conf_keep` (all
//!    candidates when fewer than two are that confident; undefined with fewer than two);
//! 3. de-duplicate: visit in descending confidence (ties: flat order), drop a candidate closer than
//!    `dedup_radius_frac x pitch_px` to one already kept;
//! 4. `marknet`: the kept candidates with c > `conf_marknet_only`. `marknet-mre`: those with
//!    c > `conf_keep`, plus each one with c <= `conf_keep` whose MRE score is > `accept`. Its feature:
//!    the 10 smallest distances to the OTHER kept candidates, ascending, divided by `pitch_px` (missing
//!    ones, or all when the pitch is undefined, = 4.0), then c.

use gelstereo_core::{Detection, Point2, TieredDetections};
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::lattice::LatticeCheck;
use crate::spacing::{median_finite, median_nearest_neighbour_px, nearest_neighbour_distances};

/// Length of an MRE feature vector: 10 neighbour distances + the confidence.
pub const MRE_FEATURES: usize = 11;
/// Neighbour distances in an MRE feature vector.
pub const MRE_NEIGHBOURS: usize = 10;

/// Value of a missing neighbour distance in an MRE feature (fewer than 10 other candidates), pitches.
pub const MISSING_DISTANCE_PITCH: f32 = 4.0;

/// Post-processing thresholds. Defaults are the paper's (Sec. II-B, III-B); a model's metadata may
/// override them (`docs/model-contract.md`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PostProcess {
    /// Candidates above this confidence are markers without further check (paper: 0.4).
    pub conf_keep: f32,
    /// Candidates at or below this confidence are discarded (paper: 0.1).
    pub conf_low: f32,
    /// Threshold of the Marknet-only baseline (paper: 0.2).
    pub conf_marknet_only: f32,
    /// De-duplication radius as a fraction of the marker pitch. Default 0.3 (the trainer's): below half
    /// the smallest compressed pitch seen in simulated contact, so two real markers are never merged.
    pub dedup_radius_frac: f64,
    /// MRE acceptance threshold (paper: 0.99).
    pub accept: f32,
    /// The lattice check of the output and of the pitch that steers the input layout
    /// ([`crate::lattice`]); `None`: the contract's steps alone (what the fixtures of a random network
    /// check).
    pub lattice: Option<LatticeCheck>,
}

impl Default for PostProcess {
    fn default() -> Self {
        Self {
            conf_keep: 0.4,
            conf_low: 0.1,
            conf_marknet_only: 0.2,
            dedup_radius_frac: 0.3,
            accept: 0.99,
            lattice: Some(LatticeCheck::default()),
        }
    }
}

/// Shape of Marknet's raw output for one image, and how its input maps to the original image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DecodeGeometry {
    /// Grid cells along y.
    pub grid_y: usize,
    /// Grid cells along x.
    pub grid_x: usize,
    /// Candidates per cell.
    pub candidates: usize,
    /// Input pixels per cell.
    pub stride: f64,
    /// Original pixels per input pixel along x (W / input_width).
    pub scale_x: f64,
    /// Original pixels per input pixel along y (H / input_height).
    pub scale_y: f64,
    /// Input pixels left of the image's first column (0 unless the image was padded, [`crate::layout::InputFit::Pad`]).
    pub offset_x: f64,
    /// Input pixels above the image's first row.
    pub offset_y: f64,
}

impl DecodeGeometry {
    /// Number of f32 values of one image's raw output (`Gy * Gx * m * 3`).
    pub fn values_per_image(&self) -> usize {
        self.grid_y * self.grid_x * self.candidates * 3
    }
}

/// The logistic function, in f32 as the network computes it.
#[inline]
pub fn sigmoid(v: f32) -> f32 {
    1.0 / (1.0 + (-v).exp())
}

/// Decodes one image's raw output (`[Gy, Gx, m, 3]` logits, row-major) into the candidates with
/// c > `min_confidence`, in original pixels:
/// `x_in = (sigmoid(tx) + gx) * stride`, `x = (x_in - offset_x) * scale_x - 0.5` (likewise y),
/// `c = sigmoid(tc)`.
/// Returns an empty list if `raw` is shorter than the geometry says.
pub fn decode(raw: &[f32], geometry: &DecodeGeometry, min_confidence: f32) -> Vec<Detection> {
    let g = geometry;
    let mut out = Vec::new();
    if raw.len() < g.values_per_image() {
        return out;
    }
    let cell_values = g.candidates * 3;
    // Logits below this cannot pass `c > min_confidence` (the sigmoid increases; the margin of 1e-3
    // in logit covers the f32 rounding of the sigmoid and the logarithm many times over), so most
    // cells skip the exponential; the test itself stays the exact one below.
    let skip_below = if min_confidence > 0.0 && min_confidence < 1.0 {
        (min_confidence / (1.0 - min_confidence)).ln() - 1e-3
    } else {
        f32::NEG_INFINITY
    };
    for gy in 0..g.grid_y {
        for gx in 0..g.grid_x {
            let base = (gy * g.grid_x + gx) * cell_values;
            for slot in raw[base..base + cell_values].chunks_exact(3) {
                if slot[2] < skip_below {
                    continue;
                }
                let c = sigmoid(slot[2]);
                // NaN (a broken model) is dropped too: it must not inject non-finite candidates.
                if c.is_nan() || c <= min_confidence {
                    continue;
                }
                let x_in = (f64::from(sigmoid(slot[0])) + gx as f64) * g.stride;
                let y_in = (f64::from(sigmoid(slot[1])) + gy as f64) * g.stride;
                if !(x_in.is_finite() && y_in.is_finite()) {
                    continue;
                }
                out.push(Detection {
                    position: Point2::new(
                        (x_in - g.offset_x) * g.scale_x - 0.5,
                        (y_in - g.offset_y) * g.scale_y - 0.5,
                    ),
                    confidence: c,
                });
            }
        }
    }
    out
}

/// The marker pitch estimate of step 2: median nearest-neighbour distance between candidates with
/// c > `conf_keep`, or between all `candidates` when fewer than two are that confident.
pub fn estimate_pitch_px(candidates: &[Detection], conf_keep: f32) -> Option<f64> {
    pitch_of_confident(candidates, conf_keep).0
}

/// [`estimate_pitch_px`], and the nearest-neighbour distance of each candidate with c > `conf_keep`
/// among those (in their order in `candidates`), which the lattice check needs again.
pub fn pitch_of_confident(candidates: &[Detection], conf_keep: f32) -> (Option<f64>, Vec<f64>) {
    let confident: Vec<Point2> = candidates
        .iter()
        .filter(|d| d.confidence > conf_keep)
        .map(|d| d.position)
        .collect();
    let nn = nearest_neighbour_distances(&confident);
    let pitch = median_finite(&nn).or_else(|| {
        let all: Vec<Point2> = candidates.iter().map(|d| d.position).collect();
        median_nearest_neighbour_px(&all)
    });
    (pitch, nn)
}

/// Step 3's radius for the pitch of step 2, px (0 without a pitch: nothing is dropped).
pub fn dedup_radius_px(pitch_px: Option<f64>, params: &PostProcess) -> f64 {
    pitch_px.map_or(0.0, |p| params.dedup_radius_frac * p)
}

/// Step 3: sorts `candidates` by descending confidence (stable) and drops each one closer than
/// `radius_px` to a candidate already kept. A non-positive radius only sorts.
pub fn deduplicate(candidates: &mut Vec<Detection>, radius_px: f64) {
    candidates.sort_by(|a, b| b.confidence.total_cmp(&a.confidence));
    if radius_px <= 0.0 || !radius_px.is_finite() || candidates.len() < 2 {
        return;
    }
    // Dense uniform grid of cell size = radius over the candidates' extent: a conflict can only be in
    // the 3x3 neighbouring cells. Each cell keeps the positions already accepted in it.
    let (mut min_x, mut min_y, mut max_x, mut max_y) =
        (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    for d in candidates.iter() {
        min_x = min_x.min(d.position.x);
        min_y = min_y.min(d.position.y);
        max_x = max_x.max(d.position.x);
        max_y = max_y.max(d.position.y);
    }
    // Cap the grid size: a radius far below the extent (a degenerate pitch) falls back to coarser cells,
    // which only costs speed (cells bigger than the radius are still correct).
    let cell_px = radius_px.max((max_x - min_x).max(max_y - min_y) / 256.0);
    let cols = ((max_x - min_x) / cell_px) as usize + 1;
    let rows = ((max_y - min_y) / cell_px) as usize + 1;
    // Each cell's kept positions as a linked list (`head` of the cell, `next` of each kept one):
    // no allocation per cell.
    const NONE: u32 = u32::MAX;
    let mut head = vec![NONE; cols * rows];
    let mut kept: Vec<(Point2, u32)> = Vec::with_capacity(candidates.len());
    let r2 = radius_px * radius_px;
    candidates.retain(|d| {
        let cx = ((d.position.x - min_x) / cell_px) as usize;
        let cy = ((d.position.y - min_y) / cell_px) as usize;
        for ny in cy.saturating_sub(1)..=(cy + 1).min(rows - 1) {
            for nx in cx.saturating_sub(1)..=(cx + 1).min(cols - 1) {
                let mut k = head[ny * cols + nx];
                while k != NONE {
                    let (p, next) = kept[k as usize];
                    let (dx, dy) = (p.x - d.position.x, p.y - d.position.y);
                    if dx * dx + dy * dy < r2 {
                        return false;
                    }
                    k = next;
                }
            }
        }
        let cell = &mut head[cy * cols + cx];
        kept.push((d.position, *cell));
        *cell = (kept.len() - 1) as u32;
        true
    });
}

/// The MRE feature of `pool[index]`: the 10 smallest distances to the other members of `pool`,
/// ascending, divided by `pitch_px` (missing ones = [`MISSING_DISTANCE_PITCH`]), then its confidence.
/// `tree` must hold `pool`'s positions in order. Without a pitch every distance counts as missing.
fn feature_of(
    pool: &[Detection],
    tree: Option<&ImmutableKdTree<f64, 2>>,
    index: usize,
    pitch_px: Option<f64>,
) -> [f32; MRE_FEATURES] {
    let mut f = [MISSING_DISTANCE_PITCH; MRE_FEATURES];
    f[MRE_NEIGHBOURS] = pool[index].confidence;
    let (Some(tree), Some(pitch)) = (tree, pitch_px.filter(|p| *p > 0.0)) else {
        return f;
    };
    let Some(k) = std::num::NonZero::new((MRE_NEIGHBOURS + 1).min(pool.len())) else {
        return f;
    };
    let p = pool[index].position;
    let found = tree
        .query(&[p.x, p.y])
        .nearest_n::<SquaredEuclidean<f64>>(k)
        .execute();
    let mut dists: Vec<f64> = found
        .iter()
        .filter(|r| r.item as usize != index)
        .map(|r| r.distance.sqrt())
        .collect();
    dists.sort_by(f64::total_cmp);
    for (slot, d) in f.iter_mut().zip(dists.iter().take(MRE_NEIGHBOURS)) {
        *slot = (d / pitch) as f32;
    }
    f
}

/// A view's candidates after steps 1-3, split into those that pass directly and those MRE must score.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Selection {
    /// Candidates that pass without MRE: c > `conf_keep` (`marknet-mre`) or c > `conf_marknet_only`
    /// (`marknet`).
    pub accepted: Vec<Detection>,
    /// Candidates with `conf_low < c <= conf_keep` awaiting MRE (empty for `marknet`).
    pub pending: Vec<Detection>,
    /// Their MRE feature vectors, one per `pending` entry.
    pub features: Vec<[f32; MRE_FEATURES]>,
    /// `marknet` only: the candidates with `conf_low < c <= conf_marknet_only`, not markers but
    /// handed to a tracker as second tier ([`finish_tiered`](Self::finish_tiered)).
    pub below: Vec<Detection>,
    /// The pitch estimate used, px (`None` with fewer than two candidates).
    pub pitch_px: Option<f64>,
    /// Number of candidates left after de-duplication (step 3).
    pub kept: usize,
}

impl Selection {
    /// Steps 2-4 (up to MRE's scores) for `candidates`, the output of step 1 (c > `conf_low`, flat
    /// order). `with_mre` selects `marknet-mre`, else `marknet`.
    pub fn new(candidates: Vec<Detection>, params: &PostProcess, with_mre: bool) -> Self {
        let pitch_px = estimate_pitch_px(&candidates, params.conf_keep);
        Self::with_pitch(candidates, pitch_px, params, with_mre)
    }

    /// [`new`](Self::new) with step 2 already done: `pitch_px` = [`estimate_pitch_px`] of
    /// `candidates` with `params.conf_keep`.
    pub fn with_pitch(
        mut candidates: Vec<Detection>,
        pitch_px: Option<f64>,
        params: &PostProcess,
        with_mre: bool,
    ) -> Self {
        deduplicate(&mut candidates, dedup_radius_px(pitch_px, params));
        Self::of_deduplicated(candidates, pitch_px, params, with_mre)
    }

    /// [`with_pitch`](Self::with_pitch) with step 3 already done: `candidates` are
    /// [`deduplicate`]'s output for `pitch_px`.
    pub fn of_deduplicated(
        candidates: Vec<Detection>,
        pitch_px: Option<f64>,
        params: &PostProcess,
        with_mre: bool,
    ) -> Self {
        let kept = candidates.len();
        if !with_mre {
            let (accepted, below) = candidates
                .into_iter()
                .partition(|d| d.confidence > params.conf_marknet_only);
            return Self {
                accepted,
                below,
                pitch_px,
                kept,
                ..Self::default()
            };
        }
        // The tree serves the features of the candidates MRE scores: none to score (most frames of
        // a clean sensor), no tree.
        let any_pending = candidates.iter().any(|d| d.confidence <= params.conf_keep);
        let tree: Option<ImmutableKdTree<f64, 2>> = if any_pending {
            let coords: Vec<[f64; 2]> = candidates.iter().map(|d| [d.position.x, d.position.y]).collect();
            ImmutableKdTree::new_from_slice(&coords).ok()
        } else {
            None
        };
        let mut out = Self {
            pitch_px,
            kept,
            ..Self::default()
        };
        for (i, d) in candidates.iter().enumerate() {
            if d.confidence > params.conf_keep {
                out.accepted.push(*d);
            } else {
                out.features
                    .push(feature_of(&candidates, tree.as_ref(), i, pitch_px));
                out.pending.push(*d);
            }
        }
        out
    }

    /// Step 4's decision: the accepted candidates plus the pending ones whose score > `accept`,
    /// sorted by y then x. `scores` has one entry per pending candidate (missing ones reject).
    pub fn finish(self, scores: &[f32], accept: f32) -> Vec<Detection> {
        self.finish_tiered(scores, accept).accepted
    }

    /// [`finish`](Self::finish) keeping what it rejects as the second tier: the pending candidates
    /// whose score is at or below `accept` (`marknet-mre`) or the [`below`](Self::below) ones
    /// (`marknet`), both sorted by y then x.
    pub fn finish_tiered(self, scores: &[f32], accept: f32) -> TieredDetections {
        let mut accepted = self.accepted;
        let mut second_tier = self.below;
        for (k, d) in self.pending.iter().enumerate() {
            if scores.get(k).is_some_and(|s| *s > accept) {
                accepted.push(*d);
            } else {
                second_tier.push(*d);
            }
        }
        crate::sort_detections(&mut accepted);
        crate::sort_detections(&mut second_tier);
        TieredDetections {
            accepted,
            second_tier,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The logit pre-filter keeps exactly the candidates the sigmoid test keeps, at the thresholds
    /// in use and for logits packed around each threshold.
    #[test]
    fn decode_prefilter_keeps_exactly_what_the_sigmoid_test_keeps() {
        let g = DecodeGeometry {
            grid_y: 40,
            grid_x: 50,
            candidates: 5,
            stride: 8.0,
            scale_x: 1.5,
            scale_y: 1.2,
            offset_x: 0.0,
            offset_y: 0.0,
        };
        for min in [0.1f32, 0.2, 0.4, 0.5, 0.99, 0.0, 1.0] {
            let thr = if min > 0.0 && min < 1.0 {
                (min / (1.0 - min)).ln()
            } else {
                0.0
            };
            let raw: Vec<f32> = (0..g.values_per_image())
                .map(|k| {
                    if k % 3 == 2 {
                        // Spacing of a few ulps around the threshold, then wider.
                        thr + ((k / 3) as f32 - 5000.0) * if k % 2 == 0 { 1e-7 } else { 1e-3 }
                    } else {
                        0.1
                    }
                })
                .collect();
            let want = raw.chunks_exact(3).filter(|s| sigmoid(s[2]) > min).count();
            assert_eq!(decode(&raw, &g, min).len(), want, "min {min}");
        }
    }

    fn logit(p: f32) -> f32 {
        (p / (1.0 - p)).ln()
    }

    fn det(x: f64, y: f64, c: f32) -> Detection {
        Detection {
            position: Point2::new(x, y),
            confidence: c,
        }
    }

    /// Hand-computed decoding: a 2x3 grid, m = 2, stride 8, original image twice the input size.
    #[test]
    fn decoding_maps_cells_to_original_pixels() {
        let g = DecodeGeometry {
            grid_y: 2,
            grid_x: 3,
            candidates: 2,
            stride: 8.0,
            scale_x: 2.0,
            scale_y: 0.5,
            offset_x: 0.0,
            offset_y: 0.0,
        };
        let mut raw = vec![-10.0f32; g.values_per_image()];
        // cell (gy=1, gx=2), slot 1: sigmoid(tx)=0.25, sigmoid(ty)=0.75, c=0.9
        let base = ((3 + 2) * 2 + 1) * 3;
        raw[base] = logit(0.25);
        raw[base + 1] = logit(0.75);
        raw[base + 2] = logit(0.9);
        let out = decode(&raw, &g, 0.1);
        assert_eq!(out.len(), 1);
        // x_in = (0.25 + 2) * 8 = 18 -> 18 * 2 - 0.5 = 35.5; y_in = (0.75 + 1) * 8 = 14 -> 7 - 0.5 = 6.5
        assert!((out[0].position.x - 35.5).abs() < 1e-5, "{:?}", out[0]);
        assert!((out[0].position.y - 6.5).abs() < 1e-5, "{:?}", out[0]);
        assert!((out[0].confidence - 0.9).abs() < 1e-6);
        assert!(
            decode(&raw[..5], &g, 0.1).is_empty(),
            "short input decodes to nothing"
        );
        let mut broken = raw.clone();
        broken[base] = f32::NAN;
        broken[2] = f32::NAN;
        assert!(
            decode(&broken, &g, 0.1).is_empty(),
            "NaN logits give no candidates"
        );
    }

    #[test]
    fn thresholds_are_strict() {
        let g = DecodeGeometry {
            grid_y: 1,
            grid_x: 1,
            candidates: 3,
            stride: 4.0,
            scale_x: 1.0,
            scale_y: 1.0,
            offset_x: 0.0,
            offset_y: 0.0,
        };
        let raw = [0.0, 0.0, logit(0.4), 0.0, 0.0, logit(0.41), 0.0, 0.0, logit(0.1)];
        let c: Vec<f32> = decode(&raw, &g, 0.4).iter().map(|d| d.confidence).collect();
        assert_eq!(c.len(), 1);
        assert!((c[0] - 0.41).abs() < 1e-6);
        assert_eq!(decode(&raw, &g, 0.1).len(), 2, "0.1 itself is not above conf_low");
    }

    /// The grid search against brute force on scattered points (seeded, with duplicates and clusters).
    #[test]
    fn pitch_and_deduplication() {
        // A 4x4 lattice of pitch 10 plus a weaker duplicate 2 px from (10, 10).
        let mut cands: Vec<Detection> = (0..16)
            .map(|i| det(f64::from(i % 4) * 10.0, f64::from(i / 4) * 10.0, 0.9))
            .collect();
        cands.push(det(12.0, 10.0, 0.3));
        assert_eq!(estimate_pitch_px(&cands, 0.4), Some(10.0));
        let mut d = cands.clone();
        deduplicate(&mut d, 5.0);
        assert_eq!(d.len(), 16);
        assert!(d.iter().all(|x| x.confidence > 0.4));
        let mut keep_all = cands.clone();
        deduplicate(&mut keep_all, 1.0);
        assert_eq!(keep_all.len(), 17);
        assert_eq!(estimate_pitch_px(&[det(0.0, 0.0, 0.9)], 0.4), None);
        // fewer than two confident ones: all candidates give the pitch
        assert_eq!(
            estimate_pitch_px(&[det(0.0, 0.0, 0.3), det(3.0, 4.0, 0.2)], 0.4),
            Some(5.0)
        );
    }

    #[test]
    fn marknet_alone_hands_its_weak_candidates_on_as_second_tier() {
        let cands = vec![det(0.0, 0.0, 0.9), det(0.0, 10.0, 0.25), det(10.0, 5.0, 0.15)];
        let s = Selection::new(cands, &PostProcess::default(), false);
        assert_eq!((s.accepted.len(), s.below.len(), s.pending.len()), (2, 1, 0));
        let tiers = s.finish_tiered(&[], 0.99);
        assert_eq!(tiers.accepted.len(), 2);
        assert_eq!(tiers.second_tier, [det(10.0, 5.0, 0.15)]);
    }

    #[test]
    fn features_are_sorted_pitch_distances_with_missing_filled() {
        // pitch 10 (two confident points 10 apart); a pending candidate at (0, 5)
        let cands = vec![det(0.0, 0.0, 0.9), det(0.0, 10.0, 0.8), det(6.0, 5.0, 0.3)];
        let s = Selection::new(
            cands,
            &PostProcess {
                dedup_radius_frac: 0.1,
                ..PostProcess::default()
            },
            true,
        );
        assert_eq!(s.pitch_px, Some(10.0));
        assert_eq!(s.accepted.len(), 2);
        assert_eq!(s.pending.len(), 1);
        let f = s.features[0];
        let d = (36.0f64 + 25.0).sqrt() / 10.0;
        assert!(
            (f[0] - d as f32).abs() < 1e-6 && (f[1] - d as f32).abs() < 1e-6,
            "{f:?}"
        );
        assert!(f[2..10].iter().all(|v| *v == MISSING_DISTANCE_PITCH));
        assert!((f[10] - 0.3).abs() < 1e-7);
        let out = s.clone().finish(&[0.995], 0.99);
        assert_eq!(out.len(), 3);
        assert!(out.windows(2).all(|w| w[0].position.y <= w[1].position.y));
        let tiers = s.clone().finish_tiered(&[0.99], 0.99);
        assert_eq!(tiers.accepted, s.clone().finish(&[0.99], 0.99));
        assert_eq!(
            tiers.second_tier.len(),
            1,
            "the rejected candidate is the second tier"
        );
        assert!((tiers.second_tier[0].confidence - 0.3).abs() < 1e-7);
        assert!(s.clone().finish_tiered(&[0.995], 0.99).second_tier.is_empty());
        assert_eq!(s.finish(&[0.99], 0.99).len(), 2, "acceptance is strict");
    }
}
