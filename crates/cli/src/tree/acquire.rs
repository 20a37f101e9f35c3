//! `acquire`: runs on simulated or real devices: `run` a plan, `resume` a paused or crashed run,
//! `check` a run directory, the `demo`, `export` a run.

use super::output::{print_json, print_run, refused};
use clap::{Args, Subcommand};
use polar_cli::acquire::{self, Ui};
use polar_rig::flags::HardwareFlags;
use std::path::PathBuf;
use std::process::ExitCode;

/// `acquire`: its subcommands.
#[derive(Debug, Args)]
pub struct AcquireGroup {
    #[command(subcommand)]
    command: AcquireCommand,
}

#[derive(Debug, Subcommand)]
enum AcquireCommand {
    /// Run a plan (TOML or YAML) on simulated devices (--simulate) or on hardware (--rig FILE,
    /// or --port, --dialect, --camera, --camera-file; a flag overrides the rig's entry). Ctrl-C
    /// once pauses at the next safe point, twice at once. Prints a JSON summary; exit status 3
    /// when left paused (resume it later). With --rig, a calibrate-analyzer run writes its
    /// result to the rig as a new revision.
    Run(RunArgs),
    /// Continue a paused or crashed run from its journal, with no duplicate and no missing
    /// frame (hardware runs need --rig or the device flags again).
    Resume(ResumeArgs),
    /// Check a run directory: every frame the journal counts is stored intact (its hash as
    /// recorded), damaged frames are named (chunk file, frame, step), products are keyed by
    /// set. Prints JSON; exit status 1 when something is damaged. Changes nothing.
    Check(CheckArgs),
    /// A short adaptive acquisition on simulated devices (no hardware): the planner re-aims
    /// the analyzer at a painted panel on a rooftop; writes ./demo-run/ and says what happened.
    Demo(DemoArgs),
    /// Export a run for viewers.
    Export(ExportGroup),
}

impl AcquireGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            AcquireCommand::Run(a) => a.run(),
            AcquireCommand::Resume(a) => a.run(),
            AcquireCommand::Check(a) => a.run(),
            AcquireCommand::Demo(a) => a.run(),
            AcquireCommand::Export(g) => g.run(),
        }
    }
}

/// `acquire demo` (and the top-level `demo`).
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// The run directory (replaced if it holds an earlier demo).
    #[arg(long, default_value = "demo-run")]
    out: PathBuf,
    /// The simulated rotation stage: native (our firmware) or a simulated Thorlabs mount.
    #[arg(long, default_value_t = acquire::demo_stages()[0].to_string(),
          value_parser = clap::builder::PossibleValuesParser::new(acquire::demo_stages()))]
    stage: String,
}

impl DemoArgs {
    /// Runs the demo; prints what happened.
    pub fn run(self) -> ExitCode {
        match acquire::demo_on_stage(&self.out, &self.stage, Ui::terminal()) {
            Ok(text) => {
                print!("{text}");
                ExitCode::SUCCESS
            }
            Err(e) => refused(e),
        }
    }
}

/// `acquire run`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// The plan file.
    plan: PathBuf,
    /// Simulated devices (our stage on a pseudo-terminal, the model-rendered camera).
    #[arg(long)]
    simulate: bool,
    /// The run directory (default: ./run-NAME-UNIXTIME).
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    hardware: HardwareFlags,
}

impl RunArgs {
    /// Runs the plan; prints the run's JSON summary.
    pub fn run(self) -> ExitCode {
        let (hw, rig) = match self.hardware.hardware() {
            Ok(hw) => hw,
            Err(e) => return refused(e.to_string()),
        };
        if self.simulate == hw.is_some() {
            return refused(
                "give either --simulate or the hardware (--rig, or --port, --dialect, --camera, --camera-file)",
            );
        }
        print_run(
            acquire::run_cmd(&self.plan, hw, rig.as_ref(), self.out, Ui::terminal())
                .map_err(|e| e.in_plan_file(&self.plan)),
        )
    }
}

/// `acquire resume`.
#[derive(Debug, Args)]
pub struct ResumeArgs {
    /// The run directory.
    run_dir: PathBuf,
    #[command(flatten)]
    hardware: HardwareFlags,
}

impl ResumeArgs {
    /// Resumes the run; prints the run's JSON summary.
    pub fn run(self) -> ExitCode {
        let (hw, rig) = match self.hardware.hardware() {
            Ok(hw) => hw,
            Err(e) => return refused(e.to_string()),
        };
        print_run(acquire::resume_cmd(
            &self.run_dir,
            hw,
            rig.as_ref(),
            Ui::terminal(),
        ))
    }
}

/// `acquire check`.
#[derive(Debug, Args)]
pub struct CheckArgs {
    /// The run directory.
    run_dir: PathBuf,
}

impl CheckArgs {
    /// Checks the run directory; prints the finding as JSON.
    pub fn run(self) -> ExitCode {
        print_run(acquire::check_cmd(&self.run_dir))
    }
}

/// `acquire export`: its subcommands.
#[derive(Debug, Args)]
pub struct ExportGroup {
    #[command(subcommand)]
    command: ExportCommand,
}

#[derive(Debug, Subcommand)]
enum ExportCommand {
    /// Every frame as a 16-bit TIFF, every product as a 32-bit float TIFF, and frames.csv.
    Tiff(ExportTiffArgs),
}

impl ExportGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            ExportCommand::Tiff(a) => a.run(),
        }
    }
}

/// `acquire export tiff`.
#[derive(Debug, Args)]
struct ExportTiffArgs {
    /// The run directory.
    run_dir: PathBuf,
    /// Output directory (default: RUN_DIR/tiff).
    #[arg(long)]
    out: Option<PathBuf>,
}

impl ExportTiffArgs {
    fn run(self) -> ExitCode {
        print_json(acquire::export_tiff(&self.run_dir, self.out))
    }
}
