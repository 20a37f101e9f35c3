//! What the drivers' pseudo-terminal tests share: the simulator's clock and truth read together.

use polar_hil_mocks::serve::SimServer;
use polar_hil_mocks::sim::Truth;

/// The simulator's clock and the stage's true angle (deg) and motion, the clock read on both
/// sides of the truth (their midpoint; the reads are microseconds apart).
pub fn sample(server: &SimServer) -> (f64, f64, bool) {
    let t0 = server.now_s();
    let truth = server.truth();
    let t1 = server.now_s();
    match truth {
        Truth::Angle { output_rad, moving } => (0.5 * (t0 + t1), output_rad.to_degrees(), moving),
        t => panic!("not a rotator: {t:?}"),
    }
}
