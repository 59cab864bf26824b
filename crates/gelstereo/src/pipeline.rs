//! [`Pipeline`]: localization in each view, grid indexing of the reference frame (with every
//! fallback), tracking, triangulation, displacement, contact geometry and slip, one frame at a time.

use gelstereo_core::{
    FrameSummary, GridIndex, GridShape, ImageSize, MarkerRecord, MarkerStatus, Point2, SlipState, StereoPair,
    TieredDetections,
};
use gelstereo_markers::{Localizer, Method};
use gelstereo_tracking::{ContactFrame, MonoFrame, StereoFrame, flagged_rows};
use opencv::core::{Mat, MatTraitConst};

use crate::start::{Indexing, Session};
use crate::{Error, PipelineConfig, Result};

/// The images of one frame.
#[derive(Debug)]
pub enum Images {
    /// Both views of a stereo sensor.
    Stereo(StereoPair<Mat>),
    /// A mono sensor's view (or a stereo recording's left view).
    Mono(Mat),
}

impl Images {
    /// The left (or only) view.
    pub fn left(&self) -> &Mat {
        match self {
            Images::Stereo(p) => &p.left,
            Images::Mono(m) => m,
        }
    }
}

/// One frame to process: its images and, when known, its capture time (s, any origin).
#[derive(Debug)]
pub struct Frame {
    /// The images.
    pub images: Images,
    /// Capture time, s (camera clock, video position, ...); `None`: frame number / frame rate.
    pub time_s: Option<f64>,
}

impl Frame {
    /// A stereo frame without a timestamp.
    pub fn stereo(left: Mat, right: Mat) -> Self {
        Self {
            images: Images::Stereo(StereoPair::new(left, right)),
            time_s: None,
        }
    }

    /// A mono frame without a timestamp.
    pub fn mono(image: Mat) -> Self {
        Self {
            images: Images::Mono(image),
            time_s: None,
        }
    }
}

/// What the stages found in one frame, for sinks that draw or export more than the tables.
#[derive(Debug, Clone)]
pub enum Stages {
    /// A stereo frame (its `markers` and `summary` moved into the [`FrameOutput`]).
    Stereo(Box<StereoFrame>),
    /// A mono frame (its `markers` and `summary` moved into the [`FrameOutput`]).
    Mono(Box<MonoFrame>),
}

/// The result of one frame: plain data, `Send`.
#[derive(Debug, Clone)]
pub struct FrameOutput {
    /// Frame number, from 0 (every frame given to the pipeline counts, flagged ones included).
    pub frame: u32,
    /// Seconds from the first frame.
    pub t_s: f64,
    /// One row per tracked id in id order (row-major): grid index, status, position in each view,
    /// 3-D position and displacement (`None` where a view, the stereo stages or the marker lack it).
    /// Empty for a frame flagged before the reference lattice was indexed.
    pub markers: Vec<MarkerRecord>,
    /// Contact (area, depth, centroid) and slip state.
    pub summary: FrameSummary,
    /// The contact region: the ids of the markers in contact.
    pub contact_region: Vec<GridIndex>,
    /// Why the frame is flagged (unreadable, cannot be localized, not the reference lattice...);
    /// `None` for a frame processed normally.
    pub note: Option<String>,
    /// Informational lines (how the reference lattice was indexed, re-zeroing).
    pub log: Vec<String>,
    /// Frames flagged before the reference lattice was indexed, now with a `lost` row per id; they
    /// precede this frame (and were returned before without rows).
    pub earlier: Vec<FrameOutput>,
    /// The reference positions of the left view's markers (px, in id order) this frame was tracked
    /// against; empty for flagged frames.
    pub reference_left_px: Vec<Point2>,
    /// The same for the right view (empty for mono sensors and flagged frames).
    pub reference_right_px: Vec<Point2>,
    /// The stages' own results; `None` for flagged frames.
    pub stages: Option<Stages>,
}

impl FrameOutput {
    /// The slip state.
    pub fn slip(&self) -> SlipState {
        self.summary.slip
    }

