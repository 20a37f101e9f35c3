//! [`AravisCamera`]: one GenICam camera as a [`BlockingCamera`].

use crate::frame::{pixels_from_bytes, FrameIdUnwrapper};
use crate::{aravis, is_not_found, sdk_error, AravisError};
use ::aravis::glib;
use ::aravis::glib::prelude::{Cast, ObjectExt};
use ::aravis::prelude::*;
use ::aravis::{AcquisitionMode, BufferPayloadType, BufferStatus, GvStreamOption};
use gio::prelude::{InetAddressExt, InetSocketAddressExt};
use polar_hal::{
    BlockingCamera, CameraInfo, DeviceError, ErrorKind, Frame, GainUnit, Grabbed, PixelFormat, Roi,
    TransportStats, TriggerMode,
};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

/// How an [`AravisCamera`] streams and watches its device.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AravisOptions {
    /// Buffers in the stream's pool. At least 8 are used: a consumer that pops a little late
    /// must not starve the stream (Aravis #849, DEVICES.md 5.2).
    pub buffers: usize,
    /// While streaming, after this long without a buffer (or three frame periods plus the
    /// exposure in free run, if longer) the device is probed with a register read on a helper
    /// thread; a failed read means it is gone. A probe of a live camera takes microseconds to
    /// milliseconds; one of a dead GigE camera fails after Aravis's fixed GVCP timeout (about
    /// 2.5 s measured: 5 tries of 500 ms).
    pub silence_before_probe: Duration,
    /// Let Aravis receive a GigE Vision stream with a packet socket where the process may
    /// (root or `CAP_NET_RAW`): Aravis's default, fewer lost packets at high rates (Aravis #894,
    /// #898). It is never used for a device on loopback (Aravis's fake cameras): Aravis captures
    /// on the interface through which discovery reached the device, which for a loopback device
    /// may be another one, and then receives nothing (measured on this kind of machine).
    pub packet_socket: bool,
}

impl Default for AravisOptions {
    fn default() -> Self {
        AravisOptions {
            buffers: 16,
            silence_before_probe: Duration::from_millis(500),
            packet_socket: true,
        }
    }
}

/// The fewest buffers in a stream's pool.
const MIN_BUFFERS: usize = 8;

/// SFNC names and their older GenICam equivalents, in the order tried.
const EXPOSURE_FEATURES: [&str; 2] = ["ExposureTime", "ExposureTimeAbs"];
/// Gain features: `Gain` is a float in dB; `GainRaw` a device-specific integer.
const GAIN_FEATURES: [(&str, GainUnit); 2] =
    [("Gain", GainUnit::Decibel), ("GainRaw", GainUnit::Raw)];
/// The trigger input used for [`TriggerMode::Hardware`].
const HARDWARE_TRIGGER_SOURCE: &str = "Line0";
/// A register every GenICam transport has at address 0 (GigE Vision bootstrap `Version`,
/// USB3 Vision ABRM `GenCP Version`); reading it bypasses the GenICam feature cache.
const PROBE_REGISTER: u64 = 0;

/// One GenICam camera opened through Aravis. Blocking; run it on its own thread through
/// `polar_hal::camera_thread::ThreadedCamera`.
pub struct AravisCamera {
    id: String,
    camera: ::aravis::Camera,
    info: CameraInfo,
    options: AravisOptions,
    exposure_feature: Option<&'static str>,
    gain_feature: Option<&'static str>,
    hardware_trigger: bool,
    /// A GigE Vision device reached on a loopback address.
    on_loopback: bool,
    trigger: TriggerMode,
    /// The stream while acquiring.
    stream: Option<::aravis::Stream>,
    frame_ids: FrameIdUnwrapper,
    /// Applied values, read back after each setting.
    exposure_us: f64,
    gain: f64,
    /// The frame period read at start, if the camera reports a frame rate.
    frame_period: Option<Duration>,
    /// Set by Aravis's `control-lost` signal (its heartbeat thread).
    control_lost: Arc<AtomicBool>,
    control_lost_handler: Option<(::aravis::Device, glib::SignalHandlerId)>,
    /// The last buffer that proved the device alive (or the last successful probe).
    last_sign_of_life: Instant,
    /// The answer of a register read running on a helper thread.
    probe: Option<mpsc::Receiver<Result<(), String>>>,
    /// Set when the camera is known to be gone; every later call reports it.
    gone: Option<DeviceError>,
}

