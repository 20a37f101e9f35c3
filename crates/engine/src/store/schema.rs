//! The store's self-description: every array's Zarr metadata (shape, chunking, data type,
//! fill value, codecs, dimension names and CF-style attributes) built in one place, so the
//! `zarr.json` of an array is the same whoever writes it (a new run, a resume, a repair).
//!
//! Arrays are never re-serialised from metadata that was read back: zarrs writes a codec it
//! read as `{"name": "crc32c"}` back as the bare string `"crc32c"`, which zarr-python 3
//! refuses. Every metadata write goes through [`array`], which builds the metadata afresh.

use super::storage::Storage;
use crate::AngleSource;
use serde_json::{json, Map, Value};
use std::sync::Arc;
use zarrs::array::builder::ArrayBuilderFillValue;
use zarrs::array::codec::{Crc32cCodec, ZstdCodec};
use zarrs::array::{
    data_type, Array, ArrayBuilder, BytesToBytesCodecTraits, DataType, ZARR_NAN_F32,
};

/// The frame-kind codes of `frames/kind`.
pub const KIND_CODES: [(u8, &str); 2] = [(0, "light"), (1, "dark")];

/// The codes of `frames/status`: whether a stored frame counts, and why not.
pub const STATUS_CODES: [(u8, &str); 4] = [
    (0, "counts"),
    (1, "rejected_set"),
    (2, "superseded"),
    (3, "damaged"),
];

/// The hash of `frames/hash`.
pub const HASH_ALGORITHM: &str = "XXH3-64 of the frame's little-endian uint16 pixel bytes";

/// The conventions every product follows, recorded in the root attribute `conventions`.
pub fn conventions() -> Value {
    json!({
        "stokes": "S0, S1, S2 in DN above the dark level, referred to the light before the \
                   analyzer (the analyzer's transmittances and extinction are in its rows)",
        "s1_positive": "light polarised along the frame's x axis (image rows)",
        "s2_positive": "light polarised at +45 deg from x towards y",
        "aop": "0.5 atan2(S2, S1), radians in (-pi/2, pi/2], from the frame's x axis, \
                positive from x towards y",
        "analyzer_zero": "analyzer angle 0 transmits light polarised along the frame's x axis; \
                          angles are the stage's, corrected by the analyzer calibration's \
                          zero offset when the run has one",
        "angle_source_codes": AngleSource::CODES.iter().map(|(c, n)| (c.to_string(), json!(n)))
            .collect::<Map<String, Value>>(),
        "frame_kind_codes": KIND_CODES.iter().map(|(c, n)| (c.to_string(), json!(n)))
            .collect::<Map<String, Value>>(),
        "frame_status_codes": STATUS_CODES.iter().map(|(c, n)| (c.to_string(), json!(n)))
            .collect::<Map<String, Value>>(),
        "hash_algorithm": HASH_ALGORITHM,
        "host_time_epoch": "1970-01-01T00:00:00Z (UTC, the host's clock)",
        "device_time_epoch": "the camera's own clock; its epoch is the camera's (not UTC)",
        "flags": "products/flags bit 0 (1): a frame of the set saturated (every product \
                  NaN); bit 1 (2): DoLP undefined (S0 <= 0); bit 2 (4): AoP carries no \
                  information (S1 = S2 = 0, or sigma_aop_rad above pi/sqrt(12) = 0.907 rad, \
                  the spread of an angle drawn uniformly over the half turn)",
        "reference": "Meng (2012), docs/MODEL.md",
    })
}

/// The attributes of an array of codes: its `long_name` and the CF `flag_values` and
/// `flag_meanings` that decode it.
fn coded(long_name: &str, codes: &[(u8, &str)]) -> Map<String, Value> {
    let mut m = Map::new();
    m.insert("long_name".into(), json!(long_name));
    m.insert(
        "flag_values".into(),
        json!(codes.iter().map(|k| k.0).collect::<Vec<_>>()),
    );
    m.insert(
        "flag_meanings".into(),
        json!(codes.iter().map(|k| k.1).collect::<Vec<_>>().join(" ")),
    );
    m
}

