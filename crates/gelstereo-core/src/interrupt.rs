//! A process-wide "stop requested" flag: the command-line tool sets it on SIGINT / SIGTERM (Ctrl-C),
//! and long loops in the libraries check it between frames, so they stop with their outputs whole
//! (tables cut at a frame boundary, temporary folders removed) instead of dying mid-write.

use std::sync::atomic::{AtomicBool, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);

/// Asks every loop that checks [`requested`] to stop at its next frame boundary.
pub fn request() {
    REQUESTED.store(true, Ordering::SeqCst);
}

/// The flag itself, for loops that take an `&AtomicBool` to watch (e.g. `gelstereo::track::run`).
pub fn flag() -> &'static AtomicBool {
    &REQUESTED
}

/// Whether a stop has been requested.
pub fn requested() -> bool {
    REQUESTED.load(Ordering::SeqCst)
}

/// Exit status of a process stopped by a signal it handled (128 + SIGINT, the shell's convention).
pub const EXIT_INTERRUPTED: u8 = 130;