    /// Flags a frame whose markers say nothing of the contact: its contact figures become
    /// unknown, per frame and per marker, and the stages' results are dropped (no PLY, height map
    /// or plot is drawn from them).
    fn forget_contact(&mut self, note: String) {
        self.summary = FrameSummary::unmeasured(self.frame);
        self.contact_region.clear();
        self.stages = None;
        for m in &mut self.markers {
            (m.pressure_kpa, m.in_contact, m.slipping) = (None, None, None);
        }
        self.note = Some(note);
    }

    fn with_stages(self, stages: Stages) -> Self {
        Self {
            stages: Some(stages),
            ..self
        }
    }

    /// A frame's rows with nothing attached: no contact region, note, log, earlier frames,
    /// reference positions or stages' results.
    pub(crate) fn rows(frame: u32, t_s: f64, markers: Vec<MarkerRecord>, summary: FrameSummary) -> Self {
        Self {
            frame,
            t_s,
            markers,
            summary,
            contact_region: Vec::new(),
            note: None,
            log: Vec::new(),
            earlier: Vec::new(),
            reference_left_px: Vec::new(),
            reference_right_px: Vec::new(),
            stages: None,
        }
    }

    fn flagged(frame: u32, t_s: f64, note: String, ids: Option<&[GridIndex]>) -> Self {
        let (markers, summary) = flagged_rows(ids.unwrap_or(&[]), frame);
        Self {
            note: Some(note),
            ..Self::rows(frame, t_s, markers, summary)
        }
    }
}

/// Share of a frame's ids that must be measured (tracked in every view) for its contact to mean
/// anything: a black, grey or noise frame, or a view covered, leaves the tracker predicting
/// markers from nothing.
const MIN_TRACKED_SHARE: f64 = 0.25;

/// Why a frame's markers cannot be used (`None` when they can): fewer than [`MIN_TRACKED_SHARE`]
/// of its ids tracked.
fn unusable(markers: &[MarkerRecord]) -> Option<String> {
    let tracked = markers
        .iter()
        .filter(|m| m.status == Some(MarkerStatus::Tracked))
        .count();
    (!markers.is_empty() && (tracked as f64) < MIN_TRACKED_SHARE * markers.len() as f64).then(|| {
        format!(
            "no usable markers: {tracked} of {} tracked, the contact is unknown",
            markers.len()
        )
    })
}

/// The whole pipeline, built once (models loaded, calibration read), then fed frame by frame.
/// The first frame that can be indexed is the reference (no contact): marker ids are its grid
/// indices, displacement is measured against it. Frames before it, and frames that cannot be read or
/// localized, come back flagged ([`FrameOutput::note`]) rather than as errors.
///
/// Per frame it runs one chain of stages: **localize** ([`FrameLocalizer`]: both views' markers) ->
/// **index** ([`Indexing`], on the reference frame only: grid ids, and for stereo the pairing of the
/// views) -> the tracking session, stereo: **track** -> **triangulate** -> **contact** -> **slip**
/// ([`gelstereo_tracking::StereoSession`]), mono: track -> in-plane contact and slip.
pub struct Pipeline {
    localize: FrameLocalizer,
    index: Indexing,
    method: Method,
    /// The tracked lattice: the grid given, then the visible part once a grid that overfills the
    /// view was indexed.
    shape: GridShape,
    mono: bool,
    frame_rate_hz: f64,
    session: Option<Session>,
    reference_size: Option<ImageSize>,
    pending: Vec<FrameOutput>,
    latest_contact: Option<ContactFrame>,
    rezero_requested: bool,
    next_frame: u32,
    first_time_s: Option<f64>,
}

impl Pipeline {
    /// Builds the pipeline: loads the calibration (when given), the localizer's models and the sensor
    /// description's lattice.
    pub fn new(config: &PipelineConfig) -> Result<Self> {
        let localizer = crate::localizer(config.chosen_method(), &config.localizer)?;
        Self::with_localizer(config, localizer)
    }

