//! `gelstereo calibrate-gel`: the gel's Young's modulus from a press of known force (a weight
//! resting on the gel, or a force gauge's reading per frame), written as a gel file that `track
//! --gel FILE` reads ([`gelstereo::gel`]).

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::PathBuf;

use anyhow::{Context, bail};
use gelstereo::core::CsvTable;
use gelstereo::gel::GelFile;
use gelstereo::source::FrameSource;
use gelstereo::{Pipeline, PipelineConfig};
use gelstereo_apps::calibrate_gel::fit_modulus;

/// Arguments of `gelstereo calibrate-gel`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The normal force on the gel in every frame in contact, N (a weight resting on it).
    #[arg(
        long,
        value_name = "N",
        conflicts_with = "forces",
        required_unless_present = "forces"
    )]
    force_n: Option<f64>,
    /// The normal force per frame: a CSV with the columns `frame` and `force_N` (a force gauge's
    /// readings; frames it lacks are not used).
    #[arg(long, value_name = "FILE.csv")]
    forces: Option<PathBuf>,
    /// Where to write the gel file (JSON).
    #[arg(long, value_name = "FILE.json")]
    out: PathBuf,
    /// Replace an existing `--out` file.
    #[arg(long)]
    force: bool,
    /// Stereo calibration (default: the recording's calib.yaml).
    #[arg(long, value_name = "FILE")]
    calib: Option<std::path::PathBuf>,
    /// The gel's thickness and Poisson ratio (and the modulus to start from: any value gives the
    /// same fit, the layer being linear).
    #[command(flatten)]
    gel: crate::gel_args::GelArgs,
    /// The stereo recording of the press (left/ and right/, its first frame untouched).
    recording: PathBuf,
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.out.exists() && !args.force {
        bail!("{} exists: give --force to replace it", args.out.display());
    }
    let known = known_forces(args)?;
    let mut config = PipelineConfig::for_recording(&args.recording)?;
    config.calibration = args.calib.clone().or(config.calibration);
    args.gel.apply(&mut config, None)?;
    if config.calibration.is_none() {
        bail!(
            "{}: a stereo recording needs --calib FILE or its calib.yaml",
            args.recording.display()
        );
    }
    let mut pipeline = Pipeline::new(&config)?;
    let source = FrameSource::open_path(&args.recording, false)?;
    let mut pairs = Vec::new();
    pipeline.for_each(source.prefetch(4), |out| {
        if let (true, Some(force), Some(estimate)) =
            (out.summary.contact, known(out.frame), out.summary.force_n)
        {
            pairs.push((force, estimate));
        }
    })?;
    let assumed = config.session.contact.layer;
    let fit = fit_modulus(assumed.modulus_kpa, &pairs)?;
    let file = GelFile {
        layer: gelstereo::tracking::Layer {
            modulus_kpa: fit.modulus_kpa,
            ..assumed
        },
        friction: Some(config.session.contact.friction),
    };
    let mut extra = serde_json::Map::new();
    extra.insert(
        "fit".into(),
        serde_json::json!({
            "recording": args.recording.display().to_string(),
            "frames": fit.frames,
            "per_frame_modulus_quartiles_kpa": fit.quartiles_kpa,
        }),
    );
    let text = serde_json::to_string_pretty(&file.to_json(extra))? + "\n";
    let mut out = gelstereo::io::atomic::AtomicFile::create(&args.out)?;
    out.write_all(text.as_bytes())
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    out.commit()?;
    println!(
        "modulus {:.1} kPa from {} frames in contact (per frame: quartiles {:.1} / {:.1} / {:.1} kPa); wrote {}",
        fit.modulus_kpa,
        fit.frames,
        fit.quartiles_kpa[0],
        fit.quartiles_kpa[1],
        fit.quartiles_kpa[2],
        args.out.display()
    );
    Ok(())
}

/// The known force of each frame: `--force-n` for all, or `--forces`' table.
fn known_forces(args: &Args) -> anyhow::Result<Box<dyn Fn(u32) -> Option<f64>>> {
    if let Some(f) = args.force_n {
        if !(f.is_finite() && f > 0.0) {
            bail!("--force-n: expected a positive force in N, found {f}");
        }
        return Ok(Box::new(move |_| Some(f)));
    }
    let Some(path) = &args.forces else {
        bail!("give --force-n N or --forces FILE.csv");
    };
    let table = CsvTable::read(path)?;
    let mut by_frame = BTreeMap::new();
    for row in 0..table.len() {
        let frame: u32 = table.value(row, "frame", "a frame number")?;
        let force: f64 = table.value(row, "force_N", "a force in N")?;
        if !(force.is_finite() && force >= 0.0) {
            bail!(
                "{}:{}: force_N: expected a non-negative force, found {force}",
                path.display(),
                row + 2
            );
        }
        by_frame.insert(frame, force);
    }
    Ok(Box::new(move |frame| by_frame.get(&frame).copied()))
}
