//! `model`: evaluate the analytical model, one call from the flags or a JSON-lines batch; JSON on
//! stdout.

use super::output::{print_json, status};
use anyhow::Context;
use clap::{Args, Subcommand};
use polar_cli::batch::{self, Kind};
use polar_cli::commands::{self, DiffuseCache};
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::ExitCode;

/// `model`: its subcommands.
#[derive(Debug, Args)]
pub struct ModelGroup {
    #[command(subcommand)]
    command: ModelCommand,
}

/// Input for a model command: its flags, or `--batch FILE` (`-` for stdin) with one JSON object
/// per line whose keys are the flag names with underscores. Batch exit status: 0 if every line
/// succeeded, 1 if any line produced an error object (all lines are still processed).
#[derive(Debug, Subcommand)]
enum ModelCommand {
    /// Fresnel amplitudes rs, rp and reflectances Rs, Rp.
    Fresnel {
        #[command(flatten)]
        args: commands::FresnelArgs,
        /// JSON-lines input file, `-` for stdin (no other flag: each line gives its values).
        #[arg(long, conflicts_with = "FresnelArgs")]
        batch: Option<PathBuf>,
    },
    /// Polarimetric BRDF Mueller matrix (Meng (2012) Eqs. 3.4-3.19), sr^-1.
    Pbrdf {
        #[command(flatten)]
        args: commands::PbrdfArgs,
        /// JSON-lines input file, `-` for stdin (no other flag: each line gives its values).
        #[arg(long, conflicts_with = "PbrdfArgs")]
        batch: Option<PathBuf>,
    },
    /// Least-squares Stokes vector, DoLP and AoP from analyzer intensities.
    Stokes {
        #[command(flatten)]
        args: commands::StokesArgs,
        /// JSON-lines input file, `-` for stdin (no other flag: each line gives its values).
        #[arg(long, conflicts_with = "StokesArgs")]
        batch: Option<PathBuf>,
    },
    /// The sun's zenith and azimuth (NREL SPA) for a UTC time and site. Azimuth is clockwise from
    /// north (0 north, 90 east).
    Sun {
        #[command(flatten)]
        args: commands::SunArgs,
        /// JSON-lines input file, `-` for stdin (no other flag: each line gives its values).
        #[arg(long, conflicts_with = "SunArgs")]
        batch: Option<PathBuf>,
    },
    /// Sky Stokes radiance, DoLP and AoP of one sky direction (rayleigh, berry or a CSV table).
    /// Azimuths are clockwise from north; S1 > 0 is a horizontal E-vector.
    Sky {
        #[command(flatten)]
        args: commands::SkyArgs,
        /// JSON-lines input file, `-` for stdin (no other flag: each line gives its values).
        #[arg(long, conflicts_with = "SkyArgs")]
        batch: Option<PathBuf>,
    },
    /// Per-tile sun and view geometry of a sensor above flat ground (Meng (2012) Appendix A).
    /// Azimuths are clockwise from north; ground_m is [east, north] of the nadir point.
    Geometry {
        #[command(flatten)]
        args: commands::GeometryArgs,
        /// JSON-lines input file, `-` for stdin (no other flag: each line gives its values).
        #[arg(long, conflicts_with = "GeometryArgs")]
        batch: Option<PathBuf>,
    },
    /// Print a scene's band sky at the ground as a sky table (CSV: zenith_deg, azimuth_deg, S0,
    /// S1, S2 in W m^-2 sr^-1, S1 > 0 horizontal), the format `[sky] model = "table"` reads.
    /// Azimuths clockwise from north.
    SkyTable {
        /// The scene (TOML).
        #[arg(long)]
        scene: PathBuf,
        /// Grid step in zenith and azimuth, degrees, [1, 30] (Meng (2012)'s MODTRAN-P grid: 10).
        #[arg(long, default_value_t = 10.0)]
        step_deg: f64,
    },
    /// Print the built-in material library as TOML (save it, edit it, cite its sources).
    Materials,
    /// Mean Stokes radiance and covariance of each material of a TOML scene (examples/*.toml)
    /// over the field of view, to a tolerance, with the error estimate and the terms evaluated
    /// and skipped. Azimuths in the file are clockwise from north; output in the camera frame.
    Scene {
        #[command(flatten)]
        args: commands::SceneArgs,
    },
    /// Condition number, EWV, singular values and pseudo-inverse of an analyzer set.
    Polarimeter {
        #[command(flatten)]
        args: commands::PolarimeterArgs,
        /// JSON-lines input file, `-` for stdin (no other flag: each line gives its values).
        #[arg(long, conflicts_with = "PolarimeterArgs")]
        batch: Option<PathBuf>,
    },
    /// The N frames' mean and covariance (DN) for a scene radiance through a camera behind
    /// analyzers: EMVA 1288 linear camera, shot, dark, read and quantisation noise.
    Sensor {
        #[command(flatten)]
        args: commands::SensorArgs,
    },
    /// DoLP and AoP mean, spread and AoP bias of a Stokes estimate (integration at every
    /// polarised SNR, with its error estimate), with an optional Monte Carlo check.
    DolpStats {
        #[command(flatten)]
        args: commands::DolpStatsArgs,
    },
    /// Analytic ROC of a detector (matched filter, RX) for a target against a background:
    /// Pd at a Pfa, SCR and the curve.
    Roc {
        #[command(flatten)]
        args: commands::RocArgs,
    },
}

