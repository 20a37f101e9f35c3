//! The registry of serial dialects: each dialect is declared once, as a [`Dialect`] descriptor
//! (name, description, device kinds, models, baud and line settings, default [`Policy`],
//! identify and the rotator or wheel constructor), and [`DIALECTS`] lists them. The CLI's
//! `--dialect`, `devices list`, `stage`, `sim stage`, the rig file, the hardware rig and the GUI
//! all read this table, so adding a dialect is its driver module, its simulator module and one
//! line here and one in `polar_hil_mocks::registry` (`docs/DEVICES.md`, "Adding a dialect").

use crate::any::{AnyRotator, AnyWheel, LocalFuture};
use crate::apt;
use crate::elliptec::{self, ElliptecRotator, ElliptecSlider};
use crate::fw102c::{self, Fw102c};
use crate::link::{BoxIo, Connector, OpenFuture, Policy};
use crate::native::{self, NativeRotator, NativeWheel};
use polar_firmware_protocol::DeviceKind as NativeKind;
use polar_hal::{angle_from_counts, DeviceError, ErrorKind, FilterWheel};
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
    /// Whether devices sit on a bus at an address 0..=15 (`--address`).
    pub addressed: bool,
    /// Deadlines and retries.
    pub policy: fn() -> Policy,
    /// Reads what the device is, without moving it.
    pub identify: Identify,
    /// Connects a rotator (None: the dialect has none).
    pub rotator: Option<ConnectRotator>,
    /// Connects a wheel or slider (None: the dialect has none).
    pub wheel: Option<ConnectWheel>,
}

/// The readback tolerance the registry gives Elliptec rotators, degrees.
pub const ELLIPTEC_TOLERANCE_DEG: f64 = 0.05;

/// Every dialect, one line each.
pub static DIALECTS: &[Dialect] = &[NATIVE, ELLIPTEC, FW102C, apt::DIALECT];

/// The dialect named `name`.
pub fn find(name: &str) -> Option<&'static Dialect> {
    DIALECTS.iter().find(|d| d.name == name)
}

