//! A tabulated sky's error floor for one material ([`Prepared::table_floor`]).

use super::budget::*;
use super::points::*;
use super::prepared::*;
use crate::error::ModelError;
use crate::pbrdf::Surface;

impl Prepared {
    /// A tabulated sky's error floor for `surface`, before the field is integrated: the
    /// centre ray's reflected skylight with the table and with its half-resolution copy, the
    /// change halved (the least a convergent interpolant gains from halving its step) plus
    /// both integrals' quadrature errors halved. The probes start at [`FLOOR_PROBE_TOL`] of
    /// `S0` (or the scene's tolerance / 8 if looser) and are tightened by 8, down to the scene's
    /// tolerance / 8, while their quadrature errors exceed a quarter of the change: so the floor
    /// is the table's, not the probes'. `None` for a sky that is not a table, or a table too
    /// coarse to halve.
    pub(super) fn table_floor(&self, surface: &Surface) -> Result<Option<FloorProbe>, ModelError> {
        let Sky::Table(t) = &self.sky else {
            return Ok(None);
        };
        if t.coarse.is_none() {
            return Ok(None);
        }
        let theta_sun = self.spec.sun_zenith_deg.to_radians();
        let centre = self.field.ray(0.0, 0.0, (0, 0))?;
        let mut tol_probe = (self.tol / 8.0).max(FLOOR_PROBE_TOL);
        let diffuse = Lambertian::at(surface, theta_sun, tol_probe / 64.0)?;
        let mut evaluations = diffuse.evaluations;
        let base = Include {
            skylight: false,
            path: true,
            tol_abs: 0.0,
            coarse_table: false,
            hint: None,
            certified: None,
        };
        let cheap = self.point(surface, diffuse.f00, &centre, base)?;
        let mut scale = cheap.total[0]
            .abs()
            .max(1e-2 * self.white_radiance())
            .max(1e-300);
        loop {
            let full = Include {
                skylight: true,
                tol_abs: tol_probe * scale,
                ..base
            };
            let half = Include {
                coarse_table: true,
                ..full
            };
            let (h, f) = rayon::join(
                || self.point(surface, diffuse.f00, &centre, half),
                || self.point(surface, diffuse.f00, &centre, full),
            );
            let (h, f) = (h?, f?);
            evaluations += h.evaluations + f.evaluations;
            let change = (h.sky - f.sky).norm();
            let quadrature = h.sky_error + f.sky_error;
            let s0 = f.total[0].abs().max(1e-300);
            if quadrature <= change / 4.0 || tol_probe <= self.tol / 8.0 {
                return Ok(Some(FloorProbe {
                    floor: (change + quadrature) / 2.0,
                    s0,
                    evaluations,
                    grid: t.full.grid(),
                }));
            }
            tol_probe = (tol_probe / 8.0).max(self.tol / 8.0);
            scale = s0;
        }
    }
}
