//! The Marknet localizer (with its MRE, `marknet-mre`): batched inference of both stereo views on its
//! [`Network`](crate::network) under the layouts of [`crate::layout`], decoding and post-processing.
//!
//! The default [`InputFit::Auto`] of a dynamic-input model scales isotropically
//! so that the marker pitch lands where the network was trained, measured on a first pass and
//! remembered per image size; a fixed-input model gets the contract's whole-image stretch.
//! Outputs are mapped back with `x_orig = (x_in - offset_x) * W / scaled_width - 0.5` (likewise y).

use std::path::Path;

use gelstereo_core::{Detection, ImageSize, Point2, StereoPair, TieredDetections};
use opencv::core::{Mat, MatTraitConst};

use crate::border::settle_the_border;
use crate::close_look::{SQUEEZED_NN_PITCH, close_look_input, close_look_zoom, merge, squeezed_region_of};
use crate::contract::AutoFit;
use crate::dots::judge_the_dots;
use crate::lattice::{
    LatticeCheck, LatticeFit, fit_lattice, fit_lattice_with_distances, keep_fitted_lattice,
};
use crate::layout::{
    COARSE_PROBE_SCALE, FINE_PROBE_SCALE, InputFit, InputLayout, MAX_RELAYOUTS, MIN_PITCH_SUPPORT,
    PROBE_MIN_COVER, PROBE_MIN_GAIN, PROBE_SCALE, decode_in_layout, fit_layout, input_per_px,
    probe_layout_at,
};
use crate::mre::Mre;
use crate::network::{Network, input_dims, map_images};
use crate::onnx::SessionOptions;
use crate::postprocess::{
    DecodeGeometry, MRE_FEATURES, Selection, dedup_radius_px, deduplicate, pitch_of_confident,
};
use crate::region::Region;
use crate::site_blobs::blobs_at_empty_sites;
use crate::spacing::nearest_neighbour_distances;
use crate::squeezed_blobs::blobs_between_squeezed;
use crate::stream::StreamState;
use crate::window::{self, LatticeWindow, WINDOW_MIN_MARKERS, Window};
use crate::{Error, Localizer, MarknetContract, PostProcess, Result, check_image};

/// What the passes of the "auto" fit and the closer look leave of one image, before the
/// post-processing ([`Marknet::fitted_candidates`]).
#[derive(Debug, Clone, PartialEq)]
pub struct FittedCandidates {
    /// The candidates with c > `conf_low`, in the image's pixels, in flat order.
    pub candidates: Vec<Detection>,
    /// The layout of the pass they come from (its scale is the lattice check's).
    pub layout: InputLayout,
    /// The region a closer look re-examined, if any.
    pub looked: Option<Region>,
}

/// One image's candidates from one network pass, and what they say about its layout.
#[derive(Debug, Clone, Default)]
struct Pass {
    /// Candidates with c > the pass's threshold, in the image's pixels, flat order.
    candidates: Vec<Detection>,
    /// Post-processing step 3's output for them: de-duplicated, by descending confidence.
    kept: Vec<Detection>,
    /// Post-processing step 2's pitch of the candidates (de-duplication, MRE features).
    pitch_px: Option<f64>,
    /// How many confident candidates support `layout_pitch_px`: with the lattice check, the lattice
    /// members among the de-duplicated confident candidates (0 without a lattice); without it, every
    /// confident candidate.
    support: usize,
    /// The marker pitch the layout follows (`None`: no lattice, the layout stays).
    layout_pitch_px: Option<f64>,
    /// With the lattice check: the de-duplicated confident candidates (sorted by y then x) and their
    /// lattice fit, which the final lattice check reuses when its accepted markers are exactly these
    /// (the MRE accepted none of the rest), as it does on most frames.
    fitted: Option<FittedSet>,
    /// The region a closer look re-examined ([`crate::close_look`]), if any.
    looked: Option<Region>,
    /// Whether the closer look found every one of `kept` at least [`SQUEEZED_NN_PITCH`] x `pitch_px`
    /// from the others: the markers, a subset of them, then hold no squeezed pair either, and the
    /// blob search between squeezed markers has nothing to search.
    spread: bool,
}

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

/// Detections and their lattice fit at one input scale.
#[derive(Debug, Clone)]
struct FittedSet {
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
    fn fit_of(self, accepted: &[Detection], input_per_px: f64) -> Option<LatticeFit> {
        (self.detections == accepted && self.input_per_px == input_per_px).then_some(self.fit)
    }
}

