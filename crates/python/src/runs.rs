//! Runs from Python: `acquire run` and `acquire resume` through the CLI's own functions, with
//! the run's events passed to a Python callable and Python's Ctrl-C (a pending
//! `KeyboardInterrupt`) pausing the run at its next safe point (a second: at once; a third:
//! leaving it), after which the `KeyboardInterrupt` is raised with the run directory to
//! resume. One run at a time per process.

use crate::errors::value_error;
use polar_cli::acquire::{event_json, resume_cmd, run_cmd, RunHooks, Ui};
use polar_engine::run::Event;
use polar_rig::flags::HardwareFlags;
use pyo3::exceptions::PyKeyboardInterrupt;
use pyo3::prelude::*;
use serde_json::Value;
use std::cell::{Cell, RefCell};
use std::path::PathBuf;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, Ordering};

/// The hooks of one run: the caller's callable (given each event as JSON text), the first
/// Python exception seen (a `KeyboardInterrupt`, or what the callable raised), which asks
/// the run to pause, and how many were seen (each more acts as one more Ctrl-C).
struct PyHooks {
    on_event: Option<Py<PyAny>>,
    raised: RefCell<Option<PyErr>>,
    interrupts: Cell<u32>,
}

impl PyHooks {
    fn record(&self, e: PyErr) {
        self.interrupts.set(self.interrupts.get() + 1);
        let mut raised = self.raised.borrow_mut();
        if raised.is_none() {
            *raised = Some(e);
        }
    }
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
            self.record(e);
        }
    }

    fn interrupts(&self) -> u32 {
        // Python runs its signal handlers here (this is the thread that called `run`; on the
        // main thread a Ctrl-C becomes a KeyboardInterrupt).
        if let Err(e) = Python::attach(|py| py.check_signals()) {
            self.record(e);
        }
        self.interrupts.get()
    }
}

/// What ran: the command's JSON, or the exception raised meanwhile (a `KeyboardInterrupt`
/// saying where the run stands and how to continue it; the callable's own exception with the
/// run directory as its `run_dir` attribute).
fn finish(result: Result<(Value, i32), String>, raised: Option<PyErr>) -> PyResult<String> {
    let Some(e) = raised else {
        return result.map(|(v, _)| v.to_string()).map_err(value_error);
    };
    let value = match result {
        Ok((v, _)) => v,
        // The run failed while the caller was interrupting it: the caller's exception, with
        // the failure as its cause.
        Err(message) => {
            return Python::attach(|py| {
                e.set_cause(py, Some(value_error(message)));
                Err(e)
            })
        }
    };
    let dir = value["run_dir"].as_str().unwrap_or("").to_string();
    Python::attach(|py| {
        if !e.is_instance_of::<PyKeyboardInterrupt>(py) {
            let _ = e.value(py).setattr("run_dir", &dir);
            return Err(e);
        }
        let said = match value["state"].as_str() {
            Some("paused") => {
                format!("the run paused at a safe point; polarimeter.resume({dir:?}) continues it")
            }
            Some("done") => format!("the run had finished before it could pause: {dir}"),
            Some(other) => format!("the run ended {other}: {dir}"),
            None => format!("the run stopped: {dir}"),
        };
        let err = PyKeyboardInterrupt::new_err(said);
        let _ = err.value(py).setattr("run_dir", &dir);
        Err(err)
    })
}

/// Whether a run is going in this process: the run log (`run.log`) is one per process, so a
/// second run at once is refused.
static RUNNING: AtomicBool = AtomicBool::new(false);

/// Clears [`RUNNING`] when the run ends, however it ends.
struct Running;

impl Running {
    fn claim() -> PyResult<Running> {
        if RUNNING.swap(true, Ordering::SeqCst) {
            return Err(value_error(
                "a run is already going in this process (one at a time: each run logs to its \
                 own run.log); wait for it, or run the other in another process",
            ));
        }
        Ok(Running)
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        RUNNING.store(false, Ordering::SeqCst);
    }
}

/// Runs `command` with an unattended UI whose hooks call `on_event` and watch for Ctrl-C (on
/// this thread, inside the GIL's release); its result and the exception raised meanwhile.
fn with_hooks<T>(on_event: Option<Py<PyAny>>, command: impl FnOnce(Ui) -> T) -> (T, Option<PyErr>) {
    let hooks = Rc::new(PyHooks {
        on_event,
        raised: RefCell::new(None),
        interrupts: Cell::new(0),
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
    let _running = Running::claim()?;
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
    let _running = Running::claim()?;
    polar_cli::logging::init(0);
    let (result, raised) = py.detach(|| {
        with_hooks(on_event, |ui| {
            resume_cmd(&run_dir, None, None, ui).map_err(|e| e.to_string())
        })
    });
    finish(result, raised)
}
