//! `bench`: speed against error of the model, the planner, the device links and the runs
//! (`scene`, `stats`, `planner`, `serial`, `run`), and the seeded reliability campaigns on
//! simulated devices (`faults`, `crash`).

use super::output::{print_text, refused, status};
use clap::{Args, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

/// `bench`: its subcommands.
#[derive(Debug, Args)]
pub struct BenchGroup {
    #[command(subcommand)]
    command: BenchCommand,
}

#[derive(Debug, Subcommand)]
enum BenchCommand {
    /// A simulated capture's wall time against the device-bound ideal (the simulated moves
    /// and exposures alone), Markdown; with --continuous, step-and-shoot against continuous
    /// rotation on the same simulated rig (sets per second, predicted sigma, products against
    /// the truth, the dim case's time to a DoLP sigma).
    Run(RunArgs),
    /// Time per scene evaluation and actual error against a reference computed in the same run,
    /// for the example scenes (bench, rooftop, airborne) at tolerances 1e-2 .. 1e-8. Prints a
    /// Markdown table.
    Scene(SceneArgs),
    /// Speed against error of the analytic DoLP/AoP statistics (each order, each regime) and of
    /// the whole-chain Monte Carlo at 1e3 .. 1e6 sets, against a reference Monte Carlo computed
    /// in the same run; the Monte Carlo sets and time at equal error. Prints Markdown.
    Stats(StatsArgs),
    /// The planner's optimum (to 0.01 deg) beside an exhaustive 1-degree grid search, in the
    /// same run: times and SCRs. Prints a Markdown table.
    Planner(PlannerArgs),
    /// Command round trip through a pseudo-terminal against in memory and against the simulated
    /// device's wire time, for each dialect. Prints a Markdown table.
    Serial(SerialArgs),
    /// Reliability: a seeded fault campaign on simulated devices: runs until at least N faults
    /// were injected; counts lost frames, silent corruption, pauses and resumes. Prints Markdown.
    Faults(FaultsArgs),
    /// Reliability: the crash campaign: runs of every plan kind on the simulated devices killed
    /// (SIGKILL) and paused (Ctrl-C) at random moments, in runs and in resumes, resumed to the
    /// end, and each dataset checked (and by zarr-python with --python). Prints Markdown, or
    /// JSON.
    Crash(CrashArgs),
}

impl BenchGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            BenchCommand::Run(a) => a.run(),
            BenchCommand::Scene(a) => status(a.run()),
            BenchCommand::Stats(a) => status(a.run()),
            BenchCommand::Planner(a) => a.run(),
            BenchCommand::Serial(a) => a.run(),
            BenchCommand::Faults(a) => a.run(),
            BenchCommand::Crash(a) => a.run(),
        }
    }
}

/// `bench run`.
#[derive(Debug, Args)]
struct RunArgs {
    #[command(flatten)]
    args: polar_cli::bench_continuous::BenchRunArgs,
}

impl RunArgs {
    fn run(self) -> ExitCode {
        print_text(
            polar_cli::bench_continuous::run(&self.args)
                .map_err(|e| polar_cli::commands::CommandError::failed(format!("{e:#}"))),
        )
    }
}

