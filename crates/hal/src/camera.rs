//! The camera trait and its frame (`ARCHITECTURE.md`, "Device abstraction").
//!
//! A [`Camera`] is configured (exposure, gain, pixel format, region of interest, trigger),
//! started, and grabbed from with a deadline. Every [`Frame`] carries its pixels widened to
//! `u16`, its host and device timestamps, its frame id, and the exposure and gain the device
//! reports it applied (read back, not the request). Backends over blocking SDKs run the SDK on a
//! named thread and hand frames over a bounded queue (`polar_hal::camera_thread`); the
//! simulated camera lives in `polar-hil-mocks`.

use crate::{DeviceError, ErrorKind};
use std::time::{Duration, SystemTime};

/// The pixel formats the polarimeter reads. Mono12 is delivered unpacked (one `u16` per pixel,
/// values `0..4096`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PixelFormat {
    /// 8 bits per pixel.
    Mono8,
    /// 12 bits per pixel, in the low bits of a `u16`.
    Mono12,
    /// 16 bits per pixel.
    Mono16,
}

impl PixelFormat {
    /// Bits per pixel of the data (not of the container).
    pub fn bits(self) -> u32 {
        match self {
            PixelFormat::Mono8 => 8,
            PixelFormat::Mono12 => 12,
            PixelFormat::Mono16 => 16,
        }
    }

    /// The largest pixel value.
    pub fn max_value(self) -> u16 {
        ((1u32 << self.bits()) - 1) as u16
    }

    /// The format's GenICam SFNC name (`"Mono8"`, ...).
    pub fn name(self) -> &'static str {
        match self {
            PixelFormat::Mono8 => "Mono8",
            PixelFormat::Mono12 => "Mono12",
            PixelFormat::Mono16 => "Mono16",
        }
    }

    /// Parses an SFNC name, case-insensitively.
    pub fn from_name(name: &str) -> Option<PixelFormat> {
        [PixelFormat::Mono8, PixelFormat::Mono12, PixelFormat::Mono16]
            .into_iter()
            .find(|f| f.name().eq_ignore_ascii_case(name))
    }
}

impl std::fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A region of interest on the sensor, pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Roi {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Width, at least 1.
    pub width: u32,
    /// Height, at least 1.
    pub height: u32,
}

impl Roi {
    /// The whole sensor.
    pub fn full(sensor_width: u32, sensor_height: u32) -> Roi {
        Roi {
            x: 0,
            y: 0,
            width: sensor_width,
            height: sensor_height,
        }
    }

    /// Checks that the region is non-empty and lies on a `sensor_width x sensor_height`
    /// sensor; the error names the device, the region and the sensor size.
    pub fn check(
        &self,
        device: &str,
        sensor_width: u32,
        sensor_height: u32,
    ) -> Result<(), DeviceError> {
        let fits = self.width >= 1
            && self.height >= 1
            && u64::from(self.x) + u64::from(self.width) <= u64::from(sensor_width)
            && u64::from(self.y) + u64::from(self.height) <= u64::from(sensor_height);
        if fits {
            Ok(())
        } else {
            Err(DeviceError::new(
                ErrorKind::OutOfRange,
                device,
                format!(
                    "roi = {}x{} at ({}, {}) is out of range: allowed a non-empty region inside the {}x{} sensor",
                    self.width, self.height, self.x, self.y, sensor_width, sensor_height
                ),
            ))
        }
    }

    /// Pixels in the region.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// When the camera exposes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TriggerMode {
    /// Continuously, at the camera's frame rate.
    FreeRun,
    /// On [`Camera::trigger`].
    Software,
    /// On an edge at the camera's trigger input (only where
    /// [`Camera::supports_hardware_trigger`]).
    Hardware,
}

/// The unit of a camera's gain setting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum GainUnit {
    /// Decibels of amplitude gain (SFNC `Gain`): 0 dB is unity.
    Decibel,
    /// A device-specific raw register value (GenICam `GainRaw`), monotonic in the gain.
    Raw,
}

