//! `gelstereo track`: the whole pipeline over a recording, video or camera, written as
//! `OUT/markers.csv` and `OUT/frames.csv` (DESIGN.md tables, `frames.csv` ending with `t_s,note`),
//! PLY clouds and meshes and overlays every N frames, plots; or streamed as JSON lines. The work is
//! [`gelstereo::track::run`]; this is argument parsing, progress and wiring. SIGINT / SIGTERM stop
//! the run after the frame in flight, with whole tables and the plots of what was processed.
//!
//! Also `gelstereo track --bench`: an alias of the pipeline benchmark `gelstereo bench --calib FILE
//! RECORDING`.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, bail};
use gelstereo::sink::{JsonlSink, OutputFolder, Sink};
use gelstereo::source::FrameSource;
use gelstereo::track::{PREFETCH_FRAMES, SinkOptions, TrackOptions};
use gelstereo::{Method, Pipeline, PipelineConfig, sim::SensorSpec};
use indicatif::{ProgressBar, ProgressStyle};

use crate::cmd_detect::LocalizerArgs;
use crate::pad_border::PadBorder;

/// Arguments of `gelstereo track`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Stereo calibration (OpenCV YAML/XML, or a folder / pair of mrcal .cameramodel files); default:
    /// the recording's calib.yaml. Needed for stereo input, ignored for mono.
    #[arg(long, value_name = "FILE")]
    calib: Option<std::path::PathBuf>,
    /// Output folder: markers.csv, frames.csv, ply/, overlays/, plots/. A folder an earlier run wrote
    /// is emptied of that run's files first; any other non-empty folder needs --force.
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Write into a non-empty output folder gelstereo did not write (only its own files are replaced).
    #[arg(long)]
    force: bool,
    /// Stream one JSON object per frame (schema docs/schema/frame-v1.json: both tables' columns,
    /// markers as column arrays, t_s, note) to standard output (`-`) or a file, flushed per frame. A
    /// reader that closes the stream ends the run quietly.
    #[arg(long, value_name = "FILE|-")]
    jsonl: Option<PathBuf>,
    /// Localization method: blob, marknet or marknet-mre (default: marknet-mre when its models are
    /// installed, else blob).
    #[arg(long)]
    method: Option<Method>,
    /// Marker lattice ROWSxCOLS (default: the recording's meta.json, else 23x23).
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// Read frames from camera N (live), or from two cameras L,R paired by capture time; a camera may
    /// be a video file path.
    #[arg(long, value_name = "N|L,R", value_delimiter = ',')]
    camera: Vec<String>,
    /// Treat the video or camera frames as side-by-side stereo (left half, right half).
    #[arg(long)]
    side_by_side: bool,
    /// Track a stereo recording's left view only, as a mono sensor.
    #[arg(long)]
    mono: bool,
    /// Kept for old scripts: markers cut by the image border are found by default, placed at their
    /// centre, and none whose centre lies outside the image is reported; a number given is ignored.
    #[arg(long, default_value_t, value_name = "auto|PX")]
    pad_border: PadBorder,
    /// Marker pitch, mm: a mono sensor's contact area and centroid in mm; for a stereo grid that
    /// overfills the view without a sensor description, it settles the right view's column offset.
    #[arg(long, value_name = "MM")]
    pitch_mm: Option<f64>,
    #[command(flatten)]
    gel: crate::gel_args::GelArgs,
    /// Sensor description (JSON, as `gelstereo simulate --sensor` takes): its gel's thickness,
    /// modulus, Poisson ratio and friction for the contact mechanics (a flag above must agree), and
    /// for a stereo sensor whose marker grid overfills the cameras' view its lattice, projected
    /// through the calibration, places the visible markers on the sensor's own grid indices. Default: the recording's
    /// meta.json `sensor`. Without one such a recording is indexed from its visible top-left marker.
    #[arg(long, value_name = "FILE")]
    sensor: Option<PathBuf>,
    /// Re-zero the reference at these frames (comma separated): drift correction.
    #[arg(long, value_delimiter = ',', value_name = "FRAME")]
    rezero_at: Vec<u32>,
    /// Stop after this many frames.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Threads that localize the frames after the reference frame ahead of the tracker (0: one per
    /// core for recordings and videos, 1 for live cameras; 1: one frame at a time, its two views in
    /// parallel, the lowest latency per frame). The outputs are the same.
    #[arg(long, default_value_t = 0, value_name = "N", value_parser = gelstereo::core::limits::parse_thread_count)]
    workers: usize,
    /// Write an overlay PNG every N frames (0: none).
    #[arg(long, default_value_t = 10, value_name = "N")]
    overlay_every: usize,
    /// Write a PLY marker cloud and mesh every N stereo frames (0: none).
    #[arg(long, default_value_t = 10, value_name = "N")]
    ply_every: usize,
    /// Do not write PLY files (as --ply-every 0).
    #[arg(long)]
    no_ply: bool,
    /// Coordinates of the PLY files: gel (origin at the centre of the reference surface, z the
    /// gel's normal away from the cameras; the transform is in gel.json) or camera (the left
    /// camera's frame, as markers.csv's X_mm, Y_mm, Z_mm).
    #[arg(long, default_value = "gel", value_name = "FRAME")]
    ply_frame: gelstereo::io::ply::CoordinateFrame,
    /// Length factor of the displacement arrows in the overlays (0 to 1000).
    #[arg(long, default_value_t = 3.0,
          value_parser = |s: &str| gelstereo::core::limits::parse_number_in(s, 0.0, 1000.0))]
    arrow_scale: f64,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Use the ground-truth 2-D marker positions of a simulated RECORDING (its markers.csv, markers
    /// visible in each view) instead of a localizer: measures indexing, tracking, triangulation,
    /// contact and slip alone. Ids are not taken from the truth: the positions are indexed and
    /// tracked like detections.
    #[arg(long)]
    from_ground_truth: bool,
    /// With --from-ground-truth: add Gaussian noise of this standard deviation to each coordinate, px.
    #[arg(long, default_value_t = 0.0, value_name = "PX")]
    gt_noise_px: f64,
    /// Benchmark the stereo pipeline on the recording instead of writing outputs (an alias of
    /// `gelstereo bench --calib FILE RECORDING`): per-stage medians, latency and throughput mode.
    #[arg(long)]
    bench: bool,
    /// Frame-runs timed per mode with --bench (after 20 warm-up runs).
    #[arg(long, default_value_t = 200)]
    bench_frames: usize,
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// A stereo recording (folder with left/ and right/), a folder of images (mono), or a video file.
    #[arg(value_name = "RECORDING|VIDEO")]
    input: Option<PathBuf>,
}

