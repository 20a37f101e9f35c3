//! Enumeration and selection of UVC cameras by name or bus info, never by position.
//!
//! What "bus info" is differs by platform: on Linux the V4L2 `bus_info` (`usb-0000:00:14.0-1`,
//! read with `VIDIOC_QUERYCAP` on the node); on Windows the Media Foundation symbolic link
//! (`\\?\usb#vid_046d&pid_0825&mi_00#...`, which names the USB vendor, product and port
//! instance); on macOS the AVFoundation unique id (which carries the USB location id). A spec is
//! `uvc:<bus info>` or `uvc:<name>` (the `uvc:` prefix is optional): an exact bus info wins;
//! otherwise the one device whose name contains the text, case-insensitively. nokhwa's
//! numeric index is kept only to open the device found; it is never accepted as a spec, so a
//! replugged or reordered camera is never silently swapped for another.

use nokhwa::utils::{ApiBackend, CameraIndex};
use polar_hal::{DeviceError, ErrorKind};
use std::panic::{catch_unwind, AssertUnwindSafe};

/// One camera nokhwa can open.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UvcDeviceInfo {
    /// nokhwa's index (the `/dev/videoN` number on Linux, the enumeration position elsewhere):
    /// used to open the device found, never accepted as a spec.
    pub index: CameraIndex,
    /// The name the platform reports (V4L2 card, Media Foundation friendly name, AVFoundation
    /// localized name).
    pub name: String,
    /// nokhwa's description (the node path on Linux, "MediaFoundation Camera" on Windows, the
    /// device type on macOS).
    pub description: String,
    /// The bus info (see the module docs); may be empty where the platform gives none.
    pub bus_info: String,
}

impl UvcDeviceInfo {
    /// The spec that reopens this device: its bus info when it has one, else its name.
    pub fn spec(&self) -> String {
        if self.bus_info.is_empty() {
            format!("uvc:{}", self.name)
        } else {
            format!("uvc:{}", self.bus_info)
        }
    }
}

impl std::fmt::Display for UvcDeviceInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} (bus info \"{}\", {})",
            self.name, self.bus_info, self.description
        )
    }
}

/// The text of a caught panic.
pub(crate) fn panic_text(payload: &(dyn std::any::Any + Send)) -> String {
    polar_frame_convert::panic_message(payload)
}

/// The capture devices nokhwa finds on this platform. On Linux, nodes without video capture
/// (the UVC driver's metadata nodes) are left out and each device's bus info is read from the
/// node. A panic inside nokhwa or `v4l` (both unwrap on some malformed replies) becomes an
/// error of kind [`ErrorKind::Other`].
pub fn list() -> Result<Vec<UvcDeviceInfo>, DeviceError> {
    let found = catch_unwind(AssertUnwindSafe(|| nokhwa::query(ApiBackend::Auto)))
        .map_err(|p| {
            DeviceError::new(
                ErrorKind::Other,
                "uvc",
                format!("camera enumeration panicked: {}", panic_text(p.as_ref())),
            )
        })?
        .map_err(|e| {
            DeviceError::new(
                ErrorKind::Other,
                "uvc",
                format!("camera enumeration failed: {e}"),
            )
        })?;
    let mut devices = Vec::with_capacity(found.len());
    for info in found {
        let mut device = UvcDeviceInfo {
            index: info.index().clone(),
            name: info.human_name(),
            description: info.description().to_string(),
            bus_info: info.misc(),
        };
        if cfg!(target_os = "linux") {
            match linux_bus_info(&device.index) {
                Some(Some(bus)) => device.bus_info = bus,
                Some(None) => continue, // not a capture node
                None => {}              // unreadable: keep it, without bus info
            }
        }
        devices.push(device);
    }
    devices.sort_by(|a, b| (&a.name, &a.bus_info).cmp(&(&b.name, &b.bus_info)));
    Ok(devices)
}

/// On Linux, a node's bus info: `Some(Some(bus))` for a capture node, `Some(None)` for a node
/// that does not capture video, `None` when the node cannot be queried.
#[cfg(target_os = "linux")]
fn linux_bus_info(index: &CameraIndex) -> Option<Option<String>> {
    let n = index.as_index().ok()?;
    catch_unwind(|| {
        let device = v4l::Device::new(n as usize).ok()?;
        let caps = device.query_caps().ok()?;
        Some(
            caps.capabilities
                .contains(v4l::capability::Flags::VIDEO_CAPTURE)
                .then_some(caps.bus),
        )
    })
    .ok()
    .flatten()
}

#[cfg(not(target_os = "linux"))]
fn linux_bus_info(_index: &CameraIndex) -> Option<Option<String>> {
    None
}

/// What was found, for error messages.
fn describe(devices: &[UvcDeviceInfo]) -> String {
    if devices.is_empty() {
        "found: no camera".to_string()
    } else {
        let all: Vec<String> = devices.iter().map(ToString::to_string).collect();
        format!("found: {}", all.join("; "))
    }
}

