//! [`run`]: frames from a source through the [`Pipeline`] into sinks, what `gelstereo track` does
//! (and what its benchmark times). Stops early, cleanly, when the `stop` flag is raised (a signal
//! handler sets it), or when the reader of a stream sink closes it (`--jsonl - | head -1`): the
//! sinks are finished with what was processed.

use std::sync::atomic::{AtomicBool, Ordering};

use gelstereo_core::{Detection, MarkerStatus, SlipState, StereoPair};

use crate::sink::{FrameContext, Sink};
use crate::source::SourceFrame;
use crate::{Error, Frame, FrameOutput, Pipeline, Result, Stages};

mod ahead;

/// How [`run`] goes over the frames.
#[derive(Debug, Clone, Default)]
pub struct TrackOptions {
    /// Stop after this many frames.
    pub max_frames: Option<usize>,
    /// Re-zero the reference at these frame numbers (drift correction).
    pub rezero_at: Vec<u32>,
    /// Per frame, the markers to use instead of localizing (ground truth of a simulated recording).
    pub detections: Option<Vec<StereoPair<Vec<Detection>>>>,
    /// Threads that localize the frames after the reference frame ahead of the tracker, each with
    /// its own localizer at one ONNX Runtime thread (0: one per core; 1: every frame localized in
    /// turn by the pipeline's own localizer, its views in parallel). The outputs are the same.
    pub workers: usize,
}

impl TrackOptions {
    /// The number of localization threads [`run`] starts (`workers`, 0 resolved to the cores).
    pub fn localization_threads(&self) -> usize {
        match self.workers {
            0 => std::thread::available_parallelism().map_or(1, std::num::NonZero::get),
            n => n,
        }
    }
}

/// What a run did.
#[derive(Debug, Clone, Default)]
pub struct TrackSummary {
    /// Frames processed (flagged ones included).
    pub frames: usize,
    /// Frames flagged, with why.
    pub flagged: Vec<String>,
    /// Marker-frames tracked in the left view / visible there.
    pub tracked_fraction: f64,
    /// Frames with contact.
    pub contact_frames: usize,
    /// Frames in partial or gross slip.
    pub slipping_frames: usize,
    /// Whether the run stopped on the `stop` flag before the source ended.
    pub interrupted: bool,
    /// Whether the run stopped because the reader of a stream sink closed it: the frames it read
    /// are whole, and the other sinks hold the frames processed.
    pub reader_closed: bool,
    /// Whether a reference lattice was indexed.
    pub started: bool,
}

/// Runs `frames` through `pipeline` into `sinks`, calling `on_frame` after each frame (progress,
/// warnings). Stops at the end of the source, after `options.max_frames`, when `stop` is raised, or
/// when a sink's reader closes its stream ([`Error::ReaderClosed`], not an error of the run); the
/// sinks are finished in every case but an error. Frames up to the reference frame are
/// localized in turn; the later ones ahead of the tracker by `options.workers` threads when the
/// pipeline's localizer can be forked ([`Pipeline::fork_localizer`]).
pub fn run(
    pipeline: &mut Pipeline,
    frames: impl Iterator<Item = SourceFrame> + Send,
    sinks: &mut [Box<dyn Sink + '_>],
    options: &TrackOptions,
    stop: &AtomicBool,
    on_frame: &mut dyn FnMut(&FrameOutput),
) -> Result<TrackSummary> {
    let mut run = Run {
        pipeline,
        sinks,
        options,
        on_frame,
        summary: TrackSummary::default(),
        tracked: 0,
        visible: 0,
    };
    let mut frames = frames.take(options.max_frames.unwrap_or(usize::MAX));
    let mut interrupted = false;
    while !run.pipeline.is_started() {
        let Some(frame) = frames.next() else { break };
        if stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        run.frame(frame, None)?;
        if run.summary.reader_closed {
            break;
        }
    }
    let ended = interrupted || run.summary.reader_closed;
    let workers = if ended || !run.pipeline.is_started() || options.detections.is_some() {
        Vec::new()
    } else {
        fork_workers(run.pipeline, options.localization_threads())?
    };
    if workers.len() > 1 {
        ahead::localize_ahead(frames, workers, stop, &mut |frame, found| {
            if stop.load(Ordering::SeqCst) {
                interrupted = true;
                return Ok(false);
            }
            run.frame(frame, found)?;
            Ok(!run.summary.reader_closed)
        })?;
        interrupted |= stop.load(Ordering::SeqCst);
    } else if !ended {
        for frame in frames {
            if stop.load(Ordering::SeqCst) {
                interrupted = true;
                break;
            }
            run.frame(frame, None)?;
            if run.summary.reader_closed {
                break;
            }
        }
    }
    run.finish(interrupted)
}

/// `n` forked localizers of `pipeline`, one ONNX Runtime thread each; none when `n` < 2 or the
/// localizer cannot be forked.
fn fork_workers(pipeline: &Pipeline, n: usize) -> Result<Vec<crate::FrameLocalizer>> {
    if n < 2 {
        return Ok(Vec::new());
    }
    (0..n)
        .map_while(|_| pipeline.fork_localizer(1))
        .collect::<Result<Vec<_>>>()
}

/// The state of one [`run`].
struct Run<'a, 's> {
    pipeline: &'a mut Pipeline,
    sinks: &'a mut [Box<dyn Sink + 's>],
    options: &'a TrackOptions,
    on_frame: &'a mut dyn FnMut(&FrameOutput),
    summary: TrackSummary,
    tracked: usize,
    visible: usize,
}

