//! The Marknet localizer (with its MRE, `marknet-mre`): batched inference of both stereo views on its
//! [`Network`](crate::network) under the layouts of [`crate::layout`], decoding and post-processing.
//!
//! The default [`InputFit::Auto`] of a dynamic-input model scales isotropically
//! so that the marker pitch lands where the network was trained, measured on a first pass and
//! remembered per image size; a fixed-input model gets the contract's whole-image stretch.
//! Outputs are mapped back with `x_orig = (x_in - offset_x) * W / scaled_width - 0.5` (likewise y).

use std::path::Path;

use gelstereo_core::{Detection, ImageSize, Point2, StereoPair, TieredDetections};
use opencv::core::Mat;

use crate::close_look::{SQUEEZED_NN_PITCH, close_look_input, close_look_zoom, merge, squeezed_region_of};
use crate::finish::finish_passes;
use crate::layout::{
    COARSE_PROBE_SCALE, FINE_PROBE_SCALE, InputFit, InputLayout, MAX_RELAYOUTS, MIN_PITCH_SUPPORT, ModelFit,
    PROBE_MIN_COVER, PROBE_MIN_GAIN, PROBE_SCALE, decode_in_layout, input_per_px, probe_layout_at,
};
use crate::mre::Mre;
use crate::network::{Network, input_dims, map_images};
use crate::onnx::SessionOptions;
use crate::pass::Pass;
use crate::postprocess::DecodeGeometry;
use crate::region::Region;
use crate::spacing::nearest_neighbour_distances;
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

/// The Marknet localizer: `marknet` (c > `conf_marknet_only`) or, with an [`Mre`], `marknet-mre`.
pub struct Marknet {
    net: Network,
    options: SessionOptions,
    post: PostProcess,
    mre: Option<Mre>,
    /// How images are fitted to the network input.
    fit: ModelFit,
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
            .field("fit", &self.fit.fit)
            .field("mre", &self.mre)
            .finish()
    }
}

impl Marknet {
    /// Loads `path` and checks its contract; the localizer is `marknet` until [`with_mre`](Self::with_mre).
    pub fn load(path: &Path, options: &SessionOptions) -> Result<Self> {
        let net = Network::load(path, options)?;
        let c = &net.contract;
        let fit = ModelFit {
            fit: InputFit::Auto,
            input_width: c.input_width,
            input_height: c.input_height,
            auto_fit: c.auto_fit,
        };
        Ok(Self {
            options: *options,
            post: net.contract.postprocess,
            net,
            mre: None,
            fit,
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
        self.fit.fit = fit;
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

    /// The layout of an image of `size` given its marker pitch (used by the "auto" fit only).
    pub fn layout(&self, size: ImageSize, pitch_px: Option<f64>) -> InputLayout {
        self.fit.layout(size, pitch_px)
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
        let stretch_to = self.fit.stretch_to();
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
        let Some(fit) = self.fit.auto().copied() else {
            return Ok(found.into_iter().zip(layouts).collect());
        };
        let (iw, ih) = (self.fit.input_width, self.fit.input_height);
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
            && self.fit.auto().is_some_and(|f| !f.prefer_stretch)
            && self.stream.may_learn_window(size, slot)
    }

    /// The window around `markers` of an image of `size` in the input of the remembered pitch's
    /// layout ([`window::window_around`]).
    fn window_around(&self, size: ImageSize, markers: &[Detection]) -> Option<LatticeWindow> {
        let pitch = self.stream.pitch(size)?;
        let multiple = self.fit.auto()?.multiple;
        window::window_around(markers, size, pitch, &self.next_layout(size), multiple)
    }

    /// Localizes `images` (each whole, or on its remembered window in `learnt`).
    fn detect_in(
        &mut self,
        images: &[&Mat],
        learnt: &[Option<LatticeWindow>],
    ) -> Result<Vec<TieredDetections>> {
        let post = self.post;
        let passes = self.candidates_with_pitch(images, learnt, post.conf_low)?;
        finish_passes(
            passes,
            images,
            &post,
            self.mre.as_mut(),
            self.close_look,
            self.parallel,
        )
    }
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
