//! The relative optical air mass of the sun's slant path through the atmosphere, and the
//! pseudo-spherical solar cosine it gives the beam's attenuation.

/// Kasten & Young (Appl. Opt. 28, 4735 (1989)) relative air mass at zenith angle (degrees):
/// `1 / (cos z + 0.50572 (96.07995 - z)^-1.6364)`; 1 at the zenith, 37.92 at the horizon.
pub fn air_mass(zenith_deg: f64) -> f64 {
    let z = zenith_deg.clamp(0.0, 90.0);
    1.0 / (z.to_radians().cos() + 0.50572 * (96.07995 - z).powf(-1.6364))
}

/// The pseudo-spherical solar cosine `1 / m(z)`, `m` the Kasten-Young air mass: the sun beam's
/// attenuation along its slant path through the layer uses it in place of `mu0` (the
/// pseudo-spherical approximation, Dahlback & Stamnes, Planet. Space Sci. 39, 671 (1991)), so
/// the sky and the path radiance stay lit with the sun at the horizon, consistently with the
/// direct beam's air mass. Normalised to be exactly 1 at the zenith (the fit gives
/// `m(0) = 0.99971`); within 0.3 % of `mu0` up to 60 deg zenith, 3 % at 80 deg, and 0.026
/// instead of 0 at the horizon, where the plane-parallel layer fails. 0 for the sun below the
/// horizon.
pub fn slant_mu0(mu0: f64) -> f64 {
    if mu0 < 0.0 || !mu0.is_finite() {
        0.0
    } else {
        air_mass(0.0) / air_mass(mu0.min(1.0).acos().to_degrees())
    }
}
