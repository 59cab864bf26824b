//! Where the shipped models (`marknet.onnx`, `mre.onnx`, `yolo.onnx`) are, wherever gelstereo is
//! installed:
//! 1. the folder an installed package names ([`use_shipped_models`]: the Python wheel carries its own);
//! 2. `data/models` of the project's home ([`project_home`]), where that folder holds the models;
//! 3. with the feature `embedded-models` (the `gelstereo` binary), the models compiled into the
//!    binary, written once into the user's cache (`$XDG_CACHE_HOME/gelstereo/models-<version>-<hash>`)
//!    because ONNX Runtime opens models by path; a binary installed by `cargo install` runs so
//!    without its checkout;
//! 4. else `data/models` of the home, whose absence the errors and `gelstereo doctor` report.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use crate::project_home;

/// The files a model folder holds.
pub const MODEL_FILES: [&str; 3] = ["marknet.onnx", "mre.onnx", "yolo.onnx"];

static INSTALLED: OnceLock<PathBuf> = OnceLock::new();

/// Makes `dir` the shipped models of this process (the Python package passes its own folder when it
/// is imported). The first call wins; returns whether this one did.
pub fn use_shipped_models(dir: PathBuf) -> bool {
    INSTALLED.set(dir).is_ok()
}

/// The folder of the shipped models (lookup order in the module docs).
pub fn shipped_models() -> PathBuf {
    if let Some(dir) = INSTALLED.get() {
        return dir.clone();
    }
    let home_models = project_home().join("data/models");
    #[cfg(feature = "embedded-models")]
    if !holds_models(&home_models)
        && let Ok(dir) = embedded::unpacked()
    {
        return dir;
    }
    home_models
}

/// Whether `dir` holds the two models of the default method, Marknet-MRE.
pub fn holds_models(dir: &Path) -> bool {
    dir.join("marknet.onnx").is_file() && dir.join("mre.onnx").is_file()
}

/// The default localizer settings with the shipped models.
pub fn localizer_config() -> gelstereo_markers::LocalizerConfig {
    let dir = shipped_models();
    gelstereo_markers::LocalizerConfig {
        marknet_path: dir.join("marknet.onnx"),
        mre_path: dir.join("mre.onnx"),
        ..gelstereo_markers::LocalizerConfig::default()
    }
}

#[cfg(feature = "embedded-models")]
mod embedded {
    use std::hash::{Hash, Hasher};
    use std::io::Write;
    use std::path::{Path, PathBuf};

    use super::MODEL_FILES;

    /// The models of this checkout's `data/models`, in [`MODEL_FILES`] order.
    const BYTES: [&[u8]; 3] = [
        include_bytes!("../../../data/models/marknet.onnx"),
        include_bytes!("../../../data/models/mre.onnx"),
        include_bytes!("../../../data/models/yolo.onnx"),
    ];

    /// The folder holding the embedded models, written on first use (each file written whole
    /// under a temporary name, then renamed, so concurrent first runs never see a partial model).
    pub fn unpacked() -> std::io::Result<PathBuf> {
        let dir = cache_root().join(format!(
            "models-{}-{:016x}",
            env!("CARGO_PKG_VERSION"),
            content_hash()
        ));
        std::fs::create_dir_all(&dir)?;
        for (name, bytes) in MODEL_FILES.iter().zip(BYTES) {
            let path = dir.join(name);
            if std::fs::metadata(&path).is_ok_and(|m| m.len() == bytes.len() as u64) {
                continue;
            }
            write_whole(&path, bytes)?;
        }
        Ok(dir)
    }

    fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut file = tempfile::NamedTempFile::new_in(dir)?;
        file.write_all(bytes)?;
        file.persist(path).map_err(|e| e.error)?;
        Ok(())
    }

    /// `$XDG_CACHE_HOME/gelstereo`, else `$HOME/.cache/gelstereo`, else the system's temporary folder.
    fn cache_root() -> PathBuf {
        let var = |name| {
            std::env::var_os(name)
                .filter(|v| !v.is_empty())
                .map(PathBuf::from)
        };
        var("XDG_CACHE_HOME")
            .or_else(|| var("HOME").map(|h| h.join(".cache")))
            .unwrap_or_else(std::env::temp_dir)
            .join("gelstereo")
    }

    /// Tells builds with different models apart, so one cache folder never mixes two versions.
    fn content_hash() -> u64 {
        let mut hasher = std::hash::DefaultHasher::new();
        BYTES.hash(&mut hasher);
        hasher.finish()
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn unpacked_models_are_the_embedded_bytes() {
            let dir = unpacked().unwrap();
            for (name, bytes) in MODEL_FILES.iter().zip(BYTES) {
                assert_eq!(std::fs::read(dir.join(name)).unwrap(), bytes, "{name}");
            }
            assert!(super::super::holds_models(&dir));
        }
    }
}