    /// Builds the pipeline around a localizer built elsewhere (`config.method` and
    /// `config.localizer` are then not used).
    pub fn with_localizer(config: &PipelineConfig, mut localizer: Box<dyn Localizer + Send>) -> Result<Self> {
        let index = Indexing::new(config)?;
        // One frame at a time: the two views' stages in parallel where a core is free (same results).
        join_rayon_pool();
        localizer.set_parallel(true);
        Ok(Self {
            localize: FrameLocalizer { localizer },
            shape: index.shape(),
            index,
            method: config.chosen_method(),
            mono: config.mono,
            frame_rate_hz: config.frame_rate_hz,
            session: None,
            reference_size: None,
            pending: Vec::new(),
            latest_contact: None,
            rezero_requested: false,
            next_frame: 0,
            first_time_s: None,
        })
    }

    /// The localization method in use.
    pub fn method(&self) -> Method {
        self.method
    }

    /// Whether stereo frames can be processed (a calibration is loaded and the pipeline is not mono).
    pub fn is_stereo(&self) -> bool {
        self.index.rig().is_some() && !self.mono
    }

    /// Whether the reference lattice has been indexed.
    pub fn is_started(&self) -> bool {
        self.session.is_some()
    }

    /// The tracked lattice (the visible part once a grid that overfills the view was indexed).
    pub fn shape(&self) -> GridShape {
        self.shape
    }

    /// The tracked ids, in id order (empty before the reference frame).
    pub fn ids(&self) -> &[GridIndex] {
        self.session.as_ref().map_or(&[], Session::ids)
    }

    /// The triangles of the reference marker surface (lattice linear indices), for meshes; empty
    /// for mono sensors and before the reference frame.
    pub fn surface_triangles(&self) -> &[[u32; 3]] {
        match &self.session {
            Some(Session::Stereo(s)) => s.surface().triangles(),
            _ => &[],
        }
    }

    /// The contact mechanics' settings: the gel's facts and the friction coefficient.
    pub fn contact_config(&self) -> &gelstereo_tracking::ContactConfig {
        self.index.contact_config()
    }

    /// The gel frame in the left camera frame; `None` for mono sensors and before the reference
    /// frame.
    pub fn gel_frame(&self) -> Option<gelstereo_tracking::GelFrame> {
        match &self.session {
            Some(Session::Stereo(s)) => Some(s.surface().gel_frame()),
            _ => None,
        }
    }

    /// The localizer (e.g. its name and MRE band).
    pub fn localizer(&self) -> &dyn Localizer {
        self.localize.localizer.as_ref()
    }

    /// The localizer, mutable (e.g. to localize a frame outside [`Self::process`]).
    pub fn localizer_mut(&mut self) -> &mut (dyn Localizer + Send) {
        self.localize.localizer.as_mut()
    }

    /// Makes the current shape of the gel the new reference from the next frame on (drift
    /// correction): displacement, contact and slip are measured against it.
    pub fn rezero(&mut self) {
        self.rezero_requested = true;
    }

    /// Processes one frame: the size checks, localization, tracking; a frame that does not fit the
    /// calibration or the first frame, or cannot be localized, comes back flagged.
    pub fn process(&mut self, frame: &Frame) -> Result<FrameOutput> {
        let located = self
            .check_size(&frame.images)
            .and_then(|()| self.localize(&frame.images));
        match located {
            Ok(dets) => self.track_checked(frame, dets),
            Err(e) => Ok(self.flag(frame.time_s, e.full_message())),
        }
    }

    /// Processes one frame whose markers were found elsewhere (e.g. ground truth of a simulated
    /// recording): the images are checked and kept for the stages, not localized.
    pub fn process_detected(
        &mut self,
        frame: &Frame,
        dets: StereoPair<TieredDetections>,
    ) -> Result<FrameOutput> {
        match self.check_size(&frame.images) {
            Ok(()) => self.track_checked(frame, dets),
            Err(e) => Ok(self.flag(frame.time_s, e.full_message())),
        }
    }