impl Pass {
    /// The candidates of an image of `size` run under `layout`, summarised for the layout decision.
    fn new(candidates: Vec<Detection>, post: &PostProcess, size: ImageSize, layout: &InputLayout) -> Self {
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
    fn cover(&self) -> f64 {
        self.support as f64 * self.layout_pitch_px.map_or(0.0, |p| p * p)
    }
}

/// The Marknet localizer: `marknet` (c > `conf_marknet_only`) or, with an [`Mre`], `marknet-mre`.
pub struct Marknet {
    net: Network,
    options: SessionOptions,
    post: PostProcess,
    mre: Option<Mre>,
    fit: InputFit,
    /// The remembered pitches and lattice windows of the stream being localized.
    stream: StreamState,
    /// Whether squeezed parts of the lattice get a closer look ([`crate::close_look`]).
    close_look: bool,
    /// Work on the images of a batch in parallel ([`set_parallel`](Self::set_parallel)).
    parallel: bool,
}

impl std::fmt::Debug for Marknet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Marknet")
            .field("path", &self.net.path)
            .field("contract", &self.net.contract)
            .field("post", &self.post)
            .field("fit", &self.fit)
            .field("mre", &self.mre)
            .finish()
    }
}

impl Marknet {
    /// Loads `path` and checks its contract; the localizer is `marknet` until [`with_mre`](Self::with_mre).
    pub fn load(path: &Path, options: &SessionOptions) -> Result<Self> {
        let net = Network::load(path, options)?;
        Ok(Self {
            options: *options,
            post: net.contract.postprocess,
            net,
            mre: None,
            fit: InputFit::Auto,
            stream: StreamState::default(),
            close_look: true,
            parallel: false,
        })
    }

    /// Adds MRE post-processing (`marknet-mre`); MRE's confidence band must match Marknet's, and its
    /// acceptance threshold replaces the default.
    pub fn with_mre(mut self, mre: Mre) -> Result<Self> {
        mre.contract.check_compatible(&mre.path, &self.post)?;
        self.post.accept = mre.contract.accept;
        self.mre = Some(mre);
        Ok(self)
    }

    /// The model's declared contract.
    pub fn contract(&self) -> &MarknetContract {
        &self.net.contract
    }

    /// The post-processing thresholds in use.
    pub fn postprocess(&self) -> &PostProcess {
        &self.post
    }

    /// Replaces the post-processing thresholds (e.g. for a threshold sweep).
    pub fn set_postprocess(&mut self, post: PostProcess) {
        self.post = post;
    }

    /// Chooses how images are fitted to the network input ([`InputFit::Auto`] by default).
    pub fn set_fit(&mut self, fit: InputFit) {
        self.fit = fit;
    }

    /// Whether the "auto" fit remembers the marker pitch measured per image size (default: yes, for
    /// streams of one sensor: one pass per image). Off, every image starts without a pitch (a first
    /// pass, and a second when the pitch asks for another scale), as the trainer's evaluation does.
    pub fn set_pitch_memory(&mut self, remember: bool) {
        self.stream.set_remember_pitch(remember);
    }

    /// Whether, with the pitch remembered, each view of a stream runs on a window around the
    /// lattice its first frame showed ([`crate::window`]; default: yes). Off, every frame runs whole.
    /// Windows are kept per image size and batch slot (a stereo pair's left and right), so the images
    /// given to one slot must come from one camera: a second camera's images interleaved through
    /// [`Localizer::detect`] would each fall back to the whole input after trying the first's window
    /// (use `detect_stereo`, one localizer per camera, or turn windows off).
    pub fn set_lattice_window(&mut self, on: bool) {
        self.stream.set_lattice_window(on);
    }

    /// Whether the network looks again, at a larger scale, where the first pass's candidates lie
    /// squeezed together ([`crate::close_look`]), and blobs between the squeezed markers it still
    /// missed join them ([`crate::squeezed_blobs`]; default: yes). It needs the "auto" fit and the
    /// lattice check (it is beyond the model contract's steps, as they are).
    pub fn set_close_look(&mut self, on: bool) {
        self.close_look = on;
    }

    /// The window view `slot` (index in the batch: 0 = left, 1 = right) of images of `size` runs
    /// on, if it has one.
    pub fn lattice_window(&self, size: ImageSize, slot: usize) -> Option<LatticeWindow> {
        self.stream.window(size, slot)
    }