impl std::fmt::Debug for AravisCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AravisCamera")
            .field("id", &self.id)
            .field("streaming", &self.stream.is_some())
            .field("trigger", &self.trigger)
            .field("gone", &self.gone)
            .finish_non_exhaustive()
    }
}

impl AravisCamera {
    /// Opens the camera with this id (as [`crate::list`] reports it, e.g. `Aravis-Fake-GV01`)
    /// with default options.
    pub fn open(id: &str) -> Result<AravisCamera, AravisError> {
        Self::open_with(id, AravisOptions::default())
    }

    /// Opens the camera with this id. Reads what it offers (sensor size, exposure and gain
    /// ranges and feature names, Mono pixel formats, trigger sources) and, if its current pixel
    /// format is not Mono8/12/16, switches it to the deepest Mono format offered.
    pub fn open_with(id: &str, options: AravisOptions) -> Result<AravisCamera, AravisError> {
        let camera = {
            // Opening may update Aravis's device list: do it under the same lock as `list`.
            let _ar = aravis()?;
            ::aravis::Camera::new(Some(id)).map_err(|e| AravisError::Sdk {
                device: id.to_string(),
                what: String::from("open"),
                kind: crate::error_kind(&e),
                message: e.message().to_string(),
            })?
        };
        let sdk = |what: &str, e: glib::Error| AravisError::from(sdk_error(id, what, &e));

        let available = |name: &str| camera.is_feature_available(name).unwrap_or(false);
        let exposure_feature = EXPOSURE_FEATURES.into_iter().find(|n| available(n));
        let gain = GAIN_FEATURES.into_iter().find(|(n, _)| available(n));
        let (gain_feature, gain_unit) = match gain {
            Some((name, unit)) => (Some(name), unit),
            None => (None, GainUnit::Raw),
        };

        let formats: Vec<PixelFormat> = camera
            .dup_available_pixel_formats_as_strings()
            .map_err(|e| sdk("list pixel formats", e))?
            .iter()
            .filter_map(|s| PixelFormat::from_name(s))
            .collect();
        if formats.is_empty() {
            return Err(AravisError::from(DeviceError::new(
                ErrorKind::OutOfRange,
                id,
                "the camera offers none of the pixel formats Mono8, Mono12, Mono16",
            )));
        }
        let current = camera
            .pixel_format_as_string()
            .ok()
            .and_then(|s| PixelFormat::from_name(&s));
        if current.is_none() {
            let deepest = [PixelFormat::Mono16, PixelFormat::Mono12, PixelFormat::Mono8]
                .into_iter()
                .find(|f| formats.contains(f))
                .unwrap_or(PixelFormat::Mono8);
            camera
                .set_pixel_format_from_string(deepest.name())
                .map_err(|e| sdk("set the pixel format", e))?;
        }

        let (sensor_width, sensor_height) = match camera.sensor_size() {
            Ok((w, h)) if w > 0 && h > 0 => (w, h),
            _ => {
                let (_, w) = camera.width_bounds().map_err(|e| sdk("read Width", e))?;
                let (_, h) = camera.height_bounds().map_err(|e| sdk("read Height", e))?;
                (w, h)
            }
        };
        let to_u32 = |v: i32| u32::try_from(v).unwrap_or(0);

        let exposure_range_us = match camera.exposure_time_bounds() {
            Ok((lo, hi)) => [lo, hi],
            Err(e) => match exposure_feature {
                Some(name) => {
                    let (lo, hi) = camera
                        .float_bounds(name)
                        .map_err(|e| sdk("read the exposure range", e))?;
                    [lo, hi]
                }
                None => return Err(sdk("read the exposure range", e)),
            },
        };
        let gain_range = match camera.gain_bounds() {
            Ok((lo, hi)) => [lo, hi],
            Err(_) if gain_feature == Some("GainRaw") => {
                let (lo, hi) = camera
                    .integer_bounds("GainRaw")
                    .map_err(|e| sdk("read the gain range", e))?;
                [lo as f64, hi as f64]
            }
            Err(_) => match gain_feature {
                Some(name) => {
                    let (lo, hi) = camera
                        .float_bounds(name)
                        .map_err(|e| sdk("read the gain range", e))?;
                    [lo, hi]
                }
                // No gain control: only unity.
                None => [0.0, 0.0],
            },
        };
        let hardware_trigger = camera
            .dup_available_trigger_sources()
            .map(|sources| {
                sources
                    .iter()
                    .any(|s| s.as_str() == HARDWARE_TRIGGER_SOURCE)
            })
            .unwrap_or(false);

        let info = CameraInfo {
            id: id.to_string(),
            vendor: camera
                .vendor_name()
                .map(|s| s.to_string())
                .unwrap_or_default(),
            model: camera
                .model_name()
                .map(|s| s.to_string())
                .unwrap_or_default(),
            serial: camera
                .device_serial_number()
                .map(|s| s.to_string())
                .unwrap_or_default(),
            sensor_width: to_u32(sensor_width),
            sensor_height: to_u32(sensor_height),
            exposure_range_us,
            gain_range,
            gain_unit,
            formats,
        };

        // Aravis's heartbeat thread emits `control-lost` when the device stops acknowledging.
        let control_lost = Arc::new(AtomicBool::new(false));
        let control_lost_handler = camera.device().map(|device| {
            let flag = Arc::clone(&control_lost);
            let handler = device.connect_control_lost(move |_| flag.store(true, Ordering::SeqCst));
            (device, handler)
        });

        let on_loopback = gige_on_loopback(&camera);
        let mut cam = AravisCamera {
            id: id.to_string(),
            camera,
            info,
            options: AravisOptions {
                buffers: options.buffers.max(MIN_BUFFERS),
                ..options
            },
            exposure_feature,
            gain_feature,
            hardware_trigger,
            on_loopback,
            trigger: TriggerMode::FreeRun,
            stream: None,
            frame_ids: FrameIdUnwrapper::new(),
            exposure_us: 0.0,
            gain: 0.0,
            frame_period: None,
            control_lost,
            control_lost_handler,
            last_sign_of_life: Instant::now(),
            probe: None,
            gone: None,
        };
        cam.exposure_us = cam.read_exposure_us()?;
        cam.gain = cam.read_gain()?;
        tracing::info!(camera = %id, info = ?cam.info, ?exposure_feature, ?gain_feature, "opened");
        Ok(cam)
    }