impl Run<'_, '_> {
    /// One frame: localized here unless `found` holds its markers, tracked, written to the sinks.
    fn frame(&mut self, source_frame: SourceFrame, found: ahead::Found) -> Result<()> {
        let pipeline = &mut *self.pipeline;
        let frame_no = source_frame.index as u32;
        if self.options.rezero_at.contains(&frame_no) {
            pipeline.rezero();
        }
        let time_s = Some(source_frame.time_s);
        let (out, frame) = match source_frame.images {
            Ok(images) => {
                let frame = Frame { images, time_s };
                let out = match (&self.options.detections, found) {
                    (Some(all), _) => match all.get(frame_no as usize) {
                        Some(d) => {
                            let dets = StereoPair::new(d.left.clone().into(), d.right.clone().into());
                            pipeline.process_detected(&frame, dets)?
                        }
                        None => pipeline.flag(time_s, format!("no ground truth for frame {frame_no}")),
                    },
                    (None, Some(found)) => pipeline.process_localized(&frame, found)?,
                    (None, None) => pipeline.process(&frame)?,
                };
                (out, Some(frame))
            }
            Err(e) => (pipeline.flag(time_s, e.full_message()), None),
        };
        for earlier in &out.earlier {
            let ctx = FrameContext {
                output: earlier,
                images: None,
                pipeline,
            };
            write(self.sinks, &ctx, &mut self.summary.reader_closed)?;
        }
        let summary = &mut self.summary;
        if !pipeline.is_started() {
            // Flagged before the reference lattice: its rows follow once the ids are known.
            summary.frames += 1;
            summary.flagged.extend(out.note.clone());
            (self.on_frame)(&out);
            return Ok(());
        }
        let ctx = FrameContext {
            output: &out,
            images: frame.as_ref().map(|f| &f.images),
            pipeline,
        };
        write(self.sinks, &ctx, &mut summary.reader_closed)?;
        summary.frames += 1;
        summary.flagged.extend(out.note.clone());
        summary.contact_frames += usize::from(out.summary.contact);
        summary.slipping_frames += usize::from(matches!(
            out.summary.slip,
            SlipState::PartialSlip | SlipState::GrossSlip
        ));
        let left = match &out.stages {
            Some(Stages::Stereo(st)) => Some(&st.left),
            Some(Stages::Mono(m)) => Some(&m.track),
            None => None,
        };
        if let Some(l) = left {
            self.tracked += l.count(MarkerStatus::Tracked);
            self.visible += l.markers.len();
        }
        (self.on_frame)(&out);
        Ok(())
    }

    /// The summary, after the sinks are finished; an error when no reference frame was indexed.
    fn finish(mut self, interrupted: bool) -> Result<TrackSummary> {
        let mut summary = std::mem::take(&mut self.summary);
        summary.interrupted = interrupted;
        summary.started = self.pipeline.is_started();
        if !summary.started {
            return Err(Error::Invalid(format!(
                "no frame could be indexed as the reference lattice ({} frames read): {}",
                summary.frames,
                summary.flagged.last().map_or("no frames", String::as_str)
            )));
        }
        for s in self.sinks.iter_mut() {
            s.finish()?;
        }
        summary.tracked_fraction = self.tracked as f64 / self.visible.max(1) as f64;
        Ok(summary)
    }
}

