//! Pure conversions from camera buffers to luminance, and the host-side crop, shared by the
//! V4L2 backend (`polar-camera-v4l`) and the UVC backend on nokhwa (`polar-camera-uvc`).
//!
//! Every function checks sizes before it reads: a short buffer, a row stride shorter than a row,
//! a size of zero or above [`MAX_PIXELS`], or a JPEG that does not decode to the expected size is
//! an error, never a panic and never a partly filled image. The JPEG decoder (`zune-jpeg`, strict
//! mode, luma output) is also run under `catch_unwind`, so that a panic inside the third-party
//! decoder becomes [`ConvertError::DecoderPanicked`] instead of taking the camera thread down.
//! Row strides are V4L2's `bytesperline` (0 = packed); a backend whose buffers are always packed
//! (nokhwa's) passes 0.
//!
//! What the numbers mean:
//!
//! * `GREY` and `Y16` are the sensor's values (`Y16` is little-endian, 16 significant bits as
//!   V4L2 defines it; drivers for 10- and 12-bit sensors shift their data up).
//! * `YUYV` and `MJPEG` carry the camera ISP's luma: gamma-encoded, usually with auto white
//!   balance and sharpening already applied, and for `YUYV` usually in the limited range
//!   16..=235 (MJPEG/JFIF uses the full 0..=255). They are delivered as they are, with no rescale.
//!   A photometric measurement through a webcam needs its response calibrated first (the
//!   photon-transfer calibration), or a camera that offers `GREY`/`Y16` raw data.
#![warn(missing_docs)]

use polar_hal::Roi;
use std::panic::{catch_unwind, AssertUnwindSafe};
use zune_jpeg::zune_core::bytestream::ZCursor;
use zune_jpeg::zune_core::colorspace::ColorSpace;
use zune_jpeg::zune_core::options::DecoderOptions;
use zune_jpeg::JpegDecoder;

/// The largest frame accepted, pixels (8192 x 8192): a guard against sizes from garbage.
pub const MAX_PIXELS: usize = 8192 * 8192;

/// Why a buffer could not be turned into a luminance image.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum ConvertError {
    /// The frame size is zero or above [`MAX_PIXELS`].
    #[error("frame size {width}x{height} is out of range: allowed 1..={MAX_PIXELS} pixels")]
    BadSize {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// The row stride is shorter than one row of pixels.
    #[error("row stride {stride_bytes} bytes is shorter than a row of {row_bytes} bytes")]
    StrideTooSmall {
        /// The stride given, bytes.
        stride_bytes: usize,
        /// One row of pixels, bytes.
        row_bytes: usize,
    },
    /// The buffer holds fewer bytes than the frame needs (a truncated buffer).
    #[error("buffer holds {got_bytes} bytes, a {width}x{height} frame needs {needed_bytes}")]
    Short {
        /// Bytes in the buffer.
        got_bytes: usize,
        /// Bytes the frame needs.
        needed_bytes: usize,
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// The JPEG decoder refused the data (truncated, corrupt, unsupported).
    #[error("JPEG does not decode: {0}")]
    Jpeg(String),
    /// The JPEG decoded, but to another size than the stream's.
    #[error("JPEG is {got_width}x{got_height}, the stream is {width}x{height}")]
    JpegSize {
        /// The JPEG's width, pixels.
        got_width: usize,
        /// The JPEG's height, pixels.
        got_height: usize,
        /// The stream's width, pixels.
        width: u32,
        /// The stream's height, pixels.
        height: u32,
    },
    /// The JPEG decoder panicked on this input (caught; a bug in the decoder, not in the data).
    #[error("JPEG decoder panicked: {0}")]
    DecoderPanicked(String),
    /// The region to crop is empty or not inside the frame.
    #[error(
        "roi = {}x{} at ({}, {}) is out of range: allowed a non-empty region inside the {width}x{height} frame",
        roi.width, roi.height, roi.x, roi.y
    )]
    RoiOutside {
        /// The region asked for.
        roi: Roi,
        /// Frame width, pixels.
        width: u32,
        /// Frame height, pixels.
        height: u32,
    },
}

