//! [`SIMULATORS`]: every serial dialect's simulators keyed by the dialect's name (one line per
//! dialect, each declared in its simulator module as `SIM`), which `simulate stage`, the
//! simulated rig and the tests use; and [`simulator`], the lookup by dialect and model.

use crate::faults::FaultProfile;
pub use crate::simulator::{
    next_request, BuildAtSpeed, BuildOnBus, BuildSimulator, Scan, SimDialect, SimMotion, Simulator,
    Truth,
};
use crate::{apt, elliptec, fw102c, native, smc100, standa};

/// Every dialect's simulators, one line each.
pub static SIMULATORS: &[SimDialect] = &[
    native::SIM,
    elliptec::SIM,
    fw102c::SIM,
    apt::SIM,
    smc100::SIM,
    standa::SIM,
];

/// Why [`simulator`] made none; the message names the value and what is allowed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SimLookupError {
    /// No simulator speaks the dialect.
    #[error("dialect = {0:?} has no simulator: allowed {1}")]
    Dialect(String, String),
    /// The dialect has no such model.
    #[error("model = {0:?} is not a {1} device: allowed {2}")]
    Model(String, String, String),
}

/// The simulator of `dialect`'s `model` (or its first model), with device faults.
pub fn simulator(
    dialect: &str,
    model: Option<&str>,
    faults: FaultProfile,
    seed: u64,
) -> Result<Box<dyn Simulator>, SimLookupError> {
    let entry = SIMULATORS
        .iter()
        .find(|s| s.dialect == dialect)
        .ok_or_else(|| {
            let names: Vec<&str> = SIMULATORS.iter().map(|s| s.dialect).collect();
            SimLookupError::Dialect(dialect.to_string(), names.join(", "))
        })?;
    let model = model.map_or(entry.models[0], |m| m);
    let known = entry.models.contains(&model);
    known
        .then(|| (entry.build)(model, faults, seed))
        .flatten()
        .ok_or_else(|| {
            SimLookupError::Model(
                model.to_string(),
                dialect.to_string(),
                entry.models.join(", "),
            )
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every listed model builds, describes itself as its dialect's device and uses a real
    /// line rate; an unknown dialect or model is refused naming what is allowed.
    #[test]
    fn every_listed_model_builds() {
        for s in SIMULATORS {
            for m in s.models {
                let sim = simulator(s.dialect, Some(m), FaultProfile::default(), 1).unwrap();
                assert!(sim.baud() >= 9600, "{} {m}", s.dialect);
            }
        }
        let Err(e) = simulator("native", Some("ell14"), FaultProfile::default(), 1) else {
            panic!("an Elliptec model built as a native device");
        };
        assert_eq!(
            e.to_string(),
            "model = \"ell14\" is not a native device: allowed rotator, wheel"
        );
        let Err(e) = simulator("nonesuch", None, FaultProfile::default(), 1) else {
            panic!("an unknown dialect built");
        };
        assert!(
            e.to_string().contains("allowed native, elliptec, fw102c"),
            "{e}"
        );
    }
}