    /// [`Localizer::fork`]: the models loaded again with `intra_threads`, the thresholds, the fit
    /// and the remembered pitches copied.
    fn forked(&self, intra_threads: usize) -> Result<Self> {
        let options = SessionOptions {
            intra_threads,
            ..self.options
        };
        let mut net = Marknet::load(&self.net.path, &options)?;
        if let Some(mre) = &self.mre {
            net = net.with_mre(Mre::load(&mre.path, &options)?)?;
        }
        net.post = self.post;
        net.fit = self.fit;
        net.stream = self.stream.clone();
        net.close_look = self.close_look;
        Ok(net)
    }

    /// Whether the "auto" fit applies (an [`InputFit::Auto`] localizer on a dynamic-input model).
    fn auto_fit(&self) -> Option<&AutoFit> {
        match self.fit {
            InputFit::Auto => self.net.contract.auto_fit.as_ref(),
            InputFit::Stretch | InputFit::Pad => None,
        }
    }

    /// The layout of an image of `size` given its marker pitch (used by the "auto" fit only).
    pub fn layout(&self, size: ImageSize, pitch_px: Option<f64>) -> InputLayout {
        let (iw, ih) = (self.net.contract.input_width, self.net.contract.input_height);
        if let Some(fit) = self.auto_fit() {
            return fit_layout(size, pitch_px, iw, ih, fit);
        }
        match self.fit {
            InputFit::Pad => {
                let (w, h) = (f64::from(size.width), f64::from(size.height));
                let scale = (f64::from(iw) / w).min(f64::from(ih) / h).min(1.0);
                let nw = ((w * scale).round() as u32).clamp(1, iw);
                let nh = ((h * scale).round() as u32).clamp(1, ih);
                InputLayout {
                    input_width: iw,
                    input_height: ih,
                    scaled_width: nw,
                    scaled_height: nh,
                    offset_x: (iw - nw) / 2,
                    offset_y: (ih - nh) / 2,
                }
            }
            InputFit::Auto | InputFit::Stretch => InputLayout::stretch(iw, ih),
        }
    }

    /// The layout the next image of `size` gets (with the remembered pitch, if any).
    pub fn next_layout(&self, size: ImageSize) -> InputLayout {
        self.layout(size, self.stream.pitch(size))
    }

    /// Whether the images of a batch (the two views of a stereo pair) are preprocessed, decoded and
    /// post-processed in parallel on rayon's thread pool (default: no). Same results; it lowers the
    /// latency of one pair where a core is free, and only adds overhead where the cores are already
    /// busy (e.g. several localizers working on frames in parallel).
    pub fn set_parallel(&mut self, parallel: bool) {
        self.parallel = parallel;
    }

    /// Whether MRE post-processing is on (`marknet-mre`).
    pub fn has_mre(&self) -> bool {
        self.mre.is_some()
    }

    /// [`Network::run_batch`] under this localizer's fit: a stretch must keep the aspect ratio
    /// within bounds (the "auto" and "pad" layouts keep it). A batch may take several runs under the
    /// "auto" fit.
    fn run_batch(
        &mut self,
        images: &[&Mat],
        windows: &[Option<Window>],
        layouts: &[InputLayout],
    ) -> Result<Vec<f32>> {
        let contract = &self.net.contract;
        let stretch =
            self.fit == InputFit::Stretch || (self.fit == InputFit::Auto && contract.auto_fit.is_none());
        let stretch_to = stretch.then_some((contract.input_width, contract.input_height));
        self.net
            .run_batch(images, windows, layouts, stretch_to, self.parallel)
    }

    /// Runs the network on `images` as one batch under the layouts the next images of their sizes get
    /// ([`next_layout`](Self::next_layout)): each image's size and its raw output (`[Gy, Gx, m, 3]`
    /// logits, row-major, concatenated). The images must share one input size (e.g. a stereo pair).
    pub fn raw_output(&mut self, images: &[&Mat]) -> Result<(Vec<ImageSize>, Vec<f32>)> {
        let sizes = images
            .iter()
            .map(|im| check_image(im))
            .collect::<Result<Vec<_>>>()?;
        let layouts: Vec<InputLayout> = sizes.iter().map(|s| self.next_layout(*s)).collect();
        if let Some(other) = layouts
            .iter()
            .find(|l| (l.input_width, l.input_height) != (layouts[0].input_width, layouts[0].input_height))
        {
            return Err(Error::Image {
                property: "size",
                expected: format!(
                    "one network input size for the whole batch ({}x{})",
                    layouts[0].input_width, layouts[0].input_height
                ),
                found: format!("{}x{}", other.input_width, other.input_height),
            });
        }
        let raw = self.run_batch(images, &vec![None; images.len()], &layouts)?;
        Ok((sizes, raw))
    }

