//! Every registered dialect against its simulator, through the registry only.

use polar_drivers::registry::{DeviceKind, Position, DIALECTS};
use polar_hal::{signed_difference, FilterWheel, Rotator, TURN_RAD};
use polar_hil_mocks::sim::{Truth, SIMULATORS};
use polar_hil_tests::{scratch, serve_at};

/// The largest backlash of the simulated rotators (our stage's 20 counts of 144000 per turn,
/// 0.05 deg; the ELL14's 10 of 262144): the encoder the readback check reads sits before the
/// backlash, so the true output may lag the readback by up to this much.
const BACKLASH_BOUND_DEG: f64 = 0.05;

/// The speed of the rotators whose simulators can be built at one (native, APT, SMC100):
/// the AG-PR100P's real 1.5 deg/s would take minutes to home; the others run at their real
/// speed.
const TEST_SPEED_DEG_S: f64 = 90.0;

/// Every dialect has a simulator line keyed by its name, and every simulated model is one of
/// the dialect's models: a dialect added without its simulator fails here.
#[test]
fn every_dialect_has_a_simulator() {
    for d in DIALECTS {
        let sim = SIMULATORS.iter().find(|s| s.dialect == d.name);
        let sim = sim.unwrap_or_else(|| panic!("dialect {} has no simulator line", d.name));
        for m in sim.models {
            assert!(
                d.models.contains(m),
                "{}: simulated model {m} not in the registry",
                d.name
            );
        }
    }
}

/// Each simulated model of each dialect, over a real pseudo-terminal at the dialect's baud and
/// line settings: identify reports the kind the registry promises without moving it; a
/// rotator homes, moves to 123.4 deg and reads back within its own tolerance (the readback
/// check), and the simulator's true output angle is within that tolerance plus one count plus
/// [`BACKLASH_BOUND_DEG`]; a
/// wheel selects its last slot, reads it back, and the simulator's truth is that slot.
#[test]
fn every_dialect_through_its_registry_constructor() {
    let dir = scratch("dialects");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let mut covered = Vec::new();
    for d in DIALECTS {
        let Some(sims) = SIMULATORS.iter().find(|s| s.dialect == d.name) else {
            continue; // every_dialect_has_a_simulator reports it
        };
        for model in sims.models {
            let server = {
                let _g = rt.enter();
                serve_at(d.name, model, TEST_SPEED_DEG_S, 7, &dir).unwrap_or_else(|e| panic!("{e}"))
            };
            let port = server.link().expect("a pty link").display().to_string();
            let policy = (d.policy)();
            let what = format!("{} {model}", d.name);
            let id = rt
                .block_on((d.identify)(
                    d.connector(&port),
                    d.default_address(),
                    policy,
                ))
                .unwrap_or_else(|e| panic!("{what}: identify: {e}"));
            assert!(d.provides(id.kind), "{what}: identified as a {:?}", id.kind);
            match id.kind {
                DeviceKind::Rotator => {
                    assert!(
                        matches!(id.position, Position::Angle { .. }),
                        "{what}: {id:?}"
                    );
                    let connect = d.rotator.expect("a rotator constructor");
                    let target = 123.4f64.to_radians();
                    let (info, reached, read) = rt.block_on(async {
                        let mut r = connect(d.connector(&port), d.default_address(), policy)
                            .await
                            .unwrap_or_else(|e| panic!("{what}: connect: {e}"));
                        r.home()
                            .await
                            .unwrap_or_else(|e| panic!("{what}: home: {e}"));
                        let reached = r
                            .move_to(target)
                            .await
                            .unwrap_or_else(|e| panic!("{what}: move: {e}"));
                        let read = r.position_rad().await.expect("position");
                        (r.info().clone(), reached, read)
                    });
                    let tol = info.tolerance_rad;
                    assert!(
                        signed_difference(reached, target, TURN_RAD).abs() <= tol,
                        "{what}: reached {reached}, target {target}, tolerance {tol}"
                    );
                    assert!(
                        signed_difference(read, reached, TURN_RAD).abs() <= tol,
                        "{what}"
                    );
                    let count = TURN_RAD / f64::from(info.counts_per_turn);
                    match server.truth() {
                        Truth::Angle { output_rad, .. } => assert!(
                            signed_difference(output_rad, target, TURN_RAD).abs()
                                <= tol + count + BACKLASH_BOUND_DEG.to_radians(),
                            "{what}: the simulator is at {output_rad} rad"
                        ),
                        t => panic!("{what}: truth {t:?}"),
                    }
                }
                DeviceKind::Wheel => {
                    let connect = d.wheel.expect("a wheel constructor");
                    let (slots, picked, read) = rt.block_on(async {
                        let mut w = connect(d.connector(&port), d.default_address(), policy)
                            .await
                            .unwrap_or_else(|e| panic!("{what}: connect: {e}"));
                        let last = w.slots().len() - 1;
                        let picked = w
                            .select(last)
                            .await
                            .unwrap_or_else(|e| panic!("{what}: select: {e}"));
                        (w.slots().len(), picked, w.slot().await.expect("slot"))
                    });
                    assert_eq!(id.slots, Some(slots), "{what}: identify's slot count");
                    assert_eq!((picked, read), (slots - 1, Some(slots - 1)), "{what}");
                    assert_eq!(
                        server.truth(),
                        Truth::Slot {
                            slot: Some(slots - 1)
                        },
                        "{what}"
                    );
                }
            }
            rt.block_on(server.shutdown());
            covered.push(what);
        }
    }
    println!("covered: {}", covered.join(", "));
    assert!(covered.len() >= DIALECTS.len(), "{covered:?}");
    let _ = std::fs::remove_dir_all(&dir);
}
