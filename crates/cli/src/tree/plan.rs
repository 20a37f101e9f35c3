//! `plan`: plan from the model: `plan scene` (angles, integration time and a forecast for a
//! scene and a camera), `plan angles` (optimal angles for given class statistics), `plan check`
//! (a plan file's forecast without running it), `plan continuous` (frames per half turn,
//! exposure and speed for a spinning analyzer), `plan schema` (every key of the files a user
//! writes).

use super::analyze::AptdArgs;
use super::output::print_json;
use clap::{Args, Subcommand};
use polar_cli::plan::{self, PlanAnglesArgs};
use polar_cli::plan_scene::{self, PlanSceneArgs};
use std::path::PathBuf;
use std::process::ExitCode;

/// `plan`: its subcommands.
#[derive(Debug, Args)]
pub struct PlanGroup {
    #[command(subcommand)]
    command: PlanCommand,
}

#[derive(Debug, Subcommand)]
enum PlanCommand {
    /// Angles, integration time and a forecast (SCR, Pd, DoLP sigma, saturation margin, frames,
    /// duration) for a target against a background in a scene, through a camera.
    Scene(SceneArgs),
    /// The SCR-optimal analyzer angles for a target against a background, with the SCR and
    /// matched-filter Pd of the conventional sets beside them.
    Angles(AnglesArgs),
    /// Validate a plan file (TOML or YAML) and print its forecast (frames, duration,
    /// predicted sigma per class) without running it.
    Check(CheckArgs),
    /// Continuous rotation: frames per half turn, exposure and speed within the camera's and
    /// the stage's limits, which limit binds, and a step-and-shoot set beside it.
    Continuous(ContinuousArgs),
    /// Every key of the files a user writes (plan, rig, scene, camera), generated from the
    /// parsers' own types: a JSON Schema, or with --markdown the reference docs/FILE-KEYS.md.
    Schema(SchemaArgs),
    /// The same as `analyze aptd`.
    #[command(hide = true)]
    Aptd(AptdArgs),
}

impl PlanGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            PlanCommand::Scene(a) => a.run(),
            PlanCommand::Angles(a) => a.run(),
            PlanCommand::Check(a) => a.run(),
            PlanCommand::Continuous(a) => a.run(),
            PlanCommand::Schema(a) => a.run(),
            PlanCommand::Aptd(a) => a.run(),
        }
    }
}

/// `plan scene`.
#[derive(Debug, Args)]
struct SceneArgs {
    #[command(flatten)]
    args: PlanSceneArgs,
}

impl SceneArgs {
    fn run(self) -> ExitCode {
        print_json(plan_scene::scene_plan(&self.args))
    }
}

/// `plan angles`.
#[derive(Debug, Args)]
struct AnglesArgs {
    #[command(flatten)]
    args: PlanAnglesArgs,
}

impl AnglesArgs {
    fn run(self) -> ExitCode {
        print_json(plan::angles(&self.args))
    }
}

/// `plan check`.
#[derive(Debug, Args)]
struct CheckArgs {
    /// The plan file.
    file: PathBuf,
    /// A rig file: its site (for a plan without one) and its camera file.
    #[arg(long)]
    rig: Option<PathBuf>,
}

impl CheckArgs {
    fn run(self) -> ExitCode {
        let file = self.file;
        print_json(
            self.rig
                .as_deref()
                .map(polar_cli::rig::load)
                .transpose()
                .and_then(|rig| polar_cli::acquire::plan_check(&file, rig.as_ref()))
                .map_err(|e| e.in_plan_file(&file)),
        )
    }
}

/// `plan schema`.
#[derive(Debug, Args)]
struct SchemaArgs {
    /// Which file's JSON Schema.
    #[arg(long, value_enum, default_value = "plan")]
    file: polar_cli::file_keys::UserFile,
    /// The Markdown reference of all four files (docs/FILE-KEYS.md) instead of a schema.
    #[arg(long)]
    markdown: bool,
}

impl SchemaArgs {
    fn run(self) -> ExitCode {
        if self.markdown {
            print!("{}", polar_cli::file_keys::file_keys_markdown());
        } else {
            let schema = self.file.schema();
            println!(
                "{}",
                serde_json::to_string_pretty(&schema).unwrap_or_else(|e| format!("{e}"))
            );
        }
        ExitCode::SUCCESS
    }
}

/// `plan continuous`.
#[derive(Debug, Args)]
struct ContinuousArgs {
    #[command(flatten)]
    args: polar_cli::plan_continuous::PlanContinuousArgs,
}

impl ContinuousArgs {
    fn run(self) -> ExitCode {
        match polar_cli::plan_continuous::run(&self.args) {
            Ok(out) => {
                print!("{out}");
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("error: {e:#}");
                ExitCode::from(2)
            }
        }
    }
}
