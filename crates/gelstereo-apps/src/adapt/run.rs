//! The whole adaptation, what `gelstereo adapt` runs: checks, pseudo-labels, fine-tuning, the model
//! contract and self-test on the result, `adapt.json`, and the rename into place.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use gelstereo_markers::self_test::{self, SelfTest};
use gelstereo_markers::{Localizer, LocalizerConfig, Method, create_localizer};

use super::labels::{GENERATOR, PseudoLabelConfig, PseudoLabelSummary, write_pseudo_labels};
use super::output::{MANIFEST, Staging, check_output, install, keep_pseudo_labels};
use super::trainer::{FineTuning, find_python};
use gelstereo::file_err;
use gelstereo::{Error, Result, parse_grid};

/// What to adapt, from what, and how. Errors name the `gelstereo adapt` option of the field at fault.
#[derive(Debug, Clone)]
pub struct AdaptOptions {
    /// The recording: a stereo recording folder (`left/`, `right/`), a folder of images, or a video.
    pub input: PathBuf,
    /// Read a video as side-by-side stereo (left half, right half).
    pub side_by_side: bool,
    /// The model folder to write (`--out`): never the shipped `data/models`, nor the base folder.
    pub out: PathBuf,
    /// The base models and localizer settings: `marknet_path` and `mre_path` must be `marknet.onnx`
    /// and `mre.onnx` of one folder, the base folder the fine-tuning starts from.
    pub localizer: LocalizerConfig,
    /// The sensor's marker grid, `ROWSxCOLS` (`--grid`; recorded in `adapt.json` as given): views
    /// with more pseudo-labels than it holds are left out.
    pub grid: Option<String>,
    /// Fine-tuning budget, minutes of wall clock, in (0, 1440] (`--minutes`).
    pub minutes: f64,
    /// PyTorch threads of the fine-tuning (`--train-threads`).
    pub train_threads: usize,
    /// Seed of the fine-tuning (`--seed`).
    pub seed: u64,
    /// At most this many frames, evenly spaced over the recording, at least 3 (`--max-frames`).
    pub max_frames: usize,
    /// Python with PyTorch, ONNX and ONNX Runtime (`--python`); `None`: the checkout's `.venv`.
    pub python: Option<PathBuf>,
    /// Also keep the pseudo-label dataset in this new folder (`--keep-data`).
    pub keep_data: Option<PathBuf>,
    /// Replace an `out` folder an earlier adaptation wrote (`--force`).
    pub force: bool,
    /// The command that asked for the run, quoted in the model card.
    pub command: Option<String>,
}

impl AdaptOptions {
    /// Options with the defaults of `gelstereo adapt`: 5 minutes, 2 threads, seed 0, 600 frames.
    pub fn new(input: PathBuf, out: PathBuf, localizer: LocalizerConfig) -> Self {
        AdaptOptions {
            input,
            side_by_side: false,
            out,
            localizer,
            grid: None,
            minutes: 5.0,
            train_threads: 2,
            seed: 0,
            max_frames: 600,
            python: None,
            keep_data: None,
            force: false,
            command: None,
        }
    }

    /// The base model folder (the one holding `marknet_path`).
    pub fn base_folder(&self) -> PathBuf {
        self.localizer
            .marknet_path
            .parent()
            .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
    }
}

/// Where a run stands, for a progress display.
#[derive(Debug, Clone, Copy)]
pub enum Progress<'a> {
    /// Pseudo-labelling: `seen` frames read of `total` (when the source knows it).
    Frames {
        /// Frames read so far.
        seen: usize,
        /// Frames to read, when known.
        total: Option<usize>,
    },
    /// The pseudo-labels are written, in `seconds`; the fine-tuning starts.
    Labelled {
        /// What pseudo-labelling produced.
        summary: &'a PseudoLabelSummary,
        /// Its wall-clock time, s.
        seconds: f64,
    },
}

/// What a finished run wrote.
#[derive(Debug, Clone)]
pub struct AdaptReport {
    /// The model folder written (absolute).
    pub out: PathBuf,
    /// What pseudo-labelling produced.
    pub summary: PseudoLabelSummary,
    /// The adapted models' self-test.
    pub self_test: SelfTest,
    /// Wall-clock time of the whole run, s.
    pub seconds: f64,
}

