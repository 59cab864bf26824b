//! `gelstereo capture`: saves camera frames as a stereo recording (`OUT/left/`, `OUT/right/`, PNG,
//! `OUT/times.csv`) for calibration checkerboards or for tracking later. The work is
//! [`gelstereo::source::FrameSource`] and [`gelstereo::sink::RecordingWriter`].

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::bail;
use gelstereo::sink::{OutputFolder, RecordingWriter};
use gelstereo::source::FrameSource;

/// Arguments of `gelstereo capture`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Camera N (with --side-by-side for a stereo device), or two cameras L,R paired by capture
    /// time; a camera may be a video file path.
    #[arg(long, value_name = "N|L,R", value_delimiter = ',', required = true)]
    camera: Vec<String>,
    /// The camera's frames are side-by-side stereo (left half, right half).
    #[arg(long)]
    side_by_side: bool,
    /// Output folder (a recording: left/, right/, times.csv).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Write into a non-empty folder gelstereo did not write (only its own files are replaced).
    #[arg(long)]
    force: bool,
    /// Stop after this many frames (default: until the camera ends or Ctrl-C).
    #[arg(long)]
    frames: Option<usize>,
    /// Keep one frame in N (e.g. 15 for a checkerboard every half second at 30 Hz).
    #[arg(long, default_value_t = 1, value_name = "N")]
    every: usize,
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.every == 0 {
        bail!("--every must be at least 1");
    }
    let source = FrameSource::open_cameras(&args.camera, args.side_by_side)?;
    let folder = Arc::new(OutputFolder::prepare(&args.out, args.force)?);
    let mut writer = RecordingWriter::create(folder)?;
    for frame in source
        .prefetch(gelstereo::track::PREFETCH_FRAMES)
        .step_by(args.every)
    {
        if gelstereo::core::interrupt::requested() || args.frames.is_some_and(|n| writer.len() >= n) {
            break;
        }
        match frame.images {
            Ok(images) => {
                writer.write(&images, frame.time_s)?;
            }
            Err(e) => eprintln!("warning: frame {}: {}; not saved", frame.index, e.full_message()),
        }
    }
    eprintln!("{} frames saved in {}", writer.len(), args.out.display());
    Ok(())
}