/// The pixel count of a `width x height` frame, checked against [`MAX_PIXELS`].
fn pixel_count(width: u32, height: u32) -> Result<usize, ConvertError> {
    let n = (width as usize).checked_mul(height as usize);
    match n {
        Some(n) if (1..=MAX_PIXELS).contains(&n) => Ok(n),
        _ => Err(ConvertError::BadSize { width, height }),
    }
}

/// Checks a packed-row layout and returns `(stride_bytes, row_bytes)`. A stride of 0 means
/// "packed" (V4L2 drivers may report `bytesperline = 0`).
fn layout(
    data_len: usize,
    width: u32,
    height: u32,
    stride_bytes: usize,
    bytes_per_pixel: usize,
) -> Result<(usize, usize), ConvertError> {
    pixel_count(width, height)?;
    // Cannot overflow: width * height <= MAX_PIXELS and bytes_per_pixel <= 2.
    let row_bytes = width as usize * bytes_per_pixel;
    let stride = if stride_bytes == 0 {
        row_bytes
    } else {
        stride_bytes
    };
    if stride < row_bytes {
        return Err(ConvertError::StrideTooSmall {
            stride_bytes: stride,
            row_bytes,
        });
    }
    // The last row needs no padding after it.
    let needed = (height as usize - 1)
        .checked_mul(stride)
        .and_then(|n| n.checked_add(row_bytes));
    match needed {
        Some(needed) if needed <= data_len => Ok((stride, row_bytes)),
        _ => Err(ConvertError::Short {
            got_bytes: data_len,
            needed_bytes: needed.unwrap_or(usize::MAX),
            width,
            height,
        }),
    }
}

/// Reads `height` rows of `row_bytes` at `stride` and maps each pixel's bytes with `pixel`.
fn rows(
    data: &[u8],
    height: u32,
    stride: usize,
    row_bytes: usize,
    bytes_per_pixel: usize,
    pixel: impl Fn(&[u8]) -> u16,
) -> Result<Vec<u16>, ConvertError> {
    let mut out = Vec::with_capacity(row_bytes / bytes_per_pixel * height as usize);
    for y in 0..height as usize {
        let start = y * stride;
        let row = data
            .get(start..start + row_bytes)
            .ok_or(ConvertError::Short {
                got_bytes: data.len(),
                needed_bytes: start + row_bytes,
                width: (row_bytes / bytes_per_pixel) as u32,
                height,
            })?;
        out.extend(row.chunks_exact(bytes_per_pixel).map(&pixel));
    }
    Ok(out)
}

/// `GREY` (8-bit luminance) to `Mono8` pixels. `stride_bytes` is V4L2's `bytesperline`
/// (0 = packed).
pub fn grey_to_luma(
    data: &[u8],
    width: u32,
    height: u32,
    stride_bytes: usize,
) -> Result<Vec<u16>, ConvertError> {
    let (stride, row_bytes) = layout(data.len(), width, height, stride_bytes, 1)?;
    rows(data, height, stride, row_bytes, 1, |p| {
        p.first().copied().map_or(0, u16::from)
    })
}

/// `YUYV` (YUV 4:2:2, `Y0 U Y1 V`) to `Mono8` pixels: the Y bytes, as they are (no range
/// expansion). `stride_bytes` is V4L2's `bytesperline` (0 = packed, `2 * width`).
pub fn yuyv_to_luma(
    data: &[u8],
    width: u32,
    height: u32,
    stride_bytes: usize,
) -> Result<Vec<u16>, ConvertError> {
    let (stride, row_bytes) = layout(data.len(), width, height, stride_bytes, 2)?;
    rows(data, height, stride, row_bytes, 2, |p| {
        p.first().copied().map_or(0, u16::from)
    })
}

