//! One image's candidates from one network pass of Marknet, summarised once for both uses: the
//! layout decisions of the "auto" fit (the pitch the layout follows and its support) and the
//! post-processing (post-processing steps 2 and 3 and the lattice fit it may reuse).

use gelstereo_core::{Detection, ImageSize};

use crate::lattice::{LatticeCheck, LatticeFit, fit_lattice, fit_lattice_with_distances};
use crate::layout::{InputLayout, input_per_px};
use crate::postprocess::{PostProcess, dedup_radius_px, deduplicate, pitch_of_confident};
use crate::region::Region;

/// One image's candidates from one network pass, and what they say about its layout.
#[derive(Debug, Clone, Default)]
pub(crate) struct Pass {
    /// Candidates with c > the pass's threshold, in the image's pixels, flat order.
    pub(crate) candidates: Vec<Detection>,
    /// Post-processing step 3's output for them: de-duplicated, by descending confidence.
    pub(crate) kept: Vec<Detection>,
    /// Post-processing step 2's pitch of the candidates (de-duplication, MRE features).
    pub(crate) pitch_px: Option<f64>,
    /// How many confident candidates support `layout_pitch_px`: with the lattice check, the lattice
    /// members among the de-duplicated confident candidates (0 without a lattice); without it, every
    /// confident candidate.
    pub(crate) support: usize,
    /// The marker pitch the layout follows (`None`: no lattice, the layout stays).
    pub(crate) layout_pitch_px: Option<f64>,
    /// With the lattice check: the de-duplicated confident candidates (sorted by y then x) and their
    /// lattice fit, which the final lattice check reuses when its accepted markers are exactly these
    /// (the MRE accepted none of the rest), as it does on most frames.
    pub(crate) fitted: Option<FittedSet>,
    /// The region a closer look re-examined ([`crate::close_look`]), if any.
    pub(crate) looked: Option<Region>,
    /// Whether the closer look found every one of `kept` at least [`SQUEEZED_NN_PITCH`] x `pitch_px`
    /// from the others: the markers, a subset of them, then hold no squeezed pair either, and the
    /// blob search between squeezed markers has nothing to search.
    pub(crate) spread: bool,
}

/// Detections and their lattice fit at one input scale.
#[derive(Debug, Clone)]
pub(crate) struct FittedSet {
    detections: Vec<Detection>,
    input_per_px: f64,
    fit: LatticeFit,
}

impl FittedSet {
    /// The lattice fit of `kept_confident`, the de-duplicated candidates with c > `conf_keep`, sorted
    /// by y then x as the final accepted markers are (so that their check can reuse the fit).
    /// `confident_nn`: the nearest-neighbour distances of `candidates`' confident ones (in their
    /// order), when de-duplication dropped none of them: the same points, whose distances the pitch
    /// estimate measured; kept candidates lie pairwise apart, so both orders sort alike.
    fn of_confident(
        candidates: &[Detection],
        kept_confident: &[Detection],
        confident_nn: Option<Vec<f64>>,
        conf_keep: f32,
        check: &LatticeCheck,
        input_per_px: f64,
    ) -> Self {
        let (detections, fit) = match confident_nn {
            Some(nn) => {
                let mut with_nn: Vec<(Detection, f64)> = candidates
                    .iter()
                    .filter(|d| d.confidence > conf_keep)
                    .copied()
                    .zip(nn)
                    .collect();
                with_nn.sort_by(|a, b| crate::detection_order(&a.0, &b.0));
                let (detections, nn): (Vec<Detection>, Vec<f64>) = with_nn.into_iter().unzip();
                let fit = fit_lattice_with_distances(&detections, nn, check, input_per_px);
                (detections, fit)
            }
            None => {
                let mut detections = kept_confident.to_vec();
                crate::sort_detections(&mut detections);
                let fit = fit_lattice(&detections, check, input_per_px);
                (detections, fit)
            }
        };
        Self {
            detections,
            input_per_px,
            fit,
        }
    }

    /// The fit, if it was made of exactly `accepted` at `input_per_px`.
    pub(crate) fn fit_of(self, accepted: &[Detection], input_per_px: f64) -> Option<LatticeFit> {
        (self.detections == accepted && self.input_per_px == input_per_px).then_some(self.fit)
    }
}

