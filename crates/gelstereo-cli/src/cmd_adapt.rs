//! `gelstereo adapt`: adapts the localizer to the user's own sensor from an unlabelled recording.
//! The work is `gelstereo_apps::adapt::run`; this is its arguments and progress display.

use std::path::PathBuf;

use gelstereo::core::interrupt;
use gelstereo_apps::adapt::{AdaptOptions, Progress};
use indicatif::{ProgressBar, ProgressStyle};

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo adapt`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Model folder to write (marknet.onnx, mre.onnx, MODEL_CARD.md, adapt.json); use it with
    /// `--models DIR`. Never the shipped default data/models, nor the base folder.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// The sensor's marker grid, ROWSxCOLS: views with more pseudo-labels than it holds are left out.
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// Fine-tuning budget, minutes of wall clock (pseudo-labelling and export come on top).
    #[arg(long, default_value_t = 5.0, value_name = "MIN")]
    minutes: f64,
    /// Threads of the fine-tuning (PyTorch).
    #[arg(long = "train-threads", default_value_t = 2, value_name = "N")]
    train_threads: usize,
    /// Seed of the fine-tuning.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// At most this many frames are used, evenly spaced over the recording.
    #[arg(long, default_value_t = 600, value_name = "N")]
    max_frames: usize,
    /// Treat a video as side-by-side stereo (left half, right half).
    #[arg(long)]
    side_by_side: bool,
    /// Python with PyTorch (default: the checkout's .venv/bin/python, made by scripts/setup.sh).
    #[arg(long, value_name = "FILE")]
    python: Option<PathBuf>,
    /// Also keep the pseudo-label dataset (images, labels, ignore masks) in this folder.
    #[arg(long, value_name = "DIR")]
    keep_data: Option<PathBuf>,
    /// Replace an --out folder that an earlier `gelstereo adapt` wrote.
    #[arg(long)]
    force: bool,
    /// The base models (`--models DIR`, default data/models) and localizer options.
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// The recording: a stereo recording folder (left/ and right/), a folder of images, or a video.
    #[arg(value_name = "RECORDING")]
    input: PathBuf,
}

/// Runs `gelstereo adapt`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let style = ProgressStyle::with_template("pseudo-labels {bar:30} {pos}/{len} frames {elapsed}");
    let bar = ProgressBar::new(0).with_style(style.unwrap_or_else(|_| ProgressStyle::default_bar()));
    let report = gelstereo_apps::adapt::run(&options(args)?, interrupt::flag(), &|step| show(&bar, step))?;
    let (out, test) = (args.out.display(), report.self_test);
    eprintln!(
        "wrote {out} in {:.0} s (self-test: {} of {} markers); use it with --models {out}",
        report.seconds, test.found, test.drawn
    );
    Ok(())
}

/// The library's options from the arguments.
fn options(args: &Args) -> anyhow::Result<AdaptOptions> {
    let localizer = args.localizer.config()?;
    let command = std::env::args_os().map(|a| a.to_string_lossy().into_owned());
    Ok(AdaptOptions {
        side_by_side: args.side_by_side,
        grid: args.grid.clone(),
        minutes: args.minutes,
        train_threads: args.train_threads,
        seed: args.seed,
        max_frames: args.max_frames,
        python: args.python.clone(),
        keep_data: args.keep_data.clone(),
        force: args.force,
        command: Some(command.collect::<Vec<_>>().join(" ")),
        ..AdaptOptions::new(args.input.clone(), args.out.clone(), localizer)
    })
}

/// The pseudo-labelling bar, then its summary line.
fn show(bar: &ProgressBar, step: Progress<'_>) {
    match step {
        Progress::Frames { seen, total } => {
            bar.set_length(total.unwrap_or(0) as u64);
            bar.set_position(seen as u64);
        }
        Progress::Labelled { summary, seconds } => {
            bar.finish_and_clear();
            let (frames, counts) = (summary.frames_used, summary.counts_text());
            eprintln!("pseudo-labels from {frames} frames in {seconds:.1} s: {counts}");
        }
    }
}
