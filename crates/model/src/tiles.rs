//! Per-tile viewing geometry of a sensor above flat ground (MODEL.md section 11, Meng (2012)'s
//! Appendix A, reconstructed): a pinhole camera at height `H` looks down with its boresight
//! `theta_v0` off nadir towards azimuth `phi_l`; its field of view is split into `nx x ny` tiles;
//! the ray through each tile centre is intersected with the ground. For each tile the scene
//! needs the sun and view zenith angles, the relative azimuth of [`crate::pbrdf`]'s convention,
//! and the rotation that carries the reflected Stokes vector from the surface's frame into the
//! camera's.
//!
//! World frame: x east, y north, z up (right-handed); user-facing azimuths are clockwise from
//! north. Camera frame: image x axis `right = (cos phi_l, -sin phi_l, 0)` (horizontal, to the
//! right of the look direction), image up `u = right × b` for boresight `b`; the Stokes frame of
//! a ray arriving at the camera has `x` = `right` made transverse to the ray, `y = k × x`, so an
//! analyzer at `psi = 0` passes light polarised along the image rows.

use crate::angles::{direction_from_deg, sin_cos_deg};
use crate::error::ModelError;
pub use crate::geometry::reflected_frame_x;
use crate::geometry::Geometry;
use crate::polarization::cos_sin_2eta;
use nalgebra::Vector3;

/// Where the sensor is and where it looks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pointing {
    /// Height of the sensor above the ground, metres, `(0, 1e5]`.
    pub altitude_m: f64,
    /// Boresight angle from nadir, degrees, `[0, 89]`.
    pub off_nadir_deg: f64,
    /// Azimuth the boresight looks towards, degrees clockwise from north.
    pub look_azimuth_deg: f64,
    /// Full field of view across and along the image, degrees, each `(0, 120]`.
    pub fov_deg: (f64, f64),
}

/// The geometry of one tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tile {
    /// Column and row of the tile (column 0 on the image's left, row 0 at the image's top).
    pub index: (usize, usize),
    /// Sun zenith angle (same for every tile on flat ground), degrees.
    pub theta_i_deg: f64,
    /// View zenith angle of the ground point (ground-to-sensor direction), degrees.
    pub theta_r_deg: f64,
    /// Relative azimuth in the pBRDF's convention (180 deg = specular plane), degrees `[0, 360)`.
    pub phi_deg: f64,
    /// The ground point, metres east and north of the sensor's nadir point.
    pub ground_m: [f64; 2],
    /// Slant range from the sensor, metres.
    pub range_m: f64,
    /// Unit vector from the ground point towards the sensor (world frame).
    pub omega_view: Vector3<f64>,
    /// The pBRDF geometry of the tile.
    pub geometry: Geometry,
    /// `(cos 2eta, sin 2eta)` of the rotation camera frame <- reflected surface frame:
    /// `S_camera = rotation_from_cos_sin_2eta(c, s) S_surface`.
    pub camera_from_surface: (f64, f64),
}

/// A validated sensor view of flat ground under the sun: computes the geometry of the ray through
/// any point of the image plane (for tiles, or for quadrature nodes over the field of view).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Field {
    altitude_m: f64,
    boresight: Vector3<f64>,
    right: Vector3<f64>,
    up: Vector3<f64>,
    half_tan: (f64, f64),
    omega_sun: Vector3<f64>,
    sun_zenith_deg: f64,
}

