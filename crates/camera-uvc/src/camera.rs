//! The UVC camera: nokhwa's `Camera` owned by a thread of its own, driven through a queue of
//! calls, with frames handed back over a bounded channel so that every wait has a deadline.
//!
//! nokhwa's `Camera` is not `Send` (its backends hold platform COM/Objective-C objects), and its
//! `frame()` blocks with no timeout until the device delivers. So the camera is created on, and
//! never leaves, a named thread (`uvc-<name>`). That thread runs the calls it is sent (controls,
//! start, stop) and, while streaming, reads frames and puts them in a bounded channel; a full
//! channel drops the new frame (the frame ids then show the gap). [`UvcCamera`] holds only the
//! channels, so it is `Send` and is a [`BlockingCamera`]; every call waits at most its deadline.
//! `open_stream` is always called (by [`BlockingCamera::start`]) before the thread reads a frame:
//! nokhwa's `frame()` on a camera whose stream is not open can hang. A call made while the
//! thread is inside `frame()` is served when that frame arrives (within a frame period); if the
//! device has stalled the call ends with [`ErrorKind::Timeout`]. A panic inside nokhwa is caught
//! on the thread and becomes an error. Dropping the camera ends the thread (and closes the device)
//! after its current frame read; a device that never returns from that read keeps the thread
//! parked, never the caller.

use crate::controls::{
    integer_value, is_automatic, not_offered, ExposureControl, GainControl, IntRange, Platform,
};
use crate::device::{list, panic_text, select, UvcDeviceInfo};
use crate::source::SourceFormat;
use nokhwa::utils::{
    CameraControl, CameraIndex, ControlValueSetter, KnownCameraControl, RequestedFormat,
    RequestedFormatType,
};
use polar_frame_convert::crop;
use polar_hal::{
    BlockingCamera, CameraInfo, DeviceError, ErrorKind, Frame, GainUnit, Grabbed, PixelFormat, Roi,
    TriggerMode,
};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender, SyncSender, TryRecvError};
use std::time::{Duration, SystemTime};

/// How a camera is opened.
#[derive(Debug, Clone, PartialEq)]
pub struct OpenOptions {
    /// Formats to try, in order; the first the camera offers is used at its highest
    /// resolution. Default: [`SourceFormat::PREFERENCE`].
    pub formats: Vec<SourceFormat>,
    /// How long opening may take (enumeration excluded). Default 10 s: Media Foundation and
    /// AVFoundation can take seconds to bring a camera up.
    pub open_timeout: Duration,
    /// How long a setting, start or stop may wait for the camera thread. Default 3 s, longer
    /// than one frame at the slowest UVC frame rate a measurement uses (about 1 fps).
    pub call_timeout: Duration,
    /// Frames held between the camera thread and [`BlockingCamera::wait_frame`]. Default 4.
    pub queue_frames: usize,
}

impl Default for OpenOptions {
    fn default() -> Self {
        OpenOptions {
            formats: SourceFormat::PREFERENCE.to_vec(),
            open_timeout: Duration::from_secs(10),
            call_timeout: Duration::from_secs(3),
            queue_frames: 4,
        }
    }
}

/// The stream a camera was opened with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Source {
    /// Its format.
    pub format: SourceFormat,
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Frame rate the device was set to, frames per second.
    pub frame_rate: u32,
}

/// What the camera thread owns.
struct Held {
    camera: nokhwa::Camera,
    streaming: bool,
    next_id: u64,
}

/// A call run on the camera thread.
type Call = Box<dyn FnOnce(&mut Held) + Send>;

/// One frame as read by the camera thread, before conversion.
struct RawFrame {
    data: Vec<u8>,
    frame_id: u64,
    host_time: SystemTime,
}

/// What the thread reports once the camera is open.
struct Opened {
    source: Source,
    controls: Vec<CameraControl>,
}

/// A UVC camera on nokhwa, as a [`BlockingCamera`] (wrap it in
/// `polar_hal::camera_thread::ThreadedCamera` for the async [`polar_hal::Camera`]).
pub struct UvcCamera {
    id: String,
    device: UvcDeviceInfo,
    platform: Option<Platform>,
    source: Source,
    info: CameraInfo,
    exposure: Option<ExposureControl>,
    gain: Option<GainControl>,
    exposure_us: f64,
    gain_value: f64,
    roi: Roi,
    streaming: bool,
    call_timeout: Duration,
    calls: Sender<Call>,
    frames: Receiver<Result<RawFrame, String>>,
}