    /// A frame whose size was checked, and its markers: tracked (the reference frame indexed first).
    fn track_checked(&mut self, frame: &Frame, dets: StereoPair<TieredDetections>) -> Result<FrameOutput> {
        let frame_no = self.next_frame;
        let t_s = self.time_of(frame.time_s);
        self.next_frame += 1;
        let mut log = Vec::new();
        let mut earlier = Vec::new();
        if self.session.is_none()
            && let Some(flagged) = self.start_session(frame_no, t_s, frame, &dets, &mut log, &mut earlier)
        {
            return Ok(flagged);
        }
        self.rezero_if_requested(frame_no, &mut log)?;
        let Some(session) = self.session.as_mut() else {
            return Err(Error::Invalid(
                "no session after indexing the reference frame".into(),
            ));
        };
        let mut out = track_session(session, &frame.images, &dets, frame_no, t_s, &self.shape)?;
        if let Some(note) = unusable(&out.markers) {
            out.forget_contact(note);
        }
        // The contact a re-zero starts from: the last stereo frame whose markers could be used
        // (an unusable frame's stages are gone).
        if let Some(Stages::Stereo(st)) = &out.stages {
            self.latest_contact = Some(st.contact.clone());
        }
        out.log = log;
        out.earlier = earlier;
        Ok(out)
    }

    /// Indexes the reference lattice on this frame and starts the session, logging how; the frames
    /// flagged before it come back in `earlier` with a lost row per marker. Returns the flagged
    /// frame when the lattice cannot be indexed here (it is kept to come back later).
    fn start_session(
        &mut self,
        frame_no: u32,
        t_s: f64,
        frame: &Frame,
        dets: &StereoPair<TieredDetections>,
        log: &mut Vec<String>,
        earlier: &mut Vec<FrameOutput>,
    ) -> Option<FrameOutput> {
        let (session, notes) = match self.index.run(&frame.images, dets, self.reference_size) {
            Ok(started) => started,
            Err(e) => {
                let note = format!("cannot index the reference lattice: {}", e.full_message());
                let out = FrameOutput::flagged(frame_no, t_s, note, None);
                self.pending.push(out.clone());
                return Some(out);
            }
        };
        log.extend(
            notes
                .into_iter()
                .map(|n| format!("reference frame {frame_no}: {n}")),
        );
        self.shape = session.shape();
        log.push(format!(
            "reference frame {frame_no}: {} markers indexed on the {}x{} lattice ({})",
            session.ids().len(),
            self.shape.rows,
            self.shape.cols,
            self.method
        ));
        for mut f in self.pending.drain(..) {
            (f.markers, f.summary) = flagged_rows(session.ids(), f.frame);
            earlier.push(f);
        }
        self.session = Some(session);
        None
    }

    /// Makes the current shape the reference when [`Self::rezero`] asked for it (a stereo session
    /// from the last usable frame's contact).
    fn rezero_if_requested(&mut self, frame_no: u32, log: &mut Vec<String>) -> Result<()> {
        if !std::mem::take(&mut self.rezero_requested) {
            return Ok(());
        }
        match self.session.as_mut() {
            Some(Session::Stereo(st)) => {
                if let Some(c) = &self.latest_contact {
                    st.rezero(c)?;
                }
            }
            Some(Session::Mono(m)) => m.rezero(),
            None => return Ok(()),
        }
        log.push(format!("frame {frame_no}: reference re-zeroed"));
        Ok(())
    }

    /// Processes every frame of `frames` (a [`crate::source::FrameSource`] or its
    /// [`crate::source::Prefetch`]), calling `on_frame` with each result in order (frames that
    /// cannot be read come flagged); returns the number of frames.
    pub fn for_each(
        &mut self,
        frames: impl IntoIterator<Item = crate::source::SourceFrame>,
        mut on_frame: impl FnMut(&FrameOutput),
    ) -> Result<usize> {
        let mut n = 0;
        for f in frames {
            let time_s = Some(f.time_s);
            let out = match f.images {
                Ok(images) => self.process(&Frame { images, time_s })?,
                Err(e) => self.flag(time_s, e.full_message()),
            };
            out.earlier.iter().for_each(&mut on_frame);
            on_frame(&out);
            n += 1;
        }
        Ok(n)
    }