/// `Y16` (16-bit little-endian luminance) to `Mono16` pixels. `stride_bytes` is V4L2's
/// `bytesperline` (0 = packed, `2 * width`).
pub fn y16_to_luma(
    data: &[u8],
    width: u32,
    height: u32,
    stride_bytes: usize,
) -> Result<Vec<u16>, ConvertError> {
    let (stride, row_bytes) = layout(data.len(), width, height, stride_bytes, 2)?;
    rows(data, height, stride, row_bytes, 2, |p| match p {
        [lo, hi] => u16::from_le_bytes([*lo, *hi]),
        _ => 0,
    })
}

/// The standard Huffman tables of ITU-T T.81 Annex K.3 (K.3 DC luma, K.5 AC luma, K.4 DC chroma,
/// K.6 AC chroma) as `(class_and_id, counts of codes of length 1..=16, symbols)`: the tables a
/// UVC/AVI MJPEG frame uses when it carries no DHT segment.
const DEFAULT_HUFFMAN_TABLES: [(u8, [u8; 16], &[u8]); 4] = [
    (
        0x00,
        [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0],
        &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11],
    ),
    (
        0x10,
        [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7D],
        &[
            0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51,
            0x61, 0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xA1, 0x08, 0x23, 0x42, 0xB1, 0xC1,
            0x15, 0x52, 0xD1, 0xF0, 0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0A, 0x16, 0x17, 0x18,
            0x19, 0x1A, 0x25, 0x26, 0x27, 0x28, 0x29, 0x2A, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39,
            0x3A, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48, 0x49, 0x4A, 0x53, 0x54, 0x55, 0x56, 0x57,
            0x58, 0x59, 0x5A, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6A, 0x73, 0x74, 0x75,
            0x76, 0x77, 0x78, 0x79, 0x7A, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8A, 0x92,
            0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9A, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7,
            0xA8, 0xA9, 0xAA, 0xB2, 0xB3, 0xB4, 0xB5, 0xB6, 0xB7, 0xB8, 0xB9, 0xBA, 0xC2, 0xC3,
            0xC4, 0xC5, 0xC6, 0xC7, 0xC8, 0xC9, 0xCA, 0xD2, 0xD3, 0xD4, 0xD5, 0xD6, 0xD7, 0xD8,
            0xD9, 0xDA, 0xE1, 0xE2, 0xE3, 0xE4, 0xE5, 0xE6, 0xE7, 0xE8, 0xE9, 0xEA, 0xF1, 0xF2,
            0xF3, 0xF4, 0xF5, 0xF6, 0xF7, 0xF8, 0xF9, 0xFA,
        ],
    ),
    (
        0x01,
        [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0],
        &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11],
    ),
    (
        0x11,
        [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77],
        &[
            0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07,
            0x61, 0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xA1, 0xB1, 0xC1, 0x09,
            0x23, 0x33, 0x52, 0xF0, 0x15, 0x62, 0x72, 0xD1, 0x0A, 0x16, 0x24, 0x34, 0xE1, 0x25,
            0xF1, 0x17, 0x18, 0x19, 0x1A, 0x26, 0x27, 0x28, 0x29, 0x2A, 0x35, 0x36, 0x37, 0x38,
            0x39, 0x3A, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48, 0x49, 0x4A, 0x53, 0x54, 0x55, 0x56,
            0x57, 0x58, 0x59, 0x5A, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6A, 0x73, 0x74,
            0x75, 0x76, 0x77, 0x78, 0x79, 0x7A, 0x82, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89,
            0x8A, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9A, 0xA2, 0xA3, 0xA4, 0xA5,
            0xA6, 0xA7, 0xA8, 0xA9, 0xAA, 0xB2, 0xB3, 0xB4, 0xB5, 0xB6, 0xB7, 0xB8, 0xB9, 0xBA,
            0xC2, 0xC3, 0xC4, 0xC5, 0xC6, 0xC7, 0xC8, 0xC9, 0xCA, 0xD2, 0xD3, 0xD4, 0xD5, 0xD6,
            0xD7, 0xD8, 0xD9, 0xDA, 0xE2, 0xE3, 0xE4, 0xE5, 0xE6, 0xE7, 0xE8, 0xE9, 0xEA, 0xF2,
            0xF3, 0xF4, 0xF5, 0xF6, 0xF7, 0xF8, 0xF9, 0xFA,
        ],
    ),
];

