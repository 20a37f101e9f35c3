//! GenICam cameras (GigE Vision, USB3 Vision) through [Aravis](https://github.com/AravisProject/aravis),
//! as a [`polar_hal::BlockingCamera`] (`ARCHITECTURE.md`, "Device abstraction";
//! `docs/DEVICES.md` sections 3.3, 4.1, 4.2 and 5.2).
//!
//! * [`list`] discovers cameras (id, vendor, model, serial, address); [`AravisCamera::open`]
//!   opens one by id.
//! * Exposure and gain go through Aravis's high-level calls, with fallbacks over the SFNC
//!   feature names (`ExposureTime` / `ExposureTimeAbs`, `Gain` / `GainRaw`), and every setting
//!   is read back.
//! * Frames stream through a pool of buffers. Every buffer's status is checked before anything
//!   reads its image; incomplete buffers are reported as [`polar_hal::Grabbed::Incomplete`] and
//!   every buffer goes back to the pool. Frame ids are unwrapped across the 16-bit GigE Vision
//!   wrap ([`FrameIdUnwrapper`]).
//! * A camera that goes away is reported as [`polar_hal::ErrorKind::Disconnected`]: Aravis's
//!   `control-lost` signal, or a stream silent for [`AravisOptions::silence_before_probe`]
//!   followed by a register read that fails.
//!
//! Run it on its own thread with `polar_hal::camera_thread::ThreadedCamera` to get an async
//! [`polar_hal::Camera`]. With the `fake` feature, [`FakeAnalyzerCamera`] runs Aravis's fake
//! GigE Vision camera inside the process, with an image that follows an analyzer angle.
//!
//! This crate needs the system's libaravis (Debian: `libaravis-dev libusb-1.0-0-dev`); its tests
//! also need `arv-fake-gv-camera-0.8` (Debian: `aravis-tools`). See the README.
#![warn(missing_docs)]

mod camera;
#[cfg(feature = "fake")]
mod fake;
mod frame;

pub use camera::{AravisCamera, AravisOptions};
#[cfg(feature = "fake")]
pub use fake::{AnalyzerScene, FakeAnalyzerCamera};
pub use frame::{bytes_per_pixel, pixels_from_bytes, FrameIdUnwrapper};

use aravis::glib;
use polar_hal::{DeviceError, ErrorKind};
use std::sync::{Mutex, MutexGuard, OnceLock};

/// Errors outside the camera trait: discovery, opening, the fake camera.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AravisError {
    /// Something else in this process called `aravis::Aravis::initialize` (allowed once per
    /// process), so this crate cannot hold Aravis's global state.
    #[error("Aravis was already initialised elsewhere in this process: only one owner of aravis::Aravis::initialize is allowed, use polar_camera_aravis::list")]
    AlreadyInitialized,
    /// An Aravis call failed.
    #[error("{device}: {kind}: {what}: {message}")]
    Sdk {
        /// The camera id (or `aravis` for library-wide calls).
        device: String,
        /// What was being done.
        what: String,
        /// The shared kind.
        kind: ErrorKind,
        /// Aravis's message.
        message: String,
    },
    /// The in-process fake camera could not start.
    #[error("fake camera: {0}")]
    Fake(String),
}

impl AravisError {
    /// The shared kind of this error.
    pub fn kind(&self) -> ErrorKind {
        match self {
            AravisError::AlreadyInitialized | AravisError::Fake(_) => ErrorKind::Other,
            AravisError::Sdk { kind, .. } => *kind,
        }
    }
}

impl From<AravisError> for DeviceError {
    fn from(e: AravisError) -> Self {
        match &e {
            AravisError::Sdk {
                device,
                kind,
                what,
                message,
            } => DeviceError::new(*kind, device, format!("{what}: {message}")),
            _ => DeviceError::new(e.kind(), "aravis", e.to_string()),
        }
    }
}

impl From<DeviceError> for AravisError {
    fn from(e: DeviceError) -> Self {
        AravisError::Sdk {
            kind: e.kind(),
            device: e.device,
            what: String::from("camera"),
            message: e.message,
        }
    }
}

/// The shared kind of an Aravis error, from its domain and code.
pub(crate) fn error_kind(e: &glib::Error) -> ErrorKind {
    use aravis::DeviceError as D;
    use aravis::GcError as G;
    if let Some(code) = e.kind::<D>() {
        match code {
            D::Timeout => ErrorKind::Timeout,
            D::NotConnected | D::NotFound => ErrorKind::Disconnected,
            D::ProtocolError
            | D::TransferError
            | D::ProtocolErrorNotImplemented
            | D::ProtocolErrorInvalidParameter => ErrorKind::Protocol,
            D::FeatureNotFound | D::WrongFeature | D::InvalidParameter => ErrorKind::OutOfRange,
            D::NotController => ErrorKind::Busy,
            _ => ErrorKind::Other,
        }
    } else if let Some(code) = e.kind::<G>() {
        match code {
            G::OutOfRange | G::EnumEntryNotFound | G::NodeNotFound | G::ReadOnly => {
                ErrorKind::OutOfRange
            }
            _ => ErrorKind::Protocol,
        }
    } else {
        ErrorKind::Other
    }
}

