//! `gelstereo simulate`'s dataset writer on its own, for a training machine that lacks the
//! `gelstereo` build (a rented GPU box): a small binary whose shared libraries
//! `train/scripts/pack_simulator.py` packs into a few MB.
//!
//! ```text
//! simulate_split OUT EXPERIMENTS FRAMES SEED RANDOMIZATION [SPLIT]
//! ```
//! writes what `gelstereo simulate --out OUT --experiments EXPERIMENTS --frames-per-experiment FRAMES
//! --seed SEED --randomization RANDOMIZATION [--split SPLIT]` writes with the reference sensor, byte
//! for byte. OUT must not exist or be empty (there is no `--force`).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use gelstereo_sim::dataset::{DatasetConfig, write_dataset};

const USAGE: &str = "usage: simulate_split OUT EXPERIMENTS FRAMES SEED RANDOMIZATION [SPLIT]";

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("simulate_split: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if !(5..=6).contains(&args.len()) {
        return Err(USAGE.into());
    }
    let number = |i: usize, name: &str| -> Result<u64, String> {
        args[i]
            .parse()
            .map_err(|_| format!("{name} {:?}: expected a whole number ({USAGE})", args[i]))
    };
    let mut config = DatasetConfig::new(
        u32::try_from(number(1, "EXPERIMENTS")?)?,
        u32::try_from(number(2, "FRAMES")?)?,
        number(3, "SEED")?,
    );
    config.randomization = args[4].parse()?;
    config.only_split = args.get(5).map(|s| s.parse()).transpose()?;
    config.validate()?;
    let out = PathBuf::from(&args[0]);
    let start = Instant::now();
    let summary = write_dataset(&out, &config, false, &|| {})?;
    eprintln!(
        "{} stereo frames in {:.1} s to {}",
        summary.frames,
        start.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}
