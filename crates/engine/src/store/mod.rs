//! The run's Zarr v3 store, `RUN_DIR/run.zarr`: raw frames (one chunk per frame, so a crash
//! loses at most the frame being written), per-frame metadata, products, the dark mean and the
//! run's record (plan, software, devices, calibration, decision log, summary).
//!
//! The journal (`journal.jsonl`, [`crate::journal`]) is the run's source of truth; the store
//! mirrors it for readers. Open it from Python with `zarr` (v3):
//!
//! ```python
//! import zarr
//! run = zarr.open_group("RUN_DIR/run.zarr", mode="r")
//! pixels = run["frames/pixels"]            # uint16 [N, H, W], lazily read per frame
//! angles = run["frames/measured_angle_deg"][:]
//! dolp = run["products/dolp"][0]           # float32 [H, W] of the first processed set
//! plan = run.attrs["plan"]
//! ```
//!
//! # Layout
//!
//! ```text
//! run.zarr/                 group; attributes:
//!                             "format": "polarimeter-run", "format_version": 1,
//!                             "plan", "software", "devices" (json, as given at creation),
//!                             "state" (json, e.g. "running" / "done"),
//!                             "calibration" (json object, one entry per kind),
//!                             "decisions" (json array, the planner's decision log),
//!                             "summary" (json object, written at the end)
//!   frames/                 group; attributes: "labels" (json array of strings, one per frame:
//!                             the plan step's label, e.g. "set 3 angle 45")
//!     pixels                uint16  [N, H, W], chunk [1, H, W] (one chunk per frame), fill 0
//!     kind                  uint8   [N]   0 light, 1 dark
//!     step                  uint64  [N]   the plan step the frame fulfils
//!     set                   int64   [N]   angle set, -1: none
//!     commanded_angle_deg   float64 [N]
//!     measured_angle_deg    float64 [N]   NaN: not read back
//!     angle_start_deg       float64 [N]   analyzer angle at the exposure's start, [0, 180)
//!     angle_end_deg         float64 [N]   at its end, unwrapped: end - start in [0, 180)
//!     angle_source          uint8   [N]   0 settled, 1 encoder trigger, 2 timestamps
//!     angle_sigma_deg       float64 [N]   uncertainty of each end, NaN: not estimated
//!     exposure_us           float64 [N]
//!     gain                  float64 [N]
//!     host_time_unix_ns     int64   [N]
//!     device_timestamp_ns   int64   [N]   -1: none
//!     frame_id              uint64  [N]
//!     sun_zenith_deg        float64 [N]   NaN: none
//!     sun_azimuth_deg       float64 [N]   NaN: none
//!     hash                  uint64  [N]   XXH3-64 of the frame's little-endian pixel bytes
//!   products/               group (one slot per processed angle set); attributes: "names"
//!                             (json array of the product names written so far)
//!     <name>                float32 [M, H, W], chunk [1, H, W], fill NaN, for each product
//!                             name (e.g. s0 s1 s2 dolp aop_rad sigma_s0 ...)
//!     set                   int64   [M]    the angle set of each slot, -1: slot not written
//!     angles_deg            float64 [M, K] the analyzer angles of each slot's frames, K the
//!                             largest number of angles of any slot, NaN padded
//!   darks/                  group
//!     mean                  float32 [H, W] the mean dark frame (written at the end, if any)
//! ```
//!
//! Every chunk carries a `crc32c` checksum (a core Zarr v3 codec; no compression), so a
//! damaged chunk fails to read instead of returning wrong numbers. The per-frame metadata
//! arrays and `products/set`, `products/angles_deg` are small and rewritten whole
//! ([`RunStore::write_frame_metadata`] mirrors the journal's frame records), in chunks of a
//! fixed 4096 rows (32 columns): a chunk's size never depends on the array's length, so a
//! crash between a chunk and its array's metadata leaves an array that still reads.
//!
//! # Durability
//!
//! Every file of the store (chunks and `zarr.json` metadata) is written to a temporary file
//! in the same directory (`.<name>.<pid>-<n>.partial`), synced, renamed over the target and the
//! directory synced: a write is atomic and durable when it returns, so a crash leaves either
//! the old or the new file, never a torn one. (zarrs' own filesystem store truncates and
//! rewrites in place.) A crash can leave a stray `.<name>.<pid>-<n>.partial` file: zarrs
//! ignores it, Python's zarr warns about it ("not recognized as a component") and reads on;
//! it may be deleted when no run is writing.
//!
//! Attribute updates are read-modify-write of a group's `zarr.json`: serialised within one
//! `RunStore`, not across `RunStore`s or processes (the run has one writer).
//!
//! [`RunStore::write_frame`] stores the chunk first and grows `frames/pixels` afterwards, so a
//! frame is either stored and visible or invisible. A frame counts once its journal entry is
//! written (after `write_frame` returns); [`RunStore::write_frame_metadata`] resizes
//! `frames/pixels` to the frames the journal records, hiding a frame written by a process that
//! crashed before journaling it.
//!
//! A `RunStore` may be used from several threads (`&self` methods; the arrays are held behind
//! mutexes), and several `RunStore`s may be open on one run (one writer, any readers: readers
//! see frames written after they opened the store).

mod schema;

pub use schema::{conventions, HASH_ALGORITHM, KIND_CODES};

use crate::{pixel_hash, AngleSource, FrameKind, FrameRecord};
use serde::{Deserialize, Serialize};
use serde_json::{json, Map, Value};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use zarrs::array::builder::ArrayBuilderFillValue;
use zarrs::array::{
    data_type, Array, CodecOptions, DataType, Element, ElementOwned, ZARR_NAN_F32, ZARR_NAN_F64,
};
use zarrs::filesystem::FilesystemStore;
use zarrs::group::{Group, GroupBuilder};
use zarrs::storage::byte_range::ByteRangeIterator;
use zarrs::storage::{
    store_set_partial_many, Bytes, ListableStorageTraits, MaybeBytes, MaybeBytesIterator,
    OffsetBytesIterator, ReadableStorageTraits, StorageError, StoreKey, StoreKeys,
    StoreKeysPrefixes, StorePrefix, WritableStorageTraits,
};

/// The store's directory name inside a run directory.
pub const STORE_DIR: &str = "run.zarr";
/// The `"format"` root attribute.
pub const FORMAT: &str = "polarimeter-run";
/// The `"format_version"` root attribute.
pub const FORMAT_VERSION: u64 = 1;

