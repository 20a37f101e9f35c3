//! `polarimeter._native`: the Rust half of the `polarimeter` Python package (pyo3, abi3).
//!
//! Every number the package returns is computed here, by the workspace's crates: the model
//! (`polar-model`), the products kernel of the runs (`polar-engine`) and the command layer
//! of the `polarimeter` CLI (`polar-cli`), so that Python and the CLI answer the same
//! question with the same code. The Python half (`python/polarimeter/`) only broadcasts
//! arrays, names arguments and wraps results in dataclasses.
//!
//! Modules:
//!
//! * [`errors`]: Rust errors as Python `ValueError`s naming the argument (and the element).
//! * [`optics`]: Fresnel amplitudes and the pBRDF Mueller matrix over arrays of angles.
//! * [`sun`]: the sun's position over arrays of instants and sites.
//! * [`estimator`]: Stokes, DoLP, AoP, their predicted sigma and the flags from a stack of
//!   frames, with the engine's kernel, reading the numpy frames in place.
//! * [`commands`]: the CLI's document commands (planner, scene, statistics) by their flags.
//! * [`runs`]: `acquire run` and `acquire resume`, with events and Ctrl-C.
#![warn(missing_docs)]

mod commands;
mod errors;
mod estimator;
mod optics;
mod runs;
mod sun;

use pyo3::prelude::*;

/// The extension module.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(optics::fresnel, m)?)?;
    m.add_function(wrap_pyfunction!(optics::pbrdf_mueller, m)?)?;
    m.add_function(wrap_pyfunction!(sun::sun_position, m)?)?;
    m.add_function(wrap_pyfunction!(estimator::analyzer_rows, m)?)?;
    m.add_function(wrap_pyfunction!(estimator::camera_noise, m)?)?;
    m.add_function(wrap_pyfunction!(estimator::stokes_products, m)?)?;
    m.add_function(wrap_pyfunction!(commands::command, m)?)?;
    m.add_function(wrap_pyfunction!(runs::run_plan, m)?)?;
    m.add_function(wrap_pyfunction!(runs::resume_run, m)?)?;
    Ok(())
}
