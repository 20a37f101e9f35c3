//! The frame formats nokhwa delivers that carry luminance, and their conversion to `Mono8`
//! pixels (through `polar-frame-convert`, the conversions the V4L2 backend uses too).
//!
//! nokhwa 0.10 knows six formats: `MJPEG`, `YUYV`, `NV12`, `GRAY`, `RAWRGB`, `RAWBGR`. The first
//! four carry a luma plane or channel and are read here; the two RGB ones would need a colour
//! to luminance weighting that the ISP has already chosen differently per camera, so they are
//! not offered. nokhwa has no 16-bit format (no `Y16`), so every frame from this backend is
//! `Mono8`. On Linux nokhwa looks for the fourcc `GRAY`, which no V4L2 driver reports (V4L2's
//! 8-bit grey is `GREY`), so there `GRAY` is never found (`docs/DEVICES.md`, section 3.4).

use nokhwa::utils::FrameFormat;
use polar_frame_convert::{self as convert, ConvertError};

/// A nokhwa format this backend reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SourceFormat {
    /// 8-bit grey.
    Gray,
    /// YUV 4:2:2, `Y0 U Y1 V`.
    Yuyv,
    /// YUV 4:2:0: a full-resolution Y plane, then interleaved half-resolution UV.
    Nv12,
    /// Motion JPEG, one JPEG per frame.
    Mjpeg,
}

impl SourceFormat {
    /// Every format read, in the order tried when opening: raw grey first, then the
    /// uncompressed YUV formats, then MJPEG (lossy, the last resort).
    pub const PREFERENCE: [SourceFormat; 4] = [
        SourceFormat::Gray,
        SourceFormat::Yuyv,
        SourceFormat::Nv12,
        SourceFormat::Mjpeg,
    ];

    /// The nokhwa format.
    pub fn nokhwa(self) -> FrameFormat {
        match self {
            SourceFormat::Gray => FrameFormat::GRAY,
            SourceFormat::Yuyv => FrameFormat::YUYV,
            SourceFormat::Nv12 => FrameFormat::NV12,
            SourceFormat::Mjpeg => FrameFormat::MJPEG,
        }
    }

    /// The format for a nokhwa format, `None` for the RGB ones.
    pub fn from_nokhwa(format: FrameFormat) -> Option<SourceFormat> {
        SourceFormat::PREFERENCE
            .into_iter()
            .find(|f| f.nokhwa() == format)
    }

    /// The format's name, as nokhwa prints it.
    pub fn name(self) -> &'static str {
        match self {
            SourceFormat::Gray => "GRAY",
            SourceFormat::Yuyv => "YUYV",
            SourceFormat::Nv12 => "NV12",
            SourceFormat::Mjpeg => "MJPEG",
        }
    }

    /// One packed frame (nokhwa's buffers have no row padding) to `Mono8` pixels, row-major.
    /// A short buffer, a bad size or a JPEG that does not decode to `width x height` is an
    /// error, never a partial image.
    pub fn to_luma(self, data: &[u8], width: u32, height: u32) -> Result<Vec<u16>, ConvertError> {
        match self {
            SourceFormat::Gray => convert::grey_to_luma(data, width, height, 0),
            SourceFormat::Yuyv => convert::yuyv_to_luma(data, width, height, 0),
            SourceFormat::Nv12 => {
                // The Y plane is the first width x height bytes; the UV plane after it holds
                // width x ceil(height / 2) bytes. A buffer without all of it is truncated.
                let y_bytes = width as usize * height as usize;
                let needed = y_bytes + width as usize * (height as usize).div_ceil(2);
                if data.len() < needed && y_bytes > 0 {
                    return Err(ConvertError::Short {
                        got_bytes: data.len(),
                        needed_bytes: needed,
                        width,
                        height,
                    });
                }
                convert::grey_to_luma(data, width, height, 0)
            }
            SourceFormat::Mjpeg => convert::mjpeg_to_luma(data, width, height),
        }
    }
}

