//! Finding V4L2 capture devices, and choosing one by name, bus info or path (never "the first").
//!
//! [`list`] opens every `/dev/videoN` node, asks it what it is (`VIDIOC_QUERYCAP`: card name,
//! driver, bus info, capabilities) and which capture formats it offers (`VIDIOC_ENUM_FMT`), and
//! keeps the video capture nodes. A UVC webcam usually has two nodes, one for video and one
//! for metadata; the metadata node is skipped with the reason. On a machine with no video
//! device (CI, this container) the list is empty, not an error.
//!
//! [`select`] picks one device by a spec, so that a v4l2loopback device or a second camera
//! taking `/dev/video0` is never opened by accident (DEVICES.md 3.2, nokhwa #47):
//!
//! * a path: `/dev/video2`, or a stable link such as `/dev/v4l/by-id/usb-...-video-index0`;
//! * a bus info, exactly as `v4l2-ctl --list-devices` prints it in parentheses:
//!   `usb-0000:00:14.0-1`, `platform:vivid-000`;
//! * a card name: a case-insensitive substring of it, `HD Pro Webcam`.
//!
//! Each may be written with a `v4l:` prefix (`v4l:HD Pro Webcam`). They are tried in that order.
//! A spec matching nothing, or a name matching several devices, is an error that lists what was
//! found.

use crate::sys::guarded;
use linuxvideo::{BufType, CapabilityFlags, Device};
use polar_hal::{DeviceError, ErrorKind};
use std::fmt;
use std::os::unix::fs::FileTypeExt;
use std::path::{Path, PathBuf};

/// One V4L2 video capture node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct V4lDeviceInfo {
    /// Its device node, `/dev/videoN`.
    pub path: PathBuf,
    /// The card name the driver reports (`VIDIOC_QUERYCAP` `card`), e.g. `HD Pro Webcam C920`.
    pub card: String,
    /// The driver, e.g. `uvcvideo`, `vivid`, `v4l2 loopback`.
    pub driver: String,
    /// Where it is attached, e.g. `usb-0000:00:14.0-1`: stable for a given port.
    pub bus_info: String,
    /// The capture formats it offers, as fourcc codes (`YUYV`, `MJPG`, `GREY`, `Y16`, ...).
    pub fourccs: Vec<String>,
}

impl fmt::Display for V4lDeviceInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} \"{}\" (driver {}, bus {}) formats [{}]",
            self.path.display(),
            self.card,
            self.driver,
            self.bus_info,
            self.fourccs.join(", ")
        )
    }
}

/// A `/dev/videoN` node that is not listed, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    /// The node.
    pub path: PathBuf,
    /// Why it is not a usable capture device (metadata node, permission denied, ...).
    pub reason: String,
}

/// What a scan found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Listing {
    /// The video capture devices, in node-number order.
    pub devices: Vec<V4lDeviceInfo>,
    /// The other `videoN` nodes.
    pub skipped: Vec<Skipped>,
}

impl Listing {
    /// One line per device and per skipped node, or a sentence saying there is none.
    pub fn describe(&self) -> String {
        if self.devices.is_empty() && self.skipped.is_empty() {
            return "no /dev/video* node on this machine".to_string();
        }
        let mut lines: Vec<String> = self.devices.iter().map(|d| d.to_string()).collect();
        if self.devices.is_empty() {
            lines.push("no video capture device".to_string());
        }
        lines.extend(
            self.skipped
                .iter()
                .map(|s| format!("{} skipped: {}", s.path.display(), s.reason)),
        );
        lines.join("; ")
    }
}

/// Every V4L2 video capture device on this machine (`/dev/video*`). Empty, not an error, when
/// there is none.
pub fn list() -> Result<Vec<V4lDeviceInfo>, DeviceError> {
    Ok(scan(Path::new("/dev"))?.devices)
}

/// The `videoN` nodes in `dir` (normally `/dev`): the capture devices and the others with the
/// reason each was skipped. A missing `dir` gives an empty listing.
pub fn scan(dir: &Path) -> Result<Listing, DeviceError> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Listing::default()),
        Err(e) => {
            return Err(DeviceError::new(
                ErrorKind::Other,
                dir.display().to_string(),
                format!("cannot list V4L2 devices: {e}"),
            ))
        }
    };
    let mut nodes: Vec<(u32, PathBuf)> = entries
        .filter_map(Result::ok)
        .filter_map(|entry| {
            let name = entry.file_name();
            let number = name.to_str()?.strip_prefix("video")?.parse::<u32>().ok()?;
            Some((number, entry.path()))
        })
        .collect();
    nodes.sort();
    let mut listing = Listing::default();
    for (_, path) in nodes {
        match probe(&path) {
            Ok(info) => listing.devices.push(info),
            Err(reason) => {
                tracing::debug!(node = %path.display(), %reason, "V4L2 node skipped");
                listing.skipped.push(Skipped { path, reason });
            }
        }
    }
    Ok(listing)
}

