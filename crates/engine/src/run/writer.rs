//! The storage thread: it owns the journal and the store, writes frames, computes each
//! set's products and the suspender's verdict, and finishes the run.

use super::outcome::{RunError, Verdict};
use crate::journal::{Entry, Journal};
use crate::products;
use crate::products::{Dark, NoiseModel, Products, SetGeometry};
use crate::store::{Plane, RunStore};
use crate::{FrameKind, FrameRecord};
use polar_model::sensor::Camera as CameraModel;
use polar_model::sensor::SensorModel;
use serde_json::json;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tracing::{info_span, warn};

// ---------------------------------------------------------------------------------------
// The storage thread.

pub(super) enum ToStore {
    Frame {
        record: FrameRecord,
        pixels: Vec<u16>,
    },
    Entry(Entry),
    ProcessSet(SetJob),
    /// Mirror the journal's frame records into the store's metadata arrays now (at a pause;
    /// the storage thread also does at set boundaries, at most about once a second, and at
    /// the end: the journal is the truth in between).
    SyncMetadata,
    Attribute {
        key: String,
        value: Value,
        reply: std::sync::mpsc::Sender<Result<(), String>>,
    },
    Finish {
        reply: std::sync::mpsc::Sender<Result<Value, String>>,
        summary: Value,
        checks: FinishChecks,
    },
}

pub(super) struct SetJob {
    pub(super) set: u64,
    /// Frame indices in step order.
    pub(super) frames: Vec<u64>,
    pub(super) measured_deg: Vec<f64>,
    pub(super) commanded_deg: Vec<f64>,
    pub(super) exposure_us: f64,
    pub(super) gain_db: f64,
    /// The analyzer rows of the frames, when not the still analyzer's at `measured_deg`
    /// (continuous rotation: the span rows of `crate::continuous::SpanEstimator`).
    pub(super) rows: Option<Vec<[f64; 3]>>,
}

pub(super) struct FinishChecks {
    /// Planned steps that must each have an accepted frame.
    pub(super) planned_steps: BTreeSet<u64>,
    /// Accepted frame per step.
    pub(super) accepted: BTreeMap<u64, u64>,
    /// Frames found damaged and kept aside: recorded, not verified.
    pub(super) damaged: BTreeSet<u64>,
}

pub(super) enum FromStore {
    Durable {
        index: u64,
        label: String,
    },
    SetChecked {
        set: u64,
        verdict: Verdict,
        mean_dolp: f64,
    },
    Failed(String),
}

pub(super) struct Writer {
    pub(super) store: RunStore,
    pub(super) journal: Journal,
    pub(super) sensor: SensorModel,
    pub(super) camera_model: CameraModel,
    pub(super) suspender: crate::plan::Suspender,
    pub(super) records: BTreeMap<u64, FrameRecord>,
    pub(super) cache: HashMap<u64, Vec<u16>>,
    pub(super) products: Products,
    /// The last accepted set's mean S0 by (exposure, gain) (bits of the f64s): a set is
    /// compared with the last one taken at its own exposure and gain only.
    pub(super) last_s0: HashMap<(u64, u64), f64>,
    pub(super) threads: usize,
    /// Sum and count of dark frames by exposure (bits of the f64).
    pub(super) darks: HashMap<u64, (Vec<f64>, u32)>,
    /// The frames that do not count, with their `frames/status` code (from the journal).
    pub(super) status: BTreeMap<u64, u8>,
    /// When the metadata last mirrored the journal, and how long that took.
    pub(super) last_sync: Option<(Instant, Duration)>,
}

impl Writer {
    /// The storage thread's state for a run opened in `store` and `journal`: the frames the
    /// journal records and the darks earlier processes took; no products yet.
    pub(super) fn new(
        store: RunStore,
        journal: Journal,
        plan: &crate::plan::Plan,
        sensor: &SensorModel,
        camera_model: &CameraModel,
        records: BTreeMap<u64, FrameRecord>,
        darks: HashMap<u64, (Vec<f64>, u32)>,
    ) -> Result<Writer, RunError> {
        // Which recorded frames count so far: the journal as it stands (with the damaged
        // frames this resume found).
        let dir = journal
            .path()
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_default();
        let status = crate::journal::frame_status(&crate::journal::replay(&dir)?.entries);
        Ok(Writer {
            store,
            journal,
            sensor: sensor.clone(),
            camera_model: camera_model.clone(),
            suspender: plan.suspender.clone(),
            records,
            cache: HashMap::new(),
            products: Products::empty(),
            last_s0: HashMap::new(),
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            darks,
            status,
            last_sync: None,
        })
    }

