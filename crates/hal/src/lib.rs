//! Device traits of the polarimeter and the error kinds every device shares
//! (`ARCHITECTURE.md`, "Device abstraction").
//!
//! * [`Rotator`]: a rotation stage (home, move to an absolute angle, read the position back;
//!   where the stage can, spin at a set speed and fire position-compare trigger pulses:
//!   [`ContinuousSupport`], [`TriggerPulse`]).
//! * [`FilterWheel`]: a wheel (or slider) of labelled slots.
//! * [`Camera`]: a camera (exposure, gain, pixel format, region, trigger, grab with a deadline).
//! * [`Analyzer`]: the view plans use. It speaks analyzer angles whether a rotator turns one
//!   polarizer or a wheel holds fixed polarizers at known angles. It uses the polarizer's
//!   180-degree period to take the shorter way, and always approaches a target from the same
//!   side, so that gear backlash is taken up the same way every time.
//!
//! Every error maps to an [`ErrorKind`] through [`DeviceError::kind`], so that the engine can
//! retry, reconnect or abort without knowing the device. Traits use `async fn`: drivers
//! implement them on tokio, simulated devices in memory. This crate has no I/O; its
//! [`camera_thread`] runs a [`BlockingCamera`] on its own thread behind tokio channels.
#![warn(missing_docs)]

mod analyzer;
pub mod camera;
pub mod camera_thread;

pub use analyzer::{Analyzer, Approach, OnRotator, OnWheel, SlotAngle};
pub use camera::{
    BlockingCamera, Camera, CameraInfo, ExposureEndHook, Frame, GainUnit, Grabbed, PixelFormat,
    Roi, StreamStats, TransportStats, TriggerMode,
};

use std::f64::consts::PI;
use std::time::Duration;

/// What went wrong, as the engine needs to know it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ErrorKind {
    /// No (complete) answer within the deadline.
    Timeout,
    /// The device is gone (unplugged, port closed); it may come back.
    Disconnected,
    /// The device answered with bytes that do not parse, or an unexpected reply.
    Protocol,
    /// A request outside the device's range (a slot past the last, an angle not fitted).
    OutOfRange,
    /// The device is busy with another operation.
    Busy,
    /// The mechanism did not follow (stall, position not reached).
    Stalled,
    /// Anything else (over temperature, a refused command, an internal fault).
    Other,
}

impl ErrorKind {
    /// Whether repeating the same request can succeed without intervention.
    pub fn is_transient(self) -> bool {
        matches!(
            self,
            ErrorKind::Timeout | ErrorKind::Busy | ErrorKind::Protocol
        )
    }
}

impl std::fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ErrorKind::Timeout => "timeout",
            ErrorKind::Disconnected => "disconnected",
            ErrorKind::Protocol => "protocol error",
            ErrorKind::OutOfRange => "out of range",
            ErrorKind::Busy => "busy",
            ErrorKind::Stalled => "stalled",
            ErrorKind::Other => "device error",
        })
    }
}

/// A device error: its kind, the device, and what happened.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{device}: {kind}: {message}")]
pub struct DeviceError {
    kind: ErrorKind,
    /// The device, as the user names it (port and address, or a simulator's name).
    pub device: String,
    /// What happened, with the values involved.
    pub message: String,
}

impl DeviceError {
    /// A new error.
    pub fn new(kind: ErrorKind, device: impl Into<String>, message: impl Into<String>) -> Self {
        DeviceError {
            kind,
            device: device.into(),
            message: message.into(),
        }
    }

    /// The kind.
    pub fn kind(&self) -> ErrorKind {
        self.kind
    }
}

/// What a rotator reports about itself.
#[derive(Debug, Clone, PartialEq)]
pub struct RotatorInfo {
    /// Model and serial number, as the device reports them.
    pub model: String,
    /// Encoder counts per turn of the output (the angular resolution is one count).
    pub counts_per_turn: u32,
    /// How close a move must land to its target, radians (the readback check).
    pub tolerance_rad: f64,
}

