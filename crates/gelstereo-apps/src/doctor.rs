//! The components a user needs, each checked (`gelstereo doctor`): OpenCV, ONNX Runtime, the
//! models and one Marknet-MRE run, the calibration files, the Python training environment.

use std::path::Path;
use std::process::Command;

/// How much a missing component matters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Need {
    /// The default pipeline (Marknet-MRE) cannot run without it.
    Required,
    /// Only some commands need it (training, a given sensor).
    Optional,
}

/// One component, checked.
#[derive(Debug, Clone)]
pub struct Check {
    /// The component.
    pub name: &'static str,
    /// How much it matters.
    pub need: Need,
    /// What was found, or why it is missing.
    pub outcome: Result<String, String>,
    /// How to fix it when missing, in one line.
    pub fix: &'static str,
}

/// Checks every component, with the project's files in `home` and the models in `models`.
pub fn checks(home: &Path, models: &Path) -> Vec<Check> {
    vec![
        Check {
            name: "OpenCV",
            need: Need::Required,
            outcome: opencv::core::get_version_string()
                .map(|v| format!("{v} (linked)"))
                .map_err(|e| e.to_string()),
            fix: "install Debian's libopencv-dev (scripts/setup.sh does)",
        },
        Check {
            name: "ONNX Runtime",
            need: Need::Required,
            outcome: gelstereo_markers::runtime::init()
                .map(|rt| format!("{} at {}", rt.version, rt.library.display()))
                .map_err(|e| e.to_string()),
            fix: "in a checkout run scripts/setup.sh; else `pip install onnxruntime==1.31.1` and set ORT_DYLIB_PATH to its onnxruntime/capi/libonnxruntime.so.1.31.1, or put libonnxruntime.so next to the gelstereo binary",
        },
        Check {
            name: "Marknet model",
            need: Need::Required,
            outcome: model_summary(&models.join("marknet.onnx")),
            fix: "train/retrain.sh retrains it, or restore data/models/ from git",
        },
        Check {
            name: "MRE model",
            need: Need::Required,
            outcome: model_summary(&models.join("mre.onnx")),
            fix: "train/retrain.sh retrains it, or restore data/models/ from git",
        },
        Check {
            name: "Marknet-MRE run",
            need: Need::Required,
            outcome: self_test(home, models),
            fix: "the model files are broken (NaN, infinite or untrained weights): restore data/models/ from git or retrain",
        },
        Check {
            name: "Calibration files",
            need: Need::Optional,
            outcome: calibrations(&home.join("calib")),
            fix: "restore calib/ from git, or write your sensor's with `gelstereo calibrate`",
        },
        Check {
            name: "Python training env",
            need: Need::Optional,
            outcome: python_env(home),
            fix: "run scripts/setup.sh --with-train (adds train/requirements.txt, PyTorch, to .venv)",
        },
    ]
}

/// Opens an ONNX model with ONNX Runtime and lists its contract metadata.
fn model_summary(path: &Path) -> Result<String, String> {
    if !path.exists() {
        return Err(format!("{} not found", path.display()));
    }
    let metadata = gelstereo_markers::onnx::model_metadata(path).map_err(|e| e.to_string())?;
    if metadata.is_empty() {
        return Err(format!(
            "{} has no metadata_props (contract missing)",
            path.display()
        ));
    }
    let props: Vec<String> = metadata.iter().map(|(k, v)| format!("{k}={v}")).collect();
    Ok(format!("{} [{}]", path.display(), props.join(", ")))
}

/// The real frame the models are tried on: the bundled sample's first left view.
pub const SAMPLE_FRAME: &str = "data/sample/press-slide/left/000000.jpg";

/// Loads Marknet-MRE from `models` (each network is run once at load on a fixed input and must
/// give finite outputs), then runs it once on the sample's first left view ([`SAMPLE_FRAME`] in
/// `home`; a synthetic marker image where the checkout has no sample): a non-finite output, or no
/// marker found, is the error.
fn self_test(home: &Path, models: &Path) -> Result<String, String> {
    let config = gelstereo_markers::LocalizerConfig {
        marknet_path: models.join("marknet.onnx"),
        mre_path: models.join("mre.onnx"),
        blob: gelstereo_markers::BlobParams::opencv_defaults().map_err(|e| e.to_string())?,
        session: gelstereo_markers::SessionOptions::default(),
        fit: gelstereo_markers::InputFit::Auto,
        remember_pitch: false,
        lattice_window: false,
        close_look: true,
    };
    let mut localizer = gelstereo_markers::create_localizer(gelstereo_markers::Method::MarknetMre, &config)
        .map_err(|e| format!("{e:#}"))?;
    let frame = home.join(SAMPLE_FRAME);
    let found = if frame.is_file() {
        let image = gelstereo_io::images::read_image(&frame).map_err(|e| format!("{e:#}"))?;
        let what = frame.display().to_string();
        let n = gelstereo_markers::self_test::run_on(localizer.as_mut(), &image, &what)
            .map_err(|e| format!("{e:#}"))?;
        format!("{n} markers found on {what}")
    } else {
        let run = gelstereo_markers::self_test::run(localizer.as_mut()).map_err(|e| format!("{e:#}"))?;
        format!(
            "{} of {} markers found on a synthetic marker image",
            run.found, run.drawn
        )
    };
    Ok(found)
}

/// Loads every calibration in `dir` (OpenCV YAML/XML files and a `left/right.cameramodel` mrcal pair)
/// and summarises each; any that fails to load is the error.
fn calibrations(dir: &Path) -> Result<String, String> {
    let entries = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut specs: Vec<String> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .is_some_and(|x| x == "yaml" || x == "yml" || x == "xml")
        })
        .map(|p| p.display().to_string())
        .collect();
    specs.sort();
    if dir.join("left.cameramodel").exists() && dir.join("right.cameramodel").exists() {
        specs.push(dir.display().to_string());
    }
    let mut loaded = Vec::new();
    for spec in &specs {
        let rig = gelstereo_geometry::StereoRig::load(spec).map_err(|e| e.to_string())?;
        let baseline_mm = rig.baseline_mm();
        let size = rig.left.image_size;
        loaded.push(format!(
            "{spec} ({}x{}, baseline {baseline_mm:.2} mm)",
            size.width, size.height
        ));
    }
    if loaded.is_empty() {
        return Err(format!(
            "no calibration (.yaml, .xml, left/right.cameramodel) in {}",
            dir.display()
        ));
    }
    Ok(loaded.join("; "))
}

/// Asks the project's Python environment for its PyTorch and ONNX Runtime versions.
fn python_env(home: &Path) -> Result<String, String> {
    let python = crate::project_python(home);
    if !python.exists() {
        return Err(format!("{} not found", python.display()));
    }
    let out = Command::new(&python)
        .args(["-c", "import torch, onnx, onnxruntime; print(f'torch {torch.__version__}, onnx {onnx.__version__}, onnxruntime {onnxruntime.__version__}')"])
        .output()
        .map_err(|e| format!("{}: {e}", python.display()))?;
    if !out.status.success() {
        return Err(format!(
            "{} cannot import torch/onnx/onnxruntime: {}",
            python.display(),
            String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("")
        ));
    }
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_owned())
}
