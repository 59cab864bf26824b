//! [`OutputFolder`]: an output folder that records every file gelstereo writes into it (its
//! manifest), so a later run removes exactly those files and never leaves an older run's files
//! looking current, and never touches a file it did not write.

use std::fs::{File, OpenOptions};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use crate::error::file_err;
use crate::{Error, Result};

/// The manifest's name inside the output folder: one path per line, relative to the folder.
pub const MANIFEST: &str = ".gelstereo-manifest";

/// The lock file inside the output folder: a run holds an exclusive lock on it while it writes,
/// so a second run into the same folder is refused. The operating system releases the lock when
/// the run ends, however it ends (a killed run leaves no stale lock).
pub const LOCK: &str = ".gelstereo-lock";

/// An output folder and the manifest of what was written into it.
#[derive(Debug)]
pub struct OutputFolder {
    dir: PathBuf,
    manifest: Mutex<File>,
    /// Held (locked) for as long as the folder is written.
    _lock: File,
}

impl OutputFolder {
    /// Prepares `dir` for a new run: creates it, or empties it of the files an earlier run listed in
    /// its manifest. A non-empty folder without a manifest (not written by gelstereo) is refused
    /// unless `force`, which still removes only files a manifest lists. `-` is refused: it names
    /// standard output, not a folder.
    pub fn prepare(dir: &Path, force: bool) -> Result<Self> {
        Self::prepare_apart_from(dir, force, &[])
    }

    /// [`Self::prepare`], refusing a folder that is, or lies inside, one of `inputs` (a recording
    /// written over by its own outputs) or that holds one of them (`--force` would replace it).
    pub fn prepare_apart_from(dir: &Path, force: bool, inputs: &[&Path]) -> Result<Self> {
        refuse_overlap(dir, inputs)?;
        if dir.as_os_str() == "-" {
            return Err(Error::Invalid(
                "--out -: an output folder is needed here ('-' would be a folder named '-'); stream to standard output with --jsonl -".into(),
            ));
        }
        if dir.exists() && !dir.is_dir() {
            return Err(Error::Invalid(format!(
                "{}: exists and is not a folder",
                dir.display()
            )));
        }
        let manifest_path = dir.join(MANIFEST);
        if !manifest_path.is_file() && !force && is_non_empty(dir)? {
            return Err(Error::Invalid(format!(
                "{}: the folder is not empty and holds no gelstereo manifest ({MANIFEST}); choose an empty or new folder, or give --force to write into it (only files gelstereo writes are replaced)",
                dir.display()
            )));
        }
        std::fs::create_dir_all(dir).map_err(file_err(dir))?;
        let lock = take_lock(dir)?;
        if manifest_path.is_file() {
            remove_listed(dir, &manifest_path)?;
        }
        let manifest = OpenOptions::new()
            .create(true)
            .write(true)
            .truncate(true)
            .open(&manifest_path)
            .map_err(file_err(&manifest_path))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            manifest: Mutex::new(manifest),
            _lock: lock,
        })
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The path of `relative` inside the folder, listed in the manifest before it is created (so
    /// an interrupted run leaves no file unlisted); its parent folder is created.
    pub fn claim(&self, relative: &str) -> Result<PathBuf> {
        let path = self.dir.join(relative);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(file_err(parent))?;
        }
        if let Some(link) = linked_folder(&self.dir, Path::new(relative)) {
            return Err(Error::Invalid(format!(
                "{}: a symbolic link inside the output folder; gelstereo writes only into folders of its own (remove the link)",
                link.display()
            )));
        }
        gelstereo_core::files::ensure_replaceable(&path).map_err(file_err(&path))?;
        let manifest_path = self.dir.join(MANIFEST);
        let mut m = self
            .manifest
            .lock()
            .map_err(|_| Error::Invalid("the manifest writer failed earlier".into()))?;
        m.write_all(format!("{relative}\n").as_bytes())
            .and_then(|()| m.flush())
            .map_err(file_err(&manifest_path))?;
        Ok(path)
    }

    /// Writes `relative` whole or not at all: `write` fills a temporary file beside it (listed in
    /// the manifest too), which is then renamed over it, so an interrupted run never leaves a cut
    /// image or PLY under the final name.
    pub fn write_atomic(&self, relative: &str, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
        let (parent, name) = relative.rsplit_once('/').unwrap_or(("", relative));
        let temp_rel = if parent.is_empty() {
            format!(".partial-{name}")
        } else {
            format!("{parent}/.partial-{name}")
        };
        let temp = self.claim(&temp_rel)?;
        let path = self.claim(relative)?;
        write(&temp)?;
        std::fs::rename(&temp, &path).map_err(file_err(&path))
    }
}

fn is_non_empty(dir: &Path) -> Result<bool> {
    if !dir.exists() {
        return Ok(false);
    }
    // The lock file of a run that ended before writing its manifest does not count.
    Ok(std::fs::read_dir(dir)
        .map_err(file_err(dir))?
        .flatten()
        .any(|e| e.file_name() != LOCK))
}