/// What a rotator offers for continuous-rotation acquisition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ContinuousSupport {
    /// Moves and stops only ([`Rotator::spin`] refuses).
    None,
    /// Velocity mode ([`Rotator::spin`], [`Rotator::stop_spin`]) without a trigger output:
    /// a camera runs free and the span of each frame comes from timestamps.
    Velocity,
    /// Velocity mode and a position-compare trigger output ([`Rotator::arm_trigger`],
    /// [`Rotator::next_trigger`]): each pulse reports the encoder count it fired at.
    VelocityAndTrigger,
}

impl ContinuousSupport {
    /// Whether the stage can spin.
    pub fn can_spin(self) -> bool {
        !matches!(self, ContinuousSupport::None)
    }

    /// Whether the stage can fire position-compare trigger pulses.
    pub fn can_trigger(self) -> bool {
        matches!(self, ContinuousSupport::VelocityAndTrigger)
    }
}

impl std::fmt::Display for ContinuousSupport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ContinuousSupport::None => "none",
            ContinuousSupport::Velocity => "velocity",
            ContinuousSupport::VelocityAndTrigger => "velocity and trigger",
        })
    }
}

/// One position-compare trigger pulse, as the stage reported it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriggerPulse {
    /// The pulse's index from the arming, from 0.
    pub index: u32,
    /// The encoder count latched at the pulse, unwrapped (it keeps counting past a turn while
    /// the stage spins).
    pub counts: i64,
    /// The same position, radians, unwrapped.
    pub angle_rad: f64,
    /// The controller's clock at the pulse, microseconds (wraps at 2^32).
    pub device_time_us: u32,
}

/// The time a position read spends on a serial line, seconds: the request's bytes, before the
/// device can latch the position, and the reply's, after it latched. A read's round trip on
/// the host's clock brackets the latch only to within these: the latch lies in `[request
/// sent + request_s, reply received - reply_s]`. Zero where the transport adds no such time
/// (USB, or a driver that does not say).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct WireTimes {
    /// Seconds for the request's bytes on the line.
    pub request_s: f64,
    /// Seconds for the reply's bytes on the line.
    pub reply_s: f64,
}

impl WireTimes {
    /// A UART at `baud` with `bits_per_byte` (start, data, parity and stop bits: 10 for 8N1,
    /// 11 for 8N2) carrying `request_bytes` and `reply_bytes`.
    pub fn uart(request_bytes: usize, reply_bytes: usize, baud: u32, bits_per_byte: u32) -> Self {
        let per_byte_s = f64::from(bits_per_byte) / f64::from(baud.max(1));
        WireTimes {
            request_s: request_bytes as f64 * per_byte_s,
            reply_s: reply_bytes as f64 * per_byte_s,
        }
    }
}

/// The error a stage without continuous rotation gives for `what` (kind
/// [`ErrorKind::OutOfRange`]: the request is outside what the stage offers).
fn unsupported(info: &RotatorInfo, what: &str, support: ContinuousSupport) -> DeviceError {
    DeviceError::new(
        ErrorKind::OutOfRange,
        info.model.clone(),
        format!(
            "{what} is not supported by stage {}: its continuous-rotation support is \"{support}\"",
            info.model
        ),
    )
}

