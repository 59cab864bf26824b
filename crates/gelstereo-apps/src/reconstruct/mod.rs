//! Localization, grid indexing, left/right pairing and triangulation of a stereo recording or of
//! one stereo pair, what `gelstereo reconstruct` runs: [`run`] writes `OUT/markers.csv`
//! (docs/design.md per-frame marker table, displacement and status empty), `OUT/rejected_pairs.csv`
//! (markers seen in both views but not triangulated, with the reason), one binary PLY point cloud per
//! frame (`OUT/ply/NNNNNN.ply`) and, for a simulated recording, its comparison with the ground truth
//! (`OUT/evaluation.json`). The per-frame work is [`StereoReconstructor`].

mod evaluation;
mod input;
mod output;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use gelstereo_core::{Detection, GridShape, StereoPair};
use gelstereo_geometry::{StereoRig, TriangulationConfig};
use gelstereo_io::video;
use gelstereo_markers::{LocalizerConfig, Method};
use gelstereo_matching::eval::{Evaluation, GroundTruth};
use gelstereo_matching::{StereoConfig, StereoPrior, StereoReconstructor};
use gelstereo_sensor::RecordingMeta;

pub use evaluation::EvaluationReport;
pub use input::Perturbation;

use gelstereo::{Error, Result};
use input::{FrameInput, LazyLocalizer};
use output::{EVALUATION_FILE, MARKERS_FILE, OutputFiles, REJECTIONS_FILE};

/// What [`run`] reconstructs, and how. [`ReconstructionJob::new`] gives `gelstereo reconstruct`'s
/// defaults.
#[derive(Debug, Clone)]
pub struct ReconstructionJob {
    /// Stereo calibration: OpenCV YAML/XML, or a folder / comma-separated pair of mrcal files.
    pub calibration: PathBuf,
    /// A stereo recording (folder with `left/` and `right/`), a side-by-side stereo video, or
    /// `[LEFT, RIGHT]`: two images (one stereo frame) or two folders of images with matching names.
    pub inputs: Vec<PathBuf>,
    /// The output folder.
    pub out: PathBuf,
    /// Write into an output folder that gelstereo did not write (only the files it writes are
    /// replaced).
    pub force: bool,
    /// Localization method.
    pub method: Method,
    /// Model paths, blob parameters and ONNX Runtime options of the localizer.
    pub localizer: LocalizerConfig,
    /// Take the ground-truth 2-D positions of a simulated recording (markers visible in each view)
    /// instead of a localizer, perturbed by this; they are indexed like detections (their ids are not
    /// used). `None`: localize.
    pub from_ground_truth: Option<Perturbation>,
    /// The marker lattice; `None`: the recording's `meta.json`, else 23 x 23. A lattice other than
    /// the one `meta.json` names is an error.
    pub grid: Option<GridShape>,
    /// The no-contact reference frame (number in sorted order) that defines the marker ids.
    pub reference: usize,
    /// Seed each frame's indexing with the previous frame's (else the reference alone).
    pub use_prior: bool,
    /// Pairing: epipolar tolerance and indexing settings.
    pub stereo: StereoConfig,
    /// Triangulation: reprojection error bound.
    pub triangulation: TriangulationConfig,
    /// Write the per-frame PLY point clouds.
    pub write_ply: bool,
    /// Compare with the ground truth of a simulated recording (`evaluation.json`).
    pub evaluate: bool,
}

impl ReconstructionJob {
    /// Reconstructs `inputs` with `calibration` into `out`: Marknet-MRE with the shipped models,
    /// frame 0 as the reference, each frame seeded by the previous one, pairs within 3 px of their
    /// epipolar line and points within 2 px of reprojection error, point clouds written.
    pub fn new(calibration: impl Into<PathBuf>, inputs: Vec<PathBuf>, out: PathBuf) -> Self {
        Self {
            calibration: calibration.into(),
            inputs,
            out,
            force: false,
            method: Method::MarknetMre,
            localizer: gelstereo::models::localizer_config(),
            from_ground_truth: None,
            grid: None,
            reference: 0,
            use_prior: true,
            stereo: StereoConfig::default(),
            triangulation: TriangulationConfig::default(),
            write_ply: true,
            evaluate: false,
        }
    }

    /// The recording folder or video, when one input is given.
    fn recording(&self) -> Option<&Path> {
        match self.inputs.as_slice() {
            [one] => Some(one),
            _ => None,
        }
    }
}

