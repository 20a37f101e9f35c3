//! `--rig FILE` in the commands: the rig file's site for a plan, its camera file for a
//! forecast, and calibrations written back to it (`polar_rig::file`).

use crate::commands::CommandError;
use polar_engine::plan::{Plan, PlanKind};
use polar_rig::{Hardware, Rig};
use serde_json::{json, Value};
use std::path::Path;

/// Reads a rig file; the error names `--rig` and the file.
pub fn load(path: &Path) -> Result<Rig, CommandError> {
    Rig::load(path).map_err(|e| CommandError::input("--rig", format!(": {e}")))
}

/// The rig a run was started with, from what its store recorded (the `devices` attribute's
/// `rig`: the file's path, its content hash and the flags given), for `acquire resume RUN`
/// without `--rig` or device flags. Returns the rig, its hardware and the differences between
/// the devices now and those the run recorded, each named ("zero_offset_deg: 0 then, 0.4
/// now"). `None` when the run was not started from a rig file.
pub fn recorded(devices: &Value) -> Result<Option<(Rig, Hardware, Vec<String>)>, CommandError> {
    let recorded = &devices["rig"];
    let Some(path) = recorded["absolute_file"]
        .as_str()
        .or_else(|| recorded["file"].as_str())
    else {
        return Ok(None);
    };
    let rig = Rig::load(Path::new(path)).map_err(|e| {
        CommandError::failed(format!(
            "the run was started with the rig file {path}, which cannot be read now ({e}): \
             give --rig (and any flags) to resume it"
        ))
    })?;
    let overrides = polar_rig::Overrides::from_json(&recorded["overrides"]);
    let hw = rig
        .hardware(&overrides)
        .map_err(CommandError::of)?
        .ok_or_else(|| CommandError::failed(format!("rig {path} names no devices now")))?;
    let mut differences = Vec::new();
    if let Some(then) = recorded["content_xxh3"].as_str() {
        if then != rig.content_xxh3 {
            differences.push(format!(
                "rig file {path}: content hash {then} then, {} now",
                rig.content_xxh3
            ));
        }
    }
    let now = json!({
        "stage.port": hw.port,
        "stage.dialect": hw.dialect.name,
        "stage.address": hw.address,
        "camera": hw.camera,
        "camera_file": hw.camera_file.display().to_string(),
        "zero_offset_deg": hw.zero_offset_deg,
        "extinction_ratio": hw.extinction_ratio,
    });
    let then = json!({
        "stage.port": devices["stage"]["port"],
        "stage.dialect": devices["stage"]["dialect"],
        "stage.address": devices["stage"]["address"],
        "camera": devices["camera"],
        "camera_file": devices["camera_file"],
        "zero_offset_deg": devices["zero_offset_deg"],
        "extinction_ratio": devices["extinction_ratio"],
    });
    for (key, value) in now.as_object().into_iter().flatten() {
        if then[key] != *value {
            differences.push(format!("{key}: {} then, {value} now", then[key]));
        }
    }
    Ok(Some((rig, hw, differences)))
}

/// The rig's site for a plan that names none (a plan's own `[site]` wins).
pub fn apply_site(plan: &mut Plan, rig: &Rig) {
    if plan.site.is_none() {
        plan.site = rig.file.site.clone();
    }
}

/// The rig's camera file as a camera model (with the analyzer's extinction ratio, if the rig
/// gives one), or `None` if the rig names no camera file.
pub fn camera_model(rig: &Rig) -> Result<Option<polar_model::sensor::Camera>, CommandError> {
    let Some(path) = &rig.camera_file else {
        return Ok(None);
    };
    let mut camera = read_camera_file(rig, path)?;
    if let Some(er) = rig.analyzer.as_ref().and_then(|a| a.extinction_ratio) {
        camera.polarizer.extinction_ratio = Some(er);
    }
    Ok(Some(camera))
}

/// The rig's camera file at `path`, as written (errors name the rig and `camera.file`).
fn read_camera_file(rig: &Rig, path: &Path) -> Result<polar_model::sensor::Camera, CommandError> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        CommandError::failed(format!(
            "rig {}: camera.file = {}: cannot read: {e}",
            rig.path.display(),
            path.display()
        ))
    })?;
    polar_model::sensor::Camera::from_toml_str(&text).map_err(|e| {
        CommandError::failed(format!(
            "rig {}: camera.file = {}: {e}",
            rig.path.display(),
            path.display()
        ))
    })
}

/// The stage's new zero offset after a calibrate-analyzer run made with zero offset
/// `used_deg` measured `delta_deg` (the analyzer's true axis is the commanded angle plus
/// `delta_deg`, `polar_engine::analyzer_cal`): the stage angle at which the axis is along x
/// moves by `-delta_deg`. Reduced to `(-90, 90]` (the analyzer's period is half a turn).
pub fn corrected_zero_offset_deg(used_deg: f64, delta_deg: f64) -> f64 {
    let z = (used_deg - delta_deg).rem_euclid(180.0);
    if z > 90.0 {
        z - 180.0
    } else {
        z
    }
}

