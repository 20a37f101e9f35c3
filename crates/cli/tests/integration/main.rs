//! The CLI's integration tests, one test binary (as ripgrep's are): each module drives the
//! release `polarimeter` binary (or the library) the way a user does. One binary links once,
//! and its tests share the machine's threads as the modules' own tests did.

mod bad_inputs;
mod calibrate;
mod cli;
mod continuous_from_planner;
mod crash;
mod demo;
mod faults;
mod plan_aptd;
mod plan_check;
mod store_size;
mod study;
mod study_aptd;
mod study_fov;
mod study_scr;
mod tree;
mod validation;