    /// The decoding geometry of an image of `size` under `layout`.
    pub fn geometry_for(&self, size: ImageSize, layout: &InputLayout) -> DecodeGeometry {
        self.net.geometry_for(size, layout)
    }

    /// The decoding geometry the next image of `size` gets ([`next_layout`](Self::next_layout)).
    pub fn geometry(&self, size: ImageSize) -> DecodeGeometry {
        self.geometry_for(size, &self.next_layout(size))
    }

    /// Runs `images` under `layouts` (grouped into one batch per input size) and decodes each image's
    /// candidates with c > `min_confidence`, in its own pixels; candidates in the padding are dropped
    /// (a marker whose centre lies outside the image is not reported). An image with a window in
    /// `windows` runs on that window of its layout's input. Each image's [`Pass`].
    fn decode_pass(
        &mut self,
        images: &[&Mat],
        windows: &[Option<Window>],
        sizes: &[ImageSize],
        layouts: &[InputLayout],
        min_confidence: f32,
    ) -> Result<Vec<Pass>> {
        let post = self.post;
        self.decode_each(images, windows, sizes, layouts, min_confidence, |i, dets| {
            Pass::new(dets, &post, sizes[i], &layouts[i])
        })
    }

    /// [`decode_pass`](Self::decode_pass) with `finish` (index into `images`, its candidates) making
    /// each image's result.
    fn decode_each<T: Default + Send>(
        &mut self,
        images: &[&Mat],
        windows: &[Option<Window>],
        sizes: &[ImageSize],
        layouts: &[InputLayout],
        min_confidence: f32,
        finish: impl Fn(usize, Vec<Detection>) -> T + Sync + Send,
    ) -> Result<Vec<T>> {
        let mut found: Vec<T> = (0..images.len()).map(|_| T::default()).collect();
        let mut pending: Vec<usize> = (0..images.len()).collect();
        let dims = |i: usize| input_dims(&layouts[i], windows[i].as_ref());
        while let Some(&lead) = pending.first() {
            let key = dims(lead);
            let (group, rest): (Vec<usize>, Vec<usize>) = pending.iter().partition(|&&i| dims(i) == key);
            pending = rest;
            let batch_images: Vec<&Mat> = group.iter().map(|&i| images[i]).collect();
            let batch_windows: Vec<Option<Window>> = group.iter().map(|&i| windows[i]).collect();
            let batch_layouts: Vec<InputLayout> = group.iter().map(|&i| layouts[i]).collect();
            let raw = self.run_batch(&batch_images, &batch_windows, &batch_layouts)?;
            let per_image = raw.len() / group.len().max(1);
            let jobs = group
                .iter()
                .map(|&i| {
                    (
                        i,
                        self.net
                            .window_geometry(sizes[i], &layouts[i], windows[i].as_ref()),
                    )
                })
                .zip(raw.chunks(per_image.max(1)))
                .collect();
            let decoded = map_images(self.parallel, jobs, |((i, geometry), raw)| {
                let dets = decode_in_layout(raw, &geometry, &layouts[i], sizes[i], min_confidence);
                (i, finish(i, dets))
            });
            for (i, d) in decoded {
                found[i] = d;
            }
        }
        Ok(found)
    }

    /// Runs the network on `images` and returns each image's candidates with c > `min_confidence`, in
    /// that image's pixels, in flat order (step 1 of [`crate::postprocess`]). Under the "auto" fit an
    /// image whose measured pitch asks for another scale is run again at that scale, and the pitch is
    /// remembered for its size.
    pub fn candidates(&mut self, images: &[&Mat], min_confidence: f32) -> Result<Vec<Vec<Detection>>> {
        let found = self.candidates_with_pitch(images, &vec![None; images.len()], min_confidence)?;
        Ok(found.into_iter().map(|(pass, _)| pass.candidates).collect())
    }

    /// Each image's [`FittedCandidates`]: the network passes [`Localizer::detect`] runs before its
    /// post-processing (probes, relayouts, the closer look), for a caller that post-processes the
    /// candidates itself (the trainer's evaluation scores them with and without its own MRE).
    pub fn fitted_candidates(&mut self, images: &[&Mat]) -> Result<Vec<FittedCandidates>> {
        let found = self.candidates_with_pitch(images, &vec![None; images.len()], self.post.conf_low)?;
        Ok(found
            .into_iter()
            .map(|(pass, layout)| FittedCandidates {
                candidates: pass.candidates,
                layout,
                looked: pass.looked,
            })
            .collect())
    }