/// `bench faults`.
#[derive(Debug, Args)]
struct FaultsArgs {
    /// Faults to inject at least, 1..=1000000.
    #[arg(long, default_value_t = 200)]
    faults: u64,
    /// Seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

impl FaultsArgs {
    fn run(self) -> ExitCode {
        print_text(polar_cli::acquire::bench_faults(self.faults, self.seed))
    }
}

/// `bench crash`.
#[derive(Debug, Args)]
struct CrashArgs {
    /// SIGKILLs per plan kind, 1..=10000.
    #[arg(long, default_value_t = 20)]
    kills_per_kind: u32,
    /// Seed of the kill moments.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// An empty directory for the runs (kept as evidence).
    #[arg(long)]
    out: PathBuf,
    /// A Python with zarr, xarray and xxhash: each dataset is also checked from the
    /// outside by scripts/check_run.py.
    #[arg(long)]
    python: Option<String>,
    /// Plan kinds (capture, exposures, time-lapse, adaptive, calibrate-noise,
    /// calibrate-analyzer, continuous); default all.
    #[arg(long, value_delimiter = ',')]
    kinds: Vec<String>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

impl CrashArgs {
    /// The campaign; exit status 1 when a dataset failed a check.
    fn run(self) -> ExitCode {
        use polar_cli::bench_crash::{campaign, markdown, CrashConfig, PLANS};
        let kills_per_kind = self.kills_per_kind;
        if !(1..=10_000).contains(&kills_per_kind) {
            return refused(format!(
                "--kills-per-kind {kills_per_kind} is out of range: allowed 1..=10000"
            ));
        }
        if let Some(k) = self
            .kinds
            .iter()
            .find(|k| !PLANS.iter().any(|(n, _)| n == k))
        {
            let names: Vec<&str> = PLANS.iter().map(|p| p.0).collect();
            return refused(format!(
                "--kinds {k:?} is not a plan kind of the campaign: allowed {names:?}"
            ));
        }
        let binary = match std::env::current_exe() {
            Ok(b) => b,
            Err(e) => {
                eprintln!("error: cannot find this program's path: {e}");
                return ExitCode::FAILURE;
            }
        };
        let script = PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scripts/check_run.py"
        ));
        let cfg = CrashConfig {
            kills_per_kind,
            seed: self.seed,
            binary,
            base: self.out,
            outside: self.python.map(|p| (p, script)),
            kinds: self.kinds,
        };
        match campaign(&cfg) {
            Ok(r) => {
                if self.json {
                    println!("{}", serde_json::to_string(&r).unwrap_or_default());
                } else {
                    print!("{}", markdown(&r));
                }
                if r.passed == r.datasets && r.kinds.iter().all(|k| k.failures.is_empty()) {
                    ExitCode::SUCCESS
                } else {
                    ExitCode::FAILURE
                }
            }
            Err(e) => refused(e),
        }
    }
}

/// `bench planner`.
#[derive(Debug, Args)]
struct PlannerArgs {
    /// Largest number of channels, 1..=4 (the 1-degree grid grows as 180^N / N!).
    #[arg(long, default_value_t = 3)]
    max_channels: usize,
    /// Timing runs of the optimiser per row (median), 1..=1000.
    #[arg(long, default_value_t = 21)]
    runs: usize,
}

impl PlannerArgs {
    fn run(self) -> ExitCode {
        let (max_channels, runs) = (self.max_channels, self.runs);
        if !(1..=4).contains(&max_channels) || !(1..=1000).contains(&runs) {
            return refused(format!(
                "max_channels = {max_channels} (allowed 1..=4), runs = {runs} (allowed 1..=1000)"
            ));
        }
        match polar_cli::plan::bench(max_channels, runs) {
            Ok(rows) => {
                print!("{}", polar_cli::plan::markdown(&rows));
                ExitCode::SUCCESS
            }
            Err(e) => status(Err(anyhow::anyhow!("{e}"))),
        }
    }
}

/// `bench serial`.
#[derive(Debug, Args)]
struct SerialArgs {
    /// Queries per row, 10..=100000.
    #[arg(long, default_value_t = 200)]
    queries: usize,
}

impl SerialArgs {
    fn run(self) -> ExitCode {
        let queries = self.queries;
        if !(10..=100_000).contains(&queries) {
            return refused(format!(
                "--queries = {queries} is out of range: allowed 10..=100000"
            ));
        }
        match polar_cli::bench_serial::serial(queries) {
            Ok(rows) => {
                print!("{}", polar_cli::bench_serial::markdown(&rows, queries));
                ExitCode::SUCCESS
            }
            Err(e) => status(Err(anyhow::anyhow!("{e}"))),
        }
    }
}

/// `bench scene`.
#[derive(Debug, Args)]
struct SceneArgs {
    /// Tolerance of the reference, [1e-10, 1e-6].
    #[arg(long, default_value_t = 1e-9)]
    reference_tolerance: f64,
    /// Loosest and tightest tolerance exponents, e.g. 2,8 for 1e-2 .. 1e-8.
    #[arg(long, value_delimiter = ',', default_values_t = [2u32, 8])]
    exponents: Vec<u32>,
    /// Minimum timing runs per row.
    #[arg(long, default_value_t = 3)]
    min_runs: usize,
}

