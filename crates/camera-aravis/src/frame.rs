//! Pure helpers of the backend: frame-id unwrapping and pixel conversion. No Aravis calls, so
//! they are unit-tested without a camera.

use polar_hal::PixelFormat;

/// The GigE Vision 1.x block-id space: ids are 16-bit and wrap (0 is reserved, so after 65535
/// comes 1).
const BLOCK_ID_SPAN: u64 = 1 << 16;

/// Turns the device's frame ids, which wrap at 16 bits on GigE Vision 1.x (Aravis's fake starts
/// near 65401 to make the wrap come early), into a strictly increasing `u64`.
///
/// * A backward jump of more than half the 16-bit space between two 16-bit ids is a wrap: the
///   id keeps counting, and the gap of lost frames across the wrap is preserved.
/// * Any other step that is not forward (the device restarted its counter on a new
///   acquisition, or repeated an id) continues one past the last id, so ids never repeat.
/// * Ids above 16 bits (GigE Vision 2 extended ids, USB3 Vision) are 64-bit and never wrap in
///   practice; they pass through shifted by whatever offset earlier restarts required.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FrameIdUnwrapper {
    /// The last raw id and the unwrapped id it was given.
    last: Option<(u64, u64)>,
    /// Added to raw ids.
    offset: u64,
}

impl FrameIdUnwrapper {
    /// A new unwrapper; the first id passes unchanged.
    pub fn new() -> Self {
        Self::default()
    }

    /// The unwrapped id of the next buffer's raw id.
    pub fn unwrap(&mut self, raw: u64) -> u64 {
        if let Some((last_raw, last_unwrapped)) = self.last {
            let both_16_bit = last_raw < BLOCK_ID_SPAN && raw < BLOCK_ID_SPAN;
            if both_16_bit && last_raw > raw && last_raw - raw > BLOCK_ID_SPAN / 2 {
                self.offset = self.offset.saturating_add(BLOCK_ID_SPAN);
            }
            if self.offset.saturating_add(raw) <= last_unwrapped {
                // A restart or a repeat: continue just after the last id.
                self.offset = last_unwrapped.saturating_add(1).saturating_sub(raw);
            }
        }
        let unwrapped = self.offset.saturating_add(raw);
        self.last = Some((raw, unwrapped));
        unwrapped
    }
}

/// Bytes per pixel of a format as Aravis delivers it (Mono12 unpacked in 16 bits).
pub fn bytes_per_pixel(format: PixelFormat) -> usize {
    match format {
        PixelFormat::Mono8 => 1,
        PixelFormat::Mono12 | PixelFormat::Mono16 => 2,
    }
}