impl std::fmt::Debug for UvcCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UvcCamera")
            .field("id", &self.id)
            .field("device", &self.device)
            .field("source", &self.source)
            .field("exposure", &self.exposure)
            .field("gain", &self.gain)
            .finish_non_exhaustive()
    }
}

impl UvcCamera {
    /// Opens the camera a spec names (`uvc:<bus info>` or `uvc:<name>`, see [`crate::device`])
    /// with the default options.
    pub fn open(spec: &str) -> Result<UvcCamera, DeviceError> {
        UvcCamera::open_with(spec, OpenOptions::default())
    }

    /// Opens the camera a spec names.
    pub fn open_with(spec: &str, options: OpenOptions) -> Result<UvcCamera, DeviceError> {
        let devices = list()?;
        let device = select(spec, &devices)?.clone();
        UvcCamera::open_device(device, options)
    }

    /// Opens a device found by [`list`].
    pub fn open_device(
        device: UvcDeviceInfo,
        options: OpenOptions,
    ) -> Result<UvcCamera, DeviceError> {
        let id = device.spec();
        if options.formats.is_empty() || options.queue_frames == 0 {
            return Err(DeviceError::new(
                ErrorKind::OutOfRange,
                &id,
                format!(
                    "formats = {} and queue_frames = {} are out of range: allowed at least one \
                     format and at least 1 frame",
                    options.formats.len(),
                    options.queue_frames
                ),
            ));
        }
        let (calls_tx, calls_rx) = mpsc::channel::<Call>();
        let (frames_tx, frames_rx) = mpsc::sync_channel(options.queue_frames);
        let (opened_tx, opened_rx) = mpsc::sync_channel(1);
        let index = device.index.clone();
        let formats = options.formats.clone();
        std::thread::Builder::new()
            .name(format!("uvc-{}", device.name))
            .spawn(move || {
                let opened = catch_unwind(AssertUnwindSafe(|| open_on_thread(&index, &formats)))
                    .unwrap_or_else(|p| {
                        Err(format!("nokhwa panicked: {}", panic_text(p.as_ref())))
                    });
                match opened {
                    Ok((camera, opened)) => {
                        if opened_tx.send(Ok(opened)).is_ok() {
                            run(
                                Held {
                                    camera,
                                    streaming: false,
                                    next_id: 0,
                                },
                                &calls_rx,
                                &frames_tx,
                            );
                        }
                    }
                    Err(e) => {
                        let _ = opened_tx.send(Err(e));
                    }
                }
            })
            .map_err(|e| {
                DeviceError::new(
                    ErrorKind::Other,
                    &id,
                    format!("cannot start the camera thread: {e}"),
                )
            })?;
        let opened = match opened_rx.recv_timeout(options.open_timeout) {
            Ok(Ok(opened)) => opened,
            Ok(Err(e)) => {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    &id,
                    format!("cannot open {device}: {e}"),
                ))
            }
            Err(_) => {
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    &id,
                    format!(
                        "{device} did not open within {:?} (another program may hold it)",
                        options.open_timeout
                    ),
                ))
            }
        };
        Ok(UvcCamera::assemble(
            id,
            device,
            Platform::current(),
            opened.source,
            &opened.controls,
            options.call_timeout,
            calls_tx,
            frames_rx,
        ))
    }

    /// Puts a camera together from what its thread reported.
    #[allow(clippy::too_many_arguments)]
    fn assemble(
        id: String,
        device: UvcDeviceInfo,
        platform: Option<Platform>,
        source: Source,
        controls: &[CameraControl],
        call_timeout: Duration,
        calls: Sender<Call>,
        frames: Receiver<Result<RawFrame, String>>,
    ) -> UvcCamera {
        let (exposure, exposure_us) = exposure_of(platform, controls);
        let (gain, gain_value) = gain_of(platform, controls);
        let info = CameraInfo {
            id: id.clone(),
            vendor: device.description.clone(),
            model: device.name.clone(),
            serial: String::new(),
            sensor_width: source.width,
            sensor_height: source.height,
            exposure_range_us: exposure.map_or([0.0, 0.0], |e| e.range_us()),
            gain_range: gain.map_or([0.0, 0.0], |g| [g.range.min as f64, g.range.max as f64]),
            gain_unit: GainUnit::Raw,
            formats: vec![PixelFormat::Mono8],
        };
        UvcCamera {
            id,
            device,
            platform,
            source,
            info,
            exposure,
            gain,
            exposure_us,
            gain_value,
            roi: Roi::full(source.width, source.height),
            streaming: false,
            call_timeout,
            calls,
            frames,
        }
    }

    /// The device as listed.
    pub fn device(&self) -> &UvcDeviceInfo {
        &self.device
    }

    /// The stream it was opened with.
    pub fn source(&self) -> Source {
        self.source
    }

    /// The manual exposure control, if the platform and camera offer one.
    pub fn exposure_control(&self) -> Option<ExposureControl> {
        self.exposure
    }

    /// The gain control, if the platform and camera offer one.
    pub fn gain_control(&self) -> Option<GainControl> {
        self.gain
    }

    fn error(&self, kind: ErrorKind, message: impl Into<String>) -> DeviceError {
        DeviceError::new(kind, &self.id, message)
    }

    /// Runs `f` on the camera thread and waits at most the call deadline for its result.
    fn call<R: Send + 'static>(
        &self,
        what: &str,
        f: impl FnOnce(&mut Held) -> R + Send + 'static,
    ) -> Result<R, DeviceError> {
        let (tx, rx) = mpsc::sync_channel(1);
        self.calls
            .send(Box::new(move |held: &mut Held| {
                let _ = tx.send(f(held));
            }))
            .map_err(|_| self.error(ErrorKind::Disconnected, "the camera thread has ended"))?;
        rx.recv_timeout(self.call_timeout).map_err(|e| match e {
            RecvTimeoutError::Timeout => self.error(
                ErrorKind::Timeout,
                format!(
                    "{what}: no answer within {:?} (the camera delivers no frames)",
                    self.call_timeout
                ),
            ),
            RecvTimeoutError::Disconnected => self.error(
                ErrorKind::Disconnected,
                format!("{what}: the camera thread ended (a panic in nokhwa?)"),
            ),
        })
    }

    /// Writes an integer control and reads it back: returns the value and its flags.
    fn write_control(
        &self,
        what: &'static str,
        mode: Option<(KnownCameraControl, ControlValueSetter)>,
        control: KnownCameraControl,
        value: i64,
    ) -> Result<(i64, bool), DeviceError> {
        let result = self.call(what, move |held| {
            catch_unwind(AssertUnwindSafe(|| {
                if let Some((mode, mode_value)) = mode {
                    held.camera
                        .set_camera_control(mode, mode_value)
                        .map_err(|e| format!("switching to manual: {e}"))?;
                }
                held.camera
                    .set_camera_control(control, ControlValueSetter::Integer(value))
                    .map_err(|e| e.to_string())?;
                let read = held
                    .camera
                    .camera_control(control)
                    .map_err(|e| format!("reading back: {e}"))?;
                let v = integer_value(&read.value())
                    .ok_or_else(|| format!("reads back {:?}, not an integer", read.value()))?;
                Ok::<_, String>((v, is_automatic(read.flag())))
            }))
            .unwrap_or_else(|p| Err(format!("nokhwa panicked: {}", panic_text(p.as_ref()))))
        })?;
        result.map_err(|e| self.error(ErrorKind::Other, format!("{what} = {value} failed: {e}")))
    }
}

