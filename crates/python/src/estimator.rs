//! The estimator of the runs on numpy arrays: Stokes, DoLP, AoP, their predicted sigma and
//! the quality flags of one angle set, by the engine's products kernel
//! (`polar_engine::products::compute`), reading the frames where numpy holds them.

use crate::errors::{same_length, value_error};
use nalgebra::Matrix3;
use numpy::ndarray::Array2;
use numpy::{
    IntoPyArray, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
    PyUntypedArrayMethods,
};
use polar_engine::flags::pixel_flags;
use polar_engine::products::{compute, Dark, NoiseModel, Products, SetGeometry};
use polar_model::analyzer::AnalyzerModel;
use polar_model::sensor::Camera;
use polar_model::span::span_row;
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// The analyzer rows (`(count, 3)`) of exposures during which the analyzer turned from
/// `start_deg` to `end_deg` (equal for a step-and-shoot frame): `m = 0.5 [1, cos 2psi,
/// sin 2psi]` for an ideal analyzer, averaged over the span (MODEL.md: the `sin D / D`
/// factor). The analyzer is a camera file's (its polarizer and fore-optics, as a run's
/// products take them) when `camera_toml` is given, else one of `extinction_ratio` whose
/// axis is `offset_deg` from the commanded angle.
#[pyfunction]
#[pyo3(signature = (start_deg, end_deg, *, camera_toml=None, extinction_ratio=None,
    offset_deg=None))]
pub fn analyzer_rows<'py>(
    py: Python<'py>,
    start_deg: PyReadonlyArray1<'py, f64>,
    end_deg: PyReadonlyArray1<'py, f64>,
    camera_toml: Option<&str>,
    extinction_ratio: Option<f64>,
    offset_deg: Option<f64>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (analyzer, fore) = match camera_toml {
        Some(_) if extinction_ratio.is_some() || offset_deg.is_some() => {
            return Err(value_error(
                "give camera or extinction_ratio and offset_deg, not both: the camera file's \
                 polarizer has its own",
            ))
        }
        Some(text) => {
            let camera = camera_of(text)?;
            let analyzer = camera.polarizer.analyzer().map_err(value_error)?;
            (analyzer, camera.fore_optics().0)
        }
        None => {
            let er = extinction_ratio.unwrap_or(f64::INFINITY);
            let offset = offset_deg.unwrap_or(0.0).to_radians();
            let analyzer = AnalyzerModel::from_extinction_ratio(er, offset).map_err(value_error)?;
            (analyzer, Matrix3::identity())
        }
    };
    let (start, end) = (start_deg.as_slice()?, end_deg.as_slice()?);
    same_length(start.len(), &[("end_deg", end.len())])?;
    let mut rows = Array2::<f64>::zeros((start.len(), 3));
    for (i, (s, e)) in start.iter().zip(end).enumerate() {
        if !(s.is_finite() && e.is_finite()) {
            return Err(value_error(format!(
                "start_deg = {s}, end_deg = {e} at element {i}: allowed finite angles"
            )));
        }
        // As the runs' rows: the span's row through the analyzer, then the fore-optics.
        let row = fore.transpose() * span_row(&analyzer, s.to_radians(), e.to_radians());
        for c in 0..3 {
            rows[(i, c)] = row[c];
        }
    }
    Ok(rows.into_pyarray(py))
}

/// The noise model of a camera file's frames at `gain_db` (the runs' rule,
/// `NoiseModel::from_camera`): `gain_dn_per_e`, `offset_dn`, `read_var_dn2`,
/// `saturation_dn`, and the dark level `offset_dn + K dark_current t` at `exposure_us`.
#[pyfunction]
#[pyo3(signature = (camera_toml, *, gain_db=0.0, exposure_us=0.0))]
pub fn camera_noise<'py>(
    py: Python<'py>,
    camera_toml: &str,
    gain_db: f64,
    exposure_us: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let camera = camera_of(camera_toml)?;
    for (name, value, hi) in [
        ("gain_db", gain_db, 48.0),
        ("exposure_us", exposure_us, 1e11),
    ] {
        if !(value.is_finite() && (0.0..=hi).contains(&value)) {
            return Err(value_error(format!(
                "{name} = {value} is out of range: allowed [0, {hi}]"
            )));
        }
    }
    let noise = NoiseModel::from_camera(&camera, gain_db);
    let d = PyDict::new(py);
    d.set_item("gain_dn_per_e", noise.gain_dn_per_e)?;
    d.set_item("offset_dn", noise.offset_dn)?;
    d.set_item("read_var_dn2", noise.read_var_dn2)?;
    d.set_item("saturation_dn", noise.saturation_dn)?;
    d.set_item("dark_dn", noise.dark_level_dn(&camera, exposure_us))?;
    Ok(d)
}

/// The ten product images (`(height, width)` float32: s0, s1, s2, dolp, aop_rad and their
/// predicted sigma), the flags (uint8, `polar_engine::flags`) and the count of saturated
/// pixels of one angle set: `frames` `(count, height, width)` uint16, C-contiguous (read in
/// place), `rows` `(count, 3)`, the dark as a level (`dark_dn`) or a per-pixel map
/// (`dark_map`, float32 `(height, width)`), and the noise model.
#[pyfunction]
#[pyo3(signature = (frames, rows, *, gain_dn_per_e, offset_dn, read_var_dn2, saturation_dn,
    dark_dn=None, dark_map=None, threads=1))]
