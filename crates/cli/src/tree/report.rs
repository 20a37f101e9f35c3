//! `report`: reports that write files: Meng (2012)'s figures (`report figures`), the validation
//! report of the DoLP/AoP statistics (`report validation`), the trade studies (`report study`).

use super::output::{print_files, status};
use clap::{Args, Subcommand};
use polar_cli::study::{StudyArgs, StudySelection};
use std::path::PathBuf;
use std::process::ExitCode;

/// `report`: its subcommands.
#[derive(Debug, Args)]
pub struct ReportGroup {
    #[command(subcommand)]
    command: ReportCommand,
}

#[derive(Debug, Subcommand)]
enum ReportCommand {
    /// Draw Meng (2012)'s Figs. 2.1, 3.6 and 3.7 analogues (PNG + CSV).
    Figures(FiguresArgs),
    /// Validate the analytic DoLP and AoP statistics against a seeded, parallel Monte Carlo of
    /// the whole sensor chain over a grid of states, angle sets and noise levels (Markdown).
    Validation(ValidationArgs),
    /// Meng (2012)'s trade studies (Ch. 4: sources, altitude, geometry, roughness, noise factor,
    /// integration time, field of view; Ch. 5: APTD, SCR): DoLP SNR and ROC of black paint and
    /// glass against asphalt; writes <kind>.csv, <kind>_roc.csv and <kind>.png.
    Study(StudyCmd),
}

impl ReportGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            ReportCommand::Figures(a) => a.run(),
            ReportCommand::Validation(a) => a.run(),
            ReportCommand::Study(a) => a.run(),
        }
    }
}

/// `report figures`.
#[derive(Debug, Args)]
struct FiguresArgs {
    /// Output directory.
    #[arg(long, default_value = "docs/figures")]
    out: PathBuf,
}

impl FiguresArgs {
    fn run(self) -> ExitCode {
        status(
            polar_cli::figures::draw_all(&self.out)
                .map(|files| {
                    for f in files {
                        println!("{}", f.display());
                    }
                    ExitCode::SUCCESS
                })
                .map_err(anyhow::Error::from),
        )
    }
}

/// `report validation`.
#[derive(Debug, Args)]
struct ValidationArgs {
    /// Output file.
    #[arg(long, default_value = "docs/VALIDATION.md")]
    out: PathBuf,
    /// Frame sets per grid point, 2..=10000000.
    #[arg(long, default_value_t = 20_000)]
    sets: usize,
    /// Seed of the run.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

impl ValidationArgs {
    fn run(self) -> ExitCode {
        let (out, sets, seed) = (self.out, self.sets, self.seed);
        let command = format!(
            "polarimeter report validation --out {} --sets {sets} --seed {seed}",
            out.display()
        );
        status(
            polar_cli::validation::write_report(&out, sets, seed, &command)
                .map(|rows| {
                    println!("{} ({} grid points)", out.display(), rows.len());
                    ExitCode::SUCCESS
                })
                .map_err(anyhow::Error::from),
        )
    }
}

/// `report study` (and the hidden top-level `study`).
#[derive(Debug, Args)]
pub struct StudyCmd {
    #[command(flatten)]
    args: StudyArgs,
}

impl StudyCmd {
    /// Runs the study; prints the files it wrote.
    pub fn run(self) -> ExitCode {
        if self.args.kind == StudySelection::Aptd {
            print_files(polar_cli::study_aptd::execute(&self.args))
        } else {
            print_files(polar_cli::study_files::execute(&self.args))
        }
    }
}