    /// Records a frame that could not be read (`reason` names the file and the problem): it comes
    /// back flagged, with a `lost` row per id, and counts as a frame.
    pub fn flag(&mut self, time_s: Option<f64>, reason: String) -> FrameOutput {
        let frame_no = self.next_frame;
        let t_s = self.time_of(time_s);
        self.next_frame += 1;
        match &self.session {
            Some(s) => FrameOutput::flagged(frame_no, t_s, reason, Some(s.ids())),
            None => {
                let out = FrameOutput::flagged(frame_no, t_s, reason, None);
                self.pending.push(out.clone());
                out
            }
        }
    }

    fn time_of(&mut self, time_s: Option<f64>) -> f64 {
        let t = time_s.unwrap_or(f64::from(self.next_frame) / self.frame_rate_hz.max(1e-9));
        let first = *self.first_time_s.get_or_insert(t);
        t - first
    }

    /// Checks the frame against the calibration and the first frame's size.
    fn check_size(&mut self, images: &Images) -> Result<()> {
        let size = image_size(images.left());
        if let Images::Stereo(pair) = images {
            let right = image_size(&pair.right);
            if right != size {
                return Err(Error::Invalid(format!(
                    "left and right images differ in size ({}x{} vs {}x{})",
                    size.width, size.height, right.width, right.height
                )));
            }
            let Some(rig) = self.index.rig().filter(|_| !self.mono) else {
                return Err(Error::Invalid(
                    "stereo frames need a calibration (or a mono pipeline)".into(),
                ));
            };
            rig.check_image_sizes(size, size)
                .map_err(|e| Error::from(e).context("the frame does not match the calibration"))?;
        }
        match self.reference_size {
            Some(r) if r != size => Err(Error::Invalid(format!(
                "image size {}x{} differs from the first frame's {}x{}",
                size.width, size.height, r.width, r.height
            ))),
            Some(_) => Ok(()),
            None => {
                self.reference_size = Some(size);
                Ok(())
            }
        }
    }

    fn localize(&mut self, images: &Images) -> Result<StereoPair<TieredDetections>> {
        self.localize.localize(images)
    }

    /// A localizer for a worker thread that localizes frames of this pipeline's stream ahead of it
    /// ([`FrameLocalizer`]), its network on `intra_threads` ONNX Runtime threads; `None` when the
    /// pipeline's localizer cannot be forked ([`Localizer::fork`]).
    pub fn fork_localizer(&self, intra_threads: usize) -> Option<Result<FrameLocalizer>> {
        let forked = self.localize.localizer.fork(intra_threads)?;
        Some(
            forked
                .map_err(Error::from)
                .map(|localizer| FrameLocalizer { localizer }),
        )
    }

    /// A frame and its localization (by [`Self::process`], or by a [`FrameLocalizer`] of this
    /// pipeline on another thread): tracked, or flagged when it does not fit the calibration or the
    /// first frame (that reason first) or could not be localized.
    pub fn process_localized(
        &mut self,
        frame: &Frame,
        found: Result<StereoPair<TieredDetections>>,
    ) -> Result<FrameOutput> {
        match found {
            Ok(dets) => self.process_detected(frame, dets),
            Err(e) => {
                let reason = match self.check_size(&frame.images) {
                    Err(size) => size.full_message(),
                    Ok(()) => e.full_message(),
                };
                Ok(self.flag(frame.time_s, reason))
            }
        }
    }
}

