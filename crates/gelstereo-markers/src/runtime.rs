//! Finding and starting ONNX Runtime.
//!
//! `ort` is built with `load-dynamic`: the shared library is opened at run time, so a machine without it
//! can still run the blob baseline and `gelstereo doctor` can say what is missing. The library is
//! looked up in this order (the first that exists wins):
//! 1. `ORT_DYLIB_PATH`, when set (an explicit choice: if that file is missing it is an error, no fallback);
//! 2. the project folder `scripts/setup.sh` fills, `.deps/onnxruntime/lib/libonnxruntime.so` of the
//!    checkout this binary was built from (not in a `relocatable` build);
//! 3. next to the executable: `libonnxruntime.so` or `lib/libonnxruntime.so` beside it;
//! 4. the system's dynamic loader (`LD_LIBRARY_PATH`, ldconfig) by name.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// The library's file name on this platform (`libonnxruntime.so` on Linux).
pub const LIBRARY_FILE: &str = "libonnxruntime.so";

/// Where `scripts/setup.sh` unpacks ONNX Runtime for the checkout this crate was built from.
#[cfg(not(feature = "relocatable"))]
pub const PROJECT_LIBRARY_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../.deps/onnxruntime/lib");

/// Why ONNX Runtime could not be used.
#[derive(Debug, thiserror::Error)]
pub enum OnnxRuntimeError {
    /// `ORT_DYLIB_PATH` names a file that does not exist.
    #[error(
        "ORT_DYLIB_PATH={0} does not exist; unset it or point it at libonnxruntime.so (run scripts/setup.sh)"
    )]
    EnvPathMissing(PathBuf),
    /// No candidate location holds the library.
    #[error(
        "ONNX Runtime library not found (looked in: {tried}); run scripts/setup.sh or set ORT_DYLIB_PATH"
    )]
    NotFound {
        /// The locations tried, in order.
        tried: String,
    },
    /// The library exists but could not be loaded or is too old for `ort`.
    #[error("cannot load ONNX Runtime from {path}: {reason}")]
    Load {
        /// The library file.
        path: PathBuf,
        /// What the loader said.
        reason: String,
    },
}

/// A started ONNX Runtime: where it came from, its version, and the environment sessions are built in.
#[derive(Debug)]
pub struct OnnxRuntime {
    /// The shared library that was loaded.
    pub library: PathBuf,
    /// ONNX Runtime's version, e.g. `1.31.1`.
    pub version: String,
    /// The process-wide environment to build sessions with (`Session::builder(&rt.environment)`).
    pub environment: ort::environment::Environment,
}

/// The locations of the lookup order above, in order, with the one `ORT_DYLIB_PATH` forces if set.
pub fn candidate_paths() -> Result<Vec<PathBuf>, OnnxRuntimeError> {
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        return if p.exists() {
            Ok(vec![p])
        } else {
            Err(OnnxRuntimeError::EnvPathMissing(p))
        };
    }
    let mut paths = Vec::new();
    #[cfg(not(feature = "relocatable"))]
    paths.push(Path::new(PROJECT_LIBRARY_DIR).join(LIBRARY_FILE));
    if let Some(dir) = std::env::current_exe().ok().as_deref().and_then(Path::parent) {
        paths.push(dir.join(LIBRARY_FILE));
        paths.push(dir.join("lib").join(LIBRARY_FILE));
    }
    Ok(paths)
}

/// Finds the ONNX Runtime library: the first existing candidate, or the bare name for the system
/// loader when no candidate exists and the system loader has it.
pub fn locate() -> Result<PathBuf, OnnxRuntimeError> {
    let candidates = candidate_paths()?;
    if let Some(found) = candidates.iter().find(|p| p.exists()) {
        return Ok(normalise(found));
    }
    let system = system_library();
    match system {
        Some(p) => Ok(p),
        None => Err(OnnxRuntimeError::NotFound {
            tried: candidates
                .iter()
                .map(|p| p.display().to_string())
                .chain(std::iter::once(format!(
                    "{LIBRARY_FILE} via LD_LIBRARY_PATH/ldconfig"
                )))
                .collect::<Vec<_>>()
                .join(", "),
        }),
    }
}

fn normalise(p: &Path) -> PathBuf {
    p.canonicalize().unwrap_or_else(|_| p.to_path_buf())
}

/// The library as the system loader would find it by name: `LD_LIBRARY_PATH` entries, then the
/// ldconfig cache's usual directories.
fn system_library() -> Option<PathBuf> {
    let from_env = std::env::var_os("LD_LIBRARY_PATH")
        .map(|v| std::env::split_paths(&v).collect::<Vec<_>>())
        .unwrap_or_default();
    from_env
        .into_iter()
        .chain(
            [
                "/usr/local/lib",
                "/usr/lib",
                "/usr/lib/x86_64-linux-gnu",
                "/lib/x86_64-linux-gnu",
            ]
            .map(PathBuf::from),
        )
        .map(|d| d.join(LIBRARY_FILE))
        .find(|p| p.exists())
        .map(|p| normalise(&p))
}

static RUNTIME: OnceLock<Result<OnnxRuntime, String>> = OnceLock::new();

/// Loads ONNX Runtime once per process (lookup order in the module docs) and returns it.
///
/// Later calls return the same runtime, or the same error.
pub fn init() -> Result<&'static OnnxRuntime, OnnxRuntimeError> {
    let result = RUNTIME.get_or_init(|| start().map_err(|e| e.to_string()));
    result.as_ref().map_err(|reason| match locate() {
        Ok(path) => OnnxRuntimeError::Load {
            path,
            reason: reason.clone(),
        },
        Err(e) => e,
    })
}

fn start() -> Result<OnnxRuntime, OnnxRuntimeError> {
    let library = locate()?;
    let load_err = |reason: String| OnnxRuntimeError::Load {
        path: library.clone(),
        reason,
    };
    let builder = ort::init_from(&library).map_err(|e| load_err(e.to_string()))?;
    let environment = builder
        .with_name("gelstereo")
        .build()
        .map_err(|e| load_err(e.to_string()))?;
    let version = library_version(&library).unwrap_or_else(|| "unknown".to_owned());
    Ok(OnnxRuntime {
        library,
        version,
        environment,
    })
}

/// Asks the library for its version (`OrtGetApiBase()->GetVersionString()`, e.g. "1.31.1"); `ort`
/// checks compatibility when loading but does not expose the string, and ONNX Runtime's build-info
/// string does not carry it.
#[allow(unsafe_code)]
fn library_version(path: &Path) -> Option<String> {
    type GetApiBase = unsafe extern "C" fn() -> *const ort::sys::OrtApiBase;
    // SAFETY: the file was just loaded successfully by `ort::init_from` as an ONNX Runtime library
    // (same dlopen handle, refcounted). `OrtGetApiBase` takes no arguments and returns a pointer to a
    // static struct; `GetVersionString` returns a static NUL-terminated string that must not be freed.
    unsafe {
        let lib = libloading::Library::new(path).ok()?;
        let get: libloading::Symbol<GetApiBase> = lib.get(b"OrtGetApiBase").ok()?;
        let base = get();
        if base.is_null() {
            return None;
        }
        let version = ((*base).GetVersionString)();
        if version.is_null() {
            return None;
        }
        Some(std::ffi::CStr::from_ptr(version).to_string_lossy().into_owned())
    }
}
