//! `polarimeter`: the instrument controller's command line. Its commands:
//!
//! * `model`: evaluate the analytical model (one call, or a JSON-lines batch);
//! * `plan`: analyzer angles, integration time and a forecast from a scene and a camera; `plan
//!   angles`, `plan aptd` (offline over an image stack), `plan check` (a plan file's forecast);
//! * `demo`, `run`, `resume`, `export`: acquisition runs on simulated or real devices;
//! * `devices`, `stage`, `camera`: list the devices, and one command to a stage, wheel or camera;
//! * `sim`: a simulated stage on a pseudo-terminal, or a photon-transfer series of frames;
//! * `calibrate`: the camera's noise from frames (EMVA 1288);
//! * `report`: figures and the validation report; `study`: Meng (2012)'s Chapter 4 trade
//!   studies and APTD against conventional sets;
//! * `bench`: speed against error of the model, the planner, the device links and the runs.

use anyhow::Context;
use clap::error::{ContextKind, ContextValue, ErrorKind};
use clap::{Parser, Subcommand};
use polar_cli::batch::{self, Kind};
use polar_cli::calibrate;
use polar_cli::commands::{self, DiffuseCache};
use polar_cli::devices::{self, StageAction};
use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::ExitCode;

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

/// Real devices for `run` and `resume`: a rig file, flags, or both (a flag overrides the rig
/// file's entry, which overrides the default); without either, `run --simulate`.
#[derive(Debug, clap::Args)]
struct HardwareArgs {
    /// The rig file (TOML: [stage] dialect, port, address, model; [camera] backend, id, file;
    /// [site]; [analyzer]). The flags below override its entries.
    #[arg(long)]
    rig: Option<PathBuf>,
    /// The stage's serial port (prefer a stable /dev/serial/by-id/... path; `sim`: the
    /// dialect's simulator on a pseudo-terminal).
    #[arg(long)]
    port: Option<String>,
    /// The stage's protocol.
    #[arg(long, value_parser = devices::dialect_values())]
    dialect: Option<String>,
    /// Bus address (Elliptec 0..=15); default the rig's, else 0.
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=15))]
    address: Option<u8>,
    /// The camera: sim, genicam:ID, v4l:NAME or uvc:BUS_OR_NAME.
    #[arg(long)]
    camera: Option<String>,
    /// The camera's noise model (a calibrated camera file, e.g. from `calibrate noise`).
    #[arg(long)]
    camera_file: Option<PathBuf>,
    /// Stage angle at which the analyzer's axis is along the camera's x axis, degrees (from a
    /// calibrate-analyzer run); default the rig's, else 0.
    #[arg(long, allow_negative_numbers = true)]
    zero_offset_deg: Option<f64>,
}

impl HardwareArgs {
    /// The rig file (if given) and the hardware it and the flags describe;
    /// `--zero-offset-deg` is checked whether the devices are real or simulated.
    fn hardware(&self) -> Result<(Option<polar_rig::Hardware>, Option<polar_rig::Rig>), String> {
        if let Some(z) = self.zero_offset_deg {
            if !(z.is_finite() && z.abs() <= 360.0) {
                return Err(format!(
                    "--zero-offset-deg = {} is out of range: allowed a finite angle in \
                     [-360, 360] degrees",
                    commands::compact(z)
                ));
            }
        }
        match &self.rig {
            Some(path) => {
                let rig = polar_cli::rig::load(path).map_err(|e| e.to_string())?;
                let hw = rig
                    .hardware(&polar_rig::Overrides {
                        port: self.port.clone(),
                        dialect: self.dialect.clone(),
                        address: self.address,
                        camera: self.camera.clone(),
                        camera_file: self.camera_file.clone(),
                        zero_offset_deg: self.zero_offset_deg,
                    })
                    .map_err(|e| e.to_string())?;
                Ok((hw, Some(rig)))
            }
            None => polar_rig::Hardware::from_flags(
                self.port.clone(),
                self.dialect.as_deref(),
                self.camera.clone(),
                self.camera_file.clone(),
                self.address.unwrap_or(0),
                self.zero_offset_deg.unwrap_or(0.0),
            )
            .map(|hw| (hw, None)),
        }
    }
}

