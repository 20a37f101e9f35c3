//! The simulated rig's rotation stage as a plan names it (`[simulation] stage`): the simulated
//! rotators of the simulators' registry (`polar_hil_mocks::sim::SIMULATORS`), the plan's
//! choice checked against them, and the stage's limits for the continuous planner, all read
//! from the simulators' descriptors, so a new simulated rotator needs no change here.
//!
//! The default stage (a plan without `[simulation] stage`) is the first rotator of the
//! registry's list, our firmware's. A stage built at the plan's `simulation.stage_deg_per_s`
//! cruises at that speed; where its descriptor says how it moves
//! (`polar_hil_mocks::sim::SimMotion`), its top speed is the cruise speed capped at its
//! velocity mode's fastest spin, and its acceleration is the cruise speed over its ramp time
//! (our firmware's rotator: 1/8 s, so at the 360 deg/s of the bench rig 2880 deg/s^2, the
//! defaults of `plan continuous`). Where it does not, the limits are not known and a
//! continuous plan's `from_planner` must give them.

use polar_engine::forecast::Timing;
use polar_engine::plan::{Plan, PlanError, SimStage, Simulation};
use polar_hil_mocks::faults::FaultProfile;
use polar_hil_mocks::sim::{SimDialect, Truth, SIMULATORS};
use polar_planner::continuous::StageLimits;

/// Every simulated rotator as (dialect, model), in the simulators' registry order: the
/// models whose simulator reports an angle (wheels and sliders report a slot).
pub fn rotators() -> Vec<(&'static str, &'static str)> {
    SIMULATORS
        .iter()
        .flat_map(|s| s.models.iter().map(move |m| (s.dialect, *m, s.build)))
        .filter(|(_, m, build)| {
            build(m, FaultProfile::default(), 0)
                .is_some_and(|sim| matches!(sim.truth(0.0), Truth::Angle { .. }))
        })
        .map(|(d, m, _)| (d, m))
        .collect()
}

/// The stage of a plan without `[simulation] stage`: the registry's first rotator.
pub fn default_stage() -> (&'static str, &'static str) {
    rotators()
        .first()
        .copied()
        .expect("the simulators' registry lists a rotator")
}

fn invalid(field: &str, value: &str, allowed: String) -> PlanError {
    PlanError::Invalid {
        field: field.to_string(),
        value: value.to_string(),
        allowed,
    }
}

/// The plan's stage as (dialect, model), checked against [`rotators`] (none: the
/// [`default_stage`]); an error names `simulation.stage.dialect` or `simulation.stage.model`,
/// the value and what is allowed.
pub fn resolve(stage: Option<&SimStage>) -> Result<(&'static str, &'static str), PlanError> {
    let Some(stage) = stage else {
        return Ok(default_stage());
    };
    let rotators = rotators();
    let mut dialects: Vec<&str> = rotators.iter().map(|r| r.0).collect();
    dialects.dedup();
    let Some(dialect) = dialects.iter().copied().find(|d| *d == stage.dialect) else {
        return Err(invalid(
            "simulation.stage.dialect",
            &format!("{:?}", stage.dialect),
            format!(
                "one of {} (dialects with a simulated rotator)",
                dialects.join(", ")
            ),
        ));
    };
    let models: Vec<&'static str> = rotators
        .iter()
        .filter(|r| r.0 == dialect)
        .map(|r| r.1)
        .collect();
    match &stage.model {
        None => Ok((dialect, models[0])),
        Some(m) => models
            .iter()
            .find(|x| **x == m.as_str())
            .map(|x| (dialect, *x))
            .ok_or_else(|| {
                invalid(
                    "simulation.stage.model",
                    &format!("{m:?}"),
                    format!(
                        "one of {} (the simulated {dialect} rotators)",
                        models.join(", ")
                    ),
                )
            }),
    }
}

/// The simulators' descriptor of a dialect in the registry.
pub fn descriptor(dialect: &str) -> Option<&'static SimDialect> {
    SIMULATORS.iter().find(|s| s.dialect == dialect)
}

/// The simulated stage's limits for the continuous planner (module docs): `None` where its
/// descriptor does not say how it moves; an error for a stage that is not a simulated rotator.
pub fn stage_limits(sim: &Simulation) -> Result<Option<StageLimits>, PlanError> {
    let (dialect, _) = resolve(sim.stage.as_ref())?;
    let Some(motion) = descriptor(dialect).and_then(|d| d.motion) else {
        return Ok(None);
    };
    let cruise_deg_per_s = sim.stage_deg_per_s;
    Ok(Some(StageLimits {
        max_speed_rad_per_s: cruise_deg_per_s.min(motion.max_spin_deg_per_s).to_radians(),
        acceleration_rad_per_s2: (cruise_deg_per_s / motion.ramp_s).to_radians(),
    }))
}

/// The simulated rig's timing for forecasts ([`Timing::simulated`]) with its stage's limits.
pub fn timing(plan: &Plan) -> Result<Timing, PlanError> {
    Ok(Timing::simulated(plan, stage_limits(&plan.simulation)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn simulation(stage: Option<SimStage>, stage_deg_per_s: f64) -> Simulation {
        Simulation {
            stage,
            stage_deg_per_s,
            ..Simulation::default()
        }
    }

    /// The default stage's limits are its simulator's: the cruise speed, reached in 1/8 s
    /// (the native `at_speed` builds its acceleration as 8 x its velocity), capped at the
    /// velocity mode's 2 turns/s. Exact up to the degree-radian conversion (1e-12 relative).
    #[test]
    fn the_default_stages_limits_are_its_simulators() {
        assert_eq!(default_stage(), ("native", "rotator"));
        let l = stage_limits(&simulation(None, 360.0)).unwrap().unwrap();
        assert!((l.max_speed_rad_per_s.to_degrees() - 360.0).abs() < 1e-9);
        assert!((l.acceleration_rad_per_s2.to_degrees() - 2880.0).abs() < 1e-9);
        let fast = stage_limits(&simulation(None, 1000.0)).unwrap().unwrap();
        assert!((fast.max_speed_rad_per_s.to_degrees() - 720.0).abs() < 1e-9);
        assert!((fast.acceleration_rad_per_s2.to_degrees() - 8000.0).abs() < 1e-9);
    }

    /// A simulated rotator whose descriptor does not say how it moves has no known limits;
    /// a dialect with no simulated rotator is refused, naming the field and the allowed list.
    #[test]
    fn other_stages_limits_are_unknown_and_bad_stages_are_named() {
        let apt = SimStage {
            dialect: "apt".into(),
            model: None,
        };
        assert_eq!(resolve(Some(&apt)).unwrap(), ("apt", "k10cr1"));
        assert!(stage_limits(&simulation(Some(apt), 360.0))
            .unwrap()
            .is_none());
        let wheel = SimStage {
            dialect: "fw102c".into(),
            model: None,
        };
        let e = stage_limits(&simulation(Some(wheel), 360.0))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("simulation.stage.dialect") && e.contains("native"),
            "{e}"
        );
        let slider = SimStage {
            dialect: "elliptec".into(),
            model: Some("ell9".into()),
        };
        let e = resolve(Some(&slider)).unwrap_err().to_string();
        assert!(
            e.contains("simulation.stage.model") && e.contains("ell14"),
            "{e}"
        );
    }
}
