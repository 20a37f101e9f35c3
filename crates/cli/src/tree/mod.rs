//! The command tree's groups, one module each (its arguments and a `run` that dispatches them),
//! and what they share: how errors are worded and how results are printed.

pub mod acquire;
pub mod analyze;
pub mod bench;
pub mod calibrate;
pub mod devices;
pub mod errors;
pub mod model;
pub mod output;
pub mod plan;
pub mod report;
pub mod simulate;
pub mod station;