/// What a camera is and what it can be set to.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraInfo {
    /// The id it is opened by (GenICam device id, V4L2 path, `sim`).
    pub id: String,
    /// Vendor, as the device reports it.
    pub vendor: String,
    /// Model, as the device reports it.
    pub model: String,
    /// Serial number, if reported.
    pub serial: String,
    /// Sensor width, pixels.
    pub sensor_width: u32,
    /// Sensor height, pixels.
    pub sensor_height: u32,
    /// Exposure range, microseconds `[min, max]`.
    pub exposure_range_us: [f64; 2],
    /// Gain range in [`CameraInfo::gain_unit`].
    pub gain_range: [f64; 2],
    /// The gain's unit.
    pub gain_unit: GainUnit,
    /// Pixel formats offered.
    pub formats: Vec<PixelFormat>,
}

impl CameraInfo {
    /// Checks an exposure against the range; the error names the value and the range.
    pub fn check_exposure_us(&self, exposure_us: f64) -> Result<f64, DeviceError> {
        let [lo, hi] = self.exposure_range_us;
        if exposure_us.is_finite() && (lo..=hi).contains(&exposure_us) {
            Ok(exposure_us)
        } else {
            Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.id,
                format!("exposure_us = {exposure_us} is out of range: allowed [{lo}, {hi}]"),
            ))
        }
    }

    /// Checks a gain against the range; the error names the value and the range.
    pub fn check_gain(&self, gain: f64) -> Result<f64, DeviceError> {
        let [lo, hi] = self.gain_range;
        if gain.is_finite() && (lo..=hi).contains(&gain) {
            Ok(gain)
        } else {
            Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.id,
                format!(
                    "gain = {gain} is out of range: allowed [{lo}, {hi}] ({:?})",
                    self.gain_unit
                ),
            ))
        }
    }

    /// Checks that a pixel format is offered.
    pub fn check_format(&self, format: PixelFormat) -> Result<PixelFormat, DeviceError> {
        if self.formats.contains(&format) {
            Ok(format)
        } else {
            let offered: Vec<&str> = self.formats.iter().map(|f| f.name()).collect();
            Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.id,
                format!(
                    "pixel_format = {format} is not offered: allowed {}",
                    offered.join(", ")
                ),
            ))
        }
    }
}

/// One image and what is known about how it was taken.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Row-major pixels, `width * height` of them, each `<= format.max_value()`.
    pub pixels: Vec<u16>,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// The data's format.
    pub format: PixelFormat,
    /// When the host received the frame.
    pub host_time: SystemTime,
    /// The device's timestamp, nanoseconds on the device's clock, if it has one.
    pub device_timestamp_ns: Option<u64>,
    /// The frame id as the device counts it (may wrap; GigE Vision block ids are 16-bit).
    pub frame_id: u64,
    /// The exposure the device reports it applied, microseconds.
    pub exposure_us: f64,
    /// The gain the device reports it applied, in the camera's [`GainUnit`].
    pub gain: f64,
}

impl Frame {
    /// The pixel at `(x, y)`, or `None` outside the frame.
    pub fn at(&self, x: u32, y: u32) -> Option<u16> {
        if x < self.width && y < self.height {
            self.pixels
                .get(y as usize * self.width as usize + x as usize)
                .copied()
        } else {
            None
        }
    }

    /// The mean pixel value (0 for an empty frame).
    pub fn mean(&self) -> f64 {
        if self.pixels.is_empty() {
            return 0.0;
        }
        self.pixels.iter().map(|&p| f64::from(p)).sum::<f64>() / self.pixels.len() as f64
    }

    /// Checks the frame's own consistency (pixel count, value range); the error names what is
    /// wrong. Backends call this before handing a frame out, so a truncated or garbled buffer
    /// never passes as an image.
    pub fn check(&self, device: &str) -> Result<(), DeviceError> {
        let expected = self.width as usize * self.height as usize;
        if self.pixels.len() != expected || expected == 0 {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                device,
                format!(
                    "frame {} has {} pixels, expected {}x{} = {expected}",
                    self.frame_id,
                    self.pixels.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        let max = self.format.max_value();
        if let Some(p) = self.pixels.iter().find(|&&p| p > max) {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                device,
                format!(
                    "frame {} has pixel value {p} above the {} maximum {max}",
                    self.frame_id, self.format
                ),
            ));
        }
        Ok(())
    }
}

