//! A serial dialect's descriptor ([`Dialect`]): its name, device kinds, models, line settings,
//! default policy, identify and constructors. Each dialect's driver module declares its own
//! (`native::DIALECT`, `elliptec::DIALECT`, `fw102c::DIALECT`, `apt::DIALECT`) and
//! [`crate::registry::DIALECTS`] lists them.

use crate::any::{AnyRotator, AnyWheel, LocalFuture};
use crate::link::{BoxIo, Connector, OpenFuture, Policy};
use polar_hal::{DeviceError, ErrorKind, FilterWheel};
use std::io;
pub use tokio_serial::{DataBits, FlowControl, Parity, StopBits};

/// What a device of a dialect is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceKind {
    /// A rotation stage (turns the analyzer freely).
    Rotator,
    /// A filter wheel or slider of fixed slots.
    Wheel,
}

impl DeviceKind {
    /// `rotator` or `wheel`.
    pub fn name(self) -> &'static str {
        match self {
            DeviceKind::Rotator => "rotator",
            DeviceKind::Wheel => "wheel",
        }
    }
}

/// The serial line's framing and flow control.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LineSettings {
    /// Data bits.
    pub data_bits: DataBits,
    /// Parity.
    pub parity: Parity,
    /// Stop bits.
    pub stop_bits: StopBits,
    /// Flow control.
    pub flow_control: FlowControl,
}

/// 8 data bits, no parity, one stop bit, no flow control.
pub const LINE_8N1: LineSettings = LineSettings {
    data_bits: DataBits::Eight,
    parity: Parity::None,
    stop_bits: StopBits::One,
    flow_control: FlowControl::None,
};

/// Where a device is, as identify reads it without moving it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Position {
    /// A rotator's angle, degrees in `[0, 360)`.
    Angle {
        /// The angle.
        deg: f64,
    },
    /// A wheel's slot (`None` between slots or before a datum).
    Slot(Option<usize>),
}

/// What identify finds: the device, without moving it.
#[derive(Debug, Clone, PartialEq)]
pub struct Identity {
    /// Rotator or wheel.
    pub kind: DeviceKind,
    /// The model, as the device names it.
    pub model: String,
    /// Serial number (empty if the device reports none).
    pub serial: String,
    /// Firmware version (empty if the device reports none).
    pub firmware: String,
    /// A rotator's counts per turn.
    pub counts_per_turn: Option<u32>,
    /// A wheel's number of slots.
    pub slots: Option<usize>,
    /// Whether the device has a datum (`None`: it does not say).
    pub homed: Option<bool>,
    /// Where it is.
    pub position: Position,
}

/// Opens a port of a dialect: a connector, a bus address (0 where the dialect has no bus),
/// the policy.
pub type Identify =
    fn(Box<dyn Connector>, u8, Policy) -> LocalFuture<'static, Result<Identity, DeviceError>>;
/// Connects (and homes) a rotator.
pub type ConnectRotator =
    fn(Box<dyn Connector>, u8, Policy) -> LocalFuture<'static, Result<AnyRotator, DeviceError>>;
/// Connects a wheel or slider.
pub type ConnectWheel =
    fn(Box<dyn Connector>, u8, Policy) -> LocalFuture<'static, Result<AnyWheel, DeviceError>>;

/// One dialect, declared once.
#[derive(Debug, Clone, Copy)]
pub struct Dialect {
    /// The name the CLI, the rig file and the simulators use (`native`, `elliptec`, ...).
    pub name: &'static str,
    /// One line for `--help` and `devices list`.
    pub description: &'static str,
    /// The device kinds it provides.
    pub kinds: &'static [DeviceKind],
    /// Its models, lower case (the simulator's `--model` and the rig's `model`).
    pub models: &'static [&'static str],
    /// Line rate, baud.
    pub baud: u32,
    /// Framing and flow control.
    pub line: LineSettings,
    /// The addresses devices have on a shared bus (`--address`); `None`: one device per
    /// port (address 0).
    pub bus: Option<Bus>,
    /// Deadlines and retries.
    pub policy: fn() -> Policy,
    /// Reads what the device is, without moving it.
    pub identify: Identify,
    /// Connects a rotator (None: the dialect has none).
    pub rotator: Option<ConnectRotator>,
    /// Connects a wheel or slider (None: the dialect has none).
    pub wheel: Option<ConnectWheel>,
}

