//! Where the project's shipped files are, and the version banner.

use std::path::PathBuf;

/// The folder holding `data/` and `calib/` ([`gelstereo::project_home`]).
pub fn home() -> PathBuf {
    gelstereo::project_home()
}

/// `gelstereo --version`: the binary's version and the OpenCV and ONNX Runtime it runs with.
pub fn version_text() -> String {
    let opencv = opencv::core::get_version_string().unwrap_or_else(|e| format!("unavailable ({e})"));
    let ort = match gelstereo::markers::runtime::init() {
        Ok(rt) => format!("{} ({})", rt.version, rt.library.display()),
        Err(e) => format!("not found: {e}"),
    };
    format!(
        "{}\nOpenCV {opencv}\nONNX Runtime {ort}",
        env!("CARGO_PKG_VERSION")
    )
}