impl Field {
    /// Validates the pointing and the sun. Errors name `altitude_m`, `off_nadir_deg`,
    /// `look_azimuth_deg`, `fov_deg`, `sun_zenith_deg` or `sun_azimuth_deg`.
    pub fn new(
        pointing: &Pointing,
        sun_zenith_deg: f64,
        sun_azimuth_deg: f64,
    ) -> Result<Field, ModelError> {
        let p = pointing;
        if !(p.altitude_m.is_finite() && p.altitude_m > 0.0 && p.altitude_m <= 1e5) {
            return Err(ModelError::OutOfRange {
                field: "altitude_m",
                value: p.altitude_m,
                allowed: "(0, 1e5]",
            });
        }
        ModelError::check_range("off_nadir_deg", p.off_nadir_deg, 0.0, 89.0, "[0, 89]")?;
        ModelError::check_range(
            "look_azimuth_deg",
            p.look_azimuth_deg,
            -360.0,
            360.0,
            "[-360, 360]",
        )?;
        for v in [p.fov_deg.0, p.fov_deg.1] {
            if !(v.is_finite() && v > 0.0 && v <= 120.0) {
                return Err(ModelError::OutOfRange {
                    field: "fov_deg",
                    value: v,
                    allowed: "(0, 120] each",
                });
            }
        }
        ModelError::check_range("sun_zenith_deg", sun_zenith_deg, 0.0, 90.0, "[0, 90]")?;
        ModelError::check_range(
            "sun_azimuth_deg",
            sun_azimuth_deg,
            -360.0,
            360.0,
            "[-360, 360]",
        )?;
        let boresight = -direction_from_deg(p.off_nadir_deg, p.look_azimuth_deg + 180.0); // from sensor, downwards
        let (sl, cl) = sin_cos_deg(p.look_azimuth_deg);
        let right = Vector3::new(cl, -sl, 0.0);
        Ok(Field {
            altitude_m: p.altitude_m,
            boresight,
            right,
            up: right.cross(&boresight),
            half_tan: (
                (0.5 * p.fov_deg.0).to_radians().tan(),
                (0.5 * p.fov_deg.1).to_radians().tan(),
            ),
            omega_sun: direction_from_deg(sun_zenith_deg, sun_azimuth_deg),
            sun_zenith_deg,
        })
    }

    /// Unit vector towards the sun (world frame).
    pub fn omega_sun(&self) -> Vector3<f64> {
        self.omega_sun
    }

    /// The geometry of the ray through image-plane point `(u, v)`, each in `[-1, 1]` (`u = 1` at
    /// the right edge, `v = 1` at the top), labelled `index`. Errors name `fov_deg` when the ray
    /// does not reach the ground (looks above the horizon).
    pub fn ray(&self, u: f64, v: f64, index: (usize, usize)) -> Result<Tile, ModelError> {
        let d =
            (self.boresight + self.right * (u * self.half_tan.0) + self.up * (v * self.half_tan.1))
                .normalize();
        if d.z >= -1e-9 {
            return Err(ModelError::Invalid {
                field: "fov_deg",
                reason: format!(
                    "the ray at image point ({u:.3}, {v:.3}) looks {:.3} deg above the horizon: reduce fov_deg or off_nadir_deg",
                    d.z.asin().to_degrees()
                ),
            });
        }
        let t = self.altitude_m / -d.z;
        let ground = Vector3::new(0.0, 0.0, self.altitude_m) + d * t;
        let omega_view = -d;
        let geometry = Geometry::from_directions(&self.omega_sun, &omega_view)?;
        let phi_deg = geometry.relative_azimuth_rad().to_degrees();
        // Camera Stokes frame of this ray: `right` made transverse to k = omega_view.
        let k = omega_view;
        let x_cam = (self.right - k * self.right.dot(&k)).normalize();
        let s_r = reflected_frame_x(&self.omega_sun, &omega_view);
        Ok(Tile {
            index,
            theta_i_deg: self.sun_zenith_deg,
            theta_r_deg: omega_view.z.clamp(-1.0, 1.0).acos().to_degrees(),
            phi_deg,
            ground_m: [ground.x, ground.y],
            range_m: t,
            omega_view,
            geometry,
            camera_from_surface: cos_sin_2eta(&s_r, &x_cam, &k),
        })
    }
}