    /// [`candidates`](Self::candidates), each image's as a [`Pass`] (with its pitch estimate,
    /// post-processing step 2, computed once for both the layout decision and the post-processing)
    /// and the layout it ran under. An image with a remembered window in `learnt` runs once, on
    /// that window of its layout's input.
    fn candidates_with_pitch(
        &mut self,
        images: &[&Mat],
        learnt: &[Option<LatticeWindow>],
        min_confidence: f32,
    ) -> Result<Vec<(Pass, InputLayout)>> {
        let sizes = images
            .iter()
            .map(|im| check_image(im))
            .collect::<Result<Vec<_>>>()?;
        let mut layouts: Vec<InputLayout> = sizes
            .iter()
            .zip(learnt)
            .map(|(s, r)| r.map_or_else(|| self.next_layout(*s), |r| r.layout))
            .collect();
        let windows: Vec<Option<Window>> = learnt.iter().map(|r| r.map(|r| r.window)).collect();
        let mut found = self.decode_pass(images, &windows, &sizes, &layouts, min_confidence)?;
        let Some(fit) = self.auto_fit().copied() else {
            return Ok(found.into_iter().zip(layouts).collect());
        };
        let (iw, ih) = (self.net.contract.input_width, self.net.contract.input_height);
        let whole_images: Vec<usize> = (0..images.len()).filter(|&i| learnt[i].is_none()).collect();
        let unknown: Vec<usize> = whole_images
            .iter()
            .copied()
            .filter(|&i| self.stream.pitch(sizes[i]).is_none())
            .collect();
        for scale in [PROBE_SCALE, FINE_PROBE_SCALE, COARSE_PROBE_SCALE] {
            // The fine and coarse probes only where no pass so far found a lattice; the fine one also
            // where the lattice found (with the lattice check) lies below the network's range at its
            // input: its dots barely resolved, it may be a thinned-out part of a finer lattice, whose
            // few finds lie a multiple of its pitch apart.
            let with_lattice = self.post.lattice.is_some();
            let probes: Vec<(usize, InputLayout)> = unknown
                .iter()
                .filter(|&&i| {
                    let unresolved = || {
                        let pitch = found[i].layout_pitch_px.unwrap_or(f64::INFINITY);
                        pitch * input_per_px(sizes[i], &layouts[i]) < fit.pitch_min_px
                    };
                    scale == PROBE_SCALE
                        || found[i].support < MIN_PITCH_SUPPORT
                        || (scale == FINE_PROBE_SCALE && with_lattice && unresolved())
                })
                .map(|&i| (i, probe_layout_at(sizes[i], iw, ih, &fit, scale)))
                .filter(|&(i, probe)| probe != layouts[i])
                .collect();
            let probed = self.decode_subset(images, &sizes, &probes, min_confidence)?;
            for ((i, layout), probe) in probes.into_iter().zip(probed) {
                let n = probe.support;
                let gain = n >= MIN_PITCH_SUPPORT && n as f64 >= PROBE_MIN_GAIN * found[i].support as f64;
                if gain && probe.cover() >= PROBE_MIN_COVER * found[i].cover() {
                    found[i] = probe;
                    layouts[i] = layout;
                }
            }
        }
        // Without the lattice check a pitch is any candidates' spacing (a random network's lies at its
        // output stride at every scale), and repeating would only zoom in: one relayout, as before.
        let rounds = if self.post.lattice.is_some() {
            MAX_RELAYOUTS
        } else {
            1
        };
        let mut todo = whole_images;
        for _ in 0..rounds {
            let redo = self.relayouts(&todo, &found, &sizes, &mut layouts);
            let again = self.decode_subset(images, &sizes, &redo, min_confidence)?;
            todo = redo.iter().map(|&(i, _)| i).collect();
            for ((i, _), d) in redo.into_iter().zip(again) {
                found[i] = d;
            }
            if todo.is_empty() {
                break;
            }
        }
        if self.close_look && self.post.lattice.is_some() {
            self.look_closer(images, &sizes, &layouts, &mut found, fit.multiple, min_confidence)?;
        }
        Ok(found.into_iter().zip(layouts).collect())
    }