/// Adapts the localizer: pseudo-labels `options.input` with the base models, fine-tunes them with the
/// project's Python, checks the result loads under the model contract and passes the self-test,
/// writes `adapt.json` and renames the folder to `options.out`. Every input is checked before any
/// work; everything is written into a temporary sibling of `out` first, so a failed run, or one
/// stopped by `stop` (checked per frame and while training), leaves nothing behind.
pub fn run(
    options: &AdaptOptions,
    stop: &AtomicBool,
    progress: &dyn Fn(Progress<'_>),
) -> Result<AdaptReport> {
    let start = Instant::now();
    check_inputs(options)?;
    let base = options.base_folder();
    check_base_is_a_folder(&options.localizer, &base)?;
    let target = check_output(&options.out, &base, options.force)?;
    let grid_markers = grid_markers(options.grid.as_deref())?;
    let python = find_python(options.python.as_deref())?;
    let mut localizer = marknet_mre(&options.localizer)?;

    let staging = Staging::beside(&target)?;
    let (data, model) = (staging.data(), staging.model());
    let t_label = Instant::now();
    let summary = pseudo_label(options, grid_markers, localizer.as_mut(), &data, stop, progress)?;
    progress(Progress::Labelled {
        summary: &summary,
        seconds: t_label.elapsed().as_secs_f64(),
    });
    FineTuning {
        python: &python,
        data: &data,
        base: &base,
        model: &model,
        minutes: options.minutes,
        threads: options.train_threads,
        seed: options.seed,
        command: options.command.as_deref(),
        name: &options.out,
    }
    .run(stop)?;
    let self_test = check_adapted(&model, &options.localizer)?;
    let manifest = manifest(options, &base, &summary, self_test, start.elapsed().as_secs_f64());
    write_manifest(&model.join(MANIFEST), &manifest)?;
    if let Some(keep) = &options.keep_data {
        keep_pseudo_labels(&data, keep)?;
    }
    install(&model, &target)?;
    Ok(AdaptReport {
        out: target,
        summary,
        self_test,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Refuses a budget outside (0, 1440] minutes, fewer than 3 frames, or a missing recording.
fn check_inputs(options: &AdaptOptions) -> Result<()> {
    if !(options.minutes > 0.0 && options.minutes <= 24.0 * 60.0) {
        return Err(Error::Invalid(format!(
            "--minutes {}: expected a budget in (0, 1440]",
            options.minutes
        )));
    }
    if options.max_frames < 3 {
        return Err(Error::Invalid(format!(
            "--max-frames {}: expected at least 3 (labels are checked against neighbouring frames)",
            options.max_frames
        )));
    }
    if !options.input.exists() {
        return Err(Error::Invalid(format!(
            "{}: no such recording, folder of images or video",
            options.input.display()
        )));
    }
    Ok(())
}

/// Refuses base models that are not `marknet.onnx` and `mre.onnx` of one folder: the trainer starts
/// from the folder.
fn check_base_is_a_folder(localizer: &LocalizerConfig, base: &Path) -> Result<()> {
    if localizer.marknet_path == base.join("marknet.onnx") && localizer.mre_path == base.join("mre.onnx") {
        return Ok(());
    }
    Err(Error::Invalid(
        "--marknet/--mre: give the base models as a folder with --models DIR".into(),
    ))
}

/// The markers the `ROWSxCOLS` grid holds.
fn grid_markers(grid: Option<&str>) -> Result<Option<usize>> {
    grid.map(|g| parse_grid(g, "--grid").map(|shape| shape.count()))
        .transpose()
}

/// Marknet with the MRE, from `config`, with the method and the models named when it fails.
fn marknet_mre(config: &LocalizerConfig) -> Result<Box<dyn Localizer + Send>> {
    let method = Method::MarknetMre;
    create_localizer(method, config).map_err(|e| {
        Error::from(e).context(format!(
            "cannot set up method '{method}' (models: --models DIR, default data/models)"
        ))
    })
}

/// Writes the pseudo-label dataset into `data`, reporting each frame read.
fn pseudo_label(
    options: &AdaptOptions,
    grid_markers: Option<usize>,
    localizer: &mut dyn Localizer,
    data: &Path,
    stop: &AtomicBool,
    progress: &dyn Fn(Progress<'_>),
) -> Result<PseudoLabelSummary> {
    let config = PseudoLabelConfig {
        grid_markers,
        max_frames: options.max_frames,
        ..PseudoLabelConfig::default()
    };
    write_pseudo_labels(
        &options.input,
        options.side_by_side,
        localizer,
        &config,
        data,
        stop,
        &|seen, total| progress(Progress::Frames { seen, total }),
    )
    .map_err(|e| e.context(format!("pseudo-labelling {}", options.input.display())))
}

/// Loads the adapted folder under the model contract and runs the self-test on it.
fn check_adapted(model: &Path, base: &LocalizerConfig) -> Result<SelfTest> {
    let config = LocalizerConfig {
        marknet_path: model.join("marknet.onnx"),
        mre_path: model.join("mre.onnx"),
        remember_pitch: false,
        lattice_window: false,
        ..base.clone()
    };
    let mut adapted =
        marknet_mre(&config).map_err(|e| e.context("the adapted models do not pass the model contract"))?;
    self_test::run(adapted.as_mut())
        .map_err(|e| Error::from(e).context("the adapted models fail the self-test"))
}

/// The contents of `adapt.json`: the source, the base, the budget and what pseudo-labelling and the
/// self-test found.
fn manifest(
    options: &AdaptOptions,
    base: &Path,
    summary: &PseudoLabelSummary,
    test: SelfTest,
    seconds: f64,
) -> serde_json::Value {
    serde_json::json!({
        "generator": GENERATOR,
        "source": options.input.display().to_string(),
        "base": base.display().to_string(),
        "minutes": options.minutes,
        "seed": options.seed,
        "grid": options.grid,
        "frames_used": summary.frames_used,
        "train_views": summary.train_views,
        "train_labels": summary.train_labels,
        "train_ignored": summary.train_ignored,
        "heldout_views": summary.heldout_views,
        "heldout_labels": summary.heldout_labels,
        "heldout_frames": summary.heldout_frames,
        "skipped": summary.skipped,
        "pitch_px": summary.pitch_px,
        "self_test": { "drawn": test.drawn, "found": test.found },
        "seconds": seconds,
    })
}

fn write_manifest(path: &Path, manifest: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(manifest)
        .map_err(|e| Error::Invalid(format!("{}: {e}", path.display())))?;
    std::fs::write(path, text + "\n").map_err(file_err(path))
}
