//! Fresnel amplitudes and the pBRDF Mueller matrix (Meng (2012) Eqs. 3.4-3.19) over arrays of
//! angles, as `polarimeter model fresnel` and `model pbrdf` give them for one angle.

use crate::errors::{element_error, same_length, value_error};
use numpy::ndarray::{Array1, Array3};
use numpy::{Complex64, IntoPyArray, PyArray1, PyArray3, PyReadonlyArray1};
use polar_cli::commands::{diffuse_warnings, PbrdfArgs};
use polar_model::fresnel::{amplitudes, RefractiveIndex};
use polar_model::pbrdf::{DiffuseTerm, Geometry, Surface};
use polar_model::polarization::Mueller;
use polar_model::quadrature::Tolerance;
use polar_model::ModelError;
use pyo3::prelude::*;
use std::collections::HashMap;

/// Fresnel's four outputs, one array each.
type FresnelArrays<'py> = (
    Bound<'py, PyArray1<Complex64>>,
    Bound<'py, PyArray1<Complex64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
);

/// `rs`, `rp` (complex amplitudes), `Rs`, `Rp` for equal-length arrays `n`, `k` and
/// `theta_i_deg` (the Python layer broadcasts them).
#[pyfunction]
pub fn fresnel<'py>(
    py: Python<'py>,
    n: PyReadonlyArray1<'py, f64>,
    k: PyReadonlyArray1<'py, f64>,
    theta_i_deg: PyReadonlyArray1<'py, f64>,
) -> PyResult<FresnelArrays<'py>> {
    let (n, k, t) = (n.as_slice()?, k.as_slice()?, theta_i_deg.as_slice()?);
    let count = t.len();
    same_length(count, &[("n", n.len()), ("k", k.len())])?;
    let out = py.detach(|| {
        let mut rs = Vec::with_capacity(count);
        let mut rp = Vec::with_capacity(count);
        let mut big_rs = Vec::with_capacity(count);
        let mut big_rp = Vec::with_capacity(count);
        for i in 0..count {
            let r = fresnel_one(n[i], k[i], t[i]).map_err(|e| element_error(i, count, e))?;
            rs.push(Complex64::new(r.rs.re, r.rs.im));
            rp.push(Complex64::new(r.rp.re, r.rp.im));
            big_rs.push(r.rs_power());
            big_rp.push(r.rp_power());
        }
        Ok::<_, String>((rs, rp, big_rs, big_rp))
    });
    let (rs, rp, big_rs, big_rp) = out.map_err(value_error)?;
    Ok((
        Array1::from(rs).into_pyarray(py),
        Array1::from(rp).into_pyarray(py),
        Array1::from(big_rs).into_pyarray(py),
        Array1::from(big_rp).into_pyarray(py),
    ))
}

/// One angle, with the CLI's checks (`n` in (0, 100], `k` in [0, 100], `theta_i_deg` in
/// [0, 90]).
fn fresnel_one(
    n: f64,
    k: f64,
    theta_i_deg: f64,
) -> Result<polar_model::fresnel::FresnelAmplitudes, ModelError> {
    let index = RefractiveIndex::new(n, k)?;
    let t = ModelError::check_range("theta_i_deg", theta_i_deg, 0.0, 90.0, "[0, 90]")?;
    amplitudes(&index, t.to_radians())
}

/// The pBRDF's outputs: Mueller matrices, DoLP and AoP of the response to unpolarised light,
/// and the warnings of the diffuse terms.
type PbrdfArrays<'py> = (
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray1<f64>>,
    Vec<String>,
);

/// The pBRDF Mueller matrix (sr^-1, `(count, 3, 3)`) at equal-length arrays of incidence
/// and view zenith and relative azimuth, degrees, for one surface given as
/// `polarimeter model pbrdf` takes it (a built-in material, or n, k, sigma, dhr; explicit
/// values win over the material's). The diffuse term depends on the incidence angle only,
/// so it is integrated once per distinct `theta_i_deg`.
#[pyfunction]
#[pyo3(signature = (theta_i_deg, theta_r_deg, phi_deg, *, n=None, k=None, material=None,
    sigma=None, dhr=None, vegetation=false, tolerance=1e-9))]