    /// Runs the network once more where an image's pass in `found` shows squeezed candidates, on a
    /// window of its input at a larger scale ([`crate::close_look`]), and makes its pass of the
    /// merged candidates, still under its layout in `layouts` (whose scale the lattice check uses).
    fn look_closer(
        &mut self,
        images: &[&Mat],
        sizes: &[ImageSize],
        layouts: &[InputLayout],
        found: &mut [Pass],
        multiple: u32,
        min_confidence: f32,
    ) -> Result<()> {
        struct Look {
            image: usize,
            region: Region,
            zoomed: InputLayout,
            window: Window,
        }
        let mut looks = Vec::new();
        for (image, pass) in found.iter_mut().enumerate() {
            let points: Vec<Point2> = pass.kept.iter().map(|d| d.position).collect();
            let nn = nearest_neighbour_distances(&points);
            pass.spread = pass
                .pitch_px
                .is_some_and(|p| nn.iter().all(|&d| d >= SQUEEZED_NN_PITCH * p));
            let (Some(region), Some(pitch)) = (
                squeezed_region_of(&pass.kept, &nn, pass.pitch_px, sizes[image]),
                pass.pitch_px,
            ) else {
                continue;
            };
            let Some(zoom) = close_look_zoom(sizes[image], &layouts[image], pitch) else {
                continue;
            };
            let (zoomed, window) =
                close_look_input(sizes[image], &layouts[image], &region, pitch, zoom, multiple);
            if window.width > 0 && window.height > 0 {
                looks.push(Look {
                    image,
                    region,
                    zoomed,
                    window,
                });
            }
        }
        if looks.is_empty() {
            return Ok(());
        }
        let picked: Vec<&Mat> = looks.iter().map(|l| images[l.image]).collect();
        let picked_sizes: Vec<ImageSize> = looks.iter().map(|l| sizes[l.image]).collect();
        let zoomed: Vec<InputLayout> = looks.iter().map(|l| l.zoomed).collect();
        let windows: Vec<Option<Window>> = looks.iter().map(|l| Some(l.window)).collect();
        let closer = self.decode_each(
            &picked,
            &windows,
            &picked_sizes,
            &zoomed,
            min_confidence,
            |_, dets| dets,
        )?;
        let post = self.post;
        for (look, closer) in looks.into_iter().zip(closer) {
            let i = look.image;
            let first = std::mem::take(&mut found[i].candidates);
            found[i] = Pass::new(merge(first, closer, &look.region), &post, sizes[i], &layouts[i]);
            found[i].looked = Some(look.region);
        }
        Ok(())
    }

    /// The images of `todo` to run again and their new layouts (set in `layouts`): those whose pass
    /// measured a pitch (with enough support) that asks for a layout more than
    /// [`RELAYOUT_SCALE_CHANGE`] away and, with the pitch remembered, every image of a size under the
    /// layout the next one gets; the remembered pitch follows the measured one.
    fn relayouts(
        &mut self,
        todo: &[usize],
        found: &[Pass],
        sizes: &[ImageSize],
        layouts: &mut [InputLayout],
    ) -> Vec<(usize, InputLayout)> {
        let mut wanted: Vec<Option<InputLayout>> = vec![None; found.len()];
        for &i in todo {
            let pass = &found[i];
            // Too few markers to trust a pitch (an empty or unusual frame): keep the layout.
            let Some(pitch) = pass.layout_pitch_px.filter(|_| pass.support >= MIN_PITCH_SUPPORT) else {
                continue;
            };
            let layout = self.layout(sizes[i], Some(pitch));
            let relayout = layouts[i].needs_relayout(&layout);
            if relayout {
                wanted[i] = Some(layout);
            }
            self.stream.learn_pitch(sizes[i], pitch, relayout);
        }
        // With the pitch remembered, every image of a size runs under the layout the next one gets,
        // including the first (measured under the layout without a pitch, a few % off in scale): a
        // tracker's reference frame localized at another scale than the frames compared with it
        // carries a per-marker bias into every displacement.
        let mut redo = Vec::new();
        for &i in todo {
            let target = if self.stream.pitch(sizes[i]).is_some() {
                Some(self.next_layout(sizes[i]))
            } else {
                wanted[i]
            };
            if let Some(target) = target.filter(|t| *t != layouts[i]) {
                layouts[i] = target;
                redo.push((i, target));
            }
        }
        redo
    }

