//! Angles and directions at the user boundary: degrees in, exact trigonometry at the quadrants,
//! and the unit vector towards a zenith angle and an azimuth clockwise from north (x east,
//! y north, z up).

use nalgebra::Vector3;

/// `(sin, cos)` of an angle in degrees, exact at every multiple of 90 deg: the argument is reduced
/// to `[-45, 45]` deg in degrees (exact in f64 for `|x| <= 720`) before converting to radians.
pub fn sin_cos_deg(x_deg: f64) -> (f64, f64) {
    let q = (x_deg / 90.0).round();
    let r = (x_deg - 90.0 * q).to_radians();
    let (s, c) = r.sin_cos();
    match (q as i64).rem_euclid(4) {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// Unit vector towards a sky direction, zenith angle and azimuth clockwise from north, degrees.
pub fn direction_from_deg(zenith_deg: f64, azimuth_deg: f64) -> Vector3<f64> {
    let (sz, cz) = sin_cos_deg(zenith_deg);
    let (sa, ca) = sin_cos_deg(azimuth_deg);
    Vector3::new(sz * sa, sz * ca, cz)
}
