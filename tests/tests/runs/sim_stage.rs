//! The simulated rig's stage choice (`[simulation] stage`): a rotator of any dialect's
//! simulator from the simulators' registry, driven through its dialect's real driver over a
//! pseudo-terminal, and the checks that name the field, the value and what is allowed.
#![allow(clippy::unwrap_used)]

use polar_engine::plan::Plan;
use polar_engine::store::RunStore;
use polar_rig::sim_stage;
use polar_rig::SimRig;
use std::path::Path;

use super::common;
use common::{check_frame_set, done, go, temp_dir, Script};

/// The runs tests' capture (3 sets of 4 angles, a dark before and after, 96 x 72) with the
/// analyzer on `stage`.
fn capture(stage: &str) -> String {
    format!(
        r#"
name = "capture-stage"
kind = "capture"
[capture]
angles_deg = [0, 45, 90, 135]
exposure_us = [300]
repeats = 3
darks_before = 1
darks_after = 1
[storage]
products = "all"   # S1, S2 and their sigmas are judged against the truth
[simulation]
width = 96
height = 72
seed = 3
stage = {stage}
"#
    )
}

/// The capture on the simulated PRM1Z8 on its KDC101 (`stage = { dialect = "apt", model =
/// "prm1z8" }`), through the APT driver the dialects' registry gives: every frame is stored,
/// the run's devices record names the APT PRM1Z8, each light frame's measured angle is within
/// 0.1 deg of its command (the driver's tolerance is 0.01 deg; the servo dithers by 0.5
/// count, 0.0003 deg), and the Stokes products agree with the truth as on our firmware's
/// stage: 93-97.5 % of the values within 2 predicted sigma (an unbiased Gaussian estimate puts
/// 95.45 % there; the 20736 values give a sampling spread of 0.15 %).
#[test]
fn capture_on_the_simulated_prm1z8() {
    let plan = Plan::from_toml_str(&capture(r#"{ dialect = "apt", model = "prm1z8" }"#)).unwrap();
    let dir = temp_dir("stage-prm1z8");
    let (o, _, _) = go(&plan, &dir, false, Script::Watch);
    let s = done(&o);
    assert_eq!((s.frames_accepted, s.sets_accepted), (14, 3));
    check_frame_set(&dir, 14);
    let store = RunStore::open(&dir).unwrap();
    let stage = &store.attributes().unwrap()["devices"]["stage"];
    assert_eq!(
        (stage["dialect"].as_str(), stage["model"].as_str()),
        (Some("apt"), Some("prm1z8")),
        "{stage}"
    );
    assert!(
        stage["driver"]
            .as_str()
            .is_some_and(|d| d.starts_with("Thorlabs PRM1Z8 on KDC101")),
        "{stage}"
    );
    for r in store.read_frame_metadata().unwrap() {
        if r.kind == polar_engine::FrameKind::Light {
            let d = (r.commanded_angle_deg - r.measured_angle_deg).rem_euclid(180.0);
            assert!(d.min(180.0 - d) < 0.1, "frame {}: {d} deg off", r.index);
        }
    }
    let world = SimRig::world(&plan, Path::new(".")).unwrap();
    let scale = world.camera_model.gain_dn_per_e * world.sensor.responsivity_e_per_s() * 300e-6;
    let (mut within, mut total) = (0usize, 0usize);
    for slot in 0..3 {
        let img = |n: &str| store.read_product(n, slot).unwrap();
        let est = [img("s0"), img("s1"), img("s2")];
        let sig = [img("sigma_s0"), img("sigma_s1"), img("sigma_s2")];
        for (p, t) in world.scene.stokes.iter().enumerate() {
            for c in 0..3 {
                let z = (f64::from(est[c][p]) - t[c] * scale) / f64::from(sig[c][p]);
                total += 1;
                within += usize::from(z.abs() < 2.0);
            }
        }
    }
    let share = within as f64 / total as f64;
    println!("PRM1Z8 capture: {:.2} % within 2 sigma", 100.0 * share);
    assert!((0.93..=0.975).contains(&share), "{:.2} %", 100.0 * share);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The rotators on offer come from the simulators' registry (wheels and sliders excluded);
/// a dialect without a simulated rotator and a model that is not one of the dialect's
/// rotators are refused by the simulated rig's check (what `plan check` and `acquire run
/// --simulate` call) naming the field, the value and what is allowed; an unknown key is
/// refused by the plan's parser; a plan
/// without a stage serialises without the key (its stored plan is unchanged); the example
/// plan `examples/plans/capture_k10cr1.toml` chooses the K10CR1.
#[test]
fn stage_choice_is_checked() {
    assert_eq!(
        sim_stage::rotators(),
        [
            ("native", "rotator"),
            ("elliptec", "ell14"),
            ("elliptec", "ell18"),
            ("apt", "k10cr1"),
            ("apt", "prm1z8"),
            ("smc100", "pr50cc"),
            ("smc100", "urs"),
            ("smc100", "conex-agp"),
            ("standa", "8mpr16-1")
        ]
    );
    let default_model = Plan::from_toml_str(&capture(r#"{ dialect = "apt" }"#)).unwrap();
    let stage = default_model.simulation.stage.as_ref().unwrap();
    assert_eq!(sim_stage::resolve(Some(stage)).unwrap(), ("apt", "k10cr1"));
    let refused = |stage: &str| {
        let plan = Plan::from_toml_str(&capture(stage)).unwrap();
        let e = SimRig::validate(&plan, Path::new("."))
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            format!(
                "simulation: {}",
                sim_stage::resolve(plan.simulation.stage.as_ref()).unwrap_err()
            )
        );
        e
    };
    let e = refused(r#"{ dialect = "fw102c" }"#);
    assert!(
        e.contains("simulation.stage.dialect = \"fw102c\"")
            && e.contains("allowed one of native, elliptec, apt"),
        "{e}"
    );
    let e = refused(r#"{ dialect = "elliptec", model = "ell6" }"#);
    assert!(
        e.contains("simulation.stage.model = \"ell6\"")
            && e.contains("allowed one of ell14, ell18"),
        "{e}"
    );
    let e = Plan::from_toml_str(&capture(r#"{ dialect = "apt", speed = 3 }"#))
        .unwrap_err()
        .to_string();
    assert!(e.contains("speed"), "{e}");
    let plain = Plan::from_toml_str(
        &capture("{ dialect = \"native\" }").replace("stage = { dialect = \"native\" }\n", ""),
    )
    .unwrap();
    assert!(plain.simulation.stage.is_none());
    let json = serde_json::to_string(&plain).unwrap();
    assert!(!json.contains("\"stage\""), "{json}");
    let example =
        Plan::from_toml_str(include_str!("../../../examples/plans/capture_k10cr1.toml")).unwrap();
    let stage = example.simulation.stage.as_ref().unwrap();
    assert_eq!(sim_stage::resolve(Some(stage)).unwrap(), ("apt", "k10cr1"));
}
