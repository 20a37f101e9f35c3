//! [`FakeAnalyzerCamera`]: Aravis's fake GigE Vision camera running inside this process, whose
//! image follows the angle of an analyzer in front of a partially polarized scene
//! (`docs/DEVICES.md` section 4.2). The GenICam path (discovery, GVCP control, GVSP
//! streaming, buffer checks) then runs for real in a closed loop with a simulated stage.

use crate::camera::{AravisCamera, AravisOptions};
use crate::AravisError;
use ::aravis::glib::translate::ToGlibPtr;
use polar_hal::{BlockingCamera, CameraInfo, DeviceError, Grabbed, PixelFormat, Roi, TriggerMode};
use std::ffi::c_void;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The interface the in-process fake listens on.
const FAKE_INTERFACE: &str = "127.0.0.1";
/// How long to wait for the fake to be found and opened.
const OPEN_DEADLINE: Duration = Duration::from_secs(10);

/// What the fake camera looks at: a uniform, partially linearly polarized scene seen through an
/// ideal linear analyzer at angle `theta`. Each pixel reads Malus's law for the polarized part,
///
/// `I(theta) = I0 * (1 + dolp * cos(2 (theta - aop))) / 2`, with `I0 = s0 * exposure / reference`,
///
/// as a fraction of the pixel format's full scale, rounded and clipped to `[0, max]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnalyzerScene {
    /// Total intensity (Stokes S0) at the reference exposure, as a fraction of full scale.
    pub s0_full_scale: f64,
    /// Degree of linear polarization, `0..=1`.
    pub dolp: f64,
    /// Angle of polarization, radians.
    pub aop_rad: f64,
    /// The exposure at which S0 is `s0_full_scale`; intensity is proportional to exposure.
    pub reference_exposure_us: f64,
}

impl Default for AnalyzerScene {
    fn default() -> Self {
        AnalyzerScene {
            s0_full_scale: 0.8,
            dolp: 0.3,
            aop_rad: 30f64.to_radians(),
            reference_exposure_us: 10_000.0,
        }
    }
}

impl AnalyzerScene {
    /// The fraction of full scale a pixel reads with the analyzer at `analyzer_rad` and this
    /// exposure, before rounding and clipping.
    pub fn intensity(&self, analyzer_rad: f64, exposure_us: f64) -> f64 {
        let i0 = self.s0_full_scale * exposure_us / self.reference_exposure_us;
        i0 * (1.0 + self.dolp * (2.0 * (analyzer_rad - self.aop_rad)).cos()) / 2.0
    }

    /// The pixel value the fake camera writes, in `format`.
    pub fn pixel(&self, analyzer_rad: f64, exposure_us: f64, format: PixelFormat) -> u16 {
        let max = f64::from(format.max_value());
        let v = (self.intensity(analyzer_rad, exposure_us) * max).round();
        if v.is_nan() {
            0
        } else {
            v.clamp(0.0, max) as u16
        }
    }
}

/// What the fill callback reads; lives in a `Box` whose address Aravis holds.
struct FillState {
    analyzer_rad: Box<dyn Fn() -> f64 + Send + Sync>,
    scene: Mutex<AnalyzerScene>,
    frames: AtomicU64,
}

impl FillState {
    fn pixel(&self, exposure_us: u32, format: PixelFormat) -> u16 {
        let scene = *self.scene.lock().unwrap_or_else(|p| p.into_inner());
        scene.pixel((self.analyzer_rad)(), f64::from(exposure_us), format)
    }
}

/// Aravis's fake GigE Vision camera in this process, found as `Aravis-Fake-<serial>` on
/// 127.0.0.1, opened as an [`AravisCamera`] (Mono16), with every frame a uniform image of the
/// [`AnalyzerScene`] at the angle the angle source returns when the frame is made.
///
/// Only one fake GigE Vision camera may run per host (two on 127.0.0.1 receive each other's
/// control packets, DEVICES.md 4.1): tests that start one must be serialised with each other and
/// with any `arv-fake-gv-camera-0.8`.
pub struct FakeAnalyzerCamera {
    camera: Option<AravisCamera>,
    fake: ::aravis::FakeCamera,
    gv: ::aravis::GvFakeCamera,
    /// Read by the fill callback until `Drop` unregisters it; dropped last.
    state: Box<FillState>,
}

impl std::fmt::Debug for FakeAnalyzerCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FakeAnalyzerCamera")
            .field("camera", &self.camera)
            .finish_non_exhaustive()
    }
}