/// Whether an Aravis error says that a feature does not exist on this camera (so that another
/// SFNC name may be tried), rather than that the device refused or did not answer.
pub(crate) fn is_not_found(e: &glib::Error) -> bool {
    matches!(
        e.kind::<aravis::DeviceError>(),
        Some(aravis::DeviceError::FeatureNotFound | aravis::DeviceError::WrongFeature)
    ) || matches!(
        e.kind::<aravis::GcError>(),
        Some(aravis::GcError::NodeNotFound | aravis::GcError::PropertyNotDefined)
    )
}

/// A [`DeviceError`] from an Aravis error, naming what was being done.
pub(crate) fn sdk_error(device: &str, what: &str, e: &glib::Error) -> DeviceError {
    DeviceError::new(error_kind(e), device, format!("{what}: {}", e.message()))
}

/// Aravis's global state (the device list), initialised once per process and used under a lock:
/// `arv_update_device_list` and opening a device both touch it.
static ARAVIS: OnceLock<Option<Mutex<aravis::Aravis>>> = OnceLock::new();

/// The lock over Aravis's global state.
pub(crate) fn aravis() -> Result<MutexGuard<'static, aravis::Aravis>, AravisError> {
    let cell = ARAVIS.get_or_init(|| aravis::Aravis::initialize().ok().map(Mutex::new));
    match cell {
        // A panic while listing leaves nothing half-done that matters: keep going.
        Some(m) => Ok(m.lock().unwrap_or_else(|p| p.into_inner())),
        None => Err(AravisError::AlreadyInitialized),
    }
}

/// A camera found by discovery.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiscoveredCamera {
    /// The id to open it by ([`AravisCamera::open`]), e.g. `Aravis-Fake-GV01`.
    pub id: String,
    /// Vendor.
    pub vendor: String,
    /// Model.
    pub model: String,
    /// Serial number (empty if the transport does not report one).
    pub serial: String,
    /// Network address (GigE Vision) or empty / bus address (USB3 Vision).
    pub address: String,
    /// Transport: `GigEVision`, `USB3Vision`, `Fake`.
    pub protocol: String,
    /// Physical id (MAC address for GigE Vision).
    pub physical_id: String,
}

/// Discovers the cameras reachable now (GigE Vision discovery broadcasts on every interface and
/// takes about a second; USB3 Vision enumerates the bus).
pub fn list() -> Result<Vec<DiscoveredCamera>, AravisError> {
    let ar = aravis()?;
    let devices = ar.get_device_list();
    Ok(devices
        .iter()
        .enumerate()
        .map(|(index, d)| DiscoveredCamera {
            id: d.id.to_string_lossy().into_owned(),
            vendor: d.vendor.to_string_lossy().into_owned(),
            model: d.model.to_string_lossy().into_owned(),
            serial: u32::try_from(index)
                .map(|i| listed_serial(&ar, i))
                .unwrap_or_default(),
            address: d.address.to_string_lossy().into_owned(),
            protocol: d.protocol.to_string_lossy().into_owned(),
            physical_id: d.physical_id.to_string_lossy().into_owned(),
        })
        .collect())
}

/// The serial number of entry `index` of the device list that `get_device_list` just made
/// (aravis-rs does not expose it). Taking the token proves the caller holds the Aravis lock, so
/// the list cannot be updated while the string is copied.
#[allow(unsafe_code)]
fn listed_serial(_locked: &aravis::Aravis, index: u32) -> String {
    // SAFETY: `arv_get_device_serial_nbr` reads Aravis's global device list, which only
    // `arv_update_device_list` changes; the caller holds the lock under which this crate makes
    // every such update, and `index` is below the length of the list just read. The result is
    // NULL (index out of range) or a NUL-terminated string owned by the list, copied before the
    // lock is released.
    unsafe {
        let p = aravis_sys::arv_get_device_serial_nbr(index);
        if p.is_null() {
            String::new()
        } else {
            std::ffi::CStr::from_ptr(p).to_string_lossy().into_owned()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Aravis's error codes map onto the shared kinds the engine acts on: timeouts retry, a
    /// lost device reconnects, a missing feature is out of range.
    #[test]
    fn error_kinds() {
        let e = glib::Error::new(
            aravis::DeviceError::Timeout,
            "GigEVision read_register timeout",
        );
        assert_eq!(error_kind(&e), ErrorKind::Timeout);
        assert!(!is_not_found(&e));
        let e = glib::Error::new(aravis::DeviceError::FeatureNotFound, "[Gain] Not found");
        assert_eq!(error_kind(&e), ErrorKind::OutOfRange);
        assert!(is_not_found(&e));
        let e = glib::Error::new(aravis::DeviceError::NotFound, "Device 'x' not found");
        assert_eq!(error_kind(&e), ErrorKind::Disconnected);
        let e = glib::Error::new(aravis::GcError::OutOfRange, "value out of range");
        assert_eq!(error_kind(&e), ErrorKind::OutOfRange);
        let d = sdk_error("cam", "set exposure", &e);
        assert_eq!(d.message, "set exposure: value out of range");
        assert_eq!(d.kind(), ErrorKind::OutOfRange);
    }
}
