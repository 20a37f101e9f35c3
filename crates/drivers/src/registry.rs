//! The registry of serial dialects: [`DIALECTS`] lists every dialect's descriptor
//! ([`Dialect`]), each declared in its own driver module. The CLI's `--dialect`, `devices
//! list`, `stage`, `simulate stage`, the rig file, the hardware rig and the GUI all read this
//! list, so adding a dialect is its driver module (with its `DIALECT`), its simulator module
//! (with its `SIM`), and one line here and one in `polar_hil_mocks::sim::SIMULATORS`
//! (`docs/DEVICES.md`, "Adding a dialect").

pub use crate::dialect::{
    not_provided, Bus, ConnectRotator, ConnectWheel, DataBits, DeviceKind, Dialect, FlowControl,
    Identify, Identity, LineSettings, Parity, Position, SerialLine, StopBits, LINE_8N1,
};
pub use crate::elliptec::ELLIPTEC_TOLERANCE_DEG;
use crate::{apt, elliptec, fw102c, native, smc100, standa};

/// Every dialect, one line each.
pub static DIALECTS: &[Dialect] = &[
    native::DIALECT,
    elliptec::DIALECT,
    fw102c::DIALECT,
    apt::DIALECT,
    smc100::DIALECT,
    standa::DIALECT,
];

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