/// A rotation stage.
///
/// The continuous-rotation methods ([`Rotator::spin`] and the rest) refuse by default with
/// an [`ErrorKind::OutOfRange`] error naming the stage; a stage that offers them says so in
/// [`Rotator::continuous_support`].
#[allow(async_fn_in_trait)] // used through generics; Send-ness is the implementor's business
pub trait Rotator {
    /// Identity and resolution.
    fn info(&self) -> &RotatorInfo;
    /// Finds the index and zeroes the position.
    async fn home(&mut self) -> Result<(), DeviceError>;
    /// Moves to `angle_rad` in `[0, 2 pi)`, the short way or as the device likes, and returns
    /// the position read back afterwards (within `tolerance_rad` of the target, or an error of
    /// kind [`ErrorKind::Stalled`]).
    async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError>;
    /// The position, radians in `[0, 2 pi)`.
    async fn position_rad(&mut self) -> Result<f64, DeviceError>;
    /// Whether [`Rotator::set_velocity`] does anything.
    fn supports_velocity(&self) -> bool {
        false
    }
    /// Sets the cruise velocity, rad/s; by default a no-op (see [`Rotator::supports_velocity`]).
    async fn set_velocity(&mut self, _rad_per_s: f64) -> Result<(), DeviceError> {
        Ok(())
    }
    /// What the stage offers for continuous rotation (by default nothing).
    fn continuous_support(&self) -> ContinuousSupport {
        ContinuousSupport::None
    }
    /// Velocity mode: turns continuously at `rad_per_s` (signed) until [`Rotator::stop_spin`];
    /// a second call changes the speed. Refuses by default.
    async fn spin(&mut self, _rad_per_s: f64) -> Result<(), DeviceError> {
        Err(unsupported(self.info(), "spin", self.continuous_support()))
    }
    /// Ends velocity mode and returns where the stage stopped, radians in `[0, 2 pi)`.
    /// Refuses by default.
    async fn stop_spin(&mut self) -> Result<f64, DeviceError> {
        Err(unsupported(
            self.info(),
            "stop_spin",
            self.continuous_support(),
        ))
    }
    /// The line's share of a [`Rotator::spin_position_rad`] round trip (by default none).
    fn spin_read_wire(&self) -> WireTimes {
        WireTimes::default()
    }
    /// The position while spinning, radians, unwrapped (it keeps counting past a turn), read
    /// from the device now (never a cached value). Refuses by default.
    async fn spin_position_rad(&mut self) -> Result<f64, DeviceError> {
        Err(unsupported(
            self.info(),
            "spin_position_rad",
            self.continuous_support(),
        ))
    }
    /// Arms the position-compare trigger: `count` pulses, at `first_rad` (unwrapped, from the
    /// datum) and then every `interval_rad` (signed: the direction of motion that fires).
    /// Pulses of an earlier arming are dropped. Refuses by default.
    async fn arm_trigger(
        &mut self,
        _first_rad: f64,
        _interval_rad: f64,
        _count: u32,
    ) -> Result<(), DeviceError> {
        Err(unsupported(
            self.info(),
            "arm_trigger",
            self.continuous_support(),
        ))
    }
    /// The next pulse of the current arming, waiting up to `timeout` (then an error of kind
    /// [`ErrorKind::Timeout`]). Refuses by default.
    async fn next_trigger(&mut self, _timeout: Duration) -> Result<TriggerPulse, DeviceError> {
        Err(unsupported(
            self.info(),
            "next_trigger",
            self.continuous_support(),
        ))
    }
}

/// A filter wheel or slider of labelled slots.
#[allow(async_fn_in_trait)]
pub trait FilterWheel {
    /// The slots' labels, in slot order (slot 0 first).
    fn slots(&self) -> &[String];
    /// Moves to `slot` and returns the slot read back.
    async fn select(&mut self, slot: usize) -> Result<usize, DeviceError>;
    /// The current slot (`None` between slots).
    async fn slot(&mut self) -> Result<Option<usize>, DeviceError>;
}

/// `angle` reduced to `[0, period)`.
pub fn wrap(angle: f64, period: f64) -> f64 {
    let r = angle.rem_euclid(period);
    if r >= period {
        0.0
    } else {
        r
    }
}

/// The signed difference `a - b` reduced to `(-period/2, period/2]`.
pub fn signed_difference(a: f64, b: f64, period: f64) -> f64 {
    let d = wrap(a - b, period);
    if d > period / 2.0 {
        d - period
    } else {
        d
    }
}

/// A full turn, radians.
pub const TURN_RAD: f64 = 2.0 * PI;