/// Opens the camera on its thread: the first format of `formats` the device offers, at its
/// highest resolution; then reads its controls.
fn open_on_thread(
    index: &CameraIndex,
    formats: &[SourceFormat],
) -> Result<(nokhwa::Camera, Opened), String> {
    let mut refusals = Vec::new();
    for &format in formats {
        let wanted = [format.nokhwa()];
        let requested =
            RequestedFormat::with_formats(RequestedFormatType::AbsoluteHighestResolution, &wanted);
        match nokhwa::Camera::new(index.clone(), requested) {
            Ok(camera) => {
                let f = camera.camera_format();
                if SourceFormat::from_nokhwa(f.format()) != Some(format) {
                    refusals.push(format!("{format}: opened as {}", f.format()));
                    continue;
                }
                let source = Source {
                    format,
                    width: f.width(),
                    height: f.height(),
                    frame_rate: f.frame_rate(),
                };
                let controls = camera.camera_controls().unwrap_or_default();
                return Ok((camera, Opened { source, controls }));
            }
            Err(e) => refusals.push(format!("{format}: {e}")),
        }
    }
    Err(format!(
        "no luminance format could be set (tried {})",
        refusals.join("; ")
    ))
}

/// The camera thread: runs calls; while streaming, reads frames between them.
fn run(mut held: Held, calls: &Receiver<Call>, frames: &SyncSender<Result<RawFrame, String>>) {
    loop {
        loop {
            let call = if held.streaming {
                match calls.try_recv() {
                    Ok(call) => call,
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Disconnected) => return,
                }
            } else {
                match calls.recv() {
                    Ok(call) => call,
                    Err(_) => return,
                }
            };
            call(&mut held);
        }
        let read = catch_unwind(AssertUnwindSafe(|| held.camera.frame()));
        let host_time = SystemTime::now();
        let item = match read {
            Ok(Ok(buffer)) => {
                held.next_id += 1;
                Ok(RawFrame {
                    data: buffer.buffer().to_vec(),
                    frame_id: held.next_id,
                    host_time,
                })
            }
            Ok(Err(e)) => {
                held.streaming = false;
                tracing::warn!("reading a frame failed, the stream stops: {e}");
                Err(e.to_string())
            }
            Err(p) => {
                held.streaming = false;
                Err(format!("nokhwa panicked: {}", panic_text(p.as_ref())))
            }
        };
        match frames.try_send(item) {
            Ok(()) | Err(mpsc::TrySendError::Full(_)) => {}
            Err(mpsc::TrySendError::Disconnected(_)) => return,
        }
    }
}

