//! [`V4lCamera`]: a V4L2 capture device as a [`BlockingCamera`].

use crate::convert::{self, ConvertError};
use crate::device::{scan, select, V4lDeviceInfo};
use crate::sys::{guarded, io_error, wait_readable, Ready};
use linuxvideo::controls::{Cid, CtrlType};
use linuxvideo::format::{PixFormat, PixelFormat as Fourcc};
use linuxvideo::stream::ReadStream;
use linuxvideo::{BufType, Device};
use polar_hal::{
    BlockingCamera, CameraInfo, DeviceError, ErrorKind, Frame, GainUnit, Grabbed, PixelFormat, Roi,
    TriggerMode,
};
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// `V4L2_CID_EXPOSURE_ABSOLUTE` counts in units of 100 us.
const EXPOSURE_UNIT_US: f64 = 100.0;
/// `V4L2_EXPOSURE_MANUAL`, the `exposure_auto` menu entry for manual exposure.
const EXPOSURE_MANUAL: i32 = 1;

/// A V4L2 pixel format this backend reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SourceFormat {
    /// `GREY`: 8-bit luminance, delivered as [`PixelFormat::Mono8`].
    Grey,
    /// `YUYV`: YUV 4:2:2; its Y is delivered as [`PixelFormat::Mono8`].
    Yuyv,
    /// `MJPG`: Motion JPEG; its luma is delivered as [`PixelFormat::Mono8`].
    Mjpeg,
    /// `JPEG`: JFIF stills; as `MJPG`.
    Jpeg,
    /// `Y16 `: 16-bit little-endian luminance, delivered as [`PixelFormat::Mono16`].
    Y16,
}

impl SourceFormat {
    /// All of them, in order of preference: raw before decoded, lossless before lossy.
    pub const PREFERENCE: [SourceFormat; 5] = [
        SourceFormat::Grey,
        SourceFormat::Yuyv,
        SourceFormat::Mjpeg,
        SourceFormat::Jpeg,
        SourceFormat::Y16,
    ];

    /// Its fourcc code.
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            SourceFormat::Grey => *b"GREY",
            SourceFormat::Yuyv => *b"YUYV",
            SourceFormat::Mjpeg => *b"MJPG",
            SourceFormat::Jpeg => *b"JPEG",
            SourceFormat::Y16 => *b"Y16 ",
        }
    }

    /// Its fourcc as text without trailing spaces (`Y16`).
    pub fn name(self) -> &'static str {
        match self {
            SourceFormat::Grey => "GREY",
            SourceFormat::Yuyv => "YUYV",
            SourceFormat::Mjpeg => "MJPG",
            SourceFormat::Jpeg => "JPEG",
            SourceFormat::Y16 => "Y16",
        }
    }

    /// The pixel format frames are delivered in.
    pub fn delivers(self) -> PixelFormat {
        match self {
            SourceFormat::Y16 => PixelFormat::Mono16,
            _ => PixelFormat::Mono8,
        }
    }

    /// One buffer to luminance pixels (`stride_bytes` = V4L2 `bytesperline`, 0 = packed).
    pub fn to_luma(
        self,
        data: &[u8],
        width: u32,
        height: u32,
        stride_bytes: usize,
    ) -> Result<Vec<u16>, ConvertError> {
        match self {
            SourceFormat::Grey => convert::grey_to_luma(data, width, height, stride_bytes),
            SourceFormat::Yuyv => convert::yuyv_to_luma(data, width, height, stride_bytes),
            SourceFormat::Y16 => convert::y16_to_luma(data, width, height, stride_bytes),
            SourceFormat::Mjpeg | SourceFormat::Jpeg => convert::mjpeg_to_luma(data, width, height),
        }
    }
}

/// A negotiated capture format: what the driver agreed to send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Source {
    /// The V4L2 format.
    pub format: SourceFormat,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Bytes per row as the driver set it (0 for compressed formats).
    pub stride_bytes: usize,
}

/// How to open a camera.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct OpenOptions {
    /// The capture size `(width, height)`; by default the largest size the preferred format
    /// offers. A size the driver does not offer exactly is an error naming the size it chose.
    pub size_px: Option<(u32, u32)>,
}

