//! The run's storage end to end: the Zarr store, the journal next to it, TIFF export and
//! reading the store from Python.
#![allow(clippy::unwrap_used)]

use polar_engine::export::{export_tiff, CSV_HEADER};
use polar_engine::journal::{self, Entry, Journal};
use polar_engine::store::{Plane, RunStore, StoreError};
use polar_engine::{pixel_hash, AngleSource, FrameKind, FrameRecord};
use serde_json::{json, Map, Value};
use std::path::{Path, PathBuf};
use std::time::Instant;

const W: u32 = 64;
const H: u32 = 48;
const N: u64 = 6;

/// A unique directory under the system temp dir, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos();
        let dir = std::env::temp_dir().join(format!(
            "polar-store-test-{name}-{}-{nanos}",
            std::process::id()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        TempDir(dir)
    }

    fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Frame `i`: a ramp, except the last frame (a dark of zeros: it must be stored anyway).
fn pixels(i: u64) -> Vec<u16> {
    if i == N - 1 {
        return vec![0; (W * H) as usize];
    }
    (0..H)
        .flat_map(|y| {
            (0..W).map(move |x| ((i * 1000 + u64::from(y) * 67 + u64::from(x)) % 4096) as u16)
        })
        .collect()
}

fn record(i: u64) -> FrameRecord {
    let dark = i == N - 1;
    FrameRecord {
        index: i,
        step: i + 1,
        kind: if dark {
            FrameKind::Dark
        } else {
            FrameKind::Light
        },
        set: if dark { None } else { Some(i / 3) },
        label: if dark {
            "dark after, \"capped\"".into()
        } else {
            format!("set {} angle {}", i / 3, (i % 3) * 60)
        },
        commanded_angle_deg: (i % 3) as f64 * 60.0,
        measured_angle_deg: if i == 1 {
            f64::NAN
        } else {
            (i % 3) as f64 * 60.0 + 0.01
        },
        // Frame 4 is a continuous-rotation frame (span 7.5 deg from its trigger), the others
        // step and shoot (start = end = the settled reading).
        angle_start_deg: if i == 1 {
            f64::NAN
        } else {
            (i % 3) as f64 * 60.0 + 0.01
        },
        angle_end_deg: if i == 1 {
            f64::NAN
        } else if i == 4 {
            (i % 3) as f64 * 60.0 + 7.51
        } else {
            (i % 3) as f64 * 60.0 + 0.01
        },
        angle_source: if i == 4 {
            AngleSource::EncoderTrigger
        } else {
            AngleSource::Settled
        },
        angle_sigma_deg: if i == 4 { 0.0025 } else { f64::NAN },
        exposure_us: 1500.0,
        gain: 2.5,
        host_time_unix_ns: 1_700_000_000_000_000_000 + i as i64 * 1_000_000,
        device_timestamp_ns: if i == 2 { None } else { Some(10_000 * i) },
        frame_id: 100 + i,
        sun_zenith_deg: if i == 0 { None } else { Some(35.5 + i as f64) },
        sun_azimuth_deg: if i == 0 { None } else { Some(180.25) },
        width: W,
        height: H,
        hash: pixel_hash(&pixels(i)),
    }
}

fn product(seed: f32) -> Vec<f32> {
    (0..W * H)
        .map(|p| {
            if p == 7 {
                f32::NAN
            } else {
                seed + p as f32 * 0.001
            }
        })
        .collect()
}

const PRODUCT_NAMES: [&str; 3] = ["s0", "dolp", "aop_rad"];

fn slot_angles(slot: u64) -> Vec<f64> {
    if slot == 0 {
        vec![0.0, 60.0, 120.0]
    } else {
        vec![0.0, 45.0, 90.0, 135.0]
    }
}

fn dark_mean() -> Vec<f32> {
    (0..W * H).map(|p| 100.0 + (p % 7) as f32 * 0.5).collect()
}

fn attributes() -> Map<String, Value> {
    let mut a = Map::new();
    a.insert(
        "plan".into(),
        json!({"name": "interop", "angles_deg": [0, 60, 120]}),
    );
    a.insert("software".into(), polar_engine::software_version());
    a.insert("devices".into(), json!({"camera": "sim"}));
    a.insert("state".into(), json!("running"));
    a
}

/// Writes the whole small run into `dir`.
fn write_run(dir: &Path) -> RunStore {
    let store = RunStore::create(dir, W, H, attributes()).unwrap();
    for i in 0..N {
        store.write_frame(i, &pixels(i)).unwrap();
    }
    let records: Vec<FrameRecord> = (0..N).map(record).collect();
    store
        .write_frame_metadata(&records, &Default::default())
        .unwrap();
    for slot in 0..2u64 {
        let images: Vec<(&str, Vec<f32>)> = PRODUCT_NAMES
            .iter()
            .enumerate()
            .map(|(k, n)| (*n, product(slot as f32 * 10.0 + k as f32)))
            .collect();
        let refs: Vec<(&str, Plane)> = images.iter().map(|(n, v)| (*n, Plane::from(v))).collect();
        let written = store
            .write_products(slot + 3, &slot_angles(slot), &refs)
            .unwrap();
        assert_eq!(written, slot, "a new set takes the next slot");
    }
    store.write_dark_mean(&dark_mean()).unwrap();
    store.set_attribute("state", json!("done")).unwrap();
    store
        .set_calibration("analyzer", json!({"offset_deg": 0.2}))
        .unwrap();
    store.push_decision(json!({"round": 0})).unwrap();
    store
}

/// `products/flags` is a bit mask: stored as uint8 (the data type in its `zarr.json`), read
/// back exactly; a run whose `flags` array is float32 (written by an earlier version and
/// resumed now) takes the same uint8 mask as float32 values, so a resume never fails on it.
#[test]
fn flags_are_stored_as_unsigned_integers() {
    let tmp = TempDir::new("flags-u8");
    let store = RunStore::create(tmp.path(), W, H, attributes()).unwrap();
    let n = (W * H) as usize;
    let mask: Vec<u8> = (0..n).map(|i| (i % 8) as u8).collect();
    let dolp = product(0.5);
    store
        .write_products(
            0,
            &[0.0, 60.0, 120.0],
            &[("dolp", Plane::from(&dolp)), ("flags", Plane::U8(&mask))],
        )
        .unwrap();
    let meta: Value = serde_json::from_slice(
        &std::fs::read(tmp.path().join("run.zarr/products/flags/zarr.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(meta["data_type"], json!("uint8"), "{meta}");
    assert_eq!(meta["fill_value"], json!(0), "{meta}");
    let back = store.read_product("flags", 0).unwrap();
    let want: Vec<f32> = mask.iter().map(|&b| f32::from(b)).collect();
    assert_eq!(back, want);
    // A float32 plane is never narrowed into the integer array.
    let e = store
        .write_products(1, &[0.0], &[("flags", Plane::from(&dolp))])
        .unwrap_err();
    assert!(e.to_string().contains("flags"), "{e}");
    drop(store);

    // An earlier run's float32 flags array (its metadata turned back to float32, its chunk
    // gone) takes the uint8 mask as float32 values when the run is resumed.
    let meta_path = tmp.path().join("run.zarr/products/flags/zarr.json");
    let mut older = meta.clone();
    older["data_type"] = json!("float32");
    older["fill_value"] = json!("NaN");
    std::fs::write(&meta_path, serde_json::to_vec(&older).unwrap()).unwrap();
    std::fs::remove_dir_all(tmp.path().join("run.zarr/products/flags/c")).unwrap();
    let reopened = RunStore::open(tmp.path()).unwrap();
    reopened
        .write_products(0, &[0.0, 60.0, 120.0], &[("flags", Plane::U8(&mask))])
        .unwrap();
    assert_eq!(reopened.read_product("flags", 0).unwrap(), want);
}

/// NaN-aware equality of records.
fn same_records(a: &[FrameRecord], b: &[FrameRecord]) -> bool {
    serde_json::to_string(a).unwrap() == serde_json::to_string(b).unwrap()
}

#[test]
fn store_round_trip() {
    let tmp = TempDir::new("round-trip");
    drop(write_run(tmp.path()));
    let store = RunStore::open(tmp.path()).unwrap();
    assert_eq!((store.width(), store.height()), (W, H));
    assert_eq!(store.frame_count(), N);
    for i in 0..N {
        assert_eq!(store.read_frame(i).unwrap(), pixels(i), "frame {i}");
    }
    let records: Vec<FrameRecord> = (0..N).map(record).collect();
    let back = store.read_frame_metadata().unwrap();
    assert!(same_records(&back, &records), "{back:#?}");
    for slot in 0..2u64 {
        for (k, name) in PRODUCT_NAMES.iter().enumerate() {
            let got = store.read_product(name, slot).unwrap();
            let want = product(slot as f32 * 10.0 + k as f32);
            assert_eq!(got.len(), want.len());
            assert!(got
                .iter()
                .zip(&want)
                .all(|(a, b)| a == b || (a.is_nan() && b.is_nan())));
        }
    }
    let slots = store.product_slots().unwrap();
    assert_eq!(slots.len(), 2);
    assert_eq!(slots[0].set, Some(3));
    assert_eq!(slots[1].angles_deg, slot_angles(1));
    assert_eq!(
        slots[0].angles_deg,
        slot_angles(0),
        "NaN padding is dropped"
    );
    assert_eq!(store.product_names().unwrap(), PRODUCT_NAMES.to_vec());
    assert_eq!(store.read_dark_mean().unwrap().unwrap(), dark_mean());
    let attrs = store.attributes().unwrap();
    assert_eq!(attrs["plan"], attributes()["plan"]);
    assert_eq!(attrs["state"], json!("done"));
    assert_eq!(
        attrs["calibration"],
        json!({"analyzer": {"offset_deg": 0.2}})
    );
    assert_eq!(attrs["decisions"], json!([{"round": 0}]));
    assert_eq!(attrs["format"], json!("polarimeter-run"));

    // Errors name what is wrong; nothing panics.
    assert!(matches!(
        store.read_frame(N),
        Err(StoreError::FrameOutOfRange { index: 6, count: 6 })
    ));
    let e = store.read_product("nope", 0).unwrap_err();
    assert!(e.to_string().contains("nope"), "{e}");
    let e = store.read_product("dolp", 5).unwrap_err();
    assert!(e.to_string().contains("slot 5"), "{e}");
    let e = store.write_frame(0, &[1, 2, 3]).unwrap_err();
    assert!(e.to_string().contains("frame 0: 3 values"), "{e}");
    let e = store
        .write_products(9, &[0.0], &[("set", Plane::from(&product(0.0)))])
        .unwrap_err();
    assert!(e.to_string().contains("\"set\""), "{e}");
    assert!(matches!(
        RunStore::create(tmp.path(), W, H, Map::new()),
        Err(StoreError::Exists { .. })
    ));
    assert!(matches!(
        RunStore::open(&tmp.path().join("nowhere")),
        Err(StoreError::NotFound { .. })
    ));
}

/// A store written before frames recorded their analyzer span (no `frames/angle_*` arrays)
/// reads back with every frame's span equal to its settled reading (exactly: the same stored
/// value), source settled, sigma NaN; the other columns are unchanged.
#[test]
fn store_without_span_arrays_reads_as_step_and_shoot() {
    let tmp = TempDir::new("no-span");
    drop(write_run(tmp.path()));
    for name in [
        "angle_start_deg",
        "angle_end_deg",
        "angle_source",
        "angle_sigma_deg",
    ] {
        std::fs::remove_dir_all(tmp.path().join("run.zarr/frames").join(name)).unwrap();
    }
    let store = RunStore::open(tmp.path()).unwrap();
    let back = store.read_frame_metadata().unwrap();
    assert_eq!(back.len(), N as usize);
    for (b, r) in back.iter().zip((0..N).map(record)) {
        assert_eq!(b.angle_source, AngleSource::Settled);
        assert!(b.angle_sigma_deg.is_nan());
        assert_eq!(
            b.angle_start_deg.to_bits(),
            r.measured_angle_deg.to_bits(),
            "frame {}",
            r.index
        );
        assert_eq!(b.angle_end_deg.to_bits(), r.measured_angle_deg.to_bits());
        assert_eq!(b.hash, r.hash);
    }
    // A new store written with a timestamps source keeps it.
    drop(store);
    let store = write_run(&tmp.path().join("again"));
    let mut records: Vec<FrameRecord> = (0..N).map(record).collect();
    records[2].angle_source = AngleSource::Timestamps;
    store
        .write_frame_metadata(&records, &Default::default())
        .unwrap();
    let back = store.read_frame_metadata().unwrap();
    assert_eq!(back[2].angle_source, AngleSource::Timestamps);
}

#[test]
fn frame_metadata_must_cover_every_index() {
    let tmp = TempDir::new("gaps");
    let store = RunStore::create(tmp.path(), W, H, Map::new()).unwrap();
    let e = store
        .write_frame_metadata(&[record(0), record(2)], &Default::default())
        .unwrap_err();
    assert!(e.to_string().contains("records[1].index = 2"), "{e}");
    let mut r = record(0);
    r.width = 10;
    let e = store
        .write_frame_metadata(&[r], &Default::default())
        .unwrap_err();
    assert!(
        e.to_string().contains("records[0].width x height = 10x48"),
        "{e}"
    );
    // Empty metadata reads back empty.
    assert!(store.read_frame_metadata().unwrap().is_empty());
    assert_eq!(store.frame_count(), 0);
}

/// Frames become part of the group (frames/pixels' shape on disk) when the metadata mirrors
/// the journal, so a reader such as xarray always finds every per-frame array as long as the
/// pixels; a frame written since reads from its chunk by index, and a store reopened after a
/// crash verifies the frames the journal records past the shape on disk.
#[test]
fn a_second_reader_sees_new_frames_and_metadata_trims_unrecorded_frames() {
    let tmp = TempDir::new("reader");
    let writer = RunStore::create(tmp.path(), W, H, attributes()).unwrap();
    let reader = RunStore::open(tmp.path()).unwrap();
    for i in 0..3 {
        writer.write_frame(i, &pixels(i)).unwrap();
    }
    assert_eq!(reader.read_frame(2).unwrap(), pixels(2));
    assert_eq!(reader.frame_count(), 0);
    assert_eq!(writer.frame_count(), 3);
    // Frame 2 was written but never journaled (a crash): the metadata mirrors the journal.
    writer
        .write_frame_metadata(&[record(0), record(1)], &Default::default())
        .unwrap();
    assert_eq!(reader.frame_count(), 2);
    assert_eq!(writer.frame_count(), 2);
    let v = writer.verify(&[record(0), record(1)]).unwrap();
    assert!(v.is_ok(), "{v:?}");
    // Taking the step again overwrites the chunk.
    writer.write_frame(2, &pixels(4)).unwrap();
    assert_eq!(reader.read_frame(2).unwrap(), pixels(4));
    // Frames 2 and 3 journaled, then a crash before the next sync: the shape on disk says 2,
    // and a store opened for the resume finds both.
    writer.write_frame(3, &pixels(3)).unwrap();
    drop(writer);
    let mut r2 = record(2);
    r2.hash = polar_engine::pixel_hash(&pixels(4));
    let resumed = RunStore::open(tmp.path()).unwrap();
    assert_eq!(resumed.frame_count(), 2);
    let v = resumed
        .verify(&[record(0), record(1), r2.clone(), record(3)])
        .unwrap();
    assert!(v.is_ok() && v.ok == 4, "{v:?}");
    // A frame nobody wrote is past the store's frames, not a chunk gone missing.
    let v = resumed
        .verify(&[record(0), record(1), r2, record(3), record(4)])
        .unwrap();
    assert_eq!(v.missing, vec![4], "{v:?}");
}

#[test]
fn verify_finds_a_corrupt_and_a_missing_chunk() {
    let tmp = TempDir::new("verify");
    let store = write_run(tmp.path());
    let records: Vec<FrameRecord> = (0..N).map(record).collect();
    let v = store.verify(&records).unwrap();
    assert!(v.is_ok(), "{v:?}");
    assert_eq!(v.ok, N);

    let chunk = |i: u64| tmp.path().join(format!("run.zarr/frames/pixels/c/{i}/0/0"));
    // Overwrite a few bytes in the middle of frame 2's chunk (zstd-compressed, then a crc32c).
    let mut bytes = std::fs::read(chunk(2)).unwrap();
    assert!(bytes.len() > 200, "{} bytes", bytes.len());
    let mid = bytes.len() / 2;
    for b in &mut bytes[mid..mid + 4] {
        *b ^= 0x5a;
    }
    std::fs::write(chunk(2), &bytes).unwrap();
    std::fs::remove_file(chunk(4)).unwrap();

    let v = store.verify(&records).unwrap();
    println!("{v:#?}");
    assert_eq!(v.mismatched, vec![2]);
    assert_eq!(v.missing, vec![4]);
    assert_eq!(v.ok, N - 2);
    assert!(!v.is_ok());
    assert!(v.findings.iter().any(|f| f.contains("frame 2")));
    let e = store.read_frame(2).unwrap_err();
    assert!(e.to_string().contains("pixels/c/2/0/0"), "{e}");
    let e = store.read_frame(4).unwrap_err();
    assert!(matches!(e, StoreError::MissingChunk { .. }), "{e}");

    // A record whose hash is not the stored one is a mismatch too.
    let mut wrong = records.clone();
    wrong[0].hash ^= 1;
    let v = store.verify(&wrong[..1]).unwrap();
    assert_eq!(v.mismatched, vec![0]);
}

#[test]
fn torn_journal_resumes_into_the_same_frame_index() {
    let tmp = TempDir::new("journal");
    let dir = tmp.path();
    let mut journal = Journal::create(dir).unwrap();
    journal
        .append(&Entry::RunStarted {
            plan: attributes()["plan"].clone(),
            software: polar_engine::software_version(),
            devices: json!({}),
            width: W,
            height: H,
            started_unix_ns: 1,
        })
        .unwrap();
    let store = RunStore::create(dir, W, H, attributes()).unwrap();
    for i in 0..3 {
        store.write_frame(i, &pixels(i)).unwrap();
        journal.append(&Entry::Frame(record(i))).unwrap();
    }
    // Frame 3 reaches the store, then the process dies while journaling it.
    store.write_frame(3, &pixels(3)).unwrap();
    drop(journal);
    drop(store);
    let line = serde_json::to_string(&Entry::Frame(record(3))).unwrap();
    let path = dir.join(journal::JOURNAL_FILE);
    let mut text = std::fs::read(&path).unwrap();
    let good = text.len();
    text.extend_from_slice(&line.as_bytes()[..line.len() / 2]);
    std::fs::write(&path, &text).unwrap();

    let replay = journal::replay(dir).unwrap();
    assert!(replay.torn_tail);
    assert_eq!(replay.frames().len(), 3);
    assert_eq!(replay.next_frame_index(), 3);
    assert_eq!(replay.run_started().unwrap().width, W);

    // Resume: cut the torn line, take frame 3 again into the same index.
    let mut journal = Journal::open_append(dir).unwrap();
    assert_eq!(std::fs::metadata(&path).unwrap().len(), good as u64);
    let store = RunStore::open(dir).unwrap();
    store.write_frame(3, &pixels(3)).unwrap();
    journal.append(&Entry::Frame(record(3))).unwrap();
    let replay = journal::replay(dir).unwrap();
    assert!(!replay.torn_tail);
    let records = replay.frame_records();
    assert_eq!(records.len(), 4);
    store
        .write_frame_metadata(&records, &Default::default())
        .unwrap();
    let v = store.verify(&records).unwrap();
    assert!(v.is_ok() && v.unrecorded.is_empty(), "{v:?}");
    assert!(same_records(
        &store.read_frame_metadata().unwrap(),
        &records
    ));
}

#[test]
fn export_tiff_writes_readable_images() {
    let tmp = TempDir::new("export");
    drop(write_run(tmp.path()));
    let out = tmp.path().join("tiff");
    let summary = export_tiff(tmp.path(), &out).unwrap();
    assert_eq!(summary.frames, N);
    assert_eq!(summary.products, 2 * PRODUCT_NAMES.len() as u64);
    assert!(summary.dark_mean);
    assert_eq!(summary.csv_rows, N);
    assert!(summary.skipped.is_empty(), "{:?}", summary.skipped);

    let file = std::fs::File::open(out.join("frame_000002.tif")).unwrap();
    let mut dec = tiff::decoder::Decoder::new(std::io::BufReader::new(file)).unwrap();
    assert_eq!(dec.dimensions().unwrap(), (W, H));
    match dec.read_image().unwrap() {
        tiff::decoder::DecodingResult::U16(px) => assert_eq!(px, pixels(2)),
        other => panic!(
            "expected 16-bit pixels, got {:?}",
            std::mem::discriminant(&other)
        ),
    }
    let file = std::fs::File::open(out.join("set_0004_dolp.tif")).unwrap();
    let mut dec = tiff::decoder::Decoder::new(std::io::BufReader::new(file)).unwrap();
    match dec.read_image().unwrap() {
        tiff::decoder::DecodingResult::F32(px) => {
            let want = product(10.0 + 1.0);
            assert!(px
                .iter()
                .zip(&want)
                .all(|(a, b)| a == b || (a.is_nan() && b.is_nan())));
        }
        other => panic!(
            "expected float pixels, got {:?}",
            std::mem::discriminant(&other)
        ),
    }
    assert!(out.join("dark_mean.tif").is_file());
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines[0], CSV_HEADER);
    assert_eq!(lines.len(), N as usize + 1);
    assert!(
        lines[6].contains("\"dark after, \"\"capped\"\"\""),
        "{}",
        lines[6]
    );
    assert!(
        lines[1].starts_with("0,1,light,0,set 0 angle 0,"),
        "{}",
        lines[1]
    );

    let e = export_tiff(&tmp.path().join("nowhere"), &out).unwrap_err();
    assert!(e.to_string().contains("nowhere"), "{e}");
}

/// What the Python script must find: every array, with all values for small ones and
/// sum/min/max/samples for images.
fn expected_for_python(store: &RunStore) -> Value {
    fn image_spec(shape: Vec<u64>, dtype: &str, values: &[f64], samples: Value) -> Value {
        let finite: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
        json!({
            "shape": shape,
            "dtype": dtype,
            "sum": finite.iter().sum::<f64>(),
            "min": finite.iter().copied().fold(f64::INFINITY, f64::min),
            "max": finite.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            "samples": samples,
        })
    }
    let records: Vec<FrameRecord> = (0..N).map(record).collect();
    let mut arrays = Map::new();
    let all_px: Vec<f64> = (0..N)
        .flat_map(|i| pixels(i).into_iter().map(f64::from))
        .collect();
    let px_samples: Vec<Value> = [(0u64, 0u32, 0u32), (2, 10, 5), (4, 47, 63), (5, 3, 3)]
        .iter()
        .map(|&(i, y, x)| json!({"index": [i, y, x], "value": pixels(i)[(y * W + x) as usize]}))
        .collect();
    arrays.insert(
        "frames/pixels".into(),
        image_spec(
            vec![N, u64::from(H), u64::from(W)],
            "uint16",
            &all_px,
            json!(px_samples),
        ),
    );
    let col = |f: &dyn Fn(&FrameRecord) -> Value| -> Vec<Value> { records.iter().map(f).collect() };
    let small = [
        ("kind", "uint8", col(&|r| json!(r.kind.code()))),
        ("step", "uint64", col(&|r| json!(r.step))),
        (
            "set",
            "int64",
            col(&|r| json!(r.set.map_or(-1, |s| s as i64))),
        ),
        (
            "commanded_angle_deg",
            "float64",
            col(&|r| json!(r.commanded_angle_deg)),
        ),
        (
            "measured_angle_deg",
            "float64",
            col(&|r| json!(r.measured_angle_deg)),
        ),
        (
            "angle_start_deg",
            "float64",
            col(&|r| json!(r.angle_start_deg)),
        ),
        ("angle_end_deg", "float64", col(&|r| json!(r.angle_end_deg))),
        (
            "angle_source",
            "uint8",
            col(&|r| json!(r.angle_source.code())),
        ),
        (
            "angle_sigma_deg",
            "float64",
            col(&|r| json!(r.angle_sigma_deg)),
        ),
        ("exposure_us", "float64", col(&|r| json!(r.exposure_us))),
        ("gain", "float64", col(&|r| json!(r.gain))),
        (
            "host_time_unix_ns",
            "int64",
            col(&|r| json!(r.host_time_unix_ns)),
        ),
        (
            "device_timestamp_ns",
            "int64",
            col(&|r| json!(r.device_timestamp_ns.map_or(-1, |t| t as i64))),
        ),
        ("frame_id", "uint64", col(&|r| json!(r.frame_id))),
        (
            "sun_zenith_deg",
            "float64",
            col(&|r| json!(r.sun_zenith_deg)),
        ),
        (
            "sun_azimuth_deg",
            "float64",
            col(&|r| json!(r.sun_azimuth_deg)),
        ),
        ("hash", "uint64", col(&|r| json!(r.hash))),
        // Written with no frame marked as not counting: every frame counts.
        ("status", "uint8", col(&|_| json!(0))),
        ("accepted", "uint8", col(&|_| json!(1))),
    ];
    for (name, dtype, values) in small {
        arrays.insert(
            format!("frames/{name}"),
            json!({"shape": [N], "dtype": dtype, "values": values}),
        );
    }
    for name in PRODUCT_NAMES {
        let mut all = Vec::new();
        let mut samples = Vec::new();
        for slot in 0..2u64 {
            let img = store.read_product(name, slot).unwrap();
            samples.push(json!({"index": [slot, 0, 7], "value": Value::Null}));
            samples.push(json!({"index": [slot, 20, 30], "value": img[(20 * W + 30) as usize]}));
            all.extend(img.iter().map(|&v| f64::from(v)));
        }
        arrays.insert(
            format!("products/{name}"),
            image_spec(
                vec![2, u64::from(H), u64::from(W)],
                "float32",
                &all,
                json!(samples),
            ),
        );
    }
    arrays.insert(
        "products/set".into(),
        json!({"shape": [2], "dtype": "int64", "values": [3, 4]}),
    );
    arrays.insert(
        "products/angles_deg".into(),
        json!({"shape": [2, 4], "dtype": "float64",
               "values": [[0.0, 60.0, 120.0, null], [0.0, 45.0, 90.0, 135.0]]}),
    );
    let dark: Vec<f64> = dark_mean().iter().map(|&v| f64::from(v)).collect();
    arrays.insert(
        "darks/mean".into(),
        image_spec(
            vec![u64::from(H), u64::from(W)],
            "float32",
            &dark,
            json!([{"index": [1, 2], "value": dark_mean()[(W + 2) as usize]}]),
        ),
    );
    let attrs = attributes();
    json!({
        "attributes": {
            "plan": attrs["plan"],
            "software": attrs["software"],
            "devices": attrs["devices"],
            "state": "done",
            "calibration": {"analyzer": {"offset_deg": 0.2}},
            "decisions": [{"round": 0}],
        },
        "arrays": arrays,
        "exact_members": true,
    })
}

#[test]
fn python_zarr_reads_the_store() {
    let Some(python) = python() else {
        return;
    };
    let tmp = TempDir::new("python");
    let store = write_run(tmp.path());
    let expected = expected_for_python(&store);
    let expected_path = tmp.path().join("expected.json");
    std::fs::write(
        &expected_path,
        serde_json::to_vec_pretty(&expected).unwrap(),
    )
    .unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scripts/zarr_interop.py");
    let out = std::process::Command::new(&python)
        .arg(&script)
        .arg(tmp.path())
        .arg(&expected_path)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    println!("{stdout}{stderr}");
    assert!(
        out.status.success(),
        "{} failed ({}):\n{stdout}{stderr}",
        script.display(),
        out.status
    );

    // The script does see differences.
    let mut wrong = expected.clone();
    wrong["arrays"]["frames/kind"]["values"][0] = json!(1);
    wrong["attributes"]["plan"]["name"] = json!("other");
    std::fs::write(&expected_path, serde_json::to_vec(&wrong).unwrap()).unwrap();
    let out = std::process::Command::new(&python)
        .arg(&script)
        .arg(tmp.path())
        .arg(&expected_path)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{stdout}");
    assert!(
        stdout.contains("frames/kind") && stdout.contains("'plan'"),
        "{stdout}"
    );
}

#[test]
fn write_frame_timing_full_size() {
    // Not an assertion: prints how long a 2448x2048 frame takes to become durable here.
    let tmp = TempDir::new("timing");
    let (w, h) = (2448u32, 2048u32);
    let store = RunStore::create(tmp.path(), w, h, Map::new()).unwrap();
    let frame: Vec<u16> = (0..w * h).map(|p| (p % 4096) as u16).collect();
    let mut times = Vec::new();
    for i in 0..4 {
        let t = Instant::now();
        store.write_frame(i, &frame).unwrap();
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let t = Instant::now();
    let back = store.read_frame(3).unwrap();
    let read_ms = t.elapsed().as_secs_f64() * 1e3;
    assert_eq!(back.len(), frame.len());
    let records: Vec<FrameRecord> = (0..4)
        .map(|i| FrameRecord {
            width: w,
            height: h,
            hash: pixel_hash(&frame),
            ..record(i)
        })
        .collect();
    let t = Instant::now();
    store
        .write_frame_metadata(&records, &Default::default())
        .unwrap();
    let meta_ms = t.elapsed().as_secs_f64() * 1e3;
    println!(
        "write_frame {w}x{h} (10 MB, durable): {} ms; read_frame: {read_ms:.1} ms; \
         write_frame_metadata (4 frames): {meta_ms:.1} ms",
        times
            .iter()
            .map(|t| format!("{t:.1}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
}

/// A process killed between storing a small array's chunk and its metadata leaves the
/// newer chunk beside the older metadata. Every index array keeps a fixed chunk shape, so
/// that pair still reads (as the older values), and the next writer carries on from it.
#[test]
fn an_index_array_torn_between_chunk_and_metadata_reads_as_its_older_state() {
    let tmp = TempDir::new("torn-index");
    let store = write_run(tmp.path());
    let set_meta = tmp.path().join("run.zarr/products/set/zarr.json");
    let frames_meta = tmp.path().join("run.zarr/frames/hash/zarr.json");
    let older_set_meta = std::fs::read(&set_meta).unwrap();
    let older_frames_meta = std::fs::read(&frames_meta).unwrap();
    // A third slot and two more frame records, then the crash: both arrays' metadata revert
    // to what it was, while their chunks hold the newer values.
    let images: Vec<(&str, Vec<f32>)> = PRODUCT_NAMES.iter().map(|n| (*n, product(99.0))).collect();
    let refs: Vec<(&str, Plane)> = images.iter().map(|(n, v)| (*n, Plane::from(v))).collect();
    store.write_products(7, &slot_angles(2), &refs).unwrap();
    let records: Vec<FrameRecord> = (0..N + 2).map(record).collect();
    for i in N..N + 2 {
        store.write_frame(i, &pixels(i)).unwrap();
    }
    store
        .write_frame_metadata(&records, &Default::default())
        .unwrap();
    drop(store);
    std::fs::write(&set_meta, older_set_meta).unwrap();
    std::fs::write(&frames_meta, older_frames_meta).unwrap();

    let reopened = RunStore::open(tmp.path()).unwrap();
    let slots = reopened.product_slots().unwrap();
    let sets: Vec<Option<u64>> = slots.iter().map(|s| s.set).collect();
    assert_eq!(sets, vec![Some(3), Some(4)], "the older index: two slots");
    // The frame arrays now disagree in length (hash has the older 6, the rest 8): the
    // reader names the mismatch instead of failing to decode a chunk.
    let err = reopened.read_frame_metadata().unwrap_err().to_string();
    assert!(err.contains("frames/"), "{err}");
    // The next writer rewrites from its own records and everything reads again.
    reopened
        .write_frame_metadata(&records, &Default::default())
        .unwrap();
    assert!(same_records(
        &reopened.read_frame_metadata().unwrap(),
        &records
    ));
    let slot = reopened.write_products(7, &slot_angles(2), &refs).unwrap();
    assert_eq!(slot, 2, "set 7 takes the third slot again");
    assert_eq!(reopened.product_slots().unwrap().len(), 3);
}

/// The Python interpreter with zarr 3, xarray and xxhash (`POLARIMETER_PYTHON`, which
/// `scripts/test.sh` sets to its venv; else the venv `target/py-venv` if it exists, else
/// `python3`), or `None` when the test may skip (`POLARIMETER_SKIP_PYTHON=1`). Panics when
/// it is missing and skipping was not asked.
fn python() -> Option<String> {
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/py-venv/bin/python");
    let py = std::env::var("POLARIMETER_PYTHON").unwrap_or_else(|_| {
        if venv.is_file() {
            venv.display().to_string()
        } else {
            "python3".into()
        }
    });
    let ok = std::process::Command::new(&py)
        .args(["-c", "import zarr, xarray, xxhash"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if ok {
        return Some(py);
    }
    if std::env::var("POLARIMETER_SKIP_PYTHON").as_deref() == Ok("1") {
        println!("skipped the outside check: {py} lacks zarr, xarray or xxhash");
        return None;
    }
    panic!(
        "{py} cannot import zarr, xarray and xxhash: run the tests with `bash scripts/test.sh` \
         (it makes the venv and sets POLARIMETER_PYTHON), or set POLARIMETER_SKIP_PYTHON=1"
    );
}