    /// The id it was opened by.
    pub fn id(&self) -> &str {
        &self.id
    }

    /// The underlying Aravis camera, for features this crate does not wrap.
    pub fn aravis_camera(&self) -> &::aravis::Camera {
        &self.camera
    }

    /// Sets the free-run frame rate (where the camera has one) and returns the rate applied,
    /// frames per second.
    pub fn set_frame_rate_hz(&mut self, rate_hz: f64) -> Result<f64, DeviceError> {
        self.alive()?;
        self.camera
            .set_frame_rate(rate_hz)
            .map_err(|e| sdk_error(&self.id, "set the frame rate", &e))?;
        self.camera
            .frame_rate()
            .map_err(|e| sdk_error(&self.id, "read the frame rate back", &e))
    }

    fn alive(&self) -> Result<(), DeviceError> {
        match &self.gone {
            Some(e) => Err(e.clone()),
            None => Ok(()),
        }
    }

    fn stopped(&self, what: &str) -> Result<(), DeviceError> {
        self.alive()?;
        if self.stream.is_some() {
            return Err(DeviceError::new(
                ErrorKind::Busy,
                &self.id,
                format!("{what} needs the camera stopped; it is acquiring"),
            ));
        }
        Ok(())
    }

    fn read_exposure_us(&self) -> Result<f64, DeviceError> {
        match (self.camera.exposure_time(), self.exposure_feature) {
            (Ok(v), _) => Ok(v),
            (Err(e), Some(name)) if is_not_found(&e) => self
                .camera
                .float(name)
                .map_err(|e| sdk_error(&self.id, &format!("read {name}"), &e)),
            (Err(e), _) => Err(sdk_error(&self.id, "read the exposure", &e)),
        }
    }