/// One V4L2 control as the device describes it.
#[derive(Debug, Clone)]
struct Control {
    cid: Cid,
    name: String,
    min: i32,
    max: i32,
    step: i32,
}

/// The value the device will accept nearest to `value`: on the grid `min + k * step`, inside
/// `[min, max]`. A step of 0 or less is taken as 1.
pub fn snap_to_control(value: f64, min: i32, max: i32, step: i32) -> i32 {
    let step = f64::from(step.max(1));
    let (lo, hi) = (f64::from(min), f64::from(max.max(min)));
    let steps_in_range = ((hi - lo) / step).floor();
    let k = ((value - lo) / step).round().clamp(0.0, steps_in_range);
    // Inside [min, max] by construction, so the cast cannot saturate.
    (lo + k * step) as i32
}

struct Streaming {
    stream: ReadStream,
    source: Source,
}

/// A V4L2 camera (webcam, USB or CSI video device) as a [`BlockingCamera`]; run it through
/// `polar_hal::camera_thread::ThreadedCamera` to get an async `Camera`.
///
/// * Exposure: `V4L2_CID_EXPOSURE_ABSOLUTE` (100 us units). Setting it first switches
///   `exposure_auto` to manual where the device has it; the value read back is returned.
/// * Gain: `V4L2_CID_GAIN`, else `V4L2_CID_ANALOGUE_GAIN` ("Analogue Gain"), as
///   [`GainUnit::Raw`] over the control's range; `autogain` is switched off first.
/// * Formats: see [`SourceFormat`]. At most one source per delivered format, chosen in
///   [`SourceFormat::PREFERENCE`] order among those that negotiate to the capture size.
/// * Region of interest: V4L2 webcams have none, so the whole frame is read and cropped on the
///   host; the region can be changed at any time and costs no bandwidth saving.
/// * Trigger: free-run only.
/// * Frames: `frame_id` counts the buffers this handle dequeued since it was opened (including
///   incomplete ones); `device_timestamp_ns` is `None` (`linuxvideo` does not expose the
///   buffer's timestamp). `exposure_us` and `gain` are the last values read back, or NaN while
///   the device is in auto exposure / auto gain, or has no such control. A frame already in
///   the driver's two buffers when a setting changes carries the new value but was exposed with
///   the old one: discard one or two frames after a change.
pub struct V4lCamera {
    id: String,
    path: PathBuf,
    device: V4lDeviceInfo,
    control: Device,
    info: CameraInfo,
    sources: Vec<Source>,
    format: PixelFormat,
    roi: Roi,
    exposure: Option<Control>,
    exposure_auto: Option<Control>,
    gain: Option<Control>,
    autogain: Option<Control>,
    control_names: Vec<String>,
    exposure_us: f64,
    gain_value: f64,
    stream: Option<Streaming>,
    next_frame_id: u64,
}

impl std::fmt::Debug for V4lCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("V4lCamera")
            .field("device", &self.device)
            .field("sources", &self.sources)
            .field("format", &self.format)
            .field("roi", &self.roi)
            .field("streaming", &self.stream.is_some())
            .finish_non_exhaustive()
    }
}

impl V4lCamera {
    /// Opens the device `spec` names (a path, a bus info or a card name, optionally after
    /// `v4l:`; see [`crate::device`]) at its largest size.
    pub fn open(spec: &str) -> Result<V4lCamera, DeviceError> {
        V4lCamera::open_with(spec, OpenOptions::default())
    }

    /// As [`V4lCamera::open`], with options.
    pub fn open_with(spec: &str, options: OpenOptions) -> Result<V4lCamera, DeviceError> {
        let listing = scan(Path::new("/dev"))?;
        let device = select(spec, &listing)?.clone();
        V4lCamera::open_device(device, options)
    }

