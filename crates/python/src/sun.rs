//! The sun's position (NREL SPA) over arrays of instants and sites, evaluated per element by
//! the same function as `polarimeter model sun`, so its defaults (pressure from the
//! elevation, 15 C, Delta T estimated) and its checks are the CLI's.

use crate::errors::{element_error, same_length, value_error};
use numpy::ndarray::Array1;
use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1};
use polar_cli::commands::{sun as sun_command, SunArgs};
use pyo3::prelude::*;

/// The zenith and azimuth arrays, degrees.
type SunArrays<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

/// Zenith and azimuth (degrees; azimuth clockwise from north) at equal-length lists of
/// RFC 3339 instants and arrays of latitude, longitude and elevation (the Python layer
/// broadcasts them and writes numpy datetimes as RFC 3339 UTC).
#[pyfunction]
#[pyo3(signature = (time, lat_deg, lon_deg, elevation_m, *, pressure_hpa=None,
    temperature_c=15.0, delta_t_s=None, refraction=true))]
#[allow(clippy::too_many_arguments)]
pub fn sun_position<'py>(
    py: Python<'py>,
    time: Vec<String>,
    lat_deg: PyReadonlyArray1<'py, f64>,
    lon_deg: PyReadonlyArray1<'py, f64>,
    elevation_m: PyReadonlyArray1<'py, f64>,
    pressure_hpa: Option<f64>,
    temperature_c: f64,
    delta_t_s: Option<f64>,
    refraction: bool,
) -> PyResult<SunArrays<'py>> {
    let (lat, lon, elev) = (
        lat_deg.as_slice()?,
        lon_deg.as_slice()?,
        elevation_m.as_slice()?,
    );
    let count = time.len();
    same_length(
        count,
        &[
            ("lat_deg", lat.len()),
            ("lon_deg", lon.len()),
            ("elevation_m", elev.len()),
        ],
    )?;
    let out = py.detach(|| {
        let mut zenith = Vec::with_capacity(count);
        let mut azimuth = Vec::with_capacity(count);
        for i in 0..count {
            let args = SunArgs {
                time: Some(time[i].clone()),
                lat_deg: Some(lat[i]),
                lon_deg: Some(lon[i]),
                elevation_m: elev[i],
                pressure_hpa,
                temperature_c,
                delta_t_s,
                no_refraction: !refraction,
            };
            let v = sun_command(&args).map_err(|e| element_error(i, count, e))?;
            zenith.push(v["zenith_deg"].as_f64().unwrap_or(f64::NAN));
            azimuth.push(v["azimuth_deg"].as_f64().unwrap_or(f64::NAN));
        }
        Ok::<_, String>((zenith, azimuth))
    });
    let (zenith, azimuth) = out.map_err(value_error)?;
    Ok((
        Array1::from(zenith).into_pyarray(py),
        Array1::from(azimuth).into_pyarray(py),
    ))
}