/// The attributes of the array at `node` (`units`, `long_name`, and what a reader needs to
/// decode its values).
pub fn attributes(node: &str) -> Map<String, Value> {
    let a = |units: Option<&str>, long_name: &str| {
        let mut m = Map::new();
        if let Some(u) = units {
            m.insert("units".into(), json!(u));
        }
        m.insert("long_name".into(), json!(long_name));
        m
    };
    let name = node.rsplit('/').next().unwrap_or(node);
    let product = node.starts_with("/products/");
    let mut m = match name {
        "pixels" => {
            let mut m = a(Some("DN"), "raw frame as read from the camera");
            // CF: what describes each frame, so that xarray opens these as coordinates.
            m.insert("coordinates".into(), json!(FRAME_COORDINATES));
            m
        }
        "kind" => coded("frame kind", &KIND_CODES),
        "step" => a(None, "plan step the frame fulfils"),
        "set" if product => a(None, "angle set of the slot (-1: slot not written)"),
        "set" => a(None, "angle set of the frame (-1: none)"),
        "commanded_angle_deg" => a(Some("degree"), "analyzer angle commanded"),
        "measured_angle_deg" => a(
            Some("degree"),
            "analyzer angle read back from the stage (NaN: not read back)",
        ),
        "angle_start_deg" => a(
            Some("degree"),
            "analyzer angle when the exposure started, in [0, 180) (NaN: not known)",
        ),
        "angle_end_deg" => a(
            Some("degree"),
            "analyzer angle when the exposure ended, unwrapped from angle_start_deg \
             (end - start is the span swept, in [0, 180))",
        ),
        "angle_source" => coded("how the analyzer span was measured", &AngleSource::CODES),
        "angle_sigma_deg" => a(
            Some("degree"),
            "standard uncertainty of each end of the analyzer span (NaN: not estimated)",
        ),
        "exposure_us" => a(Some("us"), "exposure time"),
        "gain" => a(
            None,
            "gain the camera applied, in the camera's own gain unit (decibels on the \
             simulated camera; the root attribute devices names the camera)",
        ),
        "host_time_unix_ns" => a(
            Some("nanoseconds since 1970-01-01T00:00:00"),
            "host clock when the frame arrived (UTC)",
        ),
        "device_timestamp_ns" => a(
            Some("ns"),
            "camera's own timestamp (its own epoch; -1: none)",
        ),
        "frame_id" => a(None, "camera's frame counter"),
        "sun_zenith_deg" => a(Some("degree"), "sun zenith angle at the frame (NaN: none)"),
        "sun_azimuth_deg" => a(
            Some("degree"),
            "sun azimuth at the frame, from north through east (NaN: none)",
        ),
        "accepted" => a(
            None,
            "1: the frame counts (its set's products use it); 0: stored but superseded, \
             frames/status says why",
        ),
        "status" => coded("whether the frame counts, and why not", &STATUS_CODES),
        "hash" => {
            let mut m = a(None, "hash of the frame's pixels");
            m.insert("hash_algorithm".into(), json!(HASH_ALGORITHM));
            m
        }
        "angles_deg" => a(
            Some("degree"),
            "analyzer angles of the slot's frames (NaN padded)",
        ),
        "mean" => a(Some("DN"), "mean dark frame"),
        "s0" => a(
            Some("DN"),
            "Stokes S0 (total intensity) before the analyzer",
        ),
        "s1" => a(Some("DN"), "Stokes S1 (x minus y linear polarisation)"),
        "s2" => a(
            Some("DN"),
            "Stokes S2 (+45 minus -45 deg linear polarisation)",
        ),
        "dolp" => a(Some("1"), "degree of linear polarisation"),
        "aop_rad" => {
            let mut m = a(
                Some("rad"),
                "angle of linear polarisation from the frame's x axis towards y",
            );
            m.insert(
                "valid_range".into(),
                json!([-std::f64::consts::FRAC_PI_2, std::f64::consts::FRAC_PI_2]),
            );
            m
        }
        "sigma_s0" => a(Some("DN"), "predicted standard deviation of S0"),
        "sigma_s1" => a(Some("DN"), "predicted standard deviation of S1"),
        "sigma_s2" => a(Some("DN"), "predicted standard deviation of S2"),
        "sigma_dolp" => a(Some("1"), "predicted standard deviation of DoLP"),
        "sigma_aop_rad" => a(Some("rad"), "predicted standard deviation of AoP"),
        "flags" => {
            let mut m = a(None, "pixel quality flags (bit mask)");
            m.insert("flag_masks".into(), json!([1, 2, 4]));
            m.insert(
                "flag_meanings".into(),
                json!("saturated dolp_undefined aop_undefined"),
            );
            m
        }
        _ => a(None, name),
    };
    if product && !matches!(name, "set" | "angles_deg") {
        // CF: a product image's slot is described by its set and angles.
        m.insert("coordinates".into(), json!("set angles_deg"));
    }
    m
}