    /// Appends `entry` to the journal, noting which frames it says do not count.
    pub(super) fn append(&mut self, entry: &Entry) -> Result<(), String> {
        self.journal
            .append(entry)
            .map_err(|e| format!("journal: {e}"))?;
        crate::journal::mark_frame_status(&mut self.status, entry);
        Ok(())
    }

    pub(super) fn pixels(&mut self, index: u64) -> Result<Vec<u16>, String> {
        if let Some(p) = self.cache.get(&index) {
            return Ok(p.clone());
        }
        self.store.read_frame(index).map_err(|e| e.to_string())
    }

    pub(super) fn frame(&mut self, record: FrameRecord, pixels: Vec<u16>) -> Result<(), String> {
        self.store
            .write_frame(record.index, &pixels)
            .map_err(|e| format!("writing frame {}: {e}", record.index))?;
        self.journal
            .append(&Entry::Frame(record.clone()))
            .map_err(|e| format!("journal: {e}"))?;
        if record.kind == FrameKind::Dark {
            let (sum, n) = self
                .darks
                .entry(record.exposure_us.to_bits())
                .or_insert_with(|| (vec![0.0; pixels.len()], 0));
            if sum.len() == pixels.len() {
                sum.iter_mut()
                    .zip(&pixels)
                    .for_each(|(s, &p)| *s += f64::from(p));
                *n += 1;
            }
        } else {
            self.cache.insert(record.index, pixels);
        }
        self.records.insert(record.index, record);
        Ok(())
    }

    pub(super) fn noise(&self, gain_db: f64) -> NoiseModel {
        NoiseModel::from_camera(&self.camera_model, gain_db)
    }

    pub(super) fn process(&mut self, job: SetJob) -> Result<(Verdict, f64), String> {
        let mut frames = Vec::with_capacity(job.frames.len());
        for &i in &job.frames {
            frames.push(self.pixels(i)?);
        }
        let (w, h) = (self.store.width(), self.store.height());
        let rows: Vec<[f64; 3]> = match &job.rows {
            Some(rows) => rows.clone(),
            None => {
                let angles_rad: Vec<f64> =
                    job.measured_deg.iter().map(|d| d.to_radians()).collect();
                let rows_m = self
                    .sensor
                    .intensities_from_stokes(&angles_rad)
                    .map_err(|e| format!("analyzer rows: {e}"))?;
                (0..rows_m.nrows())
                    .map(|i| [rows_m[(i, 0)], rows_m[(i, 1)], rows_m[(i, 2)]])
                    .collect()
            }
        };
        let geometry = SetGeometry::new(&rows).map_err(|e| e.to_string())?;
        let noise = self.noise(job.gain_db);
        let dark_scalar = noise.dark_level_dn(&self.camera_model, job.exposure_us);
        let dark = match self.darks.get(&job.exposure_us.to_bits()) {
            // A dark map only from enough darks that its own noise is small (16 frames:
            // a quarter of one frame's temporal noise); otherwise the calibrated level.
            Some((sum, n)) if *n >= 16 && sum.len() == (w as usize * h as usize) => {
                Dark::Map(sum.iter().map(|s| (s / f64::from(*n)) as f32).collect())
            }
            _ => Dark::Scalar(dark_scalar as f32),
        };
        let refs: Vec<&[u16]> = frames.iter().map(Vec::as_slice).collect();
        products::compute_into(
            &mut self.products,
            &refs,
            w,
            h,
            &geometry,
            &dark,
            &noise,
            self.threads,
        )
        .map_err(|e| e.to_string())?;
        let verdict = self.verdict(&job, &refs, &rows, &dark, &noise);
        let mean_dolp = finite_mean(&self.products.dolp);
        if verdict.accepted {
            let names = Products::names();
            let flags = crate::flags::pixel_flags(&self.products);
            let mut images: Vec<(&str, Plane)> = names
                .iter()
                .filter_map(|n| self.products.image(n).map(|img| (*n, Plane::F32(img))))
                .collect();
            images.push(("flags", Plane::U8(&flags)));
            self.store
                .write_products(job.set, &job.measured_deg, &images)
                .map_err(|e| format!("products of set {}: {e}", job.set))?;
            let dark_text = match &dark {
                Dark::Map(_) => format!(
                    "the mean of the run's dark frames at {} us",
                    job.exposure_us
                ),
                Dark::Scalar(level) => format!(
                    "{level:.3} DN: the camera model's offset plus its dark current over {} us \
                     (fewer than 16 measured darks at this exposure)",
                    job.exposure_us
                ),
            };
            let dark_source = match &dark {
                Dark::Map(_) => json!({
                    "dark_frames": self.darks.get(&job.exposure_us.to_bits()).map_or(0, |d| d.1),
                    "exposure_us": job.exposure_us,
                }),
                Dark::Scalar(level) => json!({ "level_dn": f64::from(*level) }),
            };
            self.store
                .set_product_dark(job.set, &dark_text, dark_source)
                .map_err(|e| format!("products of set {}: {e}", job.set))?;
            self.store
                .set_product_saturation(job.set, verdict.saturated_fraction)
                .map_err(|e| format!("products of set {}: {e}", job.set))?;
            if verdict.saturated_fraction > self.suspender.max_saturated_fraction {
                warn!(
                    set = job.set,
                    "set {}: {:.1} % of its pixels saturated (more than the {:.1} % of \
                     suspender.max_saturated_fraction); their products are NaN",
                    job.set,
                    100.0 * verdict.saturated_fraction,
                    100.0 * self.suspender.max_saturated_fraction
                );
            }
            self.last_s0.insert(
                (job.exposure_us.to_bits(), job.gain_db.to_bits()),
                verdict.mean_s0_dn,
            );
            self.journal
                .append(&Entry::SetDone {
                    set: job.set,
                    frames: job.frames.clone(),
                    verdict: serde_json::to_value(&verdict).unwrap_or(Value::Null),
                })
                .map_err(|e| format!("journal: {e}"))?;
        } else {
            self.append(&Entry::SetRejected {
                set: job.set,
                frames: job.frames.clone(),
                reason: verdict.reason.clone(),
            })?;
        }
        for i in &job.frames {
            self.cache.remove(i);
        }
        Ok((verdict, mean_dolp))
    }

