//! `simulate`: simulated devices and data: a stage or wheel on a pseudo-terminal (`simulate
//! stage`), a camera's photon-transfer series for `calibrate noise` (`simulate
//! photon-transfer`).

use super::output::{print_json, refused};
use clap::{Args, Subcommand};
use polar_cli::{calibrate, devices};
use std::path::PathBuf;
use std::process::ExitCode;

/// `simulate`: its subcommands.
#[derive(Debug, Args)]
pub struct SimulateGroup {
    #[command(subcommand)]
    command: SimulateCommand,
}

#[derive(Debug, Subcommand)]
enum SimulateCommand {
    /// Start a simulated stage or wheel on a pseudo-terminal; prints {"port": PATH} and serves
    /// until stopped (Ctrl-C).
    Stage(StageArgs),
    /// Write a photon-transfer series of a camera (16-bit TIFF flats and darks, two each per
    /// exposure, from dark to past saturation, and frames.csv) for `calibrate noise`; prints
    /// the truth as JSON.
    #[command(alias = "frames")]
    PhotonTransfer(PhotonTransferArgs),
}

impl SimulateGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            SimulateCommand::Stage(a) => a.run(),
            SimulateCommand::PhotonTransfer(a) => a.run(),
        }
    }
}

/// `simulate stage`.
#[derive(Debug, Args)]
struct StageArgs {
    /// The protocol it speaks.
    #[arg(long, value_parser = polar_rig::flags::dialect_values())]
    dialect: String,
    /// The model (default: the dialect's first, as `devices list --simulate` lists them).
    #[arg(long)]
    model: Option<String>,
    /// Fault profile (TOML; see hil-mocks/src/faults.rs for the knobs).
    #[arg(long)]
    faults: Option<PathBuf>,
    /// Seed of every random choice (faults, noise, power-on position).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// A bus address a simulated controller answers at, repeatable for several controllers on
    /// one port (dialects on a bus, such as smc100 1..=31; default the dialect's first).
    #[arg(long = "address", value_name = "ADDRESS")]
    addresses: Vec<u8>,
}

impl StageArgs {
    fn run(self) -> ExitCode {
        let faults = match self.faults {
            Some(path) => devices::load_faults(&path),
            None => Ok(Default::default()),
        };
        let started = faults.and_then(|f| {
            devices::sim_stage(
                devices::dialect(&self.dialect)?,
                self.model.as_deref(),
                &self.addresses,
                f,
                self.seed,
            )
        });
        match started {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => refused(e),
        }
    }
}

/// `simulate photon-transfer`.
#[derive(Debug, Args)]
struct PhotonTransferArgs {
    /// The camera file (TOML, examples/cameras/).
    #[arg(long)]
    camera: PathBuf,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
    /// Frame width, pixels.
    #[arg(long, default_value_t = 512)]
    width: u32,
    /// Frame height, pixels.
    #[arg(long, default_value_t = 512)]
    height: u32,
    /// Exposure points up to --max-fill, 5..=1000 (six more near and past saturation).
    #[arg(long, default_value_t = 20)]
    exposures: usize,
    /// Mean signal of the last of those points, fraction of the saturation capacity.
    #[arg(long, default_value_t = 0.95)]
    max_fill: f64,
    /// Exposure time of that point, microseconds.
    #[arg(long, default_value_t = 1e6)]
    max_exposure_us: f64,
    /// Wavelength of the uniform illumination, nm (sets the QE from the camera's curve).
    #[arg(long, default_value_t = 550.0)]
    wavelength_nm: f64,
    /// PRNU pattern, rms relative gain, [0, 0.1].
    #[arg(long, default_value_t = 0.0)]
    prnu: f64,
    /// DSNU pattern, rms DN (whole DN per pixel), [0, 100].
    #[arg(long, default_value_t = 0.0)]
    dsnu_dn: f64,
    /// Leave frames.csv's photons_per_pixel empty (no QE).
    #[arg(long)]
    no_photons: bool,
    /// Seed of every random draw.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

impl PhotonTransferArgs {
    fn run(self) -> ExitCode {
        let opts = calibrate::SimFramesOptions {
            width: self.width,
            height: self.height,
            exposures: self.exposures,
            max_fill: self.max_fill,
            max_exposure_us: self.max_exposure_us,
            wavelength_nm: self.wavelength_nm,
            prnu: self.prnu,
            dsnu_dn: self.dsnu_dn,
            photons: !self.no_photons,
            seed: self.seed,
            ..calibrate::SimFramesOptions::new(self.camera, self.out)
        };
        print_json(calibrate::sim_frames(&opts).map(|s| s.to_json()))
    }
}