impl FakeAnalyzerCamera {
    /// Starts the fake with this serial number (the id is `Aravis-Fake-<serial>`), looking at
    /// `scene` through an analyzer whose angle (radians) `analyzer_rad` returns, and opens it.
    /// The angle source is called once per frame, on Aravis's fake-camera thread.
    pub fn start(
        serial: &str,
        scene: AnalyzerScene,
        analyzer_rad: impl Fn() -> f64 + Send + Sync + 'static,
    ) -> Result<FakeAnalyzerCamera, AravisError> {
        let gv = ::aravis::GvFakeCamera::new(Some(FAKE_INTERFACE), Some(serial));
        if !gv.is_running() {
            return Err(AravisError::Fake(format!(
                "the in-process fake GigE camera did not start on {FAKE_INTERFACE}"
            )));
        }
        let fake = gv
            .fake_camera()
            .ok_or_else(|| AravisError::Fake(String::from("the fake GigE camera has no camera")))?;
        let state = Box::new(FillState {
            analyzer_rad: Box::new(analyzer_rad),
            scene: Mutex::new(scene),
            frames: AtomicU64::new(0),
        });
        set_fill_pattern(&fake, Some(&state));
        let mut this = FakeAnalyzerCamera {
            camera: None,
            fake,
            gv,
            state,
        };
        let id = format!("Aravis-Fake-{serial}");
        let t0 = Instant::now();
        let mut camera = loop {
            match AravisCamera::open_with(&id, AravisOptions::default()) {
                Ok(c) => break c,
                Err(e) if t0.elapsed() < OPEN_DEADLINE => {
                    tracing::debug!(error = %e, "fake camera not reachable yet");
                    std::thread::sleep(Duration::from_millis(100));
                }
                Err(e) => return Err(e),
            }
        };
        camera.set_pixel_format(PixelFormat::Mono16)?;
        this.camera = Some(camera);
        Ok(this)
    }

    /// The opened camera, for settings outside [`BlockingCamera`] (frame rate).
    pub fn camera(&mut self) -> Result<&mut AravisCamera, DeviceError> {
        self.camera.as_mut().ok_or_else(closed)
    }

    /// Changes the scene from the next frame on.
    pub fn set_scene(&self, scene: AnalyzerScene) {
        *self.state.scene.lock().unwrap_or_else(|p| p.into_inner()) = scene;
    }

    /// Drops this share of the stream's packets from now on (0 to 1), as a lossy network would.
    pub fn set_packet_loss(&self, ratio: f64) {
        self.gv.set_gvsp_lost_ratio(ratio.clamp(0.0, 1.0));
    }

    /// Frames the fake has filled so far.
    pub fn frames_filled(&self) -> u64 {
        self.state.frames.load(Ordering::Relaxed)
    }
}

fn closed() -> DeviceError {
    DeviceError::new(
        polar_hal::ErrorKind::Disconnected,
        "fake",
        "the fake camera is closed",
    )
}

impl Drop for FakeAnalyzerCamera {
    fn drop(&mut self) {
        // Stop the client first, then give the fake its own pattern back before `state` goes.
        self.camera = None;
        set_fill_pattern(&self.fake, None);
    }
}

/// Registers (or, with `None`, unregisters) [`fill_analyzer`] with `state` on the fake camera.
#[allow(unsafe_code)]
fn set_fill_pattern(fake: &::aravis::FakeCamera, state: Option<&FillState>) {
    let ptr: *mut aravis_sys::ArvFakeCamera = fake.to_glib_none().0;
    match state {
        // SAFETY: `ptr` is a live ArvFakeCamera (borrowed from `fake`). The data pointer is
        // the address of a `FillState` in a `Box` owned by the `FakeAnalyzerCamera`, which
        // unregisters the callback (below) in its `Drop` before the box is freed; Aravis calls
        // the callback under the same mutex that `arv_fake_camera_set_fill_pattern` takes, so
        // after unregistering no call can still be using the state. `FillState` is `Sync`,
        // and the callback only reads it through a shared reference.
        Some(state) => unsafe {
            aravis_sys::arv_fake_camera_set_fill_pattern(
                ptr,
                Some(fill_analyzer),
                state as *const FillState as *mut c_void,
            )
        },
        // SAFETY: `ptr` is a live ArvFakeCamera; a NULL callback restores Aravis's own pattern.
        None => unsafe {
            aravis_sys::arv_fake_camera_set_fill_pattern(ptr, None, std::ptr::null_mut())
        },
    }
}