const PIXELS: &str = "/frames/pixels";
const FRAMES: &str = "/frames";
const PRODUCTS: &str = "/products";
const PRODUCT_SET: &str = "/products/set";
const PRODUCT_ANGLES: &str = "/products/angles_deg";
const DARK_MEAN: &str = "/darks/mean";
/// Names of `products/` members that are not product images.
const PRODUCT_RESERVED: [&str; 2] = ["set", "angles_deg"];

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

fn zarr_err<E: std::fmt::Display>(
    path: impl Into<String>,
    action: &'static str,
) -> impl FnOnce(E) -> StoreError {
    let path = path.into();
    move |e| StoreError::Zarr {
        path,
        action,
        message: e.to_string(),
    }
}

fn io_err(path: &Path, action: &'static str) -> impl FnOnce(std::io::Error) -> StoreError {
    let path = path.to_path_buf();
    move |source| StoreError::Io {
        path,
        action,
        source,
    }
}

/// A finding of [`RunStore::verify`]: what the store holds against the journal's records.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Verification {
    /// Records checked.
    pub checked: u64,
    /// Frames whose stored pixels hash to the recorded hash.
    pub ok: u64,
    /// Recorded frames with no stored chunk (or past the stored array).
    pub missing: Vec<u64>,
    /// Recorded frames whose chunk is unreadable (checksum) or whose pixels hash differs.
    pub mismatched: Vec<u64>,
    /// Stored frames with no record (written by a process that crashed before journaling).
    pub unrecorded: Vec<u64>,
    /// One line per finding, for people.
    pub findings: Vec<String>,
}

impl Verification {
    /// Every recorded frame is stored as recorded.
    pub fn is_ok(&self) -> bool {
        self.missing.is_empty() && self.mismatched.is_empty()
    }

    /// What was found about frame `index` (empty when nothing was).
    pub fn finding(&self, index: u64) -> String {
        let prefix = format!("frame {index}:");
        self.findings
            .iter()
            .find(|f| f.starts_with(&prefix))
            .cloned()
            .unwrap_or_default()
    }
}

/// One slot of `products/`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProductSlot {
    /// The slot (index in the products arrays).
    pub slot: u64,
    /// The angle set written there (`None`: slot not written).
    pub set: Option<u64>,
    /// The analyzer angles of the set's frames, degrees.
    pub angles_deg: Vec<f64>,
}

/// The run's Zarr store. See the [module documentation](self) for the layout.
#[derive(Debug)]
pub struct RunStore {
    path: PathBuf,
    store: Arc<DurableStore>,
    width: u32,
    height: u32,
    pixels: Mutex<Array<DurableStore>>,
    products: Mutex<Option<ProductsState>>,
    /// Serialises read-modify-write of group attributes within this process.
    attrs: Mutex<()>,
}

#[derive(Debug)]
struct ProductsState {
    slots: u64,
    sets: Vec<i64>,
    angles: Vec<Vec<f64>>,
    arrays: HashMap<String, Array<DurableStore>>,
    names: Vec<String>,
}

/// Rows per chunk of the small index arrays (the per-frame metadata, `products/set`,
/// `products/angles_deg`): fixed, so an array's chunks keep their size as it grows.
const INDEX_ROWS_PER_CHUNK: u64 = 4096;
/// Columns per chunk of the two-dimensional index array `products/angles_deg`.
const INDEX_COLUMNS_PER_CHUNK: u64 = 32;

/// The chunk shape of a small index array of `rank` dimensions.
fn index_chunk(rank: usize) -> Vec<u64> {
    let mut chunk = vec![INDEX_COLUMNS_PER_CHUNK; rank];
    if let Some(rows) = chunk.first_mut() {
        *rows = INDEX_ROWS_PER_CHUNK;
    }
    chunk
}

/// The chunks of a regular grid covering `shape`: each chunk's grid indices and, for each of
/// its elements in C order, the element's index in the whole array in C order (`None`
/// outside the shape, in an edge chunk's padding).
fn chunks_of(shape: &[u64], chunk: &[u64]) -> Vec<(Vec<u64>, Vec<Option<usize>>)> {
    let grid: Vec<u64> = shape
        .iter()
        .zip(chunk)
        .map(|(&s, &c)| s.div_ceil(c.max(1)))
        .collect();
    let count: u64 = grid.iter().product();
    let per_chunk: u64 = chunk.iter().product();
    let mut out = Vec::with_capacity(count as usize);
    for flat_chunk in 0..count {
        let indices = unravel(flat_chunk, &grid);
        let elements = (0..per_chunk)
            .map(|flat_element| {
                let within = unravel(flat_element, chunk);
                let mut index = 0u64;
                for d in 0..shape.len() {
                    let at = indices[d] * chunk[d] + within[d];
                    if at >= shape[d] {
                        return None;
                    }
                    index = index * shape[d] + at;
                }
                Some(index as usize)
            })
            .collect();
        out.push((indices, elements));
    }
    out
}