impl Args {
    /// The pipeline these options describe: the recording's own description, then the options.
    pub fn pipeline_config(&self) -> anyhow::Result<PipelineConfig> {
        let mut config = PipelineConfig {
            localizer: self.localizer.config()?,
            method: self.method,
            mono: self.mono,
            ..PipelineConfig::default()
        };
        if let Some(dir) = self.input.as_deref().filter(|p| p.is_dir()) {
            config.apply_recording(dir)?;
        }
        if let Some(c) = &self.calib {
            config.calibration = Some(c.clone());
        }
        if let Some(g) = &self.grid {
            config.grid = Some(gelstereo::parse_grid(g, "--grid")?);
        }
        config.session.planar.pitch_mm = self.pitch_mm;
        if let Some(path) = &self.sensor {
            config.sensor = Some(SensorSpec::load(path)?);
        }
        self.gel.apply(&mut config, self.sensor.as_deref())?;
        Ok(config)
    }

    fn sink_options(&self) -> SinkOptions {
        SinkOptions {
            ply_every: if self.no_ply { 0 } else { self.ply_every },
            ply_frame: self.ply_frame,
            overlay_every: self.overlay_every,
            arrow_scale: self.arrow_scale,
            ..SinkOptions::default()
        }
    }
}

fn open_source(args: &Args) -> anyhow::Result<FrameSource> {
    if !args.camera.is_empty() {
        if args.input.is_some() {
            bail!("give either --camera N (or L,R) or a RECORDING|VIDEO, not both");
        }
        return Ok(FrameSource::open_cameras(&args.camera, args.side_by_side)?);
    }
    let Some(input) = &args.input else {
        bail!(
            "no input: give a stereo recording (left/ and right/), a folder of images, a video file, or --camera N"
        );
    };
    Ok(if args.mono {
        FrameSource::open_left_view(input)?
    } else {
        FrameSource::open_path(input, args.side_by_side)?
    })
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    args.pad_border.note_if_given();
    if args.bench {
        return bench(args);
    }
    if args.out.is_none() && args.jsonl.is_none() {
        bail!(
            "--out DIR is required (where markers.csv, frames.csv, ply/, overlays/ and plots/ go), or --jsonl - to stream"
        )
    }
    let source = open_source(args)?;
    if let Some(warning) = source.order_warning() {
        eprintln!("warning: {warning}");
    }
    let stereo = source.is_stereo();
    let config = args.pipeline_config()?;
    if stereo && config.calibration.is_none() {
        bail!("stereo input needs --calib FILE (or a calib.yaml in the recording)")
    }
    let mut pipeline = Pipeline::new(&config)?;
    let options = TrackOptions {
        max_frames: args.max_frames,
        rezero_at: args.rezero_at.clone(),
        detections: ground_truth(args)?,
        // Live frames want the lowest latency per frame rather than the most frames per second.
        workers: match args.workers {
            0 if !args.camera.is_empty() => 1,
            n => n,
        },
    };
    let (folder, mut sinks) = output_sinks(args, stereo)?;
    let progress = progress_bar(args.quiet, source.len_hint());
    let started = std::time::Instant::now();
    let mut warnings = 0usize;
    let mut frames = source.prefetch(PREFETCH_FRAMES);
    let result = gelstereo::track::run(
        &mut pipeline,
        &mut frames,
        &mut sinks,
        &options,
        gelstereo::core::interrupt::flag(),
        &mut |out| {
            progress.inc(1);
            for line in &out.log {
                progress.suspend(|| eprintln!("{line}"));
            }
            if let Some(note) = &out.note {
                warnings += 1;
                if warnings <= MAX_WARNINGS {
                    progress.suspend(|| {
                        eprintln!(
                            "warning: frame {}: {note}; frame written with its contact unknown (empty cells)",
                            out.frame
                        )
                    });
                }
            }
        },
    );
    progress.finish_and_clear();
    // Said even when the run failed: a truncated video may be why.
    if let Some(shortfall) = frames.finish() {
        eprintln!("warning: {shortfall}");
    }
    let summary = result?;
    if warnings > MAX_WARNINGS {
        eprintln!(
            "warning: {} more warnings of the same kind not shown",
            warnings - MAX_WARNINGS
        );
    }
    report(&summary, started.elapsed().as_secs_f64(), folder.as_deref());
    if summary.interrupted {
        bail!(
            "interrupted by a signal: the outputs hold the {} frames processed",
            summary.frames
        );
    }
    Ok(())
}

