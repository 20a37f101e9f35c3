//! Crash-safe file replacement: the new content is written beside the file, flushed to disk,
//! renamed over it and the directory flushed, so a reader (or a restart after SIGKILL or a
//! power cut) sees the old file or the new one, never a part.

use crate::error::StationError;
use std::io::Write;
use std::path::Path;

/// Replaces `path` with `bytes` atomically (module docs); `private` makes the file readable by
/// its owner only (keys).
pub fn write(path: &Path, bytes: &[u8], private: bool) -> Result<(), StationError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| StationError::io(dir, e))?;
    let name = path
        .file_name()
        .map_or_else(|| "file".to_string(), |n| n.to_string_lossy().into_owned());
    let tmp = dir.join(format!(".{name}.tmp"));
    // A temporary left by a crash goes first (the mode below applies only to a new file).
    let _ = std::fs::remove_file(&tmp);
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    if private {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o600);
    }
    let mut f = options.open(&tmp).map_err(|e| StationError::io(&tmp, e))?;
    f.write_all(bytes).map_err(|e| StationError::io(&tmp, e))?;
    f.sync_all().map_err(|e| StationError::io(&tmp, e))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| StationError::io(path, e))?;
    // The rename itself reaches the disk only with the directory.
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// [`write`] of a value as pretty JSON.
pub fn write_json<T: serde::Serialize>(
    path: &Path,
    value: &T,
    private: bool,
) -> Result<(), StationError> {
    let text = serde_json::to_vec_pretty(value).map_err(|e| StationError::Corrupt {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    write(path, &text, private)
}

/// Reads a JSON file written by [`write_json`]; `None` when it does not exist.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<Option<T>, StationError> {
    let text = match std::fs::read(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(StationError::io(path, e)),
    };
    serde_json::from_slice(&text)
        .map(Some)
        .map_err(|e| StationError::Corrupt {
            path: path.to_path_buf(),
            message: e.to_string(),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_replaced_file_holds_the_new_content_and_no_temporary_is_left() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("state.json");
        write_json(&p, &vec![1, 2, 3], false).unwrap();
        write_json(&p, &vec![4], true).unwrap();
        let back: Vec<i32> = read_json(&p).unwrap().unwrap();
        assert_eq!(back, vec![4]);
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "only the file itself remains");
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(&p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600, "a private file is its owner's only");
    }
}
