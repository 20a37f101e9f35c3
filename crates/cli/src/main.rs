//! `polarimeter`: the instrument controller's command line, grouped by what the user is doing:
//!
//! * `model`: evaluate the analytical model (one call, or a JSON-lines batch);
//! * `plan`: analyzer angles, integration time and a forecast (`plan scene`, `plan angles`), and
//!   a plan file's forecast without running it (`plan check`);
//! * `acquire`: runs on simulated or real devices (`run`, `resume`, `check`, `demo`, `export`);
//!   `demo` is also at the top, as the quick start;
//! * `devices`: list the serial ports and cameras, one command to a stage or wheel (`devices
//!   stage`) or to a camera (`devices camera`);
//! * `simulate`: a simulated stage on a pseudo-terminal, or a camera's photon-transfer series;
//! * `analyze`: offline analysis of a recorded image stack (APTD);
//! * `calibrate`: the camera's noise from frames (EMVA 1288);
//! * `report`: figures, the validation report and Meng (2012)'s trade studies;
//! * `station`: an unattended station (`station serve`), its keys and its client;
//! * `bench`: speed against error of the model, the planner, the device links and the runs, and
//!   the fault and crash campaigns.
//!
//! The names of the flat tree (`run`, `resume`, `check`, `export`, `stage`, `camera`, `sim`,
//! `study`, `plan aptd`, `plan --scene ...`) still resolve, hidden from the help.
//!
//! This file holds the root of the tree; each group's arguments and dispatch live in `tree/`.

mod tree;

use clap::error::ErrorKind;
use clap::{Parser, Subcommand};
use std::process::ExitCode;
use tree::{acquire, analyze, bench, calibrate, devices, model, plan, report, simulate, station};

/// Rotating-analyzer polarimetry: model, plan and run a division-of-time polarimeter.
#[derive(Debug, Parser)]
#[command(name = "polarimeter", version, about, propagate_version = true)]
struct Cli {
    /// More log on stderr (-v info, -vv debug); every run also logs to RUN_DIR/run.log.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Evaluate the analytical model; JSON on stdout.
    Model(model::ModelGroup),
    /// Plan from the model: angles, integration time and a forecast for a scene and a camera
    /// (`plan scene`), optimal angles for given class statistics (`plan angles`), frames,
    /// exposure and speed for a spinning analyzer (`plan continuous`), a plan file's forecast
    /// (`plan check`).
    Plan(plan::PlanGroup),
    /// Acquisition runs on simulated or real devices: run a plan, resume it, check a run
    /// directory, the demo, export a run.
    Acquire(acquire::AcquireGroup),
    /// The quick start, the same as `acquire demo`: a short adaptive acquisition on simulated
    /// devices (no hardware); writes ./demo-run/ and says what happened.
    Demo(acquire::DemoArgs),
    /// The devices: list the serial ports and cameras, one command to a rotation stage or filter
    /// wheel, one command to a camera.
    Devices(devices::DevicesGroup),
    /// Simulated devices and data: a stage or wheel on a pseudo-terminal, a camera's
    /// photon-transfer series.
    #[command(alias = "sim")]
    Simulate(simulate::SimulateGroup),
    /// Offline analysis of recorded frames: APTD over an image stack.
    Analyze(analyze::AnalyzeGroup),
    /// Camera calibration from frames: the noise (EMVA 1288).
    Calibrate(calibrate::CalibrateGroup),
    /// Reports that write files: Meng (2012)'s figures, the validation report of the DoLP/AoP
    /// statistics, the trade studies.
    Report(report::ReportGroup),
    /// Benchmarks and campaigns: speed against error of the model, the planner, the device links
    /// and the runs; the seeded fault and crash campaigns.
    Bench(bench::BenchGroup),
    /// An unattended station: a persistent plan queue on a rig file, a secure HTTP API, a
    /// history, health, and the run a power cut interrupted resumed on start; its keys and
    /// its client.
    Station(station::StationGroup),
    /// The same as `acquire run`.
    #[command(hide = true)]
    Run(acquire::RunArgs),
    /// The same as `acquire resume`.
    #[command(hide = true)]
    Resume(acquire::ResumeArgs),
    /// The same as `acquire check`.
    #[command(hide = true)]
    Check(acquire::CheckArgs),
    /// The same as `acquire export`.
    #[command(hide = true)]
    Export(acquire::ExportGroup),
    /// The same as `devices stage`.
    #[command(hide = true)]
    Stage(devices::StageArgs),
    /// The same as `devices camera`.
    #[command(hide = true)]
    Camera(devices::CameraArgs),
    /// The same as `report study`.
    #[command(hide = true)]
    Study(report::StudyCmd),
}

impl Command {
    fn run(self) -> ExitCode {
        match self {
            Command::Model(g) => g.run(),
            Command::Plan(g) => g.run(),
            Command::Acquire(g) => g.run(),
            Command::Demo(a) => a.run(),
            Command::Devices(g) => g.run(),
            Command::Simulate(g) => g.run(),
            Command::Analyze(g) => g.run(),
            Command::Calibrate(g) => g.run(),
            Command::Report(g) => g.run(),
            Command::Bench(g) => g.run(),
            Command::Station(g) => g.run(),
            Command::Run(a) => a.run(),
            Command::Resume(a) => a.run(),
            Command::Check(a) => a.run(),
            Command::Export(g) => g.run(),
            Command::Stage(a) => a.run(),
            Command::Camera(a) => a.run(),
            Command::Study(a) => a.run(),
        }
    }
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse_from(tree::errors::argv()) {
        Ok(cli) => cli,
        Err(e)
            if matches!(
                e.kind(),
                ErrorKind::DisplayHelp
                    | ErrorKind::DisplayVersion
                    | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
            ) =>
        {
            let _ = e.print();
            return if e.kind() == ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand {
                ExitCode::from(2)
            } else {
                ExitCode::SUCCESS
            };
        }
        Err(e) => {
            eprintln!("{}", tree::errors::one_line_error(&e));
            return ExitCode::from(2);
        }
    };
    polar_cli::logging::init(cli.verbose);
    cli.command.run()
}
