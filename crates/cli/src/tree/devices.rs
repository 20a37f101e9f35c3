//! `devices`: list the serial ports and cameras, one command to a rotation stage or filter wheel
//! (`devices stage`), one command to a camera (`devices camera`).

use super::output::{print_device, refused};
use clap::{Args, Subcommand};
use polar_cli::camera;
use polar_cli::devices::{self, StageAction};
use std::path::PathBuf;
use std::process::ExitCode;

/// `devices`: its subcommands.
#[derive(Debug, Args)]
pub struct DevicesGroup {
    #[command(subcommand)]
    command: DevicesCommand,
}

#[derive(Debug, Subcommand)]
enum DevicesCommand {
    /// Serial ports found, with their stable names (and simulated devices with --simulate).
    List(ListArgs),
    /// One command to a rotation stage or filter wheel.
    Stage(StageArgs),
    /// One command to a camera: `sim` (rendered from the model), `genicam:ID` or `v4l:NAME`
    /// (cargo features `genicam`, `v4l`), named by --camera or a rig file's [camera].
    Camera(CameraArgs),
}

impl DevicesGroup {
    /// Runs the subcommand; its exit status.
    pub fn run(self) -> ExitCode {
        match self.command {
            DevicesCommand::List(a) => a.run(),
            DevicesCommand::Stage(a) => a.run(),
            DevicesCommand::Camera(a) => a.run(),
        }
    }
}

/// `devices list`.
#[derive(Debug, Args)]
struct ListArgs {
    /// Also list the simulated devices running and on offer.
    #[arg(long)]
    simulate: bool,
    /// A rig file: identify its stage and look for its camera among those found.
    #[arg(long)]
    rig: Option<PathBuf>,
    /// Write a starting rig file (a new file) from what is found: the first port whose
    /// device identifies in a dialect of the registry, the first camera.
    #[arg(long)]
    write_rig: Option<PathBuf>,
    /// JSON output.
    #[arg(long)]
    json: bool,
}

impl ListArgs {
    fn run(self) -> ExitCode {
        print_device(
            devices::list_cmd(
                self.simulate,
                self.rig.as_deref(),
                self.write_rig.as_deref(),
            ),
            self.json,
        )
    }
}

/// `devices stage`: the device and one action.
#[derive(Debug, Args)]
pub struct StageArgs {
    /// A rig file: its [stage] (the flags below override its entries).
    #[arg(long)]
    rig: Option<PathBuf>,
    /// The serial port (prefer a stable /dev/serial/by-id/... path).
    #[arg(long)]
    port: Option<String>,
    /// The device's protocol.
    #[arg(long, value_parser = polar_rig::flags::dialect_values())]
    dialect: Option<String>,
    /// Bus address (Elliptec 0..=15, SMC100 1..=31); default the rig's, else the dialect's
    /// first.
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=31))]
    address: Option<u8>,
    /// JSON output.
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    action: StageCommand,
}

#[derive(Debug, Subcommand)]
enum StageCommand {
    /// Identify the device (without homing).
    Info,
    /// Home.
    Home,
    /// Move a rotator to an angle (the short way), verified by readback.
    Move {
        /// The angle, degrees.
        #[arg(long, allow_negative_numbers = true)]
        angle_deg: f64,
    },
    /// Select a wheel's or slider's slot (from 0), verified by readback.
    Slot {
        /// The slot, from 0.
        #[arg(long)]
        slot: usize,
    },
    /// Read the position.
    Position,
}

impl StageArgs {
    /// Sends the action to the stage; prints the reply.
    pub fn run(self) -> ExitCode {
        let action = match self.action {
            StageCommand::Info => StageAction::Info,
            StageCommand::Home => StageAction::Home,
            StageCommand::Move { angle_deg } => StageAction::Move { angle_deg },
            StageCommand::Slot { slot } => StageAction::Slot { slot },
            StageCommand::Position => StageAction::Position,
        };
        let target =
            devices::stage_target(self.rig.as_deref(), self.port, self.dialect, self.address);
        print_device(
            target.and_then(|(port, d, address)| devices::stage(&port, d, address, &action)),
            self.json,
        )
    }
}

/// `devices camera`: the camera and one action.
#[derive(Debug, Args)]
pub struct CameraArgs {
    /// The camera: sim, genicam:ID, v4l:NAME or uvc:BUS_OR_NAME (overrides the rig's).
    #[arg(long)]
    camera: Option<String>,
    /// A rig file: its [camera] (name and camera file).
    #[arg(long)]
    rig: Option<PathBuf>,
    /// Simulated camera: the scene file (default: the rooftop example plus a metal panel).
    #[arg(long)]
    scene: Option<PathBuf>,
    /// Simulated camera: the camera file (default: examples/cameras/cmos_modern.toml).
    #[arg(long)]
    camera_file: Option<PathBuf>,
    /// Simulated camera: the analyzer angle, degrees.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    analyzer_deg: f64,
    /// Simulated camera: sensor width, pixels, 1..=4096.
    #[arg(long, default_value_t = 320)]
    width: u32,
    /// Simulated camera: sensor height, pixels, 1..=4096.
    #[arg(long, default_value_t = 240)]
    height: u32,
    /// Simulated camera: seed of the texture and the noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    #[command(subcommand)]
    action: CameraCommand,
}

#[derive(Debug, Subcommand)]
enum CameraCommand {
    /// Grab frames into 16-bit TIFF files, each with a JSON sidecar of its metadata; prints a
    /// JSON summary.
    Grab(GrabArgs),
}

/// `devices camera grab`.
#[derive(Debug, Args)]
struct GrabArgs {
    /// Exposure, microseconds.
    #[arg(long)]
    exposure_us: f64,
    /// Gain, in the camera's unit (dB for the simulated camera).
    #[arg(long)]
    gain: Option<f64>,
    /// Frames, 1..=100000.
    #[arg(long, default_value_t = 1)]
    count: usize,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
    /// Deadline of each grab, seconds, (0, 3600].
    #[arg(long, default_value_t = 5.0)]
    deadline_s: f64,
}

impl CameraArgs {
    /// Runs the action on the camera; prints its JSON summary.
    pub fn run(self) -> ExitCode {
        let CameraCommand::Grab(grab) = self.action;
        let deadline_s = grab.deadline_s;
        if !(deadline_s > 0.0 && deadline_s <= 3600.0) {
            return refused(format!(
                "--deadline-s = {deadline_s} is out of range: allowed (0, 3600]"
            ));
        }
        let (camera, camera_file) =
            match camera::from_rig(self.rig.as_deref(), self.camera, self.camera_file) {
                Ok(c) => c,
                Err(e) => return refused(e),
            };
        let sim = camera::SimOptions {
            scene: self.scene,
            camera_file,
            analyzer_deg: self.analyzer_deg,
            width: self.width,
            height: self.height,
            seed: self.seed,
        };
        let opts = camera::GrabOptions {
            exposure_us: grab.exposure_us,
            gain: grab.gain,
            count: grab.count,
            out: grab.out,
            deadline: std::time::Duration::from_secs_f64(deadline_s),
        };
        let run = async {
            let mut cam = camera::open(&camera, &sim)?;
            camera::grab(&mut cam, &opts).await
        };
        let result = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .map(|rt| rt.block_on(run));
        match result {
            Ok(Ok(v)) => {
                println!("{v}");
                ExitCode::SUCCESS
            }
            Ok(Err(e)) => refused(e),
            Err(e) => {
                eprintln!("error: tokio runtime: {e}");
                ExitCode::FAILURE
            }
        }
    }
}