#[allow(clippy::too_many_arguments)]
pub fn pbrdf_mueller<'py>(
    py: Python<'py>,
    theta_i_deg: PyReadonlyArray1<'py, f64>,
    theta_r_deg: PyReadonlyArray1<'py, f64>,
    phi_deg: PyReadonlyArray1<'py, f64>,
    n: Option<f64>,
    k: Option<f64>,
    material: Option<String>,
    sigma: Option<f64>,
    dhr: Option<f64>,
    vegetation: bool,
    tolerance: f64,
) -> PyResult<PbrdfArrays<'py>> {
    let args = PbrdfArgs {
        n,
        k,
        material,
        sigma,
        dhr,
        theta_i_deg: None,
        theta_r_deg: None,
        phi_deg: None,
        vegetation,
        tolerance,
    };
    let surface = args
        .resolved()
        .and_then(|a| a.surface())
        .map_err(value_error)?;
    let tol = ModelError::check_range("tolerance", tolerance, 1e-14, 1e-2, "[1e-14, 1e-2]")
        .map_err(value_error)?;
    let (ti, tr, phi) = (
        theta_i_deg.as_slice()?,
        theta_r_deg.as_slice()?,
        phi_deg.as_slice()?,
    );
    let count = ti.len();
    same_length(count, &[("theta_r_deg", tr.len()), ("phi_deg", phi.len())])?;
    let out = py.detach(|| mueller_matrices(&surface, Tolerance::absolute(tol), ti, tr, phi));
    let (m, dolp, aop_deg, warnings) = out.map_err(value_error)?;
    Ok((
        m.into_pyarray(py),
        Array1::from(dolp).into_pyarray(py),
        Array1::from(aop_deg).into_pyarray(py),
        warnings,
    ))
}

/// The Mueller matrices, DoLP and AoP (degrees; NaN where undefined) of `surface` at each
/// geometry, and the distinct warnings of the diffuse terms.
#[allow(clippy::type_complexity)]
fn mueller_matrices(
    surface: &Surface,
    tol: Tolerance,
    ti: &[f64],
    tr: &[f64],
    phi: &[f64],
) -> Result<(Array3<f64>, Vec<f64>, Vec<f64>, Vec<String>), String> {
    let count = ti.len();
    let mut m: Vec<f64> = Vec::with_capacity(count * 9);
    let mut dolp = Vec::with_capacity(count);
    let mut aop_deg = Vec::with_capacity(count);
    let mut diffuse: HashMap<u64, DiffuseTerm> = HashMap::new();
    let mut warnings: Vec<String> = Vec::new();
    let mut last: Option<(u64, DiffuseTerm)> = None;
    for i in 0..count {
        let fail = |e: ModelError| element_error(i, count, e);
        let g = Geometry::from_deg(ti[i], tr[i], phi[i]).map_err(fail)?;
        // Runs of equal incidence (one sun, many views) skip the map.
        let d = match last.filter(|(t, _)| *t == ti[i].to_bits()) {
            Some((_, d)) => d,
            None => match diffuse.get(&ti[i].to_bits()) {
                Some(d) => *d,
                None => {
                    let d = surface.diffuse(ti[i].to_radians(), tol).map_err(fail)?;
                    for w in diffuse_warnings(&d, tol.abs) {
                        if !warnings.contains(&w) {
                            warnings.push(w);
                        }
                    }
                    diffuse.insert(ti[i].to_bits(), d);
                    d
                }
            },
        };
        last = Some((ti[i].to_bits(), d));
        let f = surface.mueller_with(&g, &d);
        // Row-major, as numpy's (3, 3) blocks.
        let f = f.0;
        m.extend_from_slice(&[
            f[(0, 0)],
            f[(0, 1)],
            f[(0, 2)],
            f[(1, 0)],
            f[(1, 1)],
            f[(1, 2)],
            f[(2, 0)],
            f[(2, 1)],
            f[(2, 2)],
        ]);
        let response = Mueller(f).response_to_unpolarized();
        dolp.push(response.dolp().unwrap_or(0.0));
        aop_deg.push(response.aop_rad().map_or(f64::NAN, f64::to_degrees));
    }
    let m = Array3::from_shape_vec((count, 3, 3), m).map_err(|e| e.to_string())?;
    Ok((m, dolp, aop_deg, warnings))
}