/// The angle of an axis at `counts` with `counts_per_turn`, radians in `[0, 2 pi)`.
pub fn angle_from_counts(counts: i64, counts_per_turn: u32) -> f64 {
    wrap(
        counts as f64 / counts_per_turn.max(1) as f64 * TURN_RAD,
        TURN_RAD,
    )
}

/// The absolute count nearest `current` at which the axis is at `angle_rad`: the target of a
/// move the short way round (saturating at the ends of the i32 range).
pub fn counts_toward(current: i32, angle_rad: f64, counts_per_turn: u32) -> i32 {
    let cpt = counts_per_turn.max(1) as f64;
    let delta = signed_difference(
        angle_rad,
        angle_from_counts(i64::from(current), counts_per_turn),
        TURN_RAD,
    ) / TURN_RAD
        * cpt;
    (current as f64 + delta.round()).clamp(i32::MIN as f64, i32::MAX as f64) as i32
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stage with moves only.
    struct Fixed(RotatorInfo);

    impl Rotator for Fixed {
        fn info(&self) -> &RotatorInfo {
            &self.0
        }
        async fn home(&mut self) -> Result<(), DeviceError> {
            Ok(())
        }
        async fn move_to(&mut self, angle_rad: f64) -> Result<f64, DeviceError> {
            Ok(angle_rad)
        }
        async fn position_rad(&mut self) -> Result<f64, DeviceError> {
            Ok(0.0)
        }
    }

    /// A stage that does not override the continuous-rotation methods reports no support and
    /// refuses every one of them with an OutOfRange error naming the stage and the method.
    #[test]
    fn continuous_rotation_refused_by_default() {
        let mut r = Fixed(RotatorInfo {
            model: "test stage 7".into(),
            counts_per_turn: 360,
            tolerance_rad: 0.01,
        });
        assert_eq!(r.continuous_support(), ContinuousSupport::None);
        assert!(!r.continuous_support().can_spin());
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .expect("runtime");
        let errors = rt.block_on(async {
            vec![
                ("spin", r.spin(1.0).await.err()),
                ("stop_spin", r.stop_spin().await.err()),
                ("spin_position_rad", r.spin_position_rad().await.err()),
                ("arm_trigger", r.arm_trigger(0.0, 0.1, 3).await.err()),
                (
                    "next_trigger",
                    r.next_trigger(Duration::from_millis(1)).await.err(),
                ),
            ]
        });
        for (what, e) in errors {
            let e = e.unwrap_or_else(|| panic!("{what} should be refused"));
            assert_eq!(e.kind(), ErrorKind::OutOfRange, "{what}");
            let text = e.to_string();
            assert!(
                text.contains("test stage 7") && text.contains(what),
                "{text}"
            );
        }
    }

    /// Counts and angles: a quarter of 143360 counts is 90 deg; a move from just below a full
    /// turn to 1 deg goes forward across the turn (short way), and from 1 deg to 359 deg
    /// backwards below zero, to the count of the target angle (rounding: half a count); the
    /// target saturates at the end of the i32 range.
    #[test]
    fn counts_and_angles() {
        let cpt = 143_360;
        assert!((angle_from_counts(35_840, cpt).to_degrees() - 90.0).abs() < 1e-12);
        assert!((angle_from_counts(-35_840, cpt).to_degrees() - 270.0).abs() < 1e-9);
        let one_deg = cpt as f64 / 360.0;
        let t = counts_toward(143_000, 1f64.to_radians(), cpt);
        assert!((t as f64 - (143_360.0 + one_deg)).abs() <= 0.5, "{t}");
        let t = counts_toward(398, 359f64.to_radians(), cpt);
        assert!((t as f64 + one_deg).abs() <= 0.5, "{t}");
        // Past the end of the i32 range the target saturates instead of overflowing.
        let at_max = angle_from_counts(i64::from(i32::MAX), cpt);
        assert_eq!(counts_toward(i32::MAX, at_max + 0.1, cpt), i32::MAX);
    }
}