/// The manual exposure a camera offers on `platform`, and its current value in µs (0 without
/// one).
fn exposure_of(
    platform: Option<Platform>,
    controls: &[CameraControl],
) -> (Option<ExposureControl>, f64) {
    let Some((control, scale)) = platform.and_then(Platform::exposure_control) else {
        return (None, 0.0);
    };
    let found = controls
        .iter()
        .find(|c| c.control() == control)
        .and_then(|c| IntRange::of(c.description()));
    match found {
        Some(range) => (
            Some(ExposureControl {
                control,
                scale,
                range,
            }),
            scale.to_us(range.value),
        ),
        None => (None, 0.0),
    }
}

/// The gain a camera offers on `platform`, and its current value (0 without one).
fn gain_of(platform: Option<Platform>, controls: &[CameraControl]) -> (Option<GainControl>, f64) {
    let Some(control) = platform.and_then(Platform::gain_control) else {
        return (None, 0.0);
    };
    match controls
        .iter()
        .find(|c| c.control() == control)
        .and_then(|c| IntRange::of(c.description()))
    {
        Some(range) => (Some(GainControl { control, range }), range.value as f64),
        None => (None, 0.0),
    }
}

/// Converts, crops and checks one raw frame.
fn frame_from(
    raw: RawFrame,
    source: Source,
    roi: Roi,
    exposure_us: f64,
    gain: f64,
    id: &str,
) -> Grabbed {
    let pixels = source
        .format
        .to_luma(&raw.data, source.width, source.height)
        .and_then(|px| crop(&px, source.width, source.height, roi));
    let pixels = match pixels {
        Ok(p) => p,
        Err(e) => {
            return Grabbed::Incomplete {
                frame_id: Some(raw.frame_id),
                reason: format!("{} frame: {e}", source.format),
            }
        }
    };
    let frame = Frame {
        pixels,
        width: roi.width,
        height: roi.height,
        format: PixelFormat::Mono8,
        host_time: raw.host_time,
        device_timestamp_ns: None,
        frame_id: raw.frame_id,
        exposure_us,
        gain,
    };
    match frame.check(id) {
        Ok(()) => Grabbed::Frame(frame),
        Err(e) => Grabbed::Incomplete {
            frame_id: Some(raw.frame_id),
            reason: e.message,
        },
    }
}

impl BlockingCamera for UvcCamera {
    fn info(&self) -> CameraInfo {
        self.info.clone()
    }

    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError> {
        let Some(exposure) = self.exposure else {
            let why = if self.platform.and_then(Platform::exposure_control).is_some() {
                "exposure (the camera has no such control)"
            } else {
                "exposure"
            };
            return Err(self.error(
                ErrorKind::OutOfRange,
                not_offered("exposure_us", exposure_us, self.platform, why),
            ));
        };
        let value = exposure
            .device_value(exposure_us)
            .map_err(|m| self.error(ErrorKind::OutOfRange, m))?;
        let mode = self.platform.and_then(Platform::manual_exposure_mode);
        let (read, automatic) = self.write_control("exposure", mode, exposure.control, value)?;
        if automatic {
            return Err(self.error(
                ErrorKind::Other,
                format!(
                    "exposure is in automatic mode on {}: nokhwa keeps a control's mode, so set \
                     the camera's exposure to manual in its driver settings first",
                    self.platform.map_or("this platform", Platform::name)
                ),
            ));
        }
        self.exposure_us = exposure.scale.to_us(read);
        Ok(self.exposure_us)
    }

    fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
        let Some(control) = self.gain else {
            return Err(self.error(
                ErrorKind::OutOfRange,
                not_offered("gain", gain, self.platform, "gain"),
            ));
        };
        let value = control
            .device_value(gain)
            .map_err(|m| self.error(ErrorKind::OutOfRange, m))?;
        let (read, _) = self.write_control("gain", None, control.control, value)?;
        self.gain_value = read as f64;
        Ok(self.gain_value)
    }

    fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError> {
        self.info.check_format(format).map(|_| ())
    }

    fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError> {
        if self.streaming {
            return Err(self.error(
                ErrorKind::Busy,
                "roi can only be set while stopped: stop the stream first",
            ));
        }
        roi.check(&self.id, self.source.width, self.source.height)?;
        self.roi = roi;
        Ok(roi)
    }

    fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError> {
        match mode {
            TriggerMode::FreeRun => Ok(()),
            TriggerMode::Software | TriggerMode::Hardware => Err(self.error(
                ErrorKind::OutOfRange,
                format!(
                    "trigger = {} is not offered by this camera: allowed free-run (UVC cameras \
                     through nokhwa free-run)",
                    if mode == TriggerMode::Software {
                        "software"
                    } else {
                        "hardware"
                    }
                ),
            )),
        }
    }

    fn supports_software_trigger(&self) -> bool {
        false
    }

    fn start(&mut self) -> Result<(), DeviceError> {
        if self.streaming {
            return Ok(());
        }
        while self.frames.try_recv().is_ok() {}
        self.call("start", |held| {
            catch_unwind(AssertUnwindSafe(|| held.camera.open_stream()))
                .map_err(|p| format!("nokhwa panicked: {}", panic_text(p.as_ref())))?
                .map_err(|e| e.to_string())?;
            held.streaming = true;
            Ok::<(), String>(())
        })?
        .map_err(|e| self.error(ErrorKind::Other, format!("open_stream failed: {e}")))?;
        self.streaming = true;
        Ok(())
    }

    fn stop(&mut self) -> Result<(), DeviceError> {
        if !self.streaming {
            return Ok(());
        }
        self.streaming = false;
        let stopped = self.call("stop", |held| {
            held.streaming = false;
            catch_unwind(AssertUnwindSafe(|| held.camera.stop_stream()))
                .map_err(|p| format!("nokhwa panicked: {}", panic_text(p.as_ref())))?
                .map_err(|e| e.to_string())
        });
        while self.frames.try_recv().is_ok() {}
        stopped?.map_err(|e| self.error(ErrorKind::Other, format!("stop_stream failed: {e}")))
    }

    fn trigger(&mut self) -> Result<(), DeviceError> {
        Err(self.error(
            ErrorKind::OutOfRange,
            "trigger: software triggers are not offered: allowed free-run only",
        ))
    }

    fn wait_frame(&mut self, wait: Duration) -> Result<Grabbed, DeviceError> {
        if !self.streaming {
            return Err(self.error(
                ErrorKind::Other,
                "wait_frame: the stream is not started (start opens it)",
            ));
        }
        match self.frames.recv_timeout(wait) {
            Ok(Ok(raw)) => Ok(frame_from(
                raw,
                self.source,
                self.roi,
                self.exposure_us,
                self.gain_value,
                &self.id,
            )),
            Ok(Err(e)) => {
                self.streaming = false;
                Err(self.error(
                    ErrorKind::Disconnected,
                    format!(
                        "reading a frame failed: {e}; the stream is stopped (start again, or \
                         after an unplug open the camera again by name or bus info)"
                    ),
                ))
            }
            Err(RecvTimeoutError::Timeout) => Ok(Grabbed::Nothing),
            Err(RecvTimeoutError::Disconnected) => {
                self.streaming = false;
                Err(self.error(ErrorKind::Disconnected, "the camera thread has ended"))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nokhwa::utils::ControlValueDescription;

    fn integer_control(
        control: KnownCameraControl,
        min: i64,
        max: i64,
        value: i64,
    ) -> CameraControl {
        CameraControl::new(
            control,
            control.to_string(),
            ControlValueDescription::IntegerRange {
                min,
                max,
                value,
                step: 1,
                default: value,
            },
            vec![],
            true,
        )
    }

    fn source() -> Source {
        Source {
            format: SourceFormat::Yuyv,
            width: 4,
            height: 2,
            frame_rate: 30,
        }
    }

    /// A camera whose thread is a stand-in: calls are received and dropped, no frame is ever
    /// sent (a stalled device). The senders are returned so the channels stay open.
    fn stalled(
        platform: Option<Platform>,
        controls: &[CameraControl],
    ) -> (
        UvcCamera,
        Receiver<Call>,
        SyncSender<Result<RawFrame, String>>,
    ) {
        let (calls_tx, calls_rx) = mpsc::channel();
        let (frames_tx, frames_rx) = mpsc::sync_channel(2);
        let device = UvcDeviceInfo {
            index: CameraIndex::Index(3),
            name: "Test Cam".into(),
            description: "test".into(),
            bus_info: "usb-test-1".into(),
        };
        let camera = UvcCamera::assemble(
            device.spec(),
            device,
            platform,
            source(),
            controls,
            Duration::from_millis(50),
            calls_tx,
            frames_rx,
        );
        (camera, calls_rx, frames_tx)
    }

    /// On Linux the exposure is the V4L2 absolute control in 100 µs units: a camera reporting
    /// `exposure_time_absolute` in [3, 2047] at 156 has the range [300, 204 700] µs and reads
    /// 15 600 µs; gain comes from `V4L2_CID_GAIN` as raw units. nokhwa's own
    /// `KnownCameraControl::Exposure` (`V4L2_CID_EXPOSURE`) is ignored there.
    #[test]
    fn linux_controls_map_to_the_v4l2_absolute_exposure() {
        let controls = [
            integer_control(
                KnownCameraControl::Other(u128::from(crate::controls::V4L2_CID_EXPOSURE_ABSOLUTE)),
                3,
                2047,
                156,
            ),
            integer_control(KnownCameraControl::Exposure, 0, 10, 5),
            integer_control(KnownCameraControl::Gain, 0, 255, 32),
        ];
        let (camera, _calls, _frames) = stalled(Some(Platform::Linux), &controls);
        let info = BlockingCamera::info(&camera);
        assert_eq!(info.exposure_range_us, [300.0, 204_700.0]);
        assert_eq!(info.gain_range, [0.0, 255.0]);
        assert_eq!(info.gain_unit, GainUnit::Raw);
        assert_eq!(camera.exposure_us, 15_600.0);
        assert_eq!(camera.gain_value, 32.0);
        assert_eq!(info.formats, vec![PixelFormat::Mono8]);
        assert_eq!((info.sensor_width, info.sensor_height), (4, 2));
    }

    /// Where a control is missing (macOS always; a camera without gain), setting it is refused
    /// with OutOfRange naming the setting, the value and the empty range, before the camera
    /// thread is asked anything; an out-of-range exposure names the range in µs.
    #[test]
    fn missing_and_out_of_range_controls_are_refused() {
        let (mut mac, calls, _frames) = stalled(Some(Platform::MacOs), &[]);
        let e = mac.set_exposure_us(1000.0).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(
            e.message
                .contains("exposure_us = 1000 is out of range: allowed none"),
            "{e}"
        );
        assert!(e.message.contains("macOS (AVFoundation)"), "{e}");
        let e = mac.set_gain(2.0).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.starts_with("gain = 2 is out of range"), "{e}");
        assert!(
            calls.try_recv().is_err(),
            "nothing was sent to the camera thread"
        );

        let controls = [integer_control(
            KnownCameraControl::Other(u128::from(crate::controls::V4L2_CID_EXPOSURE_ABSOLUTE)),
            1,
            5000,
            100,
        )];
        let (mut cam, calls, _frames) = stalled(Some(Platform::Linux), &controls);
        let e = cam.set_exposure_us(600_000.0).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.ends_with("allowed [100, 500000]"), "{e}");
        let e = cam.set_gain(1.0).unwrap_err();
        assert!(e.message.contains("no manual gain"), "{e}");
        assert!(
            calls.try_recv().is_err(),
            "nothing was sent to the camera thread"
        );
    }

    /// Every wait has a deadline: a camera thread that never answers makes a setting end with
    /// Timeout, and a grab with no frame returns Nothing after its wait, not a hang.
    #[test]
    fn waits_end_at_their_deadline() {
        let controls = [integer_control(KnownCameraControl::Gain, 0, 255, 32)];
        let (mut cam, _calls, _frames) = stalled(Some(Platform::Linux), &controls);
        let e = cam.set_gain(10.0).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Timeout);
        assert!(e.message.contains("gain: no answer within 50ms"), "{e}");
        let e = cam.start().unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Timeout);
        cam.streaming = true;
        assert_eq!(
            cam.wait_frame(Duration::from_millis(20)),
            Ok(Grabbed::Nothing)
        );
    }

    /// Grabbing before start is refused (nokhwa's frame() must never run on a closed stream),
    /// and a thread that has gone reports Disconnected.
    #[test]
    fn grab_before_start_and_after_thread_end() {
        let (mut cam, calls, frames) = stalled(Some(Platform::Linux), &[]);
        let e = cam.wait_frame(Duration::from_millis(1)).unwrap_err();
        assert!(e.message.contains("not started"), "{e}");
        drop(calls);
        drop(frames);
        let e = cam.start().unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        cam.streaming = true;
        let e = cam.wait_frame(Duration::from_millis(1)).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
    }

    /// A frame from the thread is converted (YUYV luma), cropped to the region and carries the
    /// exposure and gain read back; a truncated one is Incomplete with its id, never an image;
    /// a read error ends the stream as Disconnected.
    #[test]
    fn frames_are_converted_cropped_and_checked() {
        let (mut cam, _calls, frames) = stalled(Some(Platform::Linux), &[]);
        let roi = Roi {
            x: 1,
            y: 1,
            width: 2,
            height: 1,
        };
        assert_eq!(cam.set_roi(roi), Ok(roi));
        cam.streaming = true;
        // 4x2 YUYV: Y values 1..=8, chroma 128.
        let data: Vec<u8> = (1..=8u8).flat_map(|y| [y, 128]).collect();
        let now = SystemTime::now();
        frames
            .send(Ok(RawFrame {
                data: data.clone(),
                frame_id: 7,
                host_time: now,
            }))
            .expect("queue");
        match cam.wait_frame(Duration::from_secs(1)) {
            Ok(Grabbed::Frame(f)) => {
                assert_eq!(f.pixels, vec![6, 7]);
                assert_eq!((f.width, f.height, f.frame_id), (2, 1, 7));
                assert_eq!(f.format, PixelFormat::Mono8);
                assert_eq!(f.host_time, now);
            }
            other => panic!("expected a frame, got {other:?}"),
        }
        frames
            .send(Ok(RawFrame {
                data: data[..10].to_vec(),
                frame_id: 8,
                host_time: now,
            }))
            .expect("queue");
        match cam.wait_frame(Duration::from_secs(1)) {
            Ok(Grabbed::Incomplete { frame_id, reason }) => {
                assert_eq!(frame_id, Some(8));
                assert!(reason.contains("YUYV frame"), "{reason}");
            }
            other => panic!("expected an incomplete frame, got {other:?}"),
        }
        frames.send(Err("No such device".into())).expect("queue");
        let e = cam.wait_frame(Duration::from_secs(1)).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(e.message.contains("No such device"), "{e}");
    }

    /// Only free-run is offered; the refusal names the mode asked for. A region outside the
    /// frame is refused naming the frame size, and only Mono8 is offered.
    #[test]
    fn trigger_roi_and_format_limits() {
        let (mut cam, _calls, _frames) = stalled(Some(Platform::Windows), &[]);
        assert!(cam.set_trigger(TriggerMode::FreeRun).is_ok());
        let e = cam.set_trigger(TriggerMode::Software).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.contains("trigger = software"), "{e}");
        let e = cam
            .set_roi(Roi {
                x: 3,
                y: 0,
                width: 2,
                height: 1,
            })
            .unwrap_err();
        assert!(e.message.contains("4x2 sensor"), "{e}");
        assert!(cam.set_pixel_format(PixelFormat::Mono8).is_ok());
        let e = cam.set_pixel_format(PixelFormat::Mono16).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.contains("allowed Mono8"), "{e}");
    }
}
