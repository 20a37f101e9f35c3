//! The check of a set's inputs (frames, image size, analyzer rows, dark) before its
//! products are computed.

use super::error::ProductsError;
use super::geometry::SetGeometry;
use super::noise::{Dark, NoiseModel};

/// Checks the inputs; returns `width * height`.
pub(super) fn validate(
    frames: &[&[u16]],
    width: u32,
    height: u32,
    geometry: &SetGeometry,
    dark: &Dark,
    noise: &NoiseModel,
) -> Result<usize, ProductsError> {
    let n = usize::try_from(u64::from(width) * u64::from(height))
        .map_err(|_| ProductsError::Size { width, height })?;
    if frames.len() != geometry.rows.len() {
        return Err(ProductsError::FrameCount {
            frames: frames.len(),
            rows: geometry.rows.len(),
        });
    }
    for (index, f) in frames.iter().enumerate() {
        if f.len() != n {
            return Err(ProductsError::FrameLength {
                index,
                len: f.len(),
                expected: n,
                width,
                height,
            });
        }
    }
    match dark {
        Dark::Scalar(v) if !v.is_finite() => {
            return Err(ProductsError::NonFiniteDark { value: *v });
        }
        Dark::Map(m) if m.len() != n => {
            return Err(ProductsError::DarkMapLength {
                len: m.len(),
                expected: n,
            });
        }
        _ => {}
    }
    noise.validate()?;
    Ok(n)
}
