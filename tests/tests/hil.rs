//! The workspace's hardware-in-the-loop tests, one binary (`cargo test -p polar-hil-tests`):
//!
//! * [`hil::dialects`]: every dialect of `polar_drivers::registry` against its simulator from
//!   `polar_hil_mocks::sim::SIMULATORS`, over a real pseudo-terminal, connected by its registry
//!   constructor: identify, home, move or select, read back, and the simulator's truth agrees.
//! * [`hil::doc_tables`]: ARCHITECTURE.md's and docs/DEVICES.md's tables of dialects and camera
//!   backends against the registries.
//! * [`hil::cameras`]: the camera backends' registry, and Aravis's fake GigE Vision camera opened
//!   through it (skipped, with the reason printed, where `arv-fake-gv-camera-0.8` is absent).
//! * [`hil::plans`]: a capture plan end to end on `examples/rigs/sim.toml` (the simulated stage on
//!   a pseudo-terminal, the camera rendering through the stage's true angle, its lens capped
//!   by the run for darks), and the operator's lens-cap pauses of a hardware camera resumed in
//!   new connections.
//! * [`hil::plan_kinds`]: time-lapse, adaptive, continuous, calibrate-analyzer (written back to
//!   a copy of the rig file) and calibrate-noise on the devices of `examples/rigs/sim.toml`,
//!   through the `run` command's entry point (small plans, `tests/fixtures/`).
//! * [`hil::following`]: the simulated camera behind a stage simulator served apart, following
//!   the positions it reports; a continuous plan on that pair refused.
//! * [`hil::k10cr1`]: a capture on `examples/rigs/sim_k10cr1.toml` (the simulated K10CR1 through
//!   the APT driver) through the `run` command's entry point; its Stokes products against the
//!   rendered truth.
//! * [`hil::pr50cc`]: the same capture on `examples/rigs/sim_pr50cc.toml` (the simulated
//!   SMC100CC with a PR50CC through the SMC100 driver).
//! * [`hil::standa_rig`]: the same capture on `examples/rigs/sim_8mpr16.toml` (the simulated
//!   8SMC5-USB with the 8MPR16-1 through the Standa driver, at the stage's real speeds).
//! * [`hil::apt_capture`]: a capture through the real APT driver on the simulated K10CR1 and
//!   PRM1Z8, the engine's run with the analyzer on an `AptRotator`; Stokes against the truth.
//! * [`hil::genicam_loop`]: Aravis's in-process fake GigE camera painting each frame from the
//!   simulated stage's true angle, the stage driven by its real driver; DoLP and AoP recovered.
//! * [`hil::conformance_elliptec`], [`hil::conformance_apt`], [`hil::conformance_smc100`],
//!   [`hil::conformance_standa`]: the
//!   public client libraries
//!   public client libraries (pylablib, thorlabs_elliptec, elliptec, thorlabs-apt-device,
//!   pystages, yaqd-newport, pylablib's Standa8SMC) against the simulated devices on
//!   pseudo-terminals, and Standa's libximc against its own virtual controller and the
//!   simulator, through `scripts/conformance/*.py` in the venv `POLARIMETER_PYTHON` names.
//!
//! Crate-level tests stay in their crates.

mod hil {
    pub mod apt_capture;
    pub mod cameras;
    pub mod conformance_apt;
    pub mod conformance_elliptec;
    pub mod conformance_smc100;
    pub mod conformance_standa;
    pub mod dialects;
    pub mod doc_tables;
    pub mod following;
    pub mod genicam_loop;
    pub mod k10cr1;
    pub mod plan_kinds;
    pub mod plans;
    pub mod pr50cc;
    pub mod standa_rig;
}
