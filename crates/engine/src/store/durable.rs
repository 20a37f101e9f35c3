//! The durable filesystem store: every write to a temporary file, synced, renamed and the directory synced.

use super::error::StoreError;
use std::collections::BTreeSet;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use zarrs::filesystem::FilesystemStore;
use zarrs::storage::byte_range::ByteRangeIterator;
use zarrs::storage::{
    store_set_partial_many, Bytes, ListableStorageTraits, MaybeBytes, MaybeBytesIterator,
    OffsetBytesIterator, ReadableStorageTraits, StorageError, StoreKey, StoreKeys,
    StoreKeysPrefixes, StorePrefix, WritableStorageTraits,
};

/// A filesystem store whose writes are atomic and durable: write a temporary file, sync it,
/// rename it over the target, sync the directory. Reads, listing and erasing are zarrs'
/// [`FilesystemStore`].
#[derive(Debug)]
pub(super) struct DurableStore {
    pub(super) inner: FilesystemStore,
    root: PathBuf,
    /// Writes of one thread held back for [`DurableStore::commit_batch`] (synced temporary
    /// files and their targets, in write order).
    batch: Mutex<Option<Batch>>,
}

/// Locks `m`; a panic while holding the lock leaves the data as consistent as the files: keep going.
pub(super) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl DurableStore {
    pub(super) fn new(root: &Path) -> Result<DurableStore, StoreError> {
        let inner = FilesystemStore::new(root).map_err(|e| StoreError::Zarr {
            path: root.display().to_string(),
            action: "opening the filesystem store",
            message: e.to_string(),
        })?;
        Ok(DurableStore {
            inner,
            root: root.to_path_buf(),
            batch: Mutex::new(None),
        })
    }

    /// From now until [`Self::commit_batch`], this thread's writes are written and synced
    /// to their temporary files but not renamed over their targets: readers keep seeing the
    /// old files.
    pub(super) fn begin_batch(&self) {
        *lock(&self.batch) = Some(Batch {
            thread: std::thread::current().id(),
            renames: Vec::new(),
        });
    }

    /// Renames every held-back write over its target, in write order, then syncs each
    /// directory once: the files change together, within microseconds, so a reader (or a
    /// crash) almost never sees some new and some old. With `keep` false (a write of the
    /// batch failed) the temporary files are removed and the targets keep their old content.
    pub(super) fn commit_batch(&self, keep: bool) -> std::io::Result<()> {
        let Some(batch) = lock(&self.batch).take() else {
            return Ok(());
        };
        if !keep {
            for (tmp, _) in &batch.renames {
                let _ = std::fs::remove_file(tmp);
            }
            return Ok(());
        }
        let mut dirs = BTreeSet::new();
        for (i, (tmp, path)) in batch.renames.iter().enumerate() {
            if let Err(e) = std::fs::rename(tmp, path) {
                for (tmp, _) in &batch.renames[i..] {
                    let _ = std::fs::remove_file(tmp);
                }
                return Err(e);
            }
            dirs.insert(path.parent().unwrap_or(&self.root).to_path_buf());
        }
        for d in dirs {
            File::open(&d)?.sync_all()?;
        }
        Ok(())
    }

    fn write_atomic(&self, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
        let parent = path.parent().unwrap_or(&self.root);
        create_dirs_durably(parent)?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        // Unique per write: two stores in one process may replace the same file.
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let tmp = parent.join(format!(".{name}.{}-{n}.partial", std::process::id()));
        let result = (|| {
            let mut f = File::create(&tmp)?;
            f.write_all(bytes)?;
            f.sync_all()?;
            drop(f);
            if let Some(batch) = lock(&self.batch)
                .as_mut()
                .filter(|b| b.thread == std::thread::current().id())
            {
                batch.renames.push((tmp.clone(), path.to_path_buf()));
                return Ok(());
            }
            std::fs::rename(&tmp, path)?;
            File::open(parent)?.sync_all()
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        result
    }
}

/// Writes held back by [`DurableStore::begin_batch`].
#[derive(Debug)]
pub(super) struct Batch {
    thread: std::thread::ThreadId,
    renames: Vec<(PathBuf, PathBuf)>,
}

/// Creates `dir` and its missing ancestors, syncing the parent of each directory created so
/// that the new entries survive a crash.
pub(super) fn create_dirs_durably(dir: &Path) -> std::io::Result<()> {
    if dir.is_dir() {
        return Ok(());
    }
    let mut missing = Vec::new();
    let mut d = Some(dir);
    while let Some(p) = d {
        if p.is_dir() {
            break;
        }
        missing.push(p.to_path_buf());
        d = p.parent();
    }
    std::fs::create_dir_all(dir)?;
    for p in missing.iter().rev() {
        if let Some(parent) = p.parent() {
            File::open(parent)?.sync_all()?;
        }
    }
    Ok(())
}

impl ReadableStorageTraits for DurableStore {
    fn get(&self, key: &StoreKey) -> Result<MaybeBytes, StorageError> {
        self.inner.get(key)
    }

    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> Result<MaybeBytesIterator<'a>, StorageError> {
        self.inner.get_partial_many(key, byte_ranges)
    }

    fn size_key(&self, key: &StoreKey) -> Result<Option<u64>, StorageError> {
        self.inner.size_key(key)
    }

    fn supports_get_partial(&self) -> bool {
        self.inner.supports_get_partial()
    }
}

impl ListableStorageTraits for DurableStore {
    fn list(&self) -> Result<StoreKeys, StorageError> {
        self.inner.list()
    }

    fn list_prefix(&self, prefix: &StorePrefix) -> Result<StoreKeys, StorageError> {
        self.inner.list_prefix(prefix)
    }

    fn list_dir(&self, prefix: &StorePrefix) -> Result<StoreKeysPrefixes, StorageError> {
        self.inner.list_dir(prefix)
    }

    fn size_prefix(&self, prefix: &StorePrefix) -> Result<u64, StorageError> {
        self.inner.size_prefix(prefix)
    }
}

impl WritableStorageTraits for DurableStore {
    fn set(&self, key: &StoreKey, value: Bytes) -> Result<(), StorageError> {
        let path = self.inner.key_to_fspath(key);
        self.write_atomic(&path, &value)?;
        Ok(())
    }

    fn set_partial_many(
        &self,
        key: &StoreKey,
        offset_values: OffsetBytesIterator,
    ) -> Result<(), StorageError> {
        // Read, patch, and replace whole (atomically).
        store_set_partial_many(self, key, offset_values)
    }

    fn erase(&self, key: &StoreKey) -> Result<(), StorageError> {
        self.inner.erase(key)
    }

    fn erase_prefix(&self, prefix: &StorePrefix) -> Result<(), StorageError> {
        self.inner.erase_prefix(prefix)
    }

    fn supports_set_partial(&self) -> bool {
        false
    }
}
