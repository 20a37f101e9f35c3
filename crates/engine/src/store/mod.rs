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
//!                             name the storage keeps (essential: s0 dolp aop_rad sigma_s0
//!                             sigma_dolp; all: every plane); flags uint8
//!     set                   int64   [M]    the angle set of each slot, -1: slot not written
//!     angles_deg            float64 [M, K] the analyzer angles of each slot's frames, K the
//!                             largest number of angles of any slot, NaN padded
//!   darks/                  group
//!     mean                  float32 [H, W] the mean dark frame (written at the end, if any)
//! ```
//!
//! Every chunk is zstd-compressed and carries a `crc32c` checksum (both core Zarr v3 codecs),
//! so a damaged chunk fails to read instead of returning wrong numbers. Which product planes a
//! store keeps, at what precision, and whether it compresses is its `storage` root attribute
//! ([`Storage`], from the plan's `[storage]`; a store without it is uncompressed with every
//! plane, as stores were before it existed). The per-frame metadata
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
//! [`RunStore::write_frame`] stores the chunk only; [`RunStore::write_frame_metadata`] (at set
//! boundaries, pauses and the end) writes every per-frame array and then resizes
//! `frames/pixels` to the frames the journal records, renaming the synced files into place
//! together: the frames group always has one length (xarray opens it whole, a killed run
//! included), frames written since the last mirror read by index from their chunks, and a
//! frame written by a process that crashed before journaling it stays hidden. A frame counts
//! once its journal entry is written (after `write_frame` returns).
//!
//! A `RunStore` may be used from several threads (`&self` methods; the arrays are held behind
//! mutexes), and several `RunStore`s may be open on one run (one writer, any readers: readers
//! see frames written after they opened the store).

mod durable;
mod error;
mod metadata;
mod plane;
mod products;
mod schema;
mod storage;
use durable::{lock, DurableStore};
pub use error::StoreError;
pub use plane::Plane;
pub use schema::STATUS_CODES;
pub use storage::{Compression, Precision, ProductSet, Storage};

pub use schema::{conventions, HASH_ALGORITHM, KIND_CODES};

use crate::{pixel_hash, AngleSource, FrameKind, FrameRecord};
use serde::{Deserialize, Serialize};
use serde_json::{json, Map, Value};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use zarrs::array::builder::ArrayBuilderFillValue;
use zarrs::array::{
    data_type, Array, CodecOptions, DataType, Element, ElementOwned, ZARR_NAN_F32, ZARR_NAN_F64,
};
use zarrs::group::{Group, GroupBuilder};

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
    /// How images are kept (the `storage` root attribute).
    storage: Storage,
    pixels: Mutex<Array<DurableStore>>,
    /// This instance holds frames past the `frames/pixels` shape on disk (written, or looked
    /// for by [`RunStore::verify`], since the metadata last mirrored the journal): it keeps
    /// its own shape instead of re-reading the disk's.
    pixels_ahead: AtomicBool,
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

/// Store every chunk, even one that equals the fill value (zarrs skips those by default; a
/// frame of zeros must still be stored).
fn codec_options() -> CodecOptions {
    CodecOptions::default().with_store_empty_chunks(true)
}

/// `frames/pixels` with `frames` frames of `width x height`, one chunk per frame.
fn pixels_array(
    store: &Arc<DurableStore>,
    frames: u64,
    size: (u32, u32),
    storage: &Storage,
) -> Result<Array<DurableStore>, zarrs::array::ArrayCreateError> {
    schema::image_stack(store.clone(), PIXELS, frames, size, storage)
}

/// `products/<name>` with `slots` slots of `width x height`, one chunk per slot.
fn product_array(
    store: &Arc<DurableStore>,
    node: &str,
    slots: u64,
    size: (u32, u32),
    storage: &Storage,
) -> Result<Array<DurableStore>, zarrs::array::ArrayCreateError> {
    schema::image_stack(store.clone(), node, slots, size, storage)
}

