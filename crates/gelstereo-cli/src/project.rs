//! Where the project's shipped files are, and the version banner.

use std::path::PathBuf;

/// The folder holding `data/` and `calib/`: `GELSTEREO_HOME` when set, else the checkout this binary
/// was built from, else the folder of the executable.
pub fn home() -> PathBuf {
    if let Some(p) = std::env::var_os("GELSTEREO_HOME").filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    let checkout = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."));
    if checkout.join("data").is_dir() {
        return checkout.canonicalize().unwrap_or(checkout);
    }
    std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from("."))
}

/// `gelstereo --version`: the binary's version and the OpenCV and ONNX Runtime it runs with.
pub fn version_text() -> String {
    let opencv = opencv::core::get_version_string().unwrap_or_else(|e| format!("unavailable ({e})"));
    let ort = match gelstereo_markers::runtime::init() {
        Ok(rt) => format!("{} ({})", rt.version, rt.library.display()),
        Err(e) => format!("not found: {e}"),
    };
    format!(
        "{}\nOpenCV {opencv}\nONNX Runtime {ort}",
        env!("CARGO_PKG_VERSION")
    )
}
