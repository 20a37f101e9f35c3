//! The one plotting helper every figure of the CLI draws with (plotters, into PNGs): the
//! embedded font, a white canvas with the font registered, the legend box every chart uses,
//! and errors that name the file. `report figures`, the studies and
//! `calibrate noise`'s photon-transfer plot all go through it.

use plotters::coord::CoordTranslate;
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::{Path, PathBuf};

/// Errors drawing figures.
#[derive(Debug, thiserror::Error)]
pub enum FigureError {
    /// Plotting or file-system failure.
    #[error("{path}: {message}")]
    Draw {
        /// The file being written.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A model evaluation failed (a bug: every input here is in range).
    #[error("model: {0}")]
    Model(#[from] polar_model::ModelError),
}

/// Maps a plotters error to a [`FigureError`] naming the file.
pub(crate) fn draw_err<E: std::fmt::Display>(path: &Path) -> impl Fn(E) -> FigureError + '_ {
    move |e| FigureError::Draw {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// The font family every figure of the CLI draws with (the embedded DejaVu Sans).
pub(crate) const FONT: &str = "sans-serif";

/// Registers the embedded font under [`FONT`] (plotters' `ab_glyph` backend has no system
/// fonts).
fn register_font() {
    // Registering twice is harmless; an invalid embedded font would be a build bug and leaves
    // plotters to report a font error when drawing text.
    let _ = plotters::style::register_font(
        FONT,
        FontStyle::Normal,
        include_bytes!("../assets/DejaVuSans.ttf"),
    );
}

/// A figure's drawing area: a bitmap written to its file on `present`.
pub(crate) type Canvas<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

/// A white canvas of `size` pixels that writes `path`, with [`FONT`] registered.
pub(crate) fn canvas(path: &Path, size: (u32, u32)) -> Result<Canvas<'_>, FigureError> {
    register_font();
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(draw_err(path))?;
    Ok(root)
}

/// Draws `chart`'s series labels as every figure does: a white box, 85 % opaque, with a black
/// border, at `position`, in [`FONT`] at `font_px`.
pub(crate) fn legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
    position: SeriesLabelPosition,
    font_px: u32,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    chart
        .configure_series_labels()
        .position(position)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FONT, font_px))
        .draw()
}
