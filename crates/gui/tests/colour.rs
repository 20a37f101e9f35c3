//! The false-colour maps.
#![allow(clippy::unwrap_used)]

use polar_gui::colour::{self, aop_dolp, aop_hue, histogram, robust_range, scalar, viridis};
use std::f32::consts::FRAC_PI_2;

/// AoP -pi/2 and +pi/2 are the same direction: the same hue, the same colour.
#[test]
fn aop_hue_wraps_at_half_pi() {
    let lo = aop_hue(-FRAC_PI_2);
    let hi = aop_hue(FRAC_PI_2 - 1e-6);
    assert!(lo.abs() < 1e-5, "{lo}");
    assert!((hi - 1.0).abs() < 1e-5, "{hi}");
    assert_eq!(
        aop_dolp(-FRAC_PI_2, 0.5, 0.5),
        aop_dolp(FRAC_PI_2, 0.5, 0.5)
    );
    // 0 is half way round the wheel.
    assert!((aop_hue(0.0) - 0.5).abs() < 1e-6);
}

/// DoLP 0 is grey whatever the AoP; full DoLP is saturated.
#[test]
fn dolp_zero_is_grey() {
    for a in [-1.5f32, -0.7, 0.0, 0.4, 1.2] {
        let [r, g, b] = aop_dolp(a, 0.0, 0.3);
        assert_eq!((r, g), (g, b), "AoP {a}: {r} {g} {b}");
        let [r, g, b] = aop_dolp(a, 0.3, 0.3);
        let max = r.max(g).max(b);
        let min = r.min(g).min(b);
        assert_eq!(min, 0, "AoP {a}: full saturation has a zero channel");
        assert!(max > 200);
    }
    assert_eq!(aop_dolp(f32::NAN, 0.2, 0.3), colour::NAN_COLOUR);
}

/// Viridis runs dark purple to yellow; NaN is black; the scale clamps.
#[test]
fn viridis_ends_and_scale() {
    let a = viridis(0.0);
    let b = viridis(1.0);
    assert!(a[2] > a[1] && b[0] > 200 && b[1] > 200);
    assert_eq!(viridis(f32::NAN), colour::NAN_COLOUR);
    assert_eq!(scalar(-5.0, 0.0, 1.0), a);
    assert_eq!(scalar(5.0, 0.0, 1.0), b);
}

/// The display range skips non-finite values; the histogram counts every finite pixel.
#[test]
fn range_and_histogram() {
    let mut v: Vec<f32> = (0..=100).map(|i| i as f32).collect();
    v.push(f32::NAN);
    let (lo, hi) = robust_range(&v).unwrap();
    assert_eq!((lo, hi), (1.0, 99.0));
    let h = histogram(&v, lo, hi, 10);
    assert_eq!(h.iter().sum::<u32>(), 101);
    assert!(robust_range(&[f32::NAN]).is_none());
}