#[derive(Debug, Subcommand)]
enum Command {
    /// A short adaptive acquisition on simulated devices (no hardware): the planner re-aims
    /// the analyzer at a painted panel on a rooftop; writes ./demo-run/ and says what happened.
    Demo {
        /// The run directory (replaced if it holds an earlier demo).
        #[arg(long, default_value = "demo-run")]
        out: PathBuf,
    },
    /// Run a plan (TOML or YAML) on simulated devices (--simulate) or on hardware (--rig FILE,
    /// or --port, --dialect, --camera, --camera-file; a flag overrides the rig's entry). Ctrl-C
    /// once pauses at the next safe point, twice at once. Prints a JSON summary; exit status 3
    /// when left paused (resume it later). With --rig, a calibrate-analyzer run writes its
    /// result to the rig as a new revision.
    Run {
        /// The plan file.
        plan: PathBuf,
        /// Simulated devices (our stage on a pseudo-terminal, the model-rendered camera).
        #[arg(long)]
        simulate: bool,
        /// The run directory (default: ./run-NAME-UNIXTIME).
        #[arg(long)]
        out: Option<PathBuf>,
        #[command(flatten)]
        hardware: HardwareArgs,
    },
    /// Continue a paused or crashed run from its journal, with no duplicate and no missing
    /// frame (hardware runs need --rig or the device flags again).
    Resume {
        /// The run directory.
        run_dir: PathBuf,
        #[command(flatten)]
        hardware: HardwareArgs,
    },
    /// Check a run directory: every frame the journal counts is stored intact (its hash as
    /// recorded), damaged frames are named (chunk file, frame, step), products are keyed by
    /// set. Prints JSON; exit status 1 when something is damaged. Changes nothing.
    Check {
        /// The run directory.
        run_dir: PathBuf,
    },
    /// Export a run for viewers.
    Export {
        #[command(subcommand)]
        command: ExportCommand,
    },
    /// One command to a camera: `sim` (rendered from the model), `genicam:ID` or `v4l:NAME`
    /// (cargo features `genicam`, `v4l`), named by --camera or a rig file's [camera].
    Camera {
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
    },
    /// Plan from the model; JSON on stdout. `plan --scene FILE --camera FILE --target M
    /// --background M`: angles, integration time and a forecast (SCR, Pd, DoLP sigma,
    /// saturation margin, frames, duration); `plan angles`: the optimal angles for given class
    /// statistics.
    #[command(args_conflicts_with_subcommands = true)]
    Plan {
        #[command(subcommand)]
        command: Option<PlanCommand>,
        #[command(flatten)]
        scene: polar_cli::plan::PlanSceneArgs,
    },
    /// Evaluate the analytical model; JSON on stdout.
    Model {
        #[command(subcommand)]
        command: ModelCommand,
    },
    /// Generate reports.
    Report {
        #[command(subcommand)]
        command: ReportCommand,
    },
    /// Speed against error of the model and of the device links.
    Bench {
        #[command(subcommand)]
        command: BenchCommand,
    },
    /// Serial ports and devices.
    Devices {
        #[command(subcommand)]
        command: DevicesCommand,
    },
    /// One command to a rotation stage or filter wheel.
    Stage {
        /// A rig file: its [stage] (the flags below override its entries).
        #[arg(long)]
        rig: Option<PathBuf>,
        /// The serial port (prefer a stable /dev/serial/by-id/... path).
        #[arg(long)]
        port: Option<String>,
        /// The device's protocol.
        #[arg(long, value_parser = devices::dialect_values())]
        dialect: Option<String>,
        /// Bus address (Elliptec 0..=15); default the rig's, else 0.
        #[arg(long, value_parser = clap::value_parser!(u8).range(0..=15))]
        address: Option<u8>,
        /// JSON output.
        #[arg(long, global = true)]
        json: bool,
        #[command(subcommand)]
        action: StageCommand,
    },
    /// Camera calibration from frames.
    Calibrate {
        #[command(subcommand)]
        command: CalibrateCommand,
    },
    /// Simulated devices.
    Sim {
        #[command(subcommand)]
        command: SimCommand,
    },
    /// Meng (2012)'s Ch. 4 trade studies (sources, altitude, geometry, roughness, noise factor,
    /// integration time): DoLP SNR and ROC of black paint and glass against asphalt; writes
    /// <kind>.csv, <kind>_roc.csv and <kind>.png.
    Study {
        #[command(flatten)]
        args: polar_cli::study::StudyArgs,
    },
}

