//! A capture on `examples/rigs/sim_pr50cc.toml` through the command's own entry point: the
//! smc100 dialect's simulator of an SMC100CC with a PR50CC on a pseudo-terminal, driven through
//! the SMC100 driver, the camera rendering through the stage's true angle.

use super::k10cr1::capture_on_a_rig_file;

/// `polarimeter run --rig examples/rigs/sim_pr50cc.toml` with one set of four angles and a
/// dark before and after (`tests/fixtures/capture_pr50cc.toml`): done, every frame intact, the
/// smc100 dialect recorded, and 93-97.5 % of the set's Stokes products within 2 predicted sigma
/// of the rendered truth (95.45 % for an unbiased Gaussian estimate; see the K10CR1's test).
#[test]
fn capture_on_the_simulated_pr50cc_rig_file() {
    capture_on_a_rig_file(
        "sim_pr50cc.toml",
        "tests/fixtures/capture_pr50cc.toml",
        "smc100",
        "pr50cc",
    );
}
