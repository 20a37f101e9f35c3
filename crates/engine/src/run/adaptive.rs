//! The adaptive plan kind: the APTD state machine's sets, replayed from the stored frames
//! on resume.

use super::outcome::RunError;
use crate::plan::{Plan, StepSpec};
use crate::store::RunStore;
use crate::{FrameKind, FrameRecord};
use polar_model::sensor::Camera as CameraModel;
use polar_planner::aptd::{Aptd, AptdFrame, TargetSpec};
use polar_planner::aptd::{AptdConfig, Step as AptdStep};
use polar_planner::Constraints;
use serde_json::{json, Value};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// The steps of adaptive set `set` at `angles_rad`, numbered from `first_step`.
pub(super) fn adaptive_set(
    plan: &Plan,
    set: u64,
    first_step: u64,
    angles_rad: &[f64],
) -> Vec<(u64, StepSpec)> {
    let (exposure_us, gain_db) = plan
        .adaptive()
        .map_or((1000.0, 0.0), |a| (a.exposure_us, a.gain_db));
    angles_rad
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let deg = a.to_degrees().rem_euclid(180.0);
            (
                first_step + i as u64,
                StepSpec {
                    kind: FrameKind::Light,
                    set: Some(set),
                    angle_deg: deg,
                    exposure_us,
                    gain_db,
                    label: format!("round {} {deg:.3} deg", set + 1),
                    not_before_s: None,
                },
            )
        })
        .collect()
}

/// A stored light frame as APTD sees it: dark-subtracted DN at the measured angle.
pub(super) fn aptd_frame(
    r: &FrameRecord,
    pixels: &[u16],
    camera: &CameraModel,
    plan: &Plan,
) -> AptdFrame {
    let gain_db = plan.adaptive().map_or(0.0, |a| a.gain_db);
    let k = camera.gain_dn_per_e * 10f64.powf(gain_db / 20.0);
    let dark = camera.offset_dn + k * camera.dark_current_e_per_s * r.exposure_us * 1e-6;
    AptdFrame {
        angle_rad: r.measured_angle_deg.to_radians(),
        pixels: pixels.iter().map(|&p| f64::from(p) - dark).collect(),
    }
}

pub(super) fn decision_json(d: &polar_planner::aptd::Decision) -> Value {
    json!({
        "round": d.round,
        "frames_used": d.frames_used,
        "target_pixels": d.target_pixels,
        "d": d.d,
        "clutter_cov": d.clutter_cov,
        "scr_last_set": d.scr_last_set,
        "next_angles_deg": d.next_angles_rad.iter().map(|a| a.to_degrees()).collect::<Vec<_>>(),
        "scr_next": d.scr_next,
        "angle_change_deg": d.angle_change_rad.to_degrees(),
        "reason": d.reason,
    })
}

pub(super) enum AdaptiveNext {
    Acquire(u64, Vec<(u64, StepSpec)>),
    Done(Vec<f64>),
}

