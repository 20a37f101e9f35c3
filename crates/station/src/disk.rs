//! Free space on the data directory's file system, against the station's reserve.

use std::path::Path;

/// Bytes available to the station under `dir` (`None` if the file system cannot say).
pub fn free_bytes(dir: &Path) -> Option<u64> {
    fs4::available_space(dir).ok()
}

/// Whether `bytes` more fit on `dir`'s disk with `reserve` left free: `Err` says how much is
/// free and what is needed.
pub fn fits(dir: &Path, bytes: u64, reserve: u64) -> Result<u64, String> {
    let Some(free) = free_bytes(dir) else {
        return Err(format!(
            "cannot read the free space of {}: refusing to queue what might not fit",
            dir.display()
        ));
    };
    if free < reserve.saturating_add(bytes) {
        return Err(format!(
            "the run needs about {:.1} MB and the station keeps {:.1} MB free, but only {:.1} MB \
             is free on {} (free space, delete or upload runs, or lower reserve_mb)",
            bytes as f64 / 1e6,
            reserve as f64 / 1e6,
            free as f64 / 1e6,
            dir.display()
        ));
    }
    Ok(free)
}
