//! The station's instrument: [`polar_station::Runner`] with the command line's own `plan
//! check --rig`, `acquire run --rig` and `acquire resume`, so a station's run is exactly the
//! run a person would start on the same rig file.

use crate::acquire::{event_json, plan_check, resume_cmd, run_cmd, RunHooks, Ui};
use polar_engine::plan::Plan;
use polar_engine::run::{Control, Event};
use polar_engine::store::RunStore;
use polar_rig::flags::HardwareFlags;
use polar_rig::{Hardware, Rig, SIM_PORT};
use polar_station::schedule::SunSite;
use polar_station::{Plane, Request, RunControl, RunEnd, Runner};
use serde_json::{json, Value};
use std::path::Path;
use std::sync::Arc;

/// The rig a station runs on.
pub struct CliRunner {
    hardware: Hardware,
    rig: Rig,
    auto_resume: u32,
}

impl CliRunner {
    /// The rig file's devices (checked as `acquire run --rig` checks them); `auto_resume`
    /// device-error pauses are resumed before an item waits for a person.
    pub fn new(rig_file: &Path, auto_resume: u32) -> Result<CliRunner, String> {
        let flags = HardwareFlags {
            rig: Some(rig_file.to_path_buf()),
            ..HardwareFlags::default()
        };
        let (hardware, rig) = flags.hardware().map_err(|e| e.to_string())?;
        match (hardware, rig) {
            (Some(hardware), Some(rig)) => Ok(CliRunner {
                hardware,
                rig,
                auto_resume,
            }),
            _ => Err(format!(
                "rig {}: the station's rig file names no devices",
                rig_file.display()
            )),
        }
    }

    fn ui(&self, control: &Arc<RunControl>) -> Ui {
        let mut ui = Ui::unattended(self.auto_resume);
        ui.hooks = Some(std::rc::Rc::new(Hooks(control.clone())));
        ui
    }
}

/// A run's hooks: events to the station, its requests as controls.
struct Hooks(Arc<RunControl>);

impl RunHooks for Hooks {
    fn event(&self, event: &Event) {
        self.0.event(event_json(event));
    }

    fn interrupts(&self) -> u32 {
        0
    }

    fn control(&self) -> Option<Control> {
        self.0.take().map(|r| match r {
            Request::Pause => Control::Pause,
            Request::Abort => Control::Abort,
        })
    }
}

fn end((v, _code): (Value, i32)) -> RunEnd {
    RunEnd {
        state: v["state"].as_str().unwrap_or("failed").to_string(),
        reason: v["reason"].as_str().map(str::to_string),
        result: v,
    }
}

impl Runner for CliRunner {
    fn check(&self, plan_file: &Path) -> Result<Value, String> {
        let plan = Plan::from_path(plan_file).map_err(|e| e.to_string())?;
        // A plan sent to a station may not read the station's files.
        for (key, v) in [
            ("simulation.scene", &plan.simulation.scene),
            ("simulation.camera", &plan.simulation.camera),
        ] {
            if v.is_some() {
                return Err(format!(
                    "{key}: a station's plans name no files (the station's rig file names \
                     its camera; the simulated camera renders its built-in scene)"
                ));
            }
        }
        // A calibration writes its result back into the rig file: that is a lab's decision,
        // made with `acquire run --rig` at the instrument, not a remote queue's.
        let kind = plan.kind().name();
        if kind.starts_with("calibrate") {
            return Err(format!(
                "kind: a {kind} plan writes the rig file; run it at the instrument with \
                 `polarimeter acquire run --rig RIG PLAN`, not on a station"
            ));
        }
        let mut v = plan_check(plan_file, Some(&self.rig)).map_err(|e| e.to_string())?;
        // The store's forecast bytes (`plan check`'s `store`): what the disk budget uses.
        v["bytes"] = v["store"]["bytes"].clone();
        v["bytes_note"] = v["store"]["note"].clone();
        Ok(v)
    }

    fn run(
        &self,
        plan_file: &Path,
        run_dir: &Path,
        control: &Arc<RunControl>,
    ) -> Result<RunEnd, String> {
        let ui = self.ui(control);
        run_cmd(
            plan_file,
            Some(self.hardware.clone()),
            Some(&self.rig),
            Some(run_dir.to_path_buf()),
            ui,
        )
        .map(end)
        .map_err(|e| e.to_string())
    }

    fn resume(&self, run_dir: &Path, control: &Arc<RunControl>) -> Result<RunEnd, String> {
        // The rig the run recorded: a changed analyzer or camera file is refused, by name.
        resume_cmd(run_dir, None, None, self.ui(control))
            .map(end)
            .map_err(|e| e.to_string())
    }

    fn has_started(&self, run_dir: &Path) -> bool {
        polar_engine::run::plan_of(run_dir).is_ok()
    }

    fn latest_product(&self, run_dir: &Path, name: &str) -> Result<Plane, String> {
        let store = RunStore::open(run_dir).map_err(|e| e.to_string())?;
        let slot = store
            .product_slots()
            .map_err(|e| e.to_string())?
            .into_iter()
            .filter_map(|s| s.set.map(|set| (s.slot, set)))
            .next_back()
            .ok_or("no set written yet")?;
        let values = store
            .read_product(name, slot.0)
            .map_err(|e| e.to_string())?;
        Ok(Plane {
            width: store.width(),
            height: store.height(),
            set: slot.1,
            values,
        })
    }

    fn site(&self) -> Option<SunSite> {
        self.rig.file.site.as_ref().map(|s| SunSite {
            latitude_deg: s.latitude_deg,
            longitude_deg: s.longitude_deg,
            elevation_m: s.elevation_m,
        })
    }

    fn simulated(&self) -> bool {
        self.hardware.port == SIM_PORT && self.hardware.camera == "sim"
    }

    fn devices(&self) -> Value {
        let port = &self.hardware.port;
        let stage_ok = port == SIM_PORT || Path::new(port).exists();
        json!({
            "ok": stage_ok,
            "stage": {"port": port, "dialect": self.hardware.dialect.name, "ok": stage_ok,
                      "note": if port == SIM_PORT { "simulated: started with each run" }
                              else if stage_ok { "the serial port is present" }
                              else { "the serial port is gone (unplugged, or the adapter died)" }},
            "camera": {"camera": self.hardware.camera},
            "rig": self.rig.path.display().to_string(),
        })
    }
}
