//! How a store keeps its images: zstd on every chunk, products rounded to what their sigma
//! warrants, the essential planes stored and S1, S2 derived on read; a store written before
//! any of this (no `storage` attribute) keeps its own codecs when it grows.
#![allow(clippy::unwrap_used)]

use polar_engine::store::{Plane, ProductSet, RunStore, Storage};
use serde_json::{json, Map, Value};
use std::path::Path;

const W: u32 = 40;
const H: u32 = 30;

/// A product set of a smooth polarised scene: S0 from 200 to 2000 DN, DoLP up to 0.6, AoP
/// across the half turn, with shot-noise-like sigmas.
struct Set {
    planes: Vec<(&'static str, Vec<f32>)>,
}

fn scene() -> Set {
    let n = (W * H) as usize;
    let mut s0 = Vec::with_capacity(n);
    let (mut dolp, mut aop) = (Vec::new(), Vec::new());
    for i in 0..n {
        let (x, y) = ((i % W as usize) as f32, (i / W as usize) as f32);
        s0.push(200.0 + 1800.0 * x / W as f32 + 0.37 * y);
        dolp.push(0.6 * y / H as f32 + 0.013);
        aop.push(-1.5 + 3.0 * x / W as f32);
    }
    let s1: Vec<f32> = (0..n)
        .map(|i| s0[i] * dolp[i] * (2.0 * aop[i]).cos())
        .collect();
    let s2: Vec<f32> = (0..n)
        .map(|i| s0[i] * dolp[i] * (2.0 * aop[i]).sin())
        .collect();
    let sigma_s: Vec<f32> = s0.iter().map(|v| (2.0 * v).sqrt()).collect();
    let sigma_dolp: Vec<f32> = s0.iter().map(|v| 1.4 / v.sqrt()).collect();
    let sigma_aop: Vec<f32> = (0..n).map(|i| sigma_dolp[i] / (2.0 * dolp[i])).collect();
    Set {
        planes: vec![
            ("s0", s0),
            ("s1", s1),
            ("s2", s2),
            ("dolp", dolp),
            ("aop_rad", aop),
            ("sigma_s0", sigma_s.clone()),
            ("sigma_s1", sigma_s.clone()),
            ("sigma_s2", sigma_s),
            ("sigma_dolp", sigma_dolp),
            ("sigma_aop_rad", sigma_aop),
        ],
    }
}

impl Set {
    fn get(&self, name: &str) -> &[f32] {
        &self.planes.iter().find(|(n, _)| *n == name).unwrap().1
    }

    fn images(&self) -> Vec<(&str, Plane<'_>)> {
        self.planes
            .iter()
            .map(|(n, v)| (*n, Plane::F32(v)))
            .collect()
    }
}

fn create(dir: &Path, storage: Option<Storage>) -> RunStore {
    let mut attrs = Map::new();
    if let Some(s) = storage {
        attrs.insert("storage".into(), serde_json::to_value(s).unwrap());
    }
    RunStore::create(dir, W, H, attrs).unwrap()
}

fn codecs(dir: &Path, node: &str) -> Vec<String> {
    let meta: Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("run.zarr").join(node).join("zarr.json")).unwrap(),
    )
    .unwrap();
    meta["codecs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            c["name"]
                .as_str()
                .unwrap_or_else(|| c.as_str().unwrap())
                .to_string()
        })
        .collect()
}

