//! `gelstereo simulate`: the synthetic GelStereo sensor writes a dataset of stereo recordings with
//! exact ground truth (see `docs/sim.md`). The work is `gelstereo::sim::dataset`; this is argument
//! parsing and a progress bar.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use gelstereo::sim::SensorSpec;
use gelstereo::sim::checkerboard::write_checkerboard_set;
use gelstereo::sim::dataset::{DatasetConfig, Randomization, write_dataset};
use indicatif::{ProgressBar, ProgressStyle};

/// Arguments of `gelstereo simulate`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Output folder (refused when it exists and is not empty, unless --force).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Number of experiments (recordings), split 6:2:2 into train / val / test.
    #[arg(long, default_value_t = 10, value_name = "N")]
    experiments: u32,
    /// Stereo frames per experiment (frame 0 is the no-contact reference).
    #[arg(long, default_value_t = 80, value_name = "N")]
    frames_per_experiment: u32,
    /// Master seed: the same seed gives the same bytes.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Sensor description file (default: the reference sensor, calib/reference-sensor.json).
    #[arg(long, value_name = "FILE.json")]
    sensor: Option<PathBuf>,
    /// Domain randomisation: off (reference look), appearance (random looks), full (random looks and
    /// 30 % of the experiments on random sensor variants: other grids, resolutions, pitches; 10 % on
    /// GelSight-Mini-like sensors), wide (the sensors users have: pitch 8-100 px, images up to
    /// 1920x1080, hexagonal and irregular lattices, round and trapezoidal membranes in a housing,
    /// hue-only markers, scan lines, banding, moire, Newton rings, fingerprints, glints), rims
    /// (wide's sensors and looks under flat punches, hexagons and boxes pressed into a gel that
    /// spreads more, whose rims squeeze the dots around them into touching dashes).
    #[arg(long, default_value = "full")]
    randomization: String,
    /// Write only this split's experiments (train, val or test): the same files as in the whole
    /// dataset of these arguments, for a test set without simulating the training data.
    #[arg(long, value_name = "SPLIT")]
    split: Option<String>,
    /// Every experiment presses this indenter (its size is still drawn): sphere, flat_cylinder,
    /// side_cylinder, cube_edge, cube_corner, cone, prism, hexagon, star, cross, nut, groove, text,
    /// bumpy or fingertip. Default: the experiments cycle through all of them.
    #[arg(long, value_name = "SHAPE")]
    indenter: Option<String>,
    /// Every experiment makes this motion: press, press-slide, press-twist or press-slide-twist.
    /// Default: drawn per experiment.
    #[arg(long, value_name = "KIND")]
    motion: Option<String>,
    /// Instead of gel recordings, write a checkerboard calibration set seen through the sensor's
    /// cameras: the board's INNER corners, COLSxROWS (as `gelstereo calibrate --board`).
    #[arg(long, value_name = "COLSxROWS")]
    checkerboard: Option<String>,
    /// Checkerboard square side, mm.
    #[arg(long, default_value_t = 1.5, requires = "checkerboard", value_name = "MM")]
    square_mm: f64,
    /// Number of checkerboard poses (stereo pairs).
    #[arg(long, default_value_t = 20, requires = "checkerboard", value_name = "N")]
    poses: usize,
    /// Replace a non-empty output folder.
    #[arg(long)]
    force: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

/// Runs `gelstereo simulate`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let sensor = match &args.sensor {
        Some(path) => SensorSpec::load(path)?,
        None => SensorSpec::reference(),
    };
    if let Some(spec) = &args.checkerboard {
        let board = gelstereo::geometry::Board::parse(spec, args.square_mm)?;
        let built = sensor.build()?;
        let start = Instant::now();
        write_checkerboard_set(&args.out, &built, &board, args.poses, args.seed, args.force)
            .with_context(|| format!("writing checkerboard images into {}", args.out.display()))?;
        eprintln!(
            "wrote {} checkerboard stereo pairs ({spec} inner corners, {} mm squares) with their true \
             calibration and corners.csv to {} in {:.1} s",
            args.poses,
            args.square_mm,
            args.out.display(),
            start.elapsed().as_secs_f64()
        );
        return Ok(());
    }
    let randomization: Randomization = args.randomization.parse()?;
    let config = DatasetConfig {
        experiments: args.experiments,
        frames_per_experiment: args.frames_per_experiment,
        seed: args.seed,
        sensor,
        randomization,
        only_split: args.split.as_deref().map(str::parse).transpose()?,
        indenter: args.indenter.clone(),
        motion: args.motion.as_deref().map(str::parse).transpose()?,
    };
    config.validate()?;
    let planned = gelstereo::sim::dataset::plan(&config)?;
    let written = planned
        .iter()
        .filter(|e| config.only_split.is_none_or(|s| e.split == s))
        .count();
    let total = written as u64 * u64::from(args.frames_per_experiment);
    let bar = if args.quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(total)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} stereo frames ({per_sec}, eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    let start = Instant::now();
    let summary = write_dataset(&args.out, &config, args.force, &|| bar.inc(1))
        .with_context(|| format!("simulating into {}", args.out.display()))?;
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    let [train, val, test] = summary.experiments;
    eprintln!(
        "wrote {} stereo frames ({train} train / {val} val / {test} test experiments) to {} in {secs:.1} s ({:.1} stereo frames/s)",
        summary.frames,
        args.out.display(),
        summary.frames as f64 / secs
    );
    Ok(())
}