impl SceneArgs {
    fn run(self) -> anyhow::Result<ExitCode> {
        let reference_tol = self.reference_tolerance;
        if !(1e-10..=1e-6).contains(&reference_tol) {
            anyhow::bail!(
                "reference_tolerance = {reference_tol} is out of range: allowed [1e-10, 1e-6]"
            );
        }
        let exponents = &self.exponents;
        let (lo, hi) = match exponents[..] {
            [a, b] if 1 <= a && a <= b && b <= 10 => (a, b),
            _ => anyhow::bail!(
                "exponents = {exponents:?} is invalid: allowed two integers 1 <= a <= b <= 10"
            ),
        };
        let tolerances: Vec<f64> = (lo..=hi).map(|e| 10f64.powi(-(e as i32))).collect();
        let rows = polar_cli::bench::scene(
            &polar_cli::bench::EXAMPLES,
            &tolerances,
            reference_tol,
            self.min_runs.max(1),
            std::time::Duration::from_millis(200),
        )?;
        print!(
            "{}",
            polar_cli::bench::markdown(&rows, reference_tol, polar_cli::bench::threads())
        );
        Ok(ExitCode::SUCCESS)
    }
}

/// `bench stats`.
#[derive(Debug, Args)]
struct StatsArgs {
    /// Reference Monte Carlo frame sets per state, 10^max_exponent ..= 1e8.
    #[arg(long, default_value_t = 10_000_000)]
    reference_sets: usize,
    /// Largest Monte Carlo size, as a power of ten, 3..=7.
    #[arg(long, default_value_t = 6)]
    max_exponent: u32,
    /// Seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Minimum timing runs per Monte Carlo size.
    #[arg(long, default_value_t = 3)]
    min_runs: usize,
    /// Instead, the accuracy grid: DoLP/AoP statistics against a Stokes-level Monte Carlo
    /// over polarised SNR 0.5 .. 20, three analyzer sets, isotropic and anisotropic noise.
    #[arg(long)]
    grid: bool,
    /// Monte Carlo draws per state of `--grid`, 4e5 ..= 5e7.
    #[arg(long, default_value_t = 1_000_000)]
    grid_samples: usize,
    /// With `--grid`: write the report to this file (e.g.
    /// docs/validation/dolp-aop-grid.md) instead of stdout.
    #[arg(long, requires = "grid")]
    out: Option<PathBuf>,
}

impl StatsArgs {
    fn run(self) -> anyhow::Result<ExitCode> {
        let (seed, grid_samples) = (self.seed, self.grid_samples);
        let opt = polar_cli::bench_stats::BenchOptions {
            reference_sets: self.reference_sets,
            max_exponent: self.max_exponent,
            seed,
            min_runs: self.min_runs,
        };
        if self.grid {
            use polar_cli::bench_stats::{grid_markdown, run_grid, write_grid_report};
            let mut command = format!(
                "polarimeter bench stats --grid --grid-samples {grid_samples} --seed {seed}"
            );
            match self.out {
                Some(path) => {
                    command += &format!(" --out {}", path.display());
                    write_grid_report(&path, grid_samples, seed, &command).map(|rows| {
                        println!("{} ({} states)", path.display(), rows.len());
                        ExitCode::SUCCESS
                    })
                }
                None => run_grid(grid_samples, seed).map(|rows| {
                    print!("{}", grid_markdown(&rows, grid_samples, seed, &command));
                    ExitCode::SUCCESS
                }),
            }
        } else {
            polar_cli::bench_stats::states()
                .and_then(|s| polar_cli::bench_stats::run(&s, &opt))
                .map(|r| {
                    print!("{}", polar_cli::bench_stats::markdown(&r, &opt));
                    ExitCode::SUCCESS
                })
        }
        .map_err(anyhow::Error::from)
    }
}