/// Counters of a camera's stream since it was opened.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StreamStats {
    /// Frames handed to the caller.
    pub delivered: u64,
    /// Frames the device or transport delivered incomplete (missing packets, truncated), never
    /// handed out.
    pub incomplete: u64,
    /// Complete frames dropped because the consumer was too slow (the queue was full).
    pub dropped: u64,
    /// Grabs that ended at their deadline without a frame.
    pub timeouts: u64,
    /// The transport's own counters, where it keeps them (GigE Vision packets).
    pub transport: Option<TransportStats>,
}

/// A packet transport's counters since the stream started (GigE Vision: Aravis's stream
/// statistics).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TransportStats {
    /// Packets received.
    pub received_packets: u64,
    /// Packets found missing from a frame (before any resend).
    pub missing_packets: u64,
    /// Packets asked for again.
    pub resend_requests: u64,
    /// Packets that came back when asked for again.
    pub resent_packets: u64,
    /// Whether lost packets are asked for again at all (GigE Vision: only where the device
    /// offers packet resend in its GVCP capabilities; Aravis's fake cameras do not).
    pub packet_resend: bool,
}

/// A camera.
#[allow(async_fn_in_trait)] // used through generics; Send-ness is the implementor's business
pub trait Camera {
    /// Identity, sensor size and ranges.
    fn info(&self) -> &CameraInfo;
    /// Sets the exposure and returns the exposure the device applied (read back), microseconds.
    async fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError>;
    /// Sets the gain (in [`CameraInfo::gain_unit`]) and returns the gain applied (read back).
    async fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError>;
    /// Sets the pixel format (while stopped).
    async fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError>;
    /// Sets the region of interest (while stopped) and returns the region applied (devices may
    /// round to their increments).
    async fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError>;
    /// Sets the trigger mode (while stopped).
    async fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError>;
    /// Whether [`TriggerMode::Hardware`] is available.
    fn supports_hardware_trigger(&self) -> bool {
        false
    }
    /// Whether [`TriggerMode::Software`] is available.
    fn supports_software_trigger(&self) -> bool {
        true
    }
    /// Starts acquisition.
    async fn start(&mut self) -> Result<(), DeviceError>;
    /// Stops acquisition; frames not yet grabbed are discarded.
    async fn stop(&mut self) -> Result<(), DeviceError>;
    /// Fires a software trigger (in [`TriggerMode::Software`]).
    async fn trigger(&mut self) -> Result<(), DeviceError>;
    /// The next complete frame, or [`ErrorKind::Timeout`] after `deadline`, or
    /// [`ErrorKind::Disconnected`] if the camera went away.
    async fn grab(&mut self, deadline: Duration) -> Result<Frame, DeviceError>;
    /// Waits until the exposure started by the last [`Camera::trigger`] has ended: the sensor
    /// no longer integrates, so the analyzer may move while the frame is read out and
    /// transferred (GenICam's `ExposureEnd` event). Returns the id of the frame that exposure
    /// will be delivered as, or `Ok(None)` at once when this camera does not report exposure
    /// ends (then only the frame's arrival says the sensor is done). A caller that moves on the
    /// event must check that the frame it then grabs carries the returned id.
    async fn exposure_end(&mut self, deadline: Duration) -> Result<Option<u64>, DeviceError> {
        let _ = deadline;
        Ok(None)
    }
    /// Stream counters.
    fn stats(&self) -> StreamStats;
}

/// Told, on the camera's own thread, the frame id of each exposure as it ends (see
/// [`BlockingCamera::on_exposure_end`]).
pub type ExposureEndHook = Box<dyn Fn(u64) + Send>;

/// What one wait on a blocking SDK's stream gave.
#[derive(Debug, Clone, PartialEq)]
pub enum Grabbed {
    /// A complete frame (already [`Frame::check`]ed by the backend).
    Frame(Frame),
    /// A buffer that came back incomplete (missing packets, truncated); never an image.
    Incomplete {
        /// Its frame id, if the transport knew it.
        frame_id: Option<u64>,
        /// What was wrong, as the SDK said it.
        reason: String,
    },
    /// Nothing arrived within the wait.
    Nothing,
}

