//! `gelstereo adapt`: adapts the localizer to the user's own sensor from an unlabelled recording.
//! The pseudo-labels are `gelstereo::adapt`; the fine-tuning is `train/gelstereo_train/adapt.py`, run
//! with the project's Python environment (`.venv`, made by `scripts/setup.sh`). This is argument
//! checks, a progress bar, the child process and the final checks and rename.

use std::path::{Component, Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use gelstereo::adapt::{PseudoLabelConfig, skipped_text, write_pseudo_labels};
use gelstereo_core::interrupt;
use gelstereo_markers::{LocalizerConfig, Method};
use indicatif::{ProgressBar, ProgressStyle};

use crate::cmd_detect::LocalizerArgs;
use crate::project;

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

/// The file that marks a folder as written by `gelstereo adapt` (and says how).
const MANIFEST: &str = "adapt.json";

/// `path` made absolute and without `.`/`..`, without requiring it to exist (symbolic links in the
/// part that exists are resolved).
fn normalise(path: &Path) -> anyhow::Result<PathBuf> {
    let abs = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir()
            .context("reading the current folder")?
            .join(path)
    };
    let mut out = PathBuf::new();
    for c in abs.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other),
        }
    }
    // Resolve links in the longest existing prefix.
    let mut existing = out.clone();
    let mut rest = Vec::new();
    while !existing.exists() {
        match existing.file_name() {
            Some(name) => rest.push(name.to_owned()),
            None => break,
        }
        if !existing.pop() {
            break;
        }
    }
    let mut resolved = std::fs::canonicalize(&existing).unwrap_or(existing);
    for name in rest.iter().rev() {
        resolved.push(name);
    }
    Ok(resolved)
}

/// Refuses an output that is or holds the shipped models or the base models, or a non-empty folder
/// `gelstereo adapt` did not write (or any non-empty one without `force`).
fn check_output(out: &Path, base: &Path, force: bool) -> anyhow::Result<PathBuf> {
    let target = normalise(out)?;
    let shipped = normalise(&project::home().join("data/models"))?;
    let base = normalise(base)?;
    for (what, protected) in [
        ("the shipped default models", &shipped),
        ("the base models", &base),
    ] {
        if target == *protected || protected.starts_with(&target) {
            bail!(
                "--out {}: is or holds {what} ({}); adapted models go to a folder of their own, e.g. \
                 data/models-adapted/my-sensor",
                out.display(),
                protected.display()
            );
        }
    }
    if target.starts_with(&shipped) {
        bail!(
            "--out {}: inside the shipped models folder {}; adapted models go to a folder of their own, \
             e.g. data/models-adapted/my-sensor",
            out.display(),
            shipped.display()
        );
    }
    if target.exists() {
        if !target.is_dir() {
            bail!("--out {}: exists and is not a folder", out.display());
        }
        let empty = std::fs::read_dir(&target)
            .with_context(|| format!("reading {}", out.display()))?
            .next()
            .is_none();
        if !empty {
            if !force {
                bail!(
                    "--out {}: exists and is not empty (give --force to replace an earlier adapted model)",
                    out.display()
                );
            }
            if !target.join(MANIFEST).is_file() {
                bail!(
                    "--out {}: --force replaces only a folder written by gelstereo adapt (with {MANIFEST}); \
                     this one has none",
                    out.display()
                );
            }
        }
    }
    Ok(target)
}