/// What [`run`] did.
#[derive(Debug, Clone)]
pub struct ReconstructionSummary {
    /// Stereo frames of the input.
    pub frames: usize,
    /// Frames reconstructed (fewer than `frames` when stopped).
    pub processed: usize,
    /// The marker lattice.
    pub shape: GridShape,
    /// Markers with a 3-D position, all frames together.
    pub reconstructed: usize,
    /// Markers seen in both views without a 3-D position, all frames together.
    pub rejected_pairs: usize,
    /// Localization time, all frames together, ms.
    pub localize_ms: f64,
    /// Indexing, pairing and triangulation time, all frames together, ms.
    pub match_ms: f64,
    /// The marker table written.
    pub markers_csv: PathBuf,
    /// The table of rejected pairs written.
    pub rejections_csv: PathBuf,
    /// The folder of the point clouds, when written.
    pub ply_dir: Option<PathBuf>,
    /// The comparison with the ground truth, when asked for and the run was not stopped.
    pub evaluation: Option<EvaluationReport>,
}

impl ReconstructionSummary {
    /// Whether the run stopped before the last frame.
    pub fn interrupted(&self) -> bool {
        self.processed < self.frames
    }

    /// The run in one line: markers per frame, times per frame, files written.
    pub fn describe(&self) -> String {
        let n = self.frames as f64;
        format!(
            "{} frames, {}x{} lattice: {:.1} markers reconstructed per frame ({} pairs rejected in all); \
             localization {:.2} ms/frame, indexing+pairing+triangulation {:.3} ms/frame; wrote {}{}",
            self.frames,
            self.shape.rows,
            self.shape.cols,
            self.reconstructed as f64 / n,
            self.rejected_pairs,
            self.localize_ms / n,
            self.match_ms / n,
            self.markers_csv.display(),
            self.ply_dir
                .as_ref()
                .map_or_else(String::new, |d| format!(" and {}/", d.display()))
        )
    }
}

/// Runs `job`: reads the frames, indexes the reference frame, then reconstructs and writes every
/// frame. Stops at the next frame boundary when `stop` is raised (the tables then hold the frames
/// done). `warn` receives what the caller should show but is no error (a video shorter than declared).
pub fn run(
    job: &ReconstructionJob,
    stop: &AtomicBool,
    warn: &mut dyn FnMut(String),
) -> Result<ReconstructionSummary> {
    let rig = StereoRig::load(&job.calibration).map_err(|e| {
        Error::from(e).context(format!(
            "cannot load the calibration '{}'",
            job.calibration.display()
        ))
    })?;
    let shape = lattice_shape(job, &rig)?;
    let truth = ground_truth(job)?;
    let mut localizer = LazyLocalizer::new(job.method, &job.localizer);
    let mut localize_ms = 0.0;
    let frames = read_frames(job, &rig, truth.as_ref(), &mut localizer, &mut localize_ms, warn)?;
    let reference = reference_frame(&frames, job.reference)?;
    let (reference_dets, _) = input::detect(reference, &rig, &job.calibration, &mut localizer)?;
    let reconstructor = reference_lattice(job, &rig, shape, reference.frame, &reference_dets)?;
    let inputs: Vec<&Path> = job.inputs.iter().map(PathBuf::as_path).collect();
    let mut files = OutputFiles::create(&job.out, job.write_ply, job.force, &inputs)?;
    let mut summary = ReconstructionSummary {
        frames: frames.len(),
        processed: 0,
        shape,
        reconstructed: 0,
        rejected_pairs: 0,
        localize_ms,
        match_ms: 0.0,
        markers_csv: job.out.join(MARKERS_FILE),
        rejections_csv: job.out.join(REJECTIONS_FILE),
        ply_dir: files.ply_dir(),
        evaluation: None,
    };
    let r_px = match_radius_px(&reconstructor);
    let mut evaluation = Evaluation::default();
    let mut prior: Option<StereoPrior> = None;
    for input in &frames {
        if stop.load(Ordering::SeqCst) {
            break;
        }
        let (dets, ms) = input::detect(input, &rig, &job.calibration, &mut localizer)?;
        summary.localize_ms += ms;
        let t = Instant::now();
        let rec = reconstructor
            .reconstruct(&dets.left, &dets.right, prior.as_ref())
            .map_err(|e| Error::from(e).context(format!("frame {}", input.frame)))?;
        summary.match_ms += t.elapsed().as_secs_f64() * 1e3;
        if job.use_prior {
            prior = Some(rec.matched.to_prior());
        }
        summary.reconstructed += rec.reconstructed_count();
        summary.rejected_pairs += files.write_frame(input.frame, &rec)?;
        if let Some(truth) = truth.as_ref().filter(|_| job.evaluate) {
            evaluation.add_frame(truth, input.frame, &rec, &r_px);
        }
        summary.processed += 1;
    }
    if job.evaluate && !summary.interrupted() {
        let report = EvaluationReport::new(&evaluation, &r_px, summary.match_ms / frames.len() as f64);
        let text = serde_json::to_string_pretty(&report.json)
            .map_err(|e| Error::Invalid(format!("cannot format the evaluation: {e}")))?;
        files.write_text(EVALUATION_FILE, &text)?;
        summary.evaluation = Some(report);
    }
    Ok(summary)
}