/// The DHT segment (marker, length, the four tables) of [`DEFAULT_HUFFMAN_TABLES`].
fn default_dht_segment() -> Vec<u8> {
    let body: usize = DEFAULT_HUFFMAN_TABLES
        .iter()
        .map(|(_, counts, symbols)| 1 + counts.len() + symbols.len())
        .sum();
    let length = (body + 2) as u16; // 418: the length field counts itself
    let mut out = Vec::with_capacity(body + 4);
    out.extend_from_slice(&[0xFF, 0xC4]);
    out.extend_from_slice(&length.to_be_bytes());
    for (class_and_id, counts, symbols) in DEFAULT_HUFFMAN_TABLES {
        out.push(class_and_id);
        out.extend_from_slice(&counts);
        out.extend_from_slice(symbols);
    }
    out
}

/// `jpeg` with the standard Huffman tables inserted before its first scan when it has no DHT
/// segment there (UVC MJPEG leaves them out, and decoders fill them in only for AVI files that
/// say `AVI1`). A frame with its own tables, or one whose headers do not parse, is returned
/// as it is; the decoder then reports what is wrong.
pub fn with_default_huffman_tables(jpeg: &[u8]) -> std::borrow::Cow<'_, [u8]> {
    use std::borrow::Cow;
    if jpeg.get(..2) != Some(&[0xFF, 0xD8][..]) {
        return Cow::Borrowed(jpeg);
    }
    let mut i = 2;
    loop {
        if jpeg.get(i) != Some(&0xFF) {
            return Cow::Borrowed(jpeg);
        }
        // Fill bytes: any number of 0xFF before the marker code.
        while jpeg.get(i + 1) == Some(&0xFF) {
            i += 1;
        }
        let Some(&marker) = jpeg.get(i + 1) else {
            return Cow::Borrowed(jpeg);
        };
        match marker {
            0xC4 => return Cow::Borrowed(jpeg), // has its own tables
            0xDA => {
                let mut out = Vec::with_capacity(jpeg.len() + 420);
                out.extend_from_slice(&jpeg[..i]);
                out.extend_from_slice(&default_dht_segment());
                out.extend_from_slice(&jpeg[i..]);
                return Cow::Owned(out);
            }
            // Markers without a length.
            0x01 | 0xD0..=0xD8 => i += 2,
            _ => {
                let Some(len) = jpeg
                    .get(i + 2..i + 4)
                    .map(|b| usize::from(u16::from_be_bytes([b[0], b[1]])))
                else {
                    return Cow::Borrowed(jpeg);
                };
                if len < 2 {
                    return Cow::Borrowed(jpeg);
                }
                i += 2 + len;
            }
        }
    }
}

