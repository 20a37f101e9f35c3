//! The Berry-Dennis-Lee sky: the Rayleigh pattern's neutral points split as multiple scattering
//! splits them.

use crate::sky::radiance::cos_sin_2chi;
use nalgebra::Vector3;

/// The Berry-Dennis-Lee sky (Berry, Dennis & Lee, New J. Phys. 6, 162 (2004)): the Rayleigh
/// pattern's one double neutral point at the sun (and one at the antisun) split into the
/// Babinet and Brewster points `separation` apart above and below the sun (and the Arago point
/// and its partner about the antisun), which is how the real sky, with multiple scattering,
/// looks. In the stereographic chart `zeta = tan(theta / 2) e^{i phi}` the polarisation is
/// `w = -4 (z - zBa)(z - zBr)(z + 1/zBr*)(z + 1/zBa*) / ((1 + |z|^2)^2 |zBa + 1/zBa*| |zBr + 1/zBr*|)`,
/// the DoLP `d_max |w| / (2 - |w|)` and the E-vector at `arg(w e^{-2i phi_sun}) / 2` in the chart. With zero
/// separation it is the Rayleigh pattern (tested).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BerrySky {
    /// Unit vector towards the sun.
    pub sun: Vector3<f64>,
    /// Angle between the Babinet and Brewster points, radians (about 0.5 in a clear sky).
    pub separation_rad: f64,
    /// Largest DoLP (at 90 deg from the sun when the separation is 0).
    pub max_dolp: f64,
}

impl BerrySky {
    /// Chart coordinate of a direction (x east, y north, z up).
    fn chart(d: &Vector3<f64>) -> num_complex::Complex64 {
        let theta = d.z.clamp(-1.0, 1.0).acos();
        let phi = d.y.atan2(d.x);
        num_complex::Complex64::from_polar((0.5 * theta).tan(), phi)
    }

    /// `(DoLP, cos 2chi, sin 2chi)` of light arriving from `towards` (unit, upward), `chi` the
    /// E-vector's angle in the frame of this module (x horizontal) for the ray `-towards`.
    pub fn polarization(&self, towards: &Vector3<f64>) -> (f64, f64, f64) {
        use num_complex::Complex64 as C;
        let theta_s = self.sun.z.clamp(-1.0, 1.0).acos();
        let phi_s = self.sun.y.atan2(self.sun.x);
        let half = 0.5 * self.separation_rad;
        let z_ba = C::from_polar((0.5 * (theta_s - half)).tan(), phi_s);
        let z_br = C::from_polar((0.5 * (theta_s + half)).tan(), phi_s);
        let z = Self::chart(towards);
        // (z + 1/z0*) / |z0 + 1/z0*| = (1 + z z0*) (z0/|z0|) / (1 + |z0|^2): finite at z0 = 0
        // (the sun at the zenith), where z0/|z0| is taken as the sun's azimuth.
        let factor = |z0: C| {
            let unit = if z0.norm() > 1e-12 {
                z0 / z0.norm()
            } else {
                C::from_polar(1.0, phi_s)
            };
            (1.0 + z * z0.conj()) * unit / (1.0 + z0.norm_sqr())
        };
        let w = -4.0 * (z - z_ba) * (z - z_br) * factor(z_ba) * factor(z_br)
            / (1.0 + z.norm_sqr()).powi(2);
        let m = w.norm().min(1.0);
        let dolp = self.max_dolp * m / (2.0 - m);
        let phi = towards.y.atan2(towards.x);
        // The E-vector's chart angle is arg(w e^{-2i phi_s}) / 2 (the inscribed-angle theorem on
        // the circles through the neutral points); on the sphere it is measured from the local
        // radial direction e_theta towards e_phi.
        let chi = 0.5 * w.arg() - phi_s;
        let a = chi - phi;
        let theta = towards.z.clamp(-1.0, 1.0).acos();
        let e_theta = Vector3::new(
            theta.cos() * phi.cos(),
            theta.cos() * phi.sin(),
            -theta.sin(),
        );
        let e_phi = Vector3::new(-phi.sin(), phi.cos(), 0.0);
        let e = e_theta * a.cos() + e_phi * a.sin();
        let (c2, s2) = cos_sin_2chi(&-towards, &e);
        (dolp, c2, s2)
    }
}
