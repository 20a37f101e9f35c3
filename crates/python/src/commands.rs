//! The CLI's document commands from Python: the planner (`plan angles`, `plan scene`,
//! `plan continuous`, `plan check`) and the model's scene, sky, sensor and statistics
//! commands, parsed from the same flags by the same `clap` definitions and evaluated by the
//! same functions, so a Python call and the command line give the same JSON.

use crate::errors::value_error;
use clap::{ArgMatches, Args, Command, FromArgMatches};
use polar_cli::commands::{self, CommandError};
use polar_cli::{acquire, plan, plan_continuous, plan_scene, rig};
use pyo3::prelude::*;
use serde_json::Value;
use std::path::PathBuf;

/// `plan check`'s flags: the plan file and an optional rig file.
#[derive(Debug, Clone, Args)]
struct PlanCheckArgs {
    /// The plan file.
    #[arg(long)]
    file: PathBuf,
    /// A rig file: its site (for a plan without one) and its camera file.
    #[arg(long)]
    rig: Option<PathBuf>,
}

/// Evaluates the command `name` (`plan_scene`, `model_dolp_stats`, ...; the CLI's words
/// joined by `_`) with `argv`, the CLI's flags; its JSON output. The GIL is released while
/// it runs.
#[pyfunction]
pub fn command(py: Python<'_>, name: &str, argv: Vec<String>) -> PyResult<String> {
    let out = py.detach(|| evaluate(name, argv));
    out.map(|v| v.to_string()).map_err(value_error)
}

/// Parses `argv` into `A` as the CLI would (the same flags, defaults and checks).
fn parse<A: Args + FromArgMatches>(argv: Vec<String>) -> Result<A, String> {
    let command = A::augment_args(Command::new("polarimeter").no_binary_name(true));
    let matches: ArgMatches = command.try_get_matches_from(argv).map_err(|e| {
        // clap's first paragraph names the flag and the problem; the usage after it is the
        // command line's, not Python's.
        let text = e.to_string();
        let first = text.split("\n\n").next().unwrap_or(&text);
        first.trim_start_matches("error: ").trim().to_string()
    })?;
    A::from_arg_matches(&matches).map_err(|e| e.to_string())
}

/// A command's result with its error as text.
fn text<T, E: std::fmt::Display>(r: Result<T, E>) -> Result<T, String> {
    r.map_err(|e| e.to_string())
}

fn evaluate(name: &str, argv: Vec<String>) -> Result<Value, String> {
    match name {
        "model_scene" => text(commands::scene(&parse(argv)?)),
        "model_sky" => text(commands::sky(&parse(argv)?)),
        "model_sensor" => text(commands::sensor(&parse(argv)?)),
        "model_dolp_stats" => text(commands::dolp_stats(&parse(argv)?)),
        "model_roc" => text(commands::roc(&parse(argv)?)),
        "model_polarimeter" => text(commands::polarimeter(&parse(argv)?)),
        "model_stokes" => text(commands::stokes(&parse(argv)?)),
        "model_geometry" => text(commands::geometry(&parse(argv)?)),
        "plan_angles" => text(plan::angles(&parse(argv)?)),
        "plan_scene" => text(plan_scene::scene_plan(&parse(argv)?)),
        "plan_continuous" => plan_continuous::plan(&parse(argv)?).map_err(|e| format!("{e:#}")),
        "plan_check" => {
            let a: PlanCheckArgs = parse(argv)?;
            let rig = a.rig.as_deref().map(rig::load).transpose();
            text(rig.and_then(|r| acquire::plan_check(&a.file, r.as_ref())))
        }
        other => Err(CommandError::failed(format!("no command {other:?}")).to_string()),
    }
}