    /// The suspender (module doc): Malus residuals, S0 drift, analyzer readback, repeats.
    pub(super) fn verdict(
        &self,
        job: &SetJob,
        frames: &[&[u16]],
        rows: &[[f64; 3]],
        dark: &Dark,
        noise: &NoiseModel,
    ) -> Verdict {
        let p = &self.products;
        let mean_s0 = finite_mean(&p.s0);
        let max_angle_error_deg = job
            .commanded_deg
            .iter()
            .zip(&job.measured_deg)
            .map(|(c, m)| {
                let d = (c - m).rem_euclid(180.0);
                d.min(180.0 - d)
            })
            .fold(0.0, f64::max);
        // Mean reduced chi-square over unsaturated pixels (every 1 in `stride`).
        let n = frames.len();
        let mut chi2 = f64::NAN;
        if n > 3 {
            let px = p.s0.len();
            let stride = (px / 200_000).max(1);
            let (mut sum, mut count) = (0.0f64, 0u64);
            let mut i = 0;
            while i < px {
                if p.s0[i].is_finite() {
                    let s = [f64::from(p.s0[i]), f64::from(p.s1[i]), f64::from(p.s2[i])];
                    let d = match dark {
                        Dark::Scalar(v) => f64::from(*v),
                        Dark::Map(m) => f64::from(m[i]),
                    };
                    let mut c = 0.0;
                    for (f, r) in frames.iter().zip(rows) {
                        let y = f64::from(f[i]);
                        let model = r[0] * s[0] + r[1] * s[1] + r[2] * s[2];
                        let var = noise.gain_dn_per_e * (y - noise.offset_dn).max(0.0)
                            + noise.read_var_dn2;
                        c += (y - d - model).powi(2) / var;
                    }
                    sum += c / (n - 3) as f64;
                    count += 1;
                }
                i += stride;
            }
            if count > 0 {
                chi2 = sum / count as f64;
            }
        }
        let cfg = &self.suspender;
        let mut reasons = Vec::new();
        for a in 0..frames.len() {
            for b in a + 1..frames.len() {
                if frames[a] == frames[b] {
                    reasons.push(format!(
                        "frames {} and {} are identical (a stuck camera)",
                        job.frames[a], job.frames[b]
                    ));
                }
            }
        }
        if max_angle_error_deg > cfg.max_angle_error_deg {
            reasons.push(format!(
                "the analyzer is {max_angle_error_deg:.3} deg from where it was commanded \
                 (allowed {} deg): an analyzer slip",
                cfg.max_angle_error_deg
            ));
        }
        if chi2.is_finite() && chi2 > cfg.max_reduced_chi2 {
            reasons.push(format!(
                "the intensities do not follow Malus's law: mean reduced chi-square {chi2:.2} \
                 (allowed {}); the light changed during the set (a cloud?) or a frame is bad",
                cfg.max_reduced_chi2
            ));
        }
        if n == 3 {
            let key = (job.exposure_us.to_bits(), job.gain_db.to_bits());
            if let Some(&last) = self.last_s0.get(&key) {
                let change = (mean_s0 - last).abs() / last.abs().max(1e-9);
                if change > cfg.max_s0_change {
                    reasons.push(format!(
                        "the mean S0 changed by {:.1} % from the last set (allowed {:.1} %): \
                         the light changed",
                        100.0 * change,
                        100.0 * cfg.max_s0_change
                    ));
                }
            }
        }
        if !mean_s0.is_finite() {
            reasons.push("every pixel of the set is saturated or dark".into());
        }
        let accepted = !cfg.enabled || reasons.is_empty();
        let saturated = (0..p.s0.len())
            .filter(|&i| p.s0[i].is_nan() && p.s1[i].is_nan() && p.s2[i].is_nan())
            .count();
        Verdict {
            accepted,
            reason: reasons.join("; "),
            reduced_chi2: chi2,
            mean_s0_dn: mean_s0,
            max_angle_error_deg,
            saturated_fraction: saturated as f64 / p.s0.len().max(1) as f64,
        }
    }