    /// Opens a device found by [`crate::list`].
    pub fn open_device(
        device: V4lDeviceInfo,
        options: OpenOptions,
    ) -> Result<V4lCamera, DeviceError> {
        let id = device.path.display().to_string();
        let path = device.path.clone();
        let control = guarded(&id, "open", || Device::open(&path))?;

        let offered: Vec<SourceFormat> = SourceFormat::PREFERENCE
            .into_iter()
            .filter(|f| device.fourccs.iter().any(|c| c == f.name()))
            .collect();
        let Some(&preferred) = offered.first() else {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &id,
                format!(
                    "pixel formats [{}] offered; this backend reads GREY, YUYV, MJPG, JPEG, Y16",
                    device.fourccs.join(", ")
                ),
            ));
        };
        let wanted = match options.size_px {
            Some(size) => size,
            None => largest_size(&control, &id, preferred),
        };
        let first = negotiate(&path, &id, preferred, wanted)?;
        if options.size_px.is_some() && (first.width, first.height) != wanted {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &id,
                format!(
                    "size_px = {}x{} is not offered in {}: the driver chose {}x{}",
                    wanted.0,
                    wanted.1,
                    preferred.name(),
                    first.width,
                    first.height
                ),
            ));
        }
        let mut sources = vec![first];
        for format in offered.into_iter().skip(1) {
            if sources
                .iter()
                .any(|s| s.format.delivers() == format.delivers())
            {
                continue;
            }
            match negotiate(&path, &id, format, (first.width, first.height)) {
                Ok(s) if (s.width, s.height) == (first.width, first.height) => sources.push(s),
                Ok(s) => tracing::debug!(
                    camera = %id, format = format.name(), width = s.width, height = s.height,
                    "format not offered at the capture size"
                ),
                Err(e) => tracing::debug!(camera = %id, format = format.name(), error = %e,
                    "format does not negotiate"),
            }
        }

        let controls = guarded(&id, "list controls", || {
            let mut out = Vec::new();
            // Bounded: a driver that repeats an id must not hang the open.
            for desc in control.controls().take(1024) {
                let desc = desc?;
                if desc.control_type() == CtrlType::CTRL_CLASS {
                    continue;
                }
                out.push(Control {
                    cid: desc.id(),
                    name: desc.name().to_string(),
                    min: desc.minimum(),
                    max: desc.maximum(),
                    step: desc.step(),
                });
            }
            Ok(out)
        })
        .unwrap_or_else(|e| {
            tracing::warn!(camera = %id, error = %e, "cannot list controls; exposure and gain unavailable");
            Vec::new()
        });
        let find = |cid: Cid| controls.iter().find(|c| c.cid == cid).cloned();
        let exposure = find(Cid::EXPOSURE_ABSOLUTE);
        let exposure_auto = find(Cid::EXPOSURE_AUTO);
        let gain = find(Cid::GAIN).or_else(|| {
            controls
                .iter()
                .find(|c| c.name.eq_ignore_ascii_case("Analogue Gain"))
                .cloned()
        });
        let autogain = find(Cid::AUTOGAIN);

        let (sysfs_vendor, serial) = usb_strings(&path);
        let info = CameraInfo {
            id: id.clone(),
            vendor: sysfs_vendor.unwrap_or_else(|| device.driver.clone()),
            model: device.card.clone(),
            serial: serial.unwrap_or_default(),
            sensor_width: first.width,
            sensor_height: first.height,
            exposure_range_us: exposure.as_ref().map_or([0.0, 0.0], |c| {
                [
                    f64::from(c.min) * EXPOSURE_UNIT_US,
                    f64::from(c.max) * EXPOSURE_UNIT_US,
                ]
            }),
            gain_range: gain
                .as_ref()
                .map_or([0.0, 0.0], |c| [f64::from(c.min), f64::from(c.max)]),
            gain_unit: GainUnit::Raw,
            formats: sources.iter().map(|s| s.format.delivers()).collect(),
        };
        let mut camera = V4lCamera {
            format: first.format.delivers(),
            roi: Roi::full(first.width, first.height),
            control_names: controls.iter().map(|c| c.name.clone()).collect(),
            id,
            path,
            device,
            control,
            info,
            sources,
            exposure,
            exposure_auto,
            gain,
            autogain,
            exposure_us: f64::NAN,
            gain_value: f64::NAN,
            stream: None,
            next_frame_id: 0,
        };
        camera.exposure_us = camera.read_exposure_us();
        camera.gain_value = camera.read_gain();
        tracing::info!(camera = %camera.id, card = %camera.device.card,
            bus = %camera.device.bus_info, sources = ?camera.sources, "V4L2 camera opened");
        Ok(camera)
    }

    /// The device as enumerated.
    pub fn device(&self) -> &V4lDeviceInfo {
        &self.device
    }

    /// The negotiated capture formats, one per delivered pixel format.
    pub fn sources(&self) -> &[Source] {
        &self.sources
    }

    /// The names of every control the device offers (for diagnostics).
    pub fn control_names(&self) -> &[String] {
        &self.control_names
    }

    fn read(&self, cid: Cid, what: &str) -> Result<i32, DeviceError> {
        guarded(&self.id, what, || self.control.read_control_raw(cid))
    }

    fn write(&mut self, cid: Cid, value: i32, what: &str) -> Result<(), DeviceError> {
        let id = self.id.clone();
        let control = &mut self.control;
        guarded(&id, what, || control.write_control_raw(cid, value))
    }

    /// The exposure in force, or NaN when unknown (no control, or auto exposure on).
    fn read_exposure_us(&self) -> f64 {
        let Some(c) = &self.exposure else {
            return f64::NAN;
        };
        if let Some(auto) = &self.exposure_auto {
            if self.read(auto.cid, "read exposure_auto").ok() != Some(EXPOSURE_MANUAL) {
                return f64::NAN;
            }
        }
        self.read(c.cid, "read exposure")
            .map_or(f64::NAN, |v| f64::from(v) * EXPOSURE_UNIT_US)
    }

    /// The gain in force, or NaN when unknown (no control, or auto gain on).
    fn read_gain(&self) -> f64 {
        let Some(c) = &self.gain else {
            return f64::NAN;
        };
        if let Some(auto) = &self.autogain {
            if self.read(auto.cid, "read autogain").ok() != Some(0) {
                return f64::NAN;
            }
        }
        self.read(c.cid, "read gain").map_or(f64::NAN, f64::from)
    }

    fn source(&self, format: PixelFormat) -> Result<Source, DeviceError> {
        self.sources
            .iter()
            .find(|s| s.format.delivers() == format)
            .copied()
            .ok_or_else(|| {
                DeviceError::new(
                    ErrorKind::OutOfRange,
                    &self.id,
                    format!(
                        "pixel_format = {format} is not offered: allowed {}",
                        self.info
                            .formats
                            .iter()
                            .map(|f| f.name())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                )
            })
    }

    fn missing_control(&self, what: &str, control: &str) -> DeviceError {
        DeviceError::new(
            ErrorKind::OutOfRange,
            &self.id,
            format!(
                "{what}: this device has no {control} control; its controls are [{}]",
                self.control_names.join(", ")
            ),
        )
    }

    /// Ends the stream after a disconnect; passes the error on.
    fn end_stream_if_gone(&mut self, e: DeviceError) -> DeviceError {
        if e.kind() == ErrorKind::Disconnected {
            self.stream = None;
        }
        e
    }
}