impl Pass {
    /// The candidates of an image of `size` run under `layout`, summarised for the layout decision.
    pub(crate) fn new(
        candidates: Vec<Detection>,
        post: &PostProcess,
        size: ImageSize,
        layout: &InputLayout,
    ) -> Self {
        let (pitch_px, confident_nn) = pitch_of_confident(&candidates, post.conf_keep);
        let radius_px = dedup_radius_px(pitch_px, post);
        let mut kept = candidates.clone();
        deduplicate(&mut kept, radius_px);
        // Step 3 visits in descending confidence and keeps that order: the confident ones lead.
        let confident = kept.partition_point(|d| d.confidence > post.conf_keep);
        let (support, layout_pitch_px, fitted) = match &post.lattice {
            None => (confident_nn.len(), pitch_px, None),
            Some(check) => {
                let scale = input_per_px(size, layout);
                let reuse_nn = (radius_px > 0.0 && confident == confident_nn.len()).then_some(confident_nn);
                let fitted = FittedSet::of_confident(
                    &candidates,
                    &kept[..confident],
                    reuse_nn,
                    post.conf_keep,
                    check,
                    scale,
                );
                let (support, pitch) = if fitted.fit.is_lattice {
                    (fitted.fit.members, fitted.fit.pitch_px)
                } else {
                    (0, None)
                };
                (support, pitch, Some(fitted))
            }
        };
        Self {
            candidates,
            kept,
            pitch_px,
            support,
            layout_pitch_px,
            fitted,
            looked: None,
            spread: false,
        }
    }

    /// The area the supporting candidates cover (count x pitch^2, original px^2): about the gel's for a
    /// lattice and for a thinned-out one alike; a small part of it for several finds per oversized
    /// marker (the pitch then measures the spread of the duplicates).
    pub(crate) fn cover(&self) -> f64 {
        self.support as f64 * self.layout_pitch_px.map_or(0.0, |p| p * p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A jittered 14 x 11 lattice (pitch 20 px) of confident candidates in a scrambled order, with
    /// doubtful ones between its dots, a row of 8 confident ones 45 px apart below it, and
    /// `duplicates` confident near-copies of its dots.
    fn lattice_candidates(duplicates: usize) -> Vec<Detection> {
        let jitter = |k: usize| ((k * 7919 + 13) % 1000) as f64 / 1000.0 - 0.5;
        let mut out = Vec::new();
        for k in 0..154 {
            let site = (k * 37) % 154;
            let (col, row) = ((site % 14) as f64, (site / 14) as f64);
            let (x, y) = (30.0 + 20.0 * col + jitter(k), 30.0 + 20.0 * row + jitter(k + 500));
            let c = 0.45 + 0.5 * (jitter(k + 900) + 0.5) as f32;
            let at = |x: f64, y: f64, confidence: f32| Detection {
                position: gelstereo_core::Point2::new(x, y),
                confidence,
            };
            out.push(at(x, y, c));
            if k % 3 == 0 {
                out.push(at(x + 10.0, y + 10.0, 0.25));
            }
            if k < duplicates {
                out.push(at(x + 1.0, y - 1.0, c - 0.01));
            }
            // Confident finds off the lattice, far apart: their distances must stay theirs.
            if k < 8 {
                out.push(at(30.0 + 45.0 * k as f64, 310.0, 0.9));
            }
        }
        out
    }

    /// The pass de-duplicates all candidates once and reuses the pitch estimate's nearest-neighbour
    /// distances for the lattice check when no confident candidate was dropped: among the confident
    /// ones it keeps exactly what de-duplicating them alone keeps, and its fit is the one
    /// `fit_lattice` makes of them, with and without dropped duplicates.
    #[test]
    fn one_deduplication_and_reused_distances_leave_the_fit_as_it_was() {
        let post = PostProcess::default();
        let check = post.lattice.expect("the default has the lattice check");
        let size = ImageSize {
            width: 340,
            height: 340,
        };
        for duplicates in [0, 5] {
            let candidates = lattice_candidates(duplicates);
            let pass = Pass::new(candidates.clone(), &post, size, &InputLayout::stretch(340, 340));
            let radius = dedup_radius_px(pass.pitch_px, &post);
            let mut alone: Vec<Detection> = candidates
                .iter()
                .filter(|d| d.confidence > post.conf_keep)
                .copied()
                .collect();
            deduplicate(&mut alone, radius);
            assert_eq!(alone.len(), 162, "{duplicates} duplicates");
            assert_eq!(&pass.kept[..alone.len()], &alone[..]);
            assert!(
                pass.kept[alone.len()..]
                    .iter()
                    .all(|d| d.confidence <= post.conf_keep)
            );
            crate::sort_detections(&mut alone);
            let fitted = pass.fitted.expect("the lattice check runs");
            assert_eq!(fitted.detections, alone);
            assert_eq!(fitted.fit, fit_lattice(&alone, &check, 1.0));
            assert!(fitted.fit.is_lattice && (150..=154).contains(&fitted.fit.members));
        }
    }
}