/// The lattice: `job.grid` (checked against the recording's `meta.json`), else the recording's, else
/// 23 x 23; the recording's image size is checked against the calibration.
fn lattice_shape(job: &ReconstructionJob, rig: &StereoRig) -> Result<GridShape> {
    let meta = match job.recording().filter(|p| p.is_dir()) {
        Some(dir) => RecordingMeta::read(dir)?,
        None => None,
    };
    let shape = match (job.grid, &meta) {
        (Some(shape), Some(meta)) => {
            meta.check_grid(shape)?;
            shape
        }
        (Some(shape), None) => shape,
        (None, meta) => meta.as_ref().and_then(|m| m.grid).unwrap_or(GridShape::REFERENCE),
    };
    if let Some(size) = meta.as_ref().and_then(|m| m.image_size) {
        rig.check_image_sizes(size, size).map_err(|e| {
            Error::from(e).context("the recording's meta.json image size does not match the calibration")
        })?;
    }
    Ok(shape)
}

/// The simulator's ground truth of the recording, when the job needs it.
fn ground_truth(job: &ReconstructionJob) -> Result<Option<GroundTruth>> {
    if job.from_ground_truth.is_none() && !job.evaluate {
        return Ok(None);
    }
    let Some(dir) = job.recording() else {
        return Err(Error::Invalid(
            "--from-ground-truth and --evaluate need a simulated RECORDING folder, not LEFT RIGHT".into(),
        ));
    };
    GroundTruth::read(dir).map(Some).map_err(|e| {
        Error::from(e).context(format!(
            "--from-ground-truth / --evaluate need the simulator's ground truth in {}",
            dir.display()
        ))
    })
}

/// The input's frames: ground truth, a localized video, or image pairs to localize.
fn read_frames(
    job: &ReconstructionJob,
    rig: &StereoRig,
    truth: Option<&GroundTruth>,
    localizer: &mut LazyLocalizer<'_>,
    localize_ms: &mut f64,
    warn: &mut dyn FnMut(String),
) -> Result<Vec<FrameInput>> {
    if let (Some(perturbation), Some(truth)) = (&job.from_ground_truth, truth) {
        return Ok(input::ground_truth_frames(truth, perturbation));
    }
    match job.recording() {
        Some(path) if path.is_file() && video::has_video_extension(path) => {
            let (frames, shortfall) =
                input::localized_video(path, rig, &job.calibration, localizer, localize_ms)?;
            if let Some(warning) = shortfall {
                warn(warning);
            }
            Ok(frames)
        }
        _ => input::image_frames(&job.inputs),
    }
}

/// Frame `reference` of `frames`.
fn reference_frame(frames: &[FrameInput], reference: usize) -> Result<&FrameInput> {
    if frames.is_empty() {
        return Err(Error::Invalid("the input holds no stereo frames".into()));
    }
    frames.get(reference).ok_or_else(|| {
        Error::Invalid(format!(
            "--reference {reference}: the input has only {} frames",
            frames.len()
        ))
    })
}

/// The reconstructor whose lattices the reference frame's detections define.
fn reference_lattice(
    job: &ReconstructionJob,
    rig: &StereoRig,
    shape: GridShape,
    frame: u32,
    dets: &StereoPair<Vec<Detection>>,
) -> Result<StereoReconstructor> {
    StereoReconstructor::new(
        rig,
        &dets.left,
        &dets.right,
        shape,
        job.stereo.clone(),
        job.triangulation,
    )
    .map_err(|e| {
        Error::from(e).context(format!(
            "indexing the reference frame {frame} ({} left / {} right markers) as a {}x{} lattice",
            dets.left.len(),
            dets.right.len(),
            shape.rows,
            shape.cols
        ))
    })
}

/// The match radius of the evaluation in each view: a quarter of the reference lattice's pitch
/// (docs/design.md "Metrics").
fn match_radius_px(reconstructor: &StereoReconstructor) -> StereoPair<f64> {
    let lattice = reconstructor.lattice();
    StereoPair::new(
        0.25 * lattice.left().pitch_px(),
        0.25 * lattice.right().pitch_px(),
    )
}
