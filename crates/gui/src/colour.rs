//! False colour: a perceptual map for scalar images, and AoP as hue with DoLP as saturation.

use std::f32::consts::FRAC_PI_2;

/// An RGB colour, 8 bits a channel.
pub type Rgb = [u8; 3];

/// Colour of non-finite pixels (saturated or masked).
pub const NAN_COLOUR: Rgb = [0, 0, 0];

/// Brightness of the AoP/DoLP map: DoLP 0 is this grey.
pub const AOP_VALUE: f32 = 0.85;

/// Stops of the viridis map, at equal steps from 0 to 1.
const VIRIDIS: [[f32; 3]; 9] = [
    [0.267, 0.005, 0.329],
    [0.279, 0.175, 0.483],
    [0.230, 0.322, 0.546],
    [0.173, 0.449, 0.558],
    [0.128, 0.567, 0.551],
    [0.157, 0.684, 0.502],
    [0.369, 0.789, 0.383],
    [0.678, 0.864, 0.190],
    [0.993, 0.906, 0.144],
];

fn to_u8(x: f32) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// The viridis colour of `t` in `[0, 1]` (clamped; NaN gives [`NAN_COLOUR`]).
pub fn viridis(t: f32) -> Rgb {
    if !t.is_finite() {
        return NAN_COLOUR;
    }
    let x = t.clamp(0.0, 1.0) * (VIRIDIS.len() - 1) as f32;
    let i = (x.floor() as usize).min(VIRIDIS.len() - 2);
    let f = x - i as f32;
    let (a, b) = (VIRIDIS[i], VIRIDIS[i + 1]);
    [
        to_u8(a[0] + f * (b[0] - a[0])),
        to_u8(a[1] + f * (b[1] - a[1])),
        to_u8(a[2] + f * (b[2] - a[2])),
    ]
}

/// The viridis colour of `v` on the scale `[lo, hi]`.
pub fn scalar(v: f32, lo: f32, hi: f32) -> Rgb {
    if !v.is_finite() {
        return NAN_COLOUR;
    }
    let span = hi - lo;
    let t = if span > 0.0 && span.is_finite() {
        (v - lo) / span
    } else {
        0.5
    };
    viridis(t)
}

/// HSV (all in `[0, 1]`, hue wrapping) to RGB.
pub fn hsv(h: f32, s: f32, v: f32) -> Rgb {
    let h = h.rem_euclid(1.0) * 6.0;
    let s = s.clamp(0.0, 1.0);
    let v = v.clamp(0.0, 1.0);
    let i = h.floor();
    let f = h - i;
    let p = v * (1.0 - s);
    let q = v * (1.0 - s * f);
    let t = v * (1.0 - s * (1.0 - f));
    let (r, g, b) = match i as u32 % 6 {
        0 => (v, t, p),
        1 => (q, v, p),
        2 => (p, v, t),
        3 => (p, q, v),
        4 => (t, p, v),
        _ => (v, p, q),
    };
    [to_u8(r), to_u8(g), to_u8(b)]
}

/// The hue of an AoP in radians: `-pi/2` and `+pi/2` (the same direction) are the same hue.
pub fn aop_hue(aop_rad: f32) -> f32 {
    ((aop_rad + FRAC_PI_2) / std::f32::consts::PI).rem_euclid(1.0)
}

/// AoP as hue, DoLP as saturation (DoLP `dolp_full` or more: full saturation); DoLP 0 is
/// grey. Non-finite inputs give [`NAN_COLOUR`].
pub fn aop_dolp(aop_rad: f32, dolp: f32, dolp_full: f32) -> Rgb {
    if !aop_rad.is_finite() || !dolp.is_finite() {
        return NAN_COLOUR;
    }
    let s = if dolp_full > 0.0 {
        dolp / dolp_full
    } else {
        0.0
    };
    hsv(aop_hue(aop_rad), s, AOP_VALUE)
}

/// A robust display range of `values`: the 1st and 99th percentiles of the finite values
/// (`None` if there are none).
pub fn robust_range(values: &[f32]) -> Option<(f32, f32)> {
    let mut v: Vec<f32> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(0.01), at(0.99));
    if hi > lo {
        Some((lo, hi))
    } else {
        Some((lo, lo + 1.0))
    }
}

/// Counts of the finite `values` in `bins` equal bins over `[lo, hi]` (outside: clamped to
/// the end bins).
pub fn histogram(values: &[f32], lo: f32, hi: f32, bins: usize) -> Vec<u32> {
    let mut h = vec![0u32; bins];
    if bins == 0 || hi <= lo || !lo.is_finite() || !hi.is_finite() {
        return h;
    }
    let scale = bins as f32 / (hi - lo);
    for &x in values {
        if x.is_finite() {
            let b = ((x - lo) * scale).floor().clamp(0.0, (bins - 1) as f32) as usize;
            h[b] += 1;
        }
    }
    h
}