/// Gives `frame` to every sink. A sink whose reader closed its stream sets `reader_closed` and the
/// others still take the frame, so that they end on the same frame.
fn write(sinks: &mut [Box<dyn Sink + '_>], frame: &FrameContext, reader_closed: &mut bool) -> Result<()> {
    for sink in sinks.iter_mut() {
        match sink.frame(frame) {
            Err(Error::ReaderClosed { .. }) => *reader_closed = true,
            written => written?,
        }
    }
    Ok(())
}

/// Frames read and decoded ahead of the pipeline by [`crate::source::Prefetch`] (bounded: memory
/// stays flat over any recording length).
pub const PREFETCH_FRAMES: usize = 4;

/// Which outputs `gelstereo track` writes.
#[derive(Debug, Clone)]
pub struct SinkOptions {
    /// `markers.csv` and `frames.csv`.
    pub tables: bool,
    /// The run's plots.
    pub plots: bool,
    /// A PLY marker cloud and mesh every N stereo frames (0: none).
    pub ply_every: usize,
    /// The frame of the PLYs' coordinates (the gel's by default).
    pub ply_frame: gelstereo_io::ply::CoordinateFrame,
    /// Overlays every N frames (0: none).
    pub overlay_every: usize,
    /// Length factor of the displacement arrows in the overlays.
    pub arrow_scale: f64,
}

impl Default for SinkOptions {
    /// Tables and plots; a PLY pair and an overlay every 10 frames (a long recording's folder stays
    /// small, a short one still shows a few); arrows three times the displacement.
    fn default() -> Self {
        Self {
            tables: true,
            plots: true,
            ply_every: 10,
            ply_frame: gelstereo_io::ply::CoordinateFrame::Gel,
            overlay_every: 10,
            arrow_scale: 3.0,
        }
    }
}

impl SinkOptions {
    /// The outputs in words.
    pub fn describe(&self) -> String {
        let every = |n: usize| match n {
            0 => "none".to_owned(),
            1 => "every frame".to_owned(),
            n => format!("every {n} frames"),
        };
        let ply_frame = match (self.ply_every, self.ply_frame) {
            (0, _) => "",
            (_, gelstereo_io::ply::CoordinateFrame::Gel) => " (gel frame)",
            (_, gelstereo_io::ply::CoordinateFrame::LeftCamera) => " (left camera frame)",
        };
        format!(
            "tables {}, plots {}, PLY {}{ply_frame}, overlays {}",
            if self.tables { "yes" } else { "no" },
            if self.plots { "yes" } else { "no" },
            every(self.ply_every),
            every(self.overlay_every)
        )
    }
}

/// The sinks of `options` writing into `folder` (`stereo`: with the depth plot).
pub fn sinks(
    folder: &std::sync::Arc<crate::sink::OutputFolder>,
    options: &SinkOptions,
    stereo: bool,
) -> Result<Vec<Box<dyn Sink>>> {
    use crate::sink::{GelSink, HeightMapSink, OverlaySink, PlotSink, PlySink, TableSink};
    let mut sinks: Vec<Box<dyn Sink>> = Vec::new();
    if options.tables {
        sinks.push(Box::new(TableSink::create(folder)?));
    }
    // The gel frame's transform goes with every output written in it.
    if stereo && (options.tables || options.ply_every > 0) {
        sinks.push(Box::new(GelSink::new(folder.clone())));
    }
    if options.ply_every > 0 && stereo {
        sinks.push(Box::new(PlySink::new(
            folder.clone(),
            options.ply_every,
            options.ply_frame,
        )));
        sinks.push(Box::new(HeightMapSink::new(folder.clone(), options.ply_every)));
    }
    if options.overlay_every > 0 {
        sinks.push(Box::new(OverlaySink::new(
            folder.clone(),
            options.overlay_every,
            options.arrow_scale,
        )));
    }
    if options.plots {
        sinks.push(Box::new(PlotSink::new(
            folder.clone(),
            stereo,
            options.overlay_every,
        )));
    }
    Ok(sinks)
}