/// The dialects' names, comma-separated (for errors that list what is allowed).
pub fn names() -> String {
    DIALECTS
        .iter()
        .map(|d| d.name)
        .collect::<Vec<_>>()
        .join(", ")
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

    /// Checks a bus address against the dialect: 0..=15 on a bus, 0 otherwise.
    pub fn check_address(&self, address: u8) -> Result<(), String> {
        match (self.addressed, address) {
            (true, 0..=15) | (false, 0) => Ok(()),
            (true, a) => Err(format!("address = {a} is out of range: allowed 0..=15")),
            (false, a) => Err(format!(
                "address = {a} is invalid: {} devices have no bus address (allowed 0)",
                self.name
            )),
        }
    }
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
async fn wheel_identity<W: FilterWheel>(mut w: W, model: String) -> Result<Identity, DeviceError> {
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

/// Our firmware (`firmware-protocol/SPEC.md`).
const NATIVE: Dialect = Dialect {
    name: "native",
    description: "our firmware (firmware-protocol/SPEC.md): rotation stage or six-slot wheel",
    kinds: &[DeviceKind::Rotator, DeviceKind::Wheel],
    models: &["rotator", "wheel"],
    baud: 115_200,
    line: LINE_8N1,
    addressed: false,
    policy: native::default_policy,
    identify: |c, _, policy| {
        Box::pin(async move {
            let p = native::probe(c, policy).await?;
            let id = p.identity;
            let rotator = id.device == NativeKind::Rotator;
            Ok(Identity {
                kind: if rotator {
                    DeviceKind::Rotator
                } else {
                    DeviceKind::Wheel
                },
                model: format!("{:?}", id.device),
                serial: format!("{:08x}", id.serial),
                firmware: format!("{}.{}.{}", id.firmware[0], id.firmware[1], id.firmware[2]),
                counts_per_turn: rotator.then_some(id.counts_per_turn),
                slots: (!rotator).then_some(usize::from(id.slots)),
                homed: Some(p.homed),
                position: if rotator {
                    let a = angle_from_counts(i64::from(p.position_counts), id.counts_per_turn);
                    Position::Angle {
                        deg: a.to_degrees(),
                    }
                } else {
                    Position::Slot(p.slot.map(usize::from))
                },
            })
        })
    },
    rotator: Some(|c, _, policy| {
        Box::pin(async move { Ok(AnyRotator::new(NativeRotator::connect(c, policy).await?)) })
    }),
    wheel: Some(|c, _, policy| {
        Box::pin(async move { Ok(AnyWheel::new(NativeWheel::connect(c, policy, None).await?)) })
    }),
};

/// Thorlabs Elliptec (ASCII bus, addresses 0..=F).
const ELLIPTEC: Dialect = Dialect {
    name: "elliptec",
    description: "Thorlabs Elliptec: ELL14/ELL18 rotation mounts, ELL6/ELL9 sliders",
    kinds: &[DeviceKind::Rotator, DeviceKind::Wheel],
    models: &["ell14", "ell18", "ell6", "ell9"],
    baud: 9600,
    line: LINE_8N1,
    addressed: true,
    policy: elliptec::default_policy,
    identify: |c, address, policy| {
        Box::pin(async move {
            let (info, counts) = elliptec::probe(c, address, policy).await?;
            let slider = elliptec::slider_positions(info.model_code);
            let (kind, position) = match slider {
                None => (
                    DeviceKind::Rotator,
                    Position::Angle {
                        deg: angle_from_counts(i64::from(counts), info.pulses).to_degrees(),
                    },
                ),
                Some(s) => (
                    DeviceKind::Wheel,
                    Position::Slot(s.iter().position(|&p| (p - counts).abs() <= 5)),
                ),
            };
            Ok(Identity {
                kind,
                model: info.model(),
                serial: info.serial.clone(),
                firmware: info.firmware.to_string(),
                counts_per_turn: elliptec::is_rotator(info.model_code).then_some(info.pulses),
                slots: slider.map(<[i32]>::len),
                homed: None,
                position,
            })
        })
    },
    rotator: Some(|c, address, policy| {
        Box::pin(async move {
            let tolerance_rad = ELLIPTEC_TOLERANCE_DEG.to_radians();
            let r = ElliptecRotator::connect(c, address, policy, tolerance_rad).await?;
            Ok(AnyRotator::new(r))
        })
    }),
    wheel: Some(|c, address, policy| {
        Box::pin(async move {
            Ok(AnyWheel::new(
                ElliptecSlider::connect(c, address, policy).await?,
            ))
        })
    }),
};

/// Thorlabs FW102C/FW212C filter wheels.
const FW102C: Dialect = Dialect {
    name: "fw102c",
    description: "Thorlabs FW102C/FW212C filter wheels (ASCII, echo and prompt)",
    kinds: &[DeviceKind::Wheel],
    models: &["fw102c", "fw212c"],
    baud: 115_200,
    line: LINE_8N1,
    addressed: false,
    policy: fw102c::default_policy,
    identify: |c, _, policy| {
        Box::pin(async move {
            let w = Fw102c::connect(c, policy).await?;
            let model = w.identity().to_string();
            wheel_identity(w, model).await
        })
    },
    rotator: None,
    wheel: Some(|c, _, policy| {
        Box::pin(async move { Ok(AnyWheel::new(Fw102c::connect(c, policy).await?)) })
    }),
};

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

#[cfg(test)]
mod tests {
    use super::*;

    /// Names are unique, lower case and findable; each dialect provides what its constructors
    /// say (a kind without a constructor would fail at connect time, not at lookup).
    #[test]
    fn the_table_is_consistent() {
        for (i, d) in DIALECTS.iter().enumerate() {
            assert_eq!(find(d.name).map(|f| f.name), Some(d.name));
            assert!(
                DIALECTS[..i].iter().all(|o| o.name != d.name),
                "{} twice",
                d.name
            );
            assert_eq!(d.name, d.name.to_lowercase());
            assert_eq!(
                d.provides(DeviceKind::Rotator),
                d.rotator.is_some(),
                "{}",
                d.name
            );
            assert_eq!(
                d.provides(DeviceKind::Wheel),
                d.wheel.is_some(),
                "{}",
                d.name
            );
            assert!(!d.models.is_empty() && d.baud > 0, "{}", d.name);
        }
        assert!(find("nonesuch").is_none());
    }

    /// The bus address is checked per dialect, with the allowed range in the message.
    #[test]
    fn addresses_are_checked_against_the_dialect() {
        let e = find("elliptec").unwrap();
        e.check_address(15).unwrap();
        assert!(e.check_address(16).unwrap_err().contains("allowed 0..=15"));
        let n = find("native").unwrap();
        n.check_address(0).unwrap();
        assert!(n.check_address(3).unwrap_err().contains("allowed 0"));
    }
}