    /// Mirrors the journal's frame records into the store's metadata, with which of them
    /// count (`frames/accepted`, `frames/status`, from the journal's rejected, superseded and
    /// damaged frames).
    pub(super) fn sync_metadata(&mut self) -> Result<(), String> {
        let t0 = Instant::now();
        let records: Vec<FrameRecord> = self.records.values().cloned().collect();
        self.store
            .write_frame_metadata(&records, &self.status)
            .map_err(|e| format!("frame metadata: {e}"))?;
        self.last_sync = Some((t0, t0.elapsed()));
        Ok(())
    }

    /// At a set boundary: mirrors the metadata if at least [`SYNC_INTERVAL`], and ten times
    /// the last mirror's own duration, have passed since it was last mirrored. A reader
    /// (xarray, say) then sees the run whole up to about a second behind, even after a
    /// crash, for at most a tenth of the storage thread's time as the run grows.
    fn sync_if_due(&mut self) -> Result<(), String> {
        let due = self
            .last_sync
            .is_none_or(|(at, took)| at.elapsed() >= SYNC_INTERVAL.max(took * 10));
        if due {
            self.sync_metadata()?;
        }
        Ok(())
    }

    pub(super) fn finish(
        &mut self,
        summary: Value,
        checks: &FinishChecks,
    ) -> Result<Value, String> {
        self.sync_metadata()?;
        // Planned against written.
        let missing: Vec<u64> = checks
            .planned_steps
            .iter()
            .filter(|s| !checks.accepted.contains_key(s))
            .copied()
            .collect();
        let extra: Vec<u64> = checks
            .accepted
            .keys()
            .filter(|s| !checks.planned_steps.contains(s))
            .copied()
            .collect();
        if !missing.is_empty() || !extra.is_empty() {
            return Err(format!(
                "frames written do not match frames planned: steps missing {missing:?}, \
                 steps not planned {extra:?}"
            ));
        }
        let intact: Vec<FrameRecord> = self
            .records
            .values()
            .filter(|r| !checks.damaged.contains(&r.index))
            .cloned()
            .collect();
        let v = self
            .store
            .verify(&intact)
            .map_err(|e| format!("verify: {e}"))?;
        let v = serde_json::to_value(&v).unwrap_or(Value::Null);
        let bad = ["missing", "mismatched"].iter().any(|k| {
            v.get(*k)
                .and_then(Value::as_array)
                .is_some_and(|a| !a.is_empty())
        });
        if bad {
            return Err(format!("stored frames do not match the journal: {v}"));
        }
        // Dark means.
        if let Some((sum, n)) = self.darks.values().next() {
            if *n > 0 {
                let mean: Vec<f32> = sum.iter().map(|s| (s / f64::from(*n)) as f32).collect();
                self.store
                    .write_dark_mean(&mean)
                    .map_err(|e| format!("dark mean: {e}"))?;
            }
        }
        self.store
            .set_attribute("summary", summary.clone())
            .map_err(|e| format!("summary: {e}"))?;
        self.store
            .set_attribute("state", json!("done"))
            .map_err(|e| format!("state: {e}"))?;
        let frames = self.records.len() as u64;
        self.journal
            .append(&Entry::Finished { frames })
            .map_err(|e| format!("journal: {e}"))?;
        Ok(json!({ "verification": v, "frames": frames }))
    }
}

