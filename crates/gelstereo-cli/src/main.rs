//! `gelstereo`: the command-line tool. Thin: argument parsing, progress and error context; the work is
//! done by the library crates.

use std::process::ExitCode;

use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};
use gelstereo::core::interrupt;

mod cmd_adapt;
mod cmd_bench;
mod cmd_calibrate;
mod cmd_calibrate_gel;
mod cmd_capture;
mod cmd_detect;
mod cmd_doctor;
mod cmd_eval;
mod cmd_reconstruct;
mod cmd_simulate;
mod cmd_track;
mod gel_args;
mod pad_border;
mod project;

/// Stereo visuotactile reconstruction for GelStereo-type tactile sensors.
#[derive(Parser)]
#[command(name = "gelstereo", about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Check every component a user needs and say how to fix what is missing.
    Doctor(cmd_doctor::Args),
    /// Find markers in images, videos or stereo recordings; write image,x,y,confidence CSV.
    Detect(cmd_detect::Args),
    /// The paper's Table I (easy / hard / contact precision, recall, loss) on a simulated dataset.
    Eval(cmd_eval::Args),
    /// Localization latency per view and per stereo pair, each method against the blob baseline; with
    /// --calib FILE RECORDING: the whole stereo pipeline, per stage, latency and throughput mode.
    Bench(cmd_bench::Args),
    /// Stereo checkerboard calibration: OpenCV YAML/XML or a mrcal pair, with RMS and epipolar errors.
    Calibrate(cmd_calibrate::Args),
    /// Find the gel's Young's modulus from a press of known force; write a gel file for `track --gel`.
    CalibrateGel(cmd_calibrate_gel::Args),
    /// Save camera frames (one side-by-side camera, or two cameras L,R) as a stereo recording.
    Capture(cmd_capture::Args),
    /// Simulate a GelStereo sensor: stereo recordings with exact ground truth, split train/val/test.
    Simulate(cmd_simulate::Args),
    /// Track markers over a recording, video or camera: displacement, contact geometry, slip; CSV,
    /// PLY, overlays and plots (`--bench`: pipeline timings).
    Track(cmd_track::Args),
    /// Localize, index, pair and triangulate a stereo recording: OUT/markers.csv and one PLY per frame.
    Reconstruct(cmd_reconstruct::Args),
    /// Adapt the localizer to your own sensor from an unlabelled recording (pseudo-labels from the
    /// default's sure, lattice-consistent, tracked markers; a few minutes of CPU fine-tuning): a model
    /// folder for --models.
    Adapt(cmd_adapt::Args),
}

fn main() -> ExitCode {
    // Loading ONNX Runtime for the banner costs time: only when the banner is asked for.
    // `args_os`: a path that is not UTF-8 is a valid argument (clap reads paths as `OsString`).
    let wants_version = std::env::args_os().skip(1).any(|a| a == "--version" || a == "-V");
    let version = if wants_version {
        project::version_text()
    } else {
        env!("CARGO_PKG_VERSION").to_owned()
    };
    let matches = Cli::command().version(version).get_matches();
    let cli = match Cli::from_arg_matches(&matches) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    // Before any thread pool exists: rayon and OpenMP read these when their first pool starts.
    if let Err(e) = gelstereo::core::limits::check_thread_env() {
        eprintln!("error: {e}");
        return ExitCode::FAILURE;
    }
    if matches!(
        cli.command,
        Command::Simulate(_)
            | Command::Detect(_)
            | Command::Reconstruct(_)
            | Command::Track(_)
            | Command::Capture(_)
            | Command::Adapt(_)
    ) {
        stop_at_frame_boundary_on_signals();
    }
    let result = match cli.command {
        Command::Doctor(args) => cmd_doctor::run(&args),
        Command::Detect(args) => cmd_detect::run(&args),
        Command::Eval(args) => cmd_eval::run(&args),
        Command::Bench(args) => cmd_bench::run(&args),
        Command::Calibrate(args) => cmd_calibrate::run(&args),
        Command::CalibrateGel(args) => cmd_calibrate_gel::run(&args),
        Command::Capture(args) => cmd_capture::run(&args),
        Command::Simulate(args) => cmd_simulate::run(&args),
        Command::Track(args) => cmd_track::run(&args),
        Command::Reconstruct(args) => cmd_reconstruct::run(&args),
        Command::Adapt(args) => cmd_adapt::run(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", one_line(&e));
            if interrupt::requested() {
                ExitCode::from(interrupt::EXIT_INTERRUPTED)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}

/// `error` and its causes in one line, each said once: many errors repeat their cause's text in
/// their own message ("FILE: No such file or directory"), and anyhow's `{:#}` would print it again.
fn one_line(error: &anyhow::Error) -> String {
    let mut text = error.to_string();
    for cause in error.chain().skip(1) {
        let more = cause.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
    }
    text
}

/// SIGINT, SIGTERM and SIGHUP ask the running command to stop at its next frame boundary (its outputs
/// stay whole; see `gelstereo::core::interrupt`); a second signal ends the process at once.
fn stop_at_frame_boundary_on_signals() {
    let installed = ctrlc::set_handler(|| {
        if interrupt::requested() {
            std::process::exit(i32::from(interrupt::EXIT_INTERRUPTED));
        }
        interrupt::request();
    });
    if let Err(e) = installed {
        eprintln!(
            "warning: cannot handle interruption signals ({e}); an interrupted run may leave partial files"
        );
    }
}