#[test]
fn default_storage_rounds_by_sigma_and_derives_stokes() {
    let tmp = tempfile::tempdir().unwrap();
    let store = create(tmp.path(), None);
    assert_eq!(store.storage(), Storage::default());
    let set = scene();
    store
        .write_products(0, &[0.0, 45.0, 90.0, 135.0], &set.images())
        .unwrap();
    let mut names = store.product_names().unwrap();
    names.sort();
    assert_eq!(
        names,
        ["aop_rad", "dolp", "s0", "sigma_dolp", "sigma_s0"],
        "the essential planes (no flags were given)"
    );
    for node in ["products/s0", "frames/pixels", "frames/exposure_us"] {
        assert_eq!(
            codecs(tmp.path(), node),
            ["bytes", "zstd", "crc32c"],
            "{node}"
        );
    }
    // Each stored value lies within a quarter of its own pixel's sigma (the step is a power
    // of two at most half of it), and is not left as computed everywhere.
    for (name, sigma) in [("s0", "sigma_s0"), ("dolp", "sigma_dolp")] {
        let got = store.read_product(name, 0).unwrap();
        let (want, s) = (set.get(name), set.get(sigma));
        let worst = (0..got.len())
            .map(|i| (got[i] - want[i]).abs() / s[i])
            .fold(0f32, f32::max);
        assert!(worst <= 0.25, "{name}: {worst} sigma");
        assert!(worst > 0.01, "{name} is rounded: {worst} sigma");
    }
    // A sigma keeps 4 bits after the leading one: within 2^-5 relative.
    let (got, want) = (
        store.read_product("sigma_dolp", 0).unwrap(),
        set.get("sigma_dolp"),
    );
    let rel = (0..got.len())
        .map(|i| ((got[i] - want[i]) / want[i]).abs())
        .fold(0f32, f32::max);
    assert!(rel <= 1.0 / 32.0, "{rel}");
    // S1 and S2 derived on read from the rounded S0, DoLP and AoP: within about a sigma of
    // S1 (S0 and DoLP each off by at most sigma/4; AoP's step is at most sigma_aop/2).
    for name in ["s1", "s2"] {
        let got = store.read_product(name, 0).unwrap();
        let (want, s) = (set.get(name), set.get(&format!("sigma_{name}")));
        let worst = (0..got.len())
            .map(|i| (got[i] - want[i]).abs() / s[i])
            .fold(0f32, f32::max);
        assert!(worst < 1.0, "{name} derived: {worst} sigma");
    }
    let e = store.read_product("sigma_s1", 0).unwrap_err().to_string();
    assert!(e.contains("not in the store"), "{e}");
}

#[test]
fn all_planes_at_float32_are_stored_as_computed() {
    let tmp = tempfile::tempdir().unwrap();
    let exact = Storage {
        products: ProductSet::All,
        precision: polar_engine::store::Precision::Float32,
        ..Storage::default()
    };
    let store = create(tmp.path(), Some(exact));
    let set = scene();
    store
        .write_products(3, &[0.0, 60.0, 120.0], &set.images())
        .unwrap();
    for (name, want) in &set.planes {
        assert_eq!(&store.read_product(name, 0).unwrap(), want, "{name}");
    }
    let reopened = RunStore::open(tmp.path()).unwrap();
    assert_eq!(reopened.storage(), exact);
}

#[test]
fn a_store_without_a_storage_attribute_grows_uncompressed() {
    let tmp = tempfile::tempdir().unwrap();
    let store = create(tmp.path(), Some(Storage::legacy()));
    // What a store from before `storage` looks like: drop the attribute.
    let root = tmp.path().join("run.zarr/zarr.json");
    let mut meta: Value = serde_json::from_str(&std::fs::read_to_string(&root).unwrap()).unwrap();
    meta["attributes"]
        .as_object_mut()
        .unwrap()
        .remove("storage");
    std::fs::write(&root, meta.to_string()).unwrap();
    drop(store);
    let reopened = RunStore::open(tmp.path()).unwrap();
    assert_eq!(reopened.storage(), Storage::legacy());
    reopened
        .write_frame(0, &vec![7u16; (W * H) as usize])
        .unwrap();
    let set = scene();
    reopened.write_products(0, &[0.0], &set.images()).unwrap();
    assert_eq!(codecs(tmp.path(), "products/s0"), ["bytes", "crc32c"]);
    assert_eq!(codecs(tmp.path(), "frames/pixels"), ["bytes", "crc32c"]);
    assert_eq!(reopened.read_product("s1", 0).unwrap(), set.get("s1"));
}

#[test]
fn a_bad_storage_attribute_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let mut attrs = Map::new();
    attrs.insert("storage".into(), json!({"products": "most"}));
    let e = RunStore::create(tmp.path(), W, H, attrs)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("storage") && e.contains("most") && e.contains("essential"),
        "{e}"
    );
}
