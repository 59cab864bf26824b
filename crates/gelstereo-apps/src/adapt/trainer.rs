//! The fine-tuning: `train/gelstereo_train/adapt.py`, run with the project's Python environment as a
//! child process that an interruption ends.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use gelstereo::{Error, Result, project_home};

use crate::project_python;

/// The trainer's module, run with `python -m` from the checkout's `train/` folder.
const MODULE: &str = "gelstereo_train.adapt";

/// Python that only looks the modules up: importing PyTorch takes seconds, and the trainer does it
/// anyway.
const FIND_MODULES: &str = "import importlib.util as u, sys; \
     m = [n for n in ('torch', 'onnx', 'onnxruntime') if u.find_spec(n) is None]; \
     sys.exit('No module named ' + ', '.join(m) if m else 0)";

/// The Python to run: `given`, else the checkout's `.venv/bin/python`; checked to exist and to have
/// PyTorch, ONNX and ONNX Runtime.
pub(super) fn find_python(given: Option<&Path>) -> Result<PathBuf> {
    let python = given.map_or_else(|| project_python(&project_home()), Path::to_path_buf);
    if !python.exists() {
        return Err(Error::Invalid(format!(
            "{}: not found; the fine-tuning needs the project's Python environment with PyTorch: run \
             scripts/setup.sh --with-train (it creates .venv with PyTorch), or give --python",
            python.display()
        )));
    }
    check_modules(&python)?;
    Ok(python)
}

fn check_modules(python: &Path) -> Result<()> {
    let out = Command::new(python)
        .args(["-c", FIND_MODULES])
        .output()
        .map_err(|e| Error::Invalid(format!("{}: cannot be run ({e})", python.display())))?;
    if out.status.success() {
        return Ok(());
    }
    Err(Error::Invalid(format!(
        "{}: lacks torch, onnx or onnxruntime ({}); run scripts/setup.sh --with-train, or give --python",
        python.display(),
        String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("")
    )))
}

/// One run of the trainer: what it reads, where it writes, and its budget.
pub(super) struct FineTuning<'a> {
    /// The Python with PyTorch.
    pub python: &'a Path,
    /// The pseudo-label dataset.
    pub data: &'a Path,
    /// The base model folder it starts from.
    pub base: &'a Path,
    /// The model folder it writes.
    pub model: &'a Path,
    /// Budget, minutes of wall clock.
    pub minutes: f64,
    /// PyTorch threads.
    pub threads: usize,
    /// Seed.
    pub seed: u64,
    /// The command that asked for the run, for the model card.
    pub command: Option<&'a str>,
    /// The folder name the model card tells users to give to `--models`.
    pub name: &'a Path,
}

impl FineTuning<'_> {
    /// Runs the trainer to its end. A failed run is an error naming the command; when `stop` is set
    /// the child is killed (its outputs are in the temporary folder, removed by the caller) and the
    /// error says the run was interrupted.
    pub(super) fn run(&self, stop: &AtomicBool) -> Result<()> {
        let mut child = self.spawn()?;
        let Some(status) = wait_unless_stopped(&mut child, stop)? else {
            return Err(Error::Invalid(format!(
                "interrupted; nothing was written to {}",
                self.name.display()
            )));
        };
        if status.success() {
            return Ok(());
        }
        Err(Error::Invalid(format!(
            "the fine-tuning ({} -m {MODULE}, in {}) failed ({status}); see its messages above; \
             nothing was written to {}",
            self.python.display(),
            train_dir().display(),
            self.name.display()
        )))
    }

    fn spawn(&self) -> Result<Child> {
        let train_dir = train_dir();
        let mut command = Command::new(self.python);
        command
            .current_dir(&train_dir)
            .env("PYTHONPATH", &train_dir)
            .env("OMP_NUM_THREADS", self.threads.to_string())
            .args(["-m", MODULE, "--data"])
            .arg(self.data)
            .arg("--out")
            .arg(self.data.join("run/marknet.pt"))
            .arg("--base")
            .arg(self.base)
            .arg("--out-dir")
            .arg(self.model)
            .args(["--minutes", &self.minutes.to_string()])
            .args(["--threads", &self.threads.to_string()])
            .args(["--seed", &self.seed.to_string()]);
        if let Some(asked) = self.command {
            command.args(["--command", asked]);
        }
        command
            .arg("--name")
            .arg(self.name)
            .stdin(Stdio::null())
            .spawn()
            .map_err(|e| Error::Invalid(format!("starting {} -m {MODULE}: {e}", self.python.display())))
    }
}

/// The checkout's `train/` folder (the trainer's package).
fn train_dir() -> PathBuf {
    project_home().join("train")
}

/// Waits for `child`, polling `stop`: when it is set the child is killed (a signal sent to this
/// process alone must end it too) and `None` returned.
fn wait_unless_stopped(child: &mut Child, stop: &AtomicBool) -> Result<Option<ExitStatus>> {
    loop {
        if stop.load(Ordering::SeqCst) {
            let _ = child.kill();
            let _ = child.wait();
            return Ok(None);
        }
        let polled = child
            .try_wait()
            .map_err(|e| Error::Invalid(format!("waiting for the fine-tuning: {e}")))?;
        match polled {
            Some(status) => return Ok(Some(status)),
            None => std::thread::sleep(Duration::from_millis(100)),
        }
    }
}