/// After a finished run with `--rig`: a calibrate-analyzer run's zero offset and extinction
/// ratio written as a new `analyzer.rN.toml` the rig then points to; a calibrate-noise run's
/// measured camera (the rig's camera file with the measured detector fields) written as a new
/// revision of that camera file, which the rig then points to. Returns what was written.
pub fn write_back(
    rig: &Rig,
    plan: &Plan,
    run_dir: &Path,
    used_zero_offset_deg: f64,
) -> Result<Option<Value>, CommandError> {
    if plan.kind() == PlanKind::CalibrateNoise {
        return write_back_noise(rig, run_dir).map(Some);
    }
    if plan.kind() != PlanKind::CalibrateAnalyzer {
        return Ok(None);
    }
    let store = polar_engine::store::RunStore::open(run_dir)
        .map_err(|e| CommandError::layer(format!("{}: ", run_dir.display()), e))?;
    let attrs = store
        .attributes()
        .map_err(|e| CommandError::layer(format!("{}: ", run_dir.display()), e))?;
    let cal = &attrs
        .get("calibration")
        .and_then(|c| c.get("analyzer"))
        .cloned()
        .unwrap_or(Value::Null);
    let (Some(delta), Some(er)) = (
        cal["zero_offset_deg"].as_f64(),
        cal["extinction_ratio"].as_f64(),
    ) else {
        return Err(CommandError::failed(format!(
            "{}: the run finished without an analyzer calibration to write to the rig",
            run_dir.display()
        )));
    };
    let zero = corrected_zero_offset_deg(used_zero_offset_deg, delta);
    let path = rig
        .record_analyzer(zero, er, Some(run_dir))
        .map_err(CommandError::of)?;
    Ok(Some(json!({
        "rig": rig.path.display().to_string(),
        "analyzer_file": path.display().to_string(),
        "zero_offset_deg": zero,
        "extinction_ratio": er,
    })))
}

/// A finished calibrate-noise run's photon transfer (the store's `calibration.noise`) applied
/// to the rig's camera file; written first into the run directory as `measured_camera.toml`
/// (never over an existing file), then as the camera file's new revision.
fn write_back_noise(rig: &Rig, run_dir: &Path) -> Result<Value, CommandError> {
    let store = polar_engine::store::RunStore::open(run_dir)
        .map_err(|e| CommandError::layer(format!("{}: ", run_dir.display()), e))?;
    let attrs = store
        .attributes()
        .map_err(|e| CommandError::layer(format!("{}: ", run_dir.display()), e))?;
    let noise = attrs
        .get("calibration")
        .and_then(|c| c.get("noise"))
        .cloned()
        .ok_or_else(|| {
            CommandError::failed(format!(
                "{}: the run finished without a noise calibration to write to the rig",
                run_dir.display()
            ))
        })?;
    let fit: polar_model::calibration::PhotonTransfer =
        serde_json::from_value(noise).map_err(|e| {
            CommandError::layer(format!("{}: calibration.noise: ", run_dir.display()), e)
        })?;
    let base_path = rig.camera_file.as_ref().ok_or_else(|| {
        CommandError::failed(format!(
            "rig {}: camera.file is missing: the measured camera needs a base camera file",
            rig.path.display()
        ))
    })?;
    let base = read_camera_file(rig, base_path)?;
    let measured = run_dir.join("measured_camera.toml");
    if measured.exists() {
        return Err(CommandError::failed(format!(
            "{}: exists; not overwritten (the rig keeps its camera file)",
            measured.display()
        )));
    }
    let mut warnings = Vec::new();
    crate::calibrate::measured_camera(&base, &fit, &measured, &mut warnings)
        .map_err(CommandError::of)?;
    let mut written = record_camera_file(rig, &measured)?;
    written["gain_dn_per_e"] = json!(fit.k_dn_per_e.value);
    written["warnings"] = json!(warnings);
    Ok(written)
}

/// `calibrate noise --rig`: the measured camera file written as a new revision beside the
/// rig's camera file, and the rig pointed at it.
pub fn record_camera_file(rig: &Rig, measured: &Path) -> Result<Value, CommandError> {
    let path = rig.record_camera_file(measured).map_err(CommandError::of)?;
    Ok(json!({
        "rig": rig.path.display().to_string(),
        "camera_file": path.display().to_string(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The correction subtracts the measured offset and keeps the result in the analyzer's
    /// half-turn period: exact values, since they are sums of representable degrees.
    #[test]
    fn zero_offset_correction() {
        assert_eq!(corrected_zero_offset_deg(0.0, 2.5), -2.5);
        assert_eq!(corrected_zero_offset_deg(1.0, -1.5), 2.5);
        assert_eq!(corrected_zero_offset_deg(89.0, -3.0), -88.0);
        assert_eq!(corrected_zero_offset_deg(-89.0, 3.0), 88.0);
    }
}
