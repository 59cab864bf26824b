//! `gelstereo bench`, three benchmarks, all in [`gelstereo_apps::bench`]:
//! - localization (`--dataset DATA`, or recordings / images without `--calib`): latency of each
//!   method per view and per stereo pair against the blob baseline;
//! - the whole stereo pipeline (`--calib FILE RECORDING` or `--pipeline RECORDING`; also
//!   `gelstereo track --bench`): per-stage medians of `Pipeline::process`, latency and throughput mode;
//! - `--track RECORDING`: `gelstereo track` end to end from disk with its default outputs.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use gelstereo::PipelineConfig;
use gelstereo::markers::Method;
use gelstereo_apps::bench::{PipelineBench, localization};

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo bench`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Take stereo pairs from this dataset (written by `gelstereo simulate`): its --split's experiments.
    #[arg(long, value_name = "DIR")]
    dataset: Option<PathBuf>,
    /// Dataset split to take pairs from.
    #[arg(long, default_value = "test")]
    split: String,
    /// Number of distinct stereo pairs to cycle through.
    #[arg(long, default_value_t = 8)]
    pairs: usize,
    /// Comma-separated methods; `blob` is always measured too (it is the reference).
    #[arg(long, default_value = "blob,marknet,marknet-mre")]
    methods: String,
    /// Timed runs per method and per measurement (after the warm-up); pipeline benchmark: timed
    /// frame-runs per mode.
    #[arg(long, default_value_t = 200)]
    runs: usize,
    /// Untimed warm-up runs per method (pipeline benchmark: frame-runs before the latency mode).
    #[arg(long, default_value_t = 20)]
    warmup: usize,
    /// Also write the figures as JSON here (`--json` is the same option).
    #[arg(long, alias = "json", value_name = "FILE.json")]
    out: Option<PathBuf>,
    /// Pipeline benchmark: the stereo calibration (OpenCV YAML/XML, or a folder / pair of mrcal
    /// .cameramodel files). With it, INPUT is one stereo recording and the whole pipeline is timed.
    #[arg(long, value_name = "FILE")]
    calib: Option<std::path::PathBuf>,
    /// Pipeline benchmark with the recording's own calib.yaml (as --calib RECORDING/calib.yaml).
    #[arg(long)]
    pipeline: bool,
    /// `gelstereo track` end to end on RECORDING: read and decoded from disk, the pipeline, the
    /// default outputs written (tables, plots, PLY and overlays every 10 frames); --runs timed runs
    /// over the whole recording, median frames/s and CPU time per frame.
    #[arg(long)]
    track: bool,
    /// Pipeline benchmark: the localization method (blob, yolo, marknet or marknet-mre).
    #[arg(long, default_value = "marknet-mre")]
    method: Method,
    /// Pipeline benchmark: distinct frames loaded from frame 0 on, walked forth and back (0: all).
    #[arg(long, default_value_t = 0)]
    frames: usize,
    /// Pipeline benchmark: marker lattice ROWSxCOLS (default: the recording's meta.json, else 23x23).
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// Pipeline benchmark: worker threads of the throughput mode; --track: localization threads of
    /// `gelstereo track`'s default mode (0: one per core; at most 256).
    #[arg(long, default_value_t = 0, value_name = "N", value_parser = gelstereo::core::limits::parse_thread_count)]
    workers: usize,
    /// Pipeline benchmark: run the throughput mode this many times, each with fresh workers, and
    /// report the median CPU per frame and frames/s with their range (a shared machine's speed moves
    /// from one run to the next).
    #[arg(long, default_value_t = 1, value_name = "N", value_parser = clap::value_parser!(u16).range(1..))]
    repeats: u16,
    #[command(flatten)]
    localizer: LocalizerArgs,
    #[command(flatten)]
    gel: crate::gel_args::GelArgs,
    /// Stereo recordings (folders with left/ and right/) or images (consecutive images form pairs);
    /// with --calib or --pipeline: one stereo recording.
    #[arg(value_name = "INPUT")]
    inputs: Vec<PathBuf>,
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.track {
        return run_end_to_end(args);
    }
    if args.calib.is_some() || args.pipeline {
        let [recording] = args.inputs.as_slice() else {
            bail!(
                "the pipeline benchmark (--calib / --pipeline) takes exactly one stereo RECORDING, got {}",
                args.inputs.len()
            );
        };
        if args.dataset.is_some() {
            bail!("--dataset is for the localization benchmark; the pipeline benchmark takes one RECORDING");
        }
        let mut config = pipeline_config(args, recording)?;
        if let Some(g) = &args.grid {
            config.grid = Some(gelstereo::parse_grid(g, "--grid")?);
        }
        let report = gelstereo_apps::bench::pipeline(&PipelineBench {
            recording: recording.clone(),
            config,
            frames: args.frames,
            runs: args.runs,
            warmup: args.warmup,
            workers: args.workers,
            repeats: usize::from(args.repeats),
        })?;
        return write_report(&report, args.out.as_deref());
    }
    if args.runs < 1 {
        bail!("--runs must be at least 1");
    }
    let mut methods = Method::parse_list(&args.methods)?;
    if !methods.contains(&Method::Blob) {
        methods.insert(0, Method::Blob);
    }
    let pairs = localization::load_pairs(args.dataset.as_deref(), &args.split, &args.inputs, args.pairs)?;
    let report = localization::run(&localization::LocalizationBench {
        pairs,
        methods,
        config: args.localizer.config()?,
        runs: args.runs,
        warmup: args.warmup,
        blob_params: args.localizer.blob_params.clone(),
        one_recording: localization::one_recording(args.dataset.as_deref(), &args.inputs),
    })?;
    write_report(&report, args.out.as_deref())
}

/// The pipeline the options describe on `recording` (its own calibration unless --calib).
fn pipeline_config(args: &Args, recording: &Path) -> anyhow::Result<PipelineConfig> {
    let mut config = PipelineConfig::for_recording(recording)?;
    config.calibration = args.calib.clone().or(config.calibration);
    config.method = Some(args.method);
    config.localizer = args.localizer.config()?;
    args.gel.apply(&mut config, None)?;
    Ok(config)
}

/// Prints a benchmark's table, and writes its figures as JSON to `out` when given.
fn write_report(report: &gelstereo_apps::bench::Report, out: Option<&Path>) -> anyhow::Result<()> {
    print!("{}", report.text);
    if let Some(out) = out {
        let pretty = serde_json::to_string_pretty(&report.json).context("cannot format the JSON report")?;
        std::fs::write(out, pretty + "\n").with_context(|| format!("cannot write {}", out.display()))?;
    }
    Ok(())
}

/// `gelstereo bench --track RECORDING`: `gelstereo track` end to end with its default outputs.
fn run_end_to_end(args: &Args) -> anyhow::Result<()> {
    let [recording] = args.inputs.as_slice() else {
        bail!("--track takes exactly one RECORDING, got {}", args.inputs.len());
    };
    let config = pipeline_config(args, recording)?;
    let scratch = tempfile::tempdir().context("cannot create a folder for the outputs")?;
    let report = gelstereo_apps::bench::end_to_end(&gelstereo_apps::bench::EndToEndBench {
        recording: recording.clone(),
        config,
        sinks: gelstereo::track::SinkOptions::default(),
        runs: args.runs,
        out: scratch.path().join("out"),
        workers: args.workers,
    })?;
    write_report(&report, args.out.as_deref())
}