#[derive(Debug, Subcommand)]
enum DevicesCommand {
    /// Serial ports found, with their stable names (and simulated devices with --simulate).
    List {
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
    },
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

#[derive(Debug, Subcommand)]
enum SimCommand {
    /// Start a simulated stage or wheel on a pseudo-terminal; prints {"port": PATH} and serves
    /// until stopped (Ctrl-C).
    Stage {
        /// The protocol it speaks.
        #[arg(long, value_parser = devices::dialect_values())]
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
    },
    /// Write a photon-transfer series of a camera (16-bit TIFF flats and darks, two each per
    /// exposure, from dark to past saturation, and frames.csv) for `calibrate noise`; prints
    /// the truth as JSON.
    Frames {
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
    },
}

#[derive(Debug, Subcommand)]
enum CalibrateCommand {
    /// EMVA 1288 photon transfer from a frames directory (16-bit TIFFs and frames.csv: file,
    /// exposure_us, kind = dark|flat, optional photons_per_pixel): K, read noise, dark current,
    /// offset, saturation capacity and QE with uncertainties as JSON; writes
    /// photon_transfer.png, noise.toml and, with --base-camera, camera.toml.
    Noise {
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
    },
}

#[derive(Debug, Subcommand)]
enum CameraCommand {
    /// Grab frames into 16-bit TIFF files, each with a JSON sidecar of its metadata; prints a
    /// JSON summary.
    Grab {
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
    },
}

#[derive(Debug, Subcommand)]
enum ExportCommand {
    /// Every frame as a 16-bit TIFF, every product as a 32-bit float TIFF, and frames.csv.
    Tiff {
        /// The run directory.
        run_dir: PathBuf,
        /// Output directory (default: RUN_DIR/tiff).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

#[derive(Debug, Subcommand)]
enum PlanCommand {
    /// Validate a plan file (TOML or YAML) and print its forecast (frames, duration,
    /// predicted sigma per class) without running it.
    Check {
        /// The plan file.
        file: PathBuf,
        /// A rig file: its site (for a plan without one) and its camera file.
        #[arg(long)]
        rig: Option<PathBuf>,
    },
    /// APTD offline over an image stack (`frames.csv`: file,angle_deg; 16-bit TIFFs): the sets
    /// it chooses among the stack's angles, its decisions, and RX and matched-filter detection
    /// on the final Stokes image.
    Aptd {
        #[command(flatten)]
        args: polar_cli::plan::PlanAptdArgs,
    },
    /// The SCR-optimal analyzer angles for a target against a background, with the SCR and
    /// matched-filter Pd of the conventional sets beside them.
    Angles {
        #[command(flatten)]
        args: polar_cli::plan::PlanAnglesArgs,
    },
}

#[derive(Debug, Subcommand)]
enum BenchCommand {
    /// A simulated capture's wall time against the device-bound ideal (the simulated moves
    /// and exposures alone). Prints Markdown.
    Run {
        /// Angle sets, 1..=1000.
        #[arg(long, default_value_t = 10)]
        sets: u32,
        /// Exposure, microseconds, [10, 1000000] (the rooftop scene saturates above ~600 us).
        #[arg(long, default_value_t = 250.0)]
        exposure_us: f64,
    },
    /// A seeded fault campaign on simulated devices: runs until at least N faults were
    /// injected; counts lost frames, silent corruption, pauses and resumes. Prints Markdown.
    Faults {
        /// Faults to inject at least, 1..=1000000.
        #[arg(long, default_value_t = 200)]
        faults: u64,
        /// Seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// The crash campaign: runs of every plan kind on the simulated devices killed (SIGKILL)
    /// and paused (Ctrl-C) at random moments, in runs and in resumes, resumed to the end, and
    /// each dataset checked (and by zarr-python with --python). Prints Markdown, or JSON.
    Crash {
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
        /// calibrate-analyzer); default all.
        #[arg(long, value_delimiter = ',')]
        kinds: Vec<String>,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// The planner's optimum (to 0.01 deg) beside an exhaustive 1-degree grid search, in the
    /// same run: times and SCRs. Prints a Markdown table.
    Planner {
        /// Largest number of channels, 1..=4 (the 1-degree grid grows as 180^N / N!).
        #[arg(long, default_value_t = 3)]
        max_channels: usize,
        /// Timing runs of the optimiser per row (median), 1..=1000.
        #[arg(long, default_value_t = 21)]
        runs: usize,
    },
    /// Command round trip through a pseudo-terminal against in memory and against the simulated
    /// device's wire time, for each dialect. Prints a Markdown table.
    Serial {
        /// Queries per row, 10..=100000.
        #[arg(long, default_value_t = 200)]
        queries: usize,
    },
    /// Time per scene evaluation and actual error against a reference computed in the same run,
    /// for the example scenes (bench, rooftop, airborne) at tolerances 1e-2 .. 1e-8. Prints a
    /// Markdown table.
    Scene {
        /// Tolerance of the reference, [1e-10, 1e-6].
        #[arg(long, default_value_t = 1e-9)]
        reference_tolerance: f64,
        /// Loosest and tightest tolerance exponents, e.g. 2,8 for 1e-2 .. 1e-8.
        #[arg(long, value_delimiter = ',', default_values_t = [2u32, 8])]
        exponents: Vec<u32>,
        /// Minimum timing runs per row.
        #[arg(long, default_value_t = 3)]
        min_runs: usize,
    },
    /// Speed against error of the analytic DoLP/AoP statistics (each order, each regime) and of
    /// the whole-chain Monte Carlo at 1e3 .. 1e6 sets, against a reference Monte Carlo computed
    /// in the same run; the Monte Carlo sets and time at equal error. Prints Markdown.
    Stats {
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
    },
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

#[derive(Debug, Subcommand)]
enum ReportCommand {
    /// Draw Meng (2012)'s Figs. 2.1, 3.6 and 3.7 analogues (PNG + CSV).
    Figures {
        /// Output directory.
        #[arg(long, default_value = "docs/figures")]
        out: PathBuf,
    },
    /// Validate the analytic DoLP and AoP statistics against a seeded, parallel Monte Carlo of
    /// the whole sensor chain over a grid of states, angle sets and noise levels (Markdown).
    Validation {
        /// Output file.
        #[arg(long, default_value = "docs/VALIDATION.md")]
        out: PathBuf,
        /// Frame sets per grid point, 2..=10000000.
        #[arg(long, default_value_t = 20_000)]
        sets: usize,
        /// Seed of the run.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

/// A clap parse error as one line naming the flag, the value (cut when long) and what is
/// allowed.
fn one_line_error(e: &clap::Error) -> String {
    let arg = match e.get(ContextKind::InvalidArg) {
        Some(ContextValue::String(s)) => s.clone(),
        _ => String::new(),
    };
    let value = match e.get(ContextKind::InvalidValue) {
        Some(ContextValue::String(s)) => s.clone(),
        _ => String::new(),
    };
    if e.kind() == ErrorKind::ArgumentConflict {
        let mut flags: Vec<String> = match e.get(ContextKind::PriorArg) {
            Some(ContextValue::String(s)) => vec![s.clone()],
            Some(ContextValue::Strings(v)) => v.clone(),
            _ => Vec::new(),
        };
        flags.insert(0, arg.clone());
        let flags: Vec<String> = flags
            .iter()
            .map(|f| f.split([' ', '=']).next().unwrap_or(f).to_string())
            .collect();
        if flags.iter().any(|f| f == "--batch") {
            let others: Vec<&str> = flags
                .iter()
                .filter(|f| *f != "--batch")
                .map(String::as_str)
                .collect();
            return format!(
                "error: --batch cannot be used with {}: each batch line gives its own values \
                 (allowed: --batch FILE alone, or the flags without --batch)",
                others.join(", ")
            );
        }
        return format!(
            "error: {} cannot be used with {} (see --help)",
            flags[0],
            flags[1..].join(", ")
        );
    }
    let field = arg
        .trim_start_matches('-')
        .split([' ', '<', '='])
        .next()
        .unwrap_or("")
        .replace('-', "_");
    let mut first = e
        .to_string()
        .lines()
        .next()
        .unwrap_or("invalid arguments")
        .to_string();
    let n = value.chars().count();
    if n > commands::ECHO_MAX {
        let head: String = value.chars().take(commands::ECHO_MAX).collect();
        first = first.replacen(&value, &format!("{head}… ({n} characters)"), 1);
    }
    match (batch::allowed(&field), value.is_empty()) {
        (Some(allowed), false) => format!(
            "error: {arg} = {} is invalid: allowed {allowed}",
            commands::echo(&value)
        ),
        (Some(allowed), true) => format!("{first}; allowed {allowed}"),
        (None, _) => format!("{first} (see --help)"),
    }
}

/// The long flags of the subcommand the command line names (`model fresnel`: `n`, `k`,
/// `theta-i-deg`, `batch`).
fn command_flags() -> Vec<String> {
    use clap::CommandFactory;
    let mut cmd = Cli::command();
    cmd.build();
    let mut current = &cmd;
    for arg in std::env::args_os().skip(1) {
        if let Some(sub) = arg.to_str().and_then(|a| current.find_subcommand(a)) {
            current = sub;
        }
    }
    current
        .get_arguments()
        .filter_map(|a| a.get_long().map(str::to_string))
        .collect()
}

/// A command's error as the user sees it: a leading field that is one of the command's flags
/// spelled as the flag (`theta_i_deg = 95` -> `--theta-i-deg = 95`), long echoed text cut and
/// long numbers compact.
fn user_error(message: &str) -> String {
    let message = commands::tidy(message);
    let end = message
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(message.len());
    let (token, rest) = message.split_at(end);
    let named = [" = ", " is ", " has ", " contains ", ": ", "["]
        .iter()
        .any(|p| rest.starts_with(p));
    let flag = token.replace('_', "-");
    if !token.is_empty() && named && command_flags().contains(&flag) {
        format!("--{flag}{rest}")
    } else {
        message
    }
}

/// An error about a plan file's contents (`plan field ...`, `plan PATH: ...`) names the file.
fn in_plan_file(file: &std::path::Path, e: commands::CommandError) -> commands::CommandError {
    match e.0.strip_prefix("plan ") {
        Some(rest) if !rest.starts_with("file ") => {
            let rest = rest.strip_prefix("field ").unwrap_or(rest);
            commands::CommandError(format!("plan {}: {rest}", file.display()))
        }
        _ => e,
    }
}

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

/// Prints the files a command wrote, one per line, and returns 0; or prints `error: ...` and
/// returns 2.
fn print_files<E: std::fmt::Display>(result: Result<Vec<PathBuf>, E>) -> ExitCode {
    match result {
        Ok(files) => {
            for f in files {
                println!("{}", f.display());
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", user_error(&e.to_string()));
            ExitCode::from(2)
        }
    }
}

/// Prints a command's JSON on stdout (and its `warnings` on stderr) and returns exit status 0,
/// or prints `error: ...` on stderr and returns 2.
/// `bench crash`: exit status 1 when a dataset failed a check.
fn bench_crash(
    kills_per_kind: u32,
    seed: u64,
    out: PathBuf,
    python: Option<String>,
    kinds: Vec<String>,
    json: bool,
) -> ExitCode {
    use polar_cli::bench_crash::{campaign, markdown, CrashConfig, PLANS};
    if !(1..=10_000).contains(&kills_per_kind) {
        eprintln!("error: --kills-per-kind {kills_per_kind} is out of range: allowed 1..=10000");
        return ExitCode::from(2);
    }
    if let Some(k) = kinds.iter().find(|k| !PLANS.iter().any(|(n, _)| n == k)) {
        let names: Vec<&str> = PLANS.iter().map(|p| p.0).collect();
        eprintln!("error: --kinds {k:?} is not a plan kind of the campaign: allowed {names:?}");
        return ExitCode::from(2);
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
        seed,
        binary,
        base: out,
        outside: python.map(|p| (p, script)),
        kinds,
    };
    match campaign(&cfg) {
        Ok(r) => {
            if json {
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
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

fn print_json<E: std::fmt::Display>(result: Result<serde_json::Value, E>) -> ExitCode {
    match result {
        Ok(v) => {
            if let Some(w) = v.get("warnings").and_then(|w| w.as_array()) {
                for warning in w {
                    eprintln!("warning: {}", warning.as_str().unwrap_or_default());
                }
            }
            let mut out = std::io::stdout().lock();
            let ok = serde_json::to_writer(&mut out, &v).is_ok() && writeln!(out).is_ok();
            if ok {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            }
        }
        Err(e) => {
            eprintln!("error: {}", user_error(&e.to_string()));
            ExitCode::from(2)
        }
    }
}

/// Prints a command's text report and returns 0, or prints `error: ...` and returns 2.
fn print_text(result: Result<String, polar_cli::commands::CommandError>) -> ExitCode {
    match result {
        Ok(text) => {
            print!("{text}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", user_error(&e.to_string()));
            ExitCode::from(2)
        }
    }
}

/// Prints a run's JSON and returns its exit status (0 done, 3 paused, 4 aborted), or prints
/// `error: ...` and returns 2.
fn print_run(
    result: Result<(serde_json::Value, i32), polar_cli::commands::CommandError>,
) -> ExitCode {
    match result {
        Ok((v, code)) => {
            println!("{v}");
            ExitCode::from(u8::try_from(code).unwrap_or(1))
        }
        Err(e) => {
            eprintln!("error: {}", user_error(&e.to_string()));
            ExitCode::from(2)
        }
    }
}

fn print_device(result: Result<serde_json::Value, devices::DevicesError>, json: bool) -> ExitCode {
    match result {
        Ok(v) => {
            if json {
                println!("{v}");
            } else {
                print!("{}", devices::text(&v));
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {}", user_error(&e.to_string()));
            ExitCode::from(2)
        }
    }
}

fn bench_scene(reference_tol: f64, exponents: &[u32], min_runs: usize) -> anyhow::Result<ExitCode> {
    if !(1e-10..=1e-6).contains(&reference_tol) {
        anyhow::bail!(
            "reference_tolerance = {reference_tol} is out of range: allowed [1e-10, 1e-6]"
        );
    }
    let (lo, hi) = match exponents {
        [a, b] if 1 <= *a && a <= b && *b <= 10 => (*a, *b),
        _ => anyhow::bail!(
            "exponents = {exponents:?} is invalid: allowed two integers 1 <= a <= b <= 10"
        ),
    };
    let tolerances: Vec<f64> = (lo..=hi).map(|e| 10f64.powi(-(e as i32))).collect();
    let rows = polar_cli::bench::scene(
        &polar_cli::bench::EXAMPLES,
        &tolerances,
        reference_tol,
        min_runs.max(1),
        std::time::Duration::from_millis(200),
    )?;
    print!(
        "{}",
        polar_cli::bench::markdown(&rows, reference_tol, polar_cli::bench::threads())
    );
    Ok(ExitCode::SUCCESS)
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
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
            eprintln!("{}", one_line_error(&e));
            return ExitCode::from(2);
        }
    };
    polar_cli::logging::init(cli.verbose);
    let result = match cli.command {
        Command::Demo { out } => {
            match polar_cli::acquire::demo(&out, polar_cli::acquire::Ui::terminal()) {
                Ok(text) => {
                    print!("{text}");
                    Ok(ExitCode::SUCCESS)
                }
                Err(e) => {
                    eprintln!("error: {e}");
                    Ok(ExitCode::from(2))
                }
            }
        }
        Command::Run {
            plan,
            simulate,
            out,
            hardware,
        } => {
            let (hw, rig) = match hardware.hardware() {
                Ok(hw) => hw,
                Err(e) => {
                    eprintln!("error: {e}");
                    return ExitCode::from(2);
                }
            };
            if simulate == hw.is_some() {
                eprintln!(
                    "error: give either --simulate or the hardware (--rig, or --port, --dialect, --camera, --camera-file)"
                );
                return ExitCode::from(2);
            }
            Ok(print_run(
                polar_cli::acquire::run_cmd(
                    &plan,
                    hw,
                    rig.as_ref(),
                    out,
                    polar_cli::acquire::Ui::terminal(),
                )
                .map_err(|e| in_plan_file(&plan, e)),
            ))
        }
        Command::Resume { run_dir, hardware } => {
            let (hw, rig) = match hardware.hardware() {
                Ok(hw) => hw,
                Err(e) => {
                    eprintln!("error: {e}");
                    return ExitCode::from(2);
                }
            };
            Ok(print_run(polar_cli::acquire::resume_cmd(
                &run_dir,
                hw,
                rig.as_ref(),
                polar_cli::acquire::Ui::terminal(),
            )))
        }
        Command::Check { run_dir } => Ok(print_run(polar_cli::acquire::check_cmd(&run_dir))),
        Command::Export {
            command: ExportCommand::Tiff { run_dir, out },
        } => Ok(print_json(polar_cli::acquire::export_tiff(&run_dir, out))),
        Command::Plan {
            command: Some(PlanCommand::Check { file, rig }),
            ..
        } => Ok(print_json(
            rig.as_deref()
                .map(polar_cli::rig::load)
                .transpose()
                .and_then(|rig| polar_cli::acquire::plan_check(&file, rig.as_ref()))
                .map_err(|e| in_plan_file(&file, e)),
        )),
        Command::Bench {
            command: BenchCommand::Run { sets, exposure_us },
        } => Ok(print_text(polar_cli::acquire::bench_run(sets, exposure_us))),
        Command::Bench {
            command:
                BenchCommand::Crash {
                    kills_per_kind,
                    seed,
                    out,
                    python,
                    kinds,
                    json,
                },
        } => Ok(bench_crash(kills_per_kind, seed, out, python, kinds, json)),
        Command::Bench {
            command: BenchCommand::Faults { faults, seed },
        } => Ok(print_text(polar_cli::acquire::bench_faults(faults, seed))),
        Command::Camera {
            camera,
            rig,
            scene,
            camera_file,
            analyzer_deg,
            width,
            height,
            seed,
            action:
                CameraCommand::Grab {
                    exposure_us,
                    gain,
                    count,
                    out,
                    deadline_s,
                },
        } => {
            if !(deadline_s > 0.0 && deadline_s <= 3600.0) {
                eprintln!("error: --deadline-s = {deadline_s} is out of range: allowed (0, 3600]");
                return ExitCode::from(2);
            }
            let (camera, camera_file) =
                match polar_cli::camera::from_rig(rig.as_deref(), camera, camera_file) {
                    Ok(c) => c,
                    Err(e) => {
                        eprintln!("error: {e}");
                        return ExitCode::from(2);
                    }
                };
            let sim = polar_cli::camera::SimOptions {
                scene,
                camera_file,
                analyzer_deg,
                width,
                height,
                seed,
            };
            let opts = polar_cli::camera::GrabOptions {
                exposure_us,
                gain,
                count,
                out,
                deadline: std::time::Duration::from_secs_f64(deadline_s),
            };
            let run = async {
                let mut cam = polar_cli::camera::open(&camera, &sim)?;
                polar_cli::camera::grab(&mut cam, &opts).await
            };
            let result = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()
                .context("tokio runtime")
                .map(|rt| rt.block_on(run));
            match result {
                Ok(Ok(v)) => {
                    println!("{v}");
                    Ok(ExitCode::SUCCESS)
                }
                Ok(Err(e)) => {
                    eprintln!("error: {e}");
                    Ok(ExitCode::from(2))
                }
                Err(e) => Err(e),
            }
        }
        Command::Plan {
            command: Some(PlanCommand::Angles { args }),
            ..
        } => Ok(print_json(polar_cli::plan::angles(&args))),
        Command::Plan {
            command: Some(PlanCommand::Aptd { args }),
            ..
        } => Ok(print_json(polar_cli::plan::aptd_offline(&args))),
        Command::Plan {
            command: None,
            scene,
        } => Ok(print_json(polar_cli::plan::scene_plan(&scene))),
        Command::Bench {
            command: BenchCommand::Planner { max_channels, runs },
        } => {
            if !(1..=4).contains(&max_channels) || !(1..=1000).contains(&runs) {
                eprintln!(
                    "error: max_channels = {max_channels} (allowed 1..=4), runs = {runs} (allowed 1..=1000)"
                );
                return ExitCode::from(2);
            }
            match polar_cli::plan::bench(max_channels, runs) {
                Ok(rows) => {
                    print!("{}", polar_cli::plan::markdown(&rows));
                    Ok(ExitCode::SUCCESS)
                }
                Err(e) => Err(anyhow::anyhow!("{e}")),
            }
        }
        Command::Model { command } => match command {
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
                        eprintln!("error: {}", e.0);
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
        },
        Command::Bench {
            command: BenchCommand::Serial { queries },
        } => {
            if !(10..=100_000).contains(&queries) {
                eprintln!("error: --queries = {queries} is out of range: allowed 10..=100000");
                return ExitCode::from(2);
            }
            match polar_cli::bench_serial::serial(queries) {
                Ok(rows) => {
                    print!("{}", polar_cli::bench_serial::markdown(&rows, queries));
                    Ok(ExitCode::SUCCESS)
                }
                Err(e) => Err(anyhow::anyhow!("{e}")),
            }
        }
        Command::Bench {
            command:
                BenchCommand::Scene {
                    reference_tolerance,
                    exponents,
                    min_runs,
                },
        } => bench_scene(reference_tolerance, &exponents, min_runs),
        Command::Bench {
            command:
                BenchCommand::Stats {
                    reference_sets,
                    max_exponent,
                    seed,
                    min_runs,
                    grid,
                    grid_samples,
                    out,
                },
        } => {
            let opt = polar_cli::bench_stats::BenchOptions {
                reference_sets,
                max_exponent,
                seed,
                min_runs,
            };
            if grid {
                use polar_cli::bench_stats::{grid_markdown, run_grid, write_grid_report};
                let mut command = format!(
                    "polarimeter bench stats --grid --grid-samples {grid_samples} --seed {seed}"
                );
                match out {
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
        Command::Devices {
            command:
                DevicesCommand::List {
                    simulate,
                    rig,
                    write_rig,
                    json,
                },
        } => Ok(print_device(
            devices::list_cmd(simulate, rig.as_deref(), write_rig.as_deref()),
            json,
        )),
        Command::Stage {
            rig,
            port,
            dialect,
            address,
            json,
            action,
        } => {
            let action = match action {
                StageCommand::Info => StageAction::Info,
                StageCommand::Home => StageAction::Home,
                StageCommand::Move { angle_deg } => StageAction::Move { angle_deg },
                StageCommand::Slot { slot } => StageAction::Slot { slot },
                StageCommand::Position => StageAction::Position,
            };
            let target = devices::stage_target(rig.as_deref(), port, dialect, address);
            Ok(print_device(
                target.and_then(|(port, d, address)| devices::stage(&port, d, address, &action)),
                json,
            ))
        }
        Command::Sim {
            command:
                SimCommand::Frames {
                    camera,
                    out,
                    width,
                    height,
                    exposures,
                    max_fill,
                    max_exposure_us,
                    wavelength_nm,
                    prnu,
                    dsnu_dn,
                    no_photons,
                    seed,
                },
        } => {
            let opts = calibrate::SimFramesOptions {
                width,
                height,
                exposures,
                max_fill,
                max_exposure_us,
                wavelength_nm,
                prnu,
                dsnu_dn,
                photons: !no_photons,
                seed,
                ..calibrate::SimFramesOptions::new(camera, out)
            };
            Ok(print_json(
                calibrate::sim_frames(&opts).map(|s| s.to_json()),
            ))
        }
        Command::Calibrate {
            command:
                CalibrateCommand::Noise {
                    frames,
                    out,
                    base_camera,
                    rig,
                },
        } => Ok(print_json(calibrate::calibrate_noise_cmd(
            calibrate::NoiseOptions {
                frames,
                out,
                base_camera,
            },
            rig.as_deref(),
        ))),
        Command::Sim {
            command:
                SimCommand::Stage {
                    dialect,
                    model,
                    faults,
                    seed,
                },
        } => {
            let faults = match faults {
                Some(path) => devices::load_faults(&path),
                None => Ok(Default::default()),
            };
            let started = faults.and_then(|f| {
                devices::sim_stage(devices::dialect(&dialect)?, model.as_deref(), f, seed)
            });
            match started {
                Ok(()) => Ok(ExitCode::SUCCESS),
                Err(e) => {
                    eprintln!("error: {e}");
                    Ok(ExitCode::from(2))
                }
            }
        }
        Command::Study { args } if args.kind == polar_cli::study::StudySelection::Aptd => {
            Ok(print_files(polar_cli::study_aptd::execute(&args)))
        }
        Command::Study { args } => Ok(print_files(polar_cli::study::execute(&args))),
        Command::Report {
            command: ReportCommand::Figures { out },
        } => polar_cli::figures::draw_all(&out)
            .map(|files| {
                for f in files {
                    println!("{}", f.display());
                }
                ExitCode::SUCCESS
            })
            .map_err(anyhow::Error::from),
        Command::Report {
            command: ReportCommand::Validation { out, sets, seed },
        } => {
            let command = format!(
                "polarimeter report validation --out {} --sets {sets} --seed {seed}",
                out.display()
            );
            polar_cli::validation::write_report(&out, sets, seed, &command)
                .map(|rows| {
                    println!("{} ({} grid points)", out.display(), rows.len());
                    ExitCode::SUCCESS
                })
                .map_err(anyhow::Error::from)
        }
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