impl std::fmt::Display for SourceFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// GRAY is the sensor's bytes, one per pixel, unchanged (max 255).
    #[test]
    fn gray_is_the_bytes() {
        let data = [0u8, 17, 128, 255, 3, 4];
        assert_eq!(
            SourceFormat::Gray.to_luma(&data, 3, 2),
            Ok(vec![0, 17, 128, 255, 3, 4])
        );
    }

    /// YUYV's luma is every other byte (Y0 U Y1 V): the chroma bytes must not leak in.
    #[test]
    fn yuyv_takes_the_y_bytes() {
        // Two rows of two pixels: Y = 10, 20 / 30, 40; chroma 200 and 250 everywhere.
        let data = [10u8, 200, 20, 250, 30, 200, 40, 250];
        assert_eq!(
            SourceFormat::Yuyv.to_luma(&data, 2, 2),
            Ok(vec![10, 20, 30, 40])
        );
    }

    /// NV12's luma is its first plane; a buffer cut inside the chroma plane is refused as
    /// truncated (naming the bytes needed), and one cut inside the luma plane too.
    #[test]
    fn nv12_takes_the_y_plane_and_refuses_truncation() {
        // 4x3: Y plane 12 bytes (values 1..=12), UV plane 4 * ceil(3/2) = 8 bytes of 99.
        let mut data: Vec<u8> = (1..=12).collect();
        data.extend([99u8; 8]);
        let luma = SourceFormat::Nv12.to_luma(&data, 4, 3).expect("complete");
        assert_eq!(luma, (1..=12).collect::<Vec<u16>>());
        let e = SourceFormat::Nv12.to_luma(&data[..19], 4, 3).unwrap_err();
        assert_eq!(
            e,
            ConvertError::Short {
                got_bytes: 19,
                needed_bytes: 20,
                width: 4,
                height: 3
            }
        );
        assert!(SourceFormat::Nv12.to_luma(&data[..10], 4, 3).is_err());
    }

    /// An MJPEG frame as a colour webcam sends it (4:2:2) decodes to its luma: a uniform
    /// RGB (90, 160, 40) has BT.601 luma 0.299*90 + 0.587*160 + 0.114*40 = 125.3, and JPEG at
    /// quality 95 keeps a flat field within 2 levels. A JPEG of another size than the stream's is
    /// refused.
    #[test]
    fn mjpeg_decodes_to_its_luma() {
        use jpeg_encoder::{ColorType, Encoder, SamplingFactor};
        let (w, h) = (32u16, 16u16);
        let rgb: Vec<u8> = [90u8, 160, 40].repeat(usize::from(w) * usize::from(h));
        let mut jpeg = Vec::new();
        let mut encoder = Encoder::new(&mut jpeg, 95);
        encoder.set_sampling_factor(SamplingFactor::F_2_1);
        encoder
            .encode(&rgb, w, h, ColorType::Rgb)
            .expect("encode the test JPEG");
        let luma = SourceFormat::Mjpeg
            .to_luma(&jpeg, u32::from(w), u32::from(h))
            .expect("decodes");
        assert_eq!(luma.len(), 32 * 16);
        for &y in &luma {
            assert!((f64::from(y) - 125.3).abs() <= 2.0, "luma {y}");
        }
        assert!(matches!(
            SourceFormat::Mjpeg.to_luma(&jpeg, 64, 16),
            Err(ConvertError::JpegSize { .. })
        ));
    }

    /// A truncated buffer in any format is an error, never a partial image; a zero size is
    /// refused.
    #[test]
    fn short_and_empty_buffers_are_errors() {
        for f in SourceFormat::PREFERENCE {
            assert!(f.to_luma(&[1, 2, 3], 4, 4).is_err(), "{f}");
            assert!(f.to_luma(&[], 0, 0).is_err(), "{f}");
        }
    }

    /// Every luma format maps to nokhwa's and back; the RGB formats are not offered.
    #[test]
    fn nokhwa_formats_round_trip() {
        for f in SourceFormat::PREFERENCE {
            assert_eq!(SourceFormat::from_nokhwa(f.nokhwa()), Some(f));
        }
        assert_eq!(SourceFormat::from_nokhwa(FrameFormat::RAWRGB), None);
        assert_eq!(SourceFormat::from_nokhwa(FrameFormat::RAWBGR), None);
    }
}