impl Dialect {
    /// The connector of a serial port in this dialect (its baud and line settings).
    pub fn connector(&self, path: &str) -> Box<dyn Connector> {
        Box::new(SerialLine {
            path: path.to_string(),
            baud: self.baud,
            line: self.line,
        })
    }

    /// Whether the dialect provides `kind`.
    pub fn provides(&self, kind: DeviceKind) -> bool {
        self.kinds.contains(&kind)
    }

    /// The dialect's models, comma-separated.
    pub fn model_list(&self) -> String {
        self.models.join(", ")
    }

    /// The address a device has when none is given: the bus's first, else 0.
    pub fn default_address(&self) -> u8 {
        self.bus.map_or(0, |b| b.first)
    }

    /// Whether devices of the dialect sit on a bus at an address.
    pub fn addressed(&self) -> bool {
        self.bus.is_some()
    }

    /// Checks a bus address against the dialect: the bus's range, 0 where there is no bus.
    pub fn check_address(&self, address: u8) -> Result<(), String> {
        match self.bus {
            Some(b) if (b.first..=b.last).contains(&address) => Ok(()),
            Some(b) => Err(format!(
                "address = {address} is out of range: allowed {}..={} for {} devices",
                b.first, b.last, self.name
            )),
            None if address == 0 => Ok(()),
            None => Err(format!(
                "address = {address} is invalid: {} devices have no bus address (allowed 0)",
                self.name
            )),
        }
    }
}

/// The addresses of a dialect's bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Bus {
    /// The lowest address.
    pub first: u8,
    /// The highest address.
    pub last: u8,
}

/// A serial port by path with a dialect's baud and line settings.
#[derive(Debug, Clone, PartialEq)]
pub struct SerialLine {
    /// The device path (prefer `/dev/serial/by-id/...`).
    pub path: String,
    /// Line rate.
    pub baud: u32,
    /// Framing and flow control.
    pub line: LineSettings,
}

impl Connector for SerialLine {
    fn describe(&self) -> String {
        self.path.clone()
    }

    fn open(&self) -> OpenFuture<'_> {
        Box::pin(async move {
            let builder = tokio_serial::new(&self.path, self.baud)
                .data_bits(self.line.data_bits)
                .parity(self.line.parity)
                .stop_bits(self.line.stop_bits)
                .flow_control(self.line.flow_control);
            let port = tokio_serial::SerialStream::open(&builder).map_err(io::Error::from)?;
            Ok(Box::new(port) as BoxIo)
        })
    }
}

/// The wheel's slot and count, as a [`Position`] read through its driver.
pub(crate) async fn wheel_identity<W: FilterWheel>(
    mut w: W,
    model: String,
) -> Result<Identity, DeviceError> {
    let slot = w.slot().await?;
    Ok(Identity {
        kind: DeviceKind::Wheel,
        model,
        serial: String::new(),
        firmware: String::new(),
        counts_per_turn: None,
        slots: Some(w.slots().len()),
        homed: None,
        position: Position::Slot(slot),
    })
}

/// The error of a dialect asked for a kind it does not provide.
pub fn not_provided(dialect: &Dialect, kind: DeviceKind) -> DeviceError {
    DeviceError::new(
        ErrorKind::OutOfRange,
        dialect.name,
        format!(
            "dialect = {} provides no {}: allowed {}",
            dialect.name,
            kind.name(),
            dialect
                .kinds
                .iter()
                .map(|k| k.name())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    )
}