/// The largest size `format` offers, or the size currently set, or 640x480 for the driver to
/// adjust.
fn largest_size(control: &Device, id: &str, format: SourceFormat) -> (u32, u32) {
    let fourcc = Fourcc::from_fourcc(format.fourcc());
    let enumerated = guarded(id, "list frame sizes", || {
        Ok(match control.frame_sizes(fourcc)? {
            linuxvideo::format::FrameSizes::Discrete(sizes) => sizes
                .iter()
                .map(|s| (s.width(), s.height()))
                .max_by_key(|&(w, h)| u64::from(w) * u64::from(h)),
            linuxvideo::format::FrameSizes::Stepwise(s)
            | linuxvideo::format::FrameSizes::Continuous(s) => {
                Some((s.max_width(), s.max_height()))
            }
        })
    });
    if let Ok(Some(size)) = enumerated {
        return size;
    }
    // v4l2loopback and some others do not enumerate sizes: keep the current one.
    match guarded(id, "read the current format", || {
        control.format(BufType::VIDEO_CAPTURE)
    }) {
        Ok(linuxvideo::format::Format::VideoCapture(f)) if f.width() > 0 && f.height() > 0 => {
            (f.width(), f.height())
        }
        _ => (640, 480),
    }
}

/// Sets `format` at `size` on a second handle and returns what the driver agreed to. A
/// different fourcc back is an error ([`ErrorKind::OutOfRange`]); a different size is returned
/// for the caller to judge.
fn negotiate(
    path: &Path,
    id: &str,
    format: SourceFormat,
    (width, height): (u32, u32),
) -> Result<Source, DeviceError> {
    let agreed = guarded(id, &format!("set format {}", format.name()), || {
        let device = Device::open(path)?;
        let capture = device.video_capture(PixFormat::new(
            width,
            height,
            Fourcc::from_fourcc(format.fourcc()),
        ))?;
        Ok(Agreed::of(capture.format()))
    })?;
    check_agreed(id, format, agreed)
}