/// The C-order multi-index of `flat` in an array of `shape`.
fn unravel(mut flat: u64, shape: &[u64]) -> Vec<u64> {
    let mut index = vec![0u64; shape.len()];
    for d in (0..shape.len()).rev() {
        let n = shape[d].max(1);
        index[d] = flat % n;
        flat /= n;
    }
    index
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic while holding the lock leaves the data as consistent as the files: keep going.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Store every chunk, even one that equals the fill value (zarrs skips those by default; a
/// frame of zeros must still be stored).
fn codec_options() -> CodecOptions {
    CodecOptions::default().with_store_empty_chunks(true)
}

/// `frames/pixels` with `frames` frames of `width x height`, one chunk per frame.
fn pixels_array(
    store: &Arc<DurableStore>,
    frames: u64,
    width: u32,
    height: u32,
) -> Result<Array<DurableStore>, zarrs::array::ArrayCreateError> {
    schema::image_stack(store.clone(), PIXELS, frames, width, height)
}

/// `products/<name>` with `slots` slots of `width x height`, one chunk per slot.
fn product_array(
    store: &Arc<DurableStore>,
    node: &str,
    slots: u64,
    width: u32,
    height: u32,
) -> Result<Array<DurableStore>, zarrs::array::ArrayCreateError> {
    schema::image_stack(store.clone(), node, slots, width, height)
}

impl RunStore {
    /// Creates `run_dir/run.zarr` for `width` x `height` frames, with the root `attributes`
    /// ("plan", "software", "devices", "state", ...). Missing standard attributes get
    /// defaults: software [`crate::software_version`], calibration `{}`, decisions `[]`,
    /// summary `{}`, state `"created"`, plan and devices `null`.
    pub fn create(
        run_dir: &Path,
        width: u32,
        height: u32,
        attributes: Map<String, Value>,
    ) -> Result<RunStore, StoreError> {
        if width == 0 || height == 0 {
            return Err(StoreError::FrameSize { width, height });
        }
        let path = run_dir.join(STORE_DIR);
        if path.exists() {
            return Err(StoreError::Exists { path });
        }
        std::fs::create_dir_all(run_dir).map_err(io_err(run_dir, "creating the run directory"))?;
        let store = Arc::new(DurableStore::new(&path)?);
        let p = |node: &str| format!("{}{node}", path.display());

        let mut attrs = attributes;
        attrs.insert("format".into(), json!(FORMAT));
        attrs.insert("format_version".into(), json!(FORMAT_VERSION));
        for (k, v) in [
            ("plan", Value::Null),
            ("software", crate::software_version()),
            ("devices", Value::Null),
            ("state", json!("created")),
            ("calibration", json!({})),
            ("decisions", json!([])),
            ("late_sets", json!([])),
            ("summary", json!({})),
        ] {
            attrs.entry(k).or_insert(v);
        }
        attrs.insert("conventions".into(), conventions());
        let mut root = GroupBuilder::new()
            .build(store.clone(), "/")
            .map_err(zarr_err(p(""), "creating the root group"))?;
        *root.attributes_mut() = attrs;
        root.store_metadata()
            .map_err(zarr_err(p(""), "writing the root group"))?;
        for (group, attrs) in [
            (FRAMES, json!({"labels": []})),
            (PRODUCTS, json!({"names": []})),
            ("/darks", json!({})),
        ] {
            let mut g = GroupBuilder::new()
                .build(store.clone(), group)
                .map_err(zarr_err(p(group), "creating the group"))?;
            if let Value::Object(a) = attrs {
                *g.attributes_mut() = a;
            }
            g.store_metadata()
                .map_err(zarr_err(p(group), "writing the group"))?;
        }
        let pixels = pixels_array(&store, 0, width, height)
            .map_err(zarr_err(p(PIXELS), "creating the array"))?;
        pixels
            .store_metadata()
            .map_err(zarr_err(p(PIXELS), "writing the array metadata"))?;
        let rs = RunStore {
            path,
            store,
            width,
            height,
            pixels: Mutex::new(pixels),
            products: Mutex::new(None),
            attrs: Mutex::new(()),
        };
        rs.write_frame_metadata(&[])?;
        rs.write_product_index(&[], &[])?;
        Ok(rs)
    }

    /// Opens the store of `run_dir` (to resume, read or export a run).
    pub fn open(run_dir: &Path) -> Result<RunStore, StoreError> {
        let path = run_dir.join(STORE_DIR);
        if !path.join("zarr.json").is_file() {
            return Err(StoreError::NotFound { path });
        }
        let store = Arc::new(DurableStore::new(&path)?);
        let node = format!("{}{PIXELS}", path.display());
        let pixels = Array::open(store.clone(), PIXELS).map_err(zarr_err(&node, "opening"))?;
        let shape = pixels.shape().to_vec();
        let (height, width) = match shape.as_slice() {
            [_, h, w] => (
                u32::try_from(*h).unwrap_or(0),
                u32::try_from(*w).unwrap_or(0),
            ),
            _ => (0, 0),
        };
        if width == 0 || height == 0 || pixels.data_type() != &data_type::uint16() {
            return Err(StoreError::Layout {
                path: node,
                message: format!(
                    "expected a uint16 [N, H, W] array, found {} {shape:?}",
                    pixels.data_type()
                ),
            });
        }
        Ok(RunStore {
            path,
            store,
            width,
            height,
            pixels: Mutex::new(pixels),
            products: Mutex::new(None),
            attrs: Mutex::new(()),
        })
    }

    /// The store directory (`RUN_DIR/run.zarr`).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Frame width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Frame height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    fn node(&self, node: &str) -> String {
        format!("{}{node}", self.path.display())
    }

    fn check_image(&self, what: impl FnOnce() -> String, got: usize) -> Result<(), StoreError> {
        if got != self.pixel_count() {
            return Err(StoreError::ImageSize {
                what: what(),
                got,
                expected: self.pixel_count(),
                width: self.width,
                height: self.height,
            });
        }
        Ok(())
    }

    fn chunk_path(&self, array: &Array<DurableStore>, indices: &[u64]) -> PathBuf {
        self.store.inner.key_to_fspath(&array.chunk_key(indices))
    }

    /// Stores frame `index` (row-major, `width * height` values) as chunk `[index, 0, 0]` of
    /// `frames/pixels`, growing the array if needed. When it returns, the chunk file and its
    /// directory are synced: the pixels are durable. Overwriting a frame (taking a step again
    /// after a crash) is allowed.
    pub fn write_frame(&self, index: u64, pixels: &[u16]) -> Result<(), StoreError> {
        self.check_image(|| format!("frame {index}"), pixels.len())?;
        let mut array = lock(&self.pixels);
        let count = array.shape().first().copied().unwrap_or(0);
        if index < count {
            return self.store_frame_chunk(&array, index, pixels);
        }
        // The chunk first, then the larger shape: a crash in between leaves the frame
        // invisible, never a visible frame without its pixels.
        let grown = pixels_array(&self.store, index + 1, self.width, self.height)
            .map_err(zarr_err(self.node(PIXELS), "growing"))?;
        self.store_frame_chunk(&grown, index, pixels)?;
        grown
            .store_metadata()
            .map_err(zarr_err(self.node(PIXELS), "writing the array metadata"))?;
        *array = grown;
        Ok(())
    }

    fn store_frame_chunk(
        &self,
        array: &Array<DurableStore>,
        index: u64,
        pixels: &[u16],
    ) -> Result<(), StoreError> {
        array
            .store_chunk_opt(&[index, 0, 0], pixels, &codec_options())
            .map_err(zarr_err(
                self.chunk_path(array, &[index, 0, 0]).display().to_string(),
                "writing frame chunk",
            ))
    }

    /// Re-reads `frames/pixels` metadata if `index` is past the shape this instance knows
    /// (another `RunStore` may have written frames since).
    fn refresh_pixels(&self, array: &mut Array<DurableStore>) -> Result<(), StoreError> {
        let fresh = Array::open(self.store.clone(), PIXELS)
            .map_err(zarr_err(self.node(PIXELS), "re-reading the array metadata"))?;
        *array = fresh;
        Ok(())
    }

    /// Reads frame `index`.
    pub fn read_frame(&self, index: u64) -> Result<Vec<u16>, StoreError> {
        match self.read_frame_inner(index)? {
            FrameRead::Pixels(p) => Ok(p),
            FrameRead::OutOfRange(count) => Err(StoreError::FrameOutOfRange { index, count }),
            FrameRead::Missing(path) => Err(StoreError::MissingChunk {
                path,
                what: format!("frame {index}"),
            }),
            FrameRead::Unreadable(path, message) => Err(StoreError::Zarr {
                path: path.display().to_string(),
                action: "reading frame chunk",
                message,
            }),
        }
    }

    fn read_frame_inner(&self, index: u64) -> Result<FrameRead, StoreError> {
        let mut array = lock(&self.pixels);
        let count = |a: &Array<DurableStore>| a.shape().first().copied().unwrap_or(0);
        if index >= count(&array) {
            self.refresh_pixels(&mut array)?;
            if index >= count(&array) {
                return Ok(FrameRead::OutOfRange(count(&array)));
            }
        }
        let path = self.chunk_path(&array, &[index, 0, 0]);
        match array.retrieve_chunk_if_exists_opt::<Vec<u16>>(&[index, 0, 0], &codec_options()) {
            Ok(Some(p)) => Ok(FrameRead::Pixels(p)),
            Ok(None) => Ok(FrameRead::Missing(path)),
            Err(e) => Ok(FrameRead::Unreadable(path, e.to_string())),
        }
    }

    /// Frames in `frames/pixels` (its first dimension, as on disk).
    pub fn frame_count(&self) -> u64 {
        let mut array = lock(&self.pixels);
        if let Err(e) = self.refresh_pixels(&mut array) {
            tracing::warn!("{e}");
        }
        array.shape().first().copied().unwrap_or(0)
    }

    /// Rewrites the per-frame metadata arrays (and the `labels` attribute of `frames/`) from
    /// `records`, which must be sorted by index and cover `0..N` without gaps, and resizes
    /// `frames/pixels` to N frames: the journal is the truth, the store mirrors it.
    ///
    /// Each call rewrites every array (O(N), about 30 small synced files): call it at set
    /// boundaries and at the end, not for every frame.
    pub fn write_frame_metadata(&self, records: &[FrameRecord]) -> Result<(), StoreError> {
        let n = records.len();
        let mut kind = Vec::with_capacity(n);
        let mut step = Vec::with_capacity(n);
        let mut set = Vec::with_capacity(n);
        let mut commanded = Vec::with_capacity(n);
        let mut measured = Vec::with_capacity(n);
        let mut start = Vec::with_capacity(n);
        let mut end = Vec::with_capacity(n);
        let mut source = Vec::with_capacity(n);
        let mut angle_sigma = Vec::with_capacity(n);
        let mut exposure = Vec::with_capacity(n);
        let mut gain = Vec::with_capacity(n);
        let mut host_time = Vec::with_capacity(n);
        let mut device_time = Vec::with_capacity(n);
        let mut frame_id = Vec::with_capacity(n);
        let mut zenith = Vec::with_capacity(n);
        let mut azimuth = Vec::with_capacity(n);
        let mut hash = Vec::with_capacity(n);
        let mut labels = Vec::with_capacity(n);
        for (i, r) in records.iter().enumerate() {
            let bad = |field: &str, value: String, message: String| StoreError::Metadata {
                field: format!("records[{i}].{field}"),
                value,
                message,
            };
            if r.index != i as u64 {
                return Err(bad(
                    "index",
                    r.index.to_string(),
                    format!(
                        "records must be sorted by index and cover 0..{n} without gaps \
                         (expected {i})"
                    ),
                ));
            }
            if (r.width, r.height) != (self.width, self.height) {
                return Err(bad(
                    "width x height",
                    format!("{}x{}", r.width, r.height),
                    format!("the store holds {}x{} frames", self.width, self.height),
                ));
            }
            let to_i64 = |field: &str, v: u64| {
                i64::try_from(v).map_err(|_| {
                    bad(
                        field,
                        v.to_string(),
                        "larger than the int64 array can hold".into(),
                    )
                })
            };
            kind.push(r.kind.code());
            step.push(r.step);
            set.push(match r.set {
                Some(s) => to_i64("set", s)?,
                None => -1,
            });
            commanded.push(r.commanded_angle_deg);
            measured.push(r.measured_angle_deg);
            start.push(r.angle_start_deg);
            end.push(r.angle_end_deg);
            source.push(r.angle_source.code());
            angle_sigma.push(r.angle_sigma_deg);
            exposure.push(r.exposure_us);
            gain.push(r.gain);
            host_time.push(r.host_time_unix_ns);
            device_time.push(match r.device_timestamp_ns {
                Some(t) => to_i64("device_timestamp_ns", t)?,
                None => -1,
            });
            frame_id.push(r.frame_id);
            zenith.push(r.sun_zenith_deg.unwrap_or(f64::NAN));
            azimuth.push(r.sun_azimuth_deg.unwrap_or(f64::NAN));
            hash.push(r.hash);
            labels.push(Value::String(r.label.clone()));
        }
        let n = n as u64;
        let dims = ["frame"];
        self.write_whole(
            "/frames/kind",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint8(),
            0u8,
            &kind,
        )?;
        self.write_whole(
            "/frames/step",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint64(),
            0u64,
            &step,
        )?;
        self.write_whole(
            "/frames/set",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::int64(),
            -1i64,
            &set,
        )?;
        for (name, values) in [
            ("commanded_angle_deg", &commanded),
            ("measured_angle_deg", &measured),
            ("angle_start_deg", &start),
            ("angle_end_deg", &end),
            ("angle_sigma_deg", &angle_sigma),
            ("exposure_us", &exposure),
            ("gain", &gain),
            ("sun_zenith_deg", &zenith),
            ("sun_azimuth_deg", &azimuth),
        ] {
            self.write_whole(
                &format!("{FRAMES}/{name}"),
                vec![n],
                index_chunk(1),
                &dims,
                data_type::float64(),
                ZARR_NAN_F64,
                values,
            )?;
        }
        self.write_whole(
            "/frames/angle_source",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint8(),
            0u8,
            &source,
        )?;
        self.write_whole(
            "/frames/host_time_unix_ns",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::int64(),
            0i64,
            &host_time,
        )?;
        self.write_whole(
            "/frames/device_timestamp_ns",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::int64(),
            -1i64,
            &device_time,
        )?;
        self.write_whole(
            "/frames/frame_id",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint64(),
            0u64,
            &frame_id,
        )?;
        self.write_whole(
            "/frames/hash",
            vec![n],
            index_chunk(1),
            &dims,
            data_type::uint64(),
            0u64,
            &hash,
        )?;
        self.update_group_attribute(FRAMES, "labels", Value::Array(labels))?;

        let mut array = lock(&self.pixels);
        let count = array.shape().first().copied().unwrap_or(0);
        if count != n {
            let resized = pixels_array(&self.store, n, self.width, self.height)
                .map_err(zarr_err(self.node(PIXELS), "resizing"))?;
            resized
                .store_metadata()
                .map_err(zarr_err(self.node(PIXELS), "writing the array metadata"))?;
            *array = resized;
        }
        Ok(())
    }

    /// Writes a small array whole (the per-frame metadata, the products' index, the dark
    /// mean). The chunk shape is fixed by the array's kind ([`index_chunk`], or one chunk for
    /// an image), never by its current length: chunks are stored before the metadata when the
    /// array grows and after it when it shrinks, so a crash between the two leaves metadata
    /// whose every chunk decodes, and readers see the older or the newer values, never a
    /// chunk of the wrong size.
    #[allow(clippy::too_many_arguments)] // one call shape for every small array
    fn write_whole<T: Element + Copy + Into<ArrayBuilderFillValue>>(
        &self,
        node: &str,
        shape: Vec<u64>,
        chunk: Vec<u64>,
        dims: &[&str],
        data_type: DataType,
        fill: T,
        data: &[T],
    ) -> Result<(), StoreError> {
        let shrinks = Array::open(self.store.clone(), node)
            .ok()
            .and_then(|old| old.shape().first().copied())
            .is_some_and(|old_len| old_len > shape.first().copied().unwrap_or(0));
        let array = schema::array(
            self.store.clone(),
            node,
            shape.clone(),
            chunk.clone(),
            data_type,
            fill,
            dims,
        )
        .map_err(zarr_err(self.node(node), "creating the array"))?;
        let store_metadata = || {
            array
                .store_metadata()
                .map_err(zarr_err(self.node(node), "writing the array metadata"))
        };
        if shrinks {
            store_metadata()?;
        }
        for (indices, elements) in chunks_of(&shape, &chunk) {
            let values: Vec<T> = elements
                .iter()
                .map(|e| e.map_or(fill, |i| data[i]))
                .collect();
            array
                .store_chunk_opt(&indices, values, &codec_options())
                .map_err(zarr_err(self.node(node), "writing the array"))?;
        }
        if !shrinks {
            store_metadata()?;
        }
        Ok(())
    }

    /// Reads a small array written by [`Self::write_whole`]: (shape, values in C order). Every
    /// chunk the shape covers must exist and pass its checksum.
    fn read_whole<T: ElementOwned + Copy>(
        &self,
        node: &str,
    ) -> Result<(Vec<u64>, Vec<T>), StoreError> {
        let array =
            Array::open(self.store.clone(), node).map_err(zarr_err(self.node(node), "opening"))?;
        let shape = array.shape().to_vec();
        if shape.contains(&0) {
            return Ok((shape, Vec::new()));
        }
        let origin = vec![0u64; shape.len()];
        let chunk: Vec<u64> = array
            .chunk_shape(&origin)
            .map_err(zarr_err(self.node(node), "reading the chunk grid"))?
            .iter()
            .map(|c| c.get())
            .collect();
        let total = shape.iter().product::<u64>() as usize;
        let mut values: Vec<Option<T>> = vec![None; total];
        for (indices, elements) in chunks_of(&shape, &chunk) {
            let stored = array
                .retrieve_chunk_if_exists_opt::<Vec<T>>(&indices, &codec_options())
                .map_err(zarr_err(self.node(node), "reading"))?
                .ok_or_else(|| StoreError::MissingChunk {
                    path: self.chunk_path(&array, &indices),
                    what: format!("the values of {}", node.trim_start_matches('/')),
                })?;
            for (value, element) in stored.into_iter().zip(elements) {
                if let Some(i) = element {
                    values[i] = Some(value);
                }
            }
        }
        let values = values
            .into_iter()
            .collect::<Option<Vec<T>>>()
            .ok_or_else(|| StoreError::Layout {
                path: self.node(node),
                message: "its chunks do not cover its shape".into(),
            })?;
        Ok((shape, values))
    }

    /// Reads the per-frame metadata back as frame records (labels from the `labels`
    /// attribute of `frames/`; width and height from the store).
    pub fn read_frame_metadata(&self) -> Result<Vec<FrameRecord>, StoreError> {
        fn column<T: ElementOwned + Copy>(
            s: &RunStore,
            name: &str,
            n: &mut Option<usize>,
        ) -> Result<Vec<T>, StoreError> {
            let (_, v) = s.read_whole::<T>(&format!("{FRAMES}/{name}"))?;
            match n {
                None => *n = Some(v.len()),
                Some(n) if *n != v.len() => {
                    return Err(StoreError::Metadata {
                        field: format!("frames/{name}"),
                        value: format!("{} values", v.len()),
                        message: format!("the other per-frame arrays hold {n}"),
                    })
                }
                Some(_) => {}
            }
            Ok(v)
        }
        let mut n = None;
        let kind: Vec<u8> = column(self, "kind", &mut n)?;
        let step: Vec<u64> = column(self, "step", &mut n)?;
        let set: Vec<i64> = column(self, "set", &mut n)?;
        let commanded: Vec<f64> = column(self, "commanded_angle_deg", &mut n)?;
        let measured: Vec<f64> = column(self, "measured_angle_deg", &mut n)?;
        let exposure: Vec<f64> = column(self, "exposure_us", &mut n)?;
        let gain: Vec<f64> = column(self, "gain", &mut n)?;
        let host_time: Vec<i64> = column(self, "host_time_unix_ns", &mut n)?;
        let device_time: Vec<i64> = column(self, "device_timestamp_ns", &mut n)?;
        let frame_id: Vec<u64> = column(self, "frame_id", &mut n)?;
        let zenith: Vec<f64> = column(self, "sun_zenith_deg", &mut n)?;
        let azimuth: Vec<f64> = column(self, "sun_azimuth_deg", &mut n)?;
        let hash: Vec<u64> = column(self, "hash", &mut n)?;
        // Runs written before frames recorded their span have no span arrays: their frames
        // are step-and-shoot frames, whose span is the settled reading.
        let span = if self.node_exists(&format!("{FRAMES}/angle_source")) {
            Some((
                column::<f64>(self, "angle_start_deg", &mut n)?,
                column::<f64>(self, "angle_end_deg", &mut n)?,
                column::<u8>(self, "angle_source", &mut n)?,
                column::<f64>(self, "angle_sigma_deg", &mut n)?,
            ))
        } else {
            None
        };
        let n = n.unwrap_or(0);
        let attrs = self.group_attributes(FRAMES)?;
        let labels = match attrs.get("labels") {
            Some(Value::Array(a)) if a.len() == n => a,
            other => {
                return Err(StoreError::Metadata {
                    field: "frames/ attribute \"labels\"".into(),
                    value: other.map_or("missing".into(), |v| {
                        let s = v.to_string();
                        s.chars().take(80).collect()
                    }),
                    message: format!("expected an array of {n} strings"),
                })
            }
        };
        let mut records = Vec::with_capacity(n);
        for i in 0..n {
            let kind = FrameKind::from_code(kind[i]).ok_or_else(|| StoreError::Metadata {
                field: format!("frames/kind[{i}]"),
                value: kind[i].to_string(),
                message: "expected 0 (light) or 1 (dark)".into(),
            })?;
            let label = labels[i]
                .as_str()
                .ok_or_else(|| StoreError::Metadata {
                    field: format!("frames/ attribute \"labels\"[{i}]"),
                    value: labels[i].to_string(),
                    message: "expected a string".into(),
                })?
                .to_string();
            let opt = |v: f64| if v.is_nan() { None } else { Some(v) };
            let (angle_start_deg, angle_end_deg, angle_source, angle_sigma_deg) = match &span {
                Some((a, b, c, d)) => (
                    a[i],
                    b[i],
                    AngleSource::from_code(c[i]).ok_or_else(|| StoreError::Metadata {
                        field: format!("frames/angle_source[{i}]"),
                        value: c[i].to_string(),
                        message: "expected 0 (settled), 1 (encoder trigger) or 2 (timestamps)"
                            .into(),
                    })?,
                    d[i],
                ),
                None => (measured[i], measured[i], AngleSource::Settled, f64::NAN),
            };
            records.push(FrameRecord {
                index: i as u64,
                step: step[i],
                kind,
                set: u64::try_from(set[i]).ok(),
                label,
                commanded_angle_deg: commanded[i],
                measured_angle_deg: measured[i],
                angle_start_deg,
                angle_end_deg,
                angle_source,
                angle_sigma_deg,
                exposure_us: exposure[i],
                gain: gain[i],
                host_time_unix_ns: host_time[i],
                device_timestamp_ns: u64::try_from(device_time[i]).ok(),
                frame_id: frame_id[i],
                sun_zenith_deg: opt(zenith[i]),
                sun_azimuth_deg: opt(azimuth[i]),
                width: self.width,
                height: self.height,
                hash: hash[i],
            });
        }
        Ok(records)
    }

    fn load_products(&self) -> Result<ProductsState, StoreError> {
        let (_, sets) = self.read_whole::<i64>(PRODUCT_SET)?;
        let (shape, flat) = self.read_whole::<f64>(PRODUCT_ANGLES)?;
        let k = shape.get(1).copied().unwrap_or(0) as usize;
        let angles: Vec<Vec<f64>> = if k == 0 {
            vec![Vec::new(); sets.len()]
        } else {
            flat.chunks(k)
                .map(|row| row.iter().copied().filter(|a| !a.is_nan()).collect())
                .collect()
        };
        // `products/set` is written last ([`Self::write_product_index`]): a process that
        // stopped between the two leaves `angles_deg` a row ahead; the set's products are
        // written again when it is processed again.
        let mut angles = angles;
        angles.resize(sets.len(), Vec::new());
        let names = self.product_names()?;
        let mut arrays = HashMap::new();
        let mut slots = sets.len() as u64;
        for name in &names {
            let node = format!("{PRODUCTS}/{name}");
            let a = Array::open(self.store.clone(), &node)
                .map_err(zarr_err(self.node(&node), "opening"))?;
            slots = slots.max(a.shape().first().copied().unwrap_or(0));
            arrays.insert(name.clone(), a);
        }
        Ok(ProductsState {
            slots,
            sets,
            angles,
            arrays,
            names,
        })
    }

    /// Rewrites `products/angles_deg`, then `products/set`: a slot counts for readers once
    /// its set is in `products/set`, which is written after the slot's images and angles.
    fn write_product_index(&self, sets: &[i64], angles: &[Vec<f64>]) -> Result<(), StoreError> {
        let m = sets.len() as u64;
        let k = angles.iter().map(Vec::len).max().unwrap_or(0);
        let mut flat = Vec::with_capacity(sets.len() * k);
        for row in angles {
            flat.extend_from_slice(row);
            flat.extend(std::iter::repeat_n(f64::NAN, k - row.len()));
        }
        self.write_whole(
            PRODUCT_ANGLES,
            vec![m, k as u64],
            index_chunk(2),
            &["slot", "channel"],
            data_type::float64(),
            ZARR_NAN_F64,
            &flat,
        )?;
        self.write_whole(
            PRODUCT_SET,
            vec![m],
            index_chunk(1),
            &["slot"],
            data_type::int64(),
            -1i64,
            sets,
        )
    }

    /// Stores the products of angle `set`: one `[H, W]` image per `(name, values)`, and the
    /// set's analyzer angles. Products are keyed by set: the set's slot (the index in the
    /// products arrays) is the one already holding it (written again, e.g. by a process that
    /// crashed before its journal recorded the set), else a new slot at the end. Product
    /// arrays are created on first use; every product array grows to the same number of
    /// slots. Returns the slot.
    pub fn write_products(
        &self,
        set: u64,
        angles_deg: &[f64],
        images: &[(&str, &[f32])],
    ) -> Result<u64, StoreError> {
        let mut seen = BTreeSet::new();
        for (name, values) in images {
            check_product_name(name)?;
            if !seen.insert(*name) {
                return Err(StoreError::Product {
                    name: (*name).to_string(),
                    message: "given twice".into(),
                });
            }
            self.check_image(|| format!("product {name:?}"), values.len())?;
        }
        let set_i64 = i64::try_from(set).map_err(|_| StoreError::Product {
            name: "set".into(),
            message: format!("set number {set} is larger than the int64 array can hold"),
        })?;
        let mut guard = lock(&self.products);
        if guard.is_none() {
            *guard = Some(self.load_products()?);
        }
        let Some(state) = guard.as_mut() else {
            return Err(StoreError::Layout {
                path: self.node(PRODUCTS),
                message: "products state not loaded".into(),
            });
        };
        let slot_usize = state
            .sets
            .iter()
            .position(|&s| s == set_i64)
            .unwrap_or(state.sets.len());
        let slot = slot_usize as u64;
        let slots = state.slots.max(slot + 1);
        // Grow existing arrays, create new ones.
        for name in state.names.clone() {
            if let Some(a) = state.arrays.get_mut(&name) {
                if a.shape().first().copied().unwrap_or(0) < slots {
                    let node = format!("{PRODUCTS}/{name}");
                    let grown = product_array(&self.store, &node, slots, self.width, self.height)
                        .map_err(zarr_err(self.node(&node), "growing"))?;
                    grown
                        .store_metadata()
                        .map_err(zarr_err(self.node(&node), "writing the array metadata"))?;
                    *a = grown;
                }
            }
        }
        let mut new_names = false;
        for (name, _) in images {
            if !state.arrays.contains_key(*name) {
                let node = format!("{PRODUCTS}/{name}");
                let a = product_array(&self.store, &node, slots, self.width, self.height)
                    .map_err(zarr_err(self.node(&node), "creating the array"))?;
                a.store_metadata()
                    .map_err(zarr_err(self.node(&node), "writing the array metadata"))?;
                state.arrays.insert((*name).to_string(), a);
                state.names.push((*name).to_string());
                new_names = true;
            }
        }
        state.slots = slots;
        if new_names {
            let names = state.names.iter().cloned().map(Value::String).collect();
            self.update_group_attribute(PRODUCTS, "names", Value::Array(names))?;
        }
        for (name, values) in images {
            if let Some(a) = state.arrays.get(*name) {
                a.store_chunk_opt(&[slot, 0, 0], *values, &codec_options())
                    .map_err(zarr_err(
                        self.chunk_path(a, &[slot, 0, 0]).display().to_string(),
                        "writing product chunk",
                    ))?;
            }
        }
        let m = slots as usize;
        state.sets.resize(m, -1);
        state.angles.resize(m, Vec::new());
        state.sets[slot_usize] = set_i64;
        state.angles[slot_usize] = angles_deg.to_vec();
        self.write_product_index(&state.sets, &state.angles)?;
        Ok(slot)
    }

    /// Records which dark level set `set`'s products subtract (the `dark` attribute of
    /// `products/`, an object by set number).
    pub fn set_product_dark(&self, set: u64, description: &str) -> Result<(), StoreError> {
        self.insert_into_attribute(PRODUCTS, "dark", &set.to_string(), json!(description))
    }

    /// Reads product `name` of `slot`.
    pub fn read_product(&self, name: &str, slot: u64) -> Result<Vec<f32>, StoreError> {
        check_product_name(name)?;
        let node = format!("{PRODUCTS}/{name}");
        if !self.node_exists(&node) {
            return Err(StoreError::Product {
                name: name.into(),
                message: format!("not in the store (products: {:?})", self.product_names()?),
            });
        }
        let a = Array::open(self.store.clone(), &node)
            .map_err(zarr_err(self.node(&node), "opening"))?;
        let slots = a.shape().first().copied().unwrap_or(0);
        if slot >= slots {
            return Err(StoreError::Product {
                name: name.into(),
                message: format!("slot {slot} is past the {slots} slots stored"),
            });
        }
        a.retrieve_chunk_if_exists_opt::<Vec<f32>>(&[slot, 0, 0], &codec_options())
            .map_err(zarr_err(
                self.chunk_path(&a, &[slot, 0, 0]).display().to_string(),
                "reading product chunk",
            ))?
            .ok_or_else(|| StoreError::MissingChunk {
                path: self.chunk_path(&a, &[slot, 0, 0]),
                what: format!("product {name:?} of slot {slot}"),
            })
    }

    /// The product names written so far (the `names` attribute of `products/`).
    pub fn product_names(&self) -> Result<Vec<String>, StoreError> {
        let attrs = self.group_attributes(PRODUCTS)?;
        let names = attrs
            .get("names")
            .and_then(Value::as_array)
            .map(|a| {
                a.iter()
                    .filter_map(|v| v.as_str().map(String::from))
                    .collect()
            })
            .unwrap_or_default();
        Ok(names)
    }

    /// The product slots: the set and angles of each.
    pub fn product_slots(&self) -> Result<Vec<ProductSlot>, StoreError> {
        let state = self.load_products()?;
        Ok(state
            .sets
            .iter()
            .zip(state.angles)
            .enumerate()
            .map(|(slot, (&set, angles_deg))| ProductSlot {
                slot: slot as u64,
                set: u64::try_from(set).ok(),
                angles_deg,
            })
            .collect())
    }

    /// Writes the mean dark frame (`darks/mean`, float32 `[H, W]`), replacing any earlier one.
    pub fn write_dark_mean(&self, mean: &[f32]) -> Result<(), StoreError> {
        self.check_image(|| "dark mean".into(), mean.len())?;
        self.write_whole(
            DARK_MEAN,
            vec![u64::from(self.height), u64::from(self.width)],
            vec![u64::from(self.height), u64::from(self.width)],
            &["y", "x"],
            data_type::float32(),
            ZARR_NAN_F32,
            mean,
        )
    }

    /// The mean dark frame, if one was written.
    pub fn read_dark_mean(&self) -> Result<Option<Vec<f32>>, StoreError> {
        if !self.node_exists(DARK_MEAN) {
            return Ok(None);
        }
        let (_, v) = self.read_whole::<f32>(DARK_MEAN)?;
        Ok(Some(v))
    }

    fn node_exists(&self, node: &str) -> bool {
        self.path
            .join(node.trim_start_matches('/'))
            .join("zarr.json")
            .is_file()
    }

    fn group_attributes(&self, node: &str) -> Result<Map<String, Value>, StoreError> {
        let g =
            Group::open(self.store.clone(), node).map_err(zarr_err(self.node(node), "opening"))?;
        Ok(g.attributes().clone())
    }

    fn update_group_attribute(
        &self,
        node: &str,
        key: &str,
        value: Value,
    ) -> Result<(), StoreError> {
        self.modify_group_attributes(node, |attrs| {
            attrs.insert(key.to_string(), value);
        })
    }

    fn modify_group_attributes(
        &self,
        node: &str,
        f: impl FnOnce(&mut Map<String, Value>),
    ) -> Result<(), StoreError> {
        let _guard = lock(&self.attrs);
        let mut g =
            Group::open(self.store.clone(), node).map_err(zarr_err(self.node(node), "opening"))?;
        f(g.attributes_mut());
        g.store_metadata()
            .map_err(zarr_err(self.node(node), "writing the group metadata"))
    }

    /// Sets `key` of the object attribute `attribute` of group `node` (made an object if it
    /// is missing or is not one).
    fn insert_into_attribute(
        &self,
        node: &str,
        attribute: &str,
        key: &str,
        value: Value,
    ) -> Result<(), StoreError> {
        self.modify_group_attributes(node, |attrs| {
            let a = attrs
                .entry(attribute)
                .or_insert_with(|| Value::Object(Map::new()));
            if !a.is_object() {
                *a = Value::Object(Map::new());
            }
            if let Value::Object(m) = a {
                m.insert(key.to_string(), value);
            }
        })
    }

    /// Appends `value` to the root array attribute `attribute` (made an array if it is
    /// missing or is not one).
    fn push_to_attribute(&self, attribute: &str, value: Value) -> Result<(), StoreError> {
        self.modify_group_attributes("/", |attrs| {
            let a = attrs
                .entry(attribute)
                .or_insert_with(|| Value::Array(Vec::new()));
            if !a.is_array() {
                *a = Value::Array(Vec::new());
            }
            if let Value::Array(list) = a {
                list.push(value);
            }
        })
    }

    /// Sets a root attribute (read-modify-write of `run.zarr/zarr.json`, replaced atomically).
    pub fn set_attribute(&self, key: &str, value: Value) -> Result<(), StoreError> {
        self.update_group_attribute("/", key, value)
    }

    /// Sets `calibration[kind]` (the root `calibration` attribute is an object by kind).
    pub fn set_calibration(&self, kind: &str, result: Value) -> Result<(), StoreError> {
        self.insert_into_attribute("/", "calibration", kind, result)
    }

    /// Appends a planner decision to the root `decisions` attribute.
    pub fn push_decision(&self, decision: Value) -> Result<(), StoreError> {
        self.push_to_attribute("decisions", decision)
    }

    /// Appends a late time-lapse set (what the plan's policy did with it) to the root
    /// `late_sets` attribute.
    pub fn push_late_set(&self, late: Value) -> Result<(), StoreError> {
        self.push_to_attribute("late_sets", late)
    }

    /// The root attributes.
    pub fn attributes(&self) -> Result<Map<String, Value>, StoreError> {
        self.group_attributes("/")
    }

    /// The chunk file of frame `index`.
    pub fn frame_chunk_path(&self, index: u64) -> PathBuf {
        let a = lock(&self.pixels);
        self.chunk_path(&a, &[index, 0, 0])
    }

    /// Moves frame `index`'s chunk aside (renamed to `<chunk>.damaged-<n>`, the first `n`
    /// not taken; never deleted), durably. Returns the new path, or `None` when there is no
    /// chunk file.
    pub fn set_aside_frame(&self, index: u64) -> Result<Option<PathBuf>, StoreError> {
        let chunk = self.frame_chunk_path(index);
        if !chunk.is_file() {
            return Ok(None);
        }
        let name = chunk
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let dir = chunk.parent().unwrap_or(Path::new("."));
        let aside = (0u32..)
            .map(|n| dir.join(format!("{name}.damaged-{n}")))
            .find(|p| !p.exists())
            .unwrap_or_else(|| dir.join(format!("{name}.damaged")));
        std::fs::rename(&chunk, &aside).map_err(io_err(&chunk, "moving a damaged chunk aside"))?;
        File::open(dir)
            .and_then(|d| d.sync_all())
            .map_err(io_err(dir, "syncing the directory"))?;
        Ok(Some(aside))
    }

    /// Re-reads every recorded frame, recomputes its [`pixel_hash`] and reports frames that
    /// are missing or do not match (findings, not errors). Also lists stored frames that no
    /// record describes.
    pub fn verify(&self, records: &[FrameRecord]) -> Result<Verification, StoreError> {
        let mut v = Verification::default();
        let mut recorded = BTreeMap::new();
        for r in records {
            recorded.insert(r.index, r);
        }
        for (&index, r) in &recorded {
            v.checked += 1;
            if (r.width, r.height) != (self.width, self.height) {
                v.mismatched.push(index);
                v.findings.push(format!(
                    "frame {index}: recorded as {}x{}, the store holds {}x{}",
                    r.width, r.height, self.width, self.height
                ));
                continue;
            }
            match self.read_frame_inner(index)? {
                FrameRead::Pixels(p) => {
                    let h = pixel_hash(&p);
                    if h == r.hash {
                        v.ok += 1;
                    } else {
                        v.mismatched.push(index);
                        v.findings.push(format!(
                            "frame {index}: stored pixels hash to {h:#018x}, the journal \
                             recorded {:#018x}",
                            r.hash
                        ));
                    }
                }
                FrameRead::OutOfRange(count) => {
                    v.missing.push(index);
                    v.findings.push(format!(
                        "frame {index}: past the {count} frames of frames/pixels"
                    ));
                }
                FrameRead::Missing(path) => {
                    v.missing.push(index);
                    v.findings
                        .push(format!("frame {index}: no chunk ({})", path.display()));
                }
                FrameRead::Unreadable(path, message) => {
                    v.mismatched.push(index);
                    v.findings.push(format!(
                        "frame {index}: unreadable chunk {}: {message}",
                        path.display()
                    ));
                }
            }
        }
        let count = self.frame_count();
        for index in 0..count {
            if !recorded.contains_key(&index) {
                let path = {
                    let a = lock(&self.pixels);
                    self.chunk_path(&a, &[index, 0, 0])
                };
                if path.is_file() {
                    v.unrecorded.push(index);
                    v.findings
                        .push(format!("frame {index}: stored but not recorded"));
                }
            }
        }
        Ok(v)
    }
}

enum FrameRead {
    Pixels(Vec<u16>),
    OutOfRange(u64),
    Missing(PathBuf),
    Unreadable(PathBuf, String),
}

fn check_product_name(name: &str) -> Result<(), StoreError> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        && !name.starts_with('-')
        && !PRODUCT_RESERVED.contains(&name);
    if ok {
        Ok(())
    } else {
        Err(StoreError::Product {
            name: name.to_string(),
            message: format!(
                "a product name is 1 to 64 of [A-Za-z0-9_-] (not starting with '-') and not \
                 one of {PRODUCT_RESERVED:?}"
            ),
        })
    }
}

/// A filesystem store whose writes are atomic and durable: write a temporary file, sync it,
/// rename it over the target, sync the directory. Reads, listing and erasing are zarrs'
/// [`FilesystemStore`].
#[derive(Debug)]
struct DurableStore {
    inner: FilesystemStore,
    root: PathBuf,
}

impl DurableStore {
    fn new(root: &Path) -> Result<DurableStore, StoreError> {
        let inner = FilesystemStore::new(root).map_err(|e| StoreError::Zarr {
            path: root.display().to_string(),
            action: "opening the filesystem store",
            message: e.to_string(),
        })?;
        Ok(DurableStore {
            inner,
            root: root.to_path_buf(),
        })
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
            std::fs::rename(&tmp, path)?;
            File::open(parent)?.sync_all()
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        result
    }
}

/// Creates `dir` and its missing ancestors, syncing the parent of each directory created so
/// that the new entries survive a crash.
fn create_dirs_durably(dir: &Path) -> std::io::Result<()> {
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