    /// [`decode_pass`](Self::decode_pass) over the whole images picked by `subset` (index into
    /// `images` and `sizes`, layout to run it at), in the order of `subset`; nothing runs for an empty
    /// one.
    fn decode_subset(
        &mut self,
        images: &[&Mat],
        sizes: &[ImageSize],
        subset: &[(usize, InputLayout)],
        min_confidence: f32,
    ) -> Result<Vec<Pass>> {
        if subset.is_empty() {
            return Ok(Vec::new());
        }
        let picked: Vec<&Mat> = subset.iter().map(|&(i, _)| images[i]).collect();
        let picked_sizes: Vec<ImageSize> = subset.iter().map(|&(i, _)| sizes[i]).collect();
        let layouts: Vec<InputLayout> = subset.iter().map(|&(_, l)| l).collect();
        self.decode_pass(
            &picked,
            &vec![None; picked.len()],
            &picked_sizes,
            &layouts,
            min_confidence,
        )
    }

    /// Full localization of a batch of images: network, post-processing and (with MRE) one MRE run
    /// for all images' pending candidates.
    pub fn detect_batch(&mut self, images: &[&Mat]) -> Result<Vec<Vec<Detection>>> {
        Ok(self
            .detect_batch_tiered(images)?
            .into_iter()
            .map(|t| t.accepted)
            .collect())
    }

    /// [`detect_batch`](Self::detect_batch) with each image's rejected candidates as second tier
    /// ([`Selection::finish_tiered`]); same accepted markers, same cost.
    /// The call runs in the span `marknet.postprocess`, the network passes' spans nested in it
    /// (crate docs, "Timing").
    pub fn detect_batch_tiered(&mut self, images: &[&Mat]) -> Result<Vec<TieredDetections>> {
        let _postprocess = tracing::trace_span!("marknet.postprocess").entered();
        self.localize_batch(images)
    }

    /// Localizes a batch: each image on its view's remembered window ([`crate::window`]) where it
    /// has one and the window holds the frame's lattice, else whole. A view's first frame with a
    /// lattice (and a remembered pitch) gives the view its window, and is then localized on it, as
    /// every later frame of the view will be (one scale and sampling for a tracker's reference frame
    /// and the frames compared with it).
    fn localize_batch(&mut self, images: &[&Mat]) -> Result<Vec<TieredDetections>> {
        let sizes = images
            .iter()
            .map(|im| check_image(im))
            .collect::<Result<Vec<_>>>()?;
        let learnt: Vec<Option<LatticeWindow>> = sizes
            .iter()
            .enumerate()
            .map(|(slot, &size)| self.stream.current_window(size, slot))
            .collect();
        let mut found = self.detect_in(images, &learnt)?;
        let fallen: Vec<(usize, Option<LatticeWindow>)> = (0..images.len())
            .filter(|&i| learnt[i].is_some_and(|r| !r.holds(&found[i].accepted, sizes[i])))
            .map(|i| (i, None))
            .collect();
        for (i, again) in self.detect_subset(images, &fallen)? {
            found[i] = again;
        }
        self.learn_windows(images, &sizes, &learnt, &mut found)?;
        Ok(found)
    }

    /// Gives each view without a window (`learnt`) one around the lattice of its markers in `found`,
    /// where it may learn one, and localizes its image again on it, as every later frame of the view
    /// will be; a window that does not hold even there is remembered as none.
    fn learn_windows(
        &mut self,
        images: &[&Mat],
        sizes: &[ImageSize],
        learnt: &[Option<LatticeWindow>],
        found: &mut [TieredDetections],
    ) -> Result<()> {
        let fresh: Vec<(usize, Option<LatticeWindow>)> = (0..images.len())
            .filter(|&i| learnt[i].is_none() && self.may_learn_window(sizes[i], i, found[i].accepted.len()))
            .map(|i| (i, self.window_around(sizes[i], &found[i].accepted)))
            .collect();
        let tried: Vec<(usize, Option<LatticeWindow>)> =
            fresh.iter().copied().filter(|(_, r)| r.is_some()).collect();
        let mut kept = vec![false; images.len()];
        for ((i, window), (_, again)) in tried.iter().zip(self.detect_subset(images, &tried)?) {
            if window.is_some_and(|r| r.holds(&again.accepted, sizes[*i])) {
                kept[*i] = true;
                found[*i] = again;
            }
        }
        for (i, r) in fresh {
            self.stream.learn_window(sizes[i], i, r.filter(|_| kept[i]));
        }
        Ok(())
    }

