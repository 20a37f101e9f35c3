//! What the window and the engine thread say to each other: the window's commands, the
//! engine's replies (events, products, device status, snapshots), the devices the GUI drives
//! and the live modes' settings.

use polar_engine::products::Products;
use polar_engine::run::{Control, Event, Outcome, RunState};
use polar_rig::Hardware;
use std::path::PathBuf;

/// Allowed spin speeds, degrees per second (the simulated native stage's limit is 2 turns/s).
pub const SPEED_RANGE_DEG_PER_S: (f64, f64) = (1.0, 720.0);

/// Allowed frames per half turn (3 are the fewest that determine S0, S1, S2).
pub const FRAMES_RANGE: (u32, u32) = (3, 180);

/// Which live mode runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LiveMode {
    /// The camera streams; the analyzer stays still.
    Camera,
    /// The analyzer spins; Stokes estimates every half turn.
    Polarimetry,
}

impl LiveMode {
    /// The mode's name in the panel.
    pub fn label(self) -> &'static str {
        match self {
            LiveMode::Camera => "Live",
            LiveMode::Polarimetry => "Live polarimetry",
        }
    }
}

/// How live polarimetry spins and exposes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpinSettings {
    /// The analyzer's speed, degrees per second.
    pub speed_deg_per_s: f64,
    /// Exposures per half turn.
    pub frames_per_half_turn: u32,
    /// The camera's trigger input is wired to the stage's position-compare output (the
    /// camera then exposes on the pulse itself; otherwise each exposure is triggered in
    /// software and placed in time by its exposure-end event).
    pub hardware_trigger: bool,
}

impl Default for SpinSettings {
    fn default() -> Self {
        SpinSettings {
            speed_deg_per_s: 180.0,
            frames_per_half_turn: 8,
            hardware_trigger: false,
        }
    }
}

impl SpinSettings {
    /// The time between two exposures, seconds.
    pub fn frame_interval_s(&self) -> f64 {
        180.0 / (f64::from(self.frames_per_half_turn) * self.speed_deg_per_s)
    }

    /// Checks the settings for an exposure of `exposure_us`: errors name the field, its
    /// value and the allowed range.
    pub fn check(&self, exposure_us: f64) -> Result<(), String> {
        let (lo, hi) = SPEED_RANGE_DEG_PER_S;
        if !(self.speed_deg_per_s.is_finite()
            && self.speed_deg_per_s >= lo
            && self.speed_deg_per_s <= hi)
        {
            return Err(format!(
                "speed_deg_per_s = {}: allowed [{lo}, {hi}] deg/s",
                self.speed_deg_per_s
            ));
        }
        let (flo, fhi) = FRAMES_RANGE;
        if !(flo..=fhi).contains(&self.frames_per_half_turn) {
            return Err(format!(
                "frames_per_half_turn = {}: allowed [{flo}, {fhi}]",
                self.frames_per_half_turn
            ));
        }
        // Half the interval is left for the readout and the next trigger.
        let max_us = 0.5 * self.frame_interval_s() * 1e6;
        if !(exposure_us.is_finite() && exposure_us > 0.0 && exposure_us <= max_us) {
            return Err(format!(
                "exposure_us = {exposure_us}: allowed (0, {max_us:.0}] us at {} deg/s and {} \
                 frames per half turn (half the time between frames)",
                self.speed_deg_per_s, self.frames_per_half_turn
            ));
        }
        Ok(())
    }
}

/// What the UI asks of the engine.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// Parse `plan_text` (TOML) and run it: on the connected devices if there are any (the run
    /// takes them over and releases them when it ends), else on a simulated rig started for it.
    Start {
        /// The plan, TOML.
        plan_text: String,
    },
    /// Connect the devices (the simulated rig of `plan_text`'s `[simulation]` section) and set
    /// the camera's exposure and gain.
    Connect {
        /// The plan, TOML.
        plan_text: String,
        /// The exposure to set, microseconds.
        exposure_us: f64,
        /// The gain to set.
        gain: f64,
    },
    /// Disconnect the devices (the simulated rig shuts down).
    Disconnect,
    /// Home the stage (identify, find the datum).
    Home,
    /// Turn the analyzer to `angle_deg` (from the camera's x axis, the stage's approach).
    MoveAnalyzer {
        /// The analyzer angle, degrees.
        angle_deg: f64,
    },
    /// Set the camera's exposure.
    SetExposure {
        /// Exposure, microseconds.
        exposure_us: f64,
    },
    /// Set the camera's gain (in the camera's unit).
    SetGain {
        /// Gain.
        gain: f64,
    },
    /// Take one frame with the current settings.
    Snapshot,
    /// Resolve the plans' relative paths (`simulation.scene`, `simulation.camera`) against
    /// this folder: the folder of the plan file opened in the editor.
    PlanDir(PathBuf),
    /// Pass a control to the run in progress.
    Control(Control),
    /// Parse `plan_text` and compute its forecast.
    Forecast {
        /// The plan, TOML.
        plan_text: String,
    },
    /// Start a live mode on the connected devices (see [`crate::live`]).
    LiveStart {
        /// Live camera or live polarimetry.
        mode: LiveMode,
        /// How live polarimetry spins and exposes.
        spin: SpinSettings,
    },
    /// Stop the live mode.
    LiveStop,
}

