//! V4L2 cameras (webcams, USB and CSI video devices) for the polarimeter, as a
//! [`polar_hal::BlockingCamera`] (`ARCHITECTURE.md`, "Device abstraction";
//! `docs/DEVICES.md` sections 3.2, 4.3, 5.2).
//!
//! ```no_run
//! use polar_camera_v4l::V4lCamera;
//! use polar_hal::camera_thread::{ThreadPolicy, ThreadedCamera};
//! # fn main() -> Result<(), polar_hal::DeviceError> {
//! for d in polar_camera_v4l::list()? {
//!     println!("{d}"); // path, card name, driver, bus info, formats
//! }
//! // By card name (or bus info, or path): never "index 0".
//! let camera = V4lCamera::open("v4l:HD Pro Webcam")?;
//! let camera = ThreadedCamera::spawn(camera, ThreadPolicy::default())?; // an async Camera
//! # Ok(()) }
//! ```
//!
//! # Which crate does what, and why
//!
//! * [`linuxvideo`] (0BSD) does the V4L2 ioctls: capabilities (card, driver, bus info), format
//!   and frame-size enumeration, format negotiation, controls, and the MMAP stream. Its bindings
//!   are written by hand, so it builds with no system package. `v4l` 0.14, the usual
//!   choice, generates its bindings with bindgen in `v4l2-sys-mit`'s build script and so
//!   needs libclang at build time. nokhwa's `input-native` depends on that same `v4l`, and
//!   offers no 16-bit format, no `GREY` and no absolute exposure of its own. Neither is used
//!   here; nokhwa is the UVC backend for Windows and macOS (`polar-camera-uvc`).
//! * `rustix` (`poll(2)`, safe API) bounds every wait for a frame by its deadline:
//!   `linuxvideo`'s dequeue blocks with no timeout.
//! * `polar-frame-convert` (re-exported as [`convert`], shared with the UVC backend) turns
//!   buffers into luminance; `zune-jpeg` (pure Rust, strict mode, luma-only output) decodes
//!   MJPEG; the standard Huffman tables are put back first when a frame leaves them out, as UVC
//!   cameras do. No mozjpeg, no C.
//! * This crate: enumeration and selection by name, bus info or path ([`device`]); the camera
//!   ([`V4lCamera`]: exposure, gain, formats, host-side ROI, free-run, grab with a deadline,
//!   error kinds); the pure conversions ([`convert`]). `unsafe` stays inside `linuxvideo`.
//!   Calls into it go through a guard that turns a panic on a malformed device reply into an
//!   error.
//!
//! # What is tested where
//!
//! CI has no video device (no `/dev/video*`, no kernel modules for vivid or v4l2loopback). CI
//! tests the conversions (known images, truncation, random bytes), device selection, scanning
//! a folder with non-devices in it, an empty enumeration on this machine, the error mapping
//! and the deadline of the wait. `tests/real_device.rs` runs against a real device when
//! `POLARIMETER_V4L2_DEVICE=/dev/videoN` is set (see the README).
#![warn(missing_docs)]

mod camera;
/// The pure conversions, shared with the UVC backend (crate `polar-frame-convert`).
pub use polar_frame_convert as convert;
pub mod device;
mod sys;

pub use camera::{assemble, snap_to_control, OpenOptions, Source, SourceFormat, V4lCamera};
pub use device::{list, scan, select, Listing, Skipped, V4lDeviceInfo};
