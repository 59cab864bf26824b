//! Marknet's post-processing of each image's final pass, after decoding: the selection (with the
//! MRE's scores for `marknet-mre`), the lattice check, and the steps after it (the dots-on-a-gel
//! check, the border, and the dots the network missed, found as blobs).

use gelstereo_core::{ImageSize, TieredDetections};
use opencv::core::{Mat, MatTraitConst};

use crate::Result;
use crate::border::settle_the_border;
use crate::dots::judge_the_dots;
use crate::lattice::{fit_lattice, keep_fitted_lattice};
use crate::layout::{InputLayout, input_per_px};
use crate::mre::Mre;
use crate::network::map_images;
use crate::pass::{FittedSet, Pass};
use crate::postprocess::{MRE_FEATURES, PostProcess, Selection};
use crate::region::Region;
use crate::site_blobs::blobs_at_empty_sites;
use crate::squeezed_blobs::blobs_between_squeezed;

/// What the lattice check and the edge margin need of an image besides its markers.
#[derive(Debug, Clone, Copy)]
struct Frame {
    size: ImageSize,
    /// Input px per original px of the final layout.
    input_per_px: f64,
    /// The candidates' pitch (post-processing step 2).
    pitch_px: Option<f64>,
    /// The region a closer look re-examined.
    looked: Option<Region>,
    /// [`Pass::spread`].
    spread: bool,
}

/// Each image's markers from its final pass in `passes` (with the layout it ran under): the
/// selection of the kept candidates under `post` (MRE-scored by `mre`, if any), then with the
/// lattice check the lattice, and [`after_the_lattice`] (between squeezed markers only with
/// `close_look`). `parallel`: the images' selections are made on rayon's thread pool.
pub(crate) fn finish_passes(
    passes: Vec<(Pass, InputLayout)>,
    images: &[&Mat],
    post: &PostProcess,
    mre: Option<&mut Mre>,
    close_look: bool,
    parallel: bool,
) -> Result<Vec<TieredDetections>> {
    let with_mre = mre.is_some();
    let post = *post;
    // Per image: its size, the input px per original px of its final layout (for the lattice
    // check) and its candidates' pitch (for the edge margin).
    let frames: Vec<Frame> = passes
        .iter()
        .zip(images)
        .map(|((pass, layout), image)| {
            let size = ImageSize {
                width: image.cols().max(0) as u32,
                height: image.rows().max(0) as u32,
            };
            Frame {
                size,
                input_per_px: input_per_px(size, layout),
                pitch_px: pass.pitch_px,
                looked: pass.looked,
                spread: pass.spread,
            }
        })
        .collect();
    let (selections, fitted): (Vec<Selection>, Vec<Option<FittedSet>>) =
        map_images(parallel, passes, |(pass, _)| {
            let selection = Selection::of_deduplicated(pass.kept, pass.pitch_px, &post, with_mre);
            (selection, pass.fitted)
        })
        .into_iter()
        .unzip();
    let finish = |found: TieredDetections, fitted: Option<FittedSet>, frame: Frame| {
        // The lattice check, beyond the model contract's steps (the border is settled after it).
        let Some(check) = &post.lattice else {
            return found;
        };
        let scale = frame.input_per_px;
        let fit = fitted
            .and_then(|f| f.fit_of(&found.accepted, scale))
            .unwrap_or_else(|| fit_lattice(&found.accepted, check, scale));
        keep_fitted_lattice(found, fit, check, frame.looked.as_ref(), Some(frame.size))
    };
    let pitch_and_spread: Vec<(Option<f64>, bool)> = frames.iter().map(|f| (f.pitch_px, f.spread)).collect();
    let found: Vec<TieredDetections> = match mre {
        None => selections
            .into_iter()
            .zip(fitted)
            .zip(frames)
            .map(|((s, fitted), frame)| finish(s.finish_tiered(&[], post.accept), fitted, frame))
            .collect(),
        Some(mre) => {
            let features: Vec<[f32; MRE_FEATURES]> = selections
                .iter()
                .flat_map(|s| s.features.iter().copied())
                .collect();
            let scores = mre.score(&features)?;
            let mut offset = 0;
            selections
                .into_iter()
                .zip(fitted)
                .zip(frames)
                .map(|((s, fitted), frame)| {
                    let n = s.pending.len();
                    let mine = scores.get(offset..offset + n).unwrap_or(&[]);
                    offset += n;
                    finish(s.finish_tiered(mine, post.accept), fitted, frame)
                })
                .collect()
        }
    };
    if post.lattice.is_none() {
        return Ok(found);
    }
    // Dots the network missed, found as blobs: between squeezed markers (part of the closer
    // look), then where the lattice's lines put a site at a hole or at the border.
    found
        .into_iter()
        .zip(images)
        .zip(pitch_and_spread)
        .map(|((found, image), (pitch, spread))| {
            after_the_lattice(found, image, pitch, close_look && !spread)
        })
        .collect()
}

/// The steps after the lattice check on one image: the dots-on-a-gel check, the border, and the
/// dots the network missed, found as blobs (between squeezed markers when `between_squeezed`, then
/// at the lattice's empty sites). `pitch`: the candidates' pitch (post-processing step 2).
pub fn after_the_lattice(
    mut found: TieredDetections,
    image: &Mat,
    pitch: Option<f64>,
    between_squeezed: bool,
) -> Result<TieredDetections> {
    // A regular pattern that is no marker gel (a checkerboard, a weave) can pass the lattice
    // check; its "markers" then lose the look of dots on a gel.
    if judge_the_dots(image, &found.accepted)?.is_some_and(|v| !v.dots()) {
        let rejected = std::mem::take(&mut found.accepted);
        found.second_tier.extend(rejected);
        return Ok(found);
    }
    settle_the_border(&mut found, image, pitch)?;
    let before = found.accepted.len();
    if between_squeezed {
        let blobs = blobs_between_squeezed(image, &found.accepted, pitch)?;
        found.accepted.extend(blobs);
    }
    let at_sites = blobs_at_empty_sites(image, &found.accepted, pitch)?;
    found.accepted.extend(at_sites);
    if found.accepted.len() > before {
        crate::sort_detections(&mut found.accepted);
    }
    Ok(found)
}