/// The APTD machine, rebuilt from the sets already accepted (a resumed run replays them; the
/// machine is deterministic, so it decides what it decided before), and the set to take next.
#[allow(clippy::too_many_arguments)]
pub(super) fn adaptive_start(
    plan: &Plan,
    a: &crate::plan::Adaptive,
    target_mask: &Option<Vec<bool>>,
    records: &BTreeMap<u64, FrameRecord>,
    accepted: &BTreeMap<u64, u64>,
    sets_done: &BTreeMap<u64, Vec<u64>>,
    reader: &RunStore,
    steps: &[StepSpec],
    width: u32,
    height: u32,
    camera: &CameraModel,
) -> Result<(Aptd, BTreeSet<u64>, AdaptiveNext), RunError> {
    let n_px = width as usize * height as usize;
    let target = if let Some(f) = a.target.anomalies {
        TargetSpec::Anomalies { fraction: f }
    } else if let Some([x0, y0, x1, y1]) = a.target.rect {
        plan.check_frame(width, height)?;
        let mut m = vec![false; n_px];
        for y in y0..y1 {
            for x in x0..x1 {
                m[(y * width + x) as usize] = true;
            }
        }
        TargetSpec::Region(m)
    } else {
        match target_mask {
            Some(m) if m.len() == n_px => TargetSpec::Region(m.clone()),
            _ => {
                return Err(RunError::Plan(crate::plan::PlanError::Invalid {
                    field: "adaptive.target.material".into(),
                    value: format!("{:?}", a.target.material),
                    allowed: "a material of the simulated scene (or use rect or anomalies \
                              on hardware)"
                        .into(),
                }))
            }
        }
    };
    // Sensor noise per frame, DN^2, at the mid-level of the camera's range.
    let k = camera.gain_dn_per_e * 10f64.powf(a.gain_db / 20.0);
    let mid_e = 0.25 * camera.full_well_e;
    let noise_var = k * k * (mid_e + camera.read_noise_e.powi(2)) + 1.0 / 12.0;
    // The rig's analyzer (the camera file's polarizer: its real extinction and offset) and
    // fore-optics: the Stokes estimate and the SCR the loop optimises use its rows, as the
    // forecast of `plan --scene` does.
    let analyzer = camera
        .polarizer
        .analyzer()
        .map_err(|e| RunError::Planner(format!("camera polarizer: {e}")))?;
    let instrument = polar_planner::Instrument {
        analyzer,
        fore_optics: camera.fore_optics().0,
        ..polar_planner::Instrument::ideal()
    };
    let config = AptdConfig {
        channels: a.channels,
        initial_angles_rad: a
            .initial_angles_deg
            .iter()
            .map(|d| d.to_radians())
            .collect(),
        noise_var,
        instrument,
        target,
        constraints: Constraints {
            min_separation_rad: a.min_separation_deg.to_radians(),
            ..Constraints::default()
        },
        angle_tol_rad: a.angle_tol_deg.to_radians(),
        scr_rel_tol: a.scr_rel_tol,
        frame_budget: a.frame_budget,
    };
    let (mut machine, mut next) =
        Aptd::new(config).map_err(|e| RunError::Planner(e.to_string()))?;
    let darks = steps.iter().filter(|s| s.kind == FrameKind::Dark).count() as u64;
    let mut planned: BTreeSet<u64> = (0..darks).collect();
    let mut set = 0u64;
    let mut first_step = darks;
    loop {
        let angles = match &next {
            AptdStep::Acquire(angles) => angles.clone(),
            AptdStep::Done(_) => {
                let last = machine
                    .decisions()
                    .last()
                    .map(|d| d.next_angles_rad.iter().map(|r| r.to_degrees()).collect())
                    .unwrap_or_default();
                return Ok((machine, planned, AdaptiveNext::Done(last)));
            }
        };
        let members = adaptive_set(plan, set, first_step, &angles);
        planned.extend(members.iter().map(|(s, _)| *s));
        if !sets_done.contains_key(&set) {
            return Ok((machine, planned, AdaptiveNext::Acquire(set, members)));
        }
        // Replay this set from the store.
        let mut frames = Vec::new();
        for (s, _) in &members {
            let idx = accepted.get(s).ok_or_else(|| {
                RunError::Check(format!("set {set} is done but step {s} has no frame"))
            })?;
            let r = records
                .get(idx)
                .ok_or_else(|| RunError::Check(format!("frame {idx} has no record")))?;
            let px = reader.read_frame(*idx)?;
            frames.push(aptd_frame(r, &px, camera, plan));
        }
        next = machine
            .on_frames(frames)
            .map_err(|e| RunError::Planner(e.to_string()))?;
        first_step += members.len() as u64;
        set += 1;
    }
}

/// The adaptive run in `run_dir` replayed: the planner rebuilt from the stored frames of every
/// set the journal records as done, in order, and its decisions as the journal writes them.
/// Equal to the journal's decisions when the planner saw exactly the stored frames (an
/// interrupted and resumed run included). `camera` and `target_mask` are those of the rig the
/// run used (a simulated rig's: [`crate::sim::SimRig`]).
pub fn replayed_decisions(
    plan: &Plan,
    run_dir: &Path,
    camera: &CameraModel,
    target_mask: &Option<Vec<bool>>,
) -> Result<Vec<Value>, RunError> {
    let a = plan
        .adaptive()
        .ok_or_else(|| RunError::Check("not an adaptive plan".into()))?;
    let replay = crate::journal::replay(run_dir)?;
    let superseded: BTreeSet<u64> = replay
        .rejected_frames()
        .union(&replay.damaged_frames())
        .copied()
        .collect();
    let records: BTreeMap<u64, FrameRecord> = replay
        .frames()
        .into_iter()
        .map(|(i, r)| (i, r.clone()))
        .collect();
    let mut accepted = BTreeMap::new();
    for r in records.values() {
        if !superseded.contains(&r.index) {
            accepted.insert(r.step, r.index);
        }
    }
    let mut sets_done = BTreeMap::new();
    for s in replay.sets_done() {
        sets_done.insert(s.set, s.frames.to_vec());
    }
    let store = RunStore::open(run_dir)?;
    let steps = plan.steps()?;
    let (machine, _, _) = adaptive_start(
        plan,
        a,
        target_mask,
        &records,
        &accepted,
        &sets_done,
        &store,
        &steps,
        store.width(),
        store.height(),
        camera,
    )?;
    Ok(machine.decisions().iter().map(decision_json).collect())
}