/// Opens one node and asks what it is; `Err(reason)` when it is not a usable capture device.
fn probe(path: &Path) -> Result<V4lDeviceInfo, String> {
    // `metadata` follows links, as opening does.
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot stat: {e}"))?;
    if !meta.file_type().is_char_device() {
        return Err("not a character device".to_string());
    }
    let id = path.display().to_string();
    let (card, driver, bus_info, caps, fourccs) = guarded(&id, "query the device", || {
        let device = Device::open(path)?;
        let caps = device.capabilities()?;
        let mut fourccs = Vec::new();
        // A bounded walk: a driver that never ends the list must not hang the scan.
        for desc in device.formats(BufType::VIDEO_CAPTURE).take(256) {
            match desc {
                Ok(desc) => fourccs.push(fourcc_text(desc.pixel_format().as_fourcc())),
                // Not a capture node: it has no capture formats.
                Err(_) => break,
            }
        }
        Ok((
            caps.card().to_string(),
            caps.driver().to_string(),
            caps.bus_info().to_string(),
            caps.device_capabilities(),
            fourccs,
        ))
    })
    .map_err(|e| e.message)?;
    if !caps.contains(CapabilityFlags::VIDEO_CAPTURE) {
        let what = if caps.contains(CapabilityFlags::VIDEO_CAPTURE_MPLANE) {
            "a multi-planar capture node (not supported by this backend)"
        } else {
            "not a video capture node (metadata, output or codec)"
        };
        return Err(format!("\"{card}\" (driver {driver}) is {what}"));
    }
    Ok(V4lDeviceInfo {
        path: path.to_path_buf(),
        card,
        driver,
        bus_info,
        fourccs,
    })
}

/// A fourcc code as text, trailing spaces kept out (`Y16 ` is shown as `Y16`); bytes that are
/// not printable ASCII are shown as `?`.
pub(crate) fn fourcc_text(code: [u8; 4]) -> String {
    code.iter()
        .map(|&b| {
            if b.is_ascii_graphic() || b == b' ' {
                char::from(b)
            } else {
                '?'
            }
        })
        .collect::<String>()
        .trim_end()
        .to_string()
}