/// Splits the field of view into `nx x ny` tiles and returns their geometry, row-major from the
/// top-left. Errors name `altitude_m`, `off_nadir_deg`, `fov_deg`, `tiles`, `sun_zenith_deg`, or
/// `fov_deg` again when a tile's ray does not reach the ground (looks above the horizon).
pub fn tiles(
    pointing: &Pointing,
    (nx, ny): (usize, usize),
    sun_zenith_deg: f64,
    sun_azimuth_deg: f64,
) -> Result<Vec<Tile>, ModelError> {
    let field = Field::new(pointing, sun_zenith_deg, sun_azimuth_deg)?;
    if nx == 0 || ny == 0 || nx * ny > 1_000_000 {
        return Err(ModelError::Invalid {
            field: "tiles",
            reason: format!("{nx}x{ny}: allowed 1x1 to 1000000 tiles in all"),
        });
    }
    let mut out = Vec::with_capacity(nx * ny);
    for row in 0..ny {
        for col in 0..nx {
            // Tile centre on the image plane.
            let u = (col as f64 + 0.5) / nx as f64 * 2.0 - 1.0;
            let v = 1.0 - (row as f64 + 0.5) / ny as f64 * 2.0;
            out.push(field.ray(u, v, (col, row))?);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fresnel::RefractiveIndex;
    use crate::pbrdf::Surface;
    use crate::polarization::{analyzer_row, rotation_from_cos_sin_2eta};

    fn pointing(off: f64, look: f64, fov: f64) -> Pointing {
        Pointing {
            altitude_m: 1000.0,
            off_nadir_deg: off,
            look_azimuth_deg: look,
            fov_deg: (fov, fov),
        }
    }

    /// One tile at nadir: view zenith 0, ground point under the sensor.
    #[test]
    fn nadir_single_tile() {
        let t = tiles(&pointing(0.0, 0.0, 1.0), (1, 1), 30.0, 90.0).unwrap();
        assert_eq!(t.len(), 1);
        assert!(
            t[0].theta_r_deg.abs() < 1e-12
                && t[0].ground_m[0].abs() < 1e-9
                && t[0].ground_m[1].abs() < 1e-9
        );
        assert!((t[0].range_m - 1000.0).abs() < 1e-9);
    }

    /// Off-nadir boresight: the centre tile of an odd grid lies at H tan(theta_v0) along the look
    /// azimuth and has view zenith theta_v0. Looking away from the sun (look azimuth = sun azimuth
    /// plus 180) puts the ground point on the anti-sun side, seen from the sun's side: relative
    /// azimuth 0 (backscatter). Looking towards the sun gives 180 (specular plane).
    #[test]
    fn off_nadir_centre_tile_and_relative_azimuth() {
        for (look, want_phi) in [(0.0, 180.0), (180.0, 0.0)] {
            let t = tiles(&pointing(45.0, look, 10.0), (3, 3), 40.0, 0.0).unwrap();
            let c = &t[4];
            assert_eq!(c.index, (1, 1));
            assert!((c.theta_r_deg - 45.0).abs() < 1e-9, "{c:?}");
            let dist = c.ground_m[0].hypot(c.ground_m[1]);
            assert!((dist - 1000.0).abs() < 1e-6);
            assert!(
                (c.phi_deg - want_phi).abs() < 1e-9 || (c.phi_deg - want_phi - 360.0).abs() < 1e-9,
                "look {look}: {}",
                c.phi_deg
            );
        }
    }

    /// MODEL.md section 11's check: horizontally polarised light at nadir peaks at psi = 0.
    /// Looking straight down with the image's rows east-west (look azimuth 0), a glass surface
    /// lit from the east reflects light polarised perpendicular to the plane of incidence (s),
    /// i.e. north-south; with the sun in the north the s direction is east-west = image rows,
    /// so the analyzer response peaks at psi = 0.
    #[test]
    fn nadir_s_polarisation_peaks_at_psi_zero_when_along_the_rows() {
        // The analyzer angle (whole degrees) of maximum response at nadir, sun at 55 deg zenith.
        let peak_psi_deg = |sun_azimuth_deg: f64| {
            let glass =
                Surface::microfacet(RefractiveIndex::new(1.52, 0.0).unwrap(), 0.5, 0.0).unwrap();
            let t = tiles(&pointing(0.0, 0.0, 1.0), (1, 1), 55.0, sun_azimuth_deg).unwrap();
            let f = glass.specular(&t[0].geometry);
            let (c, s) = t[0].camera_from_surface;
            let cam = rotation_from_cos_sin_2eta(c, s).apply(&f.response_to_unpolarized());
            (0..180)
                .map(|d| (d, analyzer_row((d as f64).to_radians()).dot(&cam.0)))
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap()
                .0
        };
        let north = peak_psi_deg(0.0);
        assert!(north == 0 || north == 179, "peak at psi = {north} deg");
        // Sun in the east instead: s is north-south, the peak moves to 90 deg.
        assert_eq!(peak_psi_deg(90.0), 90);
    }

    #[test]
    fn rays_above_the_horizon_and_bad_inputs_are_errors() {
        let e = tiles(&pointing(80.0, 0.0, 30.0), (3, 3), 30.0, 0.0)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("fov_deg") && e.contains("above the horizon"),
            "{e}"
        );
        let e = tiles(&pointing(0.0, 0.0, 10.0), (0, 3), 30.0, 0.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("tiles"), "{e}");
        let mut p = pointing(0.0, 0.0, 10.0);
        p.altitude_m = -1.0;
        assert!(tiles(&p, (1, 1), 30.0, 0.0)
            .unwrap_err()
            .to_string()
            .contains("altitude_m"));
    }
}
