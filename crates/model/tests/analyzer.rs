//! The classic reconstruction methods of Meng (2012) Sec. 2.4 are special cases of `W^+`; noise gains
//! and the real-analyzer model.

#![allow(clippy::unwrap_used)] // tests panic on failure by design

use polar_model::analyzer::{
    modified_pickering, pickering, three_angle_0_60_120, AnalyzerModel, AnalyzerSet,
};
use polar_model::polarization::Stokes;
use proptest::prelude::*;

fn set(deg: &[f64]) -> AnalyzerSet {
    AnalyzerSet::ideal(&deg.iter().map(|a| a.to_radians()).collect::<Vec<_>>()).unwrap()
}

proptest! {
    /// For arbitrary (even inconsistent, e.g. noisy) intensities the closed forms equal `W^+ I`
    /// to 1e-12 relative: three angles make `W` square, and for 0/45/90/135 the closed form is
    /// the least-squares solution.
    #[test]
    fn classic_methods_equal_pseudo_inverse(i in prop::array::uniform4(0.0f64..1e3)) {
        let close = |a: Stokes, b: Stokes| (a.0 - b.0).norm() <= 1e-12 * (1.0 + a.0.norm());
        let p = set(&[0.0, 45.0, 90.0]).reconstruct(&i[..3]).unwrap();
        prop_assert!(close(p, pickering(i[0], i[1], i[2])));
        let t = set(&[0.0, 60.0, 120.0]).reconstruct(&i[..3]).unwrap();
        prop_assert!(close(t, three_angle_0_60_120(i[0], i[1], i[2])));
        let m = set(&[0.0, 45.0, 90.0, 135.0]).reconstruct(&i).unwrap();
        prop_assert!(close(m, modified_pickering(i[0], i[1], i[2], i[3])));
    }
}

/// Noise gains equal the sums of squared coefficients of the closed forms: Pickering
/// `S0 = I0 + I90` (2), `S1 = I0 - I90` (2), `S2 = 2 I45 - I0 - I90` (6); 0/60/120:
/// 4/9 * 3 = 4/3, 4/9 * 6 = 8/3, 4/3 * 2 = 8/3; modified Pickering 4 * 1/4 = 1, 2, 2.
#[test]
fn noise_gains_match_closed_forms() {
    let cases: [(&[f64], [f64; 3]); 3] = [
        (&[0.0, 45.0, 90.0], [2.0, 2.0, 6.0]),
        (&[0.0, 60.0, 120.0], [4.0 / 3.0, 8.0 / 3.0, 8.0 / 3.0]),
        (&[0.0, 45.0, 90.0, 135.0], [1.0, 2.0, 2.0]),
    ];
    for (angles, want) in cases {
        let g = set(angles).noise_gains();
        for k in 0..3 {
            assert!(
                (g[k] - want[k]).abs() < 1e-12,
                "{angles:?}: gain {k} = {}",
                g[k]
            );
        }
    }
}

/// A real analyzer (extinction ratio 100, offset 2 deg) measured and reconstructed with its own
/// model is exact; reconstructed with the ideal model it biases DoLP low by the analyzer's
/// diattenuation `(k1 - k2)/(k1 + k2) = 99/101` and rotates AoP by minus the offset (the analyzer
/// sits 2 deg further than commanded, so the scene appears turned by -2 deg).
#[test]
fn real_analyzer_model() {
    let real = AnalyzerModel::from_extinction_ratio(100.0, 2f64.to_radians()).unwrap();
    let angles: Vec<f64> = [0.0f64, 45.0, 90.0, 135.0]
        .iter()
        .map(|a| a.to_radians())
        .collect();
    let real_set = AnalyzerSet::new(&angles, &real).unwrap();
    let s = Stokes::new(2.0, 0.6, -0.3);
    let i: Vec<f64> = real_set.intensities(&s).iter().copied().collect();
    let back = real_set.reconstruct(&i).unwrap();
    assert!((back.0 - s.0).norm() < 1e-12);
    let naive = AnalyzerSet::ideal(&angles)
        .unwrap()
        .reconstruct(&i)
        .unwrap();
    let ratio = naive.dolp().unwrap() / s.dolp().unwrap();
    // The ideal-model S0 is (k1 + k2) S0 = 1.01 S0, the polarised part (k1 - k2) p = 0.99 p.
    assert!((ratio - 0.99 / 1.01).abs() < 1e-12, "{ratio}");
    let d_aop = naive.aop_rad().unwrap() - s.aop_rad().unwrap();
    assert!(
        (d_aop + 2f64.to_radians()).abs() < 1e-12,
        "{}",
        d_aop.to_degrees()
    );
    let e = AnalyzerModel::from_extinction_ratio(1.0, 0.0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("extinction_ratio") && e.contains("> 1"), "{e}");
}
