//! How a run ends: the suspender's verdict on each set, the outcome, the summary of a finished
//! run with its saturated sets, and the errors that stop a run.

use crate::store::RunStore;
use polar_hal::DeviceError;

/// The suspender's verdict on a set.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Verdict {
    /// The set counts.
    pub accepted: bool,
    /// Why not (empty when accepted).
    pub reason: String,
    /// Mean reduced chi-square of the per-pixel Malus fit (NaN for 3 angles).
    pub reduced_chi2: f64,
    /// Mean S0 of the set, DN.
    pub mean_s0_dn: f64,
    /// Largest |commanded - measured| analyzer angle, degrees.
    pub max_angle_error_deg: f64,
    /// The share of the set's pixels where a frame saturated (their products are NaN).
    #[serde(default)]
    pub saturated_fraction: f64,
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Every planned frame stored and verified.
    Done(Summary),
    /// Paused and detached: `polarimeter resume` continues it.
    Paused(String),
    /// Aborted.
    Aborted(String),
}

/// What a finished run did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Frames stored (accepted and superseded).
    pub frames_stored: u64,
    /// Frames that count.
    pub frames_accepted: u64,
    /// Sets accepted.
    pub sets_accepted: u64,
    /// Sets the suspender rejected (and took again).
    pub sets_rejected: u64,
    /// Device operations retried.
    pub retries: u64,
    /// Pauses (any reason).
    pub pauses: u64,
    /// Wall time of this process's part of the run, seconds.
    pub elapsed_s: f64,
    /// Of which the engine waited on device operations (moves with their readback, grabs),
    /// seconds: the rest is the engine's own time that did not overlap a device.
    pub device_s: f64,
    /// The planner's last set, degrees (adaptive runs).
    pub final_angles_deg: Option<Vec<f64>>,
    /// The sets (of the whole run, every process's) whose saturated share of pixels is over
    /// the plan's `suspender.max_saturated_fraction`.
    pub saturation: Saturation,
    /// The camera's stream over this process's part of the run (`None`: not asked of it).
    pub camera_stream: Option<Box<CameraStream>>,
}

/// A camera's stream counters as a run records them (`polar_hal::StreamStats`): frames
/// delivered, incomplete, dropped and timed out, and the transport's packets where it counts
/// them (GigE Vision).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct CameraStream {
    /// Frames handed out.
    pub delivered: u64,
    /// Frames that came incomplete (never handed out).
    pub incomplete: u64,
    /// Complete frames dropped because the consumer was too slow.
    pub dropped: u64,
    /// Grabs that ended at their deadline.
    pub timeouts: u64,
    /// Packets received (GigE Vision).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub received_packets: Option<u64>,
    /// Packets missing from frames before any resend.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub missing_packets: Option<u64>,
    /// Packets asked for again.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resend_requests: Option<u64>,
    /// Packets that came back when asked for again.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resent_packets: Option<u64>,
    /// Whether lost packets were asked for again (the device offers packet resend).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub packet_resend: Option<bool>,
}

impl From<polar_hal::StreamStats> for CameraStream {
    fn from(s: polar_hal::StreamStats) -> Self {
        CameraStream {
            delivered: s.delivered,
            incomplete: s.incomplete,
            dropped: s.dropped,
            timeouts: s.timeouts,
            received_packets: s.transport.map(|t| t.received_packets),
            missing_packets: s.transport.map(|t| t.missing_packets),
            resend_requests: s.transport.map(|t| t.resend_requests),
            resent_packets: s.transport.map(|t| t.resent_packets),
            packet_resend: s.transport.map(|t| t.packet_resend),
        }
    }
}

/// Saturated pixels over a run, from the store's per-set record.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize)]
pub struct Saturation {
    /// The plan's limit, a share of a set's pixels.
    pub max_fraction: f64,
    /// The largest share of any set.
    pub worst_fraction: f64,
    /// The sets over the limit and their shares.
    pub sets_over: Vec<(u64, f64)>,
    /// What to do about it (empty when no set is over the limit).
    pub warning: String,
}

impl Saturation {
    /// The run's saturation from the store's per-set shares and the plan's limit.
    pub fn of(store: &RunStore, max_fraction: f64) -> Result<Saturation, RunError> {
        let shares = store.product_saturation()?;
        let worst_fraction = shares.values().copied().fold(0.0, f64::max);
        let sets_over: Vec<(u64, f64)> = shares
            .into_iter()
            .filter(|(_, f)| *f > max_fraction)
            .collect();
        let warning = if sets_over.is_empty() {
            String::new()
        } else {
            format!(
                "{} set(s) saturate more than {:.1} % of their pixels (the worst {:.1} %; \
                 suspender.max_saturated_fraction): their products are NaN there. Shorten the \
                 exposure or lower the gain (plan check shows the saturation margin)",
                sets_over.len(),
                100.0 * max_fraction,
                100.0 * worst_fraction
            )
        };
        Ok(Saturation {
            max_fraction,
            worst_fraction,
            sets_over,
            warning,
        })
    }
}

/// Why a run could not go on at all (as opposed to pausing).
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The plan cannot run.
    #[error(transparent)]
    Plan(#[from] crate::plan::PlanError),
    /// The run directory.
    #[error("run directory {path}: {message}")]
    Dir {
        /// The directory.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// The journal.
    #[error(transparent)]
    Journal(#[from] crate::journal::JournalError),
    /// The store.
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    /// The frames written do not match the frames planned, or a stored frame does not match
    /// its journaled hash.
    #[error("run check failed: {0}")]
    Check(String),
    /// The planner.
    #[error("planner: {0}")]
    Planner(String),
    /// A device could not be set up.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The storage thread went away.
    #[error("storage thread: {0}")]
    Storage(String),
}
