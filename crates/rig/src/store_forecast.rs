//! The disk a run's store will take, forecast by storing what the run will store: one set of
//! the plan's own frames, rendered from its simulated scene and camera at the set's angles,
//! exposure and gain, and that set's products, written into a scratch store with the plan's
//! `[storage]` (the same codecs, rounding and planes as the run). The compressed sizes measured
//! there, scaled by the forecast's frames and sets, are the forecast.
//!
//! On the simulated rig this is the run's own data with other noise draws; on a real camera it
//! is the plan's scene model standing in for the sky, and its frame size that of
//! `[simulation]`.

use crate::simulated::{SimError, SimRig, SimWorld};
use polar_engine::plan::{Plan, StepSpec};
use polar_engine::products::{compute, Dark, NoiseModel, Products, SetGeometry};
use polar_engine::store::{Plane, RunStore};
use polar_engine::FrameKind;
use polar_hal::{BlockingCamera, Grabbed};
use polar_hil_mocks::camera::{SimCamera, SimCameraConfig};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// The forecast bytes of a run's store, by part.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StoreBytes {
    /// One stored light frame (its compressed chunk).
    pub per_frame: u64,
    /// One stored dark frame (the lens capped: compresses further).
    pub per_dark_frame: u64,
    /// The run's dark frames.
    pub darks: u64,
    /// One set's products (their compressed chunks).
    pub per_set_products: u64,
    /// Everything else: the arrays' metadata, the per-frame and index arrays.
    pub fixed: u64,
}

impl StoreBytes {
    /// The store of a run of `frames` frames (its darks among them) and `sets` sets.
    pub fn total(&self, frames: u64, sets: u64) -> u64 {
        let darks = self.darks.min(frames);
        self.fixed
            + darks * self.per_dark_frame
            + (frames - darks) * self.per_frame
            + sets * self.per_set_products
    }
}

/// A scratch directory, removed on drop.
struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn scratch() -> Scratch {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    Scratch(std::env::temp_dir().join(format!(
        "polarimeter-store-forecast-{}-{n}",
        std::process::id()
    )))
}

/// The frames the forecast renders: the light frames of the plan's first set (a plan without
/// sets: its first light frames), a dark frame if the plan takes any, and how many darks.
fn sample_steps(plan: &Plan) -> Result<(Vec<StepSpec>, Option<StepSpec>, u64), SimError> {
    let steps = plan.steps().map_err(|e| SimError::Input(e.to_string()))?;
    let dark = |s: &&StepSpec| s.kind == FrameKind::Dark;
    let darks = steps.iter().filter(dark).count() as u64;
    let dark_step = steps.iter().find(dark).cloned();
    let first = steps.iter().filter_map(|s| s.set).min();
    let light = steps.iter().filter(|s| s.kind == FrameKind::Light);
    let set: Vec<StepSpec> = light
        .clone()
        .filter(|s| s.set.is_some() && s.set == first)
        .cloned()
        .collect();
    let set = if set.is_empty() {
        light.take(4).cloned().collect()
    } else {
        set
    };
    Ok((set, dark_step, darks))
}

/// Bytes of the files under `dir` (0 when it does not exist).
fn bytes_under(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => bytes_under(&e.path()),
            _ => e.metadata().map_or(0, |m| m.len()),
        })
        .sum()
}

fn io(e: impl std::fmt::Display) -> SimError {
    SimError::Input(format!("store forecast: {e}"))
}

/// Renders one frame per step from a simulated camera held at the step's angle (a dark step
/// with the lens capped).
fn render(plan: &Plan, world: &SimWorld, steps: &[StepSpec]) -> Result<Vec<Vec<u16>>, SimError> {
    let angle_bits = Arc::new(AtomicU64::new(0));
    let source = Arc::clone(&angle_bits);
    let mut cam = SimCamera::new(
        SimCameraConfig {
            id: "store-forecast".into(),
            camera: world.camera_model.clone(),
            scene: Arc::clone(&world.scene),
            max_frame_rate_hz: 1000.0,
            faults: Default::default(),
            seed: plan.simulation.seed,
            noise_stream: 1,
        },
        Arc::new(move || f64::from_bits(source.load(Ordering::Relaxed))),
    )
    .map_err(|e| SimError::Camera(e.to_string()))?;
    let mut frames = Vec::with_capacity(steps.len());
    let light = cam.illumination();
    for s in steps {
        light.set(if s.kind == FrameKind::Dark { 0.0 } else { 1.0 });
        angle_bits.store(s.angle_deg.to_radians().to_bits(), Ordering::Relaxed);
        let cam_err = |e: polar_hal::DeviceError| SimError::Camera(e.to_string());
        cam.set_exposure_us(s.exposure_us).map_err(cam_err)?;
        cam.set_gain(s.gain_db).map_err(cam_err)?;
        cam.start().map_err(cam_err)?;
        let wait = Duration::from_secs_f64(1.0 + 3.0 * s.exposure_us * 1e-6);
        let grabbed = cam.wait_frame(wait).map_err(cam_err)?;
        cam.stop().map_err(cam_err)?;
        match grabbed {
            Grabbed::Frame(f) => frames.push(f.pixels),
            _ => {
                return Err(SimError::Camera(
                    "the simulated camera gave no frame".into(),
                ))
            }
        }
    }
    Ok(frames)
}