/// Aravis's fill-pattern callback: writes the scene's pixel value for the current analyzer
/// angle into every pixel of a Mono8 or Mono16 buffer; other formats are left as they are.
#[allow(unsafe_code)]
unsafe extern "C" fn fill_analyzer(
    buffer: *mut aravis_sys::ArvBuffer,
    data: *mut c_void,
    exposure_us: u32,
    _gain: u32,
    pixel_format: aravis_sys::ArvPixelFormat,
) {
    if buffer.is_null() || data.is_null() {
        return;
    }
    let format = match pixel_format {
        aravis_sys::ARV_PIXEL_FORMAT_MONO_8 => PixelFormat::Mono8,
        aravis_sys::ARV_PIXEL_FORMAT_MONO_16 => PixelFormat::Mono16,
        _ => return,
    };
    // SAFETY: `data` is the `FillState` registered by `set_fill_pattern`, alive until it is
    // unregistered (see there).
    let state = unsafe { &*(data as *const FillState) };
    // SAFETY: `buffer` is the live ArvBuffer Aravis is filling; its image width and height were
    // set from the camera's registers just before this call.
    let (width, height) = unsafe {
        (
            aravis_sys::arv_buffer_get_image_width(buffer),
            aravis_sys::arv_buffer_get_image_height(buffer),
        )
    };
    let (Ok(width), Ok(height)) = (usize::try_from(width), usize::try_from(height)) else {
        return;
    };
    let bytes = width * height * crate::frame::bytes_per_pixel(format);
    let mut size = 0usize;
    // SAFETY: as above; the size reported here is the received size, still 0 while filling
    // (DEVICES.md 4.2), so the length comes from the image size instead.
    let ptr = unsafe { aravis_sys::arv_buffer_get_data(buffer, &mut size) };
    if ptr.is_null() || bytes == 0 {
        return;
    }
    // A panicking angle source must not unwind into C: the frame reads 0 instead.
    let value = catch_unwind(AssertUnwindSafe(|| state.pixel(exposure_us, format))).unwrap_or(0);
    // SAFETY: Aravis's fake camera checks that the buffer holds the whole payload (width x
    // height x bytes per pixel of the registers it just read) before calling the fill pattern,
    // and marks it SizeMismatch without calling us otherwise; no other reference to the data
    // exists while the callback runs.
    let pixels = unsafe { std::slice::from_raw_parts_mut(ptr, bytes) };
    match format {
        PixelFormat::Mono16 | PixelFormat::Mono12 => {
            let le = value.to_le_bytes();
            for pair in pixels.chunks_exact_mut(2) {
                pair.copy_from_slice(&le);
            }
        }
        PixelFormat::Mono8 => pixels.fill(u8::try_from(value).unwrap_or(u8::MAX)),
    }
    state.frames.fetch_add(1, Ordering::Relaxed);
}

impl BlockingCamera for FakeAnalyzerCamera {
    fn info(&self) -> CameraInfo {
        match &self.camera {
            Some(c) => c.info(),
            None => CameraInfo {
                id: String::from("fake"),
                vendor: String::new(),
                model: String::new(),
                serial: String::new(),
                sensor_width: 0,
                sensor_height: 0,
                exposure_range_us: [0.0, 0.0],
                gain_range: [0.0, 0.0],
                gain_unit: polar_hal::GainUnit::Raw,
                formats: Vec::new(),
            },
        }
    }
    fn set_exposure_us(&mut self, exposure_us: f64) -> Result<f64, DeviceError> {
        self.camera()?.set_exposure_us(exposure_us)
    }
    fn set_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
        self.camera()?.set_gain(gain)
    }
    fn set_pixel_format(&mut self, format: PixelFormat) -> Result<(), DeviceError> {
        self.camera()?.set_pixel_format(format)
    }
    fn set_roi(&mut self, roi: Roi) -> Result<Roi, DeviceError> {
        self.camera()?.set_roi(roi)
    }
    fn set_trigger(&mut self, mode: TriggerMode) -> Result<(), DeviceError> {
        self.camera()?.set_trigger(mode)
    }
    fn supports_hardware_trigger(&self) -> bool {
        self.camera
            .as_ref()
            .is_some_and(|c| c.supports_hardware_trigger())
    }
    fn start(&mut self) -> Result<(), DeviceError> {
        self.camera()?.start()
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        self.camera()?.stop()
    }
    fn trigger(&mut self) -> Result<(), DeviceError> {
        self.camera()?.trigger()
    }
    fn wait_frame(&mut self, wait: Duration) -> Result<Grabbed, DeviceError> {
        self.camera()?.wait_frame(wait)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Malus's law on the polarized part: the analyzer along the AoP passes S0 (1 + p) / 2,
    /// across it S0 (1 - p) / 2, at 45 degrees S0 / 2; intensity is proportional to exposure
    /// and clipped at full scale.
    #[test]
    fn scene_follows_malus() {
        let s = AnalyzerScene {
            s0_full_scale: 0.5,
            dolp: 0.4,
            aop_rad: 0.3,
            reference_exposure_us: 1000.0,
        };
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        assert!(close(s.intensity(0.3, 1000.0), 0.5 * 1.4 / 2.0));
        assert!(close(
            s.intensity(0.3 + std::f64::consts::FRAC_PI_2, 1000.0),
            0.5 * 0.6 / 2.0
        ));
        assert!(close(
            s.intensity(0.3 + std::f64::consts::FRAC_PI_4, 2000.0),
            0.5
        ));
        assert_eq!(s.pixel(0.3, 1000.0, PixelFormat::Mono16), 22937); // 0.35 * 65535 = 22937.25
        assert_eq!(s.pixel(0.3, 1e6, PixelFormat::Mono8), 255);
    }
}