/// The latest products of a run, with the last stored raw frame.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveProducts {
    /// The product slot read.
    pub slot: u64,
    /// The set the slot holds (if known).
    pub set: Option<u64>,
    /// The ten product images.
    pub products: Products,
    /// The last stored frame (row-major, `width * height`), if it could be read.
    pub raw: Option<Vec<u16>>,
    /// That frame's index in the store (it may be a frame of the next set, or a dark).
    pub raw_index: Option<u64>,
}

/// The devices as the engine last saw them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DeviceStatus {
    /// The devices are connected (and idle: no run holds them).
    pub connected: bool,
    /// What is connected (stage and camera models), or why nothing is.
    pub description: String,
    /// The stage angle, degrees.
    pub stage_deg: Option<f64>,
    /// The analyzer angle the stage gives, degrees in [0, 180).
    pub analyzer_deg: Option<f64>,
    /// The exposure the camera applied, microseconds.
    pub exposure_us: Option<f64>,
    /// The gain the camera applied.
    pub gain: Option<f64>,
    /// The camera's exposure range, microseconds.
    pub exposure_range_us: Option<[f64; 2]>,
    /// The camera's gain range.
    pub gain_range: Option<[f64; 2]>,
    /// The last device error (cleared by the next command that succeeds).
    pub error: Option<String>,
    /// The last command carried out, for the log.
    pub last: String,
}

/// One frame taken from the device panel.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Pixels, DN, row-major.
    pub pixels: Vec<u16>,
    /// The exposure applied, microseconds.
    pub exposure_us: f64,
    /// The camera's frame id.
    pub frame_id: u64,
}

/// What the engine tells the UI.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// The devices' state after a device command.
    Devices(DeviceStatus),
    /// A frame from [`Command::Snapshot`].
    Snapshot(Box<Snapshot>),
    /// A run started into `run_dir`; it takes `planned` frames.
    Started {
        /// The run directory.
        run_dir: PathBuf,
        /// Frames planned (an adaptive plan: its budget).
        planned: u64,
    },
    /// The run's state (from its watch).
    State(RunState),
    /// An engine event.
    Event(Event),
    /// New products after an accepted set.
    Products(Box<LiveProducts>),
    /// The run ended.
    Finished(Result<Outcome, String>),
    /// A command could not be carried out (a bad plan, a rig that did not start).
    Error(String),
    /// A line for the log.
    Log(String),
    /// A forecast (text) or why there is none.
    Forecast(Result<String, String>),
    /// News from a live mode.
    Live(LiveUpdate),
}

/// The devices the GUI drives.
#[derive(Debug, Clone)]
pub enum Devices {
    /// The simulated rig of each plan's `[simulation]` section (our stage's firmware on a
    /// pseudo-terminal, the model-rendered camera).
    Simulated,
    /// Real devices, as `polarimeter run --rig FILE` or `--port ... --dialect ... --camera ...
    /// --camera-file` (`polar_rig`).
    Hardware(Box<Hardware>),
}

/// A frame's histogram and saturation.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameStats {
    /// Counts over `[0, full_scale_dn]` in [`crate::live::LIVE_HIST_BINS`] equal bins: bin of value `v` is
    /// `v * bins / (full_scale_dn + 1)`.
    pub histogram: Vec<u32>,
    /// The camera's largest value, DN.
    pub full_scale_dn: u16,
    /// Values at or above this are saturated, DN (the products' threshold).
    pub saturation_dn: u16,
    /// Pixels at or above `saturation_dn`.
    pub saturated: usize,
    /// Smallest and largest value, DN.
    pub min_max_dn: (u16, u16),
    /// Mean, DN.
    pub mean_dn: f64,
}

/// One frame of the live camera stream.
#[derive(Debug, Clone, PartialEq)]
pub struct LiveFrame {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Pixels, DN, row-major.
    pub pixels: Vec<u16>,
    /// The camera's frame id.
    pub frame_id: u64,
    /// The exposure, microseconds.
    pub exposure_us: f64,
    /// Histogram and saturation.
    pub stats: FrameStats,
    /// The camera's frame rate (every frame counted, also those not shown), Hz.
    pub rate_hz: Option<f64>,
    /// Frames received since the stream started.
    pub frames: u64,
}

/// The Stokes estimate of one half turn of the spinning analyzer.
#[derive(Debug, Clone, PartialEq)]
pub struct HalfTurn {
    /// The half turn's number since live polarimetry started, from 0.
    pub index: u64,
    /// S0, S1, S2, DoLP, AoP and their predicted sigma.
    pub products: Products,
    /// Each frame's analyzer span, degrees (start, end; unwrapped).
    pub spans_deg: Vec<(f64, f64)>,
    /// The speed measured from the stage's pulses (or commanded), degrees per second.
    pub speed_deg_per_s: f64,
    /// Half turns estimated per second, over the last ones.
    pub rate_hz: Option<f64>,
    /// How the spans were measured.
    pub timing: String,
    /// The last frame of the half turn, DN.
    pub last_frame: Vec<u16>,
}

/// What the live worker tells the UI.
#[derive(Debug, Clone, PartialEq)]
pub enum LiveUpdate {
    /// A mode started.
    Started {
        /// The mode.
        mode: LiveMode,
        /// What it does (trigger, timing).
        note: String,
    },
    /// A camera frame (live mode; at most about 25 per second are sent).
    Frame(Box<LiveFrame>),
    /// A half turn's estimate (live polarimetry).
    HalfTurn(Box<HalfTurn>),
    /// The mode ended, with the error that ended it, if any.
    Stopped {
        /// The mode.
        mode: LiveMode,
        /// Why it ended, if not by Stop.
        error: Option<String>,
    },
}
