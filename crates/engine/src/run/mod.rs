//! A run: the state machine that turns a plan into stored frames and products.
//!
//! **States.** Running; pausing at the next safe point (between angle sets, or between
//! single frames outside sets); paused (with the reason: the user, a device error after the
//! plan's retries, a storage error, the suspender, a dark series that needs the lens capped);
//! aborting; done. [`Control::Pause`] asks for the next safe point; [`Control::PauseNow`]
//! cancels the device operation in flight (its step is taken again on resume);
//! [`Control::Resume`] continues a paused run; [`Control::Abort`] ends a paused or a running
//! run (a running one at once: the device operation in flight is cancelled);
//! [`Control::Detach`] (or dropping the controller) leaves the run to `polarimeter resume`.
//!
//! **Actors.** The analyzer and the camera are each owned by one task
//! ([`tokio::task::spawn_local`]) that takes commands from a bounded channel; nothing else
//! touches them. The storage thread owns the journal and the Zarr store, and computes the
//! products and the suspender's verdict of each set. The next move starts as soon as a frame
//! is grabbed, so it overlaps the frame's write, and the first move of the next set
//! overlaps the products of the last.
//!
//! **Durability.** A step counts when its frame's chunk is fsynced and its journal line is
//! flushed (`journal::Journal::append`). A crash loses at most the frame in flight; the
//! resumed run (a new process, [`run`] with `resume = true`) takes that step again, into the
//! same frame index, so there is no duplicate and no gap. At the end every planned step must
//! have exactly one accepted frame whose stored pixels hash to the journaled hash; anything
//! else is an error.
//!
//! **Suspender.** Every set is checked against the model before it counts: the mean reduced
//! chi-square of the per-pixel Malus fit (sets of 4 or more angles), the change of the mean S0
//! from the last accepted set (sets of 3), the analyzer's readback against the command, and
//! frames repeated bit for bit (a stuck camera). A failing set is recorded with the reason and
//! taken again, or pauses the run, as the plan says.

mod actors;
mod adaptive;
mod calibration;
mod clock;
mod core;
mod ending;
mod link;
mod outcome;
mod pause;
mod record;
pub(crate) mod rig;
mod run_dir;
mod spin_loop;
mod start;
mod step_loop;
mod step_ops;
pub mod timestamps;
mod writer;

pub use adaptive::replayed_decisions;
pub use link::{link, Control, Controller, Event, RunLink, RunState};
pub use outcome::{CameraStream, Outcome, RunError, Saturation, Summary, Verdict};
pub use pause::{CAP_LENS, UNCAP_LENS};
pub use rig::{Rig, SceneLight};
pub use run_dir::{default_run_dir, is_finished, noise_stream, plan_of, run_parts};
pub use spin_loop::{run_up_s, RUN_UP_S};
pub use start::run;
