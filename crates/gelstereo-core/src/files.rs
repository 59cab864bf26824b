//! Writing files without clobbering: gelstereo replaces only regular files, and a file is written
//! whole to a temporary name beside it, then renamed, so a full disk or an interrupted run never
//! leaves a cut file where a good one was.

use std::io::Write as _;
use std::path::{Path, PathBuf};

/// Fails unless `path` is absent or a regular file: a symbolic link, a FIFO, a device node or a
/// folder is never renamed over (as root, renaming onto `/dev/null` would replace the device).
pub fn ensure_replaceable(path: &Path) -> std::io::Result<()> {
    match std::fs::symlink_metadata(path) {
        Ok(meta) if !meta.file_type().is_file() => Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!(
                "exists and is {}, not a regular file; gelstereo writes only regular files",
                kind(&meta.file_type())
            ),
        )),
        _ => Ok(()),
    }
}

fn kind(t: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt as _;
        if t.is_fifo() {
            return "a FIFO";
        }
        if t.is_char_device() || t.is_block_device() {
            return "a device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    if t.is_symlink() {
        "a symbolic link"
    } else if t.is_dir() {
        "a folder"
    } else {
        "not a plain file"
    }
}

/// Writes `bytes` to `path` whole or not at all: to a temporary file beside it, synced, then renamed
/// over it. An existing file at `path` stays as it was when anything fails (a full disk).
pub fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    ensure_replaceable(path)?;
    let temp = temporary_beside(path);
    let written = std::fs::File::create(&temp).and_then(|mut f| {
        f.write_all(bytes)?;
        f.sync_all()
    });
    if let Err(e) = written.and_then(|()| std::fs::rename(&temp, path)) {
        let _ = std::fs::remove_file(&temp);
        return Err(e);
    }
    Ok(())
}

/// `.NAME.PID.partial` in the folder of `path`.
fn temporary_beside(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.{}.partial", std::process::id()))
}

/// `name` as text that tells every name apart: valid UTF-8 as it is, each byte that is not as
/// `\xNN` (as Python's `backslashreplace` writes it). `Path::display` would turn every such byte
/// into U+FFFD, so `a\xff.jpg` and `a\xfe.jpg` would read, and be written, as one name.
pub fn escaped(name: &std::ffi::OsStr) -> String {
    let bytes = name.as_encoded_bytes();
    let mut text = String::with_capacity(bytes.len());
    for chunk in bytes.utf8_chunks() {
        text.push_str(chunk.valid());
        for b in chunk.invalid() {
            text.push_str(&format!("\\x{b:02x}"));
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(unix)]
    #[test]
    fn names_that_are_not_utf8_stay_apart() {
        use std::os::unix::ffi::OsStrExt;
        let name = |b: &[u8]| escaped(std::ffi::OsStr::from_bytes(b));
        assert_eq!(name(b"a\xff.jpg"), "a\\xff.jpg");
        assert_ne!(name(b"a\xff.jpg"), name(b"a\xfe.jpg"));
        assert_eq!(name("äb.png".as_bytes()), "äb.png");
    }

    #[test]
    fn only_regular_files_are_replaced_and_a_failed_write_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("calib.yaml");
        write_whole(&file, b"first").unwrap();
        write_whole(&file, b"second").unwrap();
        assert_eq!(std::fs::read(&file).unwrap(), b"second");
        let folder = dir.path().join("folder");
        std::fs::create_dir(&folder).unwrap();
        let err = write_whole(&folder, b"x").unwrap_err().to_string();
        assert!(err.contains("a folder"), "{err}");
        #[cfg(unix)]
        {
            let link = dir.path().join("link.yaml");
            std::os::unix::fs::symlink(&file, &link).unwrap();
            let err = write_whole(&link, b"x").unwrap_err().to_string();
            assert!(err.contains("symbolic link"), "{err}");
            assert_eq!(std::fs::read(&file).unwrap(), b"second");
            let err = write_whole(Path::new("/dev/null"), b"x").unwrap_err().to_string();
            assert!(err.contains("a device"), "{err}");
        }
        // A write that cannot finish (its folder is gone) leaves nothing behind.
        let gone = dir.path().join("gone/calib.yaml");
        assert!(write_whole(&gone, b"x").is_err());
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(left.len(), 3, "{left:?}");
    }
}
