//! Single-channel TIFF files, the one place the workspace reads and writes them: 16-bit frames
//! written and read back, 32-bit float images (products, dark means) written. Errors say what
//! is wrong in words; the caller names the file.

use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::path::Path;
use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::{colortype, TiffEncoder};
use tiff::ColorType;

/// Writes `data` (row-major, `width x height`) as an uncompressed 16-bit grayscale TIFF.
pub fn write_gray16(path: &Path, width: u32, height: u32, data: &[u16]) -> Result<(), String> {
    if data.len() as u64 != u64::from(width) * u64::from(height) {
        return Err(format!(
            "{} pixels for a {width}x{height} frame",
            data.len()
        ));
    }
    let file = File::create(path).map_err(|e| e.to_string())?;
    let mut w = BufWriter::new(file);
    TiffEncoder::new(&mut w)
        .map_err(|e| e.to_string())?
        .write_image::<colortype::Gray16>(width, height, data)
        .map_err(|e| e.to_string())?;
    w.flush().map_err(|e| e.to_string())
}

/// Writes `data` (row-major, `width x height`) as an uncompressed 32-bit float grayscale TIFF.
pub fn write_gray32f(path: &Path, width: u32, height: u32, data: &[f32]) -> Result<(), String> {
    if data.len() as u64 != u64::from(width) * u64::from(height) {
        return Err(format!(
            "{} values for a {width}x{height} image",
            data.len()
        ));
    }
    let file = File::create(path).map_err(|e| e.to_string())?;
    let mut w = BufWriter::new(file);
    TiffEncoder::new(&mut w)
        .map_err(|e| e.to_string())?
        .write_image::<colortype::Gray32Float>(width, height, data)
        .map_err(|e| e.to_string())?;
    w.flush().map_err(|e| e.to_string())
}

fn open(path: &Path) -> Result<Decoder<BufReader<File>>, String> {
    let f = File::open(path).map_err(|e| format!("cannot open: {e}"))?;
    Decoder::new(BufReader::new(f)).map_err(|e| format!("not a readable TIFF: {e}"))
}

fn describe_color(c: ColorType) -> String {
    match c {
        ColorType::Gray(b) => format!("{b}-bit grayscale"),
        ColorType::RGB(b) => format!("{b}-bit RGB"),
        ColorType::RGBA(b) => format!("{b}-bit RGBA"),
        ColorType::GrayA(b) => format!("{b}-bit grayscale with alpha"),
        ColorType::Palette(b) => format!("{b}-bit palette"),
        other => format!("{other:?}"),
    }
}

/// The width and height of a TIFF.
pub fn dimensions(path: &Path) -> Result<(u32, u32), String> {
    open(path)?
        .dimensions()
        .map_err(|e| format!("not a readable TIFF: {e}"))
}

/// The width and height of a 16-bit single-channel TIFF; another kind of TIFF is named.
pub fn gray16_dimensions(path: &Path) -> Result<(u32, u32), String> {
    let mut dec = open(path)?;
    let color = dec
        .colortype()
        .map_err(|e| format!("not a readable TIFF: {e}"))?;
    if color != ColorType::Gray(16) {
        return Err(format!(
            "{}; allowed 16-bit single-channel (grayscale) TIFF",
            describe_color(color)
        ));
    }
    dec.dimensions()
        .map_err(|e| format!("not a readable TIFF: {e}"))
}

/// The pixels of a 16-bit single-channel TIFF of `width x height`.
pub fn read_gray16(path: &Path, width: u32, height: u32) -> Result<Vec<u16>, String> {
    let mut dec = open(path)?;
    let dims = dec
        .dimensions()
        .map_err(|e| format!("not a readable TIFF: {e}"))?;
    if dims != (width, height) {
        return Err(format!(
            "{}x{} pixels; allowed {width}x{height} like the other frames",
            dims.0, dims.1
        ));
    }
    match dec.read_image() {
        Ok(DecodingResult::U16(v)) if v.len() == width as usize * height as usize => Ok(v),
        Ok(_) => Err("not 16-bit single-channel pixel data; allowed 16-bit grayscale TIFF".into()),
        Err(e) => Err(format!("cannot decode the pixels: {e}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame written and read back is the same, bit for bit; the wrong size and a float
    /// image read as a frame are refused in words.
    #[test]
    fn gray16_round_trips_and_other_kinds_are_named() {
        let dir = std::env::temp_dir().join(format!("tiff-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let px: Vec<u16> = (0..12u16).map(|i| i * 5000).collect();
        let p = dir.join("f.tif");
        write_gray16(&p, 4, 3, &px).unwrap();
        assert_eq!(gray16_dimensions(&p).unwrap(), (4, 3));
        assert_eq!(read_gray16(&p, 4, 3).unwrap(), px);
        assert!(read_gray16(&p, 3, 4).unwrap_err().contains("allowed 3x4"));
        assert!(write_gray16(&p, 5, 3, &px)
            .unwrap_err()
            .contains("12 pixels"));
        let q = dir.join("g.tif");
        write_gray32f(&q, 2, 1, &[0.5, -1.0]).unwrap();
        assert!(gray16_dimensions(&q)
            .unwrap_err()
            .contains("allowed 16-bit"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