    fn read_gain(&self) -> Result<f64, DeviceError> {
        match (self.camera.gain(), self.gain_feature) {
            (Ok(v), _) => Ok(v),
            (Err(_), Some(name @ "GainRaw")) => self
                .camera
                .integer(name)
                .map(|v| v as f64)
                .map_err(|e| sdk_error(&self.id, &format!("read {name}"), &e)),
            (Err(_), Some(name)) => self
                .camera
                .float(name)
                .map_err(|e| sdk_error(&self.id, &format!("read {name}"), &e)),
            // No gain control at all: unity.
            (Err(_), None) => Ok(0.0),
        }
    }

    /// The longest silence of a healthy stream before the device is probed.
    fn silence_limit(&self) -> Duration {
        let floor = self.options.silence_before_probe;
        match (self.trigger, self.frame_period) {
            (TriggerMode::FreeRun, Some(period)) => {
                let exposure = Duration::from_secs_f64((self.exposure_us / 1e6).clamp(0.0, 3600.0));
                floor.max(period.saturating_mul(3) + exposure)
            }
            _ => floor,
        }
    }

    /// Marks the camera gone and ends the stream.
    fn mark_gone(&mut self, why: String) -> DeviceError {
        let e = DeviceError::new(ErrorKind::Disconnected, &self.id, why);
        tracing::warn!(camera = %self.id, error = %e, "camera gone");
        self.gone = Some(e.clone());
        self.probe = None;
        if let Some(stream) = self.stream.take() {
            // Finalizing a GigE Vision stream writes the device's stream-channel registers;
            // with the device gone each write waits out the GVCP timeout (seconds), so let a
            // helper thread do it rather than the camera thread.
            let dropped = std::thread::Builder::new()
                .name(format!("close-{}", self.id))
                .spawn(move || drop(stream));
            if let Err(err) = dropped {
                tracing::warn!(camera = %self.id, error = %err, "stream closed on the camera thread");
            }
        }
        e
    }

    /// Reports a disconnection seen by the `control-lost` signal or by a finished probe.
    fn check_health(&mut self) -> Result<(), DeviceError> {
        if let Some(e) = &self.gone {
            return Err(e.clone());
        }
        if self.control_lost.load(Ordering::SeqCst) {
            return Err(self.mark_gone(String::from(
                "Aravis lost control of the device (control-lost: heartbeat not acknowledged)",
            )));
        }
        if let Some(rx) = &self.probe {
            match rx.try_recv() {
                Ok(Ok(())) => {
                    self.probe = None;
                    self.last_sign_of_life = Instant::now();
                }
                Ok(Err(why)) => {
                    let silent = self.last_sign_of_life.elapsed();
                    return Err(self.mark_gone(format!(
                        "no buffer for {:.1} s and a register read failed: {why}",
                        silent.as_secs_f64()
                    )));
                }
                Err(mpsc::TryRecvError::Empty) => {}
                Err(mpsc::TryRecvError::Disconnected) => self.probe = None,
            }
        }
        Ok(())
    }

