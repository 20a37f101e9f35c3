//! An unpolarised sky of uniform radiance.

use crate::polarization::Stokes;
use crate::sky::radiance::SkyRadiance;
use nalgebra::Vector3;

/// An unpolarised sky of uniform radiance (a test case with closed forms, and an overcast sky).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UniformSky {
    /// Radiance.
    pub radiance: f64,
}

impl SkyRadiance for UniformSky {
    fn stokes_from(&self, _towards: &Vector3<f64>) -> Stokes {
        Stokes::unpolarized(self.radiance)
    }
}