/// Converts an image's bytes to `u16` pixels, row by row. Rows are `width * bytes_per_pixel`
/// bytes followed by `row_padding_bytes` of padding; 16-bit pixels are little-endian (GenICam
/// PFNC). The error says how many bytes came and how many were needed: a short buffer is never
/// read past its end and never padded with made-up pixels.
pub fn pixels_from_bytes(
    data: &[u8],
    format: PixelFormat,
    width: u32,
    height: u32,
    row_padding_bytes: u32,
) -> Result<Vec<u16>, String> {
    let bpp = bytes_per_pixel(format);
    let (w, h) = (width as usize, height as usize);
    if w == 0 || h == 0 {
        return Err(format!("image size {width}x{height} is empty"));
    }
    let too_big = || format!("image size {width}x{height} {format} overflows");
    let row = w.checked_mul(bpp).ok_or_else(too_big)?;
    let stride = row
        .checked_add(row_padding_bytes as usize)
        .ok_or_else(too_big)?;
    let needed = stride
        .checked_mul(h - 1)
        .and_then(|n| n.checked_add(row))
        .ok_or_else(too_big)?;
    if data.len() < needed {
        return Err(format!(
            "image data has {} bytes, expected at least {needed} for {width}x{height} {format}",
            data.len()
        ));
    }
    let mut pixels = Vec::with_capacity(w * h);
    for r in 0..h {
        let line = &data[r * stride..r * stride + row];
        match format {
            PixelFormat::Mono8 => pixels.extend(line.iter().map(|&b| u16::from(b))),
            PixelFormat::Mono12 | PixelFormat::Mono16 => pixels.extend(
                line.chunks_exact(2)
                    .map(|pair| u16::from_le_bytes([pair[0], pair[1]])),
            ),
        }
    }
    Ok(pixels)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Aravis's fake starts at 65401: ids run through the 16-bit wrap (65535 -> 1, id 0 being
    /// reserved) and keep increasing; a gap of lost frames across the wrap is kept (65534 ->
    /// 3 skips 65535, 1 and 2).
    #[test]
    fn unwraps_the_16_bit_block_id() {
        let mut u = FrameIdUnwrapper::new();
        let ids: Vec<u64> = [65401, 65402, 65535, 1, 2, 3]
            .into_iter()
            .map(|r| u.unwrap(r))
            .collect();
        assert_eq!(ids, vec![65401, 65402, 65535, 65537, 65538, 65539]);
        let mut u = FrameIdUnwrapper::new();
        assert_eq!(u.unwrap(65534), 65534);
        assert_eq!(u.unwrap(3), 65536 + 3, "the lost frames stay a gap");
        // A second wrap.
        assert_eq!(u.unwrap(65000), 65536 + 65000);
        assert_eq!(u.unwrap(10), 2 * 65536 + 10);
    }

    /// A counter restarted by a new acquisition (500 -> 1) or a repeated id continues just after
    /// the last id instead of going back: ids are strictly increasing.
    #[test]
    fn restarts_and_repeats_stay_monotonic() {
        let mut u = FrameIdUnwrapper::new();
        assert_eq!(u.unwrap(499), 499);
        assert_eq!(u.unwrap(500), 500);
        assert_eq!(u.unwrap(1), 501);
        assert_eq!(u.unwrap(2), 502);
        assert_eq!(u.unwrap(2), 503);
        assert_eq!(u.unwrap(10), 511, "forward gaps after a restart are kept");
    }

    /// 64-bit ids (GigE Vision 2 extended ids) pass through; crossing 65536 upward is not a wrap.
    #[test]
    fn extended_ids_pass_through() {
        let mut u = FrameIdUnwrapper::new();
        assert_eq!(u.unwrap(65535), 65535);
        assert_eq!(u.unwrap(65536), 65536);
        assert_eq!(u.unwrap(1 << 40), 1 << 40);
        assert_eq!(u.unwrap((1 << 40) + 1), (1 << 40) + 1);
    }

    /// Mono8 widens, Mono16 and Mono12 are little-endian pairs, and row padding is skipped.
    #[test]
    fn converts_rows_and_skips_padding() {
        assert_eq!(
            pixels_from_bytes(&[0, 7, 255, 9], PixelFormat::Mono8, 2, 2, 0),
            Ok(vec![0, 7, 255, 9])
        );
        assert_eq!(
            pixels_from_bytes(&[0x34, 0x12, 0xff, 0xff], PixelFormat::Mono16, 2, 1, 0),
            Ok(vec![0x1234, 0xffff])
        );
        // Two rows of one Mono12 pixel, each followed by 3 bytes of padding (the last row's
        // padding may be missing).
        assert_eq!(
            pixels_from_bytes(
                &[0xff, 0x0f, 9, 9, 9, 0x01, 0x00],
                PixelFormat::Mono12,
                1,
                2,
                3
            ),
            Ok(vec![4095, 1])
        );
    }

    /// A buffer shorter than its size says is refused with both byte counts, never padded; an
    /// absurd size does not overflow.
    #[test]
    fn short_or_absurd_buffers_are_refused() {
        let e = pixels_from_bytes(&[1, 2, 3], PixelFormat::Mono8, 2, 2, 0).expect_err("short");
        assert!(e.contains("3 bytes, expected at least 4"), "{e}");
        let e = pixels_from_bytes(&[1; 6], PixelFormat::Mono16, 2, 2, 0).expect_err("short");
        assert!(e.contains("6 bytes, expected at least 8"), "{e}");
        assert!(pixels_from_bytes(&[], PixelFormat::Mono8, 0, 5, 0).is_err());
        assert!(pixels_from_bytes(&[1; 8], PixelFormat::Mono16, u32::MAX, u32::MAX, 0).is_err());
    }
}