/// Forecasts the store of a run of `plan` (files it names are read relative to `plan_dir`).
/// A plan's frames are rendered at its `[simulation]` size, fully (a 5 MP frame takes about a
/// tenth of a second).
pub fn forecast(plan: &Plan, plan_dir: &Path) -> Result<StoreBytes, SimError> {
    let (steps, dark_step, darks) = sample_steps(plan)?;
    if steps.is_empty() {
        return Err(SimError::Input(
            "store forecast: the plan takes no light frames".into(),
        ));
    }
    let mut rendered = steps.clone();
    rendered.extend(dark_step);
    let world = SimRig::world(plan, plan_dir)?;
    let mut frames = render(plan, &world, &rendered)?;
    let dark_frame = (frames.len() > steps.len()).then(|| frames.pop()).flatten();
    let (w, h) = (plan.simulation.width, plan.simulation.height);
    let dir = scratch();
    let mut attrs = serde_json::Map::new();
    attrs.insert(
        "storage".into(),
        serde_json::to_value(plan.storage).map_err(io)?,
    );
    let store = RunStore::create(&dir.0, w, h, attrs).map_err(io)?;
    for (i, f) in frames.iter().enumerate() {
        store.write_frame(i as u64, f).map_err(io)?;
    }
    let chunks = root_of(&dir).join("frames/pixels/c");
    let pixels = bytes_under(&chunks);
    let per_dark_frame = match &dark_frame {
        Some(f) => {
            store.write_frame(frames.len() as u64, f).map_err(io)?;
            // A run with darks also stores their mean (`darks/mean`, in `fixed`).
            let mean: Vec<f32> = f.iter().map(|&v| f32::from(v)).collect();
            store.write_dark_mean(&mean).map_err(io)?;
            bytes_under(&chunks) - pixels
        }
        None => 0,
    };
    if steps.iter().any(|s| s.set.is_some()) {
        let camera = &world.camera_model;
        let noise = NoiseModel::from_camera(camera, steps[0].gain_db);
        let dark = Dark::Scalar(noise.dark_level_dn(camera, steps[0].exposure_us) as f32);
        let angles_rad: Vec<f64> = steps.iter().map(|s| s.angle_deg.to_radians()).collect();
        let geometry = SetGeometry::ideal(&angles_rad).map_err(io)?;
        let refs: Vec<&[u16]> = frames.iter().map(Vec::as_slice).collect();
        let p = compute(&refs, w, h, &geometry, &dark, &noise, 0).map_err(io)?;
        let flags = polar_engine::flags::pixel_flags(&p);
        let mut images: Vec<(&str, Plane<'_>)> = Products::names()
            .into_iter()
            .zip(p.images())
            .map(|(n, v)| (n, Plane::F32(v)))
            .collect();
        images.push(("flags", Plane::U8(&flags)));
        let angles_deg: Vec<f64> = steps.iter().map(|s| s.angle_deg).collect();
        store.write_products(0, &angles_deg, &images).map_err(io)?;
    }
    let root = root_of(&dir);
    let mut products = 0;
    if let Ok(entries) = std::fs::read_dir(root.join("products")) {
        for e in entries.flatten() {
            let name = e.file_name();
            if name != "set" && name != "angles_deg" {
                products += bytes_under(&e.path().join("c"));
            }
        }
    }
    let total = bytes_under(&root);
    Ok(StoreBytes {
        per_frame: pixels / frames.len() as u64,
        per_dark_frame,
        darks,
        per_set_products: products,
        fixed: total - pixels - per_dark_frame - products,
    })
}

fn root_of(dir: &Scratch) -> PathBuf {
    dir.0.join(polar_engine::store::STORE_DIR)
}
