//! The adapted model folder: which outputs are refused (the shipped or base models, a folder that
//! `gelstereo adapt` did not write), the temporary sibling everything is written into, and the final
//! hand-over by renaming.

use std::path::{Component, Path, PathBuf};

use tempfile::TempDir;

use gelstereo::file_err;
use gelstereo::{Error, Result, project_home};

/// The file that marks a folder as written by `gelstereo adapt` (and says how).
pub const MANIFEST: &str = "adapt.json";

/// Where adapted models belong, said whenever an output is refused.
const ADVICE: &str = "adapted models go to a folder of their own, e.g. data/models-adapted/my-sensor";

/// `path` made absolute and without `.`/`..`, without requiring it to exist (symbolic links in the
/// part that exists are resolved).
pub(super) fn normalise(path: &Path) -> Result<PathBuf> {
    let lexical = without_dots(&absolute(path)?);
    let mut existing = lexical.clone();
    let mut missing = Vec::new();
    while !existing.exists() {
        match existing.file_name() {
            Some(name) => missing.push(name.to_owned()),
            None => break,
        }
        if !existing.pop() {
            break;
        }
    }
    let mut resolved = std::fs::canonicalize(&existing).unwrap_or(existing);
    resolved.extend(missing.iter().rev());
    Ok(resolved)
}

fn absolute(path: &Path) -> Result<PathBuf> {
    if path.is_absolute() {
        return Ok(path.to_path_buf());
    }
    let here =
        std::env::current_dir().map_err(|e| Error::Invalid(format!("reading the current folder: {e}")))?;
    Ok(here.join(path))
}

fn without_dots(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other),
        }
    }
    out
}

/// The normalised output folder, after refusing one that is or holds the shipped models or the base
/// models, lies inside the shipped models, or is a non-empty folder `gelstereo adapt` did not write
/// (or any non-empty one without `force`).
pub(super) fn check_output(out: &Path, base: &Path, force: bool) -> Result<PathBuf> {
    let target = normalise(out)?;
    refuse_protected(out, &target, base)?;
    refuse_occupied(out, &target, force)?;
    Ok(target)
}

fn refuse_protected(out: &Path, target: &Path, base: &Path) -> Result<()> {
    let shipped = normalise(&project_home().join("data/models"))?;
    let base = normalise(base)?;
    for (what, protected) in [
        ("the shipped default models", &shipped),
        ("the base models", &base),
    ] {
        if target == protected || protected.starts_with(target) {
            return Err(Error::Invalid(format!(
                "--out {}: is or holds {what} ({}); {ADVICE}",
                out.display(),
                protected.display()
            )));
        }
    }
    if target.starts_with(&shipped) {
        return Err(Error::Invalid(format!(
            "--out {}: inside the shipped models folder {}; {ADVICE}",
            out.display(),
            shipped.display()
        )));
    }
    Ok(())
}

fn refuse_occupied(out: &Path, target: &Path, force: bool) -> Result<()> {
    if !target.exists() {
        return Ok(());
    }
    if !target.is_dir() {
        return Err(Error::Invalid(format!(
            "--out {}: exists and is not a folder",
            out.display()
        )));
    }
    let empty = std::fs::read_dir(target).map_err(file_err(out))?.next().is_none();
    if empty {
        return Ok(());
    }
    if !force {
        return Err(Error::Invalid(format!(
            "--out {}: exists and is not empty (give --force to replace an earlier adapted model)",
            out.display()
        )));
    }
    if !target.join(MANIFEST).is_file() {
        return Err(Error::Invalid(format!(
            "--out {}: --force replaces only a folder written by gelstereo adapt (with {MANIFEST}); \
             this one has none",
            out.display()
        )));
    }
    Ok(())
}

/// A temporary sibling of the output folder, `.NAME.partial-XXXX`, removed when dropped: `data/`
/// holds the pseudo-labels, `model/` the trainer's folder until it is renamed into place.
pub(super) struct Staging {
    dir: TempDir,
}

impl Staging {
    /// Creates the sibling (and the output's parent folder) and its `data/` folder.
    pub(super) fn beside(target: &Path) -> Result<Self> {
        let parent = target
            .parent()
            .map_or_else(|| PathBuf::from("."), Path::to_path_buf);
        std::fs::create_dir_all(&parent).map_err(file_err(&parent))?;
        let name = target
            .file_name()
            .map_or_else(|| "adapted".into(), |n| n.to_string_lossy().into_owned());
        let dir = tempfile::Builder::new()
            .prefix(&format!(".{name}.partial-"))
            .tempdir_in(&parent)
            .map_err(|e| file_err(&parent)(e).context("creating a temporary folder"))?;
        let staging = Staging { dir };
        let data = staging.data();
        std::fs::create_dir_all(&data).map_err(file_err(&data))?;
        Ok(staging)
    }

    /// The pseudo-label dataset's folder.
    pub(super) fn data(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    /// The model folder the trainer writes.
    pub(super) fn model(&self) -> PathBuf {
        self.dir.path().join("model")
    }
}

/// Moves the pseudo-label dataset to `keep` (a new folder; copied where a rename cannot cross file
/// systems).
pub(super) fn keep_pseudo_labels(data: &Path, keep: &Path) -> Result<()> {
    let keep = normalise(keep)?;
    if keep.exists() {
        return Err(Error::Invalid(format!(
            "--keep-data {}: exists; give a new folder",
            keep.display()
        )));
    }
    if let Some(parent) = keep.parent() {
        std::fs::create_dir_all(parent).map_err(file_err(parent))?;
    }
    std::fs::rename(data, &keep)
        .or_else(|_| copy_tree(data, &keep))
        .map_err(|e| file_err(&keep)(e).context(format!("moving the pseudo-labels to {}", keep.display())))
}

/// Renames the finished `model` folder to `target`, replacing an earlier adapted folder there.
pub(super) fn install(model: &Path, target: &Path) -> Result<()> {
    if target.exists() {
        std::fs::remove_dir_all(target)
            .map_err(|e| file_err(target)(e).context(format!("replacing {}", target.display())))?;
    }
    std::fs::rename(model, target)
        .map_err(|e| file_err(model)(e).context(format!("renaming into {}", target.display())))
}

/// Copies a folder tree.
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalise_drops_dots_of_a_path_that_does_not_exist() {
        let tmp = tempfile::tempdir().unwrap();
        let root = normalise(tmp.path()).unwrap();
        let path = tmp.path().join("a/./b/../c");
        assert_eq!(normalise(&path).unwrap(), root.join("a/c"));
    }

    #[test]
    fn an_occupied_output_needs_force_and_an_earlier_manifest() {
        let tmp = tempfile::tempdir().unwrap();
        let (out, base) = (tmp.path().join("mine"), tmp.path().join("base"));
        assert!(check_output(&out, &base, false).is_ok(), "a new folder is fine");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("notes.txt"), "x").unwrap();
        let refused = |force| check_output(&out, &base, force).unwrap_err().to_string();
        assert!(refused(false).contains("give --force"), "{}", refused(false));
        assert!(refused(true).contains(MANIFEST), "{}", refused(true));
        std::fs::write(out.join(MANIFEST), "{}").unwrap();
        assert!(check_output(&out, &base, true).is_ok());
        assert!(refused(false).contains("not empty"));
    }

    #[test]
    fn the_base_models_and_a_folder_holding_them_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let base = tmp.path().join("models/base");
        for out in [base.clone(), tmp.path().join("models")] {
            let e = check_output(&out, &base, true).unwrap_err().to_string();
            assert!(e.contains("--out") && e.contains("the base models"), "{e}");
        }
    }
}