/// What a driver agreed to in `VIDIOC_S_FMT`.
#[derive(Debug, Clone, Copy)]
struct Agreed {
    fourcc: [u8; 4],
    width: u32,
    height: u32,
    stride_bytes: u32,
}

impl Agreed {
    fn of(f: &PixFormat) -> Agreed {
        Agreed {
            fourcc: f.pixel_format().as_fourcc(),
            width: f.width(),
            height: f.height(),
            stride_bytes: f.bytes_per_line(),
        }
    }
}

fn check_agreed(id: &str, format: SourceFormat, agreed: Agreed) -> Result<Source, DeviceError> {
    if agreed.fourcc != format.fourcc() {
        return Err(DeviceError::new(
            ErrorKind::OutOfRange,
            id,
            format!(
                "format {} refused: the driver chose {}",
                format.name(),
                crate::device::fourcc_text(agreed.fourcc)
            ),
        ));
    }
    Ok(Source {
        format,
        width: agreed.width,
        height: agreed.height,
        stride_bytes: agreed.stride_bytes as usize,
    })
}

/// The USB manufacturer and serial strings from sysfs, where the node is a USB device.
fn usb_strings(path: &Path) -> (Option<String>, Option<String>) {
    let node = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    let Some(name) = node.file_name() else {
        return (None, None);
    };
    // `device` links to the USB interface; its parent is the USB device.
    let usb = Path::new("/sys/class/video4linux")
        .join(name)
        .join("device/..");
    let read = |file: &str| {
        std::fs::read_to_string(usb.join(file))
            .ok()
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
    };
    (read("manufacturer"), read("serial"))
}

/// One dequeued buffer as a [`Grabbed`]: converted, cropped and checked. Short, flagged or
/// undecodable buffers are [`Grabbed::Incomplete`]; this never fails and never panics.
#[allow(clippy::too_many_arguments)]
pub fn assemble(
    device: &str,
    source: &Source,
    data: &[u8],
    driver_flagged_error: bool,
    roi: Roi,
    frame_id: u64,
    exposure_us: f64,
    gain: f64,
) -> Grabbed {
    let incomplete = |reason: String| Grabbed::Incomplete {
        frame_id: Some(frame_id),
        reason,
    };
    if driver_flagged_error {
        return incomplete("the driver flagged the buffer as corrupt (V4L2_BUF_FLAG_ERROR)".into());
    }
    if data.is_empty() {
        return incomplete("empty buffer (bytesused = 0)".into());
    }
    let pixels = match source
        .format
        .to_luma(data, source.width, source.height, source.stride_bytes)
        .and_then(|px| convert::crop(&px, source.width, source.height, roi))
    {
        Ok(px) => px,
        Err(e) => return incomplete(format!("{} frame: {e}", source.format.name())),
    };
    let frame = Frame {
        pixels,
        width: roi.width,
        height: roi.height,
        format: source.format.delivers(),
        host_time: SystemTime::now(),
        device_timestamp_ns: None,
        frame_id,
        exposure_us,
        gain,
    };
    match frame.check(device) {
        Ok(()) => Grabbed::Frame(frame),
        Err(e) => incomplete(e.message),
    }
}

