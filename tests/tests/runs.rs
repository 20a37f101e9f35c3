//! Runs of every plan kind on the simulated rig (`polar_rig::simulated`), through the engine's
//! one entry point, one binary (`cargo test -p polar-hil-tests --test runs`). They live here,
//! above the engine, because they need the simulated rig, which sits above the engine:
//!
//! * [`runs::steps`]: every plan kind end to end on our firmware's simulated stage driven by
//!   its real driver, pause, resume, abort, detach and resume in a new rig, the suspender
//!   against a passing cloud.
//! * [`runs::crash_safety`]: interrupted, resumed and damaged runs stay whole datasets,
//!   checked from the outside (the journal, the store and zarr-python).
//! * [`runs::continuous`]: the span-row Stokes estimate on frames integrated along the
//!   analyzer's true path; trigger pulses against the simulated encoder.
//! * [`runs::continuous_timestamps`]: continuous rotation on the simulated K10CR1 with
//!   software triggers, spans against the simulator's true angle.
//! * [`runs::sim_stage`]: the plan's choice of simulated stage among the simulators' rotators.
//!
//! The engine's own tests (the store, the journal, the estimator) stay in its crate.

mod runs {
    pub mod common;
    pub mod continuous;
    pub mod continuous_timestamps;
    pub mod crash_safety;
    pub mod sim_stage;
    pub mod steps;
}