/// Takes the folder's lock, or says that another run holds it.
fn take_lock(dir: &Path) -> Result<File> {
    let path = dir.join(LOCK);
    let file = OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(file_err(&path))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => Err(Error::Invalid(format!(
            "{}: another gelstereo run is writing into this folder (it holds {LOCK}); wait for it or choose another --out",
            dir.display()
        ))),
        Err(std::fs::TryLockError::Error(e)) => Err(file_err(&path)(e)),
    }
}

/// The first folder on the way from `dir` to `relative`'s parent that is a symbolic link.
fn linked_folder(dir: &Path, relative: &Path) -> Option<PathBuf> {
    let mut at = dir.to_path_buf();
    for part in relative.parent()?.components() {
        at.push(part);
        if std::fs::symlink_metadata(&at).is_ok_and(|m| m.file_type().is_symlink()) {
            return Some(at);
        }
    }
    None
}

/// Refuses an output folder that is, lies inside or holds one of `inputs` (compared as absolute
/// paths with links resolved, as far as they exist).
fn refuse_overlap(dir: &Path, inputs: &[&Path]) -> Result<()> {
    let out = resolved(dir);
    for input in inputs {
        let input_path = resolved(input);
        if out.starts_with(&input_path) || input_path.starts_with(&out) {
            return Err(Error::Invalid(format!(
                "--out {}: the output folder overlaps the input {} (its files would be written over); choose a folder apart from it",
                dir.display(),
                input.display()
            )));
        }
    }
    Ok(())
}

/// `path` made absolute, with links resolved in its longest existing part.
fn resolved(path: &Path) -> PathBuf {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut existing = absolute.as_path();
    let mut rest = Vec::new();
    while !existing.exists() {
        match (existing.parent(), existing.file_name()) {
            (Some(parent), Some(name)) => {
                rest.push(name.to_os_string());
                existing = parent;
            }
            _ => return absolute,
        }
    }
    let mut out = std::fs::canonicalize(existing).unwrap_or_else(|_| existing.to_path_buf());
    out.extend(rest.iter().rev());
    out
}

/// Removes the files the manifest at `manifest_path` lists (those present), then the folders that
/// held them where they are left empty, then the manifest. Paths that leave the folder are ignored.
fn remove_listed(dir: &Path, manifest_path: &Path) -> Result<()> {
    let text = std::fs::read_to_string(manifest_path).map_err(file_err(manifest_path))?;
    let mut parents = std::collections::BTreeSet::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let rel = Path::new(line);
        let inside = rel
            .components()
            .all(|c| matches!(c, std::path::Component::Normal(_)));
        if !inside {
            continue;
        }
        let path = dir.join(rel);
        // A listed file below a folder that has since become a link elsewhere is not ours.
        if linked_folder(dir, rel).is_some() {
            continue;
        }
        if path.is_file() || path.is_symlink() {
            std::fs::remove_file(&path).map_err(file_err(&path))?;
        }
        let mut p = rel.parent();
        while let Some(parent) = p.filter(|p| !p.as_os_str().is_empty()) {
            parents.insert(parent.to_path_buf());
            p = parent.parent();
        }
    }
    // Deepest first; a folder that still holds something (the user's) stays.
    for parent in parents.iter().rev() {
        let _ = std::fs::remove_dir(dir.join(parent));
    }
    std::fs::remove_file(manifest_path).map_err(file_err(manifest_path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_new_run_removes_only_what_the_last_one_listed_and_a_foreign_folder_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let first = OutputFolder::prepare(&out, false).unwrap();
        std::fs::write(first.claim("ply/cloud_000001.ply").unwrap(), "old").unwrap();
        std::fs::write(first.claim("markers.csv").unwrap(), "old").unwrap();
        drop(first);
        std::fs::write(out.join("notes.txt"), "the user's").unwrap();
        let second = OutputFolder::prepare(&out, false).unwrap();
        assert!(!out.join("ply").exists() && !out.join("markers.csv").exists());
        assert_eq!(
            std::fs::read_to_string(out.join("notes.txt")).unwrap(),
            "the user's"
        );
        drop(second);

        let foreign = dir.path().join("foreign");
        std::fs::create_dir_all(&foreign).unwrap();
        std::fs::write(foreign.join("keep.csv"), "mine").unwrap();
        let err = OutputFolder::prepare(&foreign, false).unwrap_err().to_string();
        assert!(err.contains("not empty") && err.contains("--force"), "{err}");
        OutputFolder::prepare(&foreign, true).unwrap();
        assert_eq!(std::fs::read_to_string(foreign.join("keep.csv")).unwrap(), "mine");
        assert!(OutputFolder::prepare(Path::new("-"), true).is_err());
    }
}