/// One `MJPG`/`JPEG` frame to `Mono8` pixels: the JPEG's luma (Y) channel, decoded by
/// `zune-jpeg` in strict mode (a truncated or corrupt frame is an error, not a grey-filled image).
/// Webcam MJPEG often leaves out the Huffman tables (DHT); they are put back first
/// ([`with_default_huffman_tables`]), as the UVC MJPEG payload format prescribes. The frame must be exactly `width x height`; the decoder
/// refuses larger headers before it allocates anything.
pub fn mjpeg_to_luma(data: &[u8], width: u32, height: u32) -> Result<Vec<u16>, ConvertError> {
    let n = pixel_count(width, height)?;
    let options = DecoderOptions::default()
        .jpeg_set_out_colorspace(ColorSpace::Luma)
        .set_strict_mode(true)
        .set_max_width(width as usize)
        .set_max_height(height as usize);
    let data = with_default_huffman_tables(data);
    let decoded = catch_unwind(AssertUnwindSafe(|| {
        let mut decoder = JpegDecoder::new_with_options(ZCursor::new(&data[..]), options);
        decoder
            .decode_headers()
            .map_err(|e| ConvertError::Jpeg(e.to_string()))?;
        let (got_width, got_height) = decoder
            .info()
            .map(|i| (usize::from(i.width), usize::from(i.height)))
            .unwrap_or((0, 0));
        if got_width != width as usize || got_height != height as usize {
            return Err(ConvertError::JpegSize {
                got_width,
                got_height,
                width,
                height,
            });
        }
        decoder
            .decode()
            .map_err(|e| ConvertError::Jpeg(e.to_string()))
    }))
    .map_err(|payload| ConvertError::DecoderPanicked(panic_message(payload.as_ref())))??;
    if decoded.len() != n {
        return Err(ConvertError::Jpeg(format!(
            "decoded {} luma samples, expected {width}x{height} = {n}",
            decoded.len()
        )));
    }
    Ok(decoded.into_iter().map(u16::from).collect())
}

/// The text of a caught panic.
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "(no message)".to_string()
    }
}