    /// Starts a register read on a helper thread if the stream has been silent too long and no
    /// read is running: a read of a dead device blocks for Aravis's whole GVCP timeout, longer
    /// than one `wait_frame` may take.
    fn probe_if_silent(&mut self) {
        if self.probe.is_some() || self.last_sign_of_life.elapsed() < self.silence_limit() {
            return;
        }
        let Some(device) = self.camera.device() else {
            return;
        };
        let (tx, rx) = mpsc::channel();
        let spawned = std::thread::Builder::new()
            .name(format!("probe-{}", self.id))
            .spawn(move || {
                let answer = match device.read_register(PROBE_REGISTER) {
                    Ok((true, _)) => Ok(()),
                    Ok((false, _)) => Err(String::from("the read was refused")),
                    Err(e) => Err(e.message().to_string()),
                };
                // The camera may have been dropped meanwhile: nobody to tell.
                let _ = tx.send(answer);
            });
        match spawned {
            Ok(_) => self.probe = Some(rx),
            Err(e) => tracing::warn!(camera = %self.id, error = %e, "cannot start a probe thread"),
        }
    }

    /// What one buffer holds. Reads nothing of the image unless the status is `Success`.
    fn grabbed(&mut self, buffer: &::aravis::Buffer) -> Grabbed {
        let status = buffer.status();
        let frame_id = self.frame_ids.unwrap(buffer.frame_id());
        if status != BufferStatus::Success {
            return Grabbed::Incomplete {
                frame_id: Some(frame_id),
                reason: format!("buffer status {status:?}"),
            };
        }
        let incomplete = |reason: String| Grabbed::Incomplete {
            frame_id: Some(frame_id),
            reason,
        };
        let payload = buffer.payload_type();
        if !matches!(
            payload,
            BufferPayloadType::Image | BufferPayloadType::ExtendedChunkData
        ) {
            return incomplete(format!("payload type {payload:?} is not an image"));
        }
        let raw_format = buffer.image_pixel_format();
        let format = if raw_format == ::aravis::PixelFormat::MONO_8 {
            PixelFormat::Mono8
        } else if raw_format == ::aravis::PixelFormat::MONO_12 {
            PixelFormat::Mono12
        } else if raw_format == ::aravis::PixelFormat::MONO_16 {
            PixelFormat::Mono16
        } else {
            return incomplete(format!(
                "pixel format 0x{:08x} is not Mono8, Mono12 or Mono16",
                raw_format.raw()
            ));
        };
        let (Ok(width), Ok(height)) = (
            u32::try_from(buffer.image_width()),
            u32::try_from(buffer.image_height()),
        ) else {
            return incomplete(String::from("negative image size"));
        };
        let padding = u32::try_from(buffer.image_padding().0).unwrap_or(0);
        let pixels = match pixels_from_bytes(&buffer.image_data(), format, width, height, padding) {
            Ok(p) => p,
            Err(reason) => return incomplete(reason),
        };
        let timestamp = buffer.timestamp();
        let frame = Frame {
            pixels,
            width,
            height,
            format,
            host_time: SystemTime::now(),
            device_timestamp_ns: (timestamp != 0).then_some(timestamp),
            frame_id,
            exposure_us: self.exposure_us,
            gain: self.gain,
        };
        match frame.check(&self.id) {
            Ok(()) => Grabbed::Frame(frame),
            Err(e) => incomplete(e.message),
        }
    }
}

impl BlockingCamera for AravisCamera {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError> {
        self.alive()?;
        if let Err(e) = self.camera.set_exposure_time(exposure_us) {
            match self.exposure_feature {
                Some(name) if is_not_found(&e) => self
                    .camera
                    .set_float(name, exposure_us)
                    .map_err(|e| sdk_error(&self.id, &format!("set {name}"), &e))?,
                _ => return Err(sdk_error(&self.id, "set the exposure", &e)),
            }
        }
        self.exposure_us = self.read_exposure_us()?;
        Ok(self.exposure_us)
    }

    fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
        self.alive()?;
        if let Err(e) = self.camera.set_gain(gain) {
            match self.gain_feature {
                Some(name @ "GainRaw") if is_not_found(&e) => self
                    .camera
                    .set_integer(name, gain.round() as i64)
                    .map_err(|e| sdk_error(&self.id, &format!("set {name}"), &e))?,
                Some(name) if is_not_found(&e) => self
                    .camera
                    .set_float(name, gain)
                    .map_err(|e| sdk_error(&self.id, &format!("set {name}"), &e))?,
                _ => return Err(sdk_error(&self.id, "set the gain", &e)),
            }
        }
        self.gain = self.read_gain()?;
        Ok(self.gain)
    }

    fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError> {
        self.stopped("pixel_format")?;
        self.camera
            .set_pixel_format_from_string(format.name())
            .map_err(|e| sdk_error(&self.id, &format!("set PixelFormat = {format}"), &e))?;
        let applied = self
            .camera
            .pixel_format_as_string()
            .map_err(|e| sdk_error(&self.id, "read PixelFormat back", &e))?;
        if PixelFormat::from_name(&applied) != Some(format) {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                &self.id,
                format!("PixelFormat = {format} was written but {applied} was read back"),
            ));
        }
        Ok(())
    }

    fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError> {
        self.stopped("roi")?;
        let id = self.id.clone();
        let err = |what: &str, e: glib::Error| sdk_error(&id, what, &e);
        let to_i32 = |v: u32| i32::try_from(v).unwrap_or(i32::MAX);
        let step = |inc: Result<i32, glib::Error>| inc.ok().filter(|&i| i > 0).unwrap_or(1);
        // Offsets to zero first, so that the largest width and height are allowed.
        // (`is_region_offset_available` cannot say no in aravis-rs 0.11: it maps FALSE to Ok.)
        let offsets = ["OffsetX", "OffsetY"]
            .iter()
            .all(|name| self.camera.is_feature_available(name).unwrap_or(false));
        if offsets {
            self.camera
                .set_integer("OffsetX", 0)
                .map_err(|e| err("set OffsetX = 0", e))?;
            self.camera
                .set_integer("OffsetY", 0)
                .map_err(|e| err("set OffsetY = 0", e))?;
        }
        let (w_min, w_max) = self
            .camera
            .width_bounds()
            .map_err(|e| err("read Width range", e))?;
        let (h_min, h_max) = self
            .camera
            .height_bounds()
            .map_err(|e| err("read Height range", e))?;
        let (w_inc, h_inc) = (
            step(self.camera.width_increment()),
            step(self.camera.height_increment()),
        );
        let (x_inc, y_inc) = if offsets {
            (
                step(self.camera.x_offset_increment()),
                step(self.camera.y_offset_increment()),
            )
        } else {
            (1, 1)
        };
        // Round down to the increments, within the bounds.
        let round = |v: i32, inc: i32, lo: i32, hi: i32| {
            let lo = lo.max(0);
            (v - v % inc).clamp(lo, hi.max(lo))
        };
        let width = round(to_i32(roi.width), w_inc, w_min.max(1), w_max);
        let height = round(to_i32(roi.height), h_inc, h_min.max(1), h_max);
        let (x, y) = if offsets {
            (
                round(to_i32(roi.x), x_inc, 0, w_max.saturating_sub(width)),
                round(to_i32(roi.y), y_inc, 0, h_max.saturating_sub(height)),
            )
        } else {
            (0, 0)
        };
        if !offsets && (roi.x != 0 || roi.y != 0) {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.id,
                format!(
                    "roi offset = ({}, {}) is out of range: this camera has no OffsetX/OffsetY, allowed (0, 0)",
                    roi.x, roi.y
                ),
            ));
        }
        self.camera
            .set_region(x, y, width, height)
            .map_err(|e| err(&format!("set the region {width}x{height} at ({x}, {y})"), e))?;
        let (ax, ay, aw, ah) = self
            .camera
            .region()
            .map_err(|e| err("read the region back", e))?;
        let to_u32 = |v: i32| u32::try_from(v).unwrap_or(0);
        Ok(Roi {
            x: to_u32(ax),
            y: to_u32(ay),
            width: to_u32(aw),
            height: to_u32(ah),
        })
    }

    fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError> {
        self.stopped("trigger")?;
        let result = match mode {
            TriggerMode::FreeRun => self.camera.clear_triggers(),
            TriggerMode::Software => self.camera.set_trigger("Software"),
            TriggerMode::Hardware if self.hardware_trigger => {
                self.camera.set_trigger(HARDWARE_TRIGGER_SOURCE)
            }
            TriggerMode::Hardware => {
                return Err(DeviceError::new(
                    ErrorKind::OutOfRange,
                    &self.id,
                    format!("trigger = hardware needs TriggerSource {HARDWARE_TRIGGER_SOURCE}, which this camera does not offer"),
                ))
            }
        };
        result.map_err(|e| sdk_error(&self.id, &format!("set trigger = {mode:?}"), &e))?;
        self.trigger = mode;
        Ok(())
    }

    fn supports_hardware_trigger(&self) -> bool {
        self.hardware_trigger
    }

    fn start(&mut self) -> Result<(), DeviceError> {
        self.alive()?;
        if self.stream.is_some() {
            return Ok(());
        }
        if let Err(e) = self
            .camera
            .set_acquisition_mode(AcquisitionMode::Continuous)
        {
            // Cameras without AcquisitionMode stream continuously anyway.
            tracing::debug!(camera = %self.id, error = %e, "AcquisitionMode not set");
        }
        let payload = self
            .camera
            .payload()
            .map_err(|e| sdk_error(&self.id, "read PayloadSize", &e))?;
        if payload == 0 {
            return Err(DeviceError::new(
                ErrorKind::Protocol,
                &self.id,
                "PayloadSize is 0",
            ));
        }
        if self.camera.is_gv_device() && (self.on_loopback || !self.options.packet_socket) {
            self.camera
                .gv_set_stream_options(GvStreamOption::PACKET_SOCKET_DISABLED);
        }
        let stream = self
            .camera
            .create_stream()
            .map_err(|e| sdk_error(&self.id, "create the stream", &e))?;
        if let Some(gv) = stream.downcast_ref::<::aravis::GvStream>() {
            size_socket_buffer(gv, payload);
        }
        for _ in 0..self.options.buffers {
            stream.push_buffer(::aravis::Buffer::new_allocate(payload as usize));
        }
        self.frame_period = self
            .camera
            .frame_rate()
            .ok()
            .filter(|r| r.is_finite() && *r > 0.0)
            .map(|r| Duration::from_secs_f64(1.0 / r));
        self.camera
            .start_acquisition()
            .map_err(|e| sdk_error(&self.id, "start the acquisition", &e))?;
        self.stream = Some(stream);
        self.last_sign_of_life = Instant::now();
        self.probe = None;
        Ok(())
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        let Some(stream) = self.stream.take() else {
            return Ok(());
        };
        self.probe = None;
        let result = self
            .camera
            .stop_acquisition()
            .map_err(|e| sdk_error(&self.id, "stop the acquisition", &e));
        // Dropping the stream ends its thread and frees its buffers.
        drop(stream);
        result
    }

    fn trigger(&mut self) -> Result<(), DeviceError> {
        self.alive()?;
        if self.trigger != TriggerMode::Software {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &self.id,
                format!(
                    "a software trigger needs trigger = software; the camera is in {:?}",
                    self.trigger
                ),
            ));
        }
        self.camera
            .software_trigger()
            .map_err(|e| sdk_error(&self.id, "TriggerSoftware", &e))
    }

    fn wait_frame(&mut self, wait: Duration) -> Result<Grabbed, DeviceError> {
        self.check_health()?;
        let Some(stream) = &self.stream else {
            std::thread::sleep(wait);
            return Ok(Grabbed::Nothing);
        };
        let wait_us = u64::try_from(wait.as_micros()).unwrap_or(u64::MAX);
        let Some(buffer) = stream.timeout_pop_buffer(wait_us) else {
            self.check_health()?;
            self.probe_if_silent();
            return Ok(Grabbed::Nothing);
        };
        // Packets arrived for this buffer (a `Timeout` status may be the last one of a device
        // that died mid-frame, so it does not count as a sign of life).
        if !matches!(
            buffer.status(),
            BufferStatus::Timeout | BufferStatus::Aborted
        ) {
            self.last_sign_of_life = Instant::now();
        }
        let grabbed = self.grabbed(&buffer);
        // Recycle every buffer, whatever it held.
        if let Some(stream) = &self.stream {
            stream.push_buffer(buffer);
        }
        Ok(grabbed)
    }

    fn transport_stats(&self) -> Option<TransportStats> {
        let stream = self.stream.as_ref()?;
        if !self.camera.is_gv_device() {
            return None;
        }
        let info = |name: &str| stream.info_uint64_by_name(name);
        let resend = stream
            .downcast_ref::<::aravis::GvStream>()
            .is_some_and(|gv| gv.packet_resend() == ::aravis::GvStreamPacketResend::Always);
        Some(TransportStats {
            packet_resend: resend,
            received_packets: info("n_received_packets"),
            missing_packets: info("n_missing_packets"),
            resend_requests: info("n_resend_requests"),
            resent_packets: info("n_resent_packets"),
        })
    }
}

