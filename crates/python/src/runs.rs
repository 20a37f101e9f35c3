//! Runs from Python: `acquire run` and `acquire resume` through the CLI's own functions, with
//! the run's events passed to a Python callable and Python's Ctrl-C (a pending
//! `KeyboardInterrupt`) pausing the run at its next safe point, after which the
//! `KeyboardInterrupt` is raised with the run directory to resume.

use crate::errors::value_error;
use polar_cli::acquire::{resume_cmd, run_cmd, RunHooks, Ui};
use polar_engine::run::{Event, RunState};
use polar_rig::flags::HardwareFlags;
use pyo3::exceptions::PyKeyboardInterrupt;
use pyo3::prelude::*;
use serde_json::{json, Value};
use std::cell::RefCell;
use std::path::PathBuf;
use std::rc::Rc;

/// The hooks of one run: the caller's callable (given each event as JSON text) and the first
/// Python exception seen (a `KeyboardInterrupt`, or what the callable raised), which asks
/// the run to pause.
struct PyHooks {
    on_event: Option<Py<PyAny>>,
    raised: RefCell<Option<PyErr>>,
}

impl RunHooks for PyHooks {
    fn event(&self, event: &Event) {
        let Some(callable) = &self.on_event else {
            return;
        };
        if self.raised.borrow().is_some() {
            return;
        }
        let text = event_json(event).to_string();
        let result = Python::attach(|py| callable.call1(py, (text,)).map(|_| ()));
        if let Err(e) = result {
            *self.raised.borrow_mut() = Some(e);
        }
    }

    fn interrupted(&self) -> bool {
        if self.raised.borrow().is_some() {
            return true;
        }
        match Python::attach(|py| py.check_signals()) {
            Ok(()) => false,
            Err(e) => {
                *self.raised.borrow_mut() = Some(e);
                true
            }
        }
    }
}

/// An event as the Python layer reads it: `{"kind": ..., ...}`.
fn event_json(event: &Event) -> Value {
    match event {
        Event::State(s) => {
            let (state, reason) = match s {
                RunState::Starting => ("starting", None),
                RunState::Running => ("running", None),
                RunState::Pausing => ("pausing", None),
                RunState::Paused(r) => ("paused", Some(r)),
                RunState::Aborting => ("aborting", None),
                RunState::Done => ("done", None),
                RunState::Aborted(r) => ("aborted", Some(r)),
            };
            json!({"kind": "state", "state": state, "reason": reason})
        }
        Event::Progress {
            done,
            planned,
            label,
        } => json!({"kind": "progress", "done": done, "planned": planned, "label": label}),
        Event::Set {
            set,
            verdict,
            mean_s0,
            mean_dolp,
        } => json!({"kind": "set", "set": set, "accepted": verdict.accepted,
                    "reason": verdict.reason, "mean_s0_dn": mean_s0, "mean_dolp": mean_dolp}),
        Event::Decision(v) => json!({"kind": "decision", "decision": v}),
        Event::Retry(m) => json!({"kind": "retry", "message": m}),
    }
}

/// What ran: the command's JSON, or the exception the caller raised meanwhile.
fn finish(result: Result<(Value, i32), String>, raised: Option<PyErr>) -> PyResult<String> {
    let (value, _) = result.map_err(value_error)?;
    if let Some(e) = raised {
        return Python::attach(|py| {
            if e.is_instance_of::<PyKeyboardInterrupt>(py) {
                let dir = value["run_dir"].as_str().unwrap_or("the run directory");
                Err(PyKeyboardInterrupt::new_err(format!(
                    "the run paused at a safe point; polarimeter.resume({dir:?}) continues it"
                )))
            } else {
                Err(e)
            }
        });
    }
    Ok(value.to_string())
}

/// Runs `command` with an unattended UI whose hooks call `on_event` and watch for Ctrl-C (on
/// this thread, inside the GIL's release); its result and the exception raised meanwhile.
fn with_hooks<T>(on_event: Option<Py<PyAny>>, command: impl FnOnce(Ui) -> T) -> (T, Option<PyErr>) {
    let hooks = Rc::new(PyHooks {
        on_event,
        raised: RefCell::new(None),
    });
    let mut ui = Ui::unattended(0);
    ui.hooks = Some(hooks.clone() as Rc<dyn RunHooks>);
    let out = command(ui);
    let raised = hooks.raised.borrow_mut().take();
    (out, raised)
}

/// Runs `plan` into `out` (default `./run-NAME-UNIXTIME`) on the simulated devices
/// (`simulate`) or the hardware a rig file names, as `polarimeter acquire run`; the
/// command's JSON. `on_event` is called with each event's JSON text.
#[pyfunction]
#[pyo3(signature = (plan, out=None, *, simulate=false, rig=None, on_event=None))]
pub fn run_plan(
    py: Python<'_>,
    plan: PathBuf,
    out: Option<PathBuf>,
    simulate: bool,
    rig: Option<PathBuf>,
    on_event: Option<Py<PyAny>>,
) -> PyResult<String> {
    let flags = HardwareFlags {
        rig,
        ..HardwareFlags::default()
    };
    let (hardware, rig) = flags.hardware().map_err(value_error)?;
    if simulate == hardware.is_some() {
        return Err(value_error(
            "give either simulate=True or the hardware's rig file (rig=PATH)",
        ));
    }
    polar_cli::logging::init(0);
    let (result, raised) = py.detach(|| {
        with_hooks(on_event, |ui| {
            run_cmd(&plan, hardware, rig.as_ref(), out, ui).map_err(|e| e.to_string())
        })
    });
    finish(result, raised)
}

/// Continues a paused or interrupted run, as `polarimeter acquire resume`; the command's
/// JSON.
#[pyfunction]
#[pyo3(signature = (run_dir, *, on_event=None))]
pub fn resume_run(
    py: Python<'_>,
    run_dir: PathBuf,
    on_event: Option<Py<PyAny>>,
) -> PyResult<String> {
    polar_cli::logging::init(0);
    let (result, raised) = py.detach(|| {
        with_hooks(on_event, |ui| {
            resume_cmd(&run_dir, None, None, ui).map_err(|e| e.to_string())
        })
    });
    finish(result, raised)
}
