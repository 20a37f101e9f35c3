//! What can go wrong with a run's store.

use std::path::PathBuf;

/// What can go wrong with a run's store. Every error names the path, field or value.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// [`RunStore::create`] found a store already there.
    #[error("{path}: a store already exists")]
    Exists {
        /// The store directory.
        path: PathBuf,
    },
    /// [`RunStore::open`] found no store.
    #[error("{path}: no store (is this a run directory?)")]
    NotFound {
        /// The store directory.
        path: PathBuf,
    },
    /// A file operation failed.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What was being done.
        action: &'static str,
        /// The I/O error.
        source: std::io::Error,
    },
    /// zarrs failed on a node (array or group) of the store.
    #[error("{path}: {action}: {message}")]
    Zarr {
        /// The node path (e.g. `run.zarr/frames/pixels`) or chunk file.
        path: String,
        /// What was being done.
        action: &'static str,
        /// zarrs' message.
        message: String,
    },
    /// The store's structure is not what this version writes.
    #[error("{path}: {message}")]
    Layout {
        /// The node.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// A frame size of zero.
    #[error("frame size {width}x{height}: both must be at least 1")]
    FrameSize {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// An image of the wrong number of pixels.
    #[error("{what}: {got} values, expected {expected} ({width}x{height})")]
    ImageSize {
        /// Which image (e.g. `frame 3`, `product dolp`).
        what: String,
        /// Values given.
        got: usize,
        /// Values expected.
        expected: usize,
        /// Store width.
        width: u32,
        /// Store height.
        height: u32,
    },
    /// A frame index past the stored frames.
    #[error("frame {index}: not stored (the store holds {count} frames)")]
    FrameOutOfRange {
        /// The index asked for.
        index: u64,
        /// Frames in `frames/pixels`.
        count: u64,
    },
    /// A chunk that is inside the array but was never written (or was deleted).
    #[error("{path}: missing chunk ({what})")]
    MissingChunk {
        /// The chunk file.
        path: PathBuf,
        /// What it holds (e.g. `frame 3`).
        what: String,
    },
    /// Frame records that cannot be stored (or stored metadata that cannot be read back).
    #[error("frame metadata: {field} = {value}: {message}")]
    Metadata {
        /// The field (e.g. `records[3].index`, `frames/kind[2]`).
        field: String,
        /// Its value.
        value: String,
        /// What is wrong.
        message: String,
    },
    /// A product that cannot be stored or read.
    #[error("product {name:?}: {message}")]
    Product {
        /// The product's name.
        name: String,
        /// What is wrong.
        message: String,
    },
}