/// The device a spec names (see the module docs). Errors: an empty spec
/// ([`ErrorKind::OutOfRange`]), nothing matches ([`ErrorKind::Disconnected`]: plugging the
/// camera in fixes it), a name matching several devices ([`ErrorKind::OutOfRange`]); each
/// message lists what was found.
pub fn select<'a>(
    spec: &str,
    devices: &'a [UvcDeviceInfo],
) -> Result<&'a UvcDeviceInfo, DeviceError> {
    let trimmed = spec.trim();
    let key = match trimmed.get(..4) {
        Some(prefix) if prefix.eq_ignore_ascii_case("uvc:") => trimmed[4..].trim(),
        _ => trimmed,
    };
    if key.is_empty() {
        return Err(DeviceError::new(
            ErrorKind::OutOfRange,
            spec,
            format!(
                "empty UVC camera spec: give a bus info or a name (the first camera is never \
                 taken by default); {}",
                describe(devices)
            ),
        ));
    }
    if let Some(d) = devices
        .iter()
        .find(|d| !d.bus_info.is_empty() && d.bus_info.eq_ignore_ascii_case(key))
    {
        return Ok(d);
    }
    let needle = key.to_lowercase();
    let named: Vec<&UvcDeviceInfo> = devices
        .iter()
        .filter(|d| d.name.to_lowercase().contains(&needle))
        .collect();
    match named.as_slice() {
        [one] => Ok(one),
        [] => Err(DeviceError::new(
            ErrorKind::Disconnected,
            spec,
            format!(
                "no UVC camera has bus info \"{key}\" or a name containing it; {}",
                describe(devices)
            ),
        )),
        several => Err(DeviceError::new(
            ErrorKind::OutOfRange,
            spec,
            format!(
                "\"{key}\" matches {} cameras: {}; name one by its bus info",
                several.len(),
                several
                    .iter()
                    .map(|d| d.to_string())
                    .collect::<Vec<_>>()
                    .join("; ")
            ),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn device(index: u32, name: &str, bus: &str) -> UvcDeviceInfo {
        UvcDeviceInfo {
            index: CameraIndex::Index(index),
            name: name.to_string(),
            description: format!("Video4Linux Device @ /dev/video{index}"),
            bus_info: bus.to_string(),
        }
    }

    fn two_webcams() -> Vec<UvcDeviceInfo> {
        vec![
            device(0, "HD Pro Webcam C920", "usb-0000:00:14.0-1"),
            device(2, "HD Pro Webcam C920", "usb-0000:00:14.0-2"),
            device(4, "Integrated Camera", "usb-0000:00:14.0-8"),
        ]
    }

    /// A bus info picks exactly that device (even when two share a name); a unique name part
    /// picks its device, case-insensitively, with or without the `uvc:` prefix.
    #[test]
    fn selects_by_bus_info_or_unique_name() {
        let devices = two_webcams();
        let d = select("uvc:usb-0000:00:14.0-2", &devices).expect("by bus info");
        assert_eq!(d.index, CameraIndex::Index(2));
        let d = select("  integrated ", &devices).expect("by name");
        assert_eq!(d.index, CameraIndex::Index(4));
        assert_eq!(
            select(&d.spec(), &devices).expect("its own spec").index,
            CameraIndex::Index(4)
        );
    }

    /// Never "the first camera": an empty spec, an ambiguous name, a missing camera and a bare
    /// index are refused, each listing what exists.
    #[test]
    fn never_takes_a_camera_by_position() {
        let devices = two_webcams();
        let e = select("uvc:", &devices).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.contains("never taken by default"), "{e}");
        assert!(e.message.contains("Integrated Camera"), "{e}");

        let e = select("C920", &devices).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.contains("matches 2 cameras"), "{e}");
        assert!(e.message.contains("usb-0000:00:14.0-1"), "{e}");

        // "4" is the nokhwa index of the Integrated Camera, and is not taken as one.
        let e = select("4", &devices).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(e.message.contains("found: HD Pro Webcam C920"), "{e}");

        let e = select("uvc:Logitech", &[]).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(e.message.ends_with("found: no camera"), "{e}");
    }

    /// A device with no bus info is reopened by name, and an empty bus info never matches.
    #[test]
    fn empty_bus_info_falls_back_to_the_name() {
        let devices = vec![device(0, "FaceTime HD Camera", "")];
        assert_eq!(devices[0].spec(), "uvc:FaceTime HD Camera");
        assert!(select(&devices[0].spec(), &devices).is_ok());
    }

    /// Enumeration on this machine returns (CI has no camera: an empty list) without a panic,
    /// and every device listed has a name.
    #[test]
    fn enumeration_does_not_fail() {
        let devices = list().expect("enumeration");
        for d in &devices {
            assert!(!d.name.is_empty(), "{d}");
        }
    }
}