/// The receive buffer a GigE Vision stream's socket needs: a whole frame's packets arrive in
/// one burst (the fake camera sends them back to back), and with the system's default
/// (`net.core.rmem_default`, 208 KiB here) a 256 KiB frame overflows it before the stream thread
/// reads: on loopback 228 of 249 frames came incomplete, 19 248 packets lost, none resent
/// (Aravis's own `arv-camera-test-0.8` shows the same; its `--auto` socket buffer fixes it).
/// Four payloads (at least 4 MiB) hold a frame while earlier ones are still read; the kernel
/// caps it at `net.core.rmem_max` (4 MiB on this kind of machine).
pub const SOCKET_BUFFER_PAYLOADS: u32 = 4;

fn size_socket_buffer(gv: &::aravis::GvStream, payload: u32) {
    let bytes = payload
        .saturating_mul(SOCKET_BUFFER_PAYLOADS)
        .max(4 << 20)
        .min(i32::MAX as u32);
    gv.set_socket_buffer(::aravis::GvStreamSocketBuffer::Fixed);
    gv.set_socket_buffer_size(bytes as i32);
}

/// Whether the camera is a GigE Vision device at a loopback address.
fn gige_on_loopback(camera: &::aravis::Camera) -> bool {
    camera
        .device()
        .and_then(|d| d.downcast::<::aravis::GvDevice>().ok())
        .and_then(|gv| gv.device_address())
        .and_then(|a| a.downcast::<gio::InetSocketAddress>().ok())
        .is_some_and(|a| a.address().is_loopback())
}

impl Drop for AravisCamera {
    fn drop(&mut self) {
        if let Some(stream) = self.stream.take() {
            if self.gone.is_none() {
                if let Err(e) = self.camera.stop_acquisition() {
                    tracing::debug!(camera = %self.id, error = %e, "stop at close failed");
                }
            }
            drop(stream);
        }
        if let Some((device, handler)) = self.control_lost_handler.take() {
            device.disconnect(handler);
        }
    }
}