/// The region `roi` of a row-major `width x height` image. UVC and V4L2 webcams have no sensor
/// region of interest, so the backends read the whole frame and crop it here.
pub fn crop(pixels: &[u16], width: u32, height: u32, roi: Roi) -> Result<Vec<u16>, ConvertError> {
    let n = pixel_count(width, height)?;
    if pixels.len() != n {
        return Err(ConvertError::Short {
            got_bytes: pixels.len() * 2,
            needed_bytes: n * 2,
            width,
            height,
        });
    }
    let fits = roi.width >= 1
        && roi.height >= 1
        && u64::from(roi.x) + u64::from(roi.width) <= u64::from(width)
        && u64::from(roi.y) + u64::from(roi.height) <= u64::from(height);
    if !fits {
        return Err(ConvertError::RoiOutside { roi, width, height });
    }
    if roi == Roi::full(width, height) {
        return Ok(pixels.to_vec());
    }
    let mut out = Vec::with_capacity(roi.pixels());
    for y in roi.y..roi.y + roi.height {
        let start = y as usize * width as usize + roi.x as usize;
        // In range: checked above.
        if let Some(row) = pixels.get(start..start + roi.width as usize) {
            out.extend_from_slice(row);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use jpeg_encoder::{ColorType, Encoder, SamplingFactor};
    use proptest::prelude::*;

    /// A JPEG of `pixels` (`color` = RGB triplets, else luma) at quality `quality`.
    fn jpeg(pixels: &[u8], width: u16, height: u16, color: bool, quality: u8) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = Encoder::new(&mut out, quality);
        if color {
            // 4:2:2, as UVC webcams send MJPEG.
            encoder.set_sampling_factor(SamplingFactor::F_2_1);
        }
        let kind = if color {
            ColorType::Rgb
        } else {
            ColorType::Luma
        };
        encoder.encode(pixels, width, height, kind).unwrap();
        out
    }

    /// A smooth 32x16 luma ramp with a bright square: content a JPEG keeps well.
    fn test_luma(width: usize, height: usize) -> Vec<u8> {
        let mut v = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                let ramp = 20 + (x * 200 / width) as u32;
                let square = (8..16).contains(&x) && (4..12).contains(&y);
                v.push(if square { 230 } else { ramp as u8 });
            }
        }
        v
    }

    /// Removes every DHT (0xFFC4) segment, as UVC cameras send MJPEG.
    fn strip_dht(jpeg: &[u8]) -> Vec<u8> {
        let mut out = jpeg[..2].to_vec();
        let mut i = 2;
        while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
            let marker = jpeg[i + 1];
            if marker == 0xDA {
                break; // start of scan: the entropy-coded data follows
            }
            let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
            if marker != 0xC4 {
                out.extend_from_slice(&jpeg[i..i + 2 + len]);
            }
            i += 2 + len;
        }
        out.extend_from_slice(&jpeg[i..]);
        out
    }

    fn max_abs_diff(a: &[u16], b: &[u8]) -> u16 {
        a.iter()
            .zip(b)
            .map(|(&x, &y)| x.abs_diff(u16::from(y)))
            .max()
            .unwrap()
    }

    /// GREY with a padded stride: the padding bytes (0xEE) never show up in the image.
    #[test]
    fn grey_with_stride() {
        let data = [1, 2, 3, 0xEE, 4, 5, 6, 0xEE];
        assert_eq!(
            grey_to_luma(&data, 3, 2, 4).unwrap(),
            vec![1, 2, 3, 4, 5, 6]
        );
        // Packed (stride 0) and the last row without padding are both fine.
        assert_eq!(grey_to_luma(&data[..7], 3, 2, 4).unwrap().len(), 6);
        assert_eq!(grey_to_luma(&[9, 8], 2, 1, 0).unwrap(), vec![9, 8]);
    }

    /// YUYV keeps the Y bytes (0, 2, 4, ...) and drops U and V; range is not expanded.
    #[test]
    fn yuyv_takes_y() {
        // 4x2: Y0 U Y1 V Y2 U Y3 V per row.
        let row0 = [16, 128, 50, 128, 100, 90, 235, 200];
        let row1 = [0, 1, 255, 2, 17, 3, 18, 4];
        let data: Vec<u8> = row0.iter().chain(row1.iter()).copied().collect();
        assert_eq!(
            yuyv_to_luma(&data, 4, 2, 0).unwrap(),
            vec![16, 50, 100, 235, 0, 255, 17, 18]
        );
    }

    /// Y16 is little-endian: bytes [0x34, 0x12] are 0x1234; the full 16-bit range survives.
    #[test]
    fn y16_little_endian() {
        let data = [0x34, 0x12, 0xFF, 0xFF, 0x00, 0x00, 0x01, 0x00];
        assert_eq!(
            y16_to_luma(&data, 2, 2, 0).unwrap(),
            vec![0x1234, 0xFFFF, 0, 1]
        );
    }

    /// Truncated buffers, short strides and empty or absurd sizes are errors that say what
    /// was expected.
    #[test]
    fn truncated_and_bad_sizes_rejected() {
        let e = yuyv_to_luma(&[0; 15], 4, 2, 0).unwrap_err();
        assert_eq!(
            e,
            ConvertError::Short {
                got_bytes: 15,
                needed_bytes: 16,
                width: 4,
                height: 2
            }
        );
        assert!(e.to_string().contains("needs 16"), "{e}");
        assert!(matches!(
            grey_to_luma(&[0; 10], 4, 2, 3),
            Err(ConvertError::StrideTooSmall {
                stride_bytes: 3,
                row_bytes: 4
            })
        ));
        assert!(matches!(
            y16_to_luma(&[0; 7], 2, 2, 0),
            Err(ConvertError::Short { .. })
        ));
        assert!(matches!(
            grey_to_luma(&[], 0, 5, 0),
            Err(ConvertError::BadSize { .. })
        ));
        assert!(matches!(
            grey_to_luma(&[0; 4], u32::MAX, u32::MAX, usize::MAX),
            Err(ConvertError::BadSize { .. })
        ));
        // A huge stride overflows the needed size: an error, not a wrap-around.
        assert!(matches!(
            grey_to_luma(&[0; 4], 2, 3, usize::MAX / 2),
            Err(ConvertError::Short { .. })
        ));
        assert!(matches!(
            mjpeg_to_luma(&[], 2, 2),
            Err(ConvertError::Jpeg(_))
        ));
    }

    /// A grey JPEG at quality 90 decodes to the original within 6 levels (JPEG loss at this
    /// quality on a smooth ramp with one hard-edged square; measured about 3).
    #[test]
    fn mjpeg_grey_within_jpeg_loss() {
        let src = test_luma(32, 16);
        let data = jpeg(&src, 32, 16, false, 90);
        let luma = mjpeg_to_luma(&data, 32, 16).unwrap();
        assert_eq!(luma.len(), 32 * 16);
        let d = max_abs_diff(&luma, &src);
        assert!(d <= 6, "max |decoded - source| = {d} levels");
    }

    /// A colour 4:2:2 JPEG (as webcams send) yields its luma: BT.601 Y of the RGB source
    /// within 6 levels (JPEG loss plus the encoder's rounding of Y; measured 1).
    #[test]
    fn mjpeg_colour_gives_bt601_luma() {
        let (w, h) = (32usize, 16usize);
        let mut rgb = Vec::with_capacity(w * h * 3);
        let mut expected = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (r, g, b) = if y < h / 2 {
                    (200u8, 60u8, 30u8) // a flat orange half
                } else {
                    (40, 90, (x * 7) as u8) // a blue ramp half
                };
                rgb.extend_from_slice(&[r, g, b]);
                let luma = 0.299 * f64::from(r) + 0.587 * f64::from(g) + 0.114 * f64::from(b);
                expected.push(luma.round() as u8);
            }
        }
        let data = jpeg(&rgb, w as u16, h as u16, true, 92);
        let luma = mjpeg_to_luma(&data, w as u32, h as u32).unwrap();
        let d = max_abs_diff(&luma, &expected);
        assert!(d <= 6, "max |decoded Y - BT.601 Y| = {d} levels");
    }

    /// UVC MJPEG leaves out the Huffman tables; the decoder falls back to the standard ones
    /// (which is what the encoder used), so the result is identical.
    #[test]
    fn mjpeg_without_huffman_tables() {
        let src = test_luma(32, 16);
        let data = jpeg(&src, 32, 16, false, 90);
        let stripped = strip_dht(&data);
        assert!(stripped.len() < data.len(), "a DHT segment was removed");
        assert_eq!(
            mjpeg_to_luma(&stripped, 32, 16).unwrap(),
            mjpeg_to_luma(&data, 32, 16).unwrap()
        );
    }

    /// The inserted DHT segment has the well-known MJPEG layout (FF C4 01 A2, 420 bytes in
    /// all), goes in only where tables are missing, and leaves non-JPEG bytes alone.
    #[test]
    fn default_huffman_tables_inserted_only_when_missing() {
        let dht = default_dht_segment();
        assert_eq!(&dht[..4], &[0xFF, 0xC4, 0x01, 0xA2]);
        assert_eq!(dht.len(), 420);
        let data = jpeg(&test_luma(16, 8), 16, 8, false, 80);
        assert!(matches!(
            with_default_huffman_tables(&data),
            std::borrow::Cow::Borrowed(_)
        ));
        let stripped = strip_dht(&data);
        let fixed = with_default_huffman_tables(&stripped);
        assert_eq!(fixed.len(), stripped.len() + 420);
        assert!(matches!(
            with_default_huffman_tables(&[1, 2, 3]),
            std::borrow::Cow::Borrowed(_)
        ));
    }

    /// A truncated JPEG (a short USB transfer) and one of another size are errors, never a
    /// partly grey image.
    #[test]
    fn mjpeg_truncated_or_wrong_size_rejected() {
        let src = test_luma(32, 16);
        let data = jpeg(&src, 32, 16, false, 90);
        for cut in [data.len() / 3, data.len() / 2, data.len() - 40] {
            let e = mjpeg_to_luma(&data[..cut], 32, 16).unwrap_err();
            assert!(matches!(e, ConvertError::Jpeg(_)), "cut at {cut}: {e}");
        }
        let e = mjpeg_to_luma(&data, 16, 16).unwrap_err();
        assert!(
            matches!(
                e,
                ConvertError::Jpeg(_) | ConvertError::JpegSize { got_width: 32, .. }
            ),
            "{e}"
        );
        let e = mjpeg_to_luma(&data, 64, 16).unwrap_err();
        assert_eq!(
            e,
            ConvertError::JpegSize {
                got_width: 32,
                got_height: 16,
                width: 64,
                height: 16
            }
        );
    }

    /// Cropping picks the rows and columns of the region; out-of-frame regions are refused.
    #[test]
    fn crop_region() {
        let px: Vec<u16> = (0..12).collect(); // 4x3
        let roi = Roi {
            x: 1,
            y: 1,
            width: 2,
            height: 2,
        };
        assert_eq!(crop(&px, 4, 3, roi).unwrap(), vec![5, 6, 9, 10]);
        assert_eq!(crop(&px, 4, 3, Roi::full(4, 3)).unwrap(), px);
        let outside = Roi {
            x: 3,
            y: 0,
            width: 2,
            height: 1,
        };
        assert!(matches!(
            crop(&px, 4, 3, outside),
            Err(ConvertError::RoiOutside { .. })
        ));
        assert!(matches!(
            crop(&px[..11], 4, 3, roi),
            Err(ConvertError::Short { .. })
        ));
    }

    fn any_size() -> impl Strategy<Value = (u32, u32, usize)> {
        (0u32..40, 0u32..40, 0usize..100)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        /// Random bytes at random sizes and strides never panic the raw converters; when they
        /// succeed the image has exactly width x height pixels.
        #[test]
        fn raw_converters_never_panic(
            data in proptest::collection::vec(any::<u8>(), 0..4000),
            (w, h, stride) in any_size(),
        ) {
            for px in [
                grey_to_luma(&data, w, h, stride),
                yuyv_to_luma(&data, w, h, stride),
                y16_to_luma(&data, w, h, stride),
            ]
            .into_iter()
            .flatten()
            {
                prop_assert_eq!(px.len(), w as usize * h as usize);
            }
        }

        /// Random bytes never panic the JPEG path, and the decoder itself did not panic
        /// (the `catch_unwind` guard was not needed).
        #[test]
        fn mjpeg_random_bytes_never_panic(
            data in proptest::collection::vec(any::<u8>(), 0..2000),
            (w, h, _) in any_size(),
        ) {
            let out = mjpeg_to_luma(&data, w, h);
            prop_assert!(!matches!(out, Err(ConvertError::DecoderPanicked(_))), "{:?}", out);
        }

        /// A valid JPEG with random bytes overwritten and a random cut never panics, and
        /// whatever decodes has the stream's size.
        #[test]
        fn mjpeg_mutated_never_panics(
            edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..12),
            cut in any::<prop::sample::Index>(),
            strip in any::<bool>(),
        ) {
            let src = test_luma(32, 16);
            let mut data = jpeg(&src, 32, 16, false, 85);
            if strip {
                data = strip_dht(&data);
            }
            for (at, byte) in edits {
                let i = at.index(data.len());
                data[i] = byte;
            }
            let keep = 1 + cut.index(data.len());
            let out = mjpeg_to_luma(&data[..keep], 32, 16);
            prop_assert!(!matches!(out, Err(ConvertError::DecoderPanicked(_))), "{:?}", out);
            if let Ok(px) = out {
                prop_assert_eq!(px.len(), 32 * 16);
            }
        }

        /// Any region is either cropped to exactly its size or refused.
        #[test]
        fn crop_never_panics(x in 0u32..12, y in 0u32..12, rw in 0u32..12, rh in 0u32..12) {
            let px: Vec<u16> = (0..48).collect(); // 8x6
            let roi = Roi { x, y, width: rw, height: rh };
            match crop(&px, 8, 6, roi) {
                Ok(out) => prop_assert_eq!(out.len(), roi.pixels()),
                Err(e) => prop_assert!(matches!(e, ConvertError::RoiOutside { .. }), "{}", e),
            }
        }
    }
}