#[allow(clippy::too_many_arguments)]
pub fn stokes_products<'py>(
    py: Python<'py>,
    frames: PyReadonlyArray3<'py, u16>,
    rows: PyReadonlyArray2<'py, f64>,
    gain_dn_per_e: f64,
    offset_dn: f64,
    read_var_dn2: f64,
    saturation_dn: u16,
    dark_dn: Option<f64>,
    dark_map: Option<PyReadonlyArray2<'py, f32>>,
    threads: usize,
) -> PyResult<Bound<'py, PyDict>> {
    let shape = frames.shape().to_vec();
    let (count, height, width) = (shape[0], shape[1], shape[2]);
    let pixels = frames.as_slice().map_err(|_| {
        value_error("frames must be C-contiguous (numpy.ascontiguousarray(frames))")
    })?;
    let rows = rows_of(&rows, count)?;
    let dark = dark_of(dark_dn, dark_map.as_ref(), height, width)?;
    let (w, h) = (dimension("width", width)?, dimension("height", height)?);
    let noise = NoiseModel {
        gain_dn_per_e,
        offset_dn,
        read_var_dn2,
        saturation_dn,
    };
    let out = py.detach(|| {
        let geometry = SetGeometry::new(&rows)?;
        let stack: Vec<&[u16]> = pixels.chunks_exact(height * width).collect();
        let p = compute(&stack, w, h, &geometry, &dark, &noise, threads)?;
        let flags = pixel_flags(&p);
        Ok::<_, polar_engine::products::ProductsError>((p, flags))
    });
    let (p, flags) = out.map_err(value_error)?;
    let saturated = p.saturated;
    let d = PyDict::new(py);
    // The kernel's buffers become the numpy arrays as they are (no copy).
    for (name, plane) in Products::names().iter().zip(planes(p)) {
        let image = Array2::from_shape_vec((height, width), plane).map_err(value_error)?;
        d.set_item(*name, image.into_pyarray(py))?;
    }
    let flags = Array2::from_shape_vec((height, width), flags).map_err(value_error)?;
    d.set_item("flags", flags.into_pyarray(py))?;
    d.set_item("saturated", saturated)?;
    Ok(d)
}

/// The ten images of `p`, in [`Products::names`] order, moved out of it.
fn planes(p: Products) -> [Vec<f32>; 10] {
    [
        p.s0,
        p.s1,
        p.s2,
        p.dolp,
        p.aop_rad,
        p.sigma_s0,
        p.sigma_s1,
        p.sigma_s2,
        p.sigma_dolp,
        p.sigma_aop_rad,
    ]
}

/// A camera model from a camera file's TOML, or from the JSON of a run's
/// `products_camera.model` (the same fields), checked.
fn camera_of(text: &str) -> PyResult<Camera> {
    let camera = if text.trim_start().starts_with('{') {
        serde_json::from_str(text).map_err(|e| value_error(format!("camera: {e}")))?
    } else {
        Camera::from_toml_str(text).map_err(value_error)?
    };
    camera.validate().map_err(value_error)?;
    Ok(camera)
}

/// `rows` as the kernel takes them, one per frame.
fn rows_of(rows: &PyReadonlyArray2<'_, f64>, count: usize) -> PyResult<Vec<[f64; 3]>> {
    let shape = rows.shape();
    if shape[0] != count || shape[1] != 3 {
        return Err(value_error(format!(
            "rows has shape ({}, {}): allowed ({count}, 3), one analyzer row per frame",
            shape[0], shape[1]
        )));
    }
    let a = rows.as_array();
    Ok((0..count)
        .map(|i| [a[(i, 0)], a[(i, 1)], a[(i, 2)]])
        .collect())
}

/// The dark: exactly one of a level and a map of the frames' shape.
fn dark_of(
    level: Option<f64>,
    map: Option<&PyReadonlyArray2<'_, f32>>,
    height: usize,
    width: usize,
) -> PyResult<Dark> {
    match (level, map) {
        (Some(v), None) if v.is_finite() => Ok(Dark::Scalar(v as f32)),
        (Some(v), None) => Err(value_error(format!(
            "dark_dn = {v} is out of range: allowed a finite level in DN"
        ))),
        (None, Some(m)) if m.shape() == [height, width] => {
            Ok(Dark::Map(m.as_array().iter().copied().collect()))
        }
        (None, Some(m)) => Err(value_error(format!(
            "dark_map has shape {:?}: allowed ({height}, {width}), the frames' shape",
            m.shape()
        ))),
        _ => Err(value_error(
            "give exactly one of dark_dn (a level, DN) and dark_map (per pixel, DN)",
        )),
    }
}

/// An image dimension as the kernel takes it.
fn dimension(name: &str, value: usize) -> PyResult<u32> {
    u32::try_from(value)
        .ok()
        .filter(|v| *v > 0)
        .ok_or_else(|| value_error(format!("{name} = {value}: allowed 1 to {}", u32::MAX)))
}