/// A camera behind a blocking SDK (aravis, V4L2, the simulated camera's renderer). It is driven
/// from one dedicated thread (`polar_hal::camera_thread::ThreadedCamera`), which turns it into
/// an async [`Camera`]; implementations may block in every call but must return from
/// [`BlockingCamera::wait_frame`] within its `wait`.
pub trait BlockingCamera: Send + 'static {
    /// Identity, sensor size and ranges.
    fn info(&self) -> CameraInfo;
    /// As [`Camera::set_exposure_us`].
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError>;
    /// As [`Camera::set_gain`].
    fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError>;
    /// As [`Camera::set_pixel_format`].
    fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError>;
    /// As [`Camera::set_roi`].
    fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError>;
    /// As [`Camera::set_trigger`].
    fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError>;
    /// As [`Camera::supports_hardware_trigger`].
    fn supports_hardware_trigger(&self) -> bool {
        false
    }
    /// As [`Camera::supports_software_trigger`].
    fn supports_software_trigger(&self) -> bool {
        true
    }
    /// As [`Camera::start`].
    fn start(&mut self) -> Result<(), DeviceError>;
    /// As [`Camera::stop`].
    fn stop(&mut self) -> Result<(), DeviceError>;
    /// As [`Camera::trigger`].
    fn trigger(&mut self) -> Result<(), DeviceError>;
    /// Waits at most `wait` for the next buffer. An error of kind
    /// [`ErrorKind::Disconnected`] ends the stream.
    fn wait_frame(&mut self, wait: Duration) -> Result<Grabbed, DeviceError>;
    /// The transport's packet counters, where it keeps them (`None`: it keeps none).
    fn transport_stats(&self) -> Option<TransportStats> {
        None
    }
    /// Asks to be told when each exposure ends, before its readout and transfer: `hook` is
    /// called (from within [`BlockingCamera::wait_frame`]) with the frame id the exposure will
    /// be delivered as, once the sensor has stopped integrating. Returns `false`, dropping the
    /// hook, when the camera cannot tell (the default).
    fn on_exposure_end(&mut self, hook: ExposureEndHook) -> bool {
        drop(hook);
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(pixels: Vec<u16>, width: u32, height: u32, format: PixelFormat) -> Frame {
        Frame {
            pixels,
            width,
            height,
            format,
            host_time: SystemTime::UNIX_EPOCH,
            device_timestamp_ns: None,
            frame_id: 7,
            exposure_us: 1000.0,
            gain: 0.0,
        }
    }

    /// A frame with fewer pixels than its size says (a truncated buffer) or a value beyond its
    /// format (garbage) fails the check, with the frame id in the message; a good one passes.
    #[test]
    fn frame_check_catches_truncation_and_range() {
        assert!(frame(vec![0, 4095, 12, 3], 2, 2, PixelFormat::Mono12)
            .check("cam")
            .is_ok());
        let e = frame(vec![0, 1, 2], 2, 2, PixelFormat::Mono12)
            .check("cam")
            .unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Protocol);
        assert!(e.message.contains("frame 7 has 3 pixels"), "{e}");
        let e = frame(vec![0, 256, 2, 3], 2, 2, PixelFormat::Mono8)
            .check("cam")
            .unwrap_err();
        assert!(e.message.contains("256 above the Mono8 maximum 255"), "{e}");
    }

    /// Regions outside the sensor, or empty, are refused with the sizes named; one touching the
    /// sensor's edge is accepted.
    #[test]
    fn roi_check() {
        assert!(Roi {
            x: 10,
            y: 20,
            width: 630,
            height: 460
        }
        .check("cam", 640, 480)
        .is_ok());
        let e = Roi {
            x: 10,
            y: 0,
            width: 631,
            height: 1,
        }
        .check("cam", 640, 480)
        .unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.contains("640x480 sensor"), "{e}");
        assert!(Roi {
            x: 0,
            y: 0,
            width: 0,
            height: 1
        }
        .check("cam", 640, 480)
        .is_err());
        assert!(Roi {
            x: u32::MAX,
            y: 0,
            width: 2,
            height: 1
        }
        .check("cam", 640, 480)
        .is_err());
    }

    /// Formats round-trip through their SFNC names and know their ranges.
    #[test]
    fn pixel_formats() {
        for f in [PixelFormat::Mono8, PixelFormat::Mono12, PixelFormat::Mono16] {
            assert_eq!(PixelFormat::from_name(&f.name().to_lowercase()), Some(f));
        }
        assert_eq!(PixelFormat::Mono12.max_value(), 4095);
        assert_eq!(PixelFormat::Mono16.max_value(), u16::MAX);
        assert_eq!(PixelFormat::from_name("RGB8"), None);
    }
}
