//! A capture on `examples/rigs/sim_8mpr16.toml` through the command's own entry point: the
//! standa dialect's simulator of an 8SMC5-USB with the 8MPR16-1 on a pseudo-terminal, at
//! Standa's own profile for the stage, driven through the Standa driver, the camera rendering
//! through the stage's true angle.

use super::k10cr1::capture_on_a_rig_file;

/// `polarimeter run --rig examples/rigs/sim_8mpr16.toml` with one set of four angles and a
/// dark before and after (`examples/plans/capture_8mpr16.toml`): done, every frame intact, the
/// standa dialect recorded, and 93-97.5 % of the set's Stokes products within 2 predicted sigma
/// of the rendered truth (95.45 % for an unbiased Gaussian estimate; see the K10CR1's test).
/// The stage homes at its real 1.25 deg/s first (about 140 s from where the seeded simulator
/// powers on).
#[test]
fn capture_on_the_simulated_8mpr16_rig_file() {
    capture_on_a_rig_file(
        "sim_8mpr16.toml",
        "examples/plans/capture_8mpr16.toml",
        "standa",
        "8mpr16-1",
    );
}