/// The per-frame arrays that describe a frame (every one but its hash: the analyzer span and
/// angles, exposure, gain, times, set, step, kind, whether it counts, the camera's counter and
/// the sun): the CF `coordinates` of `frames/pixels`.
const FRAME_COORDINATES: &str = "angle_start_deg angle_end_deg angle_sigma_deg angle_source \
     measured_angle_deg commanded_angle_deg exposure_us gain host_time_unix_ns \
     device_timestamp_ns set step kind accepted status frame_id sun_zenith_deg sun_azimuth_deg";

/// The bytes-to-bytes codecs of a chunk: zstd when `compressed` ([`super::storage`]), then a
/// `crc32c` checksum of the stored bytes.
fn codecs(compressed: bool) -> Vec<Arc<dyn BytesToBytesCodecTraits>> {
    let mut v: Vec<Arc<dyn BytesToBytesCodecTraits>> = Vec::new();
    if compressed {
        v.push(Arc::new(ZstdCodec::new(super::storage::ZSTD_LEVEL, false)));
    }
    v.push(Arc::new(Crc32cCodec::new()));
    v
}

/// Builds the array at `node` with its canonical metadata: `shape`, `chunk`, `data_type`,
/// `fill`, dimension names `dims`, zstd compression when `compressed`, a `crc32c` checksum on
/// every chunk and the attributes of [`attributes`]. Nothing is written until the caller
/// stores metadata or chunks.
#[allow(clippy::too_many_arguments)]
pub fn array<TStorage: ?Sized>(
    store: Arc<TStorage>,
    node: &str,
    shape: Vec<u64>,
    chunk: Vec<u64>,
    data_type: DataType,
    fill: impl Into<ArrayBuilderFillValue>,
    dims: &[&str],
    compressed: bool,
) -> Result<Array<TStorage>, zarrs::array::ArrayCreateError> {
    ArrayBuilder::new(shape, chunk, data_type, fill)
        .dimension_names(Some(dims.iter().copied()))
        .bytes_to_bytes_codecs(codecs(compressed))
        .attributes(attributes(node))
        .build(store, node)
}

/// A stack of `count` images of `width x height`, one chunk per image: `frames/pixels`
/// (uint16 raw frames along `frame`, fill 0) or a product `products/<name>` (float32 along
/// `slot`, fill NaN); zstd-compressed when `storage` says so, with the plane's rounding noted
/// in its attributes.
pub fn image_stack<TStorage: ?Sized>(
    store: Arc<TStorage>,
    node: &str,
    count: u64,
    (width, height): (u32, u32),
    storage: &Storage,
) -> Result<Array<TStorage>, zarrs::array::ArrayCreateError> {
    let (h, w) = (u64::from(height), u64::from(width));
    let (shape, chunk) = (vec![count, h, w], vec![1, h, w]);
    let z = storage.compressed();
    if node == "/products/flags" {
        // A bit mask: unsigned integers, 0 (no flag) where nothing was written.
        let dims = ["slot", "y", "x"];
        array(store, node, shape, chunk, data_type::uint8(), 0u8, &dims, z)
    } else if let Some(name) = node.strip_prefix("/products/") {
        let dims = ["slot", "y", "x"];
        let mut a = array(
            store,
            node,
            shape,
            chunk,
            data_type::float32(),
            ZARR_NAN_F32,
            &dims,
            z,
        )?;
        if let Some(note) = storage.rounding_note(name) {
            a.attributes_mut().insert("precision".into(), json!(note));
        }
        Ok(a)
    } else {
        let dims = ["frame", "y", "x"];
        array(
            store,
            node,
            shape,
            chunk,
            data_type::uint16(),
            0u16,
            &dims,
            z,
        )
    }
}
