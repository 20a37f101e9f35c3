//! `analyze`: offline analysis of recorded frames: `analyze aptd`, adaptive polarimetric target
//! detection over an image stack.

use super::output::print_json;
use clap::{Args, Subcommand};
use polar_cli::plan::{self, PlanAptdArgs};
use std::process::ExitCode;

/// `analyze`: its subcommands.
#[derive(Debug, Args)]
pub struct AnalyzeGroup {
    #[command(subcommand)]
    command: AnalyzeCommand,
}

#[derive(Debug, Subcommand)]
enum AnalyzeCommand {
    /// APTD offline over an image stack (`frames.csv`: file,angle_deg; 16-bit TIFFs): the sets
    /// it chooses among the stack's angles, its decisions, and RX and matched-filter detection
    /// on the final Stokes image.
    Aptd(AptdArgs),
}

impl AnalyzeGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            AnalyzeCommand::Aptd(a) => a.run(),
        }
    }
}

/// `analyze aptd`.
#[derive(Debug, Args)]
pub struct AptdArgs {
    #[command(flatten)]
    args: PlanAptdArgs,
}

impl AptdArgs {
    /// Runs APTD over the stack; prints its JSON.
    pub fn run(self) -> ExitCode {
        print_json(plan::aptd_offline(&self.args))
    }
}