/// The device a spec names (see the module docs for the forms). Errors: an empty spec
/// ([`ErrorKind::OutOfRange`]), nothing matches ([`ErrorKind::Disconnected`]: plugging the
/// device in fixes it), a name matching several devices ([`ErrorKind::OutOfRange`]); each
/// message lists what was found.
pub fn select<'a>(spec: &str, listing: &'a Listing) -> Result<&'a V4lDeviceInfo, DeviceError> {
    let trimmed = spec.trim();
    let key = match trimmed.get(..4) {
        Some(prefix) if prefix.eq_ignore_ascii_case("v4l:") => trimmed[4..].trim(),
        _ => trimmed,
    };
    let found = || format!("found: {}", listing.describe());
    if key.is_empty() {
        return Err(DeviceError::new(
            ErrorKind::OutOfRange,
            spec,
            format!(
                "empty V4L2 device spec: give a /dev path, a bus info or a card name \
                 (the first device is never taken by default); {}",
                found()
            ),
        ));
    }
    if key.starts_with('/') {
        let wanted = canonical(Path::new(key));
        return listing
            .devices
            .iter()
            .find(|d| canonical(&d.path) == wanted)
            .ok_or_else(|| {
                DeviceError::new(
                    ErrorKind::Disconnected,
                    spec,
                    format!("no V4L2 capture device at {key}; {}", found()),
                )
            });
    }
    if let Some(d) = listing.devices.iter().find(|d| d.bus_info == key) {
        return Ok(d);
    }
    let needle = key.to_lowercase();
    let named: Vec<&V4lDeviceInfo> = listing
        .devices
        .iter()
        .filter(|d| d.card.to_lowercase().contains(&needle))
        .collect();
    match named.as_slice() {
        [one] => Ok(one),
        [] => Err(DeviceError::new(
            ErrorKind::Disconnected,
            spec,
            format!(
                "no V4L2 capture device has bus info \"{key}\" or a card name containing it; {}",
                found()
            ),
        )),
        several => Err(DeviceError::new(
            ErrorKind::OutOfRange,
            spec,
            format!(
                "\"{key}\" matches {} devices: {}; name one by its bus info or path",
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

/// The path with links resolved, or as given when it cannot be resolved.
fn canonical(path: &Path) -> PathBuf {
    std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dev(n: u32, card: &str, bus: &str) -> V4lDeviceInfo {
        V4lDeviceInfo {
            path: PathBuf::from(format!("/nonexistent-test-dev/video{n}")),
            card: card.into(),
            driver: "uvcvideo".into(),
            bus_info: bus.into(),
            fourccs: vec!["YUYV".into(), "MJPG".into()],
        }
    }

    fn listing() -> Listing {
        Listing {
            devices: vec![
                dev(
                    0,
                    "Dummy video device (0x0000)",
                    "platform:v4l2loopback-000",
                ),
                dev(2, "HD Pro Webcam C920", "usb-0000:00:14.0-1"),
                dev(4, "HD Pro Webcam C920", "usb-0000:00:14.0-2"),
                dev(6, "Polarimeter Mono Cam", "usb-0000:00:14.0-3"),
            ],
            skipped: vec![Skipped {
                path: PathBuf::from("/nonexistent-test-dev/video1"),
                reason: "not a video capture node (metadata, output or codec)".into(),
            }],
        }
    }

    /// A unique name picks its device whatever the node number (the loopback device on
    /// video0 is not taken); case and the `v4l:` prefix do not matter.
    #[test]
    fn select_by_name() {
        let l = listing();
        assert_eq!(
            select("v4l:mono cam", &l).unwrap().card,
            "Polarimeter Mono Cam"
        );
        assert_eq!(
            select("V4L: Polarimeter", &l).unwrap().bus_info,
            "usb-0000:00:14.0-3"
        );
        assert_eq!(select("Polarimeter", &l).unwrap().path, l.devices[3].path);
    }

    /// Two identical webcams: the name is ambiguous (an error listing both), the bus info
    /// tells them apart.
    #[test]
    fn select_by_bus_info_when_names_collide() {
        let l = listing();
        let e = select("v4l:C920", &l).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.contains("matches 2 devices"), "{e}");
        assert!(e.message.contains("usb-0000:00:14.0-2"), "{e}");
        assert_eq!(
            select("usb-0000:00:14.0-2", &l).unwrap().path,
            l.devices[2].path
        );
        assert_eq!(
            select("v4l:usb-0000:00:14.0-1", &l).unwrap().path,
            l.devices[1].path
        );
    }

    /// A path picks its node (links would be resolved; these test paths do not exist, so
    /// they are compared as given).
    #[test]
    fn select_by_path() {
        let l = listing();
        assert_eq!(
            select("/nonexistent-test-dev/video4", &l).unwrap().bus_info,
            "usb-0000:00:14.0-2"
        );
        let e = select("v4l:/nonexistent-test-dev/video1", &l).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(
            e.message
                .contains("video1 skipped: not a video capture node"),
            "{e}"
        );
    }

    /// Nothing matching, an empty spec, or no devices at all: errors that say what exists,
    /// and never a fallback to the first device.
    #[test]
    fn no_match_lists_what_was_found() {
        let l = listing();
        let e = select("v4l:Basler", &l).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(e.message.contains("HD Pro Webcam C920"), "{e}");
        assert_eq!(e.device, "v4l:Basler");
        let e = select("  v4l:  ", &l).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange);
        assert!(e.message.contains("never taken by default"), "{e}");
        let e = select("v4l:anything", &Listing::default()).unwrap_err();
        assert!(
            e.message.contains("no /dev/video* node on this machine"),
            "{e}"
        );
    }

    /// Scanning a folder: `videoN` regular files and non-V4L2 character devices are skipped
    /// with a reason, other names are ignored, and nothing panics or fails the scan.
    #[test]
    fn scan_skips_non_devices() {
        let dir = std::env::temp_dir().join(format!("polar-v4l-scan-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("video0"), b"not a device").unwrap();
        std::fs::write(dir.join("videonote"), b"ignored: no number").unwrap();
        std::fs::write(dir.join("ttyS0"), b"ignored").unwrap();
        // /dev/null: a character device that is not V4L2 (VIDIOC_QUERYCAP fails with ENOTTY).
        std::os::unix::fs::symlink("/dev/null", dir.join("video7")).unwrap();
        let l = scan(&dir).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
        assert!(l.devices.is_empty());
        assert_eq!(l.skipped.len(), 2, "{l:?}");
        assert!(l.skipped[0].path.ends_with("video0"));
        assert_eq!(l.skipped[0].reason, "not a character device");
        assert!(l.skipped[1].path.ends_with("video7"));
        assert!(l.skipped[1].reason.contains("not a V4L2 device"), "{l:?}");
        assert_eq!(
            scan(Path::new("/nonexistent-polar-dir")).unwrap(),
            Listing::default()
        );
    }

    /// On a machine without video devices (CI, this container) enumeration is an empty list,
    /// not an error. On a machine with devices it still succeeds, and each entry is a capture
    /// node with a path under /dev.
    #[test]
    fn list_on_this_machine() {
        let devices = list().unwrap();
        let has_nodes = std::fs::read_dir("/dev").unwrap().any(|e| {
            e.map(|e| e.file_name().to_string_lossy().starts_with("video"))
                .unwrap_or(false)
        });
        if !has_nodes {
            assert!(devices.is_empty());
        }
        for d in &devices {
            assert!(d.path.starts_with("/dev"), "{d}");
        }
    }

    #[test]
    fn fourcc_text_is_printable() {
        assert_eq!(fourcc_text(*b"Y16 "), "Y16");
        assert_eq!(fourcc_text(*b"MJPG"), "MJPG");
        assert_eq!(fourcc_text([0, 0xFF, b'A', b'B']), "??AB");
    }
}