pub(super) fn finite_mean(v: &[f32]) -> f64 {
    let (mut s, mut n) = (0.0f64, 0u64);
    for x in v {
        if x.is_finite() {
            s += f64::from(*x);
            n += 1;
        }
    }
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// The storage thread's ends: commands in, results out, and its handle.
pub(super) type WriterEnds = (
    std::sync::mpsc::SyncSender<ToStore>,
    mpsc::UnboundedReceiver<FromStore>,
    std::thread::JoinHandle<()>,
);

/// The least time between two metadata syncs at set boundaries ([`Writer::sync_if_due`]).
const SYNC_INTERVAL: Duration = Duration::from_secs(1);

pub(super) fn spawn_writer(mut writer: Writer) -> Result<WriterEnds, RunError> {
    // Two frames in flight at most: the grab loop never runs far ahead of the disk.
    let (tx, rx) = std::sync::mpsc::sync_channel::<ToStore>(2);
    let (back, back_rx) = mpsc::unbounded_channel();
    let handle = std::thread::Builder::new()
        .name("run-storage".into())
        .spawn(move || {
            let _span = info_span!("storage").entered();
            while let Ok(msg) = rx.recv() {
                match msg {
                    ToStore::Frame { record, pixels } => {
                        let (index, label) = (record.index, record.label.clone());
                        match writer.frame(record, pixels) {
                            Ok(()) => {
                                let _ = back.send(FromStore::Durable { index, label });
                            }
                            Err(e) => {
                                let _ = back.send(FromStore::Failed(e));
                            }
                        }
                    }
                    ToStore::Entry(e) => {
                        if let Err(e) = writer.append(&e) {
                            let _ = back.send(FromStore::Failed(e));
                        } else if let Entry::SetLate { .. } = &e {
                            let v = serde_json::to_value(&e).unwrap_or(Value::Null);
                            if let Err(e) = writer.store.push_late_set(v) {
                                let _ = back.send(FromStore::Failed(format!("late_sets: {e}")));
                            }
                        }
                    }
                    ToStore::ProcessSet(job) => {
                        let set = job.set;
                        let _s = info_span!("products", set).entered();
                        match writer.process(job).and_then(|r| {
                            writer.sync_if_due()?;
                            Ok(r)
                        }) {
                            Ok((verdict, mean_dolp)) => {
                                let _ = back.send(FromStore::SetChecked {
                                    set,
                                    verdict,
                                    mean_dolp,
                                });
                            }
                            Err(e) => {
                                let _ = back.send(FromStore::Failed(e));
                            }
                        }
                    }
                    ToStore::SyncMetadata => {
                        if let Err(e) = writer.sync_metadata() {
                            let _ = back.send(FromStore::Failed(e));
                        }
                    }
                    ToStore::Attribute { key, value, reply } => {
                        let _ = reply.send(
                            writer
                                .store
                                .set_attribute(&key, value)
                                .map_err(|e| format!("attribute {key}: {e}")),
                        );
                    }
                    ToStore::Finish {
                        reply,
                        summary,
                        checks,
                    } => {
                        let _ = reply.send(writer.finish(summary, &checks));
                    }
                }
            }
        })
        .map_err(|e| RunError::Storage(format!("cannot start the storage thread: {e}")))?;
    Ok((tx, back_rx, handle))
}