/// Where a run writes: its output folder, if any, and every sink.
type Outputs = (Option<Arc<OutputFolder>>, Vec<Box<dyn Sink>>);

/// The output folder (`--out`) with its sinks, and the stream (`--jsonl`).
fn output_sinks(args: &Args, stereo: bool) -> anyhow::Result<Outputs> {
    let folder = match &args.out {
        Some(dir) => {
            let inputs: Vec<&std::path::Path> = args.input.as_deref().into_iter().collect();
            Some(Arc::new(OutputFolder::prepare_apart_from(
                dir, args.force, &inputs,
            )?))
        }
        None => None,
    };
    let mut sinks: Vec<Box<dyn Sink>> = match &folder {
        Some(f) => gelstereo::track::sinks(f, &args.sink_options(), stereo)?,
        None => Vec::new(),
    };
    match args.jsonl.as_deref() {
        Some(p) if p.as_os_str() == "-" => sinks.push(Box::new(JsonlSink::new(
            std::io::stdout(),
            std::path::Path::new("standard output"),
        ))),
        Some(p) => {
            let file = std::fs::File::create(p).with_context(|| format!("cannot create {}", p.display()))?;
            sinks.push(Box::new(JsonlSink::new(file, p)));
        }
        None => {}
    }
    Ok((folder, sinks))
}

/// The progress bar on standard error (hidden for `--quiet`).
fn progress_bar(quiet: bool, frames: Option<usize>) -> ProgressBar {
    let progress = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(frames.unwrap_or(0) as u64)
    };
    progress.set_style(
        ProgressStyle::with_template("{spinner} track [{bar:30}] {pos}/{len} frames {per_sec} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    progress
}

/// The run's closing line: frames, speed, tracking, contact, slip, flags and where outputs went.
fn report(summary: &gelstereo::track::TrackSummary, secs: f64, folder: Option<&OutputFolder>) {
    eprintln!(
        "{}{} frames in {secs:.1} s ({:.1} frames/s): {:.2} % of marker-frames tracked in the left view, {} frames in contact, {} slipping, {} flagged; outputs in {}",
        match (summary.interrupted, summary.reader_closed) {
            (true, _) => "interrupted: ",
            (false, true) => "the stream's reader closed it: ",
            (false, false) => "",
        },
        summary.frames,
        summary.frames as f64 / secs.max(1e-9),
        100.0 * summary.tracked_fraction,
        summary.contact_frames,
        summary.slipping_frames,
        summary.flagged.len(),
        folder.map_or_else(|| "standard output".to_owned(), |f| f.dir().display().to_string())
    );
}

/// Warnings printed one by one; the rest are counted.
const MAX_WARNINGS: usize = 10;

fn ground_truth(
    args: &Args,
) -> anyhow::Result<Option<Vec<gelstereo::core::StereoPair<Vec<gelstereo::core::Detection>>>>> {
    if !args.from_ground_truth {
        return Ok(None);
    }
    let Some(dir) = args.input.as_deref().filter(|p| p.join("markers.csv").is_file()) else {
        bail!("--from-ground-truth needs a simulated recording with a markers.csv");
    };
    Ok(Some(gelstereo_apps::truth::ground_truth(dir, args.gt_noise_px)?))
}

/// `gelstereo track --bench`: an alias of the pipeline benchmark, `gelstereo bench --calib FILE
/// RECORDING` (one implementation, [`gelstereo_apps::bench::pipeline`]).
fn bench(args: &Args) -> anyhow::Result<()> {
    let Some(input) = &args.input else {
        bail!("--bench needs a stereo RECORDING")
    };
    let mut config = args.pipeline_config()?;
    config.method = Some(config.chosen_method());
    let report = gelstereo_apps::bench::pipeline(&gelstereo_apps::bench::PipelineBench {
        recording: input.clone(),
        config,
        frames: 0,
        runs: args.bench_frames,
        warmup: 20,
        workers: 0,
        repeats: 1,
    })?;
    print!("{}", report.text);
    Ok(())
}