/// The Python to run: `--python`, else the checkout's `.venv`; checked to have PyTorch, ONNX and ONNX
/// Runtime before any work is done.
fn find_python(args: &Args) -> anyhow::Result<PathBuf> {
    let python = match &args.python {
        Some(p) => p.clone(),
        None => project::home().join(".venv/bin/python"),
    };
    if !python.exists() {
        bail!(
            "{}: not found; the fine-tuning needs the project's Python environment with PyTorch: run \
             scripts/setup.sh (it creates .venv), or give --python",
            python.display()
        );
    }
    let out = Command::new(&python)
        // Found, not imported: importing PyTorch takes seconds, and the fine-tuning does it anyway.
        .args([
            "-c",
            "import importlib.util as u, sys; m = [n for n in ('torch', 'onnx', 'onnxruntime') if u.find_spec(n) is None]; \
             sys.exit('No module named ' + ', '.join(m) if m else 0)",
        ])
        .output()
        .with_context(|| format!("{}: cannot be run", python.display()))?;
    if !out.status.success() {
        bail!(
            "{}: lacks torch, onnx or onnxruntime ({}); run scripts/setup.sh, or give --python",
            python.display(),
            String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("")
        );
    }
    Ok(python)
}

/// Runs `gelstereo adapt`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let start = Instant::now();
    if !(args.minutes > 0.0 && args.minutes <= 24.0 * 60.0) {
        bail!("--minutes {}: expected a budget in (0, 1440]", args.minutes);
    }
    if args.max_frames < 3 {
        bail!(
            "--max-frames {}: expected at least 3 (labels are checked against neighbouring frames)",
            args.max_frames
        );
    }
    if !args.input.exists() {
        bail!(
            "{}: no such recording, folder of images or video",
            args.input.display()
        );
    }
    let base_config: LocalizerConfig = args.localizer.config()?;
    let base = base_config
        .marknet_path
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    if args.localizer.marknet.is_some() || args.localizer.mre.is_some() {
        bail!("--marknet/--mre: give the base models as a folder with --models DIR");
    }
    let target = check_output(&args.out, &base, args.force)?;
    let grid = args
        .grid
        .as_deref()
        .map(|g| gelstereo::parse_grid(g, "--grid"))
        .transpose()?;
    let python = find_python(args)?;
    let mut localizer = LocalizerArgs::localizer_from(Method::MarknetMre, &base_config)?;

    // Everything is written into a temporary sibling of --out and renamed at the end: an interrupted
    // or failed run leaves nothing that looks like a model folder.
    let parent = target
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    std::fs::create_dir_all(&parent).with_context(|| format!("creating {}", parent.display()))?;
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "adapted".into());
    let work = tempfile::Builder::new()
        .prefix(&format!(".{name}.partial-"))
        .tempdir_in(&parent)
        .with_context(|| format!("creating a temporary folder in {}", parent.display()))?;
    let data = work.path().join("data");
    let model = work.path().join("model");
    std::fs::create_dir_all(&data).with_context(|| format!("creating {}", data.display()))?;

    let config = PseudoLabelConfig {
        grid_markers: grid.map(|g| g.count()),
        max_frames: args.max_frames,
        ..PseudoLabelConfig::default()
    };
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("pseudo-labels {bar:30} {pos}/{len} frames {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let t_label = Instant::now();
    let summary = write_pseudo_labels(
        &args.input,
        args.side_by_side,
        localizer.as_mut(),
        &config,
        &data,
        interrupt::flag(),
        &|seen, total| {
            if let Some(n) = total {
                bar.set_length(n as u64);
            }
            bar.set_position(seen as u64);
        },
    )
    .with_context(|| format!("pseudo-labelling {}", args.input.display()))?;
    bar.finish_and_clear();
    eprintln!(
        "pseudo-labels from {} frames in {:.1} s: {} labels in {} training views (and {} ignore discs), \
         {} labels in {} held-out views; views left out: {}",
        summary.frames_used,
        t_label.elapsed().as_secs_f64(),
        summary.train_labels,
        summary.train_views,
        summary.train_ignored,
        summary.heldout_labels,
        summary.heldout_views,
        skipped_text(&summary.skipped)
    );

    let command: Vec<String> = std::env::args_os()
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    let train_dir = project::home().join("train");
    let mut child = Command::new(&python)
        .current_dir(&train_dir)
        .env("PYTHONPATH", &train_dir)
        .env("OMP_NUM_THREADS", args.train_threads.to_string())
        .args(["-m", "gelstereo_train.adapt", "--data"])
        .arg(&data)
        .arg("--out")
        .arg(data.join("run/marknet.pt"))
        .arg("--base")
        .arg(&base)
        .arg("--out-dir")
        .arg(&model)
        .args(["--minutes", &args.minutes.to_string()])
        .args(["--threads", &args.train_threads.to_string()])
        .args(["--seed", &args.seed.to_string()])
        .args(["--command", &command.join(" ")])
        .arg("--name")
        .arg(&args.out)
        .stdin(Stdio::null())
        .spawn()
        .with_context(|| format!("starting {} -m gelstereo_train.adapt", python.display()))?;
    let status = loop {
        if interrupt::requested() {
            // The child shares the terminal's Ctrl-C; a signal sent to us alone must end it too. Its
            // outputs are inside the temporary folder, removed below.
            let _ = child.kill();
            let _ = child.wait();
            bail!("interrupted; nothing was written to {}", args.out.display());
        }
        match child.try_wait().context("waiting for the fine-tuning")? {
            Some(status) => break status,
            None => std::thread::sleep(Duration::from_millis(100)),
        }
    };
    if !status.success() {
        bail!(
            "the fine-tuning ({} -m gelstereo_train.adapt, in {}) failed ({status}); see its messages above; \
             nothing was written to {}",
            python.display(),
            train_dir.display(),
            args.out.display()
        );
    }

    // The folder must load under the model contract and find markers before it is handed over.
    let check = LocalizerConfig {
        marknet_path: model.join("marknet.onnx"),
        mre_path: model.join("mre.onnx"),
        remember_pitch: false,
        ..base_config.clone()
    };
    let mut adapted = LocalizerArgs::localizer_from(Method::MarknetMre, &check)
        .context("the adapted models do not pass the model contract")?;
    let test = gelstereo_markers::self_test::run(adapted.as_mut())
        .context("the adapted models fail the self-test")?;
    let manifest = serde_json::json!({
        "generator": gelstereo::adapt::GENERATOR,
        "source": args.input.display().to_string(),
        "base": base.display().to_string(),
        "minutes": args.minutes,
        "seed": args.seed,
        "grid": args.grid,
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
        "seconds": start.elapsed().as_secs_f64(),
    });
    let manifest_path = model.join(MANIFEST);
    std::fs::write(&manifest_path, serde_json::to_string_pretty(&manifest)? + "\n")
        .with_context(|| format!("writing {}", manifest_path.display()))?;
    if let Some(keep) = &args.keep_data {
        let keep = normalise(keep)?;
        if keep.exists() {
            bail!("--keep-data {}: exists; give a new folder", keep.display());
        }
        if let Some(p) = keep.parent() {
            std::fs::create_dir_all(p).with_context(|| format!("creating {}", p.display()))?;
        }
        std::fs::rename(&data, &keep)
            .or_else(|_| copy_tree(&data, &keep))
            .with_context(|| format!("moving the pseudo-labels to {}", keep.display()))?;
    }
    if target.exists() {
        std::fs::remove_dir_all(&target).with_context(|| format!("replacing {}", target.display()))?;
    }
    std::fs::rename(&model, &target).with_context(|| format!("renaming into {}", target.display()))?;
    eprintln!(
        "wrote {} in {:.0} s (self-test: {} of {} markers); use it with --models {}",
        args.out.display(),
        start.elapsed().as_secs_f64(),
        test.found,
        test.drawn,
        args.out.display()
    );
    Ok(())
}

/// Copies a folder tree (for --keep-data on another file system).
fn copy_tree(from: &Path, to: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for entry in std::fs::read_dir(from)? {
        let entry = entry?;
        let dest = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_tree(&entry.path(), &dest)?;
        } else {
            std::fs::copy(entry.path(), dest)?;
        }
    }
    Ok(())
}
