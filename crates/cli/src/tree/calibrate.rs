//! `calibrate`: camera calibration from frames: `calibrate noise` (EMVA 1288 photon transfer).

use super::output::print_json;
use clap::{Args, Subcommand};
use polar_cli::calibrate;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// `calibrate`: its subcommands.
#[derive(Debug, Args)]
pub struct CalibrateGroup {
    #[command(subcommand)]
    command: CalibrateCommand,
}

#[derive(Debug, Subcommand)]
enum CalibrateCommand {
    /// EMVA 1288 photon transfer from a frames directory (16-bit TIFFs and frames.csv: file,
    /// exposure_us, kind = dark|flat, optional photons_per_pixel): K, read noise, dark current,
    /// offset, saturation capacity and QE with uncertainties as JSON; writes
    /// photon_transfer.png, noise.toml and, with --base-camera, camera.toml.
    Noise(NoiseArgs),
}

impl CalibrateGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            CalibrateCommand::Noise(a) => a.run(),
        }
    }
}

/// `calibrate noise`.
#[derive(Debug, Args)]
struct NoiseArgs {
    /// The frames directory.
    #[arg(long)]
    frames: PathBuf,
    /// Output directory (default: the frames directory).
    #[arg(long)]
    out: Option<PathBuf>,
    /// A camera file whose detector fields the measurement replaces, written as camera.toml.
    #[arg(long)]
    base_camera: Option<PathBuf>,
    /// A rig file: its camera file is the base camera (unless --base-camera), and the
    /// measured camera file is written beside it as a new revision the rig then points to.
    #[arg(long)]
    rig: Option<PathBuf>,
}

impl NoiseArgs {
    fn run(self) -> ExitCode {
        print_json(calibrate_noise_cmd(
            calibrate::NoiseOptions {
                frames: self.frames,
                out: self.out,
                base_camera: self.base_camera,
            },
            self.rig.as_deref(),
        ))
    }
}

/// `calibrate noise [--rig RIG]`: [`calibrate::calibrate_noise`]; with a rig, its camera file is the base
/// camera (unless `--base-camera` names one), and the measured camera file is written beside
/// it as a new revision the rig then points to (`rig_written` in the output).
fn calibrate_noise_cmd(
    mut opts: calibrate::NoiseOptions,
    rig: Option<&Path>,
) -> Result<serde_json::Value, polar_cli::commands::CommandError> {
    use polar_cli::commands::CommandError;
    let rig = rig.map(polar_cli::rig::load).transpose()?;
    if let Some(r) = &rig {
        if opts.base_camera.is_none() {
            opts.base_camera = Some(r.camera_file.clone().ok_or_else(|| {
                CommandError::input(
                    "--rig",
                    format!(
                        " {}: camera.file is missing: the noise calibration needs a base camera \
                     (name it there, or give --base-camera)",
                        r.path.display()
                    ),
                )
            })?);
        }
    }
    let report = calibrate::calibrate_noise(&opts).map_err(CommandError::of)?;
    let mut v = report.to_json();
    if let Some(r) = &rig {
        let measured = opts
            .out
            .as_ref()
            .unwrap_or(&opts.frames)
            .join("camera.toml");
        v["rig_written"] = polar_cli::rig::record_camera_file(r, &measured)?;
    }
    Ok(v)
}
