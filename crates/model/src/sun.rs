//! Sun position from UTC time and site (MODEL.md section 10), by the NREL Solar Position
//! Algorithm (Reda & Andreas, Solar Energy 76, 577 (2004); NREL/TP-560-34302) as implemented by
//! the `solar-positioning` crate, which validates it against the reference code.
//!
//! User-facing azimuths are clockwise from north (the SPA's convention): 0 north, 90 east.

use crate::error::ModelError;
use solar_positioning::{spa, time::DeltaT, time::JulianDate, RefractionCorrection};

/// An observer's site.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Site {
    /// Geodetic latitude, degrees north, `[-90, 90]`.
    pub latitude_deg: f64,
    /// Longitude, degrees east, `[-180, 180]`.
    pub longitude_deg: f64,
    /// Elevation above sea level, metres, `[-500, 9000]`.
    pub elevation_m: f64,
}

impl Site {
    /// Validates a site; errors name `lat_deg`, `lon_deg` or `elevation_m`.
    pub fn new(
        latitude_deg: f64,
        longitude_deg: f64,
        elevation_m: f64,
    ) -> Result<Self, ModelError> {
        ModelError::check_range("lat_deg", latitude_deg, -90.0, 90.0, "[-90, 90]")?;
        ModelError::check_range("lon_deg", longitude_deg, -180.0, 180.0, "[-180, 180]")?;
        ModelError::check_range("elevation_m", elevation_m, -500.0, 9000.0, "[-500, 9000]")?;
        Ok(Site {
            latitude_deg,
            longitude_deg,
            elevation_m,
        })
    }
}

/// A UTC instant as calendar fields (the model has no clock; callers parse and supply it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UtcTime {
    /// Year, `[-2000, 6000]` (the SPA's validity).
    pub year: i32,
    /// Month, `[1, 12]`.
    pub month: u32,
    /// Day of month, `[1, 31]`.
    pub day: u32,
    /// Hour, `[0, 23]`.
    pub hour: u32,
    /// Minute, `[0, 59]`.
    pub minute: u32,
    /// Second, `[0, 60)`.
    pub second: f64,
}

/// Surface weather for the refraction correction (Bennett's formula inside the SPA).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Weather {
    /// Surface pressure, hPa (= mbar), `(0, 2000)`.
    pub pressure_hpa: f64,
    /// Air temperature, degrees Celsius, `(-273.15, 100)`.
    pub temperature_c: f64,
}

impl Weather {
    /// The standard atmosphere at sea level: 1013.25 hPa, 15 C.
    pub const STANDARD: Weather = Weather {
        pressure_hpa: 1013.25,
        temperature_c: 15.0,
    };

    /// The standard atmosphere's surface pressure at `elevation_m` above sea level, hPa: the
    /// sea-level 1013.25 hPa scaled by `exp(-elevation / 8434 m)` (an isothermal atmosphere's
    /// scale height at 15 C), the default when a site's pressure is not given.
    pub fn standard_pressure_hpa(elevation_m: f64) -> f64 {
        Weather::STANDARD.pressure_hpa * (-elevation_m / 8434.0).exp()
    }
}

/// The sun's topocentric position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SunPosition {
    /// Zenith angle, degrees (refraction-corrected when weather was given).
    pub zenith_deg: f64,
    /// Azimuth, degrees clockwise from north, `[0, 360)`.
    pub azimuth_deg: f64,
    /// The `Delta T = TT - UT` used, seconds.
    pub delta_t_s: f64,
}

/// The SPA's sun position. `delta_t_s = None` uses the Espenak-Meeus polynomial estimate;
/// `weather = None` gives the geometric (unrefracted) position.
pub fn sun_position(
    time: &UtcTime,
    site: &Site,
    delta_t_s: Option<f64>,
    weather: Option<Weather>,
) -> Result<SunPosition, ModelError> {
    let invalid = |field: &'static str, reason: String| ModelError::Invalid { field, reason };
    if !(-2000..=6000).contains(&time.year) {
        return Err(ModelError::OutOfRange {
            field: "time",
            value: time.year as f64,
            allowed: "years -2000 to 6000",
        });
    }
    let delta_t = match delta_t_s {
        Some(d) => ModelError::check_range("delta_t_s", d, -1e4, 1e5, "[-1e4, 1e5] s")?,
        None => {
            let decimal_year = time.year as f64 + (time.month as f64 - 0.5) / 12.0;
            DeltaT::estimate(decimal_year).map_err(|e| invalid("time", e.to_string()))?
        }
    };
    let jd = JulianDate::from_utc(
        time.year,
        time.month,
        time.day,
        time.hour,
        time.minute,
        time.second,
        delta_t,
    )
    .map_err(|e| invalid("time", e.to_string()))?;
    let refraction = match weather {
        Some(w) => Some(
            RefractionCorrection::new(w.pressure_hpa, w.temperature_c)
                .map_err(|e| invalid("pressure_hpa/temperature_c", e.to_string()))?,
        ),
        None => None,
    };
    let p = spa::solar_position_from_julian(
        jd,
        site.latitude_deg,
        site.longitude_deg,
        site.elevation_m,
        refraction,
    )
    .map_err(|e| invalid("site", e.to_string()))?;
    Ok(SunPosition {
        zenith_deg: p.zenith_angle(),
        azimuth_deg: p.azimuth(),
        delta_t_s: delta_t,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// NREL/TP-560-34302, Table A5.1 worked example: 2003-10-17 12:30:30 local (UTC-7),
    /// 39.742476 N, 105.1786 W, 1830.14 m, 820 mbar, 11 C, Delta T 67 s:
    /// topocentric zenith 50.11162 deg, azimuth 194.340241 deg. Tolerance: the printed digits.
    #[test]
    fn nrel_worked_example() {
        let t = UtcTime {
            year: 2003,
            month: 10,
            day: 17,
            hour: 19,
            minute: 30,
            second: 30.0,
        };
        let site = Site::new(39.742476, -105.1786, 1830.14).unwrap();
        let w = Weather {
            pressure_hpa: 820.0,
            temperature_c: 11.0,
        };
        let p = sun_position(&t, &site, Some(67.0), Some(w)).unwrap();
        assert!(
            (p.zenith_deg - 50.11162).abs() < 5e-6,
            "zenith {}",
            p.zenith_deg
        );
        assert!(
            (p.azimuth_deg - 194.340241).abs() < 5e-7,
            "azimuth {}",
            p.azimuth_deg
        );
    }

    /// Equinox noon on the equator at longitude 0: the sun is within about 2 deg of the zenith
    /// (equation of time shifts true noon by minutes, declination is ~0).
    #[test]
    fn equinox_noon_on_the_equator_is_near_zenith() {
        let t = UtcTime {
            year: 2024,
            month: 3,
            day: 20,
            hour: 12,
            minute: 7,
            second: 0.0,
        };
        let p = sun_position(&t, &Site::new(0.0, 0.0, 0.0).unwrap(), None, None).unwrap();
        assert!(p.zenith_deg < 2.0, "{p:?}");
    }

    #[test]
    fn bad_inputs_name_the_field() {
        let e = Site::new(91.0, 0.0, 0.0).unwrap_err().to_string();
        assert!(e.contains("lat_deg") && e.contains("91"), "{e}");
        let t = UtcTime {
            year: 2024,
            month: 13,
            day: 1,
            hour: 0,
            minute: 0,
            second: 0.0,
        };
        let e = sun_position(&t, &Site::new(0.0, 0.0, 0.0).unwrap(), None, None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("time"), "{e}");
    }
}