    /// [`detect_in`](Self::detect_in) over the images picked by `subset` (index into `images`, the
    /// window to run it on, if any): each picked index with its markers.
    fn detect_subset(
        &mut self,
        images: &[&Mat],
        subset: &[(usize, Option<LatticeWindow>)],
    ) -> Result<Vec<(usize, TieredDetections)>> {
        if subset.is_empty() {
            return Ok(Vec::new());
        }
        let picked: Vec<&Mat> = subset.iter().map(|&(i, _)| images[i]).collect();
        let learnt: Vec<Option<LatticeWindow>> = subset.iter().map(|&(_, r)| r).collect();
        let found = self.detect_in(&picked, &learnt)?;
        Ok(subset.iter().map(|&(i, _)| i).zip(found).collect())
    }

    /// Whether view `slot` of images of `size` may learn its window from a frame with `markers`
    /// markers: windows on, the isotropic "auto" fit, a remembered pitch, nothing learnt yet.
    fn may_learn_window(&self, size: ImageSize, slot: usize, markers: usize) -> bool {
        markers >= WINDOW_MIN_MARKERS
            && self.auto_fit().is_some_and(|f| !f.prefer_stretch)
            && self.stream.may_learn_window(size, slot)
    }

    /// The window around `markers` of an image of `size` in the input of the remembered pitch's
    /// layout ([`window::window_around`]).
    fn window_around(&self, size: ImageSize, markers: &[Detection]) -> Option<LatticeWindow> {
        let pitch = self.stream.pitch(size)?;
        let multiple = self.auto_fit()?.multiple;
        window::window_around(markers, size, pitch, &self.next_layout(size), multiple)
    }

    /// Localizes `images` (each whole, or on its remembered window in `learnt`).
    fn detect_in(
        &mut self,
        images: &[&Mat],
        learnt: &[Option<LatticeWindow>],
    ) -> Result<Vec<TieredDetections>> {
        let with_mre = self.mre.is_some();
        let post = self.post;
        let candidates = self.candidates_with_pitch(images, learnt, post.conf_low)?;
        // Per image: its size, the input px per original px of its final layout (for the lattice
        // check) and its candidates' pitch (for the edge margin).
        let frames: Vec<Frame> = candidates
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
            map_images(self.parallel, candidates, |(pass, _)| {
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
        let pitch_and_spread: Vec<(Option<f64>, bool)> =
            frames.iter().map(|f| (f.pitch_px, f.spread)).collect();
        let found: Vec<TieredDetections> = match self.mre.as_mut() {
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
        let close_look = self.close_look;
        found
            .into_iter()
            .zip(images)
            .zip(pitch_and_spread)
            .map(|((found, image), (pitch, spread))| {
                after_the_lattice(found, image, pitch, close_look && !spread)
            })
            .collect()
    }
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

impl Localizer for Marknet {
    fn name(&self) -> &str {
        if self.mre.is_some() {
            "marknet-mre"
        } else {
            "marknet"
        }
    }

    fn detect(&mut self, image: &Mat) -> Result<Vec<Detection>> {
        Ok(self.detect_batch(&[image])?.pop().unwrap_or_default())
    }

    fn mre_band_top(&self) -> Option<f32> {
        self.mre.is_some().then_some(self.post.conf_keep)
    }

    fn set_parallel(&mut self, parallel: bool) {
        Marknet::set_parallel(self, parallel);
    }

    fn fork(&self, intra_threads: usize) -> Option<Result<Box<dyn Localizer + Send>>> {
        Some(
            self.forked(intra_threads)
                .map(|n| Box::new(n) as Box<dyn Localizer + Send>),
        )
    }

    fn detect_stereo(&mut self, pair: &StereoPair<Mat>) -> Result<StereoPair<Vec<Detection>>> {
        let t = self.detect_stereo_tiered(pair)?;
        Ok(StereoPair::new(t.left.accepted, t.right.accepted))
    }

    fn detect_tiered(&mut self, image: &Mat) -> Result<TieredDetections> {
        Ok(self.detect_batch_tiered(&[image])?.pop().unwrap_or_default())
    }

    fn detect_stereo_tiered(&mut self, pair: &StereoPair<Mat>) -> Result<StereoPair<TieredDetections>> {
        crate::check_stereo_sizes(pair)?;
        let mut out = self.detect_batch_tiered(&[&pair.left, &pair.right])?;
        let right = out.pop().unwrap_or_default();
        let left = out.pop().unwrap_or_default();
        Ok(StereoPair::new(left, right))
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