/// The `storage` root attribute of a store (absent: written before it existed).
fn storage_of(attrs: &Map<String, Value>, path: &Path) -> Result<Storage, StoreError> {
    match attrs.get("storage") {
        None => Ok(Storage::legacy()),
        Some(v) => serde_json::from_value(v.clone()).map_err(|e| StoreError::Layout {
            path: path.display().to_string(),
            message: format!("root attribute storage = {v}: {e}"),
        }),
    }
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
        let storage = storage_of(&attrs, &path)?;
        let storage = if attrs.contains_key("storage") {
            storage
        } else {
            Storage::default()
        };
        attrs.insert(
            "storage".into(),
            serde_json::to_value(storage).unwrap_or(Value::Null),
        );
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
        let pixels = pixels_array(&store, 0, (width, height), &storage)
            .map_err(zarr_err(p(PIXELS), "creating the array"))?;
        pixels
            .store_metadata()
            .map_err(zarr_err(p(PIXELS), "writing the array metadata"))?;
        let rs = RunStore {
            path,
            store,
            width,
            height,
            storage,
            pixels: Mutex::new(pixels),
            pixels_ahead: AtomicBool::new(false),
            products: Mutex::new(None),
            attrs: Mutex::new(()),
        };
        rs.write_frame_metadata(&[], &Default::default())?;
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
        let root = Group::open(store.clone(), "/").map_err(zarr_err(
            format!("{}", path.display()),
            "opening the root group",
        ))?;
        let storage = storage_of(root.attributes(), &path)?;
        Ok(RunStore {
            path,
            store,
            width,
            height,
            storage,
            pixels: Mutex::new(pixels),
            pixels_ahead: AtomicBool::new(false),
            products: Mutex::new(None),
            attrs: Mutex::new(()),
        })
    }

    /// How the store keeps its images (compression, products, precision).
    pub fn storage(&self) -> Storage {
        self.storage
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
        // The chunk only: the shape on disk grows when the metadata mirrors the journal
        // (`write_frame_metadata`), so every per-frame array and frames/pixels always have
        // one length and the group opens whole (a crash leaves the frame invisible until a
        // resume, never a visible frame without its pixels or its metadata).
        let grown = pixels_array(
            &self.store,
            index + 1,
            (self.width, self.height),
            &self.storage,
        )
        .map_err(zarr_err(self.node(PIXELS), "growing"))?;
        self.store_frame_chunk(&grown, index, pixels)?;
        *array = grown;
        self.pixels_ahead.store(true, Ordering::SeqCst);
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
        if self.pixels_ahead.load(Ordering::SeqCst) {
            return Ok(());
        }
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
                // Past the shape on disk: a frame written since the metadata last mirrored
                // the journal reads from its chunk.
                let wider = pixels_array(
                    &self.store,
                    index + 1,
                    (self.width, self.height),
                    &self.storage,
                )
                .map_err(zarr_err(self.node(PIXELS), "growing"))?;
                return Ok(
                    match wider
                        .retrieve_chunk_if_exists_opt::<Vec<u16>>(&[index, 0, 0], &codec_options())
                    {
                        Ok(Some(p)) => FrameRead::Pixels(p),
                        _ => FrameRead::OutOfRange(count(&array)),
                    },
                );
            }
        }
        let path = self.chunk_path(&array, &[index, 0, 0]);
        match array.retrieve_chunk_if_exists_opt::<Vec<u16>>(&[index, 0, 0], &codec_options()) {
            Ok(Some(p)) => Ok(FrameRead::Pixels(p)),
            Ok(None) => Ok(FrameRead::Missing(path)),
            Err(e) => Ok(FrameRead::Unreadable(path, e.to_string())),
        }
    }

    /// Frames in `frames/pixels`: as on disk (the frames the metadata mirrors), or, in the
    /// instance that wrote frames since, every frame it wrote.
    pub fn frame_count(&self) -> u64 {
        let mut array = lock(&self.pixels);
        if let Err(e) = self.refresh_pixels(&mut array) {
            tracing::warn!("{e}");
        }
        array.shape().first().copied().unwrap_or(0)
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
    ///
    /// A recorded frame is looked for whatever the shape of `frames/pixels` on disk says: a
    /// run stopped between two metadata syncs holds frames the journal records past it.
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