impl BlockingCamera for V4lCamera {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    /// V4L2 capture devices stream freely; there is no trigger.
    fn supports_software_trigger(&self) -> bool {
        false
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError> {
        let Some(c) = self.exposure.clone() else {
            return Err(self.missing_control(
                &format!("exposure_us = {exposure_us}"),
                "absolute exposure (V4L2_CID_EXPOSURE_ABSOLUTE, \"Exposure Time, Absolute\")",
            ));
        };
        self.info.check_exposure_us(exposure_us)?;
        if let Some(auto) = self.exposure_auto.clone() {
            if self.read(auto.cid, "read exposure_auto")? != EXPOSURE_MANUAL {
                self.write(
                    auto.cid,
                    EXPOSURE_MANUAL,
                    "switch exposure_auto to manual (1)",
                )?;
            }
        }
        let units = snap_to_control(exposure_us / EXPOSURE_UNIT_US, c.min, c.max, c.step);
        self.write(c.cid, units, &format!("set {} = {units}", c.name))?;
        let applied = self.read(c.cid, "read exposure back")?;
        self.exposure_us = f64::from(applied) * EXPOSURE_UNIT_US;
        Ok(self.exposure_us)
    }

    fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
        let Some(c) = self.gain.clone() else {
            return Err(self.missing_control(
                &format!("gain = {gain}"),
                "gain (V4L2_CID_GAIN \"Gain\" or V4L2_CID_ANALOGUE_GAIN \"Analogue Gain\")",
            ));
        };
        self.info.check_gain(gain)?;
        if let Some(auto) = self.autogain.clone() {
            if self.read(auto.cid, "read autogain")? != 0 {
                self.write(auto.cid, 0, "switch autogain off")?;
            }
        }
        let value = snap_to_control(gain, c.min, c.max, c.step);
        self.write(c.cid, value, &format!("set {} = {value}", c.name))?;
        self.gain_value = f64::from(self.read(c.cid, "read gain back")?);
        Ok(self.gain_value)
    }

    fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError> {
        self.source(format)?;
        if self.stream.is_some() && format != self.format {
            return Err(DeviceError::new(
                ErrorKind::Busy,
                &self.id,
                format!("pixel_format = {format}: stop the stream first"),
            ));
        }
        self.format = format;
        Ok(())
    }

    fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError> {
        roi.check(&self.id, self.info.sensor_width, self.info.sensor_height)?;
        // A host-side crop: exact, and allowed while streaming.
        self.roi = roi;
        Ok(roi)
    }

    fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError> {
        match mode {
            TriggerMode::FreeRun => Ok(()),
            TriggerMode::Software | TriggerMode::Hardware => Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.id,
                format!(
                    "trigger = {} is not offered by this camera: allowed free-run \
                     (V4L2 capture devices free-run)",
                    if mode == TriggerMode::Software {
                        "software"
                    } else {
                        "hardware"
                    }
                ),
            )),
        }
    }

    fn start(&mut self) -> Result<(), DeviceError> {
        if self.stream.is_some() {
            return Ok(());
        }
        let wanted = self.source(self.format)?;
        let path = self.path.clone();
        let capture = guarded(&self.id, "set the capture format", || {
            Device::open(&path)?.video_capture(PixFormat::new(
                wanted.width,
                wanted.height,
                Fourcc::from_fourcc(wanted.format.fourcc()),
            ))
        })?;
        let source = check_agreed(&self.id, wanted.format, Agreed::of(capture.format()))?;
        if (source.width, source.height) != (wanted.width, wanted.height) {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                &self.id,
                format!(
                    "the driver now gives {}x{} for {}, agreed {}x{} at open: reopen the camera",
                    source.width,
                    source.height,
                    wanted.format.name(),
                    wanted.width,
                    wanted.height
                ),
            ));
        }
        let stream = guarded(&self.id, "start streaming", || capture.into_stream())?;
        tracing::debug!(camera = %self.id, ?source, "streaming");
        self.stream = Some(Streaming { stream, source });
        Ok(())
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        // Dropping the stream turns it off, unmaps the buffers and closes the handle.
        self.stream = None;
        Ok(())
    }

    fn trigger(&mut self) -> Result<(), DeviceError> {
        Err(DeviceError::new(
            ErrorKind::OutOfRange,
            &self.id,
            "trigger: a software trigger is not offered by this camera: allowed free-run only",
        ))
    }

    fn wait_frame(&mut self, wait: Duration) -> Result<Grabbed, DeviceError> {
        let Some(streaming) = self.stream.as_ref() else {
            return Err(DeviceError::new(
                ErrorKind::Other,
                &self.id,
                "wait_frame: the stream is not started",
            ));
        };
        match wait_readable(&streaming.stream, wait) {
            Ok(Ready::Readable) => {}
            Ok(Ready::Nothing) => return Ok(Grabbed::Nothing),
            Ok(Ready::Failed) => {
                self.stream = None;
                return Err(DeviceError::new(
                    ErrorKind::Disconnected,
                    &self.id,
                    "the driver reports an error on the stream (POLLERR): the device failed or \
                     was unplugged; start again to reopen the stream, or after an unplug open \
                     the camera again by name or bus info (the node number may change)",
                ));
            }
            Err(e) => {
                let e = io_error(&self.id, "wait for a frame", &e);
                return Err(self.end_stream_if_gone(e));
            }
        }
        let frame_id = self.next_frame_id;
        self.next_frame_id += 1;
        let (id, roi, exposure_us, gain) =
            (self.id.clone(), self.roi, self.exposure_us, self.gain_value);
        let result = match self.stream.as_mut() {
            Some(streaming) => {
                let source = streaming.source;
                guarded(&id, "dequeue a buffer", || {
                    streaming.stream.dequeue(|view| {
                        Ok(assemble(
                            &id,
                            &source,
                            &view,
                            view.is_error(),
                            roi,
                            frame_id,
                            exposure_us,
                            gain,
                        ))
                    })
                })
            }
            None => Ok(Grabbed::Nothing),
        };
        result.map_err(|e| {
            if e.kind() == ErrorKind::Protocol {
                // The library failed on a buffer (a caught panic): its queue may have lost that
                // buffer, so the stream is not trusted any more. End it, as a disconnect, so
                // the caller reopens it.
                self.stream = None;
                DeviceError::new(
                    ErrorKind::Disconnected,
                    &self.id,
                    format!("stream closed: {}", e.message),
                )
            } else {
                self.end_stream_if_gone(e)
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values land on the control's grid, inside its range: 100 us units with step 1, a
    /// coarser step, and values beyond either end.
    #[test]
    fn snapping_to_controls() {
        // Exposure 12.34 ms in 100 us units, range 3..2047 (a typical UVC webcam).
        assert_eq!(snap_to_control(123.4, 3, 2047, 1), 123);
        assert_eq!(snap_to_control(0.2, 3, 2047, 1), 3);
        assert_eq!(snap_to_control(1e9, 3, 2047, 1), 2047);
        // Step 4 from 1: 1, 5, 9, ...; 7 is equidistant-ish, 6.9 rounds to 5.
        assert_eq!(snap_to_control(6.9, 1, 100, 4), 5);
        assert_eq!(snap_to_control(7.1, 1, 100, 4), 9);
        // The top of the range off the grid: the last grid point below it.
        assert_eq!(snap_to_control(100.0, 1, 100, 4), 97);
        // Step 0 (a broken driver) is taken as 1; max below min is taken as min.
        assert_eq!(snap_to_control(5.0, 0, 10, 0), 5);
        assert_eq!(snap_to_control(5.0, 8, 2, 1), 8);
        assert_eq!(snap_to_control(f64::NAN, 0, 10, 1), 0);
    }

    fn source(format: SourceFormat, width: u32, height: u32, stride: usize) -> Source {
        Source {
            format,
            width,
            height,
            stride_bytes: stride,
        }
    }

    /// A good YUYV buffer becomes a cropped Mono8 frame with the settings and id attached.
    #[test]
    fn assemble_good_frame_with_crop() {
        let s = source(SourceFormat::Yuyv, 4, 2, 8);
        let data = [10, 0, 11, 0, 12, 0, 13, 0, 20, 0, 21, 0, 22, 0, 23, 0];
        let roi = Roi {
            x: 1,
            y: 1,
            width: 3,
            height: 1,
        };
        match assemble("cam", &s, &data, false, roi, 42, 5000.0, 3.0) {
            Grabbed::Frame(f) => {
                assert_eq!(f.pixels, vec![21, 22, 23]);
                assert_eq!((f.width, f.height), (3, 1));
                assert_eq!(f.format, PixelFormat::Mono8);
                assert_eq!(f.frame_id, 42);
                assert_eq!(f.exposure_us, 5000.0);
                assert_eq!(f.gain, 3.0);
                assert_eq!(f.device_timestamp_ns, None);
            }
            other => panic!("{other:?}"),
        }
        let y16 = source(SourceFormat::Y16, 1, 1, 0);
        match assemble(
            "cam",
            &y16,
            &[0xCD, 0xAB],
            false,
            Roi::full(1, 1),
            0,
            1.0,
            0.0,
        ) {
            Grabbed::Frame(f) => {
                assert_eq!(f.pixels, vec![0xABCD]);
                assert_eq!(f.format, PixelFormat::Mono16);
            }
            other => panic!("{other:?}"),
        }
    }

    /// Short buffers, driver-flagged buffers, empty buffers and undecodable MJPEG are
    /// Incomplete with the reason and the frame id, never frames and never errors.
    #[test]
    fn assemble_bad_buffers_are_incomplete() {
        let s = source(SourceFormat::Grey, 4, 2, 4);
        let full = Roi::full(4, 2);
        let cases: [(&[u8], bool, &str); 3] = [
            (&[1, 2, 3, 4, 5, 6, 7], false, "needs 8"),
            (&[1, 2, 3, 4, 5, 6, 7, 8], true, "V4L2_BUF_FLAG_ERROR"),
            (&[], false, "bytesused = 0"),
        ];
        for (data, flagged, why) in cases {
            match assemble("cam", &s, data, flagged, full, 9, 1.0, 0.0) {
                Grabbed::Incomplete { frame_id, reason } => {
                    assert_eq!(frame_id, Some(9));
                    assert!(reason.contains(why), "{reason}");
                }
                other => panic!("{other:?}"),
            }
        }
        let mj = source(SourceFormat::Mjpeg, 4, 2, 0);
        match assemble(
            "cam",
            &mj,
            &[0xFF, 0xD8, 0xFF, 0xDB, 0, 3],
            false,
            full,
            1,
            1.0,
            0.0,
        ) {
            Grabbed::Incomplete { reason, .. } => {
                assert!(reason.starts_with("MJPG frame"), "{reason}")
            }
            other => panic!("{other:?}"),
        }
    }

    /// Every format knows its fourcc and what it delivers; the preference puts raw first.
    #[test]
    fn source_formats() {
        assert_eq!(SourceFormat::PREFERENCE[0], SourceFormat::Grey);
        for f in SourceFormat::PREFERENCE {
            assert_eq!(crate::device::fourcc_text(f.fourcc()), f.name());
        }
        assert_eq!(SourceFormat::Y16.delivers(), PixelFormat::Mono16);
        assert_eq!(SourceFormat::Mjpeg.delivers(), PixelFormat::Mono8);
    }

    /// Opening by a spec that matches nothing fails with the spec and the listing named, and
    /// never falls back to another device. (On this machine and in CI there is no device.)
    #[test]
    fn open_unknown_device_names_what_exists() {
        let e = V4lCamera::open("v4l:No Such Camera 7f3a").unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert_eq!(e.device, "v4l:No Such Camera 7f3a");
        assert!(e.message.contains("found:"), "{e}");
        let e = V4lCamera::open("/dev/video-polar-none").unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
    }
}
