//! Library half of the `polarimeter` command: the model subcommands, the JSON-lines batch mode
//! and the report figures, kept out of `main.rs` so benchmarks and tests can call them.
#![warn(missing_docs)]

pub mod acquire;
pub mod batch;
pub mod bench;
pub mod bench_continuous;
pub mod bench_crash;
pub mod bench_serial;
pub mod bench_stats;
pub mod calibrate;
pub mod camera;
pub mod commands;
pub mod count_arg;
pub mod devices;
pub mod figures;
pub mod file_keys;
pub mod logging;
pub mod plan;
pub mod plan_continuous;
pub mod plan_load;
pub mod plan_problem;
pub mod plan_scene;
mod plot;
pub mod rig;
pub mod station_runner;
pub mod study;
pub mod study_aptd;
pub mod study_files;
pub mod study_fov;
pub mod study_scr;
pub mod validation;