impl ModelGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        let result = match self.command {
            ModelCommand::Fresnel { batch: Some(p), .. } => run_batch(Kind::Fresnel, &p),
            ModelCommand::Fresnel { args, batch: None } => Ok(print_json(commands::fresnel(&args))),
            ModelCommand::Pbrdf { batch: Some(p), .. } => run_batch(Kind::Pbrdf, &p),
            ModelCommand::Pbrdf { args, batch: None } => Ok(print_json(commands::pbrdf(
                &args,
                &mut DiffuseCache::default(),
            ))),
            ModelCommand::Sun { batch: Some(p), .. } => run_batch(Kind::Sun, &p),
            ModelCommand::Sun { args, batch: None } => Ok(print_json(commands::sun(&args))),
            ModelCommand::Sky { batch: Some(p), .. } => run_batch(Kind::Sky, &p),
            ModelCommand::Sky { args, batch: None } => Ok(print_json(commands::sky(&args))),
            ModelCommand::SkyTable { scene, step_deg } => {
                match commands::sky_table_csv(&scene, step_deg) {
                    Ok(csv) => {
                        print!("{csv}");
                        Ok(ExitCode::SUCCESS)
                    }
                    Err(e) => {
                        eprintln!("error: {}", super::errors::user_error(&e));
                        Ok(ExitCode::from(2))
                    }
                }
            }
            ModelCommand::Geometry { batch: Some(p), .. } => run_batch(Kind::Geometry, &p),
            ModelCommand::Geometry { args, batch: None } => {
                Ok(print_json(commands::geometry(&args)))
            }
            ModelCommand::Materials => Ok(
                match polar_model::material::MaterialLibrary::builtin().to_toml_string() {
                    Ok(text) => {
                        print!("{text}");
                        ExitCode::SUCCESS
                    }
                    Err(e) => {
                        eprintln!("error: {e}");
                        ExitCode::FAILURE
                    }
                },
            ),
            ModelCommand::Scene { args } => Ok(print_json(commands::scene(&args))),
            ModelCommand::Stokes { batch: Some(p), .. } => run_batch(Kind::Stokes, &p),
            ModelCommand::Stokes { args, batch: None } => Ok(print_json(commands::stokes(&args))),
            ModelCommand::Polarimeter { batch: Some(p), .. } => run_batch(Kind::Polarimeter, &p),
            ModelCommand::Polarimeter { args, batch: None } => {
                Ok(print_json(commands::polarimeter(&args)))
            }
            ModelCommand::Roc { args } => Ok(print_json(commands::roc(&args))),
            ModelCommand::Sensor { args } => Ok(print_json(commands::sensor(&args))),
            ModelCommand::DolpStats { args } => Ok(print_json(commands::dolp_stats(&args))),
        };
        status(result)
    }
}

/// A JSON-lines batch of one model command: its results, one line each; exit status 1 when a
/// line failed.
fn run_batch(kind: Kind, path: &PathBuf) -> anyhow::Result<ExitCode> {
    let stdout = std::io::stdout().lock();
    let out = std::io::BufWriter::new(stdout);
    let input: Box<dyn BufRead> = if path.as_os_str() == "-" {
        Box::new(std::io::stdin().lock())
    } else {
        let f = std::fs::File::open(path)
            .with_context(|| format!("--batch {}: cannot open", path.display()))?;
        Box::new(BufReader::new(f))
    };
    let summary = batch::run(kind, input, out).context("batch I/O")?;
    if summary.errors > 0 {
        eprintln!(
            "polarimeter: {} of {} lines failed",
            summary.errors, summary.lines
        );
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}