/// The "localize" stage: the markers of a frame's views, found by the pipeline's localizer. The
/// pipeline runs one; [`Pipeline::fork_localizer`] makes more, for threads that localize frames of
/// its stream ahead of it (hand their results to [`Pipeline::process_localized`]).
pub struct FrameLocalizer {
    localizer: Box<dyn Localizer + Send>,
}

impl FrameLocalizer {
    /// The markers of both views (stereo) or of the image (mono).
    pub fn localize(&mut self, images: &Images) -> Result<StereoPair<TieredDetections>> {
        localize_with(self.localizer.as_mut(), images)
    }
}

/// The markers of `images` as the pipeline localizes them: both views in one batch, or the mono
/// image (markers cut by the border are the localizer's to place).
fn localize_with(
    localizer: &mut (dyn Localizer + Send),
    images: &Images,
) -> Result<StereoPair<TieredDetections>> {
    Ok(match images {
        Images::Stereo(pair) => localizer.detect_stereo_tiered(pair)?,
        Images::Mono(m) => StereoPair::new(localizer.detect_tiered(m)?, TieredDetections::default()),
    })
}

/// One frame through a started session: tracked, triangulated (stereo), contact and slip, as a
/// [`FrameOutput`] (its log and earlier frames still empty).
fn track_session(
    session: &mut Session,
    images: &Images,
    dets: &StereoPair<TieredDetections>,
    frame_no: u32,
    t_s: f64,
    shape: &GridShape,
) -> Result<FrameOutput> {
    match (session, images) {
        (Session::Stereo(st), Images::Stereo(_)) => {
            let reference_left_px = st.left().reference_px().to_vec();
            let reference_right_px = st.right().reference_px().to_vec();
            let mut tracked = st.track_tiered(frame_no, &dets.left, &dets.right)?;
            let markers = std::mem::take(&mut tracked.markers);
            Ok(FrameOutput {
                contact_region: region(st.ids(), shape, &tracked.contact.in_contact),
                reference_left_px,
                reference_right_px,
                ..FrameOutput::rows(frame_no, t_s, markers, tracked.summary.clone())
            }
            .with_stages(Stages::Stereo(Box::new(tracked))))
        }
        (Session::Mono(m), Images::Mono(_)) => {
            let reference_left_px = m.tracker().reference_px().to_vec();
            let mut tracked = m.track_tiered(frame_no, &dets.left)?;
            let ids = m.tracker().ids().iter().zip(&tracked.planar.in_contact);
            let markers = std::mem::take(&mut tracked.markers);
            Ok(FrameOutput {
                contact_region: ids.filter(|(_, c)| **c).map(|(i, _)| *i).collect(),
                reference_left_px,
                ..FrameOutput::rows(frame_no, t_s, markers, tracked.summary.clone())
            }
            .with_stages(Stages::Mono(Box::new(tracked))))
        }
        _ => Err(Error::Invalid(format!(
            "frame {frame_no}: a mono frame in a stereo session or the reverse"
        ))),
    }
}

/// The ids whose lattice position is in contact.
fn region(ids: &[GridIndex], shape: &GridShape, in_contact: &[bool]) -> Vec<GridIndex> {
    ids.iter()
        .copied()
        .filter(|i| {
            shape
                .linear(*i)
                .and_then(|l| in_contact.get(l))
                .copied()
                .unwrap_or(false)
        })
        .collect()
}

/// The size of an image (0 for an empty one).
pub fn image_size(m: &Mat) -> ImageSize {
    ImageSize {
        width: m.cols().max(0) as u32,
        height: m.rows().max(0) as u32,
    }
}

/// Makes the calling thread one of the threads of rayon's global pool (a no-op once that pool
/// exists). The two views' parallel stages of one frame then start on this thread and hand one half
/// to the pool's other thread; from outside the pool each stage would wait for a pool thread to
/// wake up first, and gain nothing when none wakes in time.
pub fn join_rayon_pool() {
    // An error means the pool exists already (started by an earlier call): nothing to do.
    let _ = rayon::ThreadPoolBuilder::new()
        .use_current_thread()
        .build_global();
}
